"""`racing train`: train a stable-baselines3 agent against planner or scripted opponents.

The learner drives one car of the Gymnasium view (:class:`racing_env.single_agent.RaceEnv`)
against agent specs (``lane-keeping``, ``ilqgame-fb``, ``rl:path.zip``, ...) on seeded rolling
grids, or alone (a time trial, ``opponents=()``). ``envs`` copies of the race run side by
side, the learner driving car ``copy % cars`` in each; every episode draws its own grid
order, so the learner starts both in front and behind. The copies are stepped by the
vectorised race (:class:`experiments.rl.vec_env.RaceVecEnv`, all copies in a few compiled
calls) unless ``vector=False`` or ``subprocesses``, which step one Gymnasium env per copy
(SB3's ``DummyVecEnv`` / ``SubprocVecEnv``). Observations (and rewards) are
normalised by SB3's ``VecNormalize`` unless ``normalize=False``; its statistics
are saved beside every model, where :class:`planners.agents.SB3Agent` finds them.

Every ``eval_every`` steps the current policy is saved and raced against the opponents
under tournament rules (:func:`experiments.tournament.race_lineup`: every starting slot, on
``eval_grids`` grids, off-track and contact penalised but not retiring): win rate, finish
margin, distance, incidents. Nothing is lost when a run stops: episodes and evaluations are
appended to JSONL files as they happen, a checkpoint is written every ``checkpoint_every``
steps and at Ctrl-C, and running the same command again resumes from the last checkpoint
(or trains further if ``timesteps`` was raised).

Output folder::

    train.json            configuration, status, timesteps, wall time, final evaluation
    model.zip             the final policy (+ model.vecnormalize.pkl): ``rl:OUT/model.zip``
    init_model_widened.zip  (+ statistics) an init_model of fewer cars, widened for this race
    checkpoints/          step_<timesteps>.zip (+ .vecnormalize.pkl; for the latest, + .replay_buffer.pkl
                          (off-policy) or + .resume.pkl (the races in flight, the random states))
    episodes.jsonl        one line per finished training episode
    evaluations.jsonl     one line per evaluation
    learning_curve.png    episode return and evaluation results against timesteps
    demonstrations.npz    with ``imitate``: the expert's driving (:mod:`experiments.rl.imitation`)
    imitation.zip         with ``imitate``: the cloned policy RL starts from (+ statistics)
    imitation.json        with ``imitate``: the expert's episodes and the fit's errors
"""

from __future__ import annotations

import ast
import copy as copying
import dataclasses
import json
import pickle
import random
import re
import signal
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from experiments.files import one_writer, replace_atomically, write_json_atomically
from experiments.jsonl import append_jsonl, drop_cut_line, read_jsonl
# TrainConfig and the pieces both learners share live below both (experiments.rl.config,
# experiments.rl.common); they stay importable from here, where they used to be
from experiments.rl.common import (check_resumable, drop_episodes_after, episode_fields,  # noqa: F401
                                   evaluate_final, finish_report, make_vector_env, next_multiple,
                                   record_evaluation)
from experiments.rl.config import (CHECKPOINTS, CONFIG, EPISODES, EVALUATION_RULE, EVALUATIONS,  # noqa: F401
                                   IMITATION_ALGOS, LEARNERS, PPO_MIN_STEPS, PPO_MINIBATCHES, PPO_ROLLOUT,
                                   RESUMABLE_CHANGES, TRAINING_STARTS, TrainConfig, algorithm_parameters,
                                   config_json, default_hyperparameters, jax_ppo_parameters)
from experiments.rl.evaluation import evaluate, evaluation_line  # noqa: F401
from experiments.rl.imitation import Demonstrations, clone, collect_demonstrations
from experiments.rl.widen import (Widening, measure_new_features, observation_widening, widen_normalizer,
                                  widen_saved_model)
from planners.agents import check_specs, make_agent, vecnormalize_path

