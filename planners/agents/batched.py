"""Batched opponents: one object drives one car in B races of the same game at once.

A vectorised race env steps B races of one track, set of cars and game in one compiled
call; its opponents must act for all B races at once. A :class:`BatchedOpponent` does::

    opponent = make_batched_opponent("ilqgame-fb:replan_every=5", env.game, index=1, num_races=64)
    opponent.reset(races, seeds)                         # races (B,) bool, seeds (B,) int64
    actions, diagnostics = opponent.act(observations, x, racing)   # (B, 2) in [-1, 1]

Specs are the registry's (:func:`planners.agents.make_agent`), so every option means what it
means for a single agent, and a list of specs is a pool that draws each race's driver at its
reset. The kinds:

* :class:`BatchedScripted` (``raceline``, ``lane-keeping``, ``constant-speed``): the driver's law as a pure
  JAX function ``jax_policy(x (N, 6)) -> action (2,)`` (:func:`planners.scripted.jax_policy`),
  for the env to fuse into its compiled step; ``act`` runs it jitted and vmapped;
* :class:`planners.agents.batched_planners.BatchedPlanner` (``ilqgame-fb``, ``ilqgame-ol``,
  ``ilqr``): the receding-horizon loop of :class:`planners.agents.RecedingHorizonAgent` with
  one batched solve (:func:`planners.ilq_batch.solve_batch`) of the races due to re-plan;
* :class:`BatchedSB3` (``rl:PATH``, a stable-baselines3 ``.zip`` or a JAX learner's ``.npz``):
  the saved model predicts for all B observations at once;
* :class:`BatchedRandom` (``random``): each race's own generator, seeded from the race's seed
  as the single agent seeds its own, so it draws the single agent's actions (host side: it
  has no JAX law, and a compiled race refuses it);
* :class:`BatchedPool` (a list of specs): each race's driver drawn from its own seed;
* :class:`LoopedOpponent`: B single agents, one race at a time, for what cannot be batched.

The protocol (:class:`BatchedOpponent`, :data:`DIAGNOSTIC_FIELDS`, :func:`empty_diagnostics`)
lives in :mod:`planners.agents.batched_protocol`, below this module and
:mod:`planners.agents.batched_planners`; its names are importable from here too.

Actions are float64 and never NaN. The single agents round their actions to float32
(:meth:`planners.agents.BaseAgent._finish`); these are not rounded (cast them to float32 to
hand an env the very numbers a single agent would).
"""

from __future__ import annotations

import functools
import warnings
from typing import Any, Callable, Sequence

import jax
import numpy as np

from planners.agents.batched_protocol import DIAGNOSTIC_FIELDS, BatchedOpponent, empty_diagnostics
from planners.agents.protocol import BaseAgent
from planners.agents.registry import make_agent
from planners.agents.scripted import ConstantSpeedAgent, LaneKeepingAgent, RacelineAgent, RandomAgent, random_generator
from planners.methods import RL
from planners import scripted as scripted_laws

SCRIPTED_AGENTS = (RacelineAgent, LaneKeepingAgent, ConstantSpeedAgent)
"""The scripted agents, whose laws :class:`BatchedScripted` runs in JAX."""

__all__ = [
    "BatchedOpponent",
    "BatchedPool",
    "BatchedRandom",
    "BatchedSB3",
    "BatchedScripted",
    "DIAGNOSTIC_FIELDS",
    "LoopedOpponent",
    "SCRIPTED_AGENTS",
    "batched_from_agent",
    "batched_from_factory",
    "empty_diagnostics",
    "make_batched_opponent",
]

# --------------------------------------------------------------------------------------
# Scripted drivers.
# --------------------------------------------------------------------------------------


def _padded_size(count: int) -> int:
    """The next power of two >= ``count``: the few batch shapes a jitted law compiles for."""
    return 1 << max(0, int(count) - 1).bit_length()


