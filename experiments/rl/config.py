"""What a training run is: :class:`TrainConfig` (the learner, its opponents, its race and
its budget), the defaults it fills in (:func:`default_hyperparameters`), the file names of
a run's folder, and the configuration as ``train.json`` keeps it (:func:`config_json`).

Both learners read it: stable-baselines3 (:mod:`experiments.rl.train`) and PPO in JAX
(:mod:`experiments.rl.train_jax`), and so do the evaluations
(:mod:`experiments.rl.evaluation`). It imports none of them; its names are importable from
:mod:`experiments.rl.train` too.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
from pathlib import Path
from typing import Any

import numpy as np

from experiments.race_spec import RaceSpec
from planners.agents import SB3_ALGOS
from racing_env.config import RaceConfig, RewardConfig, check_incident_rules
from racing_env.opponents import LEARNER_OFF_TRACK
from racing_env.steward import DEFAULT_RULES

CONFIG = "train.json"
EPISODES = "episodes.jsonl"
EVALUATIONS = "evaluations.jsonl"
CHECKPOINTS = "checkpoints"
IMITATION_ALGOS = ("ppo", "a2c")  # actor-critics with a Gaussian policy, which behaviour cloning fits
# the fields of TrainConfig that may change between a run and its resumption
RESUMABLE_CHANGES = ("timesteps", "eval_every", "checkpoint_every", "subprocesses", "vector")
TRAINING_STARTS = ("grid", "anywhere", "mixed")  # where training episodes may start (TrainConfig.start)
# fields added to TrainConfig after runs were saved, with the value those runs had
ADDED_LATER = {"start": "grid", "imitate": None, "imitate_episodes": 20, "imitate_noise": 0.2,
               "imitate_spread": None, "vector": False, "learner": "sb3", "rules": list(DEFAULT_RULES),
               "observation_units": "physical",
               "car": "paper"}
LEARNERS = ("sb3", "jax")  # TrainConfig.learner
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
    on_off_track: str = LEARNER_OFF_TRACK
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
        for copy in range(min(self.envs, max(2, self.cars))):  # every start and learner car the copies use
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

    def opponent_cars(self) -> list[str]:
        """The class of each opponent car, in car order: an opponent spec's ``car=NAME``
        (:func:`planners.agents.split_car`), else the race's ``car``. A pool's drivers are
        drawn per episode into the same cars: its specs must agree on the class."""
        classes = self.car_classes(self.opponents)
        if not self.pool:
            return classes
        if len(set(classes)) > 1:
            raise ValueError(f"a pool draws every opponent car's driver per episode, so its specs must agree on the "
                             f"car's class: {list(self.opponents)} name {sorted(set(classes))}")
        return classes[:1] * (self.cars - 1)

    def car_classes_with_learner(self, learner: int) -> list[str]:
        """Every car's class with the learner (of the race's ``car``) in slot ``learner``
        and the opponents' cars in the other slots in order (:meth:`opponent_cars`)."""
        classes = self.opponent_cars()
        classes.insert(learner, self.car)
        return classes

    def race_config(self, training: bool = True, copy: int = 0, learner: int | None = None) -> RaceConfig:
        """The race the learner trains in (``training``; copy ``copy`` of it, where the
        learner drives car ``copy % cars``) or is evaluated in (tournament rules, with
        ``eval_off_track`` if set), the learner in slot ``learner`` (default ``copy % cars``):
        the learner's car of the race's ``car``, each opponent's of its spec's class."""
        cars = self.car_classes_with_learner(copy % self.cars if learner is None else learner)
        if training:
            return self.to_race_config(self.cars, self.scenario(copy), cars=cars,
                                       reward=RewardConfig(**dict(self.reward)))
        # the tournaments' rules: incidents penalised, not retiring, unless eval_off_track says otherwise
        return self.to_race_config(self.cars, "grid", cars=cars, on_collision=EVALUATION_RULE,
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


def jax_ppo_parameters() -> set[str]:
    """The hyperparameters of the JAX learner (:class:`experiments.rl.ppo_jax.PPOSettings`;
    ``normalize`` is the configuration's own field)."""
    from experiments.rl.ppo_jax import PPOSettings

    return {f.name for f in dataclasses.fields(PPOSettings)} - {"normalize"}


def algorithm_parameters(algo: str) -> set[str]:
    """The keyword arguments an SB3 algorithm's constructor takes (besides policy and env)."""
    import stable_baselines3 as sb3

    params = inspect.signature(getattr(sb3, algo.upper()).__init__).parameters
    return {name for name in params if name not in ("self", "policy", "env")}


def config_json(config: TrainConfig) -> dict[str, Any]:
    """The configuration as ``train.json`` keeps it."""
    data = dataclasses.asdict(config)
    data["hyperparameters"] = dict(config.hyperparameters)
    data["reward"] = dict(config.reward)
    return json.loads(json.dumps(data))  # tuples as lists, as read back from disk
