"""Which float the race computes in: the state's, within what JAX allows.

The race core follows the dtype of its state ``x``: float64 when 64-bit floats are enabled
(``jax_enable_x64``, which importing :mod:`racing_env` turns on), float32 when the user
turns them off, or float32 when a float32 state is raced with them on. Its constants (the
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
    tolerances assume float64) cannot run in float32."""
    if not x64_enabled():
        raise RuntimeError(
            f"{what} needs 64-bit floats (its tolerances assume float64), and jax_enable_x64 is off: "
            "run jax.config.update('jax_enable_x64', True) (or set JAX_ENABLE_X64=1) before building it"
        )