MODEL = "model.zip"
WIDENED_MODEL = "init_model_widened.zip"  # an init_model of fewer cars, as widened for this race
DEMONSTRATIONS = "demonstrations.npz"
IMITATION_MODEL = "imitation.zip"
IMITATION_REPORT = "imitation.json"
# demonstration episode k is reset with seed DEMONSTRATION_SEED + 10_000 * seed + k (apart from the grids'
# of training, seed + copy, and of the evaluations, 1_000_000 + 10_000 * seed + grid)
DEMONSTRATION_SEED = 2_000_000
_CHECKPOINT = re.compile(r"step_(\d+)\.zip$")
# the fields of TrainConfig that do not change how the imitated expert drives: demonstrations
# saved by a run that differed only in these are reused (``demonstrations_source``)
_NOT_IN_DEMONSTRATIONS = RESUMABLE_CHANGES + ("imitate_episodes", "imitate_spread", "algo", "hyperparameters",
                                              "normalize", "eval_off_track", "eval_grids", "init_model")
# steps (all copies) over which a widened init_model's new observation features are measured
WIDENING_MEASURE_STEPS = 2048


def model_settings(config: TrainConfig) -> dict[str, Any]:
    """The keyword arguments the run's SB3 algorithm is built with: the
    :func:`default_hyperparameters` for its ``envs``, overridden by its ``hyperparameters``."""
    return {**default_hyperparameters(config.algo, config.envs), **dict(config.hyperparameters)}


def model_file(config: TrainConfig) -> str:
    """The final model's file name in a run's folder: ``model.zip`` (SB3) or ``model.npz`` (JAX)."""
    return "model.npz" if config.learner == "jax" else MODEL


def parse_hyperparameter(text: str) -> tuple[str, Any]:
    """``"name=value"`` -> ``(name, value)``; the value is read as a Python literal
    (``1024``, ``3e-4``, ``True``, ``{"net_arch": [64, 64]}``), else kept as a string."""
    name, sep, value = text.partition("=")
    name = name.strip().replace("-", "_")
    if not sep or not name:
        raise ValueError(f"expected NAME=VALUE (e.g. n_steps=1024), got {text!r}")
    try:
        return name, ast.literal_eval(value.strip())
    except (ValueError, SyntaxError):
        return name, value.strip()


def parse_reward_weight(text: str) -> tuple[str, float]:
    """``"position=0.05"`` -> ``("position", 0.05)``."""
    name, sep, value = text.partition("=")
    try:
        return name.strip(), float(value)
    except ValueError:
        raise ValueError(f"expected TERM=NUMBER (e.g. position=0.05), got {text!r}") from None


def latest_checkpoint(out: Path) -> tuple[int, Path] | None:
    """The complete checkpoint with the most timesteps in ``out/checkpoints``, or None
    (:func:`save_policy` writes a checkpoint's ``.zip`` after its companions)."""
    found = [(int(m.group(1)), p) for p in (out / CHECKPOINTS).glob("step_*.zip")
             if (m := _CHECKPOINT.search(p.name))]
    return max(found) if found else None


def _replay_buffer_path(model_path: Path) -> Path:
    return model_path.with_name(model_path.name[: -len(".zip")] + ".replay_buffer.pkl")


def save_policy(model, venv, path: Path, replay_buffer: bool = False) -> None:
    """``model.zip`` and, under ``VecNormalize``, its statistics beside it; with
    ``replay_buffer`` an off-policy model's buffer too (what a resumption needs).

    The model is written last: a checkpoint whose ``.zip`` exists is complete, so a run
    killed while saving resumes from the checkpoint before (:func:`latest_checkpoint`)."""
    from stable_baselines3.common.vec_env import VecNormalize

    path.parent.mkdir(parents=True, exist_ok=True)
    if replay_buffer and hasattr(model, "replay_buffer"):
        replace_atomically(lambda tmp: model.save_replay_buffer(tmp), _replay_buffer_path(path))
    if isinstance(venv, VecNormalize):
        replace_atomically(lambda tmp: venv.save(str(tmp)), vecnormalize_path(path))
    replace_atomically(lambda tmp: model.save(tmp), path)


