"""Claims about agents tested on duel records: paired differences with bootstrap intervals.

A claim compares two agents ``a`` and ``b`` on one measure of their races (a win, blocks,
at-fault incidents, contact, time off track). The comparison is **paired**: ``a``'s race and
``b``'s race are matched when they drove the same grid of the same circuit from the same
slot against the same opponent, so the grid, the circuit and the opponent cancel out of the
difference. The difference of the means over the matched pairs gets a 95% percentile
bootstrap interval (resampling the pairs, seeded). A claim that ``a`` is higher is
**reproduced** when the whole interval is above zero, **refuted** when it is below, and
**not separated** when it contains zero.

Input: the duel records of :func:`experiments.tournament.race_lineup` (``results.jsonl`` of
``racing tournament`` runs, two cars per race), each tagged with its circuit.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from experiments.standings import wilson_interval, won_race

MEASURES: dict[str, Callable[[dict[str, Any], dict[str, Any]], float]] = {
    "win": lambda car, race: float(won_race(car, len(race["cars"]))),
    "blocks": lambda car, race: float(car.get("blocks", np.nan)),
    "defending moves": lambda car, race: float(car.get("defending_moves", np.nan)),
    "at-fault incidents": lambda car, race: float(car["faults"]),
    "contact": lambda car, race: float(car["collision_steps"] > 0),
    "time off track [s]": lambda car, race: float(car["time_off_track"]),
    "passes made": lambda car, race: float(car["overtakes"]),
    "margin [s]": lambda car, race: _margin(car, race["cars"]),
    "lap time over the limit": lambda car, race: np.nan if car.get("limit_ratio") is None else float(car["limit_ratio"]),
}
"""Measure name -> its value for one car's record in one race (``blocks``: NaN in a record
made before :mod:`racing_env.blocking`; ``margin [s]``: the other car's finish time less
this car's, NaN unless both finished; ``lap time over the limit``: the finish time over the
car class's lap-time limit, NaN unfinished)."""


def _margin(car: dict[str, Any], cars: Sequence[dict[str, Any]]) -> float:
    others = [other for other in cars if other is not car]
    if len(others) != 1 or car["finish_time"] is None or others[0]["finish_time"] is None:
        return float("nan")
    return float(others[0]["finish_time"] - car["finish_time"])


@dataclasses.dataclass(frozen=True)
class CarRace:
    """One car's race: the ``agent``, its ``opponent``, the ``track``, ``grid`` and start
    ``slot`` (1 = in front), and its ``values`` per measure of :data:`MEASURES`."""

    agent: str
    opponent: str
    track: str
    grid: int
    slot: int
    values: dict[str, float]

    @property
    def key(self) -> tuple[str, str, int, int]:
        """What a paired comparison matches on: opponent, circuit, grid, slot."""
        return (self.opponent, self.track, self.grid, self.slot)


def car_races(records: Iterable[dict[str, Any]], track: str) -> list[CarRace]:
    """Each car's race in the duel ``records`` of one circuit ``track``."""
    rows = []
    for race in records:
        if len(race["cars"]) != 2:
            raise ValueError(f"claims compare duels; race {race.get('id')!r} has {len(race['cars'])} cars")
        for me, other in ((0, 1), (1, 0)):
            car = race["cars"][me]
            rows.append(CarRace(agent=car["agent"], opponent=race["cars"][other]["agent"], track=track,
                                grid=int(race["grid"]), slot=int(car["start_place"]),
                                values={name: f(car, race) for name, f in MEASURES.items()}))
    return rows


@dataclasses.dataclass(frozen=True)
class Mean:
    """A measure's mean over ``n`` races and its 95% interval (Wilson for a share,
    bootstrap otherwise)."""

    value: float
    low: float
    high: float
    n: int


def bootstrap_interval(values: np.ndarray, *, draws: int = 4000, seed: int = 0) -> tuple[float, float]:
    """The 95% percentile bootstrap interval of the mean of ``values (n,)`` (NaN for none)."""
    values = np.asarray(values, dtype=float)
    if values.size == 0:
        return (float("nan"), float("nan"))
    rng = np.random.default_rng(seed)
    means = values[rng.integers(0, values.size, size=(draws, values.size))].mean(axis=1)
    return (float(np.quantile(means, 0.025)), float(np.quantile(means, 0.975)))


