"""Configuration of a race: track, cars, scenario, race length, rewards and incident rules."""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from racing_env.contact import check_contact
from racing_env.costs import CostWeights, racing_weights
from racing_env.observation import check_observation_units
from racing_env.scenarios import SCENARIOS
from racing_env.steward import DEFAULT_RULES, check_stewarding
from racing_env.track import Track
from racing_env.vehicle import VehicleParams

INCIDENT_MODES = ("penalty", "terminate", "both", "ignore")
RETIRING_MODES = ("terminate", "both")  # the incident modes that retire the car


def check_incident_rules(**rules: str) -> None:
    """Refuse an incident rule (``on_collision=...``, ``on_off_track=...``) that is not one
    of :data:`INCIDENT_MODES`."""
    for name, mode in rules.items():
        if mode not in INCIDENT_MODES:
            raise ValueError(f"{name} must be one of {INCIDENT_MODES}, got {mode!r}")


def check_race_length(laps: int, race_distance: float | None, max_steps: int) -> None:
    """Refuse a race length that is not one: ``laps`` and ``max_steps`` must be integers
    >= 1, ``race_distance`` None or a finite number of metres > 0."""
    if isinstance(laps, bool) or not isinstance(laps, (int, np.integer)) or laps < 1:
        raise ValueError(f"laps must be an integer >= 1, got {laps!r}")
    if race_distance is not None and not (is_number(race_distance) and np.isfinite(race_distance)
                                          and race_distance > 0):
        raise ValueError(f"race_distance must be a finite number > 0 metres, got {race_distance!r}")
    if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
        raise ValueError(f"max_steps must be an integer >= 1, got {max_steps!r}")


def is_number(value: object) -> bool:
    """Whether ``value`` is a real number (a bool is not)."""
    return isinstance(value, (int, float, np.number)) and not isinstance(value, bool)


DEFAULT_DT = 0.1
"""The race's time step [s] on a full-size track (:attr:`RaceConfig.dt`)."""


def model_step(track: Track | str, dt: float = DEFAULT_DT) -> float:
    """The time step [s] of a race on ``track``: ``dt`` at full size (and for a track named by
    a string), ``dt * sqrt(k)`` on a model at scale k (Froude scaling, :class:`RaceConfig`)."""
    scale = track.scale if isinstance(track, Track) else 1.0
    return float(dt) if scale == 1.0 else float(dt) * float(np.sqrt(scale))


@dataclasses.dataclass(frozen=True)
class RewardConfig:
    """Per-step reward of each car: a weighted sum of these terms.

    Attributes:
        progress: per metre of arc length gained this step.
        position: per step, times ``(cars behind - cars ahead) / (N - 1)``.
        collision: per step with the car's footprint touching another's, whoever caused it
            (negative = penalty; off by default: ``fault`` charges the car that caused it).
        off_track: per step with the car's centre beyond a track boundary.
        finish: on crossing the finish line, times ``(N - place) / (N - 1)`` (winner gets it all;
            a lone car, N = 1, too).
        lead: per metre gained this step on the car's lead over the furthest of its rivals
            (negative while behind). A finished rival counts as carrying on from the line
            at its speed; a car that finishes takes its last lead at its own crossing time.
            Over a race the term sums to the weight times (the lead at the line minus the
            lead at the start): the margin in metres, or minus the time lost times the
            winner's speed. Rivals retired by an incident rule no longer count (from the
            step they retire in, so the sum then differs by their part).
        time: per second the car races (negative charges for time): every step from the
            start until it finishes or retires, the finishing step up to the crossing, so
            over a race that it finishes the term sums to the weight times its finish time.
            Progress alone is paid per metre, so a lap's return hardly depends on its pace;
            with ``time`` it does. Charging time rewards ending the episode early, so pair
            it with ``off_track`` (and ``collision``) penalties, or with ``progress``
            paying more per step at racing speed than ``time`` charges.
        fault: per contact incident the car answers for, by the steward's verdict
            (:mod:`racing_env.steward`), charged in the step the incident begins.
    """

    progress: float = 0.1
    position: float = 0.0
    collision: float = 0.0
    off_track: float = -1.0
    finish: float = 10.0
    lead: float = 0.0
    time: float = 0.0
    fault: float = -10.0


MAX_CARS = 20
"""The largest field a race takes: the cars the start grids and the renderer are made for."""


