"""`racing sweep`: races over a grid of settings, on local worker processes or a Ray cluster.

A sweep is a TOML file: a ``lineup`` of agent specs (agent 0 is the one the sweep is
about; a lineup of one is a time trial, the agent alone), the race (``track``, ``laps``
or ``race_distance``, ``grids``, ``seed``, ``max_steps``, ``jerk_weight``, the incident
rules ``on_collision`` and ``on_off_track``)
and a ``[parameters]`` table whose values are lists; every combination of them (a point)
is raced on ``grids`` seeded rolling grids, once per rotation of the starting slots::

    lineup = ["ilqgame-fb", "ilqgame-ol"]
    grids = 2

    [parameters]
    "agent0.c_collision" = [1.0, 10.0, 100.0]   # cost weight of agent 0's car, wherever it starts
    jerk_weight = [0.01, 0.03]                 # every car's jerk weight r

A lineup entry ``"SPEC*K"`` is K cars of that spec (:func:`experiments.tournament.expand_lineup`),
one agent of the lineup: a lineup with a count (``lineup = ["ilqgame-fb", "lane-keeping*9"]``)
races a field, once per grid, its cars shuffled over the starting slots as a tournament's
fields are (:func:`experiments.tournament.shuffle_field`), instead of once per rotation; an
``agent<i>.`` parameter then sets every car of entry i, and the summary pools them.

Parameter names: the race's ``track``, ``laps``, ``race_distance``, ``max_steps``,
``jerk_weight``, ``on_collision``, ``on_off_track``, ``car`` (every car's class,
:mod:`racing_env.car_classes`); ``weights.<field>`` (a
:class:`racing_env.costs.CostWeights` field, for every car), ``vehicles.<field>`` (a
:class:`racing_env.vehicle.VehicleParams` number, for every car) and ``agent<i>.<field>`` (that field for agent ``i`` of the lineup: a cost
weight, ``car`` (its class) or a car parameter of its car, known to every planner in the race, or an option of
its agent spec such as ``max_iterations`` or ``trailing.c_collision``, see
:mod:`planners.agents.registry`).

The example sweeps ship with the package (``experiments/sweeps/*.toml``): ``racing sweep
aggression`` names one (:func:`sweep_path`, :func:`example_sweeps`); any other file is given
by its path.

Each race is one job (:func:`run_job`, a pure function of the sweep and the job, so any
process can run it). Backends: ``local`` (this process for one worker, else a pool of
worker processes) and ``ray`` (tasks on a Ray cluster: ``address`` of a running one, or a
local one started for the sweep). Records are appended to ``results.jsonl`` as races end,
in whatever order they end; rerunning the sweep skips the races already there, and the
summary is built in schedule order, so it does not depend on the backend, the number of
workers or interruptions.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import json
import sys
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from experiments.backends import check_backend
from experiments.budget import StepBudget, budget_line
from experiments.files import one_writer
from experiments.formatting import mean_or_none, or_dash, share_with_interval
from experiments.jsonl import read_jsonl, settings_json
from experiments.race_spec import RACE_FIELDS, RaceSpec
from experiments.runner import JobLog
from experiments.standings import wilson_interval, won_race
from experiments.tournament import expand_lineup, has_count, shuffle_field, split_count
from planners.agents import with_options
from racing_env.car_classes import CAR_CLASSES, car_names, get_car
from racing_env.config import RaceConfig, is_number
from racing_env.costs import racing_weights
from racing_env.costs import CostWeights
from racing_env.vehicle import SCALAR_FIELDS

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

RESULTS = "results.jsonl"
CONFIG = "sweep.json"
RACE_PARAMETERS = RACE_FIELDS  # the race's fields a point may set (RaceSpec's)
ADDED_LATER = ("on_collision", "on_off_track", "rules", "observation_units", "car", "track_scale")  # left out of sweep.json at their defaults
NUMBER_PARAMETERS = ("laps", "race_distance", "max_steps", "jerk_weight")
WEIGHT_FIELDS = tuple(f.name for f in dataclasses.fields(CostWeights))
VEHICLE_FIELDS = SCALAR_FIELDS  # the car's numbers (its limit table is the class's: ``car``, ``agent<i>.car``)
CAR_FIELDS = WEIGHT_FIELDS + VEHICLE_FIELDS + ("car",)  # what ``weights.``/``vehicles.`` and ``agent<i>.`` set on a car


@dataclasses.dataclass(frozen=True, kw_only=True)
class SweepConfig(StepBudget, RaceSpec):
    """A sweep: the lineup, the race (:class:`RaceSpec`), and the swept parameters with
    their values.

    Attributes:
        lineup: agent specs by agent index (:func:`planners.agents.make_agent`); agent 0 is
            the subject of the summary, which reports every agent. One spec: a time trial,
            the agent alone on the track, where a finished lap counts as a win. An entry
            ``"SPEC*K"`` is K cars of the spec, one agent: a lineup with a count races a
            field (:attr:`field`), at most :data:`racing_env.config.MAX_CARS` cars.
        parameters: ``(name, values)`` pairs; every combination is a point.
        track, laps, race_distance, max_steps, jerk_weight, on_collision, on_off_track: the
            race (as in tournaments) where a parameter does not set them.
        grids: seeded start grids per point, each raced once per rotation of the slots (a
            field: once, its cars shuffled over the slots, :meth:`field_slots`).
        seed: seeds the grids.
        step_budget_s: an action slower than this [s] is counted in its car's record
            (``over_budget_steps``) and printed; None (the default): no budget.
        enforce_budget: such an action loses the race (:mod:`experiments.budget`).
    """

    lineup: tuple[str, ...]
    parameters: tuple[tuple[str, tuple[Any, ...]], ...]
    grids: int = 2
    seed: int = 0

    def __post_init__(self) -> None:
        if isinstance(self.lineup, str) or not all(isinstance(entry, str) for entry in self.lineup):
            raise ValueError(f"a lineup is a list of agent specs (\"SPEC*K\": K cars), got {self.lineup!r}")
        if len(self.lineup) < 1:
            raise ValueError(f"a lineup needs at least 1 agent spec (1: a time trial), got {list(self.lineup)}")
        expand_lineup(self.lineup)  # counts and the field's size
        if not _is_int(self.grids) or self.grids < 1:
            raise ValueError(f"grids must be an integer >= 1, got {self.grids!r}")
        if not _is_int(self.seed) or self.seed < 0:
            raise ValueError(f"seed must be an integer >= 0, got {self.seed!r}")
        self.check_budget()
        if not self.parameters:
            raise ValueError("a sweep needs a [parameters] table with at least one parameter")
        for name, values in self.parameters:
            check_parameter_name(name, self.specs)
            if not isinstance(values, tuple) or not values:
                raise ValueError(f"parameter {name} needs a non-empty list of values, got {values!r}")
            if name.partition(".")[2] == "car":
                _check_cars(name, values)
            elif name in NUMBER_PARAMETERS or name.partition(".")[2] in CAR_FIELDS:
                _check_numbers(name, values)
        tracks = [self.track, *dict(self.parameters).get("track", ())]
        bad = [track for track in tracks if not isinstance(track, str)]  # a Path would not go into sweep.json
        if bad:
            raise ValueError(f"track values must be strings, built-in track names or TUMFTM CSV paths, got {bad[0]!r}")
        super().__post_init__()  # the race's fields
        from planners.agents import check_specs

        self.race_config({}, rotation=0)  # the top-level race settings, also those every point overrides
        for point in self.points():  # every value is checked where it is used, before any race
            self.race_config(point, rotation=0)
            # the specs a point's options change (the lineup's own, which may load models, run_sweep checks)
            check_specs(spec for spec, base in zip(self.lineup_specs(point), self.specs) if spec != base)

    @property
    def specs(self) -> tuple[str, ...]:
        """The agents' specs by agent index: the lineup's entries without their counts."""
        return tuple(split_count(entry)[0] for entry in self.lineup)

    @property
    def counts(self) -> tuple[int, ...]:
        """Each agent's number of cars (1 unless its entry says ``*K``)."""
        return tuple(split_count(entry)[1] for entry in self.lineup)

    @property
    def cars(self) -> int:
        """Cars per race."""
        return sum(self.counts)

    @property
    def field(self) -> bool:
        """Whether the lineup gives a count (``"SPEC*K"``): then every grid is raced once,
        by a field whose cars are shuffled over the slots (:meth:`field_slots`), not once per
        rotation."""
        return any(has_count(entry) for entry in self.lineup)

    def field_slots(self, grid: int) -> list[int]:
        """The agent index of each starting slot of grid ``grid``'s field: agent 0's cars,
        then agent 1's, ..., shuffled by :func:`experiments.tournament.shuffle_field` with
        the sweep's seed (every point races the same order on the same grid)."""
        return shuffle_field([agent for agent, count in enumerate(self.counts) for _ in range(count)], grid, self.seed)

    def slot_agents(self, job: dict[str, Any]) -> list[int]:
        """The agent index of each starting slot of a scheduled race: the field's order, or
        the lineup rotated by the job's ``rotation`` (slot k holds agent ``(k + rotation) % N``)."""
        if job.get("slots") is not None:
            return list(job["slots"])
        cars = len(self.lineup)
        return [(slot + job["rotation"]) % cars for slot in range(cars)]

    def lineup_specs(self, point: dict[str, Any]) -> list[str]:
        """The lineup's specs (by agent index) with the point's agent options added."""
        specs = []
        for agent, spec in enumerate(self.specs):
            options = {key.split(".", 1)[1]: value for key, value in point.items()
                       if key.startswith(f"agent{agent}.") and key.split(".", 1)[1] not in CAR_FIELDS}
            specs.append(with_options(spec, options))
        return specs

    def agent_cars(self, point: dict[str, Any]) -> list[str]:
        """Each agent's car class (by agent index) at ``point``: its ``agent<i>.car`` there,
        else its spec's ``car=NAME`` (:func:`planners.agents.split_car`), else the point's (or
        the sweep's) ``car``."""
        race = self.race_spec() if "car" not in point else dataclasses.replace(self.race_spec(), car=point["car"])
        return [point.get(f"agent{agent}.car", car) for agent, car in enumerate(race.car_classes(self.specs))]

    def points(self) -> list[dict[str, Any]]:
        """Every combination of the parameters' values, in order (the last varies fastest)."""
        names = [name for name, _ in self.parameters]
        return [dict(zip(names, combo)) for combo in itertools.product(*(v for _, v in self.parameters))]

    def schedule(self) -> list[dict[str, Any]]:
        """Every race of the sweep in a fixed order (:func:`schedule`)."""
        return schedule(self)

    def race_config(self, point: dict[str, Any], rotation: int = 0, slots: list[int] | None = None) -> RaceConfig:
        """The race of a point with the lineup rotated by ``rotation`` (slot k holds agent
        ``(k + rotation) % N``), or with agent ``slots[k]`` in slot k (a field,
        :meth:`slot_agents`); per-agent weights and car parameters follow their agent into
        its slots."""
        race = dataclasses.replace(self.race_spec(), **{k: v for k, v in point.items() if k in RACE_FIELDS})
        if slots is None:
            slots = self.slot_agents({"rotation": rotation}) if not self.field else self.field_slots(0)
        cars = len(slots)

        def fields(prefix: str, names: tuple[str, ...]) -> dict[str, Any]:
            return {k.split(".", 1)[1]: v for k, v in point.items()
                    if k.startswith(prefix) and k.split(".", 1)[1] in names}

        weights, vehicles = [], []
        classes = self.agent_cars(point)
        for slot in range(cars):
            agent = slots[slot]
            vehicle = get_car(classes[agent]).replace(
                **{**fields("vehicles.", VEHICLE_FIELDS), **fields(f"agent{agent}.", VEHICLE_FIELDS)})
            vehicles.append(vehicle)
            weights.append(racing_weights(race.jerk_weight, vehicle, race.track_scale).replace(
                **{**fields("weights.", WEIGHT_FIELDS), **fields(f"agent{agent}.", WEIGHT_FIELDS)}))
        any_car = set(classes) != {"paper"} or any(k.split(".", 1)[-1] in VEHICLE_FIELDS for k in point if "." in k)
        return race.to_race_config(cars, "grid", weights=weights,
                                   vehicles=vehicles if any_car else None)  # None: the scenario's cars


