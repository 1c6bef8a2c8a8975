"""`racing bench --only field`: races of fields of game planners, and the vectorised env with a field.

:func:`field_rows`: a race of N feedback iLQGame planners on the trefoil's grid, every car
re-planning every step in its real-time setting (``iterations=2,trust_radius=10``, the one
that races as well as converged re-plans: docs/experiments/cheap-replans.md) and playing
its local game with its ``rivals=2`` nearest rivals (:mod:`planners.rival_game`), the
field's re-plans solved as one batch per step (:func:`planners.agents.field.solve_field`),
as ``racing tournament`` races them. Race-steps per second for each N, the first step
(which compiles) reported apart, and the exponent of the cost of a step in N fitted over
the fields (:func:`cost_exponent`). The 10- and 20-car fields race again with every other
car predicted in each local game (``obstacles`` at least the field: the local game grows with
N), and a row compares the two settings: the 20-car step over the 10-car step in each (target
at most :data:`TARGET_20_OVER_10`), and the 10-car rate of the default over the other.

:func:`vector_field_rows`: the vectorised env with a field of coasting cars (random learner
actions) beside two cars, at the same batch, timed in turns in one run.
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


def cost_exponent(cars: list[int], seconds_per_step: list[float]) -> float:
    """The exponent ``p`` of the least-squares fit ``seconds = a N^p`` (in logs)."""
    if len(cars) < 2:
        raise ValueError("the exponent needs at least two fields")
    return float(np.polyfit(np.log(cars), np.log(seconds_per_step), 1)[0])


def field_race_rate(cars: int, spec: str = FIELD_SPEC, steps: int = 40, warmup: int = 3,
                    track: str = "trefoil", seed: int = 0, name: str | None = None) -> dict[str, Any]:
    """One field's race: ``cars`` agents ``spec`` on ``track``'s seeded grid, ``warmup`` steps
    (the first compiles), then ``steps`` timed steps of the whole loop (the field's batched
    re-plans, every car's action, the env step)."""
    from planners.agents import make_agent
    from planners.agents.field import solve_field
    from racing_env import RaceConfig
    from racing_env.env import RacingParallelEnv

    env = RacingParallelEnv(RaceConfig(track=track, num_agents=cars, max_steps=warmup + steps + 1))
    observations, _ = env.reset(seed=seed)
    agents = [make_agent(spec) for _ in range(cars)]
    for i, agent in enumerate(agents):
        agent.reset(seed, i, env)
    index = {name: i for i, name in enumerate(env.possible_agents)}
    times, fallbacks, iterations = [], 0, []
    for _ in range(warmup + steps):
        if not env.agents:
            break
        start = time.perf_counter()
        state = env.state()
        racing = [agents[index[a]] for a in env.agents]
        solve_field(racing, [observations[a] for a in env.agents], state)
        actions = {a: agents[index[a]].act(observations[a], state) for a in env.agents}
        observations, *_ = env.step(actions)
        times.append(time.perf_counter() - start)
        for agent in racing:
            record = agent.diagnostics()
            fallbacks += bool(record["fallback"])
            if record["iterations"] is not None:
                iterations.append(record["iterations"])
    timed = np.array(times[warmup:])
    return {"name": name or f"field_{cars}_cars", "cars": cars, "spec": spec, "track": track,
            "steps_per_s": float(len(timed) / timed.sum()), "ms_per_step": 1e3 * float(np.median(timed)),
            "ms_per_step_p95": 1e3 * float(np.percentile(timed, 95)), "compile_s": float(times[0]),
            "steps_timed": int(len(timed)), "fallbacks": fallbacks,
            "iterations_median": float(np.median(iterations)) if iterations else None,
            "target_steps_per_s": TARGET_STEPS_PER_S if cars == 10 else None}


def field_rows(fields: tuple[int, ...] = FIELDS, steps: int = 40) -> Iterator[dict[str, Any]]:
    """A row per field (:func:`field_race_rate`), then the fitted exponent of a step's cost in
    N over every field and over the fields of local games (more than ``rivals + 1 = 3`` cars,
    whose re-plans are all games of three players)."""
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
    by_cars = {row["cars"]: row for row in rows}
    if 10 in by_cars and 20 in by_cars:
        every = {cars: field_race_rate(cars, FIELD_SPEC + EVERY_CAR_PREDICTED, steps=steps,
                                       name=f"field_{cars}_cars_every_car_predicted") for cars in (10, 20)}
        yield from every.values()
        yield {"name": "field_20_over_10", "step_20_over_10": by_cars[20]["ms_per_step"] / by_cars[10]["ms_per_step"],
               "step_20_over_10_every_car_predicted": every[20]["ms_per_step"] / every[10]["ms_per_step"],
               "target_step_20_over_10": TARGET_20_OVER_10}
        yield {"name": "field_10_speedup", "speedup": by_cars[10]["steps_per_s"] / every[10]["steps_per_s"],
               "target_speedup": TARGET_SPEEDUP_10}


def vector_field_rows(cars: tuple[int, ...] = (2, 10), num_envs: int = 256, calls: int = 200,
                      repeats: int = 3) -> Iterator[dict[str, Any]]:
    """The vectorised env (``RaceVectorEnv``) of ``num_envs`` races of ``cars`` cars on the
    trefoil, random learner actions, the other cars coasting: race-steps per second (median
    of ``repeats`` runs of ``calls`` steps), each field's row with its ratio to the first's."""
    import gymnasium

    import racing_env  # noqa: F401 - registers racing_env/Race-v0
    from experiments.bench_rl import _random_action_rate

    first = None
    for count in cars:
        envs = gymnasium.make_vec("racing_env/Race-v0", num_envs=num_envs, vectorization_mode="vector_entry_point",
                                  num_agents=count, track="trefoil", on_off_track="penalty")  # as bench_rl's RACE
        rate, rates, compile_s = _random_action_rate(envs, num_envs, calls, repeats)
        first = first or rate
        yield {"name": f"vector_env_{count}_cars_B{num_envs}", "cars": count, "races": num_envs,
               "steps_per_s": rate, "vs_first_field": rate / first, "compile_s": compile_s,
               "repeats": [round(r) for r in rates]}


def bench_field() -> Iterator[dict[str, Any]]:
    """`racing bench --only field`: :func:`field_rows`, then :func:`vector_field_rows`."""
    yield from field_rows()
    yield from vector_field_rows()
