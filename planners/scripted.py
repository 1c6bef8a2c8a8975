"""Scripted baseline drivers: a lane-keeping controller and a constant-speed cruiser.

They read the joint state (full information, like the planners) and return normalised
jerk actions in ``[-1, 1]^2``. These are the control laws alone, callables
``driver(observation, joint_state) -> action``: :mod:`planners.agents.scripted` makes them
agents, and :mod:`planners.prediction` drives predicted opponents with them. The lateral law makes the lateral offset behave like a
critically damped second-order system around a target offset; the longitudinal law tracks a
target speed capped by the tightest curve in a preview window.
"""

from __future__ import annotations

import numpy as np

from planners.methods import CONSTANT_SPEED, LANE_KEEPING
from racing_env.track import Track
from racing_env.vehicle import VehicleParams

LATERAL_STIFFNESS = 1.0  # [1/s^2] n'' = k_p (n_target - n) - k_d n'
LATERAL_DAMPING = 2.0  # [1/s] critical damping for k_p = 1
ACCEL_GAIN = 5.0  # [1/s] jerk = gain * (a_desired - a)
SPEED_GAIN = 1.5  # [1/s] ax_desired = gain * (v_target - V)
GRIP_MARGIN = 0.75  # fraction of rho(V) used for cornering
PREVIEW_TIME = 3.0  # [s] look-ahead for the curve speed limit
PREVIEW_POINTS = 16  # curvature samples over the look-ahead
_PREVIEW_INDEX = np.arange(PREVIEW_POINTS, dtype=np.float64)


def _preview_offsets(reach: float) -> np.ndarray:
    """``np.linspace(0, reach, PREVIEW_POINTS)`` [m] with the same arithmetic (index times
    step, the end point set exactly), without its per-call overhead."""
    offsets = _PREVIEW_INDEX * (reach / (PREVIEW_POINTS - 1))
    offsets[-1] = reach
    return offsets


def _curvature_grid(track: Track) -> tuple[np.ndarray, np.ndarray]:
    """Arc lengths and curvatures for ``np.interp``; on a closed track, wrapped, sorted and
    padded by one point each side, once per controller, where ``np.interp(..., period=length)``
    would prepare them again on every call."""
    s, kappa = np.asarray(track.s, dtype=np.float64), np.asarray(track.kappa, dtype=np.float64)
    if not track.closed:
        return s, kappa
    period = track.length
    s = s % period
    order = np.argsort(s)
    s, kappa = s[order], kappa[order]
    return np.concatenate((s[-1:] - period, s, s[:1] + period)), np.concatenate((kappa[-1:], kappa, kappa[:1]))


def check_targets(target_speed: float | None = None, target_n: float = 0.0) -> None:
    """Refuse a cruise speed that is not finite and positive (``None``: the car's v_max) and
    a lateral offset that is not finite (a NaN target would make every action NaN)."""
    if target_speed is not None and not 0 < float(target_speed) < np.inf:
        raise ValueError(f"target_speed must be a finite speed > 0 m/s, got {target_speed!r}")
    if not np.isfinite(float(target_n)):
        raise ValueError(f"target_n must be a finite lateral offset [m], got {target_n!r}")


class LaneKeeping:
    """Follows a lateral offset ``target_n`` [m] at ``target_speed`` [m/s] (default: v_max).

    Args:
        track: the track raced on.
        index: the car this controller drives (row of the joint state).
        vehicle: that car's parameters (limits and jerk scaling).
        target_speed: cruise speed; ``None`` tracks the car's v_max.
        target_n: lateral offset to hold [m], positive to the left.
    """

    name = LANE_KEEPING

    def __init__(
        self,
        track: Track,
        index: int,
        vehicle: VehicleParams = VehicleParams(),
        target_speed: float | None = None,
        target_n: float = 0.0,
    ) -> None:
        check_targets(target_speed, target_n)
        self.track, self.index, self.vehicle = track, int(index), vehicle
        self.target_speed = float(vehicle.v_max if target_speed is None else target_speed)
        self.target_n = float(target_n)
        self._jerk_max = np.array([float(vehicle.jx_max), float(vehicle.jy_max)])
        self._kappa_s, self._kappa_values = _curvature_grid(track)

    def _kappa(self, s: np.ndarray) -> np.ndarray:
        if self.track.closed:
            # The double wrap is np.interp's own periodic normalisation of the wrapped s.
            period = self.track.length
            return np.interp(np.mod(s, period) % period, self._kappa_s, self._kappa_values)
        return np.interp(s, self._kappa_s, self._kappa_values)

    def __call__(self, observation: np.ndarray | None, joint_state: np.ndarray) -> np.ndarray:
        # Scalar work in scalars: np.linspace and np.clip on a few numbers cost more than the
        # arithmetic; every value equals the array form (tests/test_agents.py checks it).
        s, v, n, chi, ax, ay = np.asarray(joint_state, dtype=float)[self.index]
        v_pos = max(v, 0.0)
        reach = max(v_pos, 5.0) * PREVIEW_TIME
        kappa_ahead = self._kappa(s + _preview_offsets(reach))  # kappa_ahead[0] is at s itself
        kappa_max = float(np.max(np.abs(kappa_ahead)))
        rho = float(self.vehicle.rho(v_pos))
        v_curve = np.sqrt(GRIP_MARGIN * rho / max(kappa_max, 1e-6))
        v_target = min(self.target_speed, v_curve)
        ax_des = min(max(SPEED_GAIN * (v_target - v), -GRIP_MARGIN * rho), float(self.vehicle.ax_max(v_pos)))
        n_rate = v * np.sin(chi)
        ay_des = kappa_ahead[0] * v**2 + LATERAL_STIFFNESS * (self.target_n - n) - LATERAL_DAMPING * n_rate
        jx, jy = ACCEL_GAIN * (ax_des - ax) / self._jerk_max[0], ACCEL_GAIN * (ay_des - ay) / self._jerk_max[1]
        return np.array([min(max(jx, -1.0), 1.0), min(max(jy, -1.0), 1.0)], dtype=np.float32)


class ConstantSpeed(LaneKeeping):
    """Cruises on the centre line at a constant ``target_speed`` (slowing only for curves)."""

    name = CONSTANT_SPEED

    def __init__(self, track: Track, index: int, vehicle: VehicleParams = VehicleParams(), target_speed: float = 15.0):
        super().__init__(track, index, vehicle, target_speed=target_speed, target_n=0.0)