def _check_cars(name: str, values: tuple[Any, ...]) -> None:
    """Refuse a value of ``agent<i>.car`` that is not a car class's name."""
    for value in values:
        if not isinstance(value, str) or value not in CAR_CLASSES:
            raise ValueError(f"{name} must be a car class, one of {car_names()}, got {value!r}")


def _check_numbers(name: str, values: tuple[Any, ...]) -> None:
    """Refuse a value that is not a number (the race's own checks compare, and a string
    there is a TypeError or, in a weight, a crash at the first race)."""
    for value in values:
        if not is_number(value):
            raise ValueError(f"{name} must be a number, got {value!r}")


def _is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _spec_option_types(spec: str) -> dict[str, type]:
    """The options (other than the car's cost weights) a sweep may set on an agent spec."""
    from planners.agents import AGENTS, split_spec

    if spec.strip().lower().startswith("rl:"):
        return {}
    agent = AGENTS.get(split_spec(spec)[0])
    options = agent.spec_options() if agent is not None else {}
    return {key: kind for key, kind in options.items() if key not in CAR_FIELDS}


def check_parameter_name(name: str, lineup: tuple[str, ...]) -> None:
    """Refuse a parameter the sweep does not know, saying which it does (``lineup``: the
    agents' specs, without counts)."""
    cars = len(lineup)
    head, _, field = name.partition(".")
    index = head[5:]
    if head.startswith("agent") and index.isdigit() and head != f"agent{int(index)}":
        # only agent<i>. is applied to agent i: agent01. would be accepted and then never set
        raise ValueError(f"sweep parameter {name!r}: write the agent index without leading zeros, "
                         f"agent{int(index)}.{field}")
    known_agent = head.startswith("agent") and index.isdigit() and int(index) < cars
    if name in RACE_PARAMETERS or ((head == "weights" or known_agent) and field in WEIGHT_FIELDS):
        return
    if ((head == "vehicles" or known_agent) and field in VEHICLE_FIELDS) or (known_agent and field == "car"):
        return
    if known_agent and field in _spec_option_types(lineup[int(index)]):
        return
    raise ValueError(f"unknown sweep parameter {name!r}; use one of {list(RACE_PARAMETERS)}, "
                     f"weights.<weight>, vehicles.<car> or agent<i>.<weight|car|option> (i < {cars}) with <weight> "
                     f"one of {list(WEIGHT_FIELDS)}, <car> one of {list(VEHICLE_FIELDS + ('car',))} and <option> an option of "
                     f"agent i's spec (`racing agents` lists them)")