@dataclasses.dataclass(frozen=True)
class _RaceCopy:
    """Builds copy ``copy`` of the training race (picklable, for worker processes, which
    also get the parent's compilation cache so they load the planners it compiled)."""

    config: TrainConfig
    copy: int
    in_worker: bool = False
    compile_cache: str | None = None

    def __call__(self):
        from stable_baselines3.common.monitor import Monitor

        from racing_env.single_agent import RaceEnv

        if self.in_worker:  # Ctrl-C reaches the whole process group: the parent stops the workers itself
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            from racing_env.xla_setup import configure_for_racing

            configure_for_racing()  # a spawned process starts with JAX's defaults: the parent's settings
        if self.compile_cache is not None:
            from planners.compile_cache import enable_compile_cache

            enable_compile_cache(self.compile_cache)
        from racing_env.single_agent import OpponentPool

        race = self.config.race_config(copy=self.copy)
        specs = self.config.opponents
        if self.config.pool:
            opponents = [OpponentPool([make_agent(spec) for spec in specs], names=specs)
                         for _ in range(self.config.cars - 1)]
        else:
            opponents = [make_agent(spec) for spec in specs]
        fields = {f.name: getattr(race, f.name) for f in dataclasses.fields(race)}
        return Monitor(RaceEnv(opponents=opponents, learner=self.copy % self.config.cars, **fields),
                       info_keywords=("finished", "position", "out", "finish_time"))


def make_training_env(config: TrainConfig):
    """``config.envs`` monitored copies of the race, the learner as car ``copy % N``: the
    vectorised race (:func:`make_vector_env`), or with ``vector=False`` a ``DummyVecEnv``
    of Gymnasium envs, each with opponent agents of its own, or with ``subprocesses`` a
    ``SubprocVecEnv`` of them (one worker process per copy)."""
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    from planners.compile_cache import compile_cache_dir

    if config.vectorised:
        return make_vector_env(config)
    if not config.subprocesses:
        return DummyVecEnv([_RaceCopy(config, k) for k in range(config.envs)])
    cache = compile_cache_dir()
    return _with_float32_rewards(SubprocVecEnv([_RaceCopy(config, k, True, cache) for k in range(config.envs)],
                                                 start_method="spawn"))


def _with_float32_rewards(venv):
    """The rewards of a ``SubprocVecEnv`` rounded to float32, as ``DummyVecEnv`` stores
    them: the observations of the two are identical, so training is too."""
    from stable_baselines3.common.vec_env import VecEnvWrapper

    class Float32Rewards(VecEnvWrapper):
        def reset(self):
            return self.venv.reset()

        def step_wait(self):
            observations, rewards, dones, infos = self.venv.step_wait()
            return observations, rewards.astype(np.float32), dones, infos

    return Float32Rewards(venv)


def _training_callback(config: TrainConfig, out: Path, console):
    """An SB3 callback that logs finished episodes, and writes checkpoints and evaluates
    right after a policy update (at the start of a rollout), so that a checkpoint's
    timesteps count exactly the steps its policy was trained on. ``updated_at`` is the
    timesteps of the last update; ``resume_point`` (on-policy algorithms) the model as it
    was then (:class:`_ResumePoint`)."""
    from stable_baselines3.common.callbacks import BaseCallback

    class Recorder(BaseCallback):
        rollout_s = 0.0  # wall time collecting rollouts [s]
        saving_s = 0.0  # wall time in checkpoints and evaluations [s]

        def _on_training_start(self) -> None:
            self.updated_at = self.num_timesteps
            self.resume_point = _resume_point(self.model) if _on_policy(self.model) else None
            self.next_checkpoint = next_multiple(self.num_timesteps, config.checkpoint_every)
            self.next_eval = next_multiple(self.num_timesteps, config.eval_every)

        def _resume_state(self) -> dict[str, Any] | None | str:
            return self.resume_point.state if self.resume_point is not None else _NOW

        def _on_rollout_start(self) -> None:
            began = time.perf_counter()
            self._save_and_evaluate()
            self.rollout_began = time.perf_counter()
            self.saving_s += self.rollout_began - began

        def _on_rollout_end(self) -> None:
            self.rollout_s += time.perf_counter() - self.rollout_began

        def _save_and_evaluate(self) -> None:
            self.updated_at = self.num_timesteps
            if _on_policy(self.model):
                self.resume_point = _resume_point(self.model)
            saved = None
            if self.next_checkpoint is not None and self.num_timesteps >= self.next_checkpoint:
                saved = checkpoint(self.model, out, self._resume_state())
                self.next_checkpoint = next_multiple(self.num_timesteps, config.checkpoint_every)
            if self.next_eval is not None and self.num_timesteps >= self.next_eval:
                record_evaluation(config, saved or checkpoint(self.model, out, self._resume_state()),
                                  self.num_timesteps, out, console)
                self.next_eval = next_multiple(self.num_timesteps, config.eval_every)

        def _on_step(self) -> bool:
            infos = self.locals["infos"]
            for copy in np.flatnonzero(self.locals["dones"]).tolist():
                info = infos[copy]
                if "episode" in info:
                    append_jsonl(out / EPISODES, {"timesteps": int(self.num_timesteps), "env": copy,
                                                  "car": copy % config.cars, **episode_fields(info)})
            return True

    return Recorder()


