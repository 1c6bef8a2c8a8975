"""`racing bench --only field`: races of fields of game planners, and the vectorised env with a field.

:func:`field_rows`: a race of N feedback iLQGame planners on the trefoil's grid, every car
re-planning every step in its real-time setting (``iterations=2,trust_radius=10``:
docs/experiments/cheap-replans.md) and playing
its local game with its ``rivals=2`` nearest rivals (:mod:`planners.rival_game`), the
field's re-plans solved as one batch per step (:func:`planners.agents.field.solve_field`),
as ``racing tournament`` races them. Race-steps per second for each N, the first step
(which compiles) reported apart, and the exponent of the cost of a step in N fitted over
the fields (:func:`cost_exponent`). The 10- and 20-car fields race again with every other
car predicted in each local game (``obstacles`` at least the field: the local game grows with
N), and in float32 with the default obstacles, and rows compare the settings: the 20-car step
over the 10-car step in each (target at most :data:`TARGET_20_OVER_10`), and the 10-car rate of
the default, and of the default in float32, over that with every car predicted in float64.

:func:`vector_field_rows`: the vectorised env with fields of coasting cars (random learner
actions) beside two cars, at the same batch, each with contact physics and with ghost cars
(no collision, no penalties): what colliding the cars, pair by pair, costs.
"""

from __future__ import annotations

import time
from typing import Any, Iterator

import numpy as np

FIELD_SPEC = "ilqgame-fb:iterations=2,trust_radius=10"
FIELDS = (2, 4, 10, 20)
TARGET_STEPS_PER_S = 50.0  # a 10-car field of game planners, every car re-planning every step
TARGET_EXPONENT = 1.2  # the cost of a step in N: linear, at most this exponent
EVERY_CAR_PREDICTED = ",obstacles=19"  # added to a spec: each local game predicts every other car of up to 20
TARGET_20_OVER_10 = 2.1  # a 20-car step over a 10-car step with the default obstacles (linear: 2.0)
TARGET_SPEEDUP_10 = 1.5  # the 10-car rate with the default obstacles over that with every car predicted
FLOAT32 = ",precision=float32"  # added to a spec: the planners solve in float32


def cost_exponent(cars: list[int], seconds_per_step: list[float]) -> float:
    """The exponent ``p`` of the least-squares fit ``seconds = a N^p`` (in logs)."""
    if len(cars) < 2:
        raise ValueError("the exponent needs at least two fields")
    return float(np.polyfit(np.log(cars), np.log(seconds_per_step), 1)[0])


class _FieldRace:
    """A field's race stepped one timed step at a time (so that several can run in turns):
    ``cars`` agents ``spec`` on ``track``'s seeded grid; a step is the whole loop (the field's
    batched re-plans, every car's action, the env step)."""

    def __init__(self, cars: int, spec: str, steps: int, track: str, seed: int) -> None:
        from planners.agents import make_agent
        from racing_env import RaceConfig
        from racing_env.env import RacingParallelEnv

        self.cars, self.spec, self.track = cars, spec, track
        self.env = RacingParallelEnv(RaceConfig(track=track, num_agents=cars, max_steps=steps + 1))
        self.observations, _ = self.env.reset(seed=seed)
        self.agents = [make_agent(spec) for _ in range(cars)]
        for i, agent in enumerate(self.agents):
            agent.reset(seed, i, self.env)
        self.index = {name: i for i, name in enumerate(self.env.possible_agents)}
        self.times: list[float] = []
        self.fallbacks, self.iterations = 0, []

    def step(self) -> None:
        from planners.agents.field import solve_field

        env = self.env
        if not env.agents:
            return
        start = time.perf_counter()
        state = env.state()
        racing = [self.agents[self.index[a]] for a in env.agents]
        solve_field(racing, [self.observations[a] for a in env.agents], state)
        actions = {a: self.agents[self.index[a]].act(self.observations[a], state) for a in env.agents}
        self.observations, *_ = env.step(actions)
        self.times.append(time.perf_counter() - start)
        for agent in racing:
            record = agent.diagnostics()
            self.fallbacks += bool(record["fallback"])
            if record["iterations"] is not None:
                self.iterations.append(record["iterations"])

    def row(self, warmup: int, name: str | None = None) -> dict[str, Any]:
        timed = np.array(self.times[warmup:])
        return {"name": name or f"field_{self.cars}_cars", "cars": self.cars, "spec": self.spec, "track": self.track,
                "steps_per_s": float(len(timed) / timed.sum()), "ms_per_step": 1e3 * float(np.median(timed)),
                "ms_per_step_p95": 1e3 * float(np.percentile(timed, 95)), "compile_s": float(self.times[0]),
                "steps_timed": int(len(timed)), "fallbacks": self.fallbacks,
                "iterations_median": float(np.median(self.iterations)) if self.iterations else None,
                "target_steps_per_s": TARGET_STEPS_PER_S if self.cars == 10 else None}


def field_race_rates(races: dict[str, tuple[int, str]], steps: int = 40, warmup: int = 3, track: str = "trefoil",
                     seed: int = 0) -> dict[str, dict[str, Any]]:
    """Races ``{name: (cars, spec)}`` (see :class:`_FieldRace`) timed in turns, a step of each
    in every round, so that a change in the machine's load falls on them alike: ``warmup``
    steps (the first compiles), then ``steps`` timed ones; a row per race."""
    fields = {name: _FieldRace(cars, spec, warmup + steps, track, seed) for name, (cars, spec) in races.items()}
    for _ in range(warmup + steps):
        for race in fields.values():
            race.step()
    return {name: race.row(warmup, name) for name, race in fields.items()}


