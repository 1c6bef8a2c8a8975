"""Which float the race computes in: the state's, within what JAX allows.

The race core follows the dtype of its state ``x``: float64 when 64-bit floats are enabled
(``jax_enable_x64``, which the ``racing`` commands and
:func:`racing_env.xla_setup.configure_for_racing` turn on; importing the package does not),
float32 with JAX's default, or float32 when a float32 state is raced with them on. Its constants (the
track's tables, the cars' limits, the reward weights) are float64 NumPy arrays; these
helpers give the dtype they are computed in under the current setting, without JAX's
warning about a float64 request it would truncate.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def canonical(dtype) -> np.dtype:
    """``dtype`` as JAX holds it now: float64 becomes float32 (int64 int32) with x64 off."""
    return np.dtype(jax.dtypes.canonicalize_dtype(dtype))


def default_float() -> np.dtype:
    """JAX's widest float now: float64 with ``jax_enable_x64`` on, else float32."""
    return canonical(jnp.float64)


def x64_enabled() -> bool:
    """Whether JAX holds 64-bit floats now (``jax_enable_x64``)."""
    return bool(jax.config.read("jax_enable_x64"))


def require_x64(what: str) -> None:
    """Raise ``RuntimeError`` unless 64-bit floats are on: ``what`` (a solver whose
    tolerances assume float64) cannot run in float32.

    ``GymnaxRace`` calls it for planner opponents; the solvers themselves use
    :func:`planners.precision.require_x64`, which says the same."""
    if not x64_enabled():
        raise RuntimeError(
            f"{what} needs 64-bit floats (its tolerances assume float64), and jax_enable_x64 is off: "
            "call racing_env.configure_for_racing() at the top of the script (what the racing commands "
            "use), or jax.config.update('jax_enable_x64', True) (or set JAX_ENABLE_X64=1), before making "
            "its arrays"
        )