@dataclasses.dataclass(frozen=True)
class RaceConfig:
    """Everything that defines a race (guide: docs/env.md).

    Attributes:
        track: a ``Track``, a built-in track name (``straight``, ``trefoil``, ...) or a path to
            a TUMFTM-format CSV file.
        num_agents: number of cars N, 1 to :data:`MAX_CARS` (20).
        scenario: start configuration, one of ``racing_env.scenarios.SCENARIOS``.
        vehicles: one ``VehicleParams`` for all cars, one per car, or None for the scenario's.
        weights: cost weights of the game the env builds (``env.game``), which the planners
            racing in it use: one ``CostWeights`` for all cars, one per car, or None: every car
            ``CostWeights(r_jx=RACING_JERK_WEIGHT, r_jy=RACING_JERK_WEIGHT)``, the other weights
            at their defaults, the jerk weights scaled for a car whose jerk limits are not the
            paper car's 30 m/s^3 and on a model of a circuit by its scale
            (:func:`racing_env.costs.racing_weights`). Racing wants the jerk weight small
            (:data:`racing_env.costs.RACING_JERK_WEIGHT`, 0.01): at ``CostWeights``' own default
            r = 1, the one for single solves, a 5 s horizon buys so little progress per unit of
            jerk that the planners barely accelerate. Tournaments, sweeps and training race with
            the same default (their ``jerk_weight``).
        laps: race length in laps on closed tracks.
        race_distance: finish line position [m] of arc length; overrides ``laps``. Default on
            open tracks: 20 m before the end of the track. The env refuses a finish line
            that is not ahead of every car's start or lies beyond an open track's end.
        max_steps: steps after which the race is truncated.
        dt: time step [s]; None (the default): :data:`DEFAULT_DT` on a full-size track and
            ``DEFAULT_DT * sqrt(k)`` on a model at scale k (a :class:`Track` with ``scale`` k,
            ``racing_env.track.circuit(name, k)``). A model races in Froude-scaled time: at equal
            accelerations its lengths are k times and its speeds sqrt(k) times the full size's,
            so its motion is 1/sqrt(k) times quicker and the step that resolves it sqrt(k) times
            shorter (0.032 s at 1:10). A track named by a string is full size.
        horizon: planning horizon in steps for the game built from this config.
        on_collision / on_off_track: what an incident does to the cars' rewards and
            races: ``penalty`` (reward terms only, the default), ``terminate`` (the car is
            out, no penalty), ``both`` or ``ignore`` (reported in infos only). Contact's own
            physics and the steward's penalties apply whatever ``on_collision`` says.
        contact: ``physics`` (the default: cars that meet collide, :mod:`racing_env.contact`)
            or ``ghost`` (they drive through each other; contact is only detected).
        restitution: the share ``e`` in ``[0, 1]`` of the closing speed two colliding cars
            separate with.
        contact_friction: Coulomb coefficient ``mu >= 0`` of the sliding between two cars
            in a contact.
        penalties: what the steward (:mod:`racing_env.steward`) does to a car that caused an
            incident: ``time`` (the default: ``penalty_seconds`` added to its race time,
            which orders the finish), ``drive-through``, ``disqualify`` (out at its
            ``disqualify_after``-th) or ``none`` (verdicts recorded only).
        penalty_seconds: [s] per incident, with ``penalties="time"``.
        severity_speed: None (the default): every time penalty is ``penalty_seconds``; a
            speed [m/s]: the penalty is scaled by the incident's closing speed over it.
        disqualify_after: at-fault incidents that retire a car, with ``penalties="disqualify"``.
        rules: the steward's rules that apply, a subset of :data:`racing_env.steward.RULES`
            (docs/rules.md); by default :data:`racing_env.steward.DEFAULT_RULES`, all but the
            optional ``weaving``.
        reward: reward weights.
        preview_distances: distances ahead [m] at which curvature and widths are observed.
        render_mode: None, ``rgb_array`` or ``human``.
        render_size: side of the rendered square frame [px].
        camera: ``track`` (whole track), ``follow`` (window around the cars) or ``auto``.
        follow_car: the car the follow camera centres its window on, with the pack around
            it; None (the default): the leader, and for up to four cars every car racing.
        observed_rivals: the observation's rival blocks: None (the default) every other car
            in index order; K (1 to ``MAX_CARS - 1``) the K nearest rivals by track distance,
            nearest first, a fixed size whatever N (:mod:`racing_env.observation`).
        observation_units: ``scaled`` (the default: every feature over a scale of the car
            and the track, of order one) or ``physical`` (m, m/s, rad, m/s^2, 1/m);
            :data:`racing_env.observation.OBSERVATION_UNITS`.
        slipstream: whether a car with drag (a class with ``c_drag > 0``: ``tum``, ``av21``)
            has less of it in another car's wake (:data:`racing_env.dynamics.SLIPSTREAM`), in
            the env's physics and in the game the planners solve; True by default. Cars
            without drag do not feel it either way.
    """

    track: Track | str = "trefoil"
    num_agents: int = 2
    scenario: str = "grid"
    vehicles: VehicleParams | Sequence[VehicleParams] | None = None
    weights: CostWeights | Sequence[CostWeights] | None = None
    laps: int = 1
    race_distance: float | None = None
    max_steps: int = 3000
    dt: float | None = None
    horizon: int = 50
    on_collision: str = "penalty"
    on_off_track: str = "penalty"
    reward: RewardConfig = dataclasses.field(default_factory=RewardConfig)
    preview_distances: tuple[float, ...] = (0.0, 10.0, 25.0, 50.0, 100.0)
    render_mode: str | None = None
    render_size: int = 512
    camera: str = "auto"
    follow_car: int | None = None
    observed_rivals: int | None = None
    observation_units: str = "scaled"
    contact: str = "physics"
    restitution: float = 0.3
    contact_friction: float = 0.5
    penalties: str = "time"
    penalty_seconds: float = 5.0
    severity_speed: float | None = None
    disqualify_after: int = 3
    rules: tuple[str, ...] = DEFAULT_RULES
    slipstream: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.num_agents, (int, np.integer)) or not 1 <= self.num_agents <= MAX_CARS:
            raise ValueError(f"num_agents must be an integer in [1, {MAX_CARS}], got {self.num_agents!r}")
        if self.scenario not in SCENARIOS:
            raise ValueError(f"unknown scenario {self.scenario!r}; choose one of {sorted(SCENARIOS)}")
        check_race_length(self.laps, self.race_distance, self.max_steps)
        if self.dt is None:
            object.__setattr__(self, "dt", model_step(self.track))
        if not (is_number(self.dt) and np.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"dt must be None (DEFAULT_DT, Froude-scaled on a model) or a positive number of "
                             f"seconds, got {self.dt!r}")
        check_incident_rules(on_collision=self.on_collision, on_off_track=self.on_off_track)
        check_contact(self.contact, self.restitution, self.contact_friction)
        check_stewarding(self.penalties, self.penalty_seconds, self.disqualify_after, self.rules)
        object.__setattr__(self, "rules", tuple(self.rules))  # hashable, whatever sequence came in
        if self.severity_speed is not None and not (is_number(self.severity_speed) and np.isfinite(
                self.severity_speed) and self.severity_speed > 0):
            raise ValueError(f"severity_speed must be None (unscaled penalties) or a speed > 0 m/s, "
                             f"got {self.severity_speed!r}")
        if self.render_mode not in (None, "rgb_array", "human"):
            raise ValueError(f"render_mode must be None, 'rgb_array' or 'human', got {self.render_mode!r}")
        if self.camera not in ("auto", "track", "follow"):
            raise ValueError(f"camera must be 'auto', 'track' or 'follow', got {self.camera!r}")
        if self.follow_car is not None and (isinstance(self.follow_car, bool) or not isinstance(
                self.follow_car, (int, np.integer)) or not 0 <= self.follow_car < self.num_agents):
            raise ValueError(f"follow_car must be None or a car index in [0, {self.num_agents}), got {self.follow_car!r}")
        if self.observed_rivals is not None and (isinstance(self.observed_rivals, bool) or not isinstance(
                self.observed_rivals, (int, np.integer)) or not 1 <= self.observed_rivals < MAX_CARS):
            raise ValueError(f"observed_rivals must be None (every other car) or an integer in [1, {MAX_CARS - 1}] "
                             f"(the nearest rivals observed), got {self.observed_rivals!r}")
        check_observation_units(self.observation_units)
        if not isinstance(self.slipstream, (bool, np.bool_)):
            raise ValueError(f"slipstream must be True or False, got {self.slipstream!r}")
        if len(self.preview_distances) < 1 or not all(np.isfinite(d) and d >= 0 for d in self.preview_distances):
            raise ValueError(
                f"preview_distances must be non-empty, finite and >= 0, got {self.preview_distances!r}"
            )
        if isinstance(self.vehicles, Sequence) and len(self.vehicles) != self.num_agents:
            raise ValueError(f"got {len(self.vehicles)} VehicleParams for num_agents={self.num_agents}")
        if isinstance(self.weights, Sequence) and len(self.weights) != self.num_agents:
            raise ValueError(f"got {len(self.weights)} CostWeights for num_agents={self.num_agents}")

    def game_weights(self) -> CostWeights | Sequence[CostWeights]:
        """The cost weights of the game the env builds: ``weights``, or when None the racing
        default, every car with jerk weight :data:`racing_env.costs.RACING_JERK_WEIGHT` scaled
        for its jerk limits (:func:`racing_env.costs.racing_weights`)."""
        if self.weights is not None:
            return self.weights
        scale = self.track.scale if isinstance(self.track, Track) else 1.0
        if self.vehicles is None:
            return racing_weights(scale=scale)
        if isinstance(self.vehicles, VehicleParams):
            return racing_weights(vehicle=self.vehicles, scale=scale)
        return [racing_weights(vehicle=vehicle, scale=scale) for vehicle in self.vehicles]
