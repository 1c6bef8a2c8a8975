"""Proximal policy optimisation in JAX: pure functions that compile into one program.

The PureJaxRL pattern: a training *update* collects a rollout of ``n_steps`` steps in each
of B races and then fits the policy to it for ``n_epochs`` epochs of minibatches. When the
races are a :class:`racing_env.vector.GymnaxRace` (opponents that are JAX functions of the
state), the whole update, races included, is one jitted function
(:func:`compiled_update`), and it ``vmap``\\ s over independent seeds. Against opponents
that are not JAX functions (planners, whose batched solves run beside the race core), the
rollout steps the races from Python and everything else is jitted
(:func:`policy_step`, :func:`after_env_step`, :func:`fit`).

The algorithm is stable-baselines3's PPO with ``VecNormalize`` (clipped surrogate,
generalised advantage estimate, advantages normalised per minibatch, value loss without
clipping, gradients clipped by global norm, Adam), with one difference: an episode cut
by the race's step limit is treated as ended (no bootstrap from its last value).

Shapes: observations ``(B, O)`` (float32 raw, as the races give them), actions ``(B, 2)``
normalised jerks (sampled unclipped, clipped to ``[-1, 1]`` when the races take them),
rewards and flags ``(B,)``. A rollout's arrays are ``(T, B, ...)`` with ``T = n_steps``.

Contract of the state (:class:`Learner`, a pytree): ``params`` (the flax actor-critic of
:func:`planners.agents.jax_policy.actor_critic`), ``opt_state`` (optax), ``obs_stats``
(running ``mean (O,), var (O,), count``), ``ret_stats`` (running ``mean (1,), var (1,),
count`` of the discounted return, for reward scaling), ``returns (B,)`` (each race's discounted return so
far) and ``key``.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from planners.agents.jax_policy import ObsNormalizer, actor_critic, normalize_obs

__all__ = ["EPISODE_FIELDS", "Learner", "PPOSettings", "Rollout", "after_env_step", "compiled_update",
           "fit", "init_learner", "policy_step"]

EPSILON = 1e-8  # VecNormalize's epsilon in the observation and reward scales


@dataclasses.dataclass(frozen=True)
class PPOSettings:
    """PPO's settings, named as stable-baselines3 names them (``racing train --hp NAME=VALUE``).

    Attributes:
        n_steps: steps per race per rollout (T); a rollout is ``n_steps * B`` samples.
        batch_size: samples per minibatch; must divide the rollout.
        n_epochs: passes over the rollout per update.
        learning_rate: Adam's step size.
        gamma, gae_lambda: discount and the advantage estimate's lambda.
        clip_range: the surrogate's ratio clip.
        ent_coef, vf_coef: weights of the entropy bonus and the value loss.
        max_grad_norm: gradients are clipped to this global norm.
        hidden: hidden layer sizes of the actor and of the critic.
        log_std_init: the Gaussian's initial log standard deviation.
        normalize: observations and rewards scaled by running statistics (``VecNormalize``).
        clip_obs, clip_reward: bounds of the scaled observations and rewards.
    """

    n_steps: int = 64
    batch_size: int = 512
    n_epochs: int = 10
    learning_rate: float = 3e-4
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_range: float = 0.2
    ent_coef: float = 0.0
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    hidden: tuple[int, ...] = (64, 64)
    log_std_init: float = 0.0
    normalize: bool = True
    clip_obs: float = 10.0
    clip_reward: float = 10.0

    def check(self, num_envs: int) -> None:
        """Refuse settings that cannot train ``num_envs`` races (ValueError)."""
        for name in ("n_steps", "batch_size", "n_epochs"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        rollout = self.n_steps * num_envs
        if rollout % self.batch_size:
            raise ValueError(f"batch_size {self.batch_size} must divide the rollout n_steps * envs = "
                             f"{self.n_steps} * {num_envs} = {rollout}")
        for name in ("learning_rate", "clip_range", "max_grad_norm", "clip_obs", "clip_reward"):
            if not 0.0 < float(getattr(self, name)) < np.inf:
                raise ValueError(f"{name} must be a finite number > 0, got {getattr(self, name)!r}")
        for name in ("gamma", "gae_lambda"):
            if not 0.0 <= float(getattr(self, name)) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)!r}")
        if not self.hidden or any(int(h) < 1 for h in self.hidden):
            raise ValueError(f"hidden must be one or more layer sizes >= 1, got {self.hidden!r}")

    @property
    def module(self):
        return actor_critic(self.hidden, self.log_std_init)


class Learner(NamedTuple):
    """Everything the policy's training carries from one update to the next (module docstring)."""

    params: Any
    opt_state: Any
    obs_stats: tuple
    ret_stats: tuple
    returns: jax.Array
    key: jax.Array


