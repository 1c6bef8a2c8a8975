"""The steward: who caused a contact, and what it costs them. Pure JAX, inside the race's step.

An **incident** is a run of contact steps between two cars: it begins at a contact step
when the pair has not touched for :attr:`Steward.incident_gap` steps, and it is judged once,
at that step, from the cars' states at the step's start (what each driver was doing when
they met) and the contact's geometry (:class:`racing_env.contact.Sweep`). The rules, each in
:data:`RULES` and written out with drawings in docs/rules.md:

* ``rear-end``: the footprints met end to end (the contact normal is a car's length axis):
  the car behind answers;
* ``brake-test``: a rear-end where the car ahead was braking harder than
  :attr:`Steward.brake_decel` at a speed under :attr:`Steward.brake_ratio` times its own
  quasi-steady-state speed on the centre line there (no corner asked for that braking): the
  car ahead answers;
* ``moved-across``: the footprints met side to side and one car was moving across towards
  the other (lateral speed relative to the track, towards the other car) faster than
  :attr:`Steward.across_speed`, and faster by that much than the other towards it: it
  answers;
* ``squeeze``: a ``moved-across`` whose victim had less than a car's width between itself
  and the track edge on its far side, or left the track in the contact: the mover answers;
* ``weaving`` (optional: not in :data:`DEFAULT_RULES`): a car defending on a straight (a car
  behind it within :attr:`Steward.defend_gap`, the centre line's curvature under
  :attr:`Steward.straight_kappa`) changed direction more than once, moving across faster
  than :attr:`Steward.across_speed` one way, then the other, then back again; a contact
  between it and a car behind it is its fault, whatever else the scene is. The moves are
  counted in :attr:`racing_env.referee.RaceStatus.direction_changes` by
  :func:`count_direction_changes`.

A contact that no rule pins on either car is a ``racing-incident``: nobody answers. A rule
left out of :attr:`Steward.rules_on` makes its cases racing incidents (``brake-test`` and
``squeeze`` fall back to ``rear-end`` and ``moved-across``).

**Penalties** (:data:`PENALTY_MODES`), for each at-fault incident: ``time`` adds
:attr:`Steward.seconds` to the car's race time (times the closing speed over
:attr:`Steward.severity_speed` when that is > 0), which orders the finished cars; a
``drive-through`` makes the car drive :attr:`Steward.drive_through` metres at
:data:`PIT_SPEED_RATIO` of its top speed; ``disqualify`` retires a car at its
:attr:`Steward.disqualify_after`-th at-fault incident; ``none`` records the verdicts only.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from racing_env.contact import Sweep
from racing_env.dynamics import AX, CHI, N_LAT, S, V
from racing_env.track import Track
from racing_env.vehicle import VehicleParams

RULES = ("rear-end", "brake-test", "moved-across", "squeeze", "weaving")
"""The named rules, in the order of :attr:`Steward.rules_on`."""
DEFAULT_RULES = RULES[:4]
"""The rules a race is judged by unless it names its own: all but ``weaving``."""
VERDICTS = ("racing-incident",) + RULES
"""What an incident is judged to be: index 0 nobody answers, else the rule that decided it
(the codes of :attr:`Verdicts.rule`)."""
PENALTY_MODES = ("time", "drive-through", "disqualify", "none")
PIT_SPEED_RATIO = 0.5
"""A car serving a drive-through drives at most this share of its top speed."""

RACING_INCIDENT, REAR_END, BRAKE_TEST, MOVED_ACROSS, SQUEEZE, WEAVING = range(len(VERDICTS))


@functools.partial(jax.tree_util.register_dataclass, data_fields=[
    "rules_on", "seconds", "severity_speed", "drive_through", "disqualify_after", "incident_gap", "across_speed",
    "brake_decel", "brake_ratio", "defend_gap", "straight_kappa", "v_line"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class Steward:
    """The rules a race is judged by and their penalties (arrays: one compiled step serves
    every value). Made by :func:`make_steward` from a :class:`racing_env.config.RaceConfig`.

    Attributes:
        rules_on: ``(5,)`` bool, which of :data:`RULES` apply.
        seconds: [s] the time penalty per at-fault incident (0 unless ``penalties="time"``).
        severity_speed: [m/s] the closing speed of a 1x time penalty; 0: every penalty is
            ``seconds`` whatever the speed.
        drive_through: [m] the distance of a drive-through (0 unless
            ``penalties="drive-through"``).
        disqualify_after: the at-fault incidents that retire a car (0: never).
        incident_gap: steps without contact after which a new contact is a new incident.
        across_speed: [m/s] the lateral speed that counts as moving across.
        brake_decel: [m/s^2] the deceleration beyond which braking may be a brake test.
        brake_ratio: a brake test is braking at under this share of the line's speed.
        defend_gap: [m] a car with another racing car this close behind it defends.
        straight_kappa: [1/m] the centre line's curvature under which the track is straight.
        v_line: ``(N, M)`` [m/s] each car's quasi-steady-state speed on the centre line at
            the track's grid points.
    """

    rules_on: jax.Array
    seconds: jax.Array
    severity_speed: jax.Array
    drive_through: jax.Array
    disqualify_after: jax.Array
    incident_gap: jax.Array
    across_speed: jax.Array
    brake_decel: jax.Array
    brake_ratio: jax.Array
    defend_gap: jax.Array
    straight_kappa: jax.Array
    v_line: jax.Array


def check_stewarding(penalties: str, penalty_seconds: float, disqualify_after: int, rules: Sequence[str]) -> None:
    """Refuse an unknown penalty mode or rule, a negative or non-finite penalty and a
    disqualification count below 1."""
    if penalties not in PENALTY_MODES:
        raise ValueError(f"penalties must be one of {PENALTY_MODES}, got {penalties!r}")
    if isinstance(penalty_seconds, bool) or not isinstance(penalty_seconds, (int, float, np.number)) or not (
            np.isfinite(penalty_seconds) and penalty_seconds >= 0):
        raise ValueError(f"penalty_seconds must be a finite number of seconds >= 0, got {penalty_seconds!r}")
    if isinstance(disqualify_after, bool) or not isinstance(disqualify_after, (int, np.integer)) or disqualify_after < 1:
        raise ValueError(f"disqualify_after must be an integer >= 1 (at-fault incidents), got {disqualify_after!r}")
    if isinstance(rules, str):
        raise ValueError(f"rules must be a sequence of rule names from {RULES}, got the string {rules!r}")
    unknown = [rule for rule in rules if rule not in RULES]
    if unknown:
        raise ValueError(f"unknown rule(s) {unknown}; the rules are {RULES}")


@functools.lru_cache(maxsize=64)
def _line_speeds(track: Track, vehicle_key: tuple) -> np.ndarray:
    from racing_env import limits

    vehicle = VehicleParams.from_key(vehicle_key)
    profile = limits.speed_profile(limits.centerline(track), vehicle,
                                   v_start=None if track.closed else float(vehicle.v_max))
    return np.asarray(profile.v, dtype=np.float64)


#: The steward's distances [m], lateral speed [m/s] and curvature [1/m] on a full-size
#: circuit (:func:`make_steward` scales them to a model of one).
DRIVE_THROUGH, ACROSS_SPEED, DEFEND_GAP, STRAIGHT_KAPPA = 400.0, 0.5, 20.0, 1.0 / 300.0


def make_steward(track: Track, vehicles: VehicleParams, num_cars: int, penalties: str = "time",
                 penalty_seconds: float = 5.0, severity_speed: float = 0.0, disqualify_after: int = 3,
                 rules: Sequence[str] = DEFAULT_RULES, drive_through: float | None = None, incident_gap_steps: int = 10,
                 across_speed: float | None = None, brake_decel: float = 4.0, brake_ratio: float = 0.8,
                 defend_gap: float | None = None, straight_kappa: float | None = None) -> Steward:
    """The :class:`Steward` of a race of ``num_cars`` cars ``vehicles`` (stacked or one for
    all) on ``track``, with the penalty mode ``penalties`` (:data:`PENALTY_MODES`).

    ``drive_through``, ``across_speed``, ``defend_gap`` and ``straight_kappa`` left out are
    the full-size figures (:data:`DRIVE_THROUGH`, ...) for a track at ``track.scale`` k: the
    distances k times, the lateral speed ``sqrt(k)`` times (a model's speeds at the same
    accelerations) and the curvature over k, so that a 1:10 model's race is judged as the
    full-size race it models. The deceleration ``brake_decel`` is the same at any scale."""
    check_stewarding(penalties, penalty_seconds, disqualify_after, rules)
    k = float(track.scale)
    drive_through = DRIVE_THROUGH * k if drive_through is None else drive_through
    across_speed = ACROSS_SPEED * np.sqrt(k) if across_speed is None else across_speed
    defend_gap = DEFEND_GAP * k if defend_gap is None else defend_gap
    straight_kappa = STRAIGHT_KAPPA / k if straight_kappa is None else straight_kappa
    cars = [car.key() for car in vehicles.cars(num_cars)]
    return Steward(
        rules_on=np.asarray([rule in rules for rule in RULES]),
        seconds=np.float64(penalty_seconds if penalties == "time" else 0.0),
        severity_speed=np.float64(severity_speed),
        drive_through=np.float64(drive_through if penalties == "drive-through" else 0.0),
        disqualify_after=np.int32(disqualify_after if penalties == "disqualify" else 0),
        incident_gap=np.int32(incident_gap_steps),
        across_speed=np.float64(across_speed),
        brake_decel=np.float64(brake_decel),
        brake_ratio=np.float64(brake_ratio),
        defend_gap=np.float64(defend_gap),
        straight_kappa=np.float64(straight_kappa),
        v_line=np.stack([_line_speeds(track, car) for car in cars]),
    )


class Verdicts(NamedTuple):
    """The incidents that began in a step; ``(N, N)`` fields, the pair (i, j) in row i.

    Attributes:
        incident: an incident between i and j begins in this step (symmetric).
        fault: car i answers for its incident with j.
        rule: the verdict (index into :data:`VERDICTS`; symmetric, 0 without an incident).
        closing: the closing speed [m/s] at contact (symmetric, 0 without an incident).
    """

    incident: jax.Array
    fault: jax.Array
    rule: jax.Array
    closing: jax.Array


def _symmetric(upper_value: jax.Array, upper: jax.Array) -> jax.Array:
    value = jnp.where(upper, upper_value, jnp.zeros_like(upper_value))
    return value + value.T


def judge_contacts(x0: jax.Array, x1: jax.Array, hit: Sweep, contact: jax.Array, last_contact: jax.Array,
                   step: jax.Array, outside: jax.Array, direction_changes: jax.Array, vehicles: VehicleParams,
                   steward: Steward, track: Track) -> Verdicts:
    """Judge the incidents that begin in the step from ``x0`` to ``x1`` (joint states
    ``(N, 6)``): ``contact (N, N)`` the step's contacts, ``last_contact (N, N)`` the last step
    each pair touched before, ``step`` this step's number, ``outside (N,)`` the cars off the
    track after the step, ``direction_changes (N,)`` each car's changes of direction while
    defending on the straight it is on, at the step's start (:func:`count_direction_changes`)."""
    num = x0.shape[0]
    upper = jnp.triu(jnp.ones((num, num), dtype=bool), 1)
    incident = contact & (step - last_contact > steward.incident_gap)
    on = steward.rules_on
    s, v, n, chi, ax = x0[:, S], x0[:, V], x0[:, N_LAT], x0[:, CHI], x0[:, AX]
    # seen from car i (row) of the pair (i, j)
    ahead = track.wrap_ds(s[None, :] - s[:, None])  # > 0: j is ahead of i
    end_to_end = (hit.axis == 0) | (hit.axis == 2)
    v_line = jax.vmap(track._interp)(steward.v_line, s)
    brake_testing = (ax < -steward.brake_decel) & (v < steward.brake_ratio * v_line)
    j_ahead, i_ahead = ahead > 0.0, ahead < 0.0
    rear = end_to_end & on[0]
    j_brake_test = rear & on[1] & j_ahead & brake_testing[None, :]
    i_brake_test = rear & on[1] & i_ahead & brake_testing[:, None]
    i_rear_end = rear & j_ahead & ~j_brake_test
    j_rear_end = rear & i_ahead & ~i_brake_test

    towards = jnp.sign(n[None, :] - n[:, None])  # j lies to the left (+1) or right (-1) of i
    lateral = v * jnp.sin(chi)
    i_across = lateral[:, None] * towards
    j_across = -lateral[None, :] * towards
    i_moves = ~end_to_end & (i_across > steward.across_speed) & (i_across - j_across > steward.across_speed)
    j_moves = ~end_to_end & (j_across > steward.across_speed) & (j_across - i_across > steward.across_speed)
    widths = jnp.broadcast_to(jnp.asarray(vehicles.width), (num,))
    room_left = track.width_left_at(x1[:, S]) - x1[:, N_LAT] - 0.5 * widths
    room_right = track.width_right_at(x1[:, S]) + x1[:, N_LAT] - 0.5 * widths
    squeezed = lambda room: (room < widths) | outside  # noqa: E731 - (N,) per car
    j_squeezed = jnp.where(towards > 0, squeezed(room_left)[None, :], squeezed(room_right)[None, :])
    i_squeezed = jnp.where(towards > 0, squeezed(room_right)[:, None], squeezed(room_left)[:, None])
    i_squeezes = i_moves & on[3] & j_squeezed
    j_squeezes = j_moves & on[3] & i_squeezed
    i_crosses = i_moves & on[2] & ~i_squeezes
    j_crosses = j_moves & on[2] & ~j_squeezes

    # a weaver ahead answers for any contact with the car behind it, whatever the scene
    weaving = on[4] & (direction_changes > 1)
    j_weaves = j_ahead & weaving[None, :]
    i_weaves = i_ahead & weaving[:, None]
    i_rear_end, i_brake_test, i_crosses, i_squeezes = (
        rule & ~j_weaves for rule in (i_rear_end, i_brake_test, i_crosses, i_squeezes))
    j_rear_end, j_brake_test, j_crosses, j_squeezes = (
        rule & ~i_weaves for rule in (j_rear_end, j_brake_test, j_crosses, j_squeezes))

    rule = jnp.select([i_weaves | j_weaves, i_rear_end | j_rear_end, i_brake_test | j_brake_test,
                       i_crosses | j_crosses, i_squeezes | j_squeezes],
                      [WEAVING, REAR_END, BRAKE_TEST, MOVED_ACROSS, SQUEEZE], RACING_INCIDENT)
    i_fault = i_weaves | i_rear_end | i_brake_test | i_crosses | i_squeezes
    j_fault = j_weaves | j_rear_end | j_brake_test | j_crosses | j_squeezes
    live = incident & upper
    fault = (live & i_fault) | (live & j_fault).T
    return Verdicts(
        incident=incident,
        fault=fault,
        rule=_symmetric(jnp.where(live, rule, RACING_INCIDENT).astype(jnp.int32), upper),
        closing=_symmetric(jnp.where(live, hit.closing, 0.0), upper),
    )


