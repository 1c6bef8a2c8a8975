"""Where a race begins: every scenario's start distribution as arrays, drawn with JAX.

One definition of a start serves every face of the race: the PettingZoo env, the Gymnasium
view, the vectorised env (inside its compiled step, for every race that autoresets) and the
gymnax face. A scenario (:mod:`racing_env.scenarios`) is a :class:`Starts`, a pytree of
arrays; :func:`draw` turns a JAX key into a joint start ``x0 (N, 6)``:

* the grid (``grid``; ``paper`` and ``side_by_side`` are fixed grids): the slots in car
  order, shuffled over the cars and jittered per draw, speeds capped to ``[0, 0.95 v_max]``;
* a close-quarters scene anywhere on the lap (``anywhere``, and the solver studies'
  :func:`racing_env.scenarios.random_scenes`): a reference arc length drawn uniformly from
  ``s_range``, every car ``0..spread`` metres behind it at a lateral offset drawn uniformly
  inside the track ``margin`` metres from either edge, at a speed drawn from ``speed``
  (capped at ``0.95 v_max``); positions are drawn again, up to :data:`MAX_TRIES` times,
  until no two footprints overlap by the env's own test.

Seeds and episodes. An env holds one key per race. :func:`key_from_seed` makes it from a
reset's seed; every episode then takes :func:`next_episode` of it: the key carried on and the
episode's own key, which draws the start (:func:`draw`) and the episode's integer seed for
seeded opponents (:func:`episode_seed`). A race seeded ``s`` therefore runs the same episodes
in every face, in a batch of any size, and ``make_scenario(name, ..., seed=s)`` is the start
the env's ``reset(seed=s)`` draws.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from racing_env.dynamics import N_LAT, S, STATE_DIM, V
from racing_env.physics import footprint_overlap
from racing_env.precision import canonical
from racing_env.track import Track
from racing_env.vehicle import VehicleParams

__all__ = ["MAX_TRIES", "SEED_BOUND", "Starts", "draw", "draw_episode", "episode_seed", "fresh_key", "key_from_seed",
           "next_episode", "next_start"]

#: Draws of an ``anywhere`` scene's positions before :func:`draw` reports that it found no
#: start without overlapping cars.
MAX_TRIES = 1000
#: Episode seeds lie in ``[0, SEED_BOUND)``: an int32, as NumPy's generators and every
#: seeded agent accept.
SEED_BOUND = 2**31 - 1


@functools.partial(jax.tree_util.register_dataclass, data_fields=[
    "slots", "shuffle", "jitter", "capped", "s_range", "spread", "margin", "speed"], meta_fields=["anywhere"])
@dataclasses.dataclass(frozen=True)
class Starts:
    """A scenario's start distribution (a pytree of arrays, part of
    :class:`racing_env.race.RaceParams`; one compiled draw serves every value of the arrays,
    and ``anywhere``, a Python bool, picks which draw is compiled).

    Attributes:
        slots: ``(N, 6)`` the grid's slots in car order (slot k's ``s``, ``V``, ``n``); the
            fixed start of ``paper`` and ``side_by_side``.
        shuffle: whether a grid draw permutes the cars over the slots (bool scalar).
        jitter: ``(3,)`` half-widths [m, m, m/s] of the uniform jitter of ``s``, ``n``, ``V``.
        capped: whether a grid draw caps the speeds to ``[0, 0.95 v_max]`` (a fixed start
            keeps its own: the paper's ego starts at its ``v_max``).
        anywhere: draw close-quarters scenes anywhere on the lap instead of the grid (a
            Python bool: static, so a compiled draw holds one kind of start).
        s_range: ``(2,)`` the interval ``[lo, hi)`` [m] of a scene's reference arc length.
        spread: ``()`` how far [m] behind the reference point a car may start.
        margin: ``()`` the least distance [m] of a car's centre from either track edge.
        speed: ``(2,)`` the interval [m/s] of a scene's start speeds.
    """

    slots: jax.Array
    shuffle: jax.Array
    jitter: jax.Array
    capped: jax.Array
    anywhere: bool
    s_range: jax.Array
    spread: jax.Array
    margin: jax.Array
    speed: jax.Array

    @classmethod
    def grid(cls, slots: np.ndarray, shuffle: bool, jitter: tuple[float, float, float], capped: bool = True
             ) -> "Starts":
        """A grid: ``slots (N, 6)``, shuffled or not, jittered by ``jitter`` [m, m, m/s]."""
        return cls(np.asarray(slots, dtype=np.float64), np.asarray(bool(shuffle)),
                   np.asarray(jitter, dtype=np.float64), np.asarray(bool(capped)), False, np.zeros(2), np.float64(0.0),
                   np.float64(0.0), np.zeros(2))

    @classmethod
    def scenes(cls, num_cars: int, s_range: tuple[float, float], spread: float, margin: float,
               speed: tuple[float, float]) -> "Starts":
        """Close-quarters scenes of ``num_cars`` cars anywhere in ``s_range`` [m] (the class
        docstring says what the other arguments bound)."""
        return cls(np.zeros((num_cars, STATE_DIM)), np.asarray(False), np.zeros(3), np.asarray(True), True,
                   np.asarray(s_range, dtype=np.float64), np.float64(spread), np.float64(margin),
                   np.asarray(speed, dtype=np.float64))


def key_from_seed(seed: int) -> np.ndarray:
    """The JAX key ``(2,) uint32`` of a reset's ``seed``, an integer in ``[0, 2**64)``: the
    threefry key ``jax.random.PRNGKey(seed)`` gives with 64-bit integers enabled, whatever
    the process's JAX settings."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= int(seed) < 2**64:
        raise ValueError(f"a seed must be an integer in [0, 2**64), got {seed!r}")
    seed = int(seed)
    return np.array([seed >> 32, seed & 0xFFFFFFFF], dtype=np.uint32)


def fresh_key() -> np.ndarray:
    """A key from the operating system's entropy (a reset without a seed)."""
    return key_from_seed(int(np.random.default_rng().integers(2**63)))


def next_episode(key: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``(key carried on, the episode's key)`` of a race's key (one split)."""
    carried, episode = jax.random.split(key)
    return carried, episode


def episode_seed(episode: jax.Array) -> jax.Array:
    """The episode's integer seed (int32 in ``[0, 2**31 - 1)``) for opponents seeded per
    episode, independent of the start the same key draws."""
    return jax.random.randint(jax.random.fold_in(episode, 1), (), 0, SEED_BOUND, dtype=jnp.int32)


def _grid(key: jax.Array, starts: Starts, v_cap: jax.Array) -> jax.Array:
    num = starts.slots.shape[0]
    k_order, k_jitter = jax.random.split(key)
    order = jnp.where(starts.shuffle, jax.random.permutation(k_order, num), jnp.arange(num))
    x0 = jnp.zeros_like(starts.slots).at[order].set(starts.slots)  # car order[k] takes slot k
    noise = jax.random.uniform(k_jitter, (3, num), canonical(starts.slots.dtype), -1.0, 1.0) * starts.jitter[:, None]
    x0 = x0.at[:, S].add(noise[0]).at[:, N_LAT].add(noise[1]).at[:, V].add(noise[2])
    return x0.at[:, V].set(jnp.where(starts.capped, jnp.clip(x0[:, V], 0.0, v_cap), x0[:, V]))


def _scene(key: jax.Array, starts: Starts, track: Track, vehicles: VehicleParams, v_cap: jax.Array):
    num, dtype = starts.slots.shape[0], canonical(starts.slots.dtype)
    lo, hi = starts.s_range[0], starts.s_range[1]

    def positions(k: jax.Array) -> tuple[jax.Array, jax.Array]:
        k_ref, k_back, k_n = jax.random.split(k, 3)
        s = jax.random.uniform(k_ref, (), dtype, lo, hi) - jax.random.uniform(k_back, (num,), dtype, 0.0,
                                                                              starts.spread)
        left = track.width_left_at(s) - starts.margin
        right = track.width_right_at(s) - starts.margin
        n = jax.random.uniform(k_n, (num,), dtype, -right, left)
        x = jnp.zeros((num, STATE_DIM), dtype).at[:, S].set(s).at[:, N_LAT].set(n)
        return x, ~jnp.any(footprint_overlap(x, vehicles, track))

    def again(carry):
        tries, k, _, _ = carry
        k, k_try = jax.random.split(k)
        return (tries + 1, k, *positions(k_try))

    k_positions, k_speed = jax.random.split(key)
    first = again((jnp.int32(0), k_positions, jnp.zeros((num, STATE_DIM), dtype), jnp.asarray(False)))
    _, _, x, free = jax.lax.while_loop(lambda c: ~c[3] & (c[0] < MAX_TRIES), again, first)
    speeds = jax.random.uniform(k_speed, (num,), dtype, starts.speed[0], starts.speed[1])
    return x.at[:, V].set(jnp.minimum(speeds, v_cap)), free


def draw(key: jax.Array, starts: Starts, track: Track, vehicles: VehicleParams) -> tuple[jax.Array, jax.Array]:
    """A start ``x0 (N, 6)`` drawn with ``key`` from ``starts`` on ``track`` for the cars
    ``vehicles`` (stacked, fields ``(N,)`` or scalars), and whether it is free of overlapping
    cars (always true for a grid; false when an ``anywhere`` scene found no free positions
    in :data:`MAX_TRIES` draws). Pure: jit and vmap it."""
    num = starts.slots.shape[0]
    v_cap = 0.95 * jnp.broadcast_to(jnp.asarray(vehicles.v_max, canonical(starts.slots.dtype)), (num,))
    if starts.anywhere:
        return _scene(key, starts, track, vehicles, v_cap)
    return _grid(key, starts, v_cap), jnp.asarray(True)


def next_start(key: jax.Array, starts: Starts, track: Track, vehicles: VehicleParams
               ) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """The next episode of a race whose key is ``key``: ``(key carried on, x0 (N, 6), free,
    episode seed)`` (:func:`next_episode`, :func:`draw`, :func:`episode_seed`). Pure."""
    carried, episode = next_episode(key)
    x0, free = draw(episode, starts, track, vehicles)
    return carried, x0, free, episode_seed(episode)


_next_start = jax.jit(next_start)


def draw_episode(key: np.ndarray, starts: Starts, track: Track, vehicles: VehicleParams
                 ) -> tuple[np.ndarray, np.ndarray, bool]:
    """One episode on the host: ``(key carried on (2,) uint32, x0 (N, 6), free)`` (jitted)."""
    carried, x0, free, _ = _next_start(jnp.asarray(key), starts, track, vehicles)
    return np.asarray(carried), np.asarray(x0), bool(free)