class Rollout(NamedTuple):
    """What one step of B races adds to the rollout (each ``(B, ...)``; ``(T, B, ...)`` stacked)."""

    obs: jax.Array  # normalised observations the actions were taken on
    action: jax.Array  # sampled, unclipped
    log_prob: jax.Array
    value: jax.Array
    reward: jax.Array  # scaled
    done: jax.Array


EPISODE_FIELDS = ("done", "return", "length", "finished", "position", "out", "finish_time", "truncated",
                  "nonfinite_action")
"""Per step and race in a compiled update's episode log ``(T, B)`` each: whether an episode
ended there, and its raw return, length [steps], whether the learner finished, its place,
whether it retired, its finish time [s] (NaN if not finished), whether the step limit cut it,
and whether the policy's action was not finite (NaN or inf: the race took it as zero jerk,
:class:`racing_env.vector.GymnaxRace`)."""


def optimizer(settings: PPOSettings) -> optax.GradientTransformation:
    return optax.chain(optax.clip_by_global_norm(settings.max_grad_norm),
                       optax.adam(settings.learning_rate, eps=1e-5))


def init_learner(key: jax.Array, obs_size: int, num_envs: int, settings: PPOSettings) -> Learner:
    """A fresh policy and optimiser, statistics of nothing seen, for ``num_envs`` races."""
    key, init_key = jax.random.split(key)
    params = settings.module.init(init_key, jnp.zeros((1, obs_size), jnp.float32))["params"]
    return Learner(params=params, opt_state=optimizer(settings).init(params), obs_stats=ObsNormalizer.init(obs_size),
                   ret_stats=ObsNormalizer.init(1), returns=jnp.zeros(num_envs), key=key)


def _log_prob(mean, log_std, action):
    return jnp.sum(-0.5 * ((action - mean) / jnp.exp(log_std)) ** 2 - log_std - 0.5 * jnp.log(2.0 * jnp.pi), -1)


def _scaled_obs(settings: PPOSettings, learner: Learner, raw_obs):
    if not settings.normalize:
        return raw_obs.astype(jnp.float32)
    mean, var, _ = learner.obs_stats
    return normalize_obs(raw_obs, mean, var, settings.clip_obs, EPSILON)


def policy_step(settings: PPOSettings, learner: Learner, obs):
    """Sample actions for normalised observations ``obs (B, O)``: ``(learner with its key
    advanced, action (B, 2), log_prob (B,), value (B,))``."""
    key, sample_key = jax.random.split(learner.key)
    mean, log_std, value = settings.module.apply({"params": learner.params}, obs)
    action = mean + jnp.exp(log_std) * jax.random.normal(sample_key, mean.shape, mean.dtype)
    return learner._replace(key=key), action, _log_prob(mean, log_std, action), value


def observe_start(settings: PPOSettings, learner: Learner, raw_obs):
    """The first observations of the races ``(B, O)``: the statistics take them in (as
    ``VecNormalize.reset`` does); returns ``(learner, normalised obs)``."""
    if settings.normalize:
        learner = learner._replace(obs_stats=ObsNormalizer.update(learner.obs_stats, raw_obs))
    return learner, _scaled_obs(settings, learner, raw_obs)