class BatchedScripted(BatchedOpponent):
    """A scripted driver (:class:`planners.agents.LaneKeepingAgent`,
    :class:`planners.agents.ConstantSpeedAgent`) in B races.

    ``jax_policy(x (N, 6)) -> action (2,)`` is its law in JAX (:func:`planners.scripted.jax_policy`,
    float64, equal to the NumPy law to ~1e-14, :data:`planners.scripted.BRAKE_ACTION` where the
    car's own state is not finite); ``act`` evaluates it jitted and vmapped over the races
    (padded to a power of two, so a handful of batch shapes compile).
    """

    def __init__(self, agent: BaseAgent, game: Any, index: int, num_races: int, spec: str | None = None) -> None:
        if not isinstance(agent, SCRIPTED_AGENTS):
            raise TypeError(f"BatchedScripted needs a scripted agent, got {type(agent).__name__}")
        super().__init__(spec or agent.spec, game, index, num_races)
        agent.reset(None, self.index, self.game)  # builds the controller of this car
        self.controller = agent.controller
        self.jax_policy = scripted_laws.jax_policy(self.controller)
        # a law that reads the racing flags (the racing-line driver's rules) is handed them
        self._takes_racing = bool(getattr(self.jax_policy, "takes_racing", False))
        self._batched = jax.jit(jax.vmap(self.jax_policy))

    def _act_rows(self, rows, observations, x, racing):
        count = rows.size
        size = _padded_size(count)
        padded = np.zeros((size,) + x.shape[1:])
        padded[:count] = x
        if self._takes_racing:
            flags = np.ones((size, x.shape[1]), dtype=bool)
            flags[:count] = racing
            out = self._batched(padded, flags)
        else:
            out = self._batched(padded)
        actions = np.asarray(out)[:count].astype(np.float64)
        diagnostics = empty_diagnostics(self.diagnostic_fields, count)
        braked = ~np.all(np.isfinite(x[:, self.index]), axis=1)  # where the law returned BRAKE_ACTION
        diagnostics["fallback"] |= braked
        diagnostics["brake"] |= braked
        return self._finish(actions, x, diagnostics), diagnostics


class BatchedRandom(BatchedOpponent):
    """The random driver (:class:`planners.agents.RandomAgent`) in B races: one generator per
    race, made at the race's reset from its episode seed and the car's index
    (:func:`planners.agents.scripted.random_generator`), so each race draws the actions a
    single agent reset with that seed draws, one ``(2,)`` draw per step in which the car races.

    It runs on the host (``jax_policy`` is None): a JAX law would need a key in the race's
    state, so the compiled races (:class:`racing_env.vector.GymnaxRace`) refuse it, while
    :class:`racing_env.vector.RaceVectorEnv` drives it between its compiled steps.
    """

    def __init__(self, agent: RandomAgent, game: Any, index: int, num_races: int, spec: str | None = None) -> None:
        if not isinstance(agent, RandomAgent):
            raise TypeError(f"BatchedRandom needs a RandomAgent, got {type(agent).__name__}")
        super().__init__(spec or agent.spec, game, index, num_races)
        self.scale = agent.scale
        self.generators: list[np.random.Generator | None] = [None] * self.num_races

    def _reset_rows(self, rows, seeds):
        for row, seed in zip(rows, seeds):
            self.generators[row] = random_generator(int(seed), self.index)

    def _act_rows(self, rows, observations, x, racing):
        actions = np.array([self.generators[row].uniform(-self.scale, self.scale, size=2) for row in rows])
        diagnostics = empty_diagnostics(self.diagnostic_fields, rows.size)
        return self._finish(actions.reshape(rows.size, 2), x, diagnostics), diagnostics


# --------------------------------------------------------------------------------------
# Saved stable-baselines3 policies.
# --------------------------------------------------------------------------------------


