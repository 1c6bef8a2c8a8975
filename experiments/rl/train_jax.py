"""`racing train --learner jax`: PPO in JAX (:mod:`experiments.rl.ppo_jax`), with the SB3 learner's outputs.

Two ways to run the races, chosen from the configuration:

* **compiled** (opponents that are JAX functions of the state: ``lane-keeping``,
  ``constant-speed``, ...; planners with a fixed iteration budget re-planning every step,
  ``ilqgame-fb:iterations=2``, whose re-plans compile into the step (:mod:`planners.agents.compiled_planner`); or a time
  trial; ``start`` ``grid`` or ``anywhere``; no pool): the races are a
  :class:`racing_env.vector.GymnaxRace` and a whole update, ``n_steps`` steps of all
  ``envs`` races and PPO's epochs, is one compiled call. The learner drives car 0; the
  grid's order is drawn per episode, so it starts in every slot.
* **host** (any other opponents: converging planners, ``rl:`` models, pools, ``start``
  mixed): the races are the SB3 learner's :class:`experiments.rl.vec_env.RaceVecEnv` (the
  same copies, seeds and episodes; the learner drives car ``copy % N``), stepped from Python
  with the planners' batched solves; the policy's steps and PPO's update are compiled.

The output folder is the SB3 learner's (:mod:`experiments.rl.train`), with the model in a
``.npz`` (:mod:`planners.agents.jax_policy`), raced as ``rl:OUT/model.npz``::

    train.json          configuration, status, timesteps, timing, the PPO settings, final evaluation
    model.npz           the final policy with its observation statistics
    checkpoints/        step_<timesteps>.npz (the policy at each checkpoint) and resume.pkl
                        (the whole training state at the latest one: policy, optimiser,
                        statistics, the races in flight, random keys)
    episodes.jsonl      one line per finished training episode
    evaluations.jsonl   one line per evaluation (tournament rules, experiments.rl.evaluation)
    learning_curve.png  episode returns and evaluations against timesteps

A checkpoint is taken right after an update, every ``checkpoint_every`` steps and at Ctrl-C;
the same command resumes from it and goes on exactly as if it had not stopped (the same
policies, bit for bit, in the compiled form).
"""

from __future__ import annotations

import dataclasses
import functools
import pickle
import shutil
import time
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from experiments.files import replace_atomically, write_json_atomically
from experiments.jsonl import append_jsonl, drop_cut_line
from experiments.rl import ppo_jax
from experiments.rl.common import (check_resumable, drop_episodes_after, episode_fields, evaluate_final,
                                   finish_report, make_vector_env, next_multiple, record_evaluation)
from experiments.rl.config import CHECKPOINTS, CONFIG, EPISODES, EVALUATIONS, config_json, default_hyperparameters
from planners.agents.jax_policy import save_model

__all__ = ["JAX_MODEL", "compiled_races", "ppo_settings", "run_jax_training"]

JAX_MODEL = "model.npz"
RESUME = "resume.pkl"
RACE_KEY_OFFSET = 1_000_003  # the compiled races' first starts are drawn with PRNGKey(seed + this)
_STATE_VERSION = 1


def ppo_settings(config) -> ppo_jax.PPOSettings:
    """The PPO settings of a run: the SB3 learner's defaults for its ``envs``
    (:func:`experiments.rl.train.default_hyperparameters`), then its ``hyperparameters``."""
    values = {**default_hyperparameters("ppo", config.envs), **dict(config.hyperparameters)}
    if "hidden" in values:
        values["hidden"] = tuple(int(h) for h in np.atleast_1d(values["hidden"]))
    settings = ppo_jax.PPOSettings(normalize=config.normalize, **values)
    settings.check(config.envs)
    return settings


def compiled_races(config):
    """The run's races as a :class:`racing_env.vector.GymnaxRace` when they can be compiled
    with the policy (module docstring), else None (the host form). Runs of the same race and
    opponents (seeds of a study) share one, and with it the compiled update."""
    if config.pool or config.start == "mixed":  # one scenario per GymnaxRace; mixed has two
        return None
    return _gymnax_race(tuple(config.opponents), config.race_config(training=True))