def agent_mean(rows: Sequence[CarRace], agent: str, measure: str, *, opponents: Sequence[str] | None = None) -> Mean:
    """``agent``'s mean of ``measure`` over its races (against ``opponents`` only, if given)."""
    values = np.array([r.values[measure] for r in rows
                       if r.agent == agent and (opponents is None or r.opponent in opponents)])
    if measure not in ("win", "contact"):
        return bootstrap_mean(values)
    values = values[~np.isnan(values)]
    low, high = wilson_interval(int(values.sum()), values.size)
    return Mean(value=float(values.mean()) if values.size else float("nan"), low=low, high=high, n=int(values.size))


def bootstrap_mean(values: Sequence[float]) -> Mean:
    """The mean of ``values`` (NaN left out) with its 95% bootstrap interval."""
    values = np.asarray(values, dtype=float)
    values = values[~np.isnan(values)]
    low, high = bootstrap_interval(values)
    return Mean(value=float(values.mean()) if values.size else float("nan"), low=low, high=high, n=int(values.size))


@dataclasses.dataclass(frozen=True)
class Comparison:
    """``a``'s mean minus ``b``'s over ``pairs`` matched races, with its 95% bootstrap
    interval, and the verdict on the claim that ``a`` is higher."""

    a: str
    b: str
    measure: str
    difference: float
    low: float
    high: float
    pairs: int

    @property
    def verdict(self) -> str:
        """``reproduced`` (interval above 0), ``refuted`` (below) or ``not separated``."""
        if self.pairs == 0:
            return "not measurable"
        if self.low > 0:
            return "reproduced"
        if self.high < 0:
            return "refuted"
        return "not separated"


def compare(rows: Sequence[CarRace], a: str, b: str, measure: str) -> Comparison:
    """The paired comparison of ``a`` and ``b`` on ``measure`` (module docstring): their races
    against the same opponent (neither of them), circuit, grid and slot."""
    mine = {r.key: r.values[measure] for r in rows if r.agent == a and r.opponent not in (a, b)}
    theirs = {r.key: r.values[measure] for r in rows if r.agent == b and r.opponent not in (a, b)}
    return _paired(a, b, measure, mine, theirs)


def duel_difference(rows: Sequence[CarRace], a: str, b: str, measure: str) -> Comparison:
    """``a``'s ``measure`` less ``b``'s in the same race, over their duels (``a`` against
    ``b``: each race's two cars, matched by circuit, grid and the two start slots 1 and 2)."""
    mine = {(r.track, r.grid, r.slot): r.values[measure] for r in rows if r.agent == a and r.opponent == b}
    theirs = {(r.track, r.grid, 3 - r.slot): r.values[measure] for r in rows if r.agent == b and r.opponent == a}
    return _paired(a, b, measure, mine, theirs)


def _paired(a: str, b: str, measure: str, mine: dict[Any, float], theirs: dict[Any, float]) -> Comparison:
    """The comparison of the values under the keys both hold (NaN on either side: left out)."""
    keys = sorted(k for k in mine.keys() & theirs.keys() if not (np.isnan(mine[k]) or np.isnan(theirs[k])))
    diffs = np.array([mine[k] - theirs[k] for k in keys])
    low, high = bootstrap_interval(diffs)
    return Comparison(a=a, b=b, measure=measure, difference=float(diffs.mean()) if keys else float("nan"),
                      low=low, high=high, pairs=len(keys))


def head_to_head(rows: Sequence[CarRace], agents: Sequence[str]) -> np.ndarray:
    """``(A, A)`` win rate of the row's agent against the column's in their duels (NaN on the
    diagonal and where they never met)."""
    table = np.full((len(agents), len(agents)), np.nan)
    for i, a in enumerate(agents):
        for j, b in enumerate(agents):
            wins = [r.values["win"] for r in rows if r.agent == a and r.opponent == b]
            if i != j and wins:
                table[i, j] = float(np.mean(wins))
    return table
