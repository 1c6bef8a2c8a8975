"""Tests of racing_env.limits: racing lines on the track's Frenet frame and the
quasi-steady-state lap-time limit, against closed forms and on every shipped circuit."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest

from racing_env import limits
from racing_env import track as tr
from racing_env.vehicle import VehicleParams

CIRCUITS = tr.circuit_names()


def _exact_circle(radius: float, points: int = 2000, width: float = 6.0) -> tr.Track:
    """A circle of constant curvature 1/radius, built on the grid itself (no fit)."""
    length = 2.0 * math.pi * radius
    s = np.arange(points) * (length / points)
    theta = s / radius
    return tr.Track(s=s, kappa=np.full(points, 1.0 / radius), width_left=np.full(points, width),
                    width_right=np.full(points, width), x=radius * np.sin(theta), y=radius * (1.0 - np.cos(theta)),
                    heading=theta, length=length, closed=True, name="circle")


def test_a_circle_is_driven_at_sqrt_ay_max_r_in_the_known_lap_time() -> None:
    """No aero, a top speed out of reach: V = sqrt(rho_0 R) everywhere, T = 2 pi R / V. The line has
    constant curvature and the profile is constant, so the only errors are rounding (1e-12)."""
    radius = 100.0
    car = VehicleParams(rho_aero=0.0, v_max=80.0)
    profile = limits.speed_profile(limits.centerline(_exact_circle(radius)), car)
    v = math.sqrt(12.0 * radius)
    np.testing.assert_allclose(profile.v, v, rtol=1e-12)
    assert profile.lap_time == pytest.approx(2.0 * math.pi * radius / v, rel=1e-12)
    # With downforce rho = rho_0 + rho_aero V^2: kappa V^2 = rho gives V^2 = rho_0 / (kappa - rho_aero).
    aero = VehicleParams(rho_aero=0.004, v_max=80.0)
    v_aero = math.sqrt(12.0 / (1.0 / radius - 0.004))
    assert limits.lap_time_limit(_exact_circle(radius), aero, line="centerline") == pytest.approx(
        2.0 * math.pi * radius / v_aero, rel=1e-12)
    # A top speed below the cornering speed: the whole lap at v_max (ax_max(v_max) = 0).
    assert limits.lap_time_limit(_exact_circle(radius), VehicleParams(v_max=20.0), line="centerline") == \
        pytest.approx(2.0 * math.pi * radius / 20.0, rel=1e-12)


def test_a_line_at_a_constant_offset_of_a_circle_is_a_concentric_circle() -> None:
    """n = d (left, inside of a left turn): radius R - d, length 2 pi (R - d), chi = 0."""
    radius, d = 100.0, 3.0
    circle = _exact_circle(radius)
    line = limits.line_from_offset(circle, np.full(circle.num_points, d), name="inside")
    np.testing.assert_allclose(line.kappa, 1.0 / (radius - d), rtol=1e-12)
    np.testing.assert_allclose(line.chi, 0.0, atol=1e-15)
    assert line.length == pytest.approx(2.0 * math.pi * (radius - d), rel=1e-12)
    car = VehicleParams(rho_aero=0.0, v_max=80.0)
    assert limits.speed_profile(line, car).lap_time == pytest.approx(
        2.0 * math.pi * (radius - d) / math.sqrt(12.0 * (radius - d)), rel=1e-12)


def _straight_closed_form(length: float, v0: float, a: float = 8.0, v_max: float = 25.0) -> tuple[float, callable]:
    """dV/dt = a (1 - V^2 / v_max^2) from V(0) = v0: V(t) = v_max tanh(a t / v_max + c) with
    c = artanh(v0 / v_max), x(t) = (v_max^2 / a) ln(cosh(a t / v_max + c) / cosh c); so the time
    to cover L is (v_max / a) (arcosh(cosh(c) exp(a L / v_max^2)) - c), and V(x) follows."""
    c = math.atanh(v0 / v_max)

    def time_at(x):
        return (v_max / a) * (np.arccosh(math.cosh(c) * np.exp(a * np.asarray(x) / v_max**2)) - c)

    def speed_at(x):
        return v_max * np.tanh(a * time_at(x) / v_max + c)

    return float(time_at(length)), speed_at


@pytest.mark.parametrize("v0", [0.0, 10.0])
def test_a_straight_from_a_standing_or_rolling_start_takes_the_closed_form_time(v0: float) -> None:
    """The drive limit (8 m/s^2) is inside the gg circle (12 m/s^2), so it alone binds. The
    speeds come from RK4 steps in V^2 (error O(h^4): 2e-8 m/s at h = 1 m). The segment times
    2 h / (V_k + V_k+1) are exact under constant acceleration, so their error is the change of
    acceleration within a step, O(h^2) overall from a rolling start (measured 9.8e-6 relative at
    h = 1 m, 2.4e-6 at 0.5 m) and O(h^1.5) from standstill, where it scales as 1/V^3 (1.8e-4 at
    1 m, 6.5e-5 at 0.5 m). The tolerances are twice those, and halving h must cut the error by
    the order's factor (4, or 2^1.5 = 2.8)."""
    length = 300.0
    want, speed_at = _straight_closed_form(length, v0)
    errors = []
    for ds in (1.0, 0.5):
        straight = tr.straight(length=length, ds=ds)
        profile = limits.speed_profile(limits.centerline(straight), VehicleParams(), v_start=v0)
        errors.append(abs(profile.lap_time / want - 1.0))
        np.testing.assert_allclose(profile.v, speed_at(profile.line.sigma), rtol=0, atol=1e-7)
    bound = 4e-4 if v0 == 0 else 2e-5
    assert errors[0] < bound and errors[1] < bound / (2.8 if v0 == 0 else 4.0)
    assert errors[0] / errors[1] > (2.5 if v0 == 0 else 3.8)