class BatchedSB3(BatchedOpponent):
    """A saved stable-baselines3 model (:class:`planners.agents.SB3Agent`) in B races: one
    ``predict(observations (R, obs_dim), deterministic=True)`` call per step, observations
    normalised with the model's saved ``VecNormalize`` statistics as the single agent does;
    or a JAX learner's policy (:class:`planners.agents.jax_policy.JaxPolicyAgent`), one
    compiled call per step.
    A race whose action is not finite brakes; a failed prediction brakes in every race.
    Observations of another size than the model reads are refused (ValueError): the env
    races another number of cars or preview distances, which no race can drive with."""

    def __init__(self, agent: BaseAgent, game: Any, index: int, num_races: int, spec: str | None = None) -> None:
        from planners.agents.jax_policy import JaxPolicyAgent
        from planners.agents.sb3 import SB3Agent

        if not isinstance(agent, (SB3Agent, JaxPolicyAgent)):
            raise TypeError(f"BatchedSB3 needs an SB3Agent or a JaxPolicyAgent, got {type(agent).__name__}")
        super().__init__(spec or agent.name, game, index, num_races)
        agent.reset(None, self.index, game)  # the env, where given: its observations' units
        self.agent = agent

    def _act_rows(self, rows, observations, x, racing):
        if hasattr(self.agent, "predict_many"):  # a JAX learner's policy
            return self._act_jax(rows, observations, x)
        expected = tuple(self.agent.model.observation_space.shape)
        if observations.shape[1:] != expected:
            raise ValueError(f"{self.agent.path} reads observations of shape {expected}, got "
                             f"{observations.shape[1:]} per "
                             "race (trained with another number of cars or preview distances?)")
        diagnostics = empty_diagnostics(self.diagnostic_fields, rows.size)
        try:
            actions = self.agent.predict_raw(observations)
            actions = np.asarray(actions, dtype=np.float64).reshape(rows.size, 2)
        except Exception:  # noqa: BLE001 - any policy failure: brake, as the single agent does
            actions = np.full((rows.size, 2), np.nan)
        return self._finish(actions, x, diagnostics), diagnostics

    def _act_jax(self, rows, observations, x):
        expected = self.agent.model.observation_size
        if observations.shape[1:] != (expected,):
            raise ValueError(f"{self.agent.path} reads observations of shape ({expected},), got "
                             f"{observations.shape[1:]} per race (trained with another number of cars or preview "
                             "distances?)")
        diagnostics = empty_diagnostics(self.diagnostic_fields, rows.size)
        try:
            actions = self.agent.predict_many(observations).reshape(rows.size, 2)
        except Exception:  # noqa: BLE001 - any policy failure: brake, as the single agent does
            actions = np.full((rows.size, 2), np.nan)
        return self._finish(actions, x, diagnostics), diagnostics


# --------------------------------------------------------------------------------------
# Pools.
# --------------------------------------------------------------------------------------


class BatchedPool(BatchedOpponent):
    """Several drivers for one car: every race draws its driver at each reset.

    The draw is ``np.random.default_rng(seed).integers(len(specs))`` with the race's own
    episode seed: uniform over the entries of ``specs`` (a spec listed twice is drawn twice
    as often), deterministic per race and independent of B. Each member acts on its races
    only; entries with the same spec share one member. The diagnostics add ``"driver"``, the
    drawn entry per race.

    Args:
        specs: the agent specs (at least one).
        game, index, num_races: as :class:`BatchedOpponent`.
        members: ``{spec: BatchedOpponent}`` already made for these races (default: made by
            :func:`make_batched_opponent` with ``options``).
        options: keyword options for :func:`make_batched_opponent` (``batching``, ...).
    """

    def __init__(self, specs: Sequence[str], game: Any, index: int, num_races: int,
                 members: dict[str, BatchedOpponent] | None = None, **options: Any) -> None:
        specs = list(specs)
        if not specs or not all(isinstance(s, str) for s in specs):
            raise ValueError(f"a pool needs a non-empty list of agent specs, got {specs!r}")
        super().__init__("pool(" + "; ".join(specs) + ")", game, index, num_races)
        self.specs = specs
        members = dict(members or {})
        for spec in dict.fromkeys(specs):
            if spec not in members:
                members[spec] = make_batched_opponent(spec, self.game, self.index, self.num_races, **options)
        self.members = [members[spec] for spec in specs]  # one per entry (shared by equal specs)
        self._groups = {}  # id(member) -> (member, entries)
        for entry, member in enumerate(self.members):
            self._groups.setdefault(id(member), (member, []))[1].append(entry)
        fields = dict(DIAGNOSTIC_FIELDS)
        for member in self.members:
            fields.update(member.diagnostic_fields)
        self.diagnostic_fields = {**fields, "driver": np.int64}
        self.driver = np.zeros(self.num_races, dtype=np.int64)  # the drawn entry per race

    def _reset_rows(self, rows, seeds):
        if np.any(seeds < 0):
            raise ValueError(f"a pool draws from each race's seed, which must be >= 0; got {seeds[seeds < 0][:5]}")
        self.driver[rows] = [np.random.default_rng(int(seed)).integers(len(self.specs)) for seed in seeds]
        for member, entries in self._groups.values():
            mine = rows[np.isin(self.driver[rows], entries)]
            races = np.zeros(self.num_races, dtype=bool)
            races[mine] = True
            full_seeds = np.zeros(self.num_races, dtype=np.int64)
            full_seeds[rows] = seeds
            member.reset(races, full_seeds)

    def _act_rows(self, rows, observations, x, racing):
        actions = np.zeros((rows.size, 2))
        diagnostics = empty_diagnostics(self.diagnostic_fields, rows.size)
        diagnostics["driver"][:] = self.driver[rows]
        for member, entries in self._groups.values():
            mine = np.flatnonzero(np.isin(self.driver[rows], entries))
            if not mine.size:
                continue
            part, part_diagnostics = member._act_rows(rows[mine], observations[mine], x[mine], racing[mine])
            actions[mine] = part
            for name, values in part_diagnostics.items():
                diagnostics[name][mine] = values
        return actions, diagnostics


