"""Behaviour cloning: a policy's warm start from an expert's driving (``racing train --imitate``).

An expert (any agent: a planner, the lane keeper, a trained policy) drives the learner's car
of the training race for some seeded episodes; its observations, actions and rewards are the
demonstrations. A fresh actor-critic policy (SB3's PPO or A2C) is then fitted to them before
reinforcement learning starts:

* the observation normaliser (``VecNormalize``) takes the demonstrations' mean and variance,
  and its reward normaliser the variance of their running discounted returns, as it would
  have measured them while driving those episodes itself;
* the Gaussian policy's mean is fitted to the expert's actions (least squares: the maximum
  likelihood of the mean for any fixed spread). Its state-independent standard deviation is
  not fitted (it would shrink to the clone's tiny error, and reinforcement learning would
  have nothing left to explore with) but set (`racing train`: by default to the noise the
  demonstrations were driven with, below): the policy then explores the states the
  demonstrations cover, where a spread of PPO's initial 1.0 drives a clone off them. How
  fast the reinforcement learning that follows may change the clone is its learning rate's
  to say: docs/rl.md and docs/experiments/rl-time-trial.md.
* the value function is fitted to the discounted sum of the normalised rewards that follow
  each step, so that those first updates start from advantages that mean something.

A clone of a perfect driver never sees the states its own small errors lead to, and drifts
off the line the expert held (the covariate shift of behaviour cloning). So, as in DART
(Laskey et al., 2017, "DART: Noise Injection for Robust Imitation Learning"), the car is
driven by the expert's action plus Gaussian noise, while the expert's own action is what is
recorded: the demonstrations then show how the expert recovers.

The last episode(s) are held out of the fit; the errors reported on them say whether it
carries over to states it was not fitted on.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

# the fraction of the episodes held out of the fit (at least one when there are two or more)
HOLDOUT_FRACTION = 0.1


@dataclasses.dataclass(frozen=True)
class Demonstrations:
    """An expert's driving, step by step over all episodes (M steps, E episodes).

    Attributes:
        observations: ``(M, obs_size)`` the learner's raw observations (before normalisation).
        actions: ``(M, 2)`` the expert's normalised jerk commands, in ``[-1, 1]``.
        rewards: ``(M,)`` the training race's rewards for the actions driven (the expert's,
            plus the collection's noise).
        episode: ``(M,)`` the episode (0..E-1) each step belongs to.
        finished: ``(E,)`` whether the expert finished the race in that episode.
        source: what drove, and in which race (free text, e.g. JSON settings; "" when
            unknown), so that a run can tell whether saved demonstrations are its own.
    """

    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    episode: np.ndarray
    finished: np.ndarray
    source: str = ""

    @property
    def episodes(self) -> int:
        return len(self.finished)

    def first(self, episodes: int) -> "Demonstrations":
        """The first ``episodes`` episodes (all of them when there are no more)."""
        keep = self.episode < episodes
        return dataclasses.replace(self, observations=self.observations[keep], actions=self.actions[keep],
                                   rewards=self.rewards[keep], episode=self.episode[keep],
                                   finished=self.finished[:episodes])

    def save(self, path: Path) -> None:
        with open(path, "wb") as sink:  # a file object: numpy would add ".npz" to a name without it
            np.savez_compressed(sink, **dataclasses.asdict(self))

    @classmethod
    def load(cls, path: Path) -> "Demonstrations":
        with np.load(path) as data:
            fields = {f.name: data[f.name] for f in dataclasses.fields(cls) if f.name in data}
        if "source" in fields:
            fields["source"] = str(fields["source"])  # saved as a 0-d string array
        return cls(**fields)


def collect_demonstrations(envs: Sequence[Any], expert: Any, episodes: int, seed: int, noise: float = 0.0,
                           progress: bool = True, collected: Demonstrations | None = None,
                           on_episode: Callable[[Demonstrations], None] | None = None,
                           source: str = "") -> Demonstrations:
    """Let ``expert`` drive the learner's car of ``envs`` (Gymnasium views of the race,
    :class:`racing_env.single_agent.RaceEnv`, possibly wrapped) for ``episodes`` episodes,
    taking the envs in turn; episode ``k`` is reset with seed ``seed + k``. The expert
    follows the agent protocol: it is reset as the learner's car of each episode and acts
    on ``(observation, joint state)``. The car is driven by the expert's action plus
    Gaussian noise of standard deviation ``noise`` (normalised action units, clipped to
    ``[-1, 1]``; drawn from a generator seeded by ``seed``), and the expert's action is
    recorded. ``source`` is kept with the demonstrations (:attr:`Demonstrations.source`).

    ``collected``: episodes of an earlier, interrupted collection with the same arguments
    and ``source``; driving goes on from the next episode, and the result equals an
    uninterrupted collection (the noise generator is moved past the draws those episodes
    used). With ``episodes`` or more collected, their first ``episodes`` are returned.
    ``on_episode`` is called with everything collected so far after every episode, e.g.
    to save it, so that an interruption loses at most the episode being driven."""
    from rich.progress import track

    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if not 0.0 <= noise < np.inf:
        raise ValueError(f"noise must be a finite standard deviation >= 0, got {noise}")
    if collected is not None and collected.source != source:
        raise ValueError(f"the collected demonstrations come from {collected.source!r}, not {source!r}")
    rng = np.random.default_rng(seed)
    if collected is not None and collected.episodes >= episodes:
        return collected.first(episodes)
    done = collected if collected is not None else Demonstrations(
        np.zeros((0, 0), np.float32), np.zeros((0, 0), np.float32), np.zeros(0), np.zeros(0, np.int64),
        np.zeros(0, bool), source)
    if done.episodes:
        rng.standard_normal(done.actions.size)  # one draw per action entry of every step driven so far
    observations, actions, rewards = list(done.observations), list(done.actions), list(done.rewards)
    episode_of, finished = list(done.episode), list(done.finished)
    for k in track(range(done.episodes, episodes), description=f"{getattr(expert, 'name', 'expert')} drives",
                   disable=not progress, transient=True):
        env = envs[k % len(envs)]
        race = env.unwrapped
        observation, _ = env.reset(seed=seed + k)
        expert.reset(seed + k, race.race.possible_agents.index(race.learner), race.race)
        done_episode, info = False, {}
        while not done_episode:
            action = np.clip(np.asarray(expert(observation, race.race.state()), dtype=np.float32), -1.0, 1.0)
            observations.append(observation)
            actions.append(action)
            driven = np.clip(action + noise * rng.standard_normal(action.shape), -1.0, 1.0).astype(np.float32)
            observation, reward, terminated, truncated, info = env.step(driven)
            rewards.append(reward)
            episode_of.append(k)
            done_episode = terminated or truncated
        finished.append(bool(info.get("finished", False)))
        done = Demonstrations(observations=np.asarray(observations, dtype=np.float32),
                              actions=np.asarray(actions, dtype=np.float32),
                              rewards=np.asarray(rewards, dtype=np.float64),
                              episode=np.asarray(episode_of, dtype=np.int64),
                              finished=np.asarray(finished, dtype=bool), source=done.source)
        if on_episode is not None:
            on_episode(done)
    return done


def discounted_returns(rewards: np.ndarray, episode: np.ndarray, gamma: float) -> np.ndarray:
    """Per step, the discounted sum of this and the later rewards of its episode, ``(M,)``.
    An episode's last step ends the sum (a truncated episode is read as ended)."""
    returns = np.zeros(len(rewards))
    following = 0.0
    for t in range(len(rewards) - 1, -1, -1):
        if t == len(rewards) - 1 or episode[t + 1] != episode[t]:
            following = 0.0
        following = rewards[t] + gamma * following
        returns[t] = following
    return returns


