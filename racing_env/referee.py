"""The race's rules after each physics step: finishing order, retirements, positions and
rewards, as pure JAX functions of ``(N,)`` arrays.

The environment calls :func:`judge` inside the same jitted call as the physics, so a step
crosses from Python to XLA once and reads back a few packed arrays. An incident term
without an incident is 0.0, and a lone car (N = 1) that finishes gets the whole finish
weight. Rewards and incidents: docs/env.md.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from racing_env.precision import canonical


#: Names of the reward terms, in the order of :attr:`Judgement.terms`' columns.
REWARD_TERMS = ("progress", "position", "collision", "off_track", "finish", "lead", "time", "fault")


class RaceStatus(NamedTuple):
    """Where each car stands in the race; every field has shape ``(N,)``.

    Attributes:
        active: still racing (neither finished nor retired).
        finished: crossed the finish line.
        out: retired by an incident rule (``on_collision`` / ``on_off_track``).
        place: finishing place, 1 = winner; 0 until finished (int32).
        finish_time: time of the crossing [s], interpolated inside the step; NaN until
            finished.
        penalty: time penalties [s] the steward gave the car (:mod:`racing_env.steward`);
            the finished cars are placed by ``finish_time + penalty``.
        faults: the incidents the car answered for (int32).
        serving: [m] of drive-through penalty the car has still to drive.
        last_contact: ``(N, N)`` the last step in which each pair touched (int32;
            :data:`NEVER` before the first).
        last_move: the direction of the car's last move across the track while defending on
            the straight it is on (-1 right, +1 left, 0 none; int32;
            :func:`racing_env.steward.count_direction_changes`).
        direction_changes: the changes of direction it made defending there (int32; the
            ``weaving`` rule's count).
    """

    active: jax.Array
    finished: jax.Array
    out: jax.Array
    place: jax.Array
    finish_time: jax.Array
    penalty: jax.Array
    faults: jax.Array
    serving: jax.Array
    last_contact: jax.Array
    last_move: jax.Array
    direction_changes: jax.Array

    @classmethod
    def start(cls, num: int, dtype) -> "RaceStatus":
        """The status of ``num`` cars on the grid: all racing, no penalties; floats in ``dtype``
        (as JAX holds it: float32 with ``jax_enable_x64`` off)."""
        dtype = canonical(dtype)
        return cls(
            active=jnp.ones(num, dtype=bool),
            finished=jnp.zeros(num, dtype=bool),
            out=jnp.zeros(num, dtype=bool),
            place=jnp.zeros(num, dtype=jnp.int32),
            finish_time=jnp.full(num, jnp.nan, dtype=dtype),
            penalty=jnp.zeros(num, dtype=dtype),
            faults=jnp.zeros(num, dtype=jnp.int32),
            serving=jnp.zeros(num, dtype=dtype),
            last_contact=jnp.full((num, num), NEVER, dtype=jnp.int32),
            last_move=jnp.zeros(num, dtype=jnp.int32),
            direction_changes=jnp.zeros(num, dtype=jnp.int32),
        )


#: The ``last_contact`` of a pair that never touched: far enough back that its first
#: contact begins an incident whatever the incident gap.
NEVER = -(2**30)


class RaceRules(NamedTuple):
    """The incident rules and reward weights of a race (arrays, so one compiled step
    serves every configuration).

    Attributes:
        retire_on_collision, retire_off_track: whether an incident retires the car (bool).
        weights: ``(8,)`` reward weights in the order of :data:`REWARD_TERMS`; an incident
            term whose mode gives no penalty has weight 0.
        spread: ``max(N - 1, 1)`` as a float64 scalar, the divisor of the position and
            finish terms. An argument rather than a constant: XLA turns a division by a
            constant into a multiplication by its reciprocal, which rounds differently.
    """

    retire_on_collision: jax.Array
    retire_off_track: jax.Array
    weights: jax.Array
    spread: jax.Array


class Judgement(NamedTuple):
    """One step's outcome for every car.

    Attributes:
        status: the :class:`RaceStatus` after the step.
        positions: race positions, 1 = leading, ``(N,)`` int32.
        crossed: crossed the finish line in this step, ``(N,)`` bool.
        terms: reward terms ``(N, 8)``, columns as :data:`REWARD_TERMS`.
        reward: their sum, ``(N,)``.
    """

    status: RaceStatus
    positions: jax.Array
    crossed: jax.Array
    terms: jax.Array
    reward: jax.Array


def _precedes(key: jax.Array) -> jax.Array:
    """``before[i, j]``: car j sorts before car i by ``key`` (ties by index, as a stable sort)."""
    index = jnp.arange(key.shape[0])
    return (key[None, :] < key[:, None]) | ((key[None, :] == key[:, None]) & (index[None, :] < index[:, None]))


def positions(s: jax.Array, finished: jax.Array, place: jax.Array) -> jax.Array:
    """Race positions ``(N,)`` (1 = leading): finished cars first, by place, then the others
    by arc length ``s`` [m]; equal keys keep the cars' order. Comparisons only, so exact in
    any precision."""
    both_finished = finished[:, None] & finished[None, :]
    both_racing = ~finished[:, None] & ~finished[None, :]
    before = (finished[None, :] & ~finished[:, None]) | (both_finished & _precedes(place)) | (
        both_racing & _precedes(-s))
    return 1 + jnp.sum(before, axis=1, dtype=jnp.int32)


def places(finished: jax.Array, race_time: jax.Array) -> jax.Array:
    """Finishing places ``(N,)`` int32 (1 = winner, 0 = not finished) of the ``finished`` cars
    by their ``race_time`` [s] (finish time plus penalties; ties by index)."""
    ahead = _precedes(jnp.where(finished, race_time, jnp.inf)) & finished[None, :]
    return jnp.where(finished, 1 + jnp.sum(ahead, axis=1, dtype=jnp.int32), 0)


def _standings(
    s_prev: jax.Array,
    s: jax.Array,
    acting: jax.Array,
    finished: jax.Array,
    finish_time: jax.Array,
    speed: jax.Array,
    time: jax.Array,
    t_prev: jax.Array,
    dt: float,
    finish_s: jax.Array,
) -> jax.Array:
    """Where every car stands at each of the times ``time (M,)`` [s] inside the step from
    ``t_prev`` to ``t_prev + dt``, ``(M, N)`` [m], for the lead term.

    A car that has finished by then counts as carrying on from the line at its speed after
    the step (``finish_s + V (time - finish_time)``; it is frozen from then on, so every
    later step sees the same speed). Before that, a car racing in this step moves linearly
    from ``s_prev`` to ``s`` (as its crossing time is interpolated), and any other car
    stands at ``s``."""
    time = time[:, None]
    carried_on = finish_s + speed * (time - jnp.nan_to_num(finish_time))
    moving = s_prev + (s - s_prev) * ((time - t_prev) / dt)
    return jnp.where(finished & (time >= finish_time), carried_on, jnp.where(acting, moving, s))


def _leads(standings: jax.Array, rivals: jax.Array) -> jax.Array:
    """Car i's lead [m] over the furthest of its rivals, from row i of ``standings (N, N)``
    (where every car stands when car i's lead is taken); ``rivals (N,)`` bool: the cars that
    count. ``(N,)``; 0 without a rival."""
    others = rivals[None, :] & ~jnp.eye(standings.shape[0], dtype=bool)
    best = jnp.max(jnp.where(others, standings, -jnp.inf), axis=1)
    return jnp.where(others.any(axis=1), jnp.diagonal(standings) - best, 0.0)


def judge(
    s_prev: jax.Array,
    s: jax.Array,
    status: RaceStatus,
    collided: jax.Array,
    outside: jax.Array,
    step: jax.Array,
    dt: float,
    finish_s: jax.Array,
    rules: RaceRules,
    speed: jax.Array | None = None,
    new_faults: jax.Array | None = None,
    disqualified: jax.Array | None = None,
) -> Judgement:
    """Apply the rules to one step of the cars that were active at its start.

    Args:
        s_prev, s: arc lengths [m] before and after the step, ``(N,)``.
        status: the status before the step.
        collided, outside: incidents detected after the step (active cars only), ``(N,)``.
        step: the number of the step just taken (1 for the first), a scalar.
        dt: the step length [s].
        finish_s: the finish line's arc length [m].
        rules: incident rules and reward weights.
        speed: speeds ``V`` [m/s] after the step, ``(N,)``; the lead term extrapolates
            finished cars with them. None: as if finished cars stood at the line.
        new_faults: ``(N,)`` the incidents each car answers for that began in this step
            (the ``fault`` term); None: none.
        disqualified: ``(N,)`` cars the steward retires in this step; None: none.

    The status's steward fields (``penalty``, ``faults``, ``serving``, ``last_contact``)
    are this step's already; finished cars are placed by ``finish_time + penalty``.
    """
    num = s.shape[0]
    acting = status.active
    crossed = acting & (s >= finish_s)
    # Crossing time interpolated inside the step; the finished cars are placed by it plus
    # their penalties (ties by index).
    frac = (finish_s - s_prev) / jnp.maximum(s - s_prev, 1e-9)
    t_cross = ((step - 1) + jnp.clip(frac, 0.0, 1.0)) * dt
    finish_time = jnp.where(crossed, t_cross, status.finish_time)
    finished = status.finished | crossed
    place = places(finished, finish_time + status.penalty)

    disqualified = jnp.zeros(num, dtype=bool) if disqualified is None else disqualified
    newly_out = acting & ~crossed & (
        (collided & rules.retire_on_collision) | (outside & rules.retire_off_track) | disqualified
    )
    out = status.out | newly_out
    active = acting & ~finished & ~out
    pos = positions(s, finished, place)

    # Lead over the furthest rival still in the race (finished or racing), with the same
    # rivals before and after the step, so that a car's terms telescope. Before: at the
    # step's start. After: at its end, or at the car's own crossing time if it finishes in
    # this step (its last term), so its final lead is its margin at the line.
    speed = jnp.zeros_like(s) if speed is None else speed
    rivals = ~out
    t_prev = (step - 1) * dt
    lead_before = _leads(_standings(s_prev, s_prev, acting, status.finished, status.finish_time, speed,
                                    jnp.full(num, t_prev), t_prev, dt, finish_s), rivals)
    lead_time = jnp.where(crossed, t_cross, step * dt)
    lead_after = _leads(_standings(s_prev, s, acting, finished, finish_time, speed, lead_time, t_prev, dt,
                                   finish_s), rivals)

    spread, w = rules.spread, rules.weights
    # N = 1: the lone car wins (the race's formula would give it (1 - 1) / 1 = 0)
    finish = w[4] * crossed * (num - place) / spread if num > 1 else w[4] * crossed
    terms = jnp.stack(
        [
            w[0] * (s - s_prev),
            w[1] * (((num - pos) - (pos - 1)) / spread),
            # +0.0 without an incident (a negative weight times 0 is -0.0)
            jnp.where(collided, w[2], 0.0),
            jnp.where(outside, w[3], 0.0),
            finish,
            jnp.where(acting & (w[5] != 0.0), w[5] * (lead_after - lead_before), 0.0),  # 0.0, not -0.0, when off
            # the time raced in this step: all of it, or up to the crossing (the sum is the finish time)
            jnp.where(acting & (w[6] != 0.0), w[6] * (jnp.where(crossed, jnp.clip(frac, 0.0, 1.0), 1.0) * dt), 0.0),
            # +0.0 without a fault
            jnp.zeros(num) if new_faults is None else jnp.where(new_faults > 0, w[7] * new_faults, 0.0),
        ],
        axis=1,
    )
    # summed in the terms' order
    reward = ((((((terms[:, 0] + terms[:, 1]) + terms[:, 2]) + terms[:, 3]) + terms[:, 4]) + terms[:, 5])
              + terms[:, 6]) + terms[:, 7]
    new_status = status._replace(active=active, finished=finished, out=out, place=place, finish_time=finish_time)
    return Judgement(new_status, pos, crossed, terms, reward)