EXAMPLES = Path(__file__).resolve().parent / "sweeps"
"""The folder of the example sweeps shipped with the package (one TOML file each)."""


def example_sweeps() -> list[str]:
    """The names of the example sweeps (``racing sweep NAME``), sorted."""
    return sorted(path.stem for path in EXAMPLES.glob("*.toml"))


def sweep_path(name_or_path: str | Path) -> Path:
    """The TOML file of a sweep: ``name_or_path`` if it is a file, else the example sweep of
    that name (``"aggression"`` or ``"aggression.toml"``: :func:`example_sweeps`).

    Raises:
        ValueError: neither, naming the example sweeps.
    """
    path = Path(name_or_path)
    if path.is_file():
        return path
    example = EXAMPLES / (path.name if path.suffix == ".toml" else f"{path.name}.toml")
    if path.parent == Path(".") and example.is_file():
        return example
    raise ValueError(f"no sweep file {str(name_or_path)!r}: give the path of a TOML file or the name of an example "
                     f"sweep, one of {example_sweeps()}")


def load_sweep(path: Path) -> SweepConfig:
    """Read a sweep TOML file (see the module docstring)."""
    try:
        data = tomllib.loads(Path(path).read_text())
    except tomllib.TOMLDecodeError as err:
        raise ValueError(f"{path} is not valid TOML: {err}") from None
    return sweep_from_table(data, str(path))