def running_returns(rewards: np.ndarray, episode: np.ndarray, gamma: float) -> np.ndarray:
    """Per step, the discounted sum of its episode's rewards so far, ``(M,)``: what
    ``VecNormalize`` measures the variance of to scale rewards."""
    running = np.zeros(len(rewards))
    so_far = 0.0
    for t in range(len(rewards)):
        if t == 0 or episode[t] != episode[t - 1]:
            so_far = 0.0
        so_far = so_far * gamma + rewards[t]
        running[t] = so_far
    return running


def fit_normalizer(venv: Any, demonstrations: Demonstrations) -> None:
    """Set a ``VecNormalize``'s statistics to the demonstrations' (observations, and the
    running returns its reward scaling divides by)."""
    obs = demonstrations.observations.astype(np.float64)
    venv.obs_rms.mean, venv.obs_rms.var, venv.obs_rms.count = obs.mean(axis=0), obs.var(axis=0), float(len(obs))
    running = running_returns(demonstrations.rewards, demonstrations.episode, venv.gamma)
    venv.ret_rms.mean, venv.ret_rms.var, venv.ret_rms.count = running.mean(), running.var(), float(len(running))


def _split(demonstrations: Demonstrations) -> tuple[np.ndarray, np.ndarray]:
    """Boolean masks of the steps fitted on and the steps held out (the last episodes)."""
    held = int(np.ceil(HOLDOUT_FRACTION * demonstrations.episodes)) if demonstrations.episodes > 1 else 0
    holdout = demonstrations.episode >= demonstrations.episodes - held
    return ~holdout, holdout