@functools.lru_cache(maxsize=16)
def _gymnax_race(opponents: tuple[str, ...], race):
    from planners.agents.batched import make_batched_opponent
    from racing_env.env import RacingParallelEnv
    from racing_env.vector import GymnaxRace

    policies = []
    if opponents:
        game = RacingParallelEnv(race).game
        for car, spec in enumerate(opponents, start=1):
            opponent = make_batched_opponent(spec, game, car, 1)
            if opponent.jax_policy is not None:
                policies.append(opponent.jax_policy)
            elif _compiles(opponent):
                policies.append(opponent)
            else:
                return None
    fields = {f.name: getattr(race, f.name) for f in dataclasses.fields(race) if f.name != "num_agents"}
    return GymnaxRace(opponents=policies, learner=0, num_agents=race.num_agents, **fields)


def _compiles(opponent) -> bool:
    """Whether a planner opponent races inside the compiled update: one with a fixed iteration
    budget (``iterations=K``) that re-plans every step, whose re-plans cost the same in every
    race and every step. The others stay on the host races (:mod:`planners.agents.batched_planners`):
    converging re-plans, where the batched solves stop each race at its own convergence instead
    of running in lock step, and re-plans every few steps, where only the races due solve (in
    a vmapped step every race solves once races restart at different times)."""
    agent = getattr(opponent, "agent", None)
    return (opponent.jax_planner is not None and getattr(agent, "iterations", None) is not None
            and agent.replan_every == 1)


# --- the two forms of an update ----------------------------------------------------------------
class _Compiled:
    """Races inside the compiled update (:func:`experiments.rl.ppo_jax.compiled_update`)."""

    kind = "compiled"

    def __init__(self, env, settings: ppo_jax.PPOSettings, num_envs: int) -> None:
        self.env, self.settings, self.num_envs = env, settings, num_envs
        self.update_fn = ppo_jax.compiled_update(env, settings)
        self.races = None

    @property
    def observation_size(self) -> int:
        return int(self.env.observation_space().shape[0])

    def start(self, learner: ppo_jax.Learner, seed: int):
        """``(learner, races)``: the races started from ``seed``, with a key of their own
        (:data:`RACE_KEY_OFFSET` + seed), apart from the policy's."""
        return ppo_jax.start_races(self.env, self.settings, learner, jax.random.PRNGKey(seed + RACE_KEY_OFFSET),
                                   self.num_envs)

    def update(self, learner: ppo_jax.Learner, races):
        """One update; returns ``(learner, races, episode records (step, race, car, fields),
        metrics)``, the metrics with ``nonfinite_actions``: the policy's actions in the update
        that were not finite (raced as zero jerk)."""
        learner, races, log, metrics = self.update_fn(learner, races)
        log = {name: np.asarray(value) for name, value in log.items()}
        metrics = {**metrics, "nonfinite_actions": int(log["nonfinite_action"].sum())}
        episodes = []
        for t, b in zip(*np.nonzero(log["done"])):
            episodes.append((int(t), int(b), 0, {
                "return": float(log["return"][t, b]), "length": int(log["length"][t, b]),
                "finished": bool(log["finished"][t, b]), "place": int(log["position"][t, b]),
                "out": bool(log["out"][t, b]),
                "finish_time": None if np.isnan(log["finish_time"][t, b]) else float(log["finish_time"][t, b]),
                "truncated": bool(log["truncated"][t, b])}))
        return learner, races, episodes, metrics

    def saved(self, races) -> Any:
        return jax.device_get(races)

    def restore(self, saved: Any):
        return jax.tree_util.tree_map(jnp.asarray, saved)

    def close(self) -> None:
        pass


