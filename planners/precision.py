"""The solvers' one precision requirement: 64-bit floats.

The game solvers and the certificates hold their conditions to 1e-8..1e-12 (Nash
residuals, eigenvalue signs, convergence thresholds), below float32's resolution of about
1e-7, so they run in float64 only. Importing the package leaves ``jax_enable_x64`` as the
user set it (off by default); :func:`require_x64` at the solvers' entry points turns a
float32 run into a clear ``RuntimeError`` instead of a silent low-precision solve or a
dtype error deep inside. It imports nothing but JAX, so the generic solver
(:mod:`planners.ilq`, which reaches nothing of ``racing_env``) can use it; the race's
faces use :func:`racing_env.precision.require_x64`, which says the same.
"""

from __future__ import annotations

import jax

__all__ = ["require_x64"]


def require_x64(what: str) -> None:
    """Raise ``RuntimeError`` unless 64-bit floats are on: ``what`` (a solver, a planner)
    cannot run in float32. A config read (well under a microsecond; at trace time under
    ``jit``)."""
    if not jax.config.read("jax_enable_x64"):
        raise RuntimeError(
            f"{what} needs 64-bit floats (its tolerances assume float64), and jax_enable_x64 is off: "
            "call racing_env.configure_for_racing() at the top of the script (what the racing commands "
            "use), or jax.config.update('jax_enable_x64', True) (or set JAX_ENABLE_X64=1), before making "
            "its arrays"
        )
