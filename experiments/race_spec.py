"""The race a tournament, a sweep or a training run races, declared once.

:class:`RaceSpec` holds what the three configurations share about their race (track, length,
step cap, the planners' jerk weight, incident rules, contact and the steward's penalties) and checks it once; each
configuration inherits its fields, so they stay flat keyword arguments
(``TournamentConfig(agents=..., track="straight", laps=2)``) and flat keys in the
``tournament.json``, ``sweep.json`` and ``train.json`` settings files.
:meth:`RaceSpec.to_race_config` turns it into the env's :class:`racing_env.config.RaceConfig`
for a number of cars and a start. Guide: docs/sweeps.md.
"""

from __future__ import annotations

import dataclasses
import numbers
from typing import Any, Sequence

from racing_env.car_classes import CAR_CLASSES, car_names, get_car
from racing_env.config import RaceConfig, check_incident_rules, check_race_length
from racing_env.contact import CONTACT_MODES
from racing_env.observation import check_observation_units
from racing_env.steward import DEFAULT_RULES, check_stewarding
from racing_env.costs import RACING_JERK_WEIGHT, CostWeights, racing_weights
from racing_env.track import check_scale, get_track


@dataclasses.dataclass(frozen=True, kw_only=True)
class RaceSpec:
    """The race's fields, shared by ``TournamentConfig``, ``SweepConfig`` and ``TrainConfig``.

    Attributes:
        track: a built-in track name (``straight``, ``trefoil``, ...) or the path of a
            TUMFTM-format CSV file (a string: it goes into the run's JSON settings).
        laps: race length in laps on closed tracks.
        race_distance: finish line [m] of arc length; overrides ``laps`` when given.
        max_steps: a race is truncated after this many steps.
        jerk_weight: the planners' jerk weight r (``R = r I``, every car) in the race's game.
            The default, :data:`racing_env.costs.RACING_JERK_WEIGHT`, is also the env's
            when it is given no weights (``parallel_env``).
        on_collision / on_off_track: what contact and leaving the track do
            (:data:`racing_env.config.INCIDENT_MODES`): ``penalty`` (reward term only),
            ``terminate`` (the car retires), ``both`` or ``ignore``.
        contact: ``physics`` (cars collide, the default) or ``ghost`` (they drive through
            each other), :data:`racing_env.contact.CONTACT_MODES`.
        penalties: what the steward does to the car that caused an incident
            (:data:`racing_env.steward.PENALTY_MODES`; docs/rules.md): ``time`` (the default,
            ``penalty_seconds`` added to its race time), ``drive-through``, ``disqualify`` or
            ``none``.
        penalty_seconds: [s] per incident with ``penalties="time"``.
        rules: the steward's rules (:data:`racing_env.steward.RULES`; by default
            :data:`racing_env.steward.DEFAULT_RULES`, all but the optional ``weaving``).
        observation_units: what the cars' observations are in
            (:data:`racing_env.observation.OBSERVATION_UNITS`): ``scaled`` (the default) or
            ``physical``.
        car: every car's class (:data:`racing_env.car_classes.CAR_CLASSES`: ``paper``, the
            default, ``tum``, ``av21``, ``f1tenth``), but for the cars whose agent spec names
            its own (``car=NAME``, :func:`planners.agents.split_car`; :meth:`car_classes`).
        track_scale: the track as a model at this scale (``racing_env.track.get_track``'s
            ``scale``: 0.1 is a 1:10 model for the ``f1tenth`` class, its racing line, grid and
            the steward's distances scaled alike); 1, the default, full size.
    """

    track: str = "trefoil"
    laps: int = 1
    race_distance: float | None = None
    max_steps: int = 3000
    jerk_weight: float = RACING_JERK_WEIGHT
    on_collision: str = "penalty"
    on_off_track: str = "penalty"
    contact: str = "physics"
    penalties: str = "time"
    penalty_seconds: float = 5.0
    rules: tuple[str, ...] = DEFAULT_RULES
    observation_units: str = "scaled"
    car: str = "paper"
    track_scale: float = 1.0

    def __post_init__(self) -> None:
        check_race_spec(self)
        object.__setattr__(self, "rules", tuple(self.rules))  # a list from a JSON or TOML file

    def race_spec(self) -> "RaceSpec":
        """The race's fields alone (of a configuration that inherits them)."""
        return RaceSpec(**{name: getattr(self, name) for name in RACE_FIELDS})

    def weights(self) -> CostWeights:
        """Every car's cost weights in the race's game: the defaults with jerk weight
        ``jerk_weight``, scaled for the jerk limits of the race's ``car`` and the track's
        ``track_scale`` (:func:`racing_env.costs.racing_weights`)."""
        return racing_weights(self.jerk_weight, get_car(self.car), self.track_scale)

    def car_classes(self, lineup: Sequence[str | None]) -> list[str]:
        """The class of each car of ``lineup`` (agent specs by starting slot, None for a car
        without one): the spec's ``car=NAME`` where it gives one, else the race's ``car``.

        Raises:
            ValueError: for a class name that is no class, listing the classes.
        """
        from planners.agents.registry import split_car

        return [self.car if spec is None else (split_car(spec)[1] or self.car) for spec in lineup]

    def to_race_config(self, num_agents: int, scenario: str = "grid", cars: Sequence[str] | None = None,
                       **fields: Any) -> RaceConfig:
        """This race for ``num_agents`` cars from ``scenario``
        (:data:`racing_env.scenarios.SCENARIOS`), every car's weights :meth:`weights`.
        ``cars``: the class of each car (``num_agents`` names, e.g. :meth:`car_classes` of a
        lineup), each car then with the jerk weight scaled for its own class; None: every car
        of class ``car``. ``fields``: further :class:`RaceConfig` fields (``vehicles``,
        ``reward``, ``render_mode``, ...), which override the spec's (e.g. per-car
        ``weights``). The paper's class for every car leaves the cars to the scenario (whose
        cars are the paper's)."""
        track = self.track if self.track_scale == 1.0 else get_track(self.track, self.track_scale)
        race: dict[str, Any] = dict(track=track, laps=self.laps, race_distance=self.race_distance,
                                    max_steps=self.max_steps, on_collision=self.on_collision,
                                    on_off_track=self.on_off_track, weights=self.weights(), contact=self.contact,
                                    penalties=self.penalties, penalty_seconds=self.penalty_seconds,
                                    rules=self.rules, observation_units=self.observation_units)
        if cars is not None:
            if len(cars) != num_agents:
                raise ValueError(f"{len(cars)} car classes for a race of {num_agents} cars")
            for name in cars:
                check_car(name)
        if cars is not None and len(set(cars)) > 1:
            vehicles = [get_car(name) for name in cars]
            race["vehicles"] = vehicles
            race["weights"] = [racing_weights(self.jerk_weight, vehicle, self.track_scale) for vehicle in vehicles]
        else:
            car = self.car if cars is None else cars[0]
            if car != "paper":
                race["vehicles"] = get_car(car)
                race["weights"] = racing_weights(self.jerk_weight, race["vehicles"], self.track_scale)
        race.update(fields)
        return RaceConfig(num_agents=num_agents, scenario=scenario, **race)