_NOW = "now"  # checkpoint(): the resume state is the current one


def checkpoint(model, out: Path, resume_state: dict[str, Any] | None | str = _NOW) -> Path:
    """Save ``checkpoints/step_<timesteps>.zip`` (with what a resumption needs); only the
    latest checkpoint keeps an off-policy replay buffer or a resume state (they are large).

    ``resume_state``: the races in flight and random states to resume from
    (:func:`_resume_state`, taken at the start of the rollout the model's timesteps count
    to; None: none); default: the current ones, right for a model that has just been updated."""
    path = out / CHECKPOINTS / f"step_{model.num_timesteps:09d}.zip"
    if resume_state is _NOW:
        resume_state = _resume_state(model)
    path.parent.mkdir(parents=True, exist_ok=True)
    if resume_state is not None:
        replace_atomically(lambda tmp: tmp.write_bytes(pickle.dumps(resume_state)), _resume_path(path))
    save_policy(model, model.get_env(), path, replay_buffer=True)
    for old in (out / CHECKPOINTS).glob("*.replay_buffer.pkl"):
        if old != _replay_buffer_path(path):
            old.unlink()
    for old in (out / CHECKPOINTS).glob(f"*{RESUME_SUFFIX}"):
        if resume_state is None or old != _resume_path(path):
            old.unlink()
    return path


# --- exact resumption ---------------------------------------------------------------------------
# A checkpoint is taken right after a policy update. With the vectorised races and an on-policy
# algorithm it also keeps the races in flight and the random states (``.resume.pkl``), and a run
# resumed from it goes on exactly as if it had not stopped. Ctrl-C rewinds the model and the
# normaliser to the start of the rollout it cut (:class:`_ResumePoint`), so that the checkpoint
# it writes is that point, whatever the interrupt cut (a rollout, an update, a save).
RESUME_SUFFIX = ".resume.pkl"


def _resume_path(model_path: Path) -> Path:
    return model_path.with_name(model_path.name[: -len(".zip")] + RESUME_SUFFIX)


def _on_policy(model) -> bool:
    from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm

    return isinstance(model, OnPolicyAlgorithm)


def _resume_state(model) -> dict[str, Any] | None:
    """What a run resumed from the model's checkpoint needs besides the model and the
    normaliser's statistics to go on exactly: the races in flight, the normaliser's running
    returns (B,), the last observations (B, O) and episode starts (B,), Python's, NumPy's and
    torch's random states. None where it cannot go on exactly (single-env copies, an
    off-policy algorithm, opponents whose memory is not saved, no rollout collected yet)."""
    import torch
    from stable_baselines3.common.vec_env import VecNormalize

    from experiments.rl.vec_env import RaceVecEnv

    venv = model.get_env()
    races = venv.unwrapped
    if (not _on_policy(model) or not isinstance(races, RaceVecEnv) or not races.exact_state
            or model._last_obs is None):
        return None
    normalizer = venv if isinstance(venv, VecNormalize) else None
    return {
        "timesteps": int(model.num_timesteps),
        "races": races.get_state(),
        "normalizer": None if normalizer is None else {
            name: copying.deepcopy(getattr(normalizer, name)) for name in ("returns", "old_obs", "old_reward")},
        "last_obs": np.array(model._last_obs),
        "last_episode_starts": np.array(model._last_episode_starts),
        "random": (random.getstate(), np.random.get_state(), torch.get_rng_state()),
    }