def _segment_limits(profile: limits.SpeedProfile, car: VehicleParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per segment of a closed line: the mean longitudinal acceleration (the V^2 difference over
    twice the length), and the largest drive and braking limits at its ends and its middle (the
    curvature linear along the segment, V^2 the mean of the ends')."""
    line = profile.line
    w0 = profile.v**2
    w1 = np.roll(w0, -1)
    k0, k1 = np.abs(line.kappa), np.abs(np.roll(line.kappa, -1))
    seg = np.diff(np.append(line.sigma, line.length))
    drive, brake = np.full(w0.shape, -np.inf), np.full(w0.shape, -np.inf)
    for w, k in ((w0, k0), (w1, k1), (0.5 * (w0 + w1), 0.5 * (k0 + k1))):
        v = np.sqrt(w)
        rho = car.rho(v)
        room = np.sqrt(np.maximum(rho**2 - (k * w) ** 2, 0.0))
        drive = np.maximum(drive, np.minimum(car.ax_max(v), room))
        brake = np.maximum(brake, room)
    return (w1 - w0) / (2.0 * seg), drive, brake


@pytest.mark.parametrize("name", ["Monza", "Spa", "Norisring"])
def test_the_profile_stays_inside_the_gg_limits(name: str) -> None:
    _check_gg(name)


@pytest.mark.slow
@pytest.mark.parametrize("name", CIRCUITS)
def test_the_profile_stays_inside_the_gg_limits_on_every_circuit(name: str) -> None:
    _check_gg(name)


def _check_gg(name: str) -> None:
    """Lateral accelerations at the grid points are within rho(V) to rounding, and every
    segment's mean longitudinal acceleration is within the drive and braking limits at its ends
    or middle: each step of the passes keeps its mean slope within the mean of its ends'
    limits, so to rounding."""
    car = VehicleParams()
    track = tr.get_track(name)
    for line in ("raceline", "centerline"):
        profile = limits.speed_profile(limits.get_line(track, line), car)
        v = profile.v
        assert np.all(np.abs(profile.ay) <= car.rho(v) * (1 + 1e-9)), line
        assert np.all(v <= car.v_max * (1 + 1e-12))
        ax, drive, brake = _segment_limits(profile, car)
        rounding = 1e-9  # m/s^2
        assert np.all(ax <= drive + rounding), (line, float(np.max(ax - drive)))
        assert np.all(-ax <= brake + rounding), (line, float(np.max(-ax - brake)))
