"""The players' cost functions of the racing game (the paper's stage and terminal costs).

Stage cost of player i at joint state ``x (N, 6)`` with its own input ``u_i (2,)``::

    g^i = u_i' R^i u_i                                              (jerk regularisation)
        + sum_{j != i} c_c^i * exp(1 - (ds_ij / l_ij)^2 - (dn_ij / w_ij)^2)^2   (collision)
        + c_w^i * max(n_i - wl_i(s_i), 0)^2 + c_w^i * max(-n_i - wr_i(s_i), 0)^2  (track)
        + c_ax^i * max(ax_i - drive_max^i(V_i), 0)^2                            (ax limit)
        + c_a^i * max(|(ax_i, ay_i)| - rho^i(V_i), 0)^2                        (gg limit)
        + c_a^i * max(|ay_i| - V_i^2 / R_min^i, 0)^2                           (turn limit)
        + c_r^i * max(-V_i, 0)^2                                                (reversing)

``ds_ij`` is the wrapped gap in arc length, ``l_ij``/``w_ij`` the mean length/width of the two
cars (``l_veh``/``w_veh`` of the paper when the cars are alike), and ``wl/wr`` the usable
half-widths: the track width minus half the car's width, so the penalty starts when the
car's footprint touches the boundary. ``max(z, 0)^2`` is the paper's ``1{z >= 0} z^2``.
``drive_max(V)`` is the paper's ``ax_max(V)`` for a car without drag, and ``ax_max(V)`` plus the
still-air drag for one with drag (:meth:`racing_env.vehicle.VehicleParams.drive_max`).
The turn limit (steering lock, ``VehicleParams.min_turn_radius``) and the reversing term
are not in the paper. Both are zero at racing speeds; they are what the environment
enforces at low speed (no spinning on the spot, no reverse gear), so that a planner does not
plan a way out of a standstill that the car cannot drive.

Terminal cost: ``g_K^i = -s_K^i + c_g^i * sum_{j != i} s_K^j``.

The stage costs are stated once, as residuals: :func:`stage_residuals` gives player i's
``r_k`` (the proximities ``a_ij = (ds_ij / l_ij)^2 + (dn_ij / w_ij)^2``, the excesses ``z``
inside the ``max(z, 0)^2`` terms, its input) and their weights, and the cost is
``sum_k rho_k(r_k)`` with ``rho(a) = c exp(2 (1 - a))``, ``rho(z) = c max(z, 0)^2`` and
``rho(u) = r u^2``. Every cost function here sums those, and the solvers' Gauss-Newton form
(:mod:`planners.race_problem`) differentiates the same residuals. The terminal cost is
linear in the arc lengths (:func:`terminal_weights`).

Cars out of the race (``racing``, bool ``(N,)``; ``None``: all race) are ghosts: the collision
terms of every pair with such a car are zero, and its ``s_K`` leaves the others' sums.

Responsibility (not in the paper's cost, after its remark that the trailing car bears the
greater responsibility for avoiding a collision): ``collision_scale (N, N)`` multiplies
player i's collision weight towards car j, ``c_c^i * collision_scale[i, j]`` (``None``: 1,
the paper's symmetric cost). :func:`responsibility_scale` builds it from the cars' arc lengths
at the start of a plan, so it is a constant of the game: the cost, its Gauss-Newton form and
the Nash certificates (``jax.grad`` of the cost) all see the same weights.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from racing_env.dynamics import AX, AY, N_LAT, S, V
from racing_env.track import Track, check_scale
from racing_env.vehicle import ArrayLike, VehicleParams, concrete_fields

_NORM_EPS = 1e-12  # keeps |a| differentiable at a = 0


@dataclasses.dataclass(frozen=True)
class CostWeights:
    """Cost weights of one player (scalars) or of N players (arrays of shape ``(N,)``).

    Attributes:
        r_jx, r_jy: jerk regularisation, diagonal of R^i [s^6/m^2].
        c_collision: collision weight c_c (per step, dimensionless proximity term).
        c_track: track-boundary weight c_w [1/m^2].
        c_ax: weight on exceeding the drive limit (``ax_max(V)``, plus the still-air drag for a
            car with drag: ``VehicleParams.drive_max``), c_ax [s^4/m^2].
        c_acc: weight on exceeding the gg radius rho(V) and the turn limit V^2 / R_min,
            c_a [s^4/m^2].
        c_gap: terminal weight c_g on the opponents' progress (> 0 rewards being ahead).
        c_reverse: weight on negative speed (the cars have no reverse gear), c_r [s^2/m^2].
    """

    # 1.0 keeps the iLQ games well scaled: with jerk almost free (0.01) the solvers'
    # local models change fast between iterations, and cold solves take several times the
    # iterations (docs/solvers.md, "Convergence and status").
    r_jx: ArrayLike = 1.0
    r_jy: ArrayLike = 1.0
    c_collision: ArrayLike = 10.0
    c_track: ArrayLike = 100.0
    c_ax: ArrayLike = 100.0
    c_acc: ArrayLike = 100.0
    c_gap: ArrayLike = 0.5
    c_reverse: ArrayLike = 100.0

    def __post_init__(self) -> None:
        for name, (value, arr) in (concrete_fields(self) or {}).items():
            if name in ("r_jx", "r_jy"):
                if not np.all(arr > 0):
                    raise ValueError(
                        f"CostWeights.{name} must be > 0 (R^ii must be positive definite), "
                        f"got {value!r}"
                    )
            elif name != "c_gap" and not np.all(arr >= 0):
                raise ValueError(f"CostWeights.{name} must be >= 0, got {value!r}")

    def replace(self, **changes: ArrayLike) -> "CostWeights":
        return dataclasses.replace(self, **changes)

    @property
    def jerk_weights(self) -> jax.Array:
        """Diagonal of R, shape ``(..., 2)``."""
        return jnp.stack([jnp.asarray(self.r_jx), jnp.asarray(self.r_jy)], axis=-1)


jax.tree_util.register_dataclass(
    CostWeights, data_fields=[f.name for f in dataclasses.fields(CostWeights)], meta_fields=[]
)


RACING_JERK_WEIGHT = 0.01
"""Jerk weight r [s^6/m^2] of the planners in every race: the game ``parallel_env`` and the
Gymnasium view build when no weights are given, tournaments, sweeps and training.