class _Host:
    """Races stepped from Python (:class:`experiments.rl.vec_env.RaceVecEnv`), the policy's
    steps and the fit compiled."""

    kind = "host"

    def __init__(self, config, settings: ppo_jax.PPOSettings) -> None:
        self.config, self.settings = config, settings
        self.venv = make_vector_env(config)
        self.cars = config.cars
        self.obs = None
        self._act = jax.jit(lambda learner, obs: ppo_jax.policy_step(settings, learner, obs))
        self._after = jax.jit(lambda learner, raw, reward, done: ppo_jax.after_env_step(settings, learner, raw,
                                                                                        reward, done))
        self._start = jax.jit(lambda learner, raw: ppo_jax.observe_start(settings, learner, raw))
        self._fit = jax.jit(lambda learner, rollout, last: ppo_jax.fit(settings, learner, rollout, last))

    @property
    def observation_size(self) -> int:
        return int(self.venv.observation_space.shape[0])

    def start(self, learner: ppo_jax.Learner, seed: int):
        """``(learner, races)``: the races started from ``seed``."""
        self.venv.seed(seed)
        learner, obs = self._start(learner, jnp.asarray(self.venv.reset()))
        return learner, self._snapshot(obs)

    def _snapshot(self, obs) -> dict[str, Any]:
        """The races as they stand (None where the opponents' memory cannot be saved) with
        the policy's next observations ``(B, O)``."""
        return {"races": self.venv.get_state() if self.venv.exact_state else None, "obs": obs}

    def update(self, learner: ppo_jax.Learner, races):
        """One update, as :meth:`_Compiled.update`: a policy's action that is not finite is
        raced as zero jerk and counted, as :class:`racing_env.vector.GymnaxRace` does."""
        steps, episodes = [], []
        obs = races["obs"]
        nonfinite = 0
        for t in range(self.settings.n_steps):
            learner, action, log_prob, value = self._act(learner, obs)
            env_action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
            bad = ~np.isfinite(env_action).all(axis=1)
            env_action[bad] = 0.0
            nonfinite += int(bad.sum())
            raw, reward, done, infos = self.venv.step(env_action)
            learner, next_obs, scaled = self._after(learner, jnp.asarray(raw), jnp.asarray(reward, jnp.float64),
                                                    jnp.asarray(done))
            steps.append(ppo_jax.Rollout(obs, action, log_prob, value, scaled, jnp.asarray(done)))
            obs = next_obs
            for b in np.flatnonzero(done):
                if "episode" in infos[b]:
                    episodes.append((t, int(b), int(b) % self.cars, episode_fields(infos[b])))
        rollout = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *steps)
        learner, metrics = self._fit(learner, rollout, obs)
        return learner, self._snapshot(obs), episodes, {**metrics, "nonfinite_actions": nonfinite}

    def saved(self, races) -> Any:
        return None if races["races"] is None else {"races": races["races"], "obs": np.asarray(races["obs"])}

    def restore(self, saved: Any):
        self.venv.reset()  # started (its seeds are the saved races')
        self.venv.set_state(saved["races"])
        return {"races": saved["races"], "obs": jnp.asarray(saved["obs"])}

    def close(self) -> None:
        self.venv.close()


def make_races(config, settings: ppo_jax.PPOSettings):
    """The run's races in their form (module docstring)."""
    env = compiled_races(config)
    return _Compiled(env, settings, config.envs) if env is not None else _Host(config, settings)


# --- files -------------------------------------------------------------------------------------
def _policy_file(out: Path, timesteps: int) -> Path:
    return out / CHECKPOINTS / f"step_{timesteps:09d}.npz"