def clone(model: Any, demonstrations: Demonstrations, spread: float | None = None, epochs: int = 30,
          batch_size: int = 256, learning_rate: float = 1e-3, value_weight: float = 0.5,
          seed: int = 0) -> dict[str, Any]:
    """Fit ``model`` (an SB3 actor-critic: PPO or A2C, whose env is a ``VecNormalize`` or
    not normalised) to ``demonstrations``: normaliser statistics, the policy's mean action
    by least squares on the expert's actions, the value by least squares on the discounted
    normalised returns (``model.gamma``), the two losses summed with ``value_weight`` on the
    second. Adam, minibatches of ``batch_size``, ``epochs`` passes over the fitted steps.
    The policy's standard deviation is not fitted: it is set to ``spread`` for every action
    (normalised units), or kept as the policy was built when ``spread`` is None.

    Returns the fit's report: steps fitted and held out, and for each split, before and
    after the fit, the root-mean-square error of the policy's deterministic action (clipped
    to the action bounds, as the env applies it) and of its value; the policy's standard
    deviation per action; the training loss per epoch."""
    import torch
    from stable_baselines3.common.vec_env import VecNormalize

    if spread is not None and not 0.0 < spread < np.inf:
        raise ValueError(f"spread must be a finite standard deviation > 0, got {spread}")
    if epochs < 1 or batch_size < 1 or not learning_rate > 0:
        raise ValueError(f"epochs and batch_size must be >= 1 and learning_rate > 0, "
                         f"got {epochs}, {batch_size}, {learning_rate}")
    venv = model.get_env()
    rewards, observations = demonstrations.rewards, demonstrations.observations
    if isinstance(venv, VecNormalize):
        fit_normalizer(venv, demonstrations)
        observations, rewards = venv.normalize_obs(observations), venv.normalize_reward(rewards)
    targets = discounted_returns(rewards, demonstrations.episode, model.gamma)
    policy = model.policy
    as_tensor = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32, device=policy.device)  # noqa: E731
    obs_t, act_t, target_t = as_tensor(observations), as_tensor(demonstrations.actions), as_tensor(targets)
    fitted, held = _split(demonstrations)
    low, high = as_tensor(model.action_space.low), as_tensor(model.action_space.high)

    def mean_and_value(obs):
        return policy.get_distribution(obs).distribution.mean, policy.predict_values(obs).flatten()

    def measure(mask: np.ndarray) -> dict[str, float] | None:
        if not mask.any():
            return None
        index = torch.as_tensor(np.flatnonzero(mask))
        with torch.no_grad():
            mean, values = mean_and_value(obs_t[index])
        action = torch.clamp(mean, low, high)
        return {"action_rmse": float(torch.sqrt(((action - act_t[index]) ** 2).mean())),
                "value_rmse": float(torch.sqrt(((values - target_t[index]) ** 2).mean()))}

    report: dict[str, Any] = {"steps_fitted": int(fitted.sum()), "steps_held_out": int(held.sum()),
                              "before": {"fitted": measure(fitted), "held_out": measure(held)}}
    fitted_parameters = [p for name, p in policy.named_parameters() if name != "log_std"]
    optimizer = torch.optim.Adam(fitted_parameters, lr=learning_rate)
    generator = torch.Generator().manual_seed(seed)
    fitted_index = torch.as_tensor(np.flatnonzero(fitted))
    losses = []
    policy.set_training_mode(True)
    for _ in range(epochs):
        total, batches = 0.0, 0
        for batch in fitted_index[torch.randperm(len(fitted_index), generator=generator)].split(batch_size):
            mean, values = mean_and_value(obs_t[batch])
            loss = (((mean - act_t[batch]) ** 2).sum(dim=1).mean()
                    + value_weight * ((values - target_t[batch]) ** 2).mean())
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            total, batches = total + loss.item(), batches + 1
        losses.append(total / batches)
    policy.set_training_mode(False)
    if spread is not None:
        with torch.no_grad():
            policy.log_std.fill_(float(np.log(spread)))
    report["after"] = {"fitted": measure(fitted), "held_out": measure(held)}
    report["action_std"] = [float(s) for s in torch.exp(policy.log_std.detach())]
    report["loss_per_epoch"] = losses
    return report