def field_race_rate(cars: int, spec: str = FIELD_SPEC, steps: int = 40, warmup: int = 3,
                    track: str = "trefoil", seed: int = 0) -> dict[str, Any]:
    """One field's race (:func:`field_race_rates` of one race)."""
    name = f"field_{cars}_cars"
    return field_race_rates({name: (cars, spec)}, steps, warmup, track, seed)[name]


def field_rows(fields: tuple[int, ...] = FIELDS, steps: int = 40) -> Iterator[dict[str, Any]]:
    """A row per field (:func:`field_race_rate`), then the fitted exponent of a step's cost in
    N over every field and over the fields of local games (more than ``rivals + 1 = 3`` cars,
    whose re-plans are all games of three players); then the 10- and 20-car fields with the
    default obstacles and with every other car predicted, the four timed in turns, and their
    ratios."""
    rows = []
    for cars in fields:
        row = field_race_rate(cars, steps=steps)
        rows.append(row)
        yield row
    if len(rows) >= 2:
        cars = [row["cars"] for row in rows]
        seconds = [1.0 / row["steps_per_s"] for row in rows]
        local = [(n, s) for n, s in zip(cars, seconds) if n > 3]
        exponent = {"name": "field_cost_exponent", "exponent": cost_exponent(cars, seconds),
                    "cars": cars, "target_exponent": TARGET_EXPONENT}
        if len(local) >= 2:
            exponent["exponent_local_games"] = cost_exponent(*map(list, zip(*local)))
        yield exponent
    if 10 in fields and 20 in fields:
        runs = {f"field_{cars}_cars{suffix}_in_turns": (cars, FIELD_SPEC + extra)
                for cars in (10, 20) for suffix, extra in (("", ""), ("_every_car_predicted", EVERY_CAR_PREDICTED),
                                                           ("_float32", FLOAT32))}
        timed = field_race_rates(runs, steps=steps)
        yield from timed.values()
        step = {name: row["ms_per_step"] for name, row in timed.items()}
        yield {"name": "field_20_over_10",
               "step_20_over_10": step["field_20_cars_in_turns"] / step["field_10_cars_in_turns"],
               "step_20_over_10_every_car_predicted": (step["field_20_cars_every_car_predicted_in_turns"]
                                                       / step["field_10_cars_every_car_predicted_in_turns"]),
               "step_20_over_10_float32": step["field_20_cars_float32_in_turns"] / step["field_10_cars_float32_in_turns"],
               "target_step_20_over_10": TARGET_20_OVER_10}
        yield {"name": "field_10_speedup",
               "speedup": step["field_10_cars_every_car_predicted_in_turns"] / step["field_10_cars_in_turns"],
               "target_speedup": TARGET_SPEEDUP_10}
        yield {"name": "field_10_speedup_float32",
               "speedup": step["field_10_cars_every_car_predicted_in_turns"] / step["field_10_cars_float32_in_turns"],
               "target_speedup": TARGET_SPEEDUP_10}


def vector_field_rows(cars: tuple[int, ...] = (2, 10, 20), num_envs: int = 256, calls: int = 200,
                      repeats: int = 3) -> Iterator[dict[str, Any]]:
    """The vectorised env (``RaceVectorEnv``) of ``num_envs`` races of ``cars`` cars on the
    trefoil, random learner actions, the other cars coasting, with contact physics and the
    steward (the default) and with ghost cars and no penalties: race-steps per second (median
    of ``repeats`` runs of ``calls`` steps). Each field's physics row has its ratio to the
    first field's (``vs_first_field``) and to its own ghost row (``vs_ghost``)."""
    import gymnasium

    import racing_env  # noqa: F401 - registers racing_env/Race-v0
    from experiments.bench_rl import _random_action_rate

    first = None
    for count in cars:
        rates_by_contact = {}
        for contact, extra in (("physics", {}), ("ghost", dict(contact="ghost", penalties="none"))):
            envs = gymnasium.make_vec("racing_env/Race-v0", num_envs=num_envs, vectorization_mode="vector_entry_point",
                                      num_agents=count, track="trefoil", on_off_track="penalty", **extra)  # bench_rl's RACE
            rate, rates, compile_s = _random_action_rate(envs, num_envs, calls, repeats)
            rates_by_contact[contact] = (rate, rates, compile_s)
        rate, rates, compile_s = rates_by_contact["physics"]
        first = first or rate
        yield {"name": f"vector_env_{count}_cars_B{num_envs}", "cars": count, "races": num_envs, "contact": "physics",
               "steps_per_s": rate, "vs_first_field": rate / first, "vs_ghost": rate / rates_by_contact["ghost"][0],
               "compile_s": compile_s, "repeats": [round(r) for r in rates]}
        rate, rates, compile_s = rates_by_contact["ghost"]
        yield {"name": f"vector_env_{count}_cars_B{num_envs}_ghost", "cars": count, "races": num_envs,
               "contact": "ghost", "steps_per_s": rate, "compile_s": compile_s, "repeats": [round(r) for r in rates]}


def bench_field() -> Iterator[dict[str, Any]]:
    """`racing bench --only field`: :func:`field_rows`, then :func:`vector_field_rows`."""
    yield from field_rows()
    yield from vector_field_rows()