def save_policy_file(learner: ppo_jax.Learner, settings: ppo_jax.PPOSettings, path: Path,
                     observation_units: str, car_class: str | None = None) -> Path:
    """The policy of ``learner`` as a model file (:func:`planners.agents.jax_policy.save_model`),
    trained on observations in ``observation_units`` in a car of class ``car_class``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if settings.normalize:
        mean, var = np.asarray(learner.obs_stats[0]), np.asarray(learner.obs_stats[1])
    else:  # the identity: (obs - 0) / sqrt(1 - eps + eps), and a clip far outside any observation
        mean = np.zeros_like(np.asarray(learner.obs_stats[0]))
        var = np.full_like(mean, 1.0 - ppo_jax.EPSILON)
    clip = settings.clip_obs if settings.normalize else np.finfo(np.float32).max
    return save_model(path, settings.hidden, jax.device_get(learner.params), mean, var, clip, ppo_jax.EPSILON,
                      observation_units, car_class)


class _Point(NamedTuple):
    """The training right after an update (one object, so that Ctrl-C never splits it)."""

    learner: ppo_jax.Learner
    races: Any
    timesteps: int
    updates: int


def _checkpoint(out: Path, point: _Point, races, settings, observation_units: str, car_class: str) -> None:
    """The policy at ``point`` and, in ``resume.pkl``, everything a resumption needs."""
    save_policy_file(point.learner, settings, _policy_file(out, point.timesteps), observation_units, car_class)
    state = {"version": _STATE_VERSION, "timesteps": point.timesteps, "updates": point.updates, "kind": races.kind,
             "learner": jax.device_get(point.learner), "races": races.saved(point.races)}
    replace_atomically(lambda tmp: tmp.write_bytes(pickle.dumps(state)), out / CHECKPOINTS / RESUME)


def latest_state(out: Path) -> dict[str, Any] | None:
    """The saved training state (``checkpoints/resume.pkl``), or None."""
    path = out / CHECKPOINTS / RESUME
    return pickle.loads(path.read_bytes()) if path.exists() else None


# --- the run -----------------------------------------------------------------------------------
def run_jax_training(config, out: Path, fresh: bool = False, progress: bool = True) -> dict[str, Any]:
    """Train (or resume) into ``out`` with the JAX learner; returns the report also written to
    ``train.json`` (``"status"``: ``completed`` or ``interrupted``, after Ctrl-C, not raised)."""
    from rich.console import Console

    console = Console(stderr=True)
    settings = ppo_settings(config)
    if fresh and out.exists():
        for name in (CONFIG, EPISODES, EVALUATIONS, JAX_MODEL, "learning_curve.png"):
            (out / name).unlink(missing_ok=True)
        shutil.rmtree(out / CHECKPOINTS, ignore_errors=True)
    saved = latest_state(out)
    check_resumable(config, out, saved is not None)
    out.mkdir(parents=True, exist_ok=True)
    report: dict[str, Any] = {"config": config_json(config), "status": "running", "timesteps": 0,
                              "learner": "jax", "model_settings": _settings_json(settings)}
    began = time.perf_counter()
    races = make_races(config, settings)
    report["races"] = races.kind
    learner = ppo_jax.init_learner(jax.random.PRNGKey(config.seed), races.observation_size, config.envs, settings)
    if saved is not None:
        learner = jax.tree_util.tree_map(jnp.asarray, saved["learner"])
        if saved["races"] is not None and saved["kind"] == races.kind:
            in_flight = races.restore(saved["races"])
        else:  # opponents whose memory is not saved: fresh races, from starts of their own
            learner, in_flight = races.start(learner, config.seed + saved["timesteps"])
        point = _Point(learner, in_flight, saved["timesteps"], saved["updates"])
        drop_episodes_after(out, point.timesteps)
        console.print(f"resuming from {out / CHECKPOINTS / RESUME} ({point.timesteps:,} of {config.timesteps:,} "
                      "steps)")
    else:
        point = _Point(*races.start(learner, config.seed), 0, 0)
    write_json_atomically(report, out / CONFIG)
    drop_cut_line(out / EVALUATIONS)
    per_update = settings.n_steps * config.envs
    next_checkpoint = next_multiple(point.timesteps, config.checkpoint_every)
    next_eval = next_multiple(point.timesteps, config.eval_every)
    first_update_s = fit_s = evaluations_s = 0.0
    nonfinite = 0  # the policy's actions that were not finite (raced as zero jerk)
    first = point.updates
    started = time.perf_counter()
    bar = _progress(progress, config, point.timesteps)
    try:
        while point.timesteps < config.timesteps:
            t0 = time.perf_counter()
            learner, in_flight, episodes, metrics = races.update(point.learner, point.races)
            jax.block_until_ready(learner.params)
            elapsed = time.perf_counter() - t0
            nonfinite += metrics["nonfinite_actions"]
            for t, b, car, fields in episodes:
                append_jsonl(out / EPISODES, {"timesteps": point.timesteps + (t + 1) * config.envs, "env": b,
                                              "car": car, **fields})
            point = _Point(learner, in_flight, point.timesteps + per_update, point.updates + 1)
            if point.updates == first + 1:
                first_update_s = elapsed  # with compiling
            else:
                fit_s += elapsed
            if bar is not None:
                bar[0].update(bar[1], completed=min(point.timesteps, config.timesteps),
                              description=_bar_text(episodes, per_update / elapsed))
            t0 = time.perf_counter()
            if next_checkpoint is not None and point.timesteps >= next_checkpoint:
                _checkpoint(out, point, races, settings, config.observation_units, config.car)
                next_checkpoint = next_multiple(point.timesteps, config.checkpoint_every)
            if next_eval is not None and point.timesteps >= next_eval:
                _evaluate(config, out, point, settings, console)
                next_eval = next_multiple(point.timesteps, config.eval_every)
            evaluations_s += time.perf_counter() - t0
        _checkpoint(out, point, races, settings, config.observation_units, config.car)
        save_policy_file(point.learner, settings, out / JAX_MODEL, config.observation_units, config.car)
        evaluate_final(config, out / JAX_MODEL, point.timesteps, out, console)
        report["status"] = "completed"
    except KeyboardInterrupt:
        _checkpoint(out, point, races, settings, config.observation_units, config.car)
        drop_episodes_after(out, point.timesteps)
        report["status"] = "interrupted"
        console.print(f"interrupted at {point.timesteps:,} steps: checkpoint saved; run the same command to resume")
    finally:
        if bar is not None:
            bar[0].stop()
        races.close()
    trained = (point.updates - first) * per_update
    wall = time.perf_counter() - started
    report["timesteps"] = int(point.timesteps)
    report["wall_s"] = wall
    report["learn"] = {"steps": trained, "updates": point.updates - first, "wall_s": wall, "setup_s": started - began,
                       "first_update_s": first_update_s, "fit_s": fit_s,
                       "checkpoints_evaluations_s": evaluations_s,
                       "steps_per_s": (trained - per_update) / fit_s if fit_s > 0 else None,
                       "nonfinite_actions": nonfinite}
    if nonfinite:
        console.print(f"[yellow]{nonfinite:,} of the policy's {trained:,} actions were not finite (NaN or inf) and "
                      "raced as zero jerk: its parameters have diverged (see train.json's learn.nonfinite_actions)")
    finish_report(config, out, report, out / JAX_MODEL, "PPO (JAX)", console)
    return report


def _evaluate(config, out: Path, point: _Point, settings, console) -> None:
    path = _policy_file(out, point.timesteps)
    if not path.exists():
        save_policy_file(point.learner, settings, path, config.observation_units, config.car)
    record_evaluation(config, path, point.timesteps, out, console)


def _settings_json(settings: ppo_jax.PPOSettings) -> dict[str, Any]:
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(settings).items()}


def _progress(enabled: bool, config, timesteps: int):
    """A rich progress bar over the run's steps (None when disabled)."""
    if not enabled:
        return None
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    bar = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    task = bar.add_task("compiling", total=config.timesteps, completed=timesteps)
    bar.start()
    return bar, task


def _bar_text(episodes: list, steps_per_s: float) -> str:
    """The progress line: the last update's rate and its episodes' mean return."""
    text = f"{steps_per_s:9,.0f} steps/s"
    if episodes:
        text += f"  return {np.mean([fields['return'] for _, _, _, fields in episodes]):8.2f}"
    return text