def _restore_resume_state(model, state: dict[str, Any]) -> None:
    """Put the races, the normaliser's running returns, the last observations and the random
    states back as :func:`_resume_state` found them (after ``algo.load``, which re-seeds)."""
    import torch

    venv = model.get_env()
    venv.unwrapped.set_state(state["races"])
    if state["normalizer"] is not None:
        for name, value in state["normalizer"].items():
            setattr(venv, name, copying.deepcopy(value))
    model._last_obs = np.array(state["last_obs"])
    model._last_episode_starts = np.array(state["last_episode_starts"])
    python, numpy, torch_state = state["random"]
    random.setstate(python)
    np.random.set_state(numpy)
    torch.set_rng_state(torch_state)


@dataclasses.dataclass
class _ResumePoint:
    """An on-policy model at the start of a rollout, right after its update: what Ctrl-C
    rewinds to. ``policy``/``optimizer``: state dicts (copies); ``statistics``: the
    normaliser's ``obs_rms`` and ``ret_rms`` (copies, None without one); ``state``:
    :func:`_resume_state`."""

    timesteps: int
    n_updates: int
    policy: dict[str, Any]
    optimizer: dict[str, Any]
    statistics: dict[str, Any] | None
    state: dict[str, Any] | None


def _resume_point(model) -> _ResumePoint:
    from stable_baselines3.common.vec_env import VecNormalize

    venv = model.get_env()
    statistics = ({name: copying.deepcopy(getattr(venv, name)) for name in ("obs_rms", "ret_rms")}
                  if isinstance(venv, VecNormalize) else None)
    return _ResumePoint(int(model.num_timesteps), int(getattr(model, "_n_updates", 0)),
                        copying.deepcopy(model.policy.state_dict()),
                        copying.deepcopy(model.policy.optimizer.state_dict()), statistics, _resume_state(model))


def _rewind(model, point: _ResumePoint) -> None:
    """Put the model and its normaliser's statistics back to ``point`` (the races are not:
    the checkpoint takes them from ``point.state``)."""
    model.policy.load_state_dict(point.policy)
    model.policy.optimizer.load_state_dict(point.optimizer)
    model.num_timesteps = point.timesteps
    if hasattr(model, "_n_updates"):
        model._n_updates = point.n_updates
    if point.statistics is not None:
        for name, value in point.statistics.items():
            setattr(model.get_env(), name, copying.deepcopy(value))


def _saved_resume_state(config: TrainConfig, model, path: Path) -> dict[str, Any] | None:
    """The resume state saved with the checkpoint ``path``, if this run can go on from it
    (the vectorised races, an on-policy algorithm); else None."""
    from experiments.rl.vec_env import RaceVecEnv

    saved = _resume_path(path)
    if not (saved.exists() and config.vectorised and _on_policy(model)
            and isinstance(model.get_env().unwrapped, RaceVecEnv)):
        return None
    state = pickle.loads(saved.read_bytes())
    return state if state["timesteps"] == model.num_timesteps else None