def after_env_step(settings: PPOSettings, learner: Learner, raw_obs, reward, done):
    """After the races stepped: statistics updated with the new observations ``(B, O)`` and
    the discounted returns, rewards scaled by the return's standard deviation and clipped
    (``VecNormalize``). Returns ``(learner, normalised obs, scaled reward (B,))``."""
    if not settings.normalize:
        return learner, raw_obs.astype(jnp.float32), reward
    obs_stats = ObsNormalizer.update(learner.obs_stats, raw_obs)
    returns = learner.returns * settings.gamma + reward
    ret_stats = ObsNormalizer.update(learner.ret_stats, returns[:, None])
    scaled = jnp.clip(reward / jnp.sqrt(ret_stats[1][0] + EPSILON), -settings.clip_reward, settings.clip_reward)
    learner = learner._replace(obs_stats=obs_stats, ret_stats=ret_stats, returns=jnp.where(done, 0.0, returns))
    return learner, _scaled_obs(settings, learner, raw_obs), scaled


def _advantages(settings: PPOSettings, rollout: Rollout, last_value):
    """Generalised advantage estimates and value targets, ``(T, B)`` each."""
    def back(carry, step):
        advantage, next_value = carry
        reward, done, value = step
        alive = 1.0 - done.astype(value.dtype)
        delta = reward + settings.gamma * next_value * alive - value
        advantage = delta + settings.gamma * settings.gae_lambda * alive * advantage
        return (advantage, value), advantage

    _, advantages = jax.lax.scan(back, (jnp.zeros_like(last_value), last_value),
                                 (rollout.reward.astype(last_value.dtype), rollout.done, rollout.value), reverse=True)
    return advantages, advantages + rollout.value


def fit(settings: PPOSettings, learner: Learner, rollout: Rollout, last_obs):
    """PPO's update on a rollout ``(T, B, ...)`` whose next observations are ``last_obs
    (B, O)`` (normalised). Returns ``(learner, metrics)``: the mean policy, value and
    entropy losses, the approximate KL divergence and the clipped fraction of the last epoch."""
    module, tx = settings.module, optimizer(settings)
    _, _, last_value = module.apply({"params": learner.params}, last_obs)
    advantages, targets = _advantages(settings, rollout, last_value)
    samples = rollout.obs.shape[0] * rollout.obs.shape[1]
    flat = jax.tree_util.tree_map(lambda a: a.reshape((samples,) + a.shape[2:]),
                                  (rollout.obs, rollout.action, rollout.log_prob, advantages, targets))
    minibatches = samples // settings.batch_size

    def loss(params, batch):
        obs, action, old_log_prob, advantage, target = batch
        mean, log_std, value = module.apply({"params": params}, obs)
        log_prob = _log_prob(mean, log_std, action)
        advantage = (advantage - advantage.mean()) / (advantage.std() + EPSILON)
        ratio = jnp.exp(log_prob - old_log_prob)
        policy_loss = -jnp.minimum(ratio * advantage,
                                   jnp.clip(ratio, 1 - settings.clip_range, 1 + settings.clip_range) * advantage).mean()
        value_loss = ((target - value) ** 2).mean()
        entropy = jnp.sum(log_std + 0.5 * jnp.log(2.0 * jnp.pi * jnp.e))
        total = policy_loss + settings.vf_coef * value_loss - settings.ent_coef * entropy
        kl = ((ratio - 1) - (log_prob - old_log_prob)).mean()
        clipped = (jnp.abs(ratio - 1) > settings.clip_range).mean()
        return total, jnp.stack([policy_loss, value_loss, entropy, kl, clipped])

    def minibatch(carry, batch):
        params, opt_state = carry
        grads, metrics = jax.grad(loss, has_aux=True)(params, batch)
        updates, opt_state = tx.update(grads, opt_state, params)
        return (optax.apply_updates(params, updates), opt_state), metrics

    def epoch(carry, _):
        params, opt_state, key = carry
        key, shuffle_key = jax.random.split(key)
        order = jax.random.permutation(shuffle_key, samples)
        batches = jax.tree_util.tree_map(
            lambda a: a[order].reshape((minibatches, settings.batch_size) + a.shape[1:]), flat)
        (params, opt_state), metrics = jax.lax.scan(minibatch, (params, opt_state), batches)
        return (params, opt_state, key), metrics.mean(0)

    (params, opt_state, key), metrics = jax.lax.scan(epoch, (learner.params, learner.opt_state, learner.key), None,
                                                     settings.n_epochs)
    names = ("policy_loss", "value_loss", "entropy", "approx_kl", "clip_fraction")
    return learner._replace(params=params, opt_state=opt_state, key=key), dict(zip(names, metrics[-1]))


