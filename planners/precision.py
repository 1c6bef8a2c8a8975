"""The solvers' precision: float64 by default, float32 as a choice.

float64 (``precision="float64"``, the default of every solver and agent) is what the
certificates and the paper's figures use: the Nash checks hold their conditions to
1e-8..1e-12, below float32's resolution. It needs JAX's 64-bit floats
(``jax_enable_x64``); importing the package leaves that setting as the user set it, and
:func:`require_x64` at the solvers' entry points turns a float64 solve without it into a
clear ``RuntimeError`` instead of a silent low-precision solve or a dtype error deep inside.

float32 (``precision="float32"``, :attr:`planners.ilq.SolverOptions.precision`) solves in
32-bit floats whatever ``jax_enable_x64`` says: the jitted solvers cast the problem's
floating-point parameters, the initial state and the inputs to float32 inside the trace
(:func:`cast_floating`), so every operation of an iteration is a float32 one. Two rules make
it hold:

* its convergence test allows for the trajectory's own rounding: a step counts as within
  ``tolerance`` once every state entry moved by at most ``tolerance`` plus
  :data:`ROUNDING_ULPS` times the dtype's resolution at the trajectory's scale
  (:func:`rounding_floor`; 2.2e-4 m in float32 for positions near 230 m). Without it a float32 solve at ``tolerance=1e-6`` can stall
  at the rounding of speeds near 20 m/s (float32's spacing there is 2^-19 = 1.9e-6 m/s) and
  run to the iteration cap. In float64 the floor is ~4e-13 m at 230 m, below any
  tolerance in use;
* a float32 solve refuses a ``tolerance`` below float32's resolution (:func:`check_tolerance`,
  ``finfo(float32).eps`` = 1.19e-7; 0, "run every iteration", stays allowed).

It imports nothing but JAX and NumPy, so the generic solver (:mod:`planners.ilq`, which
reaches nothing of ``racing_env``) can use it; the race's faces use
:func:`racing_env.precision.require_x64`, which says the same.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "PRECISIONS",
    "ROUNDING_ULPS",
    "cast_floating",
    "check_precision",
    "check_tolerance",
    "dtype_of",
    "require_precision",
    "require_x64",
    "resolution",
    "rounding_floor",
]

#: The precisions a solver or agent takes (``precision=...``); the first is the default.
PRECISIONS = ("float64", "float32")

#: How many units of the dtype's resolution (relative to the trajectory's scale) a
#: converged step may still move an entry by: the forward pass that checks a step rounds
#: every entry again, and a fixed point's rollout differs from the previous one by up to
#: 2 units of the resolution at the speeds' scale (measured in float32 on 64 perturbed
#: paper scenes); 8 leaves a margin of 4 where the positions are no larger than the speeds.
ROUNDING_ULPS = 8.0


def check_precision(precision: Any) -> str:
    """``precision`` if it is one of :data:`PRECISIONS`, else ``ValueError`` naming them."""
    if not isinstance(precision, str) or precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    return precision


def dtype_of(precision: str) -> np.dtype:
    """The NumPy dtype of a precision name (``"float64"`` -> float64, ``"float32"`` -> float32)."""
    return np.dtype(check_precision(precision))


def resolution(precision: str) -> float:
    """The relative resolution of a precision: ``finfo(dtype).eps``, the spacing of its
    numbers in [1, 2) (float32: 1.19e-7, float64: 2.2e-16)."""
    return float(np.finfo(dtype_of(precision)).eps)


def check_tolerance(precision: str, tolerance: float) -> None:
    """Refuse a convergence ``tolerance`` below the resolution of ``precision`` (0 stays
    allowed: it means "run every iteration"), with the allowed values named."""
    floor = resolution(precision)
    if 0 < tolerance < floor:
        raise ValueError(
            f"tolerance {tolerance!r} is below the resolution of {precision} ({floor:.3g}): a {precision} "
            f"solve cannot resolve it; use tolerance = 0 (run every iteration) or >= {floor:.3g}"
            + (", or precision='float64'" if precision != "float64" else "")
        )


def cast_floating(tree: Any, dtype: Any) -> Any:
    """``tree`` with every floating-point array leaf cast to ``dtype`` (other leaves as they
    are). Meant inside a jitted solver: a concrete :class:`racing_env.RaceGame` copies its
    tables back to float64 when it is rebuilt outside a trace, traced leaves stay cast."""
    dtype = np.dtype(dtype)

    def cast(leaf):
        if hasattr(leaf, "dtype") and jnp.issubdtype(leaf.dtype, jnp.floating) and leaf.dtype != dtype:
            return jnp.asarray(leaf).astype(dtype)
        return leaf

    return jax.tree_util.tree_map(cast, tree)


def rounding_floor(xs: jax.Array) -> jax.Array:
    """The rounding allowance of a trajectory ``xs (T+1, n)``, a scalar in state units:
    :data:`ROUNDING_ULPS` times the dtype's resolution times the trajectory's scale (its
    largest entry in magnitude, typically a car's position ``s``). A step whose entries all
    moved by at most the tolerance plus this allowance is as small as the dtype can tell.

    The scale is the whole trajectory's, not each component's: the feedback law
    ``u = u_hat - K (x - x_hat)`` carries the rounding of the largest entries (positions)
    into the inputs and from there into every other component, so a fixed point's
    rollouts differ in speeds and headings by the rounding of the positions (measured in
    float32: 1-2 units of 2^-19 in speeds near 20 m/s while positions near 230 m round to
    2^-16)."""
    eps = jnp.finfo(xs.dtype).eps
    return ROUNDING_ULPS * eps * jnp.max(jnp.abs(xs))


def require_precision(precision: str, what: str) -> None:
    """The entry check of a solver asked for ``precision``: float64 needs 64-bit floats on
    (:func:`require_x64`); float32 runs either way."""
    if check_precision(precision) == "float64":
        require_x64(what)


def require_x64(what: str) -> None:
    """Raise ``RuntimeError`` unless 64-bit floats are on: ``what`` (a solver, a planner)
    cannot run in float64 without them. A config read (well under a microsecond; at trace
    time under ``jit``)."""
    if not jax.config.read("jax_enable_x64"):
        raise RuntimeError(
            f"{what} needs 64-bit floats (its tolerances assume float64), and jax_enable_x64 is off: "
            "call racing_env.configure_for_racing() at the top of the script (what the racing commands "
            "use), or jax.config.update('jax_enable_x64', True) (or set JAX_ENABLE_X64=1), before making "
            "its arrays; or solve in float32 with precision='float32'"
        )