def sweep_from_table(data: dict[str, Any], where: str) -> SweepConfig:
    """The sweep of a TOML table (a sweep file's, or a study's part); ``where`` names it in
    the errors.

    Raises:
        ValueError: an unknown key, no lineup, parameters that are not a table, or what
            :class:`SweepConfig` refuses.
    """
    allowed = {f.name for f in dataclasses.fields(SweepConfig)}
    unknown = sorted(set(data) - allowed)
    if unknown:
        raise ValueError(f"{where}: unknown keys {unknown}; a sweep has {sorted(allowed)}")
    lineup = data.get("lineup")
    if not isinstance(lineup, list) or not all(isinstance(spec, str) for spec in lineup):
        raise ValueError(f"{where}: a sweep needs a lineup, a list of agent specs, e.g. "
                         f"lineup = [\"ilqgame-fb\", \"lane-keeping\"]; got {lineup!r}")
    table = data.get("parameters", {})
    if not isinstance(table, dict):
        raise ValueError(f"{where}: parameters must be a table ([parameters]), got {table!r}")
    parameters = tuple((name, tuple(v) if isinstance(v, list) else v)
                       for name, v in flatten_parameters(where, table).items())
    return SweepConfig(**{**data, "lineup": tuple(data["lineup"]), "parameters": parameters})