# --------------------------------------------------------------------------------------
# The looped fallback.
# --------------------------------------------------------------------------------------


class LoopedOpponent(BatchedOpponent):
    """B single agents (made by the registry from one spec), each driving one race, acting
    one race after another.

    Slow: a step costs B single-agent steps in a Python loop (for a planner B solves one
    after another, each with its own dispatch), and an agent with its own compiled parts
    (an iLQR prediction's physics rollout) compiles them once per race. It is the
    always-correct form, used for what the batched opponents cannot batch (an iLQR
    prediction other than constant velocity, agents outside the registry's kinds).
    Each agent is reset as this car with the race's seed and ``env_info``; it reads the
    racing flags from its observation, as in the PettingZoo env.

    Args:
        spec: an agent spec (:func:`planners.agents.make_agent`), or with ``factory`` the
            agents' name.
        game, index, num_races: as :class:`BatchedOpponent`.
        env_info: what the agents are reset with (default: the game); an env lets an
            ``rl:`` agent check its observation space.
        factory: a zero-argument callable that makes the agents (one call per race)
            instead of the registry from ``spec``.
    """

    def __init__(self, spec: str, game: Any, index: int, num_races: int, env_info: Any = None,
                 factory: Callable[[], Any] | None = None) -> None:
        super().__init__(spec, game, index, num_races)
        self.env_info = self.game if env_info is None else env_info
        make = factory if factory is not None else functools.partial(make_agent, spec)
        self.agents = [make() for _ in range(self.num_races)]

    def _reset_rows(self, rows, seeds):
        for row, seed in zip(rows, seeds):
            self.agents[row].reset(int(seed), self.index, self.env_info)

    def _act_rows(self, rows, observations, x, racing):
        actions = np.zeros((rows.size, 2))
        diagnostics = empty_diagnostics(self.diagnostic_fields, rows.size)
        for r, row in enumerate(rows):
            agent = self.agents[row]
            actions[r] = agent.act(observations[r], x[r])
            record = agent.diagnostics() if hasattr(agent, "diagnostics") else {}  # an agent outside planners
            diagnostics["replanned"][r] = bool(record.get("replanned"))
            diagnostics["converged"][r] = bool(record.get("converged"))
            diagnostics["iterations"][r] = int(record.get("iterations") or 0)
            diagnostics["fallback"][r] = bool(record.get("fallback"))
            diagnostics["brake"][r] = record.get("fallback_kind") == "brake"
        return self._finish(actions, x, diagnostics), diagnostics


# --------------------------------------------------------------------------------------
# The factory.
# --------------------------------------------------------------------------------------


