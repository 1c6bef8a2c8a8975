"""The race as pure functions: ``reset(key, params)`` and ``step(key, state, actions, params)``.

This is the one implementation of a race: the physics, the incident detection and the
rules (finishing order, laps, retirements, positions, rewards: :mod:`racing_env.referee`).
Every function is pure JAX on pytrees, so it can be jitted, vmapped over thousands of
races and differentiated. The PettingZoo env (:mod:`racing_env.env`), the Gymnasium env
(:mod:`racing_env.single_agent`) and the vectorised env (:mod:`racing_env.vector`) are thin
faces over it; they validate their input, the core does not.

Shapes, for N cars and an observation of size ``O`` (:mod:`racing_env.observation`):

* ``RaceState.x (N, 6)``: the joint state ``[s, V, n, chi, ax, ay]`` per car (``s`` is
  cumulative on closed tracks, laps included);
* ``RaceState.status``: :class:`racing_env.referee.RaceStatus`, ``(N,)`` fields;
* ``RaceState.steps``: the number of steps taken, an int32 scalar;
* ``actions (N, 2)``: normalised jerks ``[jx, jy]``, clipped to ``[-1, 1]`` and scaled by each
  car's jerk limits (a car no longer racing ignores its action);
* observations ``(N, O)`` float32, rewards ``(N,)``, terminations and truncations ``(N,)`` bool.

This is the multi-agent form (every car acts; the JaxMARL convention of per-agent arrays).
The single-learner form with opponents inside the step, in gymnax's interface, is
:class:`racing_env.vector.GymnaxRace`. Guide: docs/env.md, "The race core (`racing_env.race`)".
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from racing_env.config import RETIRING_MODES, RaceConfig
from racing_env.contact import ContactModel, collide, overlapping, sweep
from racing_env.dynamics import S, V
from racing_env.game import RaceGame
from racing_env.observation import observation_scale, observe
from racing_env.physics import drive, off_track
from racing_env import starts as starts_lib
from racing_env.referee import REWARD_TERMS, RaceRules, RaceStatus, judge, positions
from racing_env.steward import (PIT_SPEED_RATIO, Steward, Verdicts, count_direction_changes, judge_contacts,
                                make_steward, penalty_seconds)
from racing_env.scenarios import scenario_starts
from racing_env.starts import Starts
from racing_env.track import Track

__all__ = [
    "RaceInfo",
    "RaceParams",
    "RaceState",
    "check_starts_behind",
    "draw_start",
    "finish_line",
    "next_start",
    "race_params",
    "race_rules",
    "reset",
    "start",
    "step",
]


class RaceParams(NamedTuple):
    """What stays fixed during a race (a pytree of arrays; one compiled step serves every
    value of them).

    Attributes:
        game: the race's :class:`RaceGame` (track, cars, cost weights, ``dt``).
        finish_s: the finish line's arc length [m].
        preview: the observation's preview distances ``(P,)`` [m].
        rules: incident rules and reward weights.
        max_steps: steps after which a race is truncated (int32 scalar).
        starts: the scenario's start distribution, which :func:`draw_start` draws from
            (:class:`racing_env.starts.Starts`).
        contact: how cars that meet interact (:class:`racing_env.contact.ContactModel`).
        steward: the rules incidents are judged by and their penalties
            (:class:`racing_env.steward.Steward`).
        obs_scale: ``(N, O)`` the weights each car's observation is multiplied by
            (:func:`racing_env.observation.observation_scale`; ones for physical units).
        rival_slots: the observation's rival blocks, of which only the shape is read (it is
            static under ``jit``): ``(K,)`` for the K nearest rivals
            (``RaceConfig.observed_rivals``), ``(0,)`` (the default) for every other car in
            index order (:mod:`racing_env.observation`).

    ``max_steps_in_episode`` (gymnax's name for the step limit) is ``max_steps``, and
    :meth:`replace` takes either name, as gymnax's params' ``replace`` does.
    """

    game: RaceGame
    finish_s: jax.Array
    preview: jax.Array
    rules: RaceRules
    max_steps: jax.Array
    starts: Starts
    contact: ContactModel
    steward: Steward
    obs_scale: jax.Array
    rival_slots: jax.Array = np.zeros(0)

    @property
    def observed_rivals(self) -> int | None:
        """The observation's nearest-rival blocks K, or None: every other car (static)."""
        return int(self.rival_slots.shape[0]) or None

    @property
    def max_steps_in_episode(self) -> jax.Array:
        """The step limit under gymnax's name: ``max_steps`` (int32 scalar)."""
        return self.max_steps

    def replace(self, **changes) -> "RaceParams":
        """A copy with ``changes`` (field names, or ``max_steps_in_episode`` for
        ``max_steps``), as flax's ``struct.dataclass.replace``."""
        if "max_steps_in_episode" in changes:
            if "max_steps" in changes:
                raise ValueError("give max_steps or max_steps_in_episode, not both")
            changes["max_steps"] = changes.pop("max_steps_in_episode")
        if "max_steps" in changes:
            changes["max_steps"] = jnp.asarray(changes["max_steps"], jnp.int32)
        return self._replace(**changes)


class RaceState(NamedTuple):
    """A race in progress: joint state ``x (N, 6)``, ``status`` and ``steps`` taken (int32)."""

    x: jax.Array
    status: RaceStatus
    steps: jax.Array


class RaceInfo(NamedTuple):
    """Per-car outcome of a step (or of the start), every field ``(N,)`` unless stated.

    Attributes:
        s: arc length [m] (cumulative on closed tracks).
        lap: completed laps (0 on open tracks), int32.
        position: race position, 1 = leading, int32.
        collided: the car touched another in this step.
        contact: ``(N, N)`` which cars each one touched (met inside the step with contact
            physics; overlapping at its end with ghost cars).
        off_track: the car's centre is beyond a track boundary.
        terms: ``(N, 8)`` reward terms, columns as :data:`racing_env.referee.REWARD_TERMS`.
        incidents: the steward's verdicts on the incidents that began in this step
            (:class:`racing_env.steward.Verdicts`, ``(N, N)`` fields).
    """

    s: jax.Array
    lap: jax.Array
    position: jax.Array
    collided: jax.Array
    contact: jax.Array
    off_track: jax.Array
    terms: jax.Array
    incidents: Verdicts


# --- the params of a configured race -------------------------------------------------------
def race_rules(config: RaceConfig) -> RaceRules:
    """The config's incident rules and reward weights as arrays."""
    reward = config.reward
    penalise = lambda mode: mode in ("penalty", "both")
    weights = [
        reward.progress,
        reward.position,
        reward.collision if penalise(config.on_collision) else 0.0,
        reward.off_track if penalise(config.on_off_track) else 0.0,
        reward.finish,
        reward.lead,
        reward.time,
        reward.fault if penalise(config.on_collision) else 0.0,
    ]
    return RaceRules(
        retire_on_collision=np.asarray(config.on_collision in RETIRING_MODES),
        retire_off_track=np.asarray(config.on_off_track in RETIRING_MODES),
        weights=np.asarray(weights, dtype=np.float64),
        spread=np.asarray(max(config.num_agents - 1, 1), dtype=np.float64),
    )


def finish_line(config: RaceConfig, track: Track) -> float:
    """The finish line's arc length [m]: ``race_distance``, else ``laps`` laps of a closed
    track or 20 m before the end of an open one.

    Raises ``ValueError`` when it lies beyond the end of an open track (the cars would drive
    off its end, never to finish).
    """
    if config.race_distance is not None:
        finish_s = float(config.race_distance)
    elif track.closed:
        finish_s = float(config.laps * track.length)
    else:
        finish_s = float(track.length - 20.0)
    if not math.isfinite(finish_s):
        raise ValueError(f"the finish line must be a finite arc length [m], got {finish_s!r}")
    if not track.closed and finish_s > track.length:
        raise ValueError(
            f"the finish line at s = {finish_s:g} m lies beyond the end of the open track "
            f"{track.name!r} ({track.length:g} m): give a race_distance <= {track.length:g} m"
        )
    return finish_s


def check_starts_behind(finish_s: float, x0: np.ndarray, scenario: str) -> None:
    """Raise ``ValueError`` unless every car of the start ``x0 (N, 6)`` is behind the finish
    line ``finish_s`` [m] (a car on or past it would finish on the first step)."""
    furthest = float(np.max(x0[:, S]))
    if not furthest < finish_s:
        raise ValueError(
            f"the finish line at s = {finish_s:g} m is not ahead of every start: scenario "
            f"{scenario!r} places a car at s = {furthest:g} m (use a longer track or race_distance)"
        )


def race_params(config: RaceConfig, track: Track, game: RaceGame, finish_s: float) -> RaceParams:
    """The :class:`RaceParams` of a configured race on ``track`` with ``game`` (the env's)
    and the finish line ``finish_s`` [m] (:func:`finish_line`)."""
    return RaceParams(
        game=game,
        finish_s=np.float64(finish_s),
        preview=np.asarray(config.preview_distances, dtype=np.float64),
        rules=race_rules(config),
        max_steps=np.int32(config.max_steps),
        starts=scenario_starts(config.scenario, track, config.num_agents, config.vehicles, finish_s),
        contact=ContactModel.create(config.contact, config.restitution, config.contact_friction),
        steward=make_steward(track, game.vehicles, config.num_agents, config.penalties, config.penalty_seconds,
                             config.severity_speed or 0.0, config.disqualify_after, config.rules,
                             incident_gap_steps=max(1, round(INCIDENT_GAP_S / config.dt))),
        obs_scale=observation_scale(track, game.vehicles, len(config.preview_distances), config.observed_rivals,
                                    config.observation_units),
        rival_slots=np.zeros(config.observed_rivals or 0),
    )


INCIDENT_GAP_S = 1.0
"""[s] Contact after this long without touching is a new incident (the steward's
``incident_gap`` in steps)."""


# --- the race --------------------------------------------------------------------------------
def _lap(params: RaceParams, s: jax.Array) -> jax.Array:
    track = params.game.track
    if track.closed:
        return jnp.maximum(jnp.floor(s / track.length), 0).astype(jnp.int32)
    return jnp.zeros(s.shape, jnp.int32)


def start(x0: jax.Array, params: RaceParams) -> tuple[RaceState, jax.Array, RaceInfo]:
    """A race starting from the joint state ``x0 (N, 6)``: its state, the observations
    ``(N, O)`` float32 and the start's :class:`RaceInfo` (no incidents, no rewards). The race
    runs in ``x0``'s dtype (as JAX holds it: float32 with ``jax_enable_x64`` off)."""
    x0 = jnp.asarray(x0)
    num = x0.shape[0]
    status = RaceStatus.start(num, jnp.result_type(x0))
    state = RaceState(x0, status, jnp.zeros((), jnp.int32))
    game = params.game
    obs = observe(x0, status.active, game.track, params.finish_s, params.preview,
                  params.observed_rivals, params.obs_scale).astype(jnp.float32)
    none = jnp.zeros(num, dtype=bool)
    info = RaceInfo(
        s=x0[:, S],
        lap=_lap(params, x0[:, S]),
        position=positions(x0[:, S], status.finished, status.place),
        collided=none,
        contact=jnp.zeros((num, num), dtype=bool),
        off_track=none,
        terms=jnp.zeros((num, len(REWARD_TERMS)), dtype=jnp.result_type(x0)),
        incidents=no_incidents(num, jnp.result_type(x0)),
    )
    return state, obs, info


def no_incidents(num: int, dtype) -> Verdicts:
    """The verdicts of a step without incidents, ``(N, N)`` fields."""
    nobody = jnp.zeros((num, num), dtype=bool)
    return Verdicts(nobody, nobody, jnp.zeros((num, num), jnp.int32), jnp.zeros((num, num), dtype))


def draw_start(key: jax.Array, params: RaceParams) -> jax.Array:
    """A start ``x0 (N, 6)`` drawn with ``key`` from the race's scenario (``params.starts``,
    :func:`racing_env.starts.draw`): the env's episodes draw theirs this way, so a key gives
    the same start in every face of the race."""
    return starts_lib.draw(key, params.starts, params.game.track, params.game.vehicles)[0]


def next_start(key: jax.Array, params: RaceParams) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """The next episode of a race whose key is ``key`` (:mod:`racing_env.starts`): ``(key
    carried on, x0 (N, 6), free, episode seed)``; ``free`` is false when an ``anywhere``
    scene found no start without overlapping cars. Every env's episodes begin here."""
    return starts_lib.next_start(key, params.starts, params.game.track, params.game.vehicles)


def reset(key: jax.Array, params: RaceParams) -> tuple[RaceState, jax.Array]:
    """A new race from a start drawn with ``key`` (:func:`draw_start`): ``(state, obs (N, O))``."""
    state, obs, _ = start(draw_start(key, params), params)
    return state, obs


def step(
    key: jax.Array, state: RaceState, actions: jax.Array, params: RaceParams
) -> tuple[RaceState, jax.Array, jax.Array, jax.Array, jax.Array, RaceInfo]:
    """Advance the cars still racing by their normalised ``actions (N, 2)`` (clipped to
    ``[-1, 1]``), enforce their limits, detect incidents and apply the rules.

    ``key`` is unused (the race is deterministic) and kept for the interface's sake.

    Returns ``(state, obs (N, O) float32, rewards (N,), terminations (N,), truncations (N,),
    info)``: a car terminates when it finishes or retires, and is truncated when it is still
    racing after ``params.max_steps`` steps. A car that was no longer racing before the step
    stays as it was, terminated, with zero reward.

    The race follows the dtype of ``state.x`` (float32 or float64; the params' float64
    constants do not widen it): the next state, the rewards and the reward terms have that
    dtype, so a ``lax.scan`` of steps carries one type whatever ``jax_enable_x64`` says.
    """
    del key
    game = params.game
    x, status = state.x, state.status
    dtype = jnp.result_type(x)
    steps = state.steps + 1
    active = status.active
    # a car out of the race leaves no wake (only cars with drag feel one)
    moving = game.replace(racing=active) if game.drag else game
    x_next = jnp.where(active[:, None], serve_drive_throughs(x, drive(moving, x, actions), status.serving, game), x)
    hit = sweep(x, x_next, active, game.vehicles, game.track)
    if params.contact.physics:
        x_next = collide(x, x_next, hit, game.vehicles, params.contact, game.track, game.dt)
        contact = hit.touch
    else:
        contact = overlapping(x_next, active, game.vehicles, game.track)
    outside = off_track(x_next, game.track) & active
    collided = contact.any(axis=1)
    verdicts = judge_contacts(x, x_next, hit, contact, status.last_contact, steps, outside, status.direction_changes,
                              game.vehicles, params.steward, game.track)
    new_faults = jnp.sum(verdicts.fault, axis=1, dtype=jnp.int32)
    status = steward_status(status, verdicts, new_faults, contact, steps, x, x_next, params.steward, game.track)
    disqualified = (params.steward.disqualify_after > 0) & (status.faults >= params.steward.disqualify_after)
    verdict = judge(x[:, S], x_next[:, S], status, collided, outside, steps, game.dt, params.finish_s,
                    params.rules, speed=x_next[:, V], new_faults=new_faults, disqualified=disqualified)
    # the status keeps its dtypes (finish_time is the state's float)
    new_status = jax.tree_util.tree_map(lambda new, old: new.astype(old.dtype), verdict.status, status)
    # observed with the cars still racing after this step's verdict
    obs = observe(x_next, new_status.active, game.track, params.finish_s, params.preview,
                  params.observed_rivals, params.obs_scale).astype(jnp.float32)
    info = RaceInfo(
        s=x_next[:, S],
        lap=_lap(params, x_next[:, S]),
        position=verdict.positions,
        collided=collided,
        contact=contact,
        off_track=outside,
        terms=verdict.terms.astype(dtype),
        incidents=verdicts._replace(closing=verdicts.closing.astype(dtype)),
    )
    truncations = new_status.active & (steps >= params.max_steps)
    terminations = ~new_status.active
    return RaceState(x_next, new_status, steps), obs, verdict.reward.astype(dtype), terminations, truncations, info


def serve_drive_throughs(x: jax.Array, x_next: jax.Array, serving: jax.Array, game: RaceGame) -> jax.Array:
    """``x_next (N, 6)`` with the speed of every car serving a drive-through (``serving (N,)``
    metres left) held to :data:`racing_env.steward.PIT_SPEED_RATIO` of its top speed, slowing
    down to it at most at its gg radius."""
    vehicles = game.vehicles
    v = x[:, V]
    pit_speed = PIT_SPEED_RATIO * vehicles.v_max
    cap = jnp.maximum(pit_speed, v - vehicles.rho(jnp.maximum(v, 0.0)) * game.dt)
    limited = jnp.where(serving > 0.0, jnp.minimum(x_next[:, V], cap), x_next[:, V])
    return x_next.at[:, V].set(limited.astype(jnp.result_type(x_next)))


def steward_status(status: RaceStatus, verdicts: Verdicts, new_faults: jax.Array, contact: jax.Array,
                   steps: jax.Array, x: jax.Array, x_next: jax.Array, steward: Steward, track: Track
                   ) -> RaceStatus:
    """The status's steward fields after a step: this step's penalties and faults added, the
    drive-throughs served by the metres driven in the step (at most the pit speed, by
    :func:`serve_drive_throughs`, after the first step of braking down to it), each pair's
    last contact, each car's defending moves (:func:`racing_env.steward.count_direction_changes`).
    ``new_faults (N,)``: the incidents each car answers for that began in the step
    (``verdicts.fault`` summed over its row)."""
    dtype = status.penalty.dtype
    driven = jnp.where(status.serving > 0.0, x_next[:, S] - x[:, S], 0.0)
    serving = jnp.maximum(status.serving - driven, 0.0) + new_faults * steward.drive_through
    last_move, changes = count_direction_changes(x_next, status.active, status.last_move, status.direction_changes,
                                                 steward, track)
    return status._replace(
        penalty=(status.penalty + penalty_seconds(verdicts, steward)).astype(dtype),
        faults=status.faults + new_faults,
        serving=serving.astype(dtype),
        last_contact=jnp.where(contact, steps, status.last_contact).astype(jnp.int32),
        last_move=last_move,
        direction_changes=changes,
    )