def flatten_parameters(path: Path | str, table: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Parameters by dotted name: an unquoted dotted key (``agent0.c_gap = [...]``) is a
    nested table in TOML, the same parameter as the quoted ``"agent0.c_gap"``."""
    flat: dict[str, Any] = {}
    for key, value in table.items():
        name = f"{prefix}{key}"
        nested = flatten_parameters(path, value, f"{name}.") if isinstance(value, dict) else {name: value}
        for inner, values in nested.items():
            if inner in flat:
                raise ValueError(f"{path}: parameter {inner!r} is given twice (quoted and unquoted)")
            flat[inner] = values
    return flat


def schedule(config: SweepConfig) -> list[dict[str, Any]]:
    """Every race of the sweep in a fixed order: ``id``, point index and values, rotation (a
    field: ``slots``, the agent index of each starting slot), grid seed."""
    jobs = []
    for index, point in enumerate(config.points()):
        for grid in range(config.grids):
            if config.field:  # one race of the field per grid
                jobs.append({"id": f"p{index}/grid{grid}/field", "point_index": index, "point": point,
                             "slots": config.field_slots(grid), "grid": grid, "seed": config.seed * 10_000 + grid})
                continue
            for rotation in range(len(config.lineup)):
                jobs.append({"id": f"p{index}/grid{grid}/r{rotation}", "point_index": index, "point": point,
                             "rotation": rotation, "grid": grid, "seed": config.seed * 10_000 + grid})
    return jobs


def run_job(config: SweepConfig, job: dict[str, Any], plans: bool = False) -> dict[str, Any]:
    """Race one job and return its record: the job, and per agent (by lineup index) its
    car's result in that race (start place, place, finish time, distance, speed, incidents,
    passes made and suffered, errors), and the race's replay (with the planners' plans
    when ``plans``). In a field, ``agents`` lists the cars by starting slot instead, each
    with its agent index (``entry``)."""
    from experiments.tournament import race_lineup

    order = config.slot_agents(job)  # the agent index in each slot
    specs = config.lineup_specs(job["point"])
    classes = config.agent_cars(job["point"])
    record, _ = race_lineup(config.race_config(job["point"], slots=order), [specs[a] for a in order],
                            job["seed"], step_budget_s=config.step_budget_s, enforce_budget=config.enforce_budget,
                            plans=plans, cars=[classes[a] for a in order])
    if config.field:
        by_agent = [{**car, "slot": slot, "entry": agent} for slot, (car, agent) in enumerate(zip(record["cars"], order))]
    else:
        by_agent = [None] * len(order)
        for slot, agent in enumerate(order):
            by_agent[agent] = {**record["cars"][slot], "slot": slot}
    return {**job, "steps": record["steps"], "overtakes": record["overtakes"], "gap": record["gap"],
            "agents": by_agent, "replay": record["replay"]}


def summarize(config: SweepConfig, records: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per point and agent: races, wins (and of those started in front, how many were
    won; alone, a finished lap wins), races finished, races retired by an incident rule,
    mean place, mean finish-time margin over the other cars (races all finished; None
    alone), mean and best finish time of its finished races, overtakes per race, contact steps,
    time off track, errors, and for planners the mean share of re-plans that converged
    (results where it is low are the solver's, not the weights': see
    docs/experiments/sweep-aggression.md); and the place-based figures a field needs: passes
    made and suffered (``overtakes``, ``overtaken``; None where a record predates them) and
    the share of the other agents' cars its cars beat (``beaten`` of ``faced``, with a 95%
    Wilson interval over those pairs). In a field an agent's cars are pooled: ``races``,
    wins, places and margins count cars (an agent of three cars on two grids: 6)."""
    cars = config.cars
    position = {job["id"]: k for k, job in enumerate(schedule(config))}
    by_point: dict[int, list[dict[str, Any]]] = {}
    for record in sorted(records, key=lambda r: position[r["id"]]):  # sums in one order, however they came
        by_point.setdefault(record["point_index"], []).append(record)
    rows = []
    for index, point in enumerate(config.points()):
        races = by_point.get(index, [])
        for agent, spec in enumerate(config.lineup):
            mine = [car for r in races for car in agent_cars(r, agent)]
            times_of_mine = [car["finish_time"] for car in mine if car["finish_time"] is not None]
            margins = []
            beaten = faced = 0
            for race in races:
                times = [car["finish_time"] for car in race["agents"]]
                for k, car in enumerate(race["agents"]):
                    if car.get("entry", k) != agent:
                        continue
                    if cars > 1 and all(t is not None for t in times):
                        others = [t for j, t in enumerate(times) if j != k]
                        margins.append(float(np.mean(others)) - times[k])
                    rivals = [other for j, other in enumerate(race["agents"]) if other.get("entry", j) != agent]
                    faced += len(rivals)
                    beaten += sum(other["place"] > car["place"] for other in rivals)
            beaten_lo, beaten_hi = wilson_interval(beaten, faced)
            passes = [car.get("overtakes") for car in mine]
            lost = [car.get("overtaken") for car in mine]
            rows.append({
                "point": index, **point, "agent": agent, "spec": spec, "races": len(mine),
                "wins": sum(won_race(car, cars) for car in mine),
                "races_from_front": sum(car["start_place"] == 1 for car in mine),
                "wins_from_front": sum(car["start_place"] == 1 and won_race(car, cars) for car in mine),
                "finished": sum(car["finish_time"] is not None for car in mine),
                "retired": sum(bool(car.get("retired", False)) for car in mine),  # none in older records
                "mean_place": float(np.mean([car["place"] for car in mine])) if mine else None,
                "mean_margin_s": float(np.mean(margins)) if margins else None,
                "mean_finish_time_s": float(np.mean(times_of_mine)) if times_of_mine else None,
                "best_finish_time_s": min(times_of_mine) if times_of_mine else None,
                "overtakes_per_race": float(np.mean([r["overtakes"] for r in races])) if races else None,
                "overtakes": None if None in passes else sum(passes),
                "overtaken": None if None in lost else sum(lost),
                "beaten": beaten, "faced": faced, "beaten_share": beaten / faced if faced else None,
                "beaten_ci95_low": beaten_lo, "beaten_ci95_high": beaten_hi,
                "contact_steps": sum(car["collision_steps"] for car in mine),
                "time_off_track_s": float(sum(car["time_off_track"] for car in mine)),
                "errors": sum(car["error"] is not None for car in mine),
                "converged_fraction": mean_or_none(car.get("solver_converged_fraction") for car in mine),
            })
    return rows