def make_batched_opponent(spec: str | Sequence[str], game: Any, index: int, num_races: int, *,
                          batching: str = "auto", devices: Sequence[Any] | None = None,
                          solve_sizes: Sequence[int] | None = None) -> BatchedOpponent:
    """The batched opponent of an agent spec (or of a list of specs: a pool).

    Args:
        spec: an agent spec as :func:`planners.agents.make_agent` parses it
            (``"lane-keeping"``, ``"constant-speed:target_speed=12"``, ``"ilqr"``,
            ``"ilqgame-ol"``, ``"ilqgame-fb:replan_every=5,max_iterations=5"``,
            ``"rl:PATH"``), or a list of specs: a :class:`BatchedPool`, whose races each draw
            their driver, uniformly, at every reset from their own seed.
        game: the races' :class:`racing_env.RaceGame` (or an env that has it).
        index: the car it drives.
        num_races: B.
        batching, devices, solve_sizes: how planners solve their batches
            (:class:`planners.agents.batched_planners.BatchedPlanner`); other kinds ignore them.

    Returns:
        A :class:`BatchedScripted`, :class:`BatchedRandom`,
        :class:`~planners.agents.batched_planners.BatchedPlanner`, :class:`BatchedSB3` or
        :class:`BatchedPool`; a :class:`LoopedOpponent` (with a
        warning, it is slow) for a planner option that cannot be batched (an iLQR prediction
        other than constant velocity).

    Raises:
        ValueError: for a bad spec or option (the registry's message), or a bad index.
    """
    options = {"batching": batching, "devices": devices, "solve_sizes": solve_sizes}
    if isinstance(spec, (list, tuple)):
        return BatchedPool(spec, game, index, num_races, **options)
    if not isinstance(spec, str):
        raise ValueError(f"spec must be an agent spec (a string) or a list of them, got {spec!r}")
    return batched_from_agent(make_agent(spec), spec, game, index, num_races, **options)


def batched_from_agent(agent: BaseAgent, spec: str, game: Any, index: int, num_races: int, *,
                       batching: str = "auto", devices: Sequence[Any] | None = None,
                       solve_sizes: Sequence[int] | None = None,
                       factory: Callable[[], Any] | None = None) -> BatchedOpponent:
    """The batched form of a single ``agent`` made from ``spec`` (see :func:`make_batched_opponent`);
    ``factory``: what makes more such agents where they race one per race (the looped
    fallback), instead of the registry from ``spec``."""
    from planners.agents import batched_planners

    if isinstance(agent, SCRIPTED_AGENTS):
        return BatchedScripted(agent, game, index, num_races, spec=spec)
    if isinstance(agent, RandomAgent):
        return BatchedRandom(agent, game, index, num_races, spec=spec)
    if spec.strip().lower().startswith(f"{RL}:") or getattr(agent, "spec", None) == RL:
        return BatchedSB3(agent, game, index, num_races, spec=spec)
    reason = batched_planners.unbatchable(agent)
    if reason is None:
        return batched_planners.BatchedPlanner(agent, game, index, num_races, spec=spec, batching=batching,
                                               devices=devices, solve_sizes=solve_sizes)
    warnings.warn(f"{spec!r}: {reason}; it races as a LoopedOpponent, one single agent per race (slow)",
                  stacklevel=3)
    return LoopedOpponent(spec, game, index, num_races, factory=factory)


def batched_from_factory(factory: Callable[[], Any], game: Any, index: int, num_races: int,
                         **options: Any) -> BatchedOpponent:
    """The batched opponent of the agents a zero-argument ``factory`` makes (an agent class
    such as :class:`planners.agents.FeedbackGameAgent`, a ``functools.partial`` of one, a
    lambda): the kinds of :func:`batched_from_agent` from one agent it makes, or, for an
    agent they cannot batch, one agent per race (``factory`` called once per race, a
    :class:`LoopedOpponent`). ``options``: as :func:`make_batched_opponent`'s.

    Raises:
        TypeError: ``factory()`` made something that is not an agent (``reset`` and ``act``).
    """
    agent = factory()
    if not (callable(getattr(agent, "reset", None)) and callable(getattr(agent, "act", None))):
        raise TypeError(f"an opponent factory must make an agent (with reset(seed, index, env_info) and act); "
                        f"{factory!r} made {agent!r}")
    spec = str(getattr(agent, "spec", None) or type(agent).__name__)
    return batched_from_agent(agent, spec, game, index, num_races, factory=factory, **options)
