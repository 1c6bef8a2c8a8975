"""The planners and the racing-line driver with the fastest car class (the Dallara AV-21,
87.6 m/s): alone from Monza's grid, each drives the first 1,000 m (the start straight at
over 80 m/s and the braking zone into the first chicane) without leaving the track, within
10% of the quasi-steady-state time of the same car from the same start speed. The planners
are slow tests (their compilations); the racing-line driver is cheap."""

from __future__ import annotations

import numpy as np
import pytest

import racing_env
from planners import make_agent
from racing_env import limits
from racing_env.car_classes import CAR_CLASSES, get_car

DISTANCE = 1000.0  # [m]
FASTEST = max(CAR_CLASSES, key=lambda name: float(get_car(name).v_max))


@pytest.mark.parametrize("spec", [pytest.param(spec, marks=pytest.mark.slow) for spec in ("ilqr", "ilqgame-ol", "ilqgame-fb")]
                         + ["raceline"])
def test_each_agent_drives_monzas_first_kilometre_with_the_fastest_class(spec):
    car = get_car(FASTEST)
    env = racing_env.parallel_env(track="Monza", num_agents=1, race_distance=DISTANCE, max_steps=600, vehicles=car)
    observations, infos = env.reset(seed=0)
    start_speed = float(env.state()[0, 1])
    agent = make_agent(spec)
    agent.reset(0, 0, env)
    off, finish, top = 0, None, 0.0
    while env.agents:
        action = agent.act(observations["car_0"], env.state())
        observations, _, _, _, infos = env.step({"car_0": action})
        off += int(infos["car_0"]["off_track"])
        finish = infos["car_0"]["finish_time"]
        top = max(top, float(env.state()[0, 1]))
    line = limits.get_line(env.track, "raceline")
    profile = limits.speed_profile(line, car, v_start=start_speed)
    qss = float(np.interp(DISTANCE, np.asarray(env.track.s), profile.t))  # from s = 0 at the start speed
    assert finish is not None and off == 0, (finish, off)
    assert finish < 1.10 * qss, (finish, qss)
    assert top > 0.9 * float(car.v_max)  # the class's speed, not the paper car's 25 m/s