In a race the terminal reward ``-s_K`` is the only incentive to go fast, and one metre of
progress is worth one cost unit. With the solver default r = 1 (kept for the paper's single
solves, where it keeps the iterations well scaled) a 5 s horizon buys so little progress per
unit of jerk that the planners accelerate at a fraction of the car's limit. At r = 0.01 the
feedback iLQGame planner beats the lane keeper; a larger or a smaller weight does worse
(docs/model.md, "The jerk weight of a race").
"""


#: The paper car's jerk limits [m/s^3], the scale :data:`RACING_JERK_WEIGHT` was tuned at.
PAPER_JERK_LIMIT = 30.0


def racing_weights(jerk_weight: float = RACING_JERK_WEIGHT, vehicle: VehicleParams | None = None,
                   scale: float = 1.0) -> CostWeights:
    """The cost weights of a car in a race: the defaults with jerk weight ``jerk_weight``
    [s^6/m^2] (``R = r I``) for the paper car's jerk limits, scaled for ``vehicle``'s (one car;
    None: the paper car's) by ``(PAPER_JERK_LIMIT / jx_max)^2`` and ``(PAPER_JERK_LIMIT /
    jy_max)^2``, so that the same share of a car's jerk limits costs the same: a car of a
    class with larger limits (the AV-21's 81 m/s^3) is not held back by the weight tuned for
    30 m/s^3 (docs/model.md, "The jerk weight of a race").

    ``scale``: the track's, on a model of a circuit at scale k (``track.scale``). The jerk
    weight is then k times as large, so that the terminal reward counts progress in the full
    size's metres (one model metre is k of them: ``-s_K`` in model metres is k times the
    reward of the full size's ``-s_K / k``), and the planners weigh jerk against progress as on
    the full-size circuit. Exactly the weights above at 1."""
    k = check_scale(scale)
    if vehicle is None:
        return CostWeights(r_jx=jerk_weight * k, r_jy=jerk_weight * k)
    return CostWeights(r_jx=jerk_weight * k * (PAPER_JERK_LIMIT / float(vehicle.jx_max)) ** 2,
                       r_jy=jerk_weight * k * (PAPER_JERK_LIMIT / float(vehicle.jy_max)) ** 2)


def stack_weights(weights: Sequence[CostWeights]) -> CostWeights:
    """Stack per-player weights into one ``CostWeights`` with fields of shape ``(N,)``."""
    if len(weights) < 1:
        raise ValueError("stack_weights needs at least one CostWeights")
    names = [f.name for f in dataclasses.fields(CostWeights)]
    return CostWeights(**{k: np.array([float(getattr(w, k)) for w in weights]) for k in names})


def racing_flags(racing: jax.Array | None, num_cars: int, dtype) -> jax.Array:
    """``(N,)`` weights of the cars: 1 racing, 0 out of the race (``None``: all race)."""
    if racing is None:
        return jnp.ones(num_cars, dtype=dtype)
    return jnp.asarray(racing).astype(dtype)


RESPONSIBILITY_BLEND = 1.0
"""Half-width of the blend of :func:`responsibility_scale`, in mean car lengths: a car more than
this far ahead carries the full ratio, one more than this far behind none, one alongside half."""


def check_responsibility(ratio) -> float:
    """``ratio`` as a float, refused unless it is a finite number >= 1 (the weight a car carries
    towards a car ahead of it over the weight towards a car behind it; 1: symmetric)."""
    if isinstance(ratio, bool) or not isinstance(ratio, (int, float, np.integer, np.floating)):
        raise ValueError(f"responsibility must be a finite number >= 1, got {ratio!r}")
    value = float(ratio)
    if not (np.isfinite(value) and value >= 1.0):
        raise ValueError(f"responsibility must be a finite number >= 1 (the ratio of a car's collision weight "
                         f"towards a car ahead to that towards a car behind; 1: the symmetric cost), got {ratio!r}")
    return value


def responsibility_scale(track: Track, s, lengths, ratio, xp=np):
    """``(..., N, N)`` factors on the collision weights: car i's towards car j is ``ratio_i``
    where j is ahead of i, 1 where j is behind, blended smoothly in between.

    With the wrapped gap ``ds_ij = s_j - s_i`` and the mean length ``l_ij`` of the two cars,
    ``z = ds_ij / (RESPONSIBILITY_BLEND l_ij)`` and the smoothstep
    ``h = t^2 (3 - 2 t)``, ``t = clip((z + 1) / 2, 0, 1)``, the factor is
    ``1 + (ratio_i - 1) h``: ``ratio_i`` for a car more than a car's length ahead, 1 for one
    more than a car's length behind, ``(1 + ratio_i) / 2`` for a car alongside (both carry
    the same), and continuous, so that a car that moves from behind to alongside between two
    plans does not flip its weight.

    Args:
        track: the track (gaps wrapped on a closed one).
        s: the cars' arc lengths ``(..., N)`` [m] at the start of the plan: a constant of the
            game, never the planned states (the solvers treat weights as constants).
        lengths: the cars' lengths ``(N,)`` [m] (or a scalar).
        ratio: the ratio ``(N,)`` of each car (or one for all), >= 1.
        xp: ``np`` on the host (no device dispatch), ``jax.numpy`` under ``jit``.
    """
    s = xp.asarray(s)
    num = s.shape[-1]
    lengths = xp.broadcast_to(xp.asarray(lengths, dtype=s.dtype), (num,))
    ratio = xp.broadcast_to(xp.asarray(ratio, dtype=s.dtype), (num,))
    gap = track.wrap_ds_in(s[..., None, :] - s[..., :, None], xp)  # [i, j] = s_j - s_i
    mean_length = 0.5 * (lengths[:, None] + lengths[None, :])
    t = xp.clip((gap / (RESPONSIBILITY_BLEND * mean_length) + 1.0) * 0.5, 0.0, 1.0)
    return 1.0 + (ratio[:, None] - 1.0) * (t * t * (3.0 - 2.0 * t))


def racing_pairs(racing: jax.Array | None, num_cars: int, dtype) -> jax.Array:
    """``(N, N)`` weights of the pairs of distinct cars that are both racing (1), else 0."""
    flags = racing_flags(racing, num_cars, dtype)
    return (1.0 - jnp.eye(num_cars, dtype=dtype)) * flags[:, None] * flags[None, :]


class StageResiduals(NamedTuple):
    """Player i's stage cost as ``sum_k rho_k(r_k)``: its residuals ``r_k`` and weights.

    The one statement of the racing stage costs: :func:`player_stage_cost` (and with it
    :func:`state_cost_terms`, :func:`stage_costs`, ``RaceGame.stage_cost``) sums the outer
    functions of these residuals, and the solvers' Gauss-Newton form
    (:func:`planners.race_problem.race_stage_gauss_newton`) differentiates the same
    residuals. Shapes for N cars and inputs of size m:

    Attributes:
        proximity: ``(N,)`` ``a_ij = (ds_ij / l_ij)^2 + (dn_ij / w_ij)^2`` to every car j;
            ``rho(a) = c exp(2 (1 - a))`` (the paper's ``c exp(1 - a)^2``).
        collision_weights: ``(N,)`` ``c_c^i`` (times the pair's ``collision_scale``) for the
            rivals racing with i, 0 for i itself and for pairs with a car out of the race.
        limits: ``(6,)`` the excesses ``z`` of :data:`LIMITS` (track left and right, ax
            limit, gg limit, turn limit, reversing); ``rho(z) = c max(z, 0)^2``.
        limit_weights: ``(6,)`` ``c_w, c_w, c_ax, c_a, c_a, c_r`` of player i.
        jerk: ``(m,)`` the input ``u_i``; ``rho(u) = r u^2``.
        jerk_weights: ``(m,)`` ``r_jx, r_jy`` of player i.
    """

    proximity: jax.Array
    collision_weights: jax.Array
    limits: jax.Array
    limit_weights: jax.Array
    jerk: jax.Array
    jerk_weights: jax.Array


LIMITS = ("track_left", "track_right", "ax_limit", "gg_limit", "turn_limit", "reverse")
"""The soft limits of :attr:`StageResiduals.limits`, in order."""


def _of_player(value, i, num_cars: int) -> jax.Array:
    """Player ``i``'s entry of a per-player field (a scalar is everybody's)."""
    return jnp.broadcast_to(jnp.asarray(value), (num_cars,))[i]


def stage_residuals(
    i: int | jax.Array,
    x: jax.Array,
    u_i: jax.Array,
    vehicles: VehicleParams,
    weights: CostWeights,
    track: Track,
    racing: jax.Array | None = None,
    collision_scale: jax.Array | None = None,
) -> StageResiduals:
    """Player ``i``'s stage-cost residuals at joint state ``x (N, 6)`` with its input ``u_i``;
    ``collision_scale (N, N)`` factors on the collision weights (None: 1; module docstring)."""
    N = x.shape[0]
    s, v, n = x[:, S], x[:, V], x[:, N_LAT]
    ds = track.wrap_ds(s - s[i])
    dn = n - n[i]
    lengths = jnp.broadcast_to(jnp.asarray(vehicles.length), (N,))
    widths = jnp.broadcast_to(jnp.asarray(vehicles.width), (N,))
    length = 0.5 * (lengths[i] + lengths)
    width = 0.5 * (widths[i] + widths)
    proximity = (ds / length) ** 2 + (dn / width) ** 2  # a_ii = 0
    rivals = _of_player(weights.c_collision, i, N) * racing_pairs(racing, N, x.dtype)[i]
    if collision_scale is not None:
        rivals = rivals * jnp.asarray(collision_scale, x.dtype)[i]
    half_width = 0.5 * widths[i]
    ax_i, ay_i = x[i, AX], x[i, AY]
    limits = jnp.stack(
        [
            n[i] - (track.width_left_at(s[i]) - half_width),
            -n[i] - (track.width_right_at(s[i]) - half_width),
            ax_i - vehicles.drive_max(v)[i],
            jnp.sqrt(ax_i**2 + ay_i**2 + _NORM_EPS) - vehicles.rho(v)[i],
            jnp.sqrt(ay_i**2 + _NORM_EPS) - vehicles.ay_turn_max(v)[i],
            -v[i],
        ]
    )
    c_track, c_ax, c_acc, c_reverse = (
        _of_player(w, i, N) for w in (weights.c_track, weights.c_ax, weights.c_acc, weights.c_reverse)
    )
    limit_weights = jnp.stack([c_track, c_track, c_ax, c_acc, c_acc, c_reverse])
    jerk_weights = jnp.broadcast_to(jnp.asarray(weights.jerk_weights), (N, u_i.shape[-1]))[i]
    return StageResiduals(proximity, rivals, limits, limit_weights, u_i, jerk_weights)


def collision_costs(res: StageResiduals) -> jax.Array:
    """``(N,)`` the collision cost ``c_c exp(2 (1 - a_ij))`` of player i to every car j."""
    return res.collision_weights * jnp.exp(2.0 * (1.0 - res.proximity))


def limit_costs(res: StageResiduals) -> jax.Array:
    """``(6,)`` the soft-limit costs ``c max(z, 0)^2`` in the order of :data:`LIMITS`."""
    return res.limit_weights * jnp.maximum(res.limits, 0.0) ** 2


def _state_terms(res: StageResiduals) -> dict[str, jax.Array]:
    """Player i's input-independent stage-cost terms (scalars) from its residuals."""
    limit = limit_costs(res)
    return {
        "collision": jnp.sum(collision_costs(res)),
        "track": limit[0] + limit[1],
        "ax_limit": limit[2],
        "gg_limit": limit[3],
        "turn_limit": limit[4],
        "reverse": limit[5],
    }


def player_stage_cost(res: StageResiduals) -> jax.Array:
    """Player i's stage cost ``sum_k rho_k(r_k)`` of its residuals (a scalar)."""
    return sum(_state_terms(res).values()) + jnp.sum(res.jerk_weights * res.jerk**2)


def state_cost_terms(
    x: jax.Array,
    vehicles: VehicleParams,
    weights: CostWeights,
    track: Track,
    racing: jax.Array | None = None,
    collision_scale: jax.Array | None = None,
) -> dict[str, jax.Array]:
    """The input-independent stage-cost terms of every player, each of shape ``(N,)`` (the
    input enters only the jerk term, :func:`input_cost`, so any input will do here)."""
    def player(i):
        return _state_terms(stage_residuals(i, x, jnp.zeros(2, x.dtype), vehicles, weights, track, racing,
                                            collision_scale))

    return jax.vmap(player)(jnp.arange(x.shape[0]))


def input_cost(u: jax.Array, weights: CostWeights) -> jax.Array:
    """Jerk regularisation ``u_i' R^i u_i`` for every player: ``u (N, 2)`` -> ``(N,)``."""
    return jnp.sum(weights.jerk_weights * u**2, axis=-1)


def stage_costs(
    x: jax.Array,
    u: jax.Array,
    vehicles: VehicleParams,
    weights: CostWeights,
    track: Track,
    racing: jax.Array | None = None,
    collision_scale: jax.Array | None = None,
) -> jax.Array:
    """Stage cost of every player: ``x (N, 6)``, ``u (N, 2)`` -> ``(N,)``."""
    def player(i, u_i):
        return player_stage_cost(stage_residuals(i, x, u_i, vehicles, weights, track, racing, collision_scale))

    return jax.vmap(player)(jnp.arange(x.shape[0]), u)


def terminal_weights(weights: CostWeights, racing: jax.Array | None, num_cars: int, dtype) -> jax.Array:
    """``(N, N)`` the linear terminal costs: ``g_K^i = sum_j W[i, j] s_K^j`` with
    ``W[i, i] = -1`` and ``W[i, j] = c_g^i`` for the rivals ``j`` still racing (else 0)."""
    c_gap = jnp.broadcast_to(jnp.asarray(weights.c_gap), (num_cars,))
    rivals = c_gap[:, None] * racing_flags(racing, num_cars, dtype)[None, :]
    return jnp.where(jnp.eye(num_cars, dtype=bool), -1.0, rivals).astype(dtype)


def terminal_costs(x: jax.Array, weights: CostWeights, racing: jax.Array | None = None) -> jax.Array:
    """Terminal cost ``-s^i + c_g^i sum_{j != i, j racing} s^j`` of every player, ``(N,)``."""
    s = x[:, S]
    return jnp.sum(terminal_weights(weights, racing, s.shape[0], s.dtype) * s[None, :], axis=1)
