"""The players' cost functions of the racing game (the paper's stage and terminal costs).

Stage cost of player i at joint state ``x (N, 6)`` with its own input ``u_i (2,)``::

    g^i = u_i' R^i u_i                                              (jerk regularisation)
        + sum_{j != i} c_c^i * exp(1 - (ds_ij / l_ij)^2 - (dn_ij / w_ij)^2)^2   (collision)
        + c_w^i * max(n_i - wl_i(s_i), 0)^2 + c_w^i * max(-n_i - wr_i(s_i), 0)^2  (track)
        + c_ax^i * max(ax_i - ax_max^i(V_i), 0)^2                              (ax limit)
        + c_a^i * max(|(ax_i, ay_i)| - rho^i(V_i), 0)^2                        (gg limit)
        + c_a^i * max(|ay_i| - V_i^2 / R_min^i, 0)^2                           (turn limit)
        + c_r^i * max(-V_i, 0)^2                                                (reversing)

``ds_ij`` is the wrapped gap in arc length, ``l_ij``/``w_ij`` the mean length/width of the two
cars (``l_veh``/``w_veh`` of the paper when the cars are alike), and ``wl/wr`` the usable
half-widths: the track width minus half the car's width, so the penalty starts when the
car's footprint touches the boundary. ``max(z, 0)^2`` is the paper's ``1{z >= 0} z^2``.
The turn limit (steering lock, ``VehicleParams.min_turn_radius``) and the reversing term
are not in the paper. Both are zero at racing speeds; they are what the environment
enforces at low speed (no spinning on the spot, no reverse gear), so that a planner does not
plan a way out of a standstill that the car cannot drive.

Terminal cost: ``g_K^i = -s_K^i + c_g^i * sum_{j != i} s_K^j``.

Cars out of the race (``racing``, bool ``(N,)``; ``None``: all race) are ghosts: the collision
terms of every pair with such a car are zero, and its ``s_K`` leaves the others' sums.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from racing_env.dynamics import AX, AY, N_LAT, S, V
from racing_env.track import Track
from racing_env.vehicle import ArrayLike, VehicleParams, concrete_fields

_NORM_EPS = 1e-12  # keeps |a| differentiable at a = 0


@dataclasses.dataclass(frozen=True)
class CostWeights:
    """Cost weights of one player (scalars) or of N players (arrays of shape ``(N,)``).

    Attributes:
        r_jx, r_jy: jerk regularisation, diagonal of R^i [s^6/m^2].
        c_collision: collision weight c_c (per step, dimensionless proximity term).
        c_track: track-boundary weight c_w [1/m^2].
        c_ax: weight on exceeding ax_max(V), c_ax [s^4/m^2].
        c_acc: weight on exceeding the gg radius rho(V) and the turn limit V^2 / R_min,
            c_a [s^4/m^2].
        c_gap: terminal weight c_g on the opponents' progress (> 0 rewards being ahead).
        c_reverse: weight on negative speed (the cars have no reverse gear), c_r [s^2/m^2].
    """

    # 1.0 keeps the iLQ games well scaled: with jerk almost free (0.01) the solvers'
    # local models change fast between iterations, and cold solves take 2-5x the
    # iterations (README, Convergence away from the paper's scene).
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
"""Jerk weight r [s^6/m^2] of the planners in races (tournaments, the demo, the agents bench).

In a race the terminal reward ``-s_K`` is the only incentive to go fast, and one metre of
progress is worth one cost unit. With the solver default r = 1 (kept for the paper's single
solves, where it keeps the iterations well scaled) a 5 s horizon buys so little progress per
unit of jerk that the planners accelerate at a fraction of the car's limit: measured on the
trefoil (1 lap, rolling start, grid seeds 0 and 1, both starting slots), feedback iLQGame
lost to the lane keeper with r = 0.1 (by 0.3 s over 500 m) and beat it in 4 of 4 races by
1.0-1.9 s with r = 0.01 (mean 1.42 s). Lower is not better: r = 0.003 also won 4 of 4 but
by less (mean 1.32 s).
"""


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


def racing_pairs(racing: jax.Array | None, num_cars: int, dtype) -> jax.Array:
    """``(N, N)`` weights of the pairs of distinct cars that are both racing (1), else 0."""
    flags = racing_flags(racing, num_cars, dtype)
    return (1.0 - jnp.eye(num_cars, dtype=dtype)) * flags[:, None] * flags[None, :]


def collision_proximity(
    x: jax.Array, vehicles: VehicleParams, track: Track, racing: jax.Array | None = None
) -> jax.Array:
    """Pairwise proximity ``exp(1 - (ds/l)^2 - (dn/w)^2)^2``, shape ``(N, N)``, zero on the
    diagonal and for pairs with a car out of the race."""
    ds = track.wrap_ds(x[None, :, S] - x[:, None, S])
    dn = x[None, :, N_LAT] - x[:, None, N_LAT]
    length = 0.5 * (vehicles.length[:, None] + vehicles.length[None, :])
    width = 0.5 * (vehicles.width[:, None] + vehicles.width[None, :])
    proximity = jnp.exp(2.0 * (1.0 - (ds / length) ** 2 - (dn / width) ** 2))
    return proximity * racing_pairs(racing, x.shape[0], x.dtype)


def state_cost_terms(
    x: jax.Array,
    vehicles: VehicleParams,
    weights: CostWeights,
    track: Track,
    racing: jax.Array | None = None,
) -> dict[str, jax.Array]:
    """The input-independent stage-cost terms of every player, each of shape ``(N,)``."""
    s, v, n = x[:, S], x[:, V], x[:, N_LAT]
    ax, ay = x[:, AX], x[:, AY]
    half_width = 0.5 * vehicles.width
    beyond_left = jnp.maximum(n - (track.width_left_at(s) - half_width), 0.0)
    beyond_right = jnp.maximum(-n - (track.width_right_at(s) - half_width), 0.0)
    over_ax = jnp.maximum(ax - vehicles.ax_max(v), 0.0)
    over_gg = jnp.maximum(jnp.sqrt(ax**2 + ay**2 + _NORM_EPS) - vehicles.rho(v), 0.0)
    over_turn = jnp.maximum(jnp.sqrt(ay**2 + _NORM_EPS) - vehicles.ay_turn_max(v), 0.0)
    return {
        "collision": weights.c_collision * collision_proximity(x, vehicles, track, racing).sum(axis=1),
        "track": weights.c_track * (beyond_left**2 + beyond_right**2),
        "ax_limit": weights.c_ax * over_ax**2,
        "gg_limit": weights.c_acc * over_gg**2,
        "turn_limit": weights.c_acc * over_turn**2,
        "reverse": weights.c_reverse * jnp.maximum(-v, 0.0) ** 2,
    }


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
) -> jax.Array:
    """Stage cost of every player: ``x (N, 6)``, ``u (N, 2)`` -> ``(N,)``."""
    terms = state_cost_terms(x, vehicles, weights, track, racing)
    return input_cost(u, weights) + sum(terms.values())


def terminal_costs(x: jax.Array, weights: CostWeights, racing: jax.Array | None = None) -> jax.Array:
    """Terminal cost ``-s^i + c_g^i sum_{j != i, j racing} s^j`` of every player, ``(N,)``."""
    s = x[:, S]
    rivals = s * racing_flags(racing, s.shape[0], s.dtype)
    return -s + weights.c_gap * (jnp.sum(rivals) - rivals)