def agent_cars(record: dict[str, Any], agent: int) -> list[dict[str, Any]]:
    """The cars of agent ``agent`` (its lineup index) in a sweep's race record: its one car,
    or in a field (cars by slot, each with its ``entry``) all of its cars."""
    return [car for k, car in enumerate(record["agents"]) if car.get("entry", k) == agent]


def read_results(out: Path) -> list[dict[str, Any]]:
    """The race records in ``out/results.jsonl``; a line cut by an interruption is skipped."""
    return read_jsonl(out / RESULTS)


def run_sweep(config: SweepConfig, out: Path, backend: str = "local", workers: int = 1,
              address: str | None = None, fresh: bool = False, progress: bool = True, plans: bool = False,
              report: bool = True) -> dict[str, Any]:
    """Run (or resume) a sweep into ``out``; returns ``{"rows": summary, "interrupted": bool}``
    and writes ``results.jsonl``, ``summary.csv``, ``summary.json``, ``sweep.png``, every
    race's replay in ``replays/`` (with the planners' plans when ``plans``) and, with
    ``report``, ``report.html``."""
    from rich.console import Console

    from planners.agents import check_specs
    from racing_env.env import RacingParallelEnv

    check_backend(backend, workers)
    check_specs(config.specs)
    # every point's race as the env builds it, so that one it refuses fails before the first
    # race: a track that is not built in and not a readable file, a finish line beyond an
    # open track's end
    for point in config.points():
        RacingParallelEnv(config.race_config(point, rotation=0))
    console = Console(stderr=True, width=160)
    with one_writer(out, "sweep"):
        log = JobLog(out, schedule(config), log=RESULTS, settings_file=CONFIG,
                     settings=settings_json(config, config.added_later(ADDED_LATER)), what="sweep", fresh=fresh)
        log.announce(console)
        interrupted = log.run(functools.partial(run_job, config, plans=plans), backend, workers, address, progress=progress,
                              desc="sweep")
        records = log.records()
        rows = summarize(config, records)
        _write_summary(config, rows, out, console)
        budget = budget_line([car for record in records for car in record["agents"]], config)
        if budget is not None:
            console.print(budget)
        if report:
            from experiments.report import write_sweep_report

            console.print(f"wrote {write_sweep_report(out, config, rows, records)}")
    if interrupted:
        console.print(f"interrupted: {len(log.done)} of {len(log.jobs)} races in {out / RESULTS}; run the same "
                      "command to resume")
    return {"rows": rows, "interrupted": interrupted}


