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
import inspect
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
from experiments.race_spec import RaceSpec
from experiments.rl.evaluation import evaluate, evaluation_line, plot_learning_curve
from experiments.rl.imitation import Demonstrations, clone, collect_demonstrations
from experiments.rl.widen import (Widening, measure_new_features, observation_widening, widen_normalizer,
                                  widen_saved_model)
from planners.agents import SB3_ALGOS, check_specs, make_agent, vecnormalize_path
from racing_env.config import RaceConfig, RewardConfig, check_incident_rules

CONFIG = "train.json"
EPISODES = "episodes.jsonl"
EVALUATIONS = "evaluations.jsonl"
CHECKPOINTS = "checkpoints"
MODEL = "model.zip"
WIDENED_MODEL = "init_model_widened.zip"  # an init_model of fewer cars, as widened for this race
DEMONSTRATIONS = "demonstrations.npz"
IMITATION_MODEL = "imitation.zip"
IMITATION_REPORT = "imitation.json"
IMITATION_ALGOS = ("ppo", "a2c")  # actor-critics with a Gaussian policy, which behaviour cloning fits
# demonstration episode k is reset with seed DEMONSTRATION_SEED + 10_000 * seed + k (apart from the grids'
# of training, seed + copy, and of the evaluations, 1_000_000 + 10_000 * seed + grid)
DEMONSTRATION_SEED = 2_000_000
_CHECKPOINT = re.compile(r"step_(\d+)\.zip$")
# the fields of TrainConfig that may change between a run and its resumption
_RESUMABLE_CHANGES = ("timesteps", "eval_every", "checkpoint_every", "subprocesses", "vector")
# the fields of TrainConfig that do not change how the imitated expert drives: demonstrations
# saved by a run that differed only in these are reused (``demonstrations_source``)
_NOT_IN_DEMONSTRATIONS = _RESUMABLE_CHANGES + ("imitate_episodes", "imitate_spread", "algo", "hyperparameters",
                                               "normalize", "eval_off_track", "eval_grids", "init_model")
TRAINING_STARTS = ("grid", "anywhere", "mixed")  # where training episodes may start (TrainConfig.start)
# fields added to TrainConfig after runs were saved, with the value those runs had
_ADDED_LATER = {"start": "grid", "imitate": None, "imitate_episodes": 20, "imitate_noise": 0.2,
                "imitate_spread": None, "vector": False, "learner": "sb3"}
LEARNERS = ("sb3", "jax")  # TrainConfig.learner
# steps (all copies) over which a widened init_model's new observation features are measured
WIDENING_MEASURE_STEPS = 2048
EVALUATION_RULE = "penalty"  # what contact (and, unless eval_off_track is set, leaving the track) does in evaluations


