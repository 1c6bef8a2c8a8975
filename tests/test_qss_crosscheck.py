"""The QSS lap-time limit (racing_env.limits.speed_profile) against an independent
implementation: TUMFTM's trajectory-planning-helpers ``calc_vel_profile`` (PyPI
``trajectory-planning-helpers``, the ``crosscheck`` extra) on the same line and the same
limits, for every car class.

The two integrate differently (RK4 in ``V^2`` with the gg room's kink handled, against one
explicit step per segment with the limits at its start, which is slower by a little on every
segment), so they agree to a fraction of a percent, not to rounding: within 0.5%.
Slow (the helper's passes are Python loops over every point of the lap)."""

from __future__ import annotations

import numpy as np
import pytest

from racing_env import limits
from racing_env.car_classes import car_names, get_car
from racing_env.track import get_track

tph = pytest.importorskip("trajectory_planning_helpers", reason="pip install 'racing-games[crosscheck]'")

pytestmark = pytest.mark.slow

#: Speed step [m/s] of the tables handed to the helper, which interpolates linearly in V.
TABLE_STEP = 0.25


def helper_lap_time(line: limits.RacingLine, car) -> float:
    """The flying lap [s] of ``calc_vel_profile`` on ``line``: the car's ``rho(V)`` as the
    ggv's longitudinal and lateral limits with exponent 2 (the gg circle), its drive limit
    ``drive_max(V)`` as the machines' limit, its drag ``c_drag`` times its mass as the
    helper's ``drag_coeff`` with that mass (zero for a class without drag), its v_max; the lap
    time from the same segments."""
    speeds = np.append(np.arange(0.0, float(car.v_max), TABLE_STEP), float(car.v_max))
    rho = np.asarray(car.rho(speeds))
    ggv = np.column_stack([speeds, rho, rho])
    machines = np.column_stack([speeds, np.asarray(car.drive_max(speeds))])
    seg = np.diff(np.append(line.sigma, line.length))
    mass = float(car.mass)
    v = tph.calc_vel_profile.calc_vel_profile(machines, np.asarray(line.kappa), seg, True, float(car.c_drag) * mass,
                                             mass, ggv=ggv, v_max=float(car.v_max), dyn_model_exp=2.0)
    closed = np.append(v, v[0])
    return float(np.sum(2.0 * seg / (closed[:-1] + closed[1:])))


@pytest.mark.parametrize("circuit", ["Monza", "Spa", "Norisring"])
@pytest.mark.parametrize("name", car_names())
def test_the_qss_lap_agrees_with_trajectory_planning_helpers(circuit, name):
    line = limits.get_line(get_track(circuit), "raceline")
    car = get_car(name)
    ours = limits.speed_profile(line, car).lap_time
    assert helper_lap_time(line, car) == pytest.approx(ours, rel=0.005)