def _write_summary(config: SweepConfig, rows: list[dict[str, Any]], out: Path, console) -> None:
    import csv

    from rich.table import Table

    (out / "summary.json").write_text(json.dumps(rows, indent=2))
    with open(out / "summary.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    names = [name for name, _ in config.parameters]
    time_trial = config.cars == 1
    places = config.cars > 2  # in a field, places say more than wins

    columns = [  # (header, cell of a row, shown in a time trial)
        ("agent", lambda row: f"{row['agent']}: {row['spec']}", True),
        ("races", lambda row: str(row["races"]), True),
        ("wins", lambda row: str(row["wins"]), False),
        ("from the front", lambda row: f"{row['wins_from_front']}/{row['races_from_front']}", False),
        ("finished", lambda row: f"{row['finished']}/{row['races']}", True),
        ("retired", lambda row: str(row["retired"]), True),
        ("mean place", lambda row: or_dash(row["mean_place"], "{:.2f}"), False),
        *((("rivals beaten [95% CI]", lambda row: share_with_interval(
               row["beaten_share"], (row["beaten_ci95_low"], row["beaten_ci95_high"])), False),
           ("passes made/suffered", lambda row: f"{or_dash(row['overtakes'], '{:d}')}/{or_dash(row['overtaken'], '{:d}')}",
            False)) if places else ()),
        ("margin [s]", lambda row: or_dash(row["mean_margin_s"], "{:+.2f}"), False),
        ("finish time [s]", lambda row: or_dash(row["mean_finish_time_s"], "{:.2f}"), True),
        ("best [s]", lambda row: or_dash(row["best_finish_time_s"], "{:.2f}"), True),
        ("overtakes/race", lambda row: or_dash(row["overtakes_per_race"], "{:.2f}"), False),
        ("contact steps", lambda row: str(row["contact_steps"]), False),
        ("off track [s]", lambda row: f"{row['time_off_track_s']:.1f}", True),
        ("errors", lambda row: str(row["errors"]), True),
        ("converged", lambda row: or_dash(row["converged_fraction"], "{:.0%}"), True),
    ]
    columns = [(header, cell) for header, cell, alone in columns if alone or not time_trial]
    table = Table(title=f"sweep: {' vs '.join(config.lineup)}{' (time trial)' if time_trial else ''}")
    for column in (*names, *(header for header, _ in columns)):
        table.add_column(column, overflow="fold")  # long specs and parameter names wrap instead of being cut
    for row in rows:
        table.add_row(*(str(row[n]) for n in names), *(cell(row) for _, cell in columns))
    console.print(table)
    plot_sweep(config, rows, out / "sweep.png")
    console.print(f"wrote {out / RESULTS}, {out / 'summary.csv'}, {out / 'summary.json'}, {out / 'sweep.png'}")


def plot_sweep(config: SweepConfig, rows: list[dict[str, Any]], path: Path) -> None:
    """Agent 0's results against the first parameter, one line per combination of the
    others: its win rate (with more than two cars, the share of the other agents' cars it
    beat), mean margin and contact steps per race; in a time trial, the share of laps
    finished, the mean finish time and the time off the track per lap."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    names = [name for name, _ in config.parameters]
    first, rest = names[0], names[1:]
    subject = [row for row in rows if row["agent"] == 0]
    time_trial = config.cars == 1
    places = config.cars > 2
    key = "mean_finish_time_s" if time_trial else "mean_margin_s"

    def per_race(row: dict[str, Any], value: float) -> float:
        return value / row["races"] if row["races"] else np.nan

    panels = [  # (y label, value of a row)
        (f"laps finished by {config.lineup[0]}" if time_trial else f"rivals beaten by {config.lineup[0]}" if places
         else f"win rate of {config.lineup[0]}",
         lambda row: (np.nan if row["beaten_share"] is None else row["beaten_share"]) if places
         else per_race(row, row["wins"])),
        ("mean finish time [s]" if time_trial else "mean finish margin [s]",
         lambda row: np.nan if row[key] is None else row[key]),
        ("time off track per lap [s]" if time_trial else "contact steps per race",
         lambda row: per_race(row, row["time_off_track_s"] if time_trial else row["contact_steps"])),
    ]
    fig, axes = plt.subplots(3, 1, figsize=(7, 8), sharex=True)
    labels = {}
    for row in subject:
        labels.setdefault(tuple(row[n] for n in rest), []).append(row)
    categorical = not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in dict(config.parameters)[first])
    for line_key, line in labels.items():
        xs = list(range(len(line))) if categorical else [row[first] for row in line]
        label = ", ".join(f"{n}={v}" for n, v in zip(rest, line_key)) or None
        for axis, (_, value) in zip(axes, panels):
            axis.plot(xs, [value(row) for row in line], "o-", label=label)
    for axis, (ylabel, _) in zip(axes, panels):
        axis.set_ylabel(ylabel)
    top, middle, bottom = axes
    values = dict(config.parameters)[first]
    if categorical:
        bottom.set_xticks(range(len(values)), [str(v) for v in values])
    elif min(values) > 0 and max(values) >= 100 * min(values):  # values spread over decades
        bottom.set_xscale("log")
    top.set_ylim(-0.05, 1.05)
    if not time_trial:
        middle.axhline(0.0, color="black", lw=0.8)
    bottom.set_xlabel(first)
    if rest:
        top.legend(fontsize=8)
    top.set_title(f"{config.lineup[0]} alone (time trial)" if time_trial
                  else f"{config.lineup[0]} vs {', '.join(config.lineup[1:])}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