def _build_model(config: TrainConfig, out: Path, resume_from: tuple[int, Path] | None):
    """A new model, the ``init_model`` to train further, or the checkpointed one, with its
    env statistics and (off-policy) replay buffer."""
    import stable_baselines3 as sb3
    from stable_baselines3.common.vec_env import VecNormalize

    algo = getattr(sb3, config.algo.upper())
    venv = make_training_env(config)
    hyperparameters = dict(config.hyperparameters)  # the user's, named in errors
    settings = model_settings(config)
    if resume_from is not None:
        steps, path = resume_from
        if config.normalize:
            venv = VecNormalize.load(str(vecnormalize_path(path)), venv)
        model = algo.load(path, env=venv, device="cpu")
        if _replay_buffer_path(path).exists():
            model.load_replay_buffer(_replay_buffer_path(path))
        state = _saved_resume_state(config, model, path)
        if state is not None:  # the races go on where they were, with the random states of then
            _restore_resume_state(model, state)
        else:
            venv.seed(config.seed + steps)  # the resumed episodes start from grids of their own
        return model
    if config.init_model is None:
        try:
            return algo("MlpPolicy", VecNormalize(venv) if config.normalize else venv, seed=config.seed,
                        device="cpu", verbose=0, **settings)
        except (TypeError, ValueError, AssertionError) as err:
            if not hyperparameters and isinstance(err, TypeError):
                raise  # not a setting of the user's: a bug, keep its traceback
            # an error here need not be the hyperparameters' (e.g. one about the env): name them, not blame them
            given = f" (hyperparameters {hyperparameters})" if hyperparameters else ""
            raise ValueError(f"{config.algo} refused the model settings{given}: {type(err).__name__}: {err}") from err
    stats = vecnormalize_path(config.init_model)
    if config.normalize != stats.exists():
        raise ValueError(f"init_model {config.init_model} was trained {'with' if stats.exists() else 'without'} "
                         f"VecNormalize (statistics {'found' if stats.exists() else 'not found'} at {stats}); "
                         f"train it further with{'' if stats.exists() else ' --no-normalize'}")
    try:
        saved = algo.load(config.init_model, device="cpu")
        trained_on = getattr(saved, "observation_units", None)
        if trained_on not in (None, config.observation_units):
            raise ValueError(f"init_model {config.init_model} was trained on {trained_on} observations; train it "
                             f"further with --observation-units {trained_on}")
        widening = _init_model_widening(config, saved, venv)
        init_model = config.init_model
        if widening is not None:  # trained with fewer cars (e.g. a time trial): zero weights on the new cars
            init_model = widen_saved_model(saved, venv.observation_space, widening, out / WIDENED_MODEL)
        if config.normalize:
            venv = (VecNormalize.load(str(stats), venv) if widening is None
                    else widen_normalizer(stats, venv, widening))
        model = algo.load(init_model, env=venv, device="cpu", **settings)
    except (TypeError, ValueError, AssertionError, KeyError, AttributeError) as err:  # e.g. a PPO zip for SAC
        raise ValueError(f"{config.algo} cannot train {config.init_model} further in this race "
                         f"(hyperparameters {hyperparameters}): {err}") from err
    if widening is not None and config.normalize:
        measure_new_features(model, venv, widening, steps=WIDENING_MEASURE_STEPS)
        # beside the widened model, so that it races as trained so far: rl:OUT/init_model_widened.zip
        replace_atomically(lambda tmp: venv.save(str(tmp)), vecnormalize_path(init_model))
    model.num_timesteps = 0  # this run's steps count from zero
    model.set_random_seed(config.seed)
    return model


def demonstrations_source(config: TrainConfig) -> str:
    """The settings that decide how ``config.imitate`` drives its demonstrations (JSON):
    saved demonstrations of a run whose source differs are not its own."""
    settings = config_json(config)
    return json.dumps({k: v for k, v in settings.items() if k not in _NOT_IN_DEMONSTRATIONS}, sort_keys=True)


def _demonstrations(config: TrainConfig, path: Path, console, progress: bool) -> Demonstrations:
    """``config.imitate``'s driving for the clone, kept in ``path`` after every episode:
    after an interruption the same command drives only the episodes still missing (none
    once all are there); episodes driven in other settings are driven again."""
    source = demonstrations_source(config)
    saved = Demonstrations.load(path) if path.exists() else None
    if saved is not None and saved.source != source:
        console.print(f"{path} was driven in other settings: driving the demonstrations again")
        saved = None
    if saved is not None and saved.episodes >= config.imitate_episodes:
        console.print(f"cloning {config.imitate} from {path} ({config.imitate_episodes} of its "
                      f"{saved.episodes} episodes)")
        return saved.first(config.imitate_episodes)
    if saved is not None:
        console.print(f"{path} holds {saved.episodes} of {config.imitate_episodes} episodes: "
                      f"{config.imitate} drives the other {config.imitate_episodes - saved.episodes}")
    kept = [saved.episodes if saved is not None else 0]  # episodes saved so far

    def keep(so_far: Demonstrations) -> None:
        replace_atomically(so_far.save, path)
        kept[0] = so_far.episodes

    # episode k is driven in copy k % envs: the first imitate_episodes copies are all it needs
    envs = [_RaceCopy(config, copy)() for copy in range(min(config.envs, config.imitate_episodes))]
    try:
        return collect_demonstrations(envs, make_agent(config.imitate), config.imitate_episodes,
                                      DEMONSTRATION_SEED + 10_000 * config.seed, config.imitate_noise, progress,
                                      collected=saved, on_episode=keep, source=source)
    except KeyboardInterrupt:
        console.print(f"interrupted while {config.imitate} drove: {kept[0]} of {config.imitate_episodes} "
                      f"episodes kept in {path}")
        raise
    finally:
        for env in envs:
            env.close()