class RaceCarry(NamedTuple):
    """The races of a compiled update between updates: the env state, the last normalised
    observations ``(B, O)``, and each race's episode return and length so far ``(B,)``."""

    state: Any
    obs: jax.Array
    episode_return: jax.Array
    episode_length: jax.Array


def start_races(env, settings: PPOSettings, learner: Learner, key: jax.Array, num_envs: int):
    """Start ``num_envs`` races of ``env`` (a :class:`racing_env.vector.GymnaxRace`):
    ``(learner, RaceCarry)``."""
    raw_obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, num_envs), env.default_params)
    learner, obs = observe_start(settings, learner, raw_obs)
    zeros = jnp.zeros(num_envs)
    return learner, RaceCarry(state, obs, zeros, jnp.zeros(num_envs, jnp.int32))


@functools.lru_cache(maxsize=None)
def compiled_update(env, settings: PPOSettings):
    """The jitted update ``(learner, races: RaceCarry) -> (learner, races, episodes, metrics)``
    over ``env`` (a :class:`racing_env.vector.GymnaxRace`): ``n_steps`` steps of every race
    (opponents inside the step), then :func:`fit`. ``episodes`` is the episode log
    (:data:`EPISODE_FIELDS`, ``(T, B)`` each). Pure: ``jax.vmap`` it over stacked learners
    and races to train several seeds as one program."""
    params = env.default_params
    step_env = jax.vmap(env.race_step, in_axes=(0, 0, 0, None))

    def one_step(carry, _):
        learner, races = carry
        obs_before = races.obs
        learner, action, log_prob, value = policy_step(settings, learner, races.obs)
        key, step_key = jax.random.split(learner.key)
        learner = learner._replace(key=key)
        keys = jax.random.split(step_key, races.obs.shape[0])
        raw_obs, state, reward, done, info = step_env(keys, races.state, jnp.clip(action, -1.0, 1.0), params)
        learner, obs, scaled = after_env_step(settings, learner, raw_obs, reward, done)
        episode_return = races.episode_return + reward
        episode_length = races.episode_length + 1
        log = {"done": done, "return": episode_return, "length": episode_length, "finished": info["finished"],
               "position": info["position"], "out": info["out"],
               "finish_time": jnp.where(info["finished"], info["finish_time"], jnp.nan),
               "truncated": info["truncated"], "nonfinite_action": info["nonfinite_action"]}
        races = RaceCarry(state, obs, jnp.where(done, 0.0, episode_return), jnp.where(done, 0, episode_length))
        return (learner, races), (Rollout(obs_before, action, log_prob, value, scaled, done), log)

    def update(learner: Learner, races: RaceCarry):
        (learner, races), (rollout, log) = jax.lax.scan(one_step, (learner, races), None, settings.n_steps)
        learner, metrics = fit(settings, learner, rollout, races.obs)
        return learner, races, log, metrics

    return jax.jit(update)
