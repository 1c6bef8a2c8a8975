"""`racing tournament`: round robin of agents over start grids, with ratings and resume.

Every combination of ``cars`` distinct agent specs races on ``grids`` seeded start grids,
once per rotation of the starting slots (positions swapped for 2 cars). Each finished race
is appended to ``results.jsonl`` at once, so an interrupted tournament resumes where it
stopped; the leaderboard is recomputed from that file in schedule order, which makes it
identical for the same configuration whether or not the run was interrupted.

With ``cars = 1`` it is a time trial: each agent laps alone on every grid, and the
leaderboard ranks them by mean finish time. With more cars than agents it races fields
(:func:`field_lineup`): one race per grid whose cars are the agents, each a fair share of
the field, in an order shuffled per grid; an explicit ``lineup`` (``"SPEC*K"``: K cars of a
spec, :func:`expand_lineup`) races that field on every grid, shuffled the same way. The
leaderboard then rates the agents by their cars' places (:func:`experiments.standings.standings`).

An agent that raises loses that race: it is placed last, the error is recorded, and the
tournament goes on. Races do not depend on the machine's speed: a step budget
(``step_budget_s``) is reported, each car's actions over it counted, and decides races only
when enforced (``enforce_budget``: an action over it loses the race; :mod:`experiments.budget`).
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import itertools
import json
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from experiments.backends import check_backend
from experiments.budget import StepBudget, budget_line, over_budget
from experiments.files import one_writer
from experiments.formatting import or_dash, share_with_interval
from experiments.jsonl import read_jsonl, settings_json
from experiments.race_spec import RaceSpec
from experiments.runner import JobLog
# wilson_interval and won_race live in experiments.standings; imported from here they still work
from experiments.standings import standings, wilson_interval, won_race  # noqa: F401
from racing_env.blocking import count_blocks
from racing_env.config import MAX_CARS, RETIRING_MODES, RaceConfig
from racing_env.env import RacingParallelEnv
from racing_env.render import RACING
from racing_env.scenarios import FIXED_STARTS, SCENARIOS

RESULTS = "results.jsonl"
CONFIG = "tournament.json"
GIF = "race.gif"
ADDED_LATER = ("on_collision", "on_off_track", "rules", "scenario", "lineup", "observation_units", "car",
               "track_scale")  # left out of tournament.json at their defaults
# (enforce_budget too, without a budget: StepBudget.added_later)


@dataclasses.dataclass(frozen=True, kw_only=True)
class TournamentConfig(StepBudget, RaceSpec):
    """What a tournament races: the agents, and the race (:class:`RaceSpec`: ``track``,
    ``laps`` or ``race_distance`` [m], ``max_steps``, ``jerk_weight``, ``on_collision``,
    ``on_off_track``) on ``grids`` seeded starts of ``cars`` cars.

    ``versus`` (one of ``agents``) races every other agent against that one only (a gauntlet)
    instead of the full round robin.

    ``cars`` above the number of agents (up to :data:`racing_env.config.MAX_CARS`) races a
    field on every grid (:func:`field_lineup`): every agent drives ``cars // len(agents)`` or
    one more of the cars. ``cars`` left out (None) is 2, or the size of ``lineup``.

    ``lineup``: an explicit field instead, the specs of its cars (a spec repeated, or
    ``"SPEC*K"`` for K cars of it: :func:`expand_lineup`), raced once per grid with its cars
    shuffled over the slots (:func:`shuffle_field`). ``agents`` may then be left empty (the
    lineup's distinct specs, in order of first appearance) or name exactly those; ``cars``
    must be the lineup's size; ``versus`` and the fixed two-car starts do not apply. The
    lineup is kept expanded, each spec as ``agents`` writes it.

    ``car``: every car's class, but an agent whose spec names its own (``"ilqgame-fb:car=av21"``,
    ``"rl:car=f1tenth:PATH"``: :func:`planners.agents.split_car`) drives a car of that class
    in every race; its planners plan with their own car's limits and know the rivals' (the
    game's cars are the race's). Each car's record says its ``car_class``.

    ``jerk_weight`` is the planners' jerk weight r (R = r I) in the race's game; the default
    is :data:`racing_env.costs.RACING_JERK_WEIGHT`, the env's own racing default.

    ``scenario``: the start (:data:`racing_env.scenarios.SCENARIOS`). ``"grid"``: a seeded
    rolling grid per grid seed. ``"paper"``: the paper's overtaking scene, one start: the
    car in the first slot (v_max 20 m/s) 10 m ahead on the centre line, the second (v_max
    25 m/s) behind and 2 m to the left, so every pair races once with each agent defending
    and once attacking. ``"side_by_side"``: two cars abreast. The fixed starts take 2 cars
    and one grid.

    ``on_collision`` / ``on_off_track``: what contact and leaving the track do
    (:data:`racing_env.config.INCIDENT_MODES`). By default only the env's reward counts them,
    which no race result uses; ``terminate`` (or ``both``) retires the car, which then places
    behind every finisher by distance covered.

    ``step_budget_s`` / ``enforce_budget``: a wall-clock budget of an agent's action [s],
    reported (each car's ``over_budget_steps``) unless enforced (:mod:`experiments.budget`);
    default: none.
    """

    agents: tuple[str, ...] = ()
    grids: int = 2
    cars: int | None = None
    seed: int = 0
    versus: str | None = None
    scenario: str = "grid"
    lineup: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        super().__post_init__()  # the race's fields
        if self.lineup is not None:
            self._set_lineup()
        elif self.cars is None:
            object.__setattr__(self, "cars", 2)
        if self.scenario not in SCENARIOS:
            raise ValueError(f"unknown scenario {self.scenario!r}; choose one of {sorted(SCENARIOS)}")
        if self.scenario in FIXED_STARTS and (self.cars != 2 or self.grids != 1):
            raise ValueError(f"scenario {self.scenario!r} has one start of 2 cars: race it with cars=2 and grids=1 "
                             f"(--cars 2 --grids 1), got cars={self.cars}, grids={self.grids}")
        if len(self.agents) < (1 if self.cars == 1 else 2):
            raise ValueError(f"a tournament needs at least 2 agent specs (1 for a time trial, cars=1), "
                             f"got {list(self.agents)}")
        if len({normal_spec(spec) for spec in self.agents}) != len(self.agents):
            raise ValueError(f"agent specs must be distinct (names ignore case, options their order), "
                             f"got {list(self.agents)}")
        if isinstance(self.cars, bool) or not isinstance(self.cars, (int, np.integer)) or not 1 <= self.cars <= MAX_CARS:
            raise ValueError(f"cars per race must be an integer in [1, {MAX_CARS}] (1: a time trial; more than the "
                             f"{len(self.agents)} agents: a field of them), got {self.cars!r}")
        if self.cars > len(self.agents) and self.versus is not None:
            raise ValueError(f"a field of {self.cars} cars from {len(self.agents)} agents races them all together: "
                             "versus (a gauntlet) needs cars <= the number of agents")
        if self.cars == 1 and self.versus is not None:
            raise ValueError("a time trial (cars=1) races every agent alone: versus has no one to race")
        if self.grids < 1:
            raise ValueError(f"grids must be >= 1, got {self.grids}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise ValueError(f"seed (--seed) must be an integer >= 0, got {self.seed!r}")
        if self.versus is not None and self.versus not in self.agents:
            # the same agent written another way (name case, option order) is that agent
            same = [spec for spec in self.agents if normal_spec(spec) == normal_spec(self.versus)]
            if not same:
                raise ValueError(f"versus must be one of the agents {list(self.agents)}, got {self.versus!r}")
            object.__setattr__(self, "versus", same[0])
        self.car_classes(self.agents)  # an agent's car=NAME names a class
        self.check_budget()

    def _set_lineup(self) -> None:
        """Check ``lineup`` and set the fields it decides: the lineup expanded, each spec as
        ``agents`` writes it, ``agents`` (its distinct specs when left empty) and ``cars``."""
        if isinstance(self.lineup, str) or not all(isinstance(entry, str) for entry in self.lineup):
            raise ValueError(f"lineup must be a sequence of agent specs (\"SPEC*K\": K cars), got {self.lineup!r}")
        lineup = expand_lineup(self.lineup)
        firsts: dict[Any, str] = {}  # the first spelling of every agent in the lineup
        for spec in lineup:
            firsts.setdefault(normal_spec(spec), spec)
        agents = tuple(self.agents) or tuple(firsts.values())
        spelled = {normal_spec(spec): spec for spec in agents}
        if set(spelled) != set(firsts) or len(spelled) != len(agents):
            raise ValueError(f"agents must be the lineup's distinct specs (or left out), got agents {list(agents)} "
                             f"for the lineup's {list(firsts.values())}")
        if self.cars is not None and self.cars != len(lineup):
            raise ValueError(f"the lineup has {len(lineup)} cars, but cars (--cars) is {self.cars}: leave cars out "
                             f"or make it the lineup's size")
        if self.versus is not None:
            raise ValueError("a lineup races its whole field on every grid: versus (a gauntlet) does not apply")
        if self.scenario in FIXED_STARTS:
            raise ValueError(f"a lineup races one field per grid, from a seeded start: scenario {self.scenario!r} "
                             f"has one fixed start for each order of two cars; use {sorted(set(SCENARIOS) - set(FIXED_STARTS))}")
        object.__setattr__(self, "lineup", tuple(spelled[normal_spec(spec)] for spec in lineup))
        object.__setattr__(self, "agents", agents)
        object.__setattr__(self, "cars", len(lineup))

    @property
    def field(self) -> bool:
        """Whether the races are fields (one per grid: an explicit ``lineup``, or more cars
        than agents) rather than a round robin of distinct agents."""
        return self.lineup is not None or self.cars > len(self.agents)

    def schedule(self) -> list[dict[str, Any]]:
        """All races in a fixed order (:func:`schedule`)."""
        return schedule(self)


def normal_spec(spec: str) -> tuple[str, frozenset[tuple[str, str]]]:
    """What makes two agent specs the same agent: the name (any case) and the options in any
    order; the path of an ``rl:`` spec is kept as written."""
    from planners.agents import split_spec

    head, sep, rest = spec.strip().partition(":")
    if head.strip().lower() == "rl":
        return f"rl:{rest.strip()}", frozenset()
    name, options = split_spec(spec)
    return name, frozenset(options.items())


def field_lineup(agents: Sequence[str], cars: int, grid: int, seed: int) -> list[str]:
    """The specs by starting slot of grid ``grid``'s field of ``cars`` cars from ``agents``.

    Every agent gets ``cars // len(agents)`` cars; the ``cars % len(agents)`` left over go to
    the agents ``grid, grid + 1, ...`` (cyclically), so over the grids every agent gets as
    many extra cars as any other, within one. The cars are then shuffled over the slots
    (:func:`shuffle_field`): no agent always starts in front. Deterministic in
    ``(agents, cars, grid, seed)``."""
    count = len(agents)
    extra = {(grid + r) % count for r in range(cars % count)}
    field = [spec for k, spec in enumerate(agents) for _ in range(cars // count + (k in extra))]
    return shuffle_field(field, grid, seed)


def shuffle_field(field: Sequence[Any], grid: int, seed: int) -> list[Any]:
    """``field`` (one entry per car) in the order of grid ``grid``'s starting slots: permuted
    by ``numpy.random.default_rng([seed, grid]).permutation(len(field))`` (slot k takes entry
    ``permutation[k]``). A slot is a car's index in the race; the seeded grid start then places
    the car indices on the grid's rows by a permutation of its own (the grid seed's), so every
    car's place on the grid is drawn anew for every grid, and ``start_place`` in the records
    says where each started. Deterministic in ``(field, grid, seed)``."""
    order = np.random.default_rng([seed, grid]).permutation(len(field))
    return [field[k] for k in order]


def expand_lineup(entries: Sequence[str]) -> list[str]:
    """The cars of a lineup written with counts: ``"SPEC*K"`` is K cars of ``SPEC`` (K an
    integer >= 1; a spec's own options stay before the count, ``"ilqgame-fb:rivals=3*4"``),
    any other entry one car. ``["ilqgame-fb*2", "lane-keeping"]`` is
    ``["ilqgame-fb", "ilqgame-fb", "lane-keeping"]``. Refuses an empty lineup, a bad count
    and more than :data:`racing_env.config.MAX_CARS` cars."""
    cars: list[str] = []
    for entry in entries:
        spec, count = split_count(entry)
        cars.extend([spec] * count)
    if not cars:
        raise ValueError("a lineup needs at least one car, e.g. \"ilqgame-fb*4,ilqr*3,lane-keeping*3\"")
    if len(cars) > MAX_CARS:
        raise ValueError(f"a lineup of {len(cars)} cars; a race has at most {MAX_CARS} (racing_env.config.MAX_CARS)")
    return cars


def split_count(entry: str) -> tuple[str, int]:
    """``(spec, count)`` of a lineup entry ``"SPEC*K"`` or ``"SPEC"`` (count 1). Only a whole
    number after the last ``*`` is a count: an entry like ``"rl:runs/a*b/model.zip"`` is one
    car of that spec."""
    text = entry.strip()
    spec, star, count = text.rpartition("*")
    if not star or not count.strip().isdigit():
        spec, count = text, "1"
    if not spec.strip() or int(count) < 1:
        raise ValueError(f"lineup entry {entry!r}: write SPEC or SPEC*K with K an integer >= 1 cars of it, "
                         f"e.g. \"lane-keeping*3\"")
    return spec.strip(), int(count)


def has_count(entry: str) -> bool:
    """Whether a lineup entry gives a count (``"SPEC*K"``, :func:`split_count`)."""
    return split_count(entry)[0] != entry.strip()


def schedule(config: TournamentConfig) -> list[dict[str, Any]]:
    """All races in a fixed order: ``id``, the specs by starting slot, the grid seed."""
    races = []
    if config.field:  # a field per grid
        for grid in range(config.grids):
            lineup = (shuffle_field(config.lineup, grid, config.seed) if config.lineup is not None
                      else field_lineup(config.agents, config.cars, grid, config.seed))
            seed = config.seed * 10_000 + grid
            races.append({"id": f"field{config.cars}@grid{grid}", "lineup": lineup, "seed": seed, "grid": grid})
        return races
    for group in itertools.combinations(config.agents, config.cars):
        if config.versus is not None and config.versus not in group:
            continue
        for grid in range(config.grids):
            for shift in range(config.cars):
                lineup = group[shift:] + group[:shift]
                seed = config.seed * 10_000 + grid
                races.append({"id": f"{'|'.join(lineup)}@grid{grid}", "lineup": list(lineup), "seed": seed, "grid": grid})
    return races


def count_overtakes(s: np.ndarray, racing: np.ndarray | None = None) -> int:
    """Position swaps between any two cars along ``s (T, N)`` (sign changes of the gaps),
    while both race (:func:`overtakes_by_car`)."""
    return int(overtakes_by_car(s, racing)[0].sum())


def pass_events(s: np.ndarray, racing: np.ndarray | None = None) -> list[tuple[int, int, int]]:
    """Every pass along ``s (T, N)`` (race distance [m]) as ``(step, passer, passed)``: the
    step at which the gap between two cars changed sign (a step level with a car not counted
    as a change). With ``racing (T, N)`` bool (each car still in the race at each step) only
    the steps from which both cars were still racing count: a car that finished or retired is
    frozen, and the cars that reach its spot later do not pass it."""
    T, N = s.shape
    racing = np.ones((T, N), dtype=bool) if racing is None else np.asarray(racing, dtype=bool)
    events = []
    for i, j in itertools.combinations(range(N), 2):
        both = racing[:, i] & racing[:, j]
        counted = np.flatnonzero(np.concatenate([[True], both[:-1]]))  # step t counts if both raced at t - 1
        sign = np.sign(s[counted, i] - s[counted, j])
        steps, sign = counted[sign != 0], sign[sign != 0]
        for k in np.flatnonzero(sign[1:] != sign[:-1]) + 1:  # the sign after each change: +1 i passed j
            events.append((int(steps[k]), i, j) if sign[k] > 0 else (int(steps[k]), j, i))
    return sorted(events)


def overtakes_by_car(s: np.ndarray, racing: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Each car's passes along ``s (T, N)`` (:func:`pass_events`): ``made (N,)``, the times it
    went from behind another car to ahead of it, and ``lost (N,)``, the times another car did
    so to it."""
    made = np.zeros(s.shape[1], dtype=int)
    lost = np.zeros(s.shape[1], dtype=int)
    for _, passer, passed in pass_events(s, racing):
        made[passer] += 1
        lost[passed] += 1
    return made, lost


def _failed_setup(message: str):
    """A policy standing in for an agent that could not be built or reset."""

    def policy(observation, joint_state):
        raise RuntimeError(message)

    return policy


def race_config(config: TournamentConfig, lineup: Sequence[str] | None = None) -> RaceConfig:
    """The race a tournament's lineups run: its start (a seeded rolling grid by default) on
    its track, its length, step cap and incident rules, and the planners' jerk weight in
    the game; with ``lineup`` (the specs by starting slot) each car of the class its spec
    names (``car=NAME``), the others of the tournament's ``car``."""
    cars = None if lineup is None else config.car_classes(lineup)
    return config.to_race_config(config.cars, config.scenario, cars=cars)


def race_lineup(race: RaceConfig, lineup: list[str], seed: int, step_budget_s: float | None = None,
                render_every: int = 0, plans: bool = False, replay: bool = True,
                enforce_budget: bool = False, cars: Sequence[str] | None = None) -> tuple[dict[str, Any], list[np.ndarray]]:
    """Race agent specs (one per starting slot) on grid ``seed``; returns ``(record, frames)``.

    The record holds the finishing ``order`` (specs), the ``gap`` to the second car (None
    for a lone car, a time trial), the ``overtakes`` and, per car, its place on the grid
    (``start_place``, 1 = in front), place, finish time (the crossing plus the steward's time
    penalties; ``crossing_time`` and ``penalty`` apart), incidents it answered for
    (``faults``), distance, mean speed, contact
    steps, time off track and its steps (``off_track_steps``), its passes made and suffered (``overtakes``, ``overtaken``),
    its defending moves, blocks and the blocks made against it (``defending_moves``, ``blocks``,
    ``blocked``: :mod:`racing_env.blocking`), whether an incident rule ``retired`` it, action times, solver
    failures, its re-plans' iterations (mean, median, 95th percentile), the shares of its re-plans that converged and (a game agent with ``certify``
    on; else None) that were certified local Nash equilibria (``certified_share``), its
    actions slower than ``step_budget_s`` (``over_budget_steps``; None without a budget),
    the ``error`` of a car that faulted; and the race's ``incidents``
    (:attr:`experiments.race.RaceRecord.incidents`).
    Faults are recorded, never raised: a car that raises, or with ``enforce_budget`` acts
    slower than ``step_budget_s``, is last.
    With ``replay`` the record's ``"replay"`` is the race's :class:`experiments.replay.Replay`
    (with the planners' plans when ``plans``), which :class:`experiments.runner.JobLog`
    writes beside the records; frames (every ``render_every``-th step) are labelled with the
    specs and show the plans when ``plans``.
    ``cars``: the class of each car (:meth:`experiments.race_spec.RaceSpec.car_classes`, the
    classes ``race`` was built with), recorded as each car's ``car_class`` (None without).
    """
    from experiments.race import run_race
    from planners.agents import make_agent
    from racing_env.limits import race_limit

    if len(lineup) != race.num_agents or (cars is not None and len(cars) != race.num_agents):
        raise ValueError(f"a lineup of {len(lineup)} specs ({'no' if cars is None else len(cars)} car classes) "
                         f"for a race of {race.num_agents} cars")
    env = RacingParallelEnv(race)
    agents, policies = [], []
    for i, spec in enumerate(lineup):
        try:
            agent = make_agent(spec)
            agent.reset(seed, i, env)
            policies.append(agent)
        except Exception as err:  # noqa: BLE001 - a broken agent loses, the tournament goes on
            agent = None
            policies.append(_failed_setup(f"setup: {type(err).__name__}: {err}"))
        agents.append(agent)
    budget = StepBudget(step_budget_s=step_budget_s, enforce_budget=enforce_budget)
    budget.check_budget()
    result = run_race(env, policies, seed=seed, render_every=render_every, step_budget_s=budget.enforced_budget_s,
                      catch_errors=True, plans=plans, labels=lineup)
    xs, faults = result.xs, result.faults
    final_s = xs[-1, :, 0]
    finish = [car["race_time"] for car in result.summary]  # finish time plus the steward's penalties

    def key(i):  # finishers by race time, then the rest by distance, faulted cars last
        return (i in faults, finish[i] is None, finish[i] if finish[i] is not None else -final_s[i])

    order = sorted(range(len(lineup)), key=key)
    places = {i: p + 1 for p, i in enumerate(order)}
    grid = sorted(range(len(lineup)), key=lambda i: -xs[0, i, 0])  # s is cumulative: behind the line < 0
    start_places = {i: p + 1 for p, i in enumerate(grid)}
    winner, second = order[0], order[1] if len(order) > 1 else None
    if second is None:  # a lone car (a time trial) has no gap
        gap = None
    elif finish[winner] is not None and finish[second] is not None:
        gap = {"seconds": finish[second] - finish[winner]}
    else:
        gap = {"metres": float(final_s[winner] - final_s[second])}
    racing = np.asarray(result.status) == RACING  # (T+1, N): who was still in the race at each step
    made, lost = overtakes_by_car(xs[:, :, 0], racing)
    steward = env.params.steward
    defence = count_blocks(xs, racing, dt=race.dt, defend_gap=float(steward.defend_gap),
                           across_speed=float(steward.across_speed))
    classes, cars = cars, []
    for i, (spec, car) in enumerate(zip(lineup, result.summary)):
        agent = agents[i]
        limit = race_limit(env.track, env.game.vehicles.car(i), race.laps, race.race_distance)
        summary = agent.summary() if agent is not None and hasattr(agent, "summary") else {}
        times = result.act_times[i]
        cars.append({
            "agent": spec, "car": car["agent"], "car_class": None if classes is None else classes[i],
            "start_place": start_places[i], "place": places[i],
            # the race time: the crossing plus the steward's time penalties (``penalty``)
            "finish_time": finish[i], "crossing_time": car["finish_time"], "penalty": car["penalty"],
            "faults": car["faults"],
            # the crossing time (penalties left out: the pace) over the race's lap-time limit
            # (racing_env.limits.race_limit), and its line
            "limit_ratio": car["finish_time"] / limit[0] if limit is not None and finish[i] is not None else None,
            "limit_time": limit[0] if limit is not None else None, "limit_line": limit[1] if limit is not None else None,
            "distance": car["distance"], "mean_speed": car["mean_speed"],
            "collision_steps": car["collision_steps"], "time_off_track": car["time_off_track"],
            "off_track_steps": car["off_track_steps"], "overtakes": int(made[i]), "overtaken": int(lost[i]),
            "defending_moves": int(defence.defending_moves[i]), "blocks": int(defence.blocks[i]),
            "blocked": int(defence.blocked[i]),
            "retired": car["retired"],
            "act_time_mean_s": float(np.mean(times)) if times else float("nan"),
            "act_time_max_s": float(np.max(times)) if times else float("nan"),
            "over_budget_steps": over_budget(times, step_budget_s),
            "solver_failures": int(summary.get("fallbacks", 0)),
            "solver_converged_fraction": summary.get("converged_fraction"),
            "solver_iterations_mean": summary.get("iterations_mean"),
            "solver_iterations_median": summary.get("iterations_median"),
            "solver_iterations_p95": summary.get("iterations_p95"),
            "certified_share": summary.get("certified_share"),
            "actions_clipped_fraction": summary.get("clipped_fraction"), "error": faults.get(i),
        })
    record = {"steps": result.steps, "order": [lineup[i] for i in order], "gap": gap,
              "overtakes": int(made.sum()), "cars": cars, "incidents": result.incidents}
    if replay:
        from experiments.replay import replay_of

        record["replay"] = replay_of(result, env)
    env.close()
    return record, result.frames


def run_one_race(config: TournamentConfig, race: dict[str, Any], render_every: int = 0, plans: bool = False):
    """Race one scheduled lineup; returns ``(record, frames)`` (the record with its replay,
    with the planners' plans when ``plans``). Faults are recorded, never raised."""
    record, frames = race_lineup(race_config(config, race["lineup"]), race["lineup"], race["seed"],
                                 step_budget_s=config.step_budget_s, enforce_budget=config.enforce_budget,
                                 render_every=render_every, plans=plans, cars=config.car_classes(race["lineup"]))
    return {"id": race["id"], "grid": race["grid"], "seed": race["seed"], **record}, frames


def leaderboard(config: TournamentConfig, records: list[dict[str, Any]]) -> dict[str, Any]:
    """Win rates with intervals, head-to-head matrix and Plackett-Luce ratings (openskill),
    finish times, and for planners the mean shares of converged and of certified re-plans
    (None without any): :func:`experiments.standings.standings` of the agents over the
    records taken in schedule order. A time trial (``cars = 1``) is ranked by races
    finished, then mean finish time; its ratings stay at the prior and its head-to-head
    matrix is empty."""
    position = {r["id"]: k for k, r in enumerate(schedule(config))}
    records = sorted(records, key=lambda r: position[r["id"]])
    return standings(config.agents, records, time_trial=config.cars == 1)


def plot_head_to_head(table: dict[str, Any], path: Path, pairs: bool = False) -> None:
    """Heat map: row agent finished ahead of column agent in this many races (``pairs``: a
    field's count, pairs of cars, each car of the one with each car of the other in a race)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    names, wins = table["agents"], np.array(table["wins"])
    fig, ax = plt.subplots(figsize=(1.4 * len(names) + 2, 1.2 * len(names) + 1.5))
    image = ax.imshow(wins, cmap="Blues")
    for (i, j), value in np.ndenumerate(wins):
        if i != j:
            ax.text(j, i, str(value), ha="center", va="center", color="black")
    ax.set_xticks(range(len(names)), names, rotation=30, ha="right")
    ax.set_yticks(range(len(names)), names)
    ax.set_xlabel("... finished behind")
    ax.set_ylabel("row agent finished ahead of ...")
    fig.colorbar(image, ax=ax, shrink=0.8)
    ax.set_title("head to head (pairs of cars in a race)" if pairs else "head to head (races)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _certified_cells(board: dict[str, Any]) -> tuple[tuple[str, ...], list[tuple[str, ...]]]:
    """The ``certified`` column of the tables, ``(header, cells by row)``: empty when no
    agent certified its re-plans."""
    if all(row.get("certified_share") is None for row in board["rows"]):
        return (), [() for _ in board["rows"]]
    return ("certified",), [(or_dash(row.get("certified_share"), "{:.0%}"),) for row in board["rows"]]


def _time_trial_table(board: dict[str, Any], records: list[dict[str, Any]], config: TournamentConfig, retire: bool):
    """The leaderboard of a time trial as a rich table: finish times, not wins."""
    from rich.table import Table

    table = Table(title=f"time trial: {len(records)} laps alone on {config.track}")
    certified_header, certified = _certified_cells(board)
    for col in ("#", "agent", "finished", "mean finish time [s]", "best [s]", "x limit", "off track [s]",
                *(("retired",) if retire else ()), "errors", "act [ms]", "converged", *certified_header):
        table.add_column(col, overflow="fold")
    for k, row in enumerate(board["rows"], 1):
        table.add_row(str(k), row["agent"], f"{row['finished']}/{row['races']}", or_dash(row["mean_finish_time_s"], "{:.2f}"),
                      or_dash(row["best_finish_time_s"], "{:.2f}"), or_dash(row.get("mean_limit_ratio"), "{:.3f}"),
                      f"{row['time_off_track_s']:.1f}",
                      *((str(row["retired"]),) if retire else ()), str(row["errors"]),
                      f"{1e3 * row['mean_act_time_s']:.1f}",
                      or_dash(row["converged_fraction"], "{:.0%}"), *certified[k - 1])
    return table


def load_results(out: Path) -> list[dict[str, Any]]:
    """The race records in ``out/results.jsonl`` (a line cut by an interruption is skipped:
    that race is run again)."""
    return read_jsonl(out / RESULTS)


def _race_record(config: TournamentConfig, plans: bool, race: dict[str, Any]) -> dict[str, Any]:
    """The record of one scheduled race (a job for :func:`experiments.backends.run_jobs`)."""
    return run_one_race(config, race, plans=plans)[0]


def _drawn_race(config: TournamentConfig, out: Path, race: dict[str, Any]) -> dict[str, Any]:
    """The record of one scheduled race, drawn into ``out/race.gif`` (every third step) with
    its planners' plans."""
    from racing_env.render import save_gif

    record, frames = run_one_race(config, race, render_every=3, plans=True)
    save_gif(frames, out / GIF, fps=10.0 / 3)
    return record


def run_tournament(config: TournamentConfig, out: Path, gif: bool = True, progress: bool = True,
                   fresh: bool = False, backend: str = "local", workers: int = 1,
                   address: str | None = None, plans: bool = False, report: bool = True) -> dict[str, Any]:
    """Run (or resume) a tournament into ``out``; returns the leaderboard.

    Every race's replay goes to ``out/replays`` (:mod:`experiments.replay`), with the
    planners' plans when ``plans``; ``report`` writes ``out/report.html``
    (:mod:`experiments.report`) with the leaderboard and replays of selected races.

    The races run in this process, or with ``workers > 1`` or ``backend="ray"`` on worker
    processes or a Ray cluster (:func:`experiments.backends.run_jobs`; the race drawn as a
    GIF runs here first). Records are appended as races end; the leaderboard is built in
    schedule order, so it does not depend on where or in which order the races ran."""
    from rich.console import Console
    from rich.table import Table

    from planners.agents import check_specs

    console = Console(width=140)
    check_backend(backend, workers)
    check_specs(config.agents)
    # the race itself, so that one the env refuses (a finish line no start is behind, a
    # track file it cannot read) fails before anything is written
    RacingParallelEnv(race_config(config, schedule(config)[0]["lineup"]))
    with one_writer(out, "tournament"):
        log = JobLog(out, schedule(config), log=RESULTS, settings_file=CONFIG,
                     settings=settings_json(config, config.added_later(ADDED_LATER)),
                     what="tournament configuration", fresh=fresh, outputs=(GIF,))
        log.announce(console)
        # with no race recorded a GIF here is not this run's (e.g. results.jsonl deleted by hand): draw it
        # again; a resumed run keeps the GIF of its first race
        draw = gif and (not log.done or not (out / GIF).exists())
        if log.run(functools.partial(_race_record, config, plans), backend, workers, address, progress=progress,
                   desc="tournament", here_first=functools.partial(_drawn_race, config, out) if draw else None):
            raise KeyboardInterrupt  # the races run so far are kept in results.jsonl; no leaderboard
        records = log.records()
        board = leaderboard(config, records)
        intervals = ("win_rate_ci95", "beaten_share_ci95")  # two columns each in the CSV
        with open(out / "summary.csv", "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=[k for k in board["rows"][0] if k not in intervals]
                                    + ["ci95_low", "ci95_high", "beaten_ci95_low", "beaten_ci95_high"])
            writer.writeheader()
            for row in board["rows"]:
                flat = {k: v for k, v in row.items() if k not in intervals}
                writer.writerow({**flat, "ci95_low": row["win_rate_ci95"][0], "ci95_high": row["win_rate_ci95"][1],
                                 "beaten_ci95_low": row["beaten_share_ci95"][0],
                                 "beaten_ci95_high": row["beaten_share_ci95"][1]})
        if config.cars > 1:
            plot_head_to_head(board["head_to_head"], out / "head_to_head.png", pairs=config.field)
        (out / "leaderboard.json").write_text(json.dumps(board, indent=2))
        written = [out / RESULTS, out / "summary.csv"] + ([out / "head_to_head.png"] if config.cars > 1 else [])
        written += [out / GIF] if (out / GIF).exists() else []
        if report:
            from experiments.report import write_tournament_report

            written.append(write_tournament_report(out, config, board, records))
    retire = config.on_collision in RETIRING_MODES or config.on_off_track in RETIRING_MODES
    budget = budget_line([car for record in records for car in record["cars"]], config)
    if config.cars == 1:
        console.print(_time_trial_table(board, records, config, retire))
        if budget is not None:
            console.print(budget)
        console.print(f"wrote {', '.join(map(str, written))}")
        return board
    table = Table(title=f"leaderboard: {len(records)} races on {config.track}")
    certified_header, certified = _certified_cells(board)
    limits = any(row.get("mean_limit_ratio") is not None for row in board["rows"])  # circuits with a lap-time limit
    places = config.cars > 2  # in a field, places say more than wins
    for col in ("#", "agent", "rating (mu - 3 sigma)", "wins/races", "win rate [95% CI]",
                *(("mean place", "rivals beaten [95% CI]", "passes made/suffered") if places else ()), "finished",
                *(("retired",) if retire else ()), "margin [s]", *(("x limit",) if limits else ()), "errors", "contacts (at fault)", "off track", "act [ms]",
                "converged", *certified_header):
        table.add_column(col, overflow="fold")  # long specs (rl:PATH, options) wrap instead of being cut
    for k, row in enumerate(board["rows"], 1):
        table.add_row(str(k), row["agent"], f"{row['rating']:.2f}", f"{row['wins']}/{row['races']}",
                      share_with_interval(row["win_rate"], row["win_rate_ci95"]),
                      *((or_dash(row["mean_place"], "{:.2f}"),
                         share_with_interval(row.get("beaten_share"), row.get("beaten_share_ci95")),
                         f"{row['overtakes']}/{row['overtaken']}") if places else ()),
                      f"{row['finished']}/{row['races']}",
                      *((str(row["retired"]),) if retire else ()),
                      or_dash(row["mean_margin_s"], "{:+.2f}"),
                      *((or_dash(row.get("mean_limit_ratio"), "{:.3f}"),) if limits else ()),
                      str(row["errors"]),
                      f"{row['collision_steps']} ({row['faults']})", or_dash(row.get("off_track_steps"), "{:d}"),
                      f"{1e3 * row['mean_act_time_s']:.1f}",
                      or_dash(row["converged_fraction"], "{:.0%}"), *certified[k - 1])
    console.print(table)
    if budget is not None:
        console.print(budget)
    console.print(f"wrote {', '.join(map(str, written))}")
    return board