def _clone_expert(config: TrainConfig, model, out: Path, console, progress: bool) -> None:
    """Fit the fresh ``model`` to ``config.imitate``'s driving (:func:`_demonstrations`),
    save it as ``imitation.zip`` and evaluate it as at 0 steps."""
    started = time.perf_counter()
    demonstrations = _demonstrations(config, out / DEMONSTRATIONS, console, progress)
    collected = time.perf_counter() - started
    fit = clone(model, demonstrations, spread=config.clone_spread, seed=config.seed)
    save_policy(model, model.get_env(), out / IMITATION_MODEL)
    kept_evaluations = [e for e in read_jsonl(out / EVALUATIONS) if e["timesteps"] > 0]  # an earlier attempt's
    replace_atomically(lambda tmp: tmp.write_text("".join(json.dumps(e) + "\n" for e in kept_evaluations)),
                       out / EVALUATIONS)
    record = evaluate(config, out / IMITATION_MODEL, 0)
    append_jsonl(out / EVALUATIONS, record)
    write_json_atomically({"expert": config.imitate, "episodes": demonstrations.episodes,
                           "steps": len(demonstrations.actions),
                           "expert_finished": int(demonstrations.finished.sum()), "collect_s": collected,
                           "fit": fit, "evaluation": record}, out / IMITATION_REPORT)
    after = fit["after"]["held_out"] or fit["after"]["fitted"]
    console.print(f"cloned {config.imitate} from {len(demonstrations.actions):,} steps "
                  f"({demonstrations.episodes} episodes, {int(demonstrations.finished.sum())} finished): action "
                  f"error {after['action_rmse']:.3f} on the {'held-out' if fit['after']['held_out'] else 'fitted'} "
                  f"steps, action std {', '.join(f'{s:.2f}' for s in fit['action_std'])}")
    console.print(evaluation_line(record))


def _init_model_widening(config: TrainConfig, saved, venv) -> Widening | None:
    """How the ``saved`` init model's observation fits this race (None: it fits as it is)."""
    race = config.race_config()
    return observation_widening(saved.observation_space.shape[0], venv.observation_space.shape[0],
                                race.num_agents, len(race.preview_distances))


TORCH_THREADS = 1
"""torch's threads while training. The policy's networks are small: on 2 cores one thread
updates PPO as fast as two, and when another process keeps a core busy two threads
contending for the one left made PPO's updates about 17 times slower (docs/rl.md)."""


def run_training(config: TrainConfig, out: Path, fresh: bool = False, progress: bool = True) -> dict[str, Any]:
    """Train (or resume) into ``out``; returns the report also written to ``train.json``
    (``"status"``: ``completed`` or ``interrupted``, the latter after Ctrl-C, not raised).
    With ``config.learner == "jax"`` the JAX learner trains (:mod:`experiments.rl.train_jax`);
    else stable-baselines3, with torch on :data:`TORCH_THREADS` threads meanwhile (restored after)."""
    check_specs(config.opponents + ((config.imitate,) if config.imitate else ()))
    with one_writer(out, "training run"):
        if config.learner == "jax":
            from experiments.rl.train_jax import run_jax_training

            return run_jax_training(config, out, fresh=fresh, progress=progress)
        import torch

        threads = torch.get_num_threads()
        torch.set_num_threads(TORCH_THREADS)
        try:
            return _run_training(config, out, fresh, progress)
        finally:
            torch.set_num_threads(threads)