@dataclasses.dataclass(frozen=True, kw_only=True)
class TrainConfig(RaceSpec):
    """What to train, against whom, and how long, in which race (:class:`RaceSpec`; off
    the track the training race's default rule is ``terminate``).

    Attributes:
        opponents: agent specs of the other cars (:func:`planners.agents.make_agent`); their
            number fixes the race's N = len(opponents) + 1. ``()``: a time trial, the learner
            alone on the track (N = 1). With ``pool`` they are a pool
            instead: every episode each opponent car is driven by one of them, drawn at
            random (a spec given twice is drawn twice as often).
        pool: draw the opponents from ``opponents`` every episode
            (:class:`racing_env.single_agent.OpponentPool`); evaluations then race the
            learner against each of them in turn, and report them apart.
        pool_cars: cars per race with ``pool`` (the learner included).
        algo: ``ppo`` (default), ``sac``, ``td3``, ``a2c`` or ``ddpg``.
        timesteps: environment steps to train for, over all copies of the race.
        track: built-in track name or TUMFTM CSV path.
        laps / race_distance: the race's length (``race_distance`` [m] overrides ``laps``).
        max_steps: an episode is truncated after this many steps.
        start: where training episodes start: ``grid`` (a seeded rolling grid behind the
            line, as the evaluations) or ``anywhere`` (a seeded close-quarters scene anywhere
            on the lap, :func:`racing_env.scenarios.anywhere`, racing to the same finish
            line), so that on a long circuit the policy meets every corner from the start;
            or ``mixed``: the even copies of the race (``envs``) start on the grid, the odd
            ones anywhere. Evaluations always start on the grid.
        seed: seeds the policy, the start grids and the evaluation grids.
        envs: copies of the race stepped side by side; in copy ``k`` the learner drives car
            ``k % N``. PPO's rollout and minibatch sizes follow it unless given
            (:func:`default_hyperparameters`).
        vector: step the copies with the vectorised race (:class:`experiments.rl.vec_env.RaceVecEnv`:
            the copies of each learner car and start scenario in one compiled call, the
            opponents batched), the fast way for many copies; False: one Gymnasium env per
            copy in a ``DummyVecEnv``, for opponents the batched form cannot drive. The
            copies' episodes are the same either way (to a few ulps; a pool draws its
            drivers differently), as is the model's interface. Ignored with ``subprocesses``.
        subprocesses: step each copy in a worker process of its own (``SubprocVecEnv``, one
            Gymnasium env per copy, whatever ``vector`` says), worth it against planner
            opponents that the vectorised race cannot batch, whose solves then run on
            several cores; the results are the same as in one process.
        normalize: train under ``VecNormalize`` (observations and rewards).
        on_off_track / on_collision: the training race's incident rules
            (:data:`racing_env.config.INCIDENT_MODES`). ``terminate`` off track (the default)
            ends an episode that leaves the track, which teaches staying on it far faster
            than a penalty per step.
        eval_off_track: what leaving the track does in the evaluations: None (the
            default) the tournaments' rule, counted but not ending the race; or an
            incident mode, e.g. ``terminate`` to retire a learner that leaves the track there
            too (a policy that wins by running wide past the edge then loses).
        jerk_weight: the planners' jerk weight r in the race's game (as in tournaments).
        checkpoint_every / eval_every: steps between checkpoints / evaluations (0: only at
            the end).
        eval_grids: start grids per evaluation; each is raced once per starting slot.
        reward: weights of the training race's reward terms that differ from
            :class:`racing_env.config.RewardConfig`'s defaults, e.g. ``(("position", 0.05),)``.
        hyperparameters: keyword arguments of the SB3 algorithm, e.g.
            ``(("n_steps", 1024), ("learning_rate", 1e-4))``; they win over
            :func:`default_hyperparameters`.
        init_model: a saved model of the same algorithm to train further (its VecNormalize
            statistics too), e.g. one trained against the fast lane keeper, before a planner
            opponent; ``None`` starts from a fresh policy. A model of a race with fewer cars
            (a time trial) is widened (:mod:`experiments.rl.widen`): zero weights on the
            new cars' features, whose statistics are measured over
            ``WIDENING_MEASURE_STEPS`` steps of this race before training.
        imitate: an agent spec (e.g. ``ilqr``) whose driving a fresh policy is cloned from
            before training (:mod:`experiments.rl.imitation`): it drives the learner's car for
            ``imitate_episodes`` seeded episodes of the training race, and the policy, its
            value and the normaliser are fitted to them. PPO and A2C only; not with
            ``init_model``. The cloned policy is evaluated (at 0 steps) before training.
        imitate_episodes: the expert's episodes, taken from the copies of the race in turn.
        imitate_noise: standard deviation of the noise added to the expert's actions
            (normalised units) while it drives for the demonstrations, so that they show it
            recovering from the errors a clone makes; 0 for the expert's own line only.
        imitate_spread: the cloned policy's standard deviation per action (normalised
            units), which the reinforcement learning that follows explores with; None: the
            ``imitate_noise`` (with no noise, PPO's initial one).
        learner: ``sb3`` (stable-baselines3, every ``algo``) or ``jax`` (PPO in JAX,
            :mod:`experiments.rl.train_jax`: with opponents that are JAX functions of the
            state the races and the updates are one compiled program). The JAX learner takes
            ``ppo`` only, no ``init_model``, ``imitate`` or ``subprocesses``; its
            ``hyperparameters`` are :class:`experiments.rl.ppo_jax.PPOSettings` fields.
    """

    opponents: tuple[str, ...] = ("lane-keeping",)
    pool: bool = False
    pool_cars: int = 2
    algo: str = "ppo"
    timesteps: int = 200_000
    start: str = "grid"
    seed: int = 0
    envs: int = 2
    vector: bool = True
    subprocesses: bool = False
    normalize: bool = True
    on_off_track: str = "terminate"
    eval_off_track: str | None = None
    checkpoint_every: int = 20_000
    eval_every: int = 50_000
    eval_grids: int = 2
    reward: tuple[tuple[str, float], ...] = ()
    hyperparameters: tuple[tuple[str, Any], ...] = ()
    init_model: str | None = None
    imitate: str | None = None
    imitate_episodes: int = 20
    imitate_noise: float = 0.2
    imitate_spread: float | None = None
    learner: str = "sb3"

    def __post_init__(self) -> None:
        super().__post_init__()  # the race's fields
        if self.pool and not self.opponents:
            raise ValueError("a pool needs at least one opponent spec to draw from (e.g. lane-keeping)")
        if self.algo not in SB3_ALGOS:
            raise ValueError(f"algo must be one of {SB3_ALGOS}, got {self.algo!r}")
        if self.learner not in LEARNERS:
            raise ValueError(f"learner must be one of {LEARNERS}, got {self.learner!r}")
        if self.learner == "jax":
            refused = [name for name, bad in (("algo other than ppo", self.algo != "ppo"),
                                              ("init_model", self.init_model is not None),
                                              ("imitate", self.imitate is not None),
                                              ("subprocesses", self.subprocesses),
                                              ("vector=False (--no-vector)", not self.vector)) if bad]
            if refused:
                raise ValueError(f"the JAX learner trains PPO from a fresh policy in one process: drop "
                                 f"{', '.join(refused)} (or use --learner sb3)")
        if self.start not in TRAINING_STARTS:
            raise ValueError(f"start must be one of {TRAINING_STARTS}, got {self.start!r}")
        if not isinstance(self.pool_cars, (int, np.integer)) or self.pool_cars < 2:
            raise ValueError(f"pool_cars must be an integer >= 2, got {self.pool_cars!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise ValueError(f"seed (--seed) must be an integer >= 0, got {self.seed!r}")
        if self.imitate is not None:
            if self.algo not in IMITATION_ALGOS:
                raise ValueError(f"imitation fits a Gaussian actor-critic policy: algo must be one of "
                                 f"{IMITATION_ALGOS}, got {self.algo!r}")
            if self.init_model is not None:
                raise ValueError("imitate starts a fresh policy from the expert; init_model trains a saved one "
                                 "further: give one of them")
            if not 0.0 <= self.imitate_noise < np.inf:
                raise ValueError(f"imitate_noise must be a finite standard deviation >= 0, got {self.imitate_noise!r}")
            if self.imitate_spread is not None and not 0.0 < self.imitate_spread < np.inf:
                raise ValueError(f"imitate_spread must be a finite standard deviation > 0 (or None: the "
                                 f"imitate_noise), got {self.imitate_spread!r}")
        for name in ("vector", "subprocesses", "pool", "normalize"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"{name} must be True or False, got {getattr(self, name)!r}")
        for name in ("timesteps", "envs", "eval_grids", "imitate_episodes"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        for name in ("checkpoint_every", "eval_every"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < 0:
                raise ValueError(f"{name} must be an integer >= 0 (0: only at the end), got {value!r}")
        if self.eval_off_track is not None:
            check_incident_rules(eval_off_track=self.eval_off_track)
        terms = {f.name for f in dataclasses.fields(RewardConfig)}
        for name, value in self.reward:
            if name not in terms:
                raise ValueError(f"unknown reward term {name!r}; the terms are {sorted(terms)}")
            if not np.isfinite(value):
                raise ValueError(f"reward weight {name} must be a finite number, got {value!r}")
        if self.init_model is not None and not any(Path(p).is_file() for p in (self.init_model,
                                                                                 f"{self.init_model}.zip")):
            raise ValueError(f"init_model {self.init_model} does not exist")
        known = algorithm_parameters(self.algo) if self.learner == "sb3" else jax_ppo_parameters()
        for name, _ in self.hyperparameters:
            if name not in known:
                raise ValueError(f"{self.learner} {self.algo} has no hyperparameter {name!r}; it takes {sorted(known)}")
        for copy in range(min(self.envs, 2)):  # the race of every start the copies use (its own limits)
            self.race_config(copy=copy)

    @property
    def vectorised(self) -> bool:
        """Whether the copies are stepped by the vectorised race (``vector`` without ``subprocesses``)."""
        return self.vector and not self.subprocesses

    @property
    def cars(self) -> int:
        return self.pool_cars if self.pool else len(self.opponents) + 1

    @property
    def time_trial(self) -> bool:
        """The learner races alone (no opponents)."""
        return self.cars == 1

    @property
    def clone_spread(self) -> float | None:
        """The cloned policy's standard deviation per action with ``imitate`` (normalised
        units; None: the algorithm's initial one)."""
        return self.imitate_spread or self.imitate_noise or None

    def description(self) -> str:
        """What the learner races, for titles: ``vs ilqgame-fb``, ``vs a pool of ...``, ``time trial``."""
        if self.time_trial:
            return "time trial"
        return f"vs {'a pool of ' if self.pool else ''}{', '.join(dict.fromkeys(self.opponents))}"

    def evaluation_lineups(self) -> list[tuple[str, list[str]]]:
        """``(label, opponent specs)`` the learner is evaluated against: the lineup, or with
        a pool every distinct spec of it driving every opponent car."""
        if not self.pool:
            return [(", ".join(self.opponents) or "time trial", list(self.opponents))]
        return [(spec, [spec] * (self.cars - 1)) for spec in dict.fromkeys(self.opponents)]

    def scenario(self, copy: int = 0) -> str:
        """The scenario copy ``copy`` of the training race starts from (:attr:`start`)."""
        if self.start == "mixed":
            return "grid" if copy % 2 == 0 else "anywhere"
        return self.start

    def race_config(self, training: bool = True, copy: int = 0) -> RaceConfig:
        """The race the learner trains in (``training``; copy ``copy`` of it) or is evaluated
        in (tournament rules, with ``eval_off_track`` if set)."""
        if training:
            return self.to_race_config(self.cars, self.scenario(copy), reward=RewardConfig(**dict(self.reward)))
        # the tournaments' rules: incidents penalised, not retiring, unless eval_off_track says otherwise
        return self.to_race_config(self.cars, "grid", on_collision=EVALUATION_RULE,
                                   on_off_track=self.eval_off_track or EVALUATION_RULE)


PPO_ROLLOUT = 4096
"""Samples per PPO update by default (``n_steps * envs``): SB3's ``n_steps=2048`` for the
default 2 copies, kept for any number of copies so that a step of the policy is trained on
as often whatever ``envs`` is."""
PPO_MINIBATCHES = 8
"""Minibatches per PPO epoch by default: ``batch_size = n_steps * envs / 8`` (512 samples at
the default rollout), where SB3's ``batch_size=64`` made 64 and the update cost more than
the races (measured: docs/rl.md)."""
PPO_MIN_STEPS = 16
"""The fewest steps per copy in a PPO rollout by default (the generalised advantage
estimate looks at most this far ahead before it bootstraps from the value)."""


def default_hyperparameters(algo: str, envs: int) -> dict[str, Any]:
    """The SB3 settings a run of ``algo`` over ``envs`` copies gets unless its
    ``hyperparameters`` give them: for PPO ``n_steps`` (steps per copy per rollout, a
    multiple of 8 in ``[PPO_MIN_STEPS, 2048]``, about ``PPO_ROLLOUT / envs``) and
    ``batch_size`` (a ``PPO_MINIBATCHES``-th of the rollout, which it divides). Other
    algorithms keep SB3's defaults."""
    if algo != "ppo":
        return {}
    n_steps = min(2048, max(PPO_MIN_STEPS, PPO_ROLLOUT // envs // 8 * 8))
    return {"n_steps": n_steps, "batch_size": n_steps * envs // PPO_MINIBATCHES}


def model_settings(config: TrainConfig) -> dict[str, Any]:
    """The keyword arguments the run's SB3 algorithm is built with: the
    :func:`default_hyperparameters` for its ``envs``, overridden by its ``hyperparameters``."""
    return {**default_hyperparameters(config.algo, config.envs), **dict(config.hyperparameters)}


def jax_ppo_parameters() -> set[str]:
    """The hyperparameters of the JAX learner (:class:`experiments.rl.ppo_jax.PPOSettings`;
    ``normalize`` is the configuration's own field)."""
    from experiments.rl.ppo_jax import PPOSettings

    return {f.name for f in dataclasses.fields(PPOSettings)} - {"normalize"}


def model_file(config: TrainConfig) -> str:
    """The final model's file name in a run's folder: ``model.zip`` (SB3) or ``model.npz`` (JAX)."""
    return "model.npz" if config.learner == "jax" else MODEL


def algorithm_parameters(algo: str) -> set[str]:
    """The keyword arguments an SB3 algorithm's constructor takes (besides policy and env)."""
    import stable_baselines3 as sb3

    params = inspect.signature(getattr(sb3, algo.upper()).__init__).parameters
    return {name for name in params if name not in ("self", "policy", "env")}


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


def config_json(config: TrainConfig) -> dict[str, Any]:
    """The configuration as ``train.json`` keeps it."""
    data = dataclasses.asdict(config)
    data["hyperparameters"] = dict(config.hyperparameters)
    data["reward"] = dict(config.reward)
    return json.loads(json.dumps(data))  # tuples as lists, as read back from disk


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


def make_vector_env(config: TrainConfig):
    """The ``config.envs`` copies of the training race as one
    :class:`experiments.rl.vec_env.RaceVecEnv`: copy ``k`` races the learner as car
    ``k % N`` from the scenario :meth:`TrainConfig.scenario` gives it, against the opponent
    specs (with ``pool``, every opponent car draws from all of them)."""
    from experiments.rl.vec_env import RaceVecEnv

    specs = list(config.opponents)
    opponents = [specs for _ in range(config.cars - 1)] if config.pool else specs
    races = [(k % config.cars, config.race_config(copy=k)) for k in range(config.envs)]
    return RaceVecEnv(races, opponents)


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


def drop_episodes_after(out: Path, timesteps: int) -> None:
    """Forget the episodes logged after ``timesteps``: their steps will be collected again."""
    if not (out / EPISODES).exists():
        return
    kept = [e for e in read_jsonl(out / EPISODES) if e["timesteps"] <= timesteps]
    replace_atomically(lambda tmp: tmp.write_text("".join(json.dumps(e) + "\n" for e in kept)), out / EPISODES)


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


def episode_fields(info: dict[str, Any]) -> dict[str, Any]:
    """An ``episodes.jsonl`` line's fields from the info of the step that ended the episode
    (with the ``episode`` record of :class:`experiments.rl.vec_env.RaceVecEnv` or SB3's
    ``Monitor``): return, length [steps], finished, place, out, finish time [s],
    truncated, and a pool's drawn ``opponents``."""
    episode = info["episode"]
    return {"return": float(episode["r"]), "length": int(episode["l"]), "finished": bool(episode["finished"]),
            "place": int(episode["position"]), "out": bool(episode["out"]), "finish_time": episode["finish_time"],
            "truncated": bool(info.get("TimeLimit.truncated", False)),
            **({"opponents": info["opponents"]} if "opponents" in info else {})}


def record_evaluation(config: TrainConfig, model_path: Path, timesteps: int, out: Path, console) -> None:
    """Race the saved policy under tournament rules (:func:`evaluate`), append the record to
    ``evaluations.jsonl`` and print its line."""
    record = evaluate(config, model_path, timesteps)
    append_jsonl(out / EVALUATIONS, record)
    console.print(evaluation_line(record))


def evaluate_final(config: TrainConfig, model_path: Path, timesteps: int, out: Path, console) -> None:
    """The final policy's evaluation, unless the last one logged is already of ``timesteps``."""
    evaluations = read_jsonl(out / EVALUATIONS)
    if not evaluations or evaluations[-1]["timesteps"] != timesteps:
        record_evaluation(config, model_path, timesteps, out, console)


def finish_report(config: TrainConfig, out: Path, report: dict[str, Any], model_path: Path, title: str,
                  console) -> None:
    """Close a run: its final evaluation into ``report``, ``train.json``, the learning curve
    (titled ``title``) and, for a completed run, how to race the model."""
    evaluations = read_jsonl(out / EVALUATIONS)
    report["final_evaluation"] = evaluations[-1] if evaluations else None
    write_json_atomically(report, out / CONFIG)
    plot_learning_curve(read_jsonl(out / EPISODES), evaluations, out / "learning_curve.png",
                        title=f"{title} {config.description()} on {Path(config.track).stem}",
                        time_trial=config.time_trial)
    if report["status"] == "completed":
        # a time-trial policy observes one car: it races alone, against others' laps
        race_it = ("--cars 1 --agents rl:{} ilqr lane-keeping" if config.time_trial
                   else "--agents rl:{} " + " ".join(dict.fromkeys(config.opponents))).format(model_path)
        console.print(f"wrote {model_path} (race it: racing tournament {race_it}), "
                      f"{out / 'learning_curve.png'}, {out / EVALUATIONS}")


def next_multiple(steps: int, every: int) -> int | None:
    """The first multiple of ``every`` after ``steps`` (None for ``every == 0``: never)."""
    return None if every == 0 else (steps // every + 1) * every


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


def check_resumable(config: TrainConfig, out: Path, has_checkpoint: bool) -> None:
    """Refuse to train into ``out`` when it holds a run (a checkpoint or episodes) made with
    settings other than ``config``'s (besides those a resumption may change)."""
    config_path = out / CONFIG
    if not config_path.exists():
        return
    wanted = config_json(config)
    previous = json.loads(config_path.read_text())["config"]
    differs = sorted(k for k in wanted
                     if k not in _RESUMABLE_CHANGES and previous.get(k, _ADDED_LATER.get(k)) != wanted[k])
    if differs and (has_checkpoint or (out / EPISODES).exists()):
        raise ValueError(f"{out} holds a training run with other settings ({', '.join(differs)}); "
                         "use another --out folder or --fresh to start over")


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