RACE_FIELDS = tuple(field.name for field in dataclasses.fields(RaceSpec))
"""The names of the race's fields, in declaration order."""


def check_race_spec(spec: RaceSpec) -> None:
    """Refuse race fields that no race has, saying what is allowed."""
    if not isinstance(spec.track, str):
        raise ValueError(f"track must be a string, a built-in track name or a TUMFTM CSV path, got {spec.track!r}")
    check_race_length(spec.laps, spec.race_distance, spec.max_steps)
    weight = spec.jerk_weight
    if isinstance(weight, bool) or not isinstance(weight, numbers.Real) or not weight > 0:
        raise ValueError(f"jerk_weight must be a number > 0, got {weight!r}")
    check_incident_rules(on_collision=spec.on_collision, on_off_track=spec.on_off_track)
    if spec.contact not in CONTACT_MODES:
        raise ValueError(f"contact must be one of {CONTACT_MODES}, got {spec.contact!r}")
    check_stewarding(spec.penalties, spec.penalty_seconds, 3, spec.rules)
    check_observation_units(spec.observation_units)
    check_car(spec.car)
    check_scale(spec.track_scale)


def check_car(name: str) -> None:
    """Refuse a car class name that is no class (:data:`racing_env.car_classes.CAR_CLASSES`),
    listing the classes."""
    if not isinstance(name, str) or name not in CAR_CLASSES:
        raise ValueError(f"unknown car class {name!r}: the classes are {car_names()} (racing cars lists them)")