def _run_training(config: TrainConfig, out: Path, fresh: bool, progress: bool) -> dict[str, Any]:
    import shutil

    from rich.console import Console

    console = Console(stderr=True)
    if config.subprocesses and config.vector:
        console.print("subprocesses: each copy of the race is a Gymnasium env in a worker process of its own; the "
                      "vectorised races are not used")
    config_path = out / CONFIG
    if fresh and out.exists():
        for name in (CONFIG, EPISODES, EVALUATIONS, MODEL, WIDENED_MODEL, "learning_curve.png", DEMONSTRATIONS,
                     IMITATION_MODEL, IMITATION_REPORT):
            (out / name).unlink(missing_ok=True)
        for name in (MODEL, WIDENED_MODEL, IMITATION_MODEL):
            vecnormalize_path(out / name).unlink(missing_ok=True)
        shutil.rmtree(out / CHECKPOINTS, ignore_errors=True)
    wanted = config_json(config)
    resume_from = latest_checkpoint(out)
    check_resumable(config, out, resume_from is not None)
    out.mkdir(parents=True, exist_ok=True)
    report: dict[str, Any] = {"config": wanted, "status": "running", "timesteps": 0}
    model = _build_model(config, out, resume_from)
    model.observation_units = config.observation_units  # saved with the model: SB3Agent reads it
    model.car_class = config.car  # the learner's car's class, saved with the model alike
    report["model_settings"] = {name: getattr(model, name) for name in model_settings(config)
                                if isinstance(getattr(model, name, None), (int, float, str, bool))}
    if resume_from is not None:
        console.print(f"resuming from {resume_from[1]} ({resume_from[0]:,} of {config.timesteps:,} steps)")
        drop_episodes_after(out, resume_from[0])
    write_json_atomically(report, config_path)
    drop_cut_line(out / EVALUATIONS)
    if resume_from is None and config.imitate is not None:
        try:
            _clone_expert(config, model, out, console, progress)
        except KeyboardInterrupt:  # what was driven is kept; the clone is fitted again next time
            report["status"] = "interrupted"
            write_json_atomically(report, config_path)
            console.print("interrupted before training: run the same command to clone again and train")
            _close(model.get_env(), interrupted=True)
            return report
    remaining = config.timesteps - model.num_timesteps
    started = time.perf_counter()
    recorder = _training_callback(config, out, console)
    first_step = model.num_timesteps
    try:
        if remaining > 0:
            with warnings.catch_warnings():  # SB3's progress bar is tqdm's rich bar, which calls itself experimental
                warnings.filterwarnings("ignore", message="rich is experimental")
                model.learn(remaining, callback=recorder, reset_num_timesteps=False, progress_bar=progress)
            report["learn"] = _learn_timing(recorder, model.num_timesteps - first_step,
                                            time.perf_counter() - started)
            recorder.updated_at = model.num_timesteps  # learn ends with an update
            checkpoint(model, out)  # so that running the command again finds the run complete
        save_policy(model, model.get_env(), out / MODEL)
        evaluate_final(config, out / MODEL, model.num_timesteps, out, console)
        report["status"] = "completed"
    except KeyboardInterrupt:
        # the steps collected since the last update are not trained on: they are collected again
        point = getattr(recorder, "resume_point", None)
        if point is not None:  # back to the last update, whatever the interrupt cut (a rollout, an update)
            _rewind(model, point)
            checkpoint(model, out, point.state)
        else:
            model.num_timesteps = getattr(recorder, "updated_at", model.num_timesteps)
            checkpoint(model, out)
        drop_episodes_after(out, model.num_timesteps)
        report["status"] = "interrupted"
        console.print(f"interrupted at {model.num_timesteps:,} steps: checkpoint saved; run the same command "
                      "to resume")
    report["timesteps"] = int(model.num_timesteps)
    report["wall_s"] = time.perf_counter() - started
    _close(model.get_env(), interrupted=report["status"] == "interrupted")
    finish_report(config, out, report, out / MODEL, config.algo.upper(), console)
    return report


def _learn_timing(recorder, steps: int, wall_s: float) -> dict[str, float]:
    """Where the wall time of ``model.learn`` went [s]: collecting rollouts (races and the
    policy's actions), checkpoints and evaluations, and the rest, the policy updates; and
    the ``steps`` trained per second."""
    saving = recorder.saving_s
    return {"steps": steps, "wall_s": wall_s, "steps_per_s": steps / wall_s if wall_s > 0 else 0.0,
            "rollout_s": recorder.rollout_s, "checkpoints_evaluations_s": saving,
            "update_s": max(0.0, wall_s - recorder.rollout_s - saving)}


def _close(venv, interrupted: bool) -> None:
    """Close the training envs. After Ctrl-C, worker processes are terminated instead: the
    interrupt may have cut a step between two workers' replies, and a polite close would
    then wait for a reply that never comes."""
    from stable_baselines3.common.vec_env import SubprocVecEnv

    inner = venv.unwrapped
    if interrupted and isinstance(inner, SubprocVecEnv):
        for process in inner.processes:
            process.terminate()
            process.join()
        return
    venv.close()
