"""The warm start of a receding-horizon re-plan: the previous plan, shifted, from where the cars are.

A re-plan starts from the last plan's inputs shifted by the steps elapsed. Rolled out from
the measured joint state, those inputs drift from the plan wherever the measured state
differs from the planned one. The difference that matters is in the accelerations: the
game only penalises leaving the acceleration limits, the environment enforces them
(:func:`racing_env.physics.enforce_limits`), so a plan that leans on a limit is projected
back onto it at every step. Rolled out open loop, the shifted plan then runs just inside
the limit for the whole horizon; there the limit terms are inactive and carry no curvature,
and the first LQ step of the re-plan is a long one that the trust region cuts to a few
percent of its length (docs/solvers.md, "Warm starts and budgets").

:func:`restore_accelerations` corrects the first jerk of the shifted plan so that the
accelerations are back on the plan after one step (the jerk integrates exactly into the
acceleration over a step): ``u_0 += (a_planned - a_measured) / dt``. From then on the
rollout follows the plan's accelerations exactly. It works for any number of races at once.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from numpy.typing import ArrayLike

from racing_env.dynamics import AX, AY

__all__ = ["restore_accelerations"]


def restore_accelerations(us: ArrayLike, planned: ArrayLike, measured: ArrayLike, dt: float) -> ArrayLike:
    """The shifted inputs ``us (..., T, N, 2)`` [m/s^3] with the first stage's jerks
    corrected so that every car's accelerations ``[ax, ay]`` reach the plan's after one
    step of ``dt`` seconds: ``us[..., 0, :, :] + (planned[..., [ax, ay]] - measured[...,
    [ax, ay]]) / dt``, where ``planned (..., N, 6)`` is the state the shifted plan starts
    from (the old plan's state at the current step) and ``measured (..., N, 6)`` the
    current joint state. Non-finite corrections are left out (the inputs stay as they are).
    Returns a new array: NumPy for NumPy inputs (the host planners), JAX inside a traced
    function (the compiled planner), with the same operations either way."""
    xp = jnp if any(isinstance(a, jax.Array) for a in (us, planned, measured)) else np
    correction = (planned[..., [AX, AY]] - measured[..., [AX, AY]]) / dt
    first = us[..., :1, :, :] + xp.where(xp.isfinite(correction), correction, 0.0)[..., None, :, :]
    return xp.concatenate([first, us[..., 1:, :, :]], axis=-3)