def count_direction_changes(x: jax.Array, active: jax.Array, last_move: jax.Array, changes: jax.Array,
                            steward: Steward, track: Track) -> tuple[jax.Array, jax.Array]:
    """Each car's defending moves after a step that ended at ``x (N, 6)``: ``(last_move,
    changes)``, both ``(N,)`` int32. A car defends when another racing car (``active (N,)``)
    is behind it within :attr:`Steward.defend_gap` on a straight (the centre line's
    curvature at the car under :attr:`Steward.straight_kappa`); while it does, a move across
    the track faster than :attr:`Steward.across_speed` (``last_move``: -1 right, +1 left)
    opposite to its last one adds a change of direction. A car that stops defending starts
    again from none."""
    s, lateral = x[:, S], x[:, V] * jnp.sin(x[:, CHI])
    behind = track.wrap_ds(s[:, None] - s[None, :])  # > 0: j is behind i
    chased = (active[None, :] & ~jnp.eye(s.shape[0], dtype=bool) & (behind > 0.0) & (behind < steward.defend_gap)
              ).any(axis=1)
    defending = active & chased & (jnp.abs(track.kappa_at(s)) < steward.straight_kappa)
    move = jnp.where(jnp.abs(lateral) > steward.across_speed, jnp.sign(lateral), 0.0).astype(jnp.int32)
    turned = (move != 0) & (last_move != 0) & (move != last_move)
    last_move = jnp.where(defending, jnp.where(move != 0, move, last_move), 0)
    changes = jnp.where(defending, changes + turned, 0)
    return last_move.astype(jnp.int32), changes.astype(jnp.int32)


def penalty_seconds(verdicts: Verdicts, steward: Steward) -> jax.Array:
    """``(N,)`` the time penalties [s] the incidents of ``verdicts`` cost each car."""
    scale = jnp.where(steward.severity_speed > 0.0, verdicts.closing / jnp.where(
        steward.severity_speed > 0.0, steward.severity_speed, 1.0), 1.0)
    return jnp.sum(jnp.where(verdicts.fault, steward.seconds * scale, 0.0), axis=1)
