"""Named start configurations: the paper's overtaking scenario, seeded start grids and
seeded scenes anywhere on the lap (``anywhere``), and batches of random scenes for solver
studies (:func:`random_scenes`); and the paper's whole game (:func:`paper_game`).

A scenario returns the joint start state ``x0 (N, 6)`` and the cars' parameters. On closed
tracks the grid lines up just behind the start/finish line at ``s = 0`` (negative ``s`` is
the end of the lap before); on open tracks it starts at ``s >= 0``. See docs/env.md.

Each scenario is a start distribution (:func:`scenario_starts`, a
:class:`racing_env.starts.Starts`) that every env draws from with JAX's generator, inside
its compiled step where races autoreset; ``make_scenario(name, ..., seed=s)`` is the start
an env reset with seed ``s`` draws first.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Sequence

import numpy as np

from racing_env.costs import CostWeights
from racing_env.dynamics import STATE_DIM, N_LAT, S, V
from racing_env.game import RaceGame
from racing_env.starts import MAX_TRIES, Starts, draw_episode, fresh_key, key_from_seed
from racing_env.track import Track, straight
from racing_env.vehicle import VehicleParams, stack_vehicles


@dataclasses.dataclass(frozen=True)
class Scenario:
    """A start configuration: joint state ``x0 (N, 6)`` and one ``VehicleParams`` per car."""

    name: str
    x0: np.ndarray
    vehicles: tuple[VehicleParams, ...]


def _front_of_grid(track: Track, depth: float) -> float:
    """Arc length of the first grid slot: behind the line on closed tracks."""
    return -5.0 if track.closed else depth + 5.0


def _default_vehicles(num_cars: int, vehicles: Sequence[VehicleParams] | VehicleParams | None):
    if vehicles is None:
        return tuple(VehicleParams() for _ in range(num_cars))
    if isinstance(vehicles, VehicleParams):
        return tuple(vehicles for _ in range(num_cars))
    if len(vehicles) != num_cars:
        raise ValueError(f"got {len(vehicles)} VehicleParams for {num_cars} cars")
    return tuple(vehicles)


def paper_overtake(
    track: Track,
    num_cars: int = 2,
    vehicles=None,
    seed: int | None = None,
    gap: float = 10.0,
) -> Scenario:
    """The paper's scenario (Figs. 1-2): an overtaking manoeuvre on a straight.

    car_0 (ego, v_max 20 m/s) drives at 20 m/s on the centre line ``gap`` metres ahead;
    car_1 (opponent, v_max 25 m/s) approaches at 23 m/s with a lateral offset of 2 m
    (to the left). The paper does not state the initial gap; 10 m puts the cars side by
    side after about 3 s, inside a 5 s planning horizon.
    """
    if num_cars != 2:
        raise ValueError(f"the paper scenario has exactly 2 cars, got num_cars={num_cars}")
    if vehicles is None:
        vehicles = (VehicleParams(v_max=20.0), VehicleParams(v_max=25.0))
    vehicles = _default_vehicles(2, vehicles)
    start = _front_of_grid(track, gap)
    x0 = np.zeros((2, STATE_DIM))
    x0[0, [S, V, N_LAT]] = [start, 20.0, 0.0]
    x0[1, [S, V, N_LAT]] = [start - gap, 23.0, 2.0]
    return Scenario("paper", x0, vehicles)


PAPER_WEIGHTS = CostWeights(r_jx=10.0, r_jy=10.0)
"""Cost weights of the paper's scene (the others at their defaults). The paper does not
publish its values; with these every method converges and the opponent stays inside the
track in Figure 2 (with r = 1 it already sits at the track edge, so "swerves further left"
cannot show). How they were chosen: docs/experiments/paper.md."""


def paper_game(weights: CostWeights = PAPER_WEIGHTS,
               opponent_collision: float | None = None) -> tuple[RaceGame, np.ndarray]:
    """The paper's game (Figs. 1-2) and its start state: ``(RaceGame, x0 (2, 6))``.

    :func:`paper_overtake` on a straight 400 m long and 12 m wide (6 m each side of the centre
    line), both cars with ``weights``, 50 steps of 0.1 s (a 5 s horizon). The ego (car 0) starts
    at s = 15 m, 20 m/s, on the centre line; the opponent (car 1) at s = 5 m, 23 m/s, 2 m to the
    left. ``opponent_collision`` replaces the opponent's collision weight c_c^2 (Figure 2).
    """
    track = straight(length=400.0, width_left=6.0, width_right=6.0)
    scenario = paper_overtake(track)
    opponent = weights if opponent_collision is None else weights.replace(c_collision=opponent_collision)
    game = RaceGame.create(track, scenario.vehicles, [weights, opponent], dt=0.1, horizon=50)
    return game, scenario.x0


def _drawn(starts: Starts, track: Track, vehicles: Sequence[VehicleParams], seed: int | None) -> np.ndarray:
    """The start ``x0 (N, 6)`` of ``starts`` for ``seed``: the first episode of a race reset
    with that seed (:mod:`racing_env.starts`); None draws from fresh entropy."""
    key = fresh_key() if seed is None else key_from_seed(seed)
    _, x0, free = draw_episode(key, starts, track, stack_vehicles(vehicles))
    if not free:
        raise ValueError(f"no overlap-free start for {len(vehicles)} cars within spread={float(starts.spread):g} m "
                         f"in {MAX_TRIES} draws")
    return x0


def grid_starts(
    track: Track,
    num_cars: int = 2,
    row_spacing: float = 8.0,
    lateral_offset: float = 2.0,
    speed: float = 15.0,
    jitter: bool = True,
    shuffle: bool = True,
    vehicles=None,
) -> Starts:
    """The distribution of :func:`grid`: slot k ``k * row_spacing / 2`` metres behind the
    front, alternately at ``+lateral_offset`` (left) and ``-lateral_offset`` (a staggered
    two-wide grid for any number of cars), at ``speed`` [m/s]; the cars shuffled over the
    slots (``shuffle``) and jittered (``jitter``: up to +-1 m in s, +-0.3 m in n and +-1 m/s
    in speed). On a closed track a grid deeper than half the lap is refused, with the most
    cars it holds (on an open one the grid starts at the track's start, and a finish line
    not ahead of every car is refused where the race is made). A grid that could put two
    footprints of ``vehicles`` (default: the paper's car) closer than :data:`START_MARGIN`,
    whatever the jitter, is refused. The distances are the paper's car's (4.7 m x 2.0 m) on a
    full-size circuit: on a circuit's model (``track.scale`` k < 1, a 1:10 model:
    :func:`racing_env.track.scaled`) they are :func:`grid_size` times these (k, or more for
    cars larger than the paper's car at k: the 1:10 class is 0.58 m x 0.31 m) and the speeds
    ``sqrt(k)`` times (the full-size grid, scaled); the clearance is ``k * START_MARGIN``."""
    k = float(track.scale)
    cars = _default_vehicles(num_cars, vehicles)
    size = grid_size(k, cars)
    row_spacing, lateral_offset, speed = row_spacing * size, lateral_offset * size, speed * np.sqrt(k)
    jitter_widths = (1.0 * size, 0.3 * size, 1.0 * np.sqrt(k)) if jitter else (0.0, 0.0, 0.0)
    check_grid_clearance(num_cars, row_spacing, lateral_offset, jitter_widths, cars, START_MARGIN * k)
    depth = 0.5 * row_spacing * (num_cars - 1)
    room = 0.5 * float(track.length) - 5.0
    if track.closed and depth > room:
        most = int(room // (0.5 * row_spacing)) + 1 if row_spacing > 0 else num_cars
        raise ValueError(f"a grid of {num_cars} cars is {depth:g} m deep, more than track {track.name!r} "
                         f"({float(track.length):g} m) has room for: at most {most} cars here")
    front = _front_of_grid(track, depth)
    slots = np.zeros((num_cars, STATE_DIM))
    for slot in range(num_cars):
        slots[slot, S] = front - 0.5 * row_spacing * slot
        slots[slot, N_LAT] = lateral_offset if slot % 2 == 0 else -lateral_offset
        slots[slot, V] = speed
    return Starts.grid(slots, shuffle, jitter_widths)


START_MARGIN = 0.5
"""[m] The least clearance between two cars' footprints that a start grid may give, on the
worst draw of its jitter (the grid's footprints are aligned with the track), on a full-size
circuit (on a model at scale k: k times it)."""


def grid_size(scale: float, vehicles: Sequence[VehicleParams]) -> float:
    """The factor on a full-size grid's distances for ``vehicles`` on a track at ``scale``:
    the scale, or the largest car's length and width over the paper's car's (4.7 m, 2.0 m)
    where more (a grid made for the paper's car, widened to hold them). 1 for the full-size
    classes on a full-size circuit."""
    paper = VehicleParams()
    length = max(float(v.length) for v in vehicles) / float(paper.length)
    width = max(float(v.width) for v in vehicles) / float(paper.width)
    return max(float(scale), length, width)


def check_grid_clearance(num_cars: int, row_spacing: float, lateral_offset: float,
                         jitter: tuple[float, float, float], vehicles: Sequence[VehicleParams],
                         margin: float = START_MARGIN) -> None:
    """Refuse a grid whose worst jittered draw puts two footprints of ``vehicles`` (the
    largest of them) closer than ``margin`` [m] (:data:`START_MARGIN` on a full-size
    circuit): apart along the track or across it."""
    if num_cars < 2:
        return
    length = max(float(v.length) for v in vehicles)
    width = max(float(v.width) for v in vehicles)
    slot = np.arange(num_cars)
    s = -0.5 * row_spacing * slot
    n = np.where(slot % 2 == 0, lateral_offset, -lateral_offset)
    pairs = np.triu_indices(num_cars, 1)
    along = np.abs(s[pairs[0]] - s[pairs[1]]) - 2.0 * jitter[0] - length
    across = np.abs(n[pairs[0]] - n[pairs[1]]) - 2.0 * jitter[1] - width
    clearance = float(np.min(np.maximum(along, across)))
    if clearance < margin:
        raise ValueError(f"this grid (row_spacing={row_spacing:g} m, lateral_offset={lateral_offset:g} m) can start "
                         f"two cars {clearance:.2f} m apart, under the {margin:g} m every start keeps: "
                         f"space the rows or the columns further")


def grid(
    track: Track,
    num_cars: int = 2,
    vehicles=None,
    seed: int | None = 0,
    row_spacing: float = 8.0,
    lateral_offset: float = 2.0,
    speed: float = 15.0,
    jitter: bool = True,
) -> Scenario:
    """A staggered two-column rolling start (:func:`grid_starts`); the seed shuffles the
    grid order and, with ``jitter``, jitters it (drawn with JAX, :mod:`racing_env.starts`).
    Without a seed the cars take the slots in order, unjittered. Start speeds [m/s] are
    then capped to ``[0, 0.95 * v_max]`` of each car."""
    vehicles = _default_vehicles(num_cars, vehicles)
    starts = grid_starts(track, num_cars, row_spacing, lateral_offset, speed, jitter=jitter and seed is not None,
                         shuffle=seed is not None, vehicles=vehicles)
    return Scenario("grid", _drawn(starts, track, vehicles, seed), vehicles)


def side_by_side(track: Track, num_cars: int = 2, vehicles=None, seed: int | None = None) -> Scenario:
    """Two cars abreast at 15 m/s, 2 m left and right of the centre line."""
    if num_cars != 2:
        raise ValueError(f"side_by_side has exactly 2 cars, got num_cars={num_cars}")
    return grid(track, 2, vehicles, seed=None, row_spacing=0.0, speed=15.0, jitter=False)


def check_scene_ranges(spread: float, speed: tuple[float, float], margin: float = 0.0) -> None:
    """Raise ``ValueError`` unless :func:`random_scenes` can use these ranges:
    ``spread >= 0`` [m], ``margin >= 0`` [m] and ``0 < speed[0] <= speed[1]`` [m/s]."""
    if not (spread >= 0 and margin >= 0 and 0 < speed[0] <= speed[1]):
        raise ValueError(f"need spread >= 0, margin >= 0 and 0 < speed[0] <= speed[1]; "
                         f"got spread={spread!r}, margin={margin!r}, speed={speed!r}")


def scene_starts(
    track: Track,
    num_cars: int,
    spread: float = 15.0,
    speed: tuple[float, float] = (10.0, 19.0),
    margin: float = 1.5,
    s_max: float | None = None,
) -> Starts:
    """The distribution of :func:`random_scenes` (its docstring says what the arguments
    bound); raises ``ValueError`` when the ranges leave no room on ``track``."""
    if num_cars < 1:
        raise ValueError(f"need at least 1 car, got {num_cars}")
    check_scene_ranges(spread, speed, margin)
    if not track.closed and track.length <= spread:
        raise ValueError(f"the open track {track.name!r} ({track.length} m) is not longer than spread={spread} m")
    lo = spread if not track.closed else 0.0  # open tracks: every car at s >= 0
    hi = track.length if s_max is None else min(track.length, s_max)
    if not hi > lo:
        raise ValueError(f"no room for a scene on track {track.name!r}: its reference arc length would be "
                         f"drawn from [{lo:g}, {hi:g}) m")
    if np.min(np.asarray(track.width_left) + np.asarray(track.width_right)) < 2 * margin:
        raise ValueError(f"margin={margin} m leaves no room on track {track.name!r}: it is narrower than "
                         f"{2 * margin:g} m somewhere")
    return Starts.scenes(num_cars, (lo, hi), spread, margin, speed)


def random_scenes(
    track: Track,
    vehicles: Sequence[VehicleParams],
    count: int,
    seed: int | None = 0,
    spread: float = 15.0,
    speed: tuple[float, float] = (10.0, 19.0),
    margin: float = 1.5,
    s_max: float | None = None,
) -> np.ndarray:
    """``count`` seeded close-quarters starts anywhere on ``track``: ``x0s (count, N, 6)``.

    Per scene a reference arc length is drawn uniformly over the track (below ``s_max``
    [m] if given, e.g. to keep the scenes short of a finish line); every car starts
    0 to ``spread`` metres [m] behind it, at a lateral offset drawn uniformly inside the
    track at its own arc length, ``margin`` [m] from either edge, and at a speed drawn from
    ``speed`` [m/s] (capped at 95% of the car's ``v_max``); heading and accelerations are
    zero. No two cars start in contact by the env's test,
    :func:`racing_env.physics.footprint_overlap` (positions drawn again until so). For
    solver robustness sweeps: unlike :func:`grid` the scenes cover the whole lap, its curves
    and its width changes. Scene k is the start of episode k of a race reset with ``seed``
    (:mod:`racing_env.starts`).
    """
    if int(count) < 1:
        raise ValueError(f"need at least 1 scene, got count={count!r}")
    starts = scene_starts(track, len(vehicles), spread, speed, margin, s_max)
    stacked = stack_vehicles(vehicles)
    key = fresh_key() if seed is None else key_from_seed(seed)
    scenes = []
    for _ in range(int(count)):
        key, x0, free = draw_episode(key, starts, track, stacked)
        if not free:
            raise ValueError(f"no overlap-free start for {len(vehicles)} cars within spread={spread} m "
                             f"in {MAX_TRIES} draws")
        scenes.append(x0)
    return np.stack(scenes)


#: How far [m] before the finish line an ``anywhere`` scene's reference point lies at least, so
#: that no episode is over in its first seconds.
ANYWHERE_MIN_RUN = 100.0
#: Start speeds [m/s] of ``anywhere`` scenes: slow enough at the bottom that a start inside
#: the tightest corners of real circuits can be survived (Monza's first chicane, radius 9 m
#: on the centre line).
ANYWHERE_SPEED = (5.0, 19.0)


def field_spread(num_cars: int) -> float:
    """How far behind a scene's reference point [m] the cars of an ``anywhere`` scene start:
    15 m for up to three cars, 12 m per car beyond two for bigger fields, so that an
    overlap-free draw stays likely (20 cars: 216 m)."""
    return max(15.0, 12.0 * (num_cars - 2))


def anywhere_starts(track: Track, num_cars: int = 2, finish_s: float | None = None) -> Starts:
    """The distribution of :func:`anywhere`: :func:`scene_starts` at :data:`ANYWHERE_SPEED`
    within :func:`field_spread`, the reference point at least :data:`ANYWHERE_MIN_RUN` metres
    before ``finish_s`` [m]."""
    if finish_s is not None and finish_s <= ANYWHERE_MIN_RUN:
        raise ValueError(f"scenario 'anywhere' places its scenes at least {ANYWHERE_MIN_RUN:g} m before the finish "
                         f"line, which lies at s = {finish_s:g} m: race further (race_distance)")
    s_max = None if finish_s is None else finish_s - ANYWHERE_MIN_RUN
    return scene_starts(track, num_cars, spread=field_spread(num_cars), speed=ANYWHERE_SPEED, s_max=s_max)


def anywhere(
    track: Track, num_cars: int = 2, vehicles=None, seed: int | None = 0, finish_s: float | None = None
) -> Scenario:
    """One seeded close-quarters scene anywhere on the lap (:func:`random_scenes`: cars up to
    15 m apart, 1.5 m inside the edges, at :data:`ANYWHERE_SPEED`, 5-19 m/s), its
    reference point at least :data:`ANYWHERE_MIN_RUN` metres before the finish line
    ``finish_s`` [m] (if given). For training on long circuits: episodes start in every
    corner instead of always on the grid, so a policy meets the whole lap early."""
    vehicles = _default_vehicles(num_cars, vehicles)
    return Scenario("anywhere", _drawn(anywhere_starts(track, num_cars, finish_s), track, vehicles, seed), vehicles)


def scenario_starts(name: str, track: Track, num_cars: int, vehicles=None, finish_s: float | None = None) -> Starts:
    """The start distribution (:class:`racing_env.starts.Starts`) of the named scenario,
    the one its seeded draws come from: what an env draws every episode from."""
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; choose one of {sorted(SCENARIOS)}")
    if name == "grid":
        return grid_starts(track, num_cars, vehicles=vehicles)
    if name == "anywhere":
        return anywhere_starts(track, num_cars, finish_s)
    # the fixed starts: their one state, never shuffled or jittered
    return Starts.grid(SCENARIOS[name](track, num_cars, vehicles).x0, False, (0.0, 0.0, 0.0), capped=False)


SCENARIOS: dict[str, Callable[..., Scenario]] = {
    "paper": paper_overtake,
    "grid": grid,
    "side_by_side": side_by_side,
    "anywhere": anywhere,
}
FIXED_STARTS = ("paper", "side_by_side")
"""The scenarios with a single start whatever the seed, both of exactly 2 cars."""
NEEDS_FINISH_LINE = ("anywhere",)
"""The scenarios that place their cars relative to the finish line (``finish_s``)."""


def make_scenario(
    name: str, track: Track, num_cars: int, vehicles=None, seed: int | None = 0, finish_s: float | None = None
) -> Scenario:
    """Build the named scenario (``paper``, ``grid``, ``side_by_side``, ``anywhere``);
    ``finish_s`` [m], the race's finish line, keeps an ``anywhere`` scene short of it."""
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; choose one of {sorted(SCENARIOS)}")
    if num_cars < 1:
        raise ValueError(f"num_cars must be >= 1, got {num_cars}")
    extra = {"finish_s": finish_s} if name in NEEDS_FINISH_LINE else {}
    scenario = SCENARIOS[name](track, num_cars=num_cars, vehicles=vehicles, seed=seed, **extra)
    half_widths = np.stack([track.width_left_at(scenario.x0[:, S]), track.width_right_at(scenario.x0[:, S])])
    if np.any(scenario.x0[:, N_LAT] > half_widths[0]) or np.any(-scenario.x0[:, N_LAT] > half_widths[1]):
        raise ValueError(f"scenario {name!r} places a car outside the track {track.name!r}")
    return scenario
