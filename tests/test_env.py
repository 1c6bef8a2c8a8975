"""Tests of the PettingZoo env (racing_env.env): API conformance, determinism, physics limits,
incidents, finishing, input validation, spaces, rendering and scenarios."""

import math
import warnings

import jax.numpy as jnp
import numpy as np
import pytest
from pettingzoo.test import api_test, parallel_api_test, parallel_seed_test

import racing_env
from racing_env import track as tr
from racing_env.config import RaceConfig
from racing_env.env import RacingParallelEnv
from racing_env.observation import cars_racing
from racing_env.render import plot_race, save_gif
from racing_env.vehicle import VehicleParams

COAST = np.zeros(2)


# --- shared tracks and envs (the jitted step compiles once per track and number of cars) ----
@pytest.fixture(scope="module")
def trefoil() -> tr.Track:
    return tr.trefoil()


@pytest.fixture(scope="module")
def long_straight() -> tr.Track:
    return tr.straight(length=3000.0)


@pytest.fixture(scope="module")
def env2(trefoil):
    return racing_env.parallel_env(track=trefoil, num_agents=2)


@pytest.fixture(scope="module")
def straight_env(long_straight):
    """Two cars on a 3 km straight, race long enough never to finish in these tests."""
    return racing_env.parallel_env(track=long_straight, num_agents=2, race_distance=2900.0, max_steps=5000)


def _x0(*cars):
    """Joint state from per-car (s, V, n[, chi, ax, ay]) tuples."""
    x = np.zeros((len(cars), 6))
    for i, car in enumerate(cars):
        x[i, : len(car)] = car
    return x


def _same(a, b) -> bool:
    """Recursive equality: arrays bit for bit (dtype, shape, bytes), floats NaN-aware."""
    if type(a) is not type(b):
        return False
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    if isinstance(a, float):
        return (math.isnan(a) and math.isnan(b)) or a == b
    return a == b


def _drive(env, policy, steps):
    """Step ``env`` with ``policy(k) -> {agent: action}``; returns the joint states (steps, N, 6)."""
    states = []
    for k in range(steps):
        env.step(policy(k))
        states.append(env.state())
    return np.array(states)


# --- PettingZoo conformance ------------------------------------------------------------------
@pytest.mark.parametrize("num_agents", [2, 3])
def test_pettingzoo_parallel_api_test(trefoil, num_agents):
    """PettingZoo's own parallel_api_test passes (2 and 3 cars, with truncation at max_steps)."""
    env = racing_env.parallel_env(track=trefoil, num_agents=num_agents, max_steps=40)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        parallel_api_test(env, num_cycles=50)
    # The API test resets with options={"options": 1}: the env ignores unknown keys with a
    # warning; nothing else may warn (e.g. "Live agent was not given ...").
    messages = [str(w.message) for w in caught]
    assert all("ignoring unknown reset options ['options']" in m for m in messages), messages


def test_the_aec_env_passes_pettingzoos_api_test_and_races_the_parallel_env(trefoil):
    """``racing_env.env()`` is PettingZoo's AEC form of the race: PettingZoo's own api_test
    passes, and cars acting in turn race what the parallel env races with the same actions,
    bit for bit (the race steps once every car has acted)."""
    aec = racing_env.env(track=trefoil, num_agents=3, max_steps=40)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the API test's unknown reset options (see the parallel test)
        api_test(aec, num_cycles=50)
    assert isinstance(aec.unwrapped, racing_env.RacingParallelEnv)
    parallel = racing_env.parallel_env(track=trefoil, num_agents=3, max_steps=40)
    aec.reset(seed=4)
    parallel.reset(seed=4)
    actions = np.random.default_rng(0).uniform(-1, 1, (12, 3, 2))
    for step in actions:
        for agent in parallel.agents:
            assert aec.agent_selection == agent
            aec.step(step[int(agent.split("_")[1])])
        observations, rewards, *_ = parallel.step({agent: step[int(agent.split("_")[1])] for agent in parallel.agents})
        assert aec.state().tobytes() == parallel.state().tobytes()
        for agent in parallel.agents:
            assert aec.observe(agent).tobytes() == observations[agent].tobytes()
            assert aec.rewards[agent] == rewards[agent]


def test_pettingzoo_parallel_seed_test(trefoil):
    """PettingZoo's parallel_seed_test passes with a factory of fresh envs."""
    parallel_seed_test(lambda: racing_env.parallel_env(track=trefoil, race_distance=60.0), num_cycles=80)


def test_multi_step_determinism_bit_for_bit(trefoil):
    """Same seed, two instances, 200 steps of seeded random actions: identical in every output."""
    envs = [racing_env.parallel_env(track=trefoil, num_agents=2, race_distance=60.0) for _ in range(2)]
    first = [env.reset(seed=123) for env in envs]
    assert _same(first[0], first[1])
    rng = np.random.default_rng(7)
    finished_races = 0
    for _ in range(200):
        if not envs[0].agents:  # the short race is over: start the next one (RNG carries on)
            finished_races += 1
            resets = [env.reset() for env in envs]
            assert _same(resets[0], resets[1])
        # random, biased forward so that races finish; |jx| up to 1.2 also exercises clipping
        actions = {a: rng.uniform([-0.4, -0.3], [1.2, 0.3]) for a in envs[0].agents}
        outs = [env.step(dict(actions)) for env in envs]
        for part in range(5):  # observations, rewards, terminations, truncations, infos
            assert _same(outs[0][part], outs[1][part]), part
        assert _same(envs[0].state(), envs[1].state())
        assert envs[0].agents == envs[1].agents
    assert finished_races >= 2  # the comparison covered finishing and new races


# --- physics limits --------------------------------------------------------------------------
def test_flat_out_reaches_but_never_exceeds_v_max(straight_env):
    """A car at full throttle from standstill approaches v_max from below and gets within 1e-3."""
    env = straight_env
    v_max = float(env.game.vehicles.v_max[0])
    env.reset(seed=0, options={"x0": _x0((100.0, 0.0, 2.0), (50.0, 10.0, -3.0))})
    states = _drive(env, lambda k: {"car_0": np.array([1.0, 0.0]), "car_1": COAST}, 350)
    speed = states[:, 0, 1]
    assert speed.max() <= v_max + 1e-9
    assert abs(speed[-1] - v_max) < 1e-3
    assert np.all(np.diff(speed) >= -1e-12)  # monotone acceleration, no overshoot-and-return


def test_gg_and_ax_limits_hold_and_speed_stays_non_negative(straight_env):
    """Asking for too much lateral/longitudinal acceleration never leaves the gg diamond; V >= 0."""
    env = straight_env
    veh = env.game.vehicles
    env.reset(seed=0, options={"x0": _x0((100.0, 20.0, 0.0), (50.0, 10.0, -3.0))})

    def policy(k):
        action = [0.0, 1.0] if k < 80 else ([1.0, 1.0] if k < 160 else [-1.0, -1.0])
        return {"car_0": np.array(action), "car_1": COAST}

    states = _drive(env, policy, 240)
    v, ax, ay = states[:, 0, 1], states[:, 0, 4], states[:, 0, 5]
    rho = veh.rho_0[0] + veh.rho_aero[0] * v**2
    ax_max = veh.ax_max_0[0] * (1.0 - (v / veh.v_max[0]) ** 2)
    assert np.max(np.hypot(ax, ay) - rho) <= 1e-9
    assert np.max(ax - ax_max) <= 1e-9
    assert np.all(v >= 0.0)
    # The limits were actually reached (the test is not vacuous).
    assert np.max(np.hypot(ax, ay) - rho) > -1e-6


def test_hard_braking_stops_without_reversing(straight_env):
    """Braking flat out ([-1, 0]) stops the car: V >= 0 always, then V == 0 and s never decreases."""
    env = straight_env
    env.reset(seed=0, options={"x0": _x0((100.0, 20.0, 0.0), (50.0, 10.0, -3.0))})
    states = _drive(env, lambda k: {"car_0": np.array([-1.0, 0.0]), "car_1": COAST}, 120)
    v, s = states[:, 0, 1], states[:, 0, 0]
    assert np.all(v >= 0.0)
    assert np.all(v[-50:] == 0.0)
    assert np.all(np.diff(s) >= 0.0), np.diff(s).min()  # a stopped car does not creep backwards


def test_stopped_car_does_not_turn_on_the_spot(straight_env):
    """A car at rest asked for full lateral jerk keeps its heading and lateral offset."""
    env = straight_env
    env.reset(seed=0, options={"x0": _x0((100.0, 0.0, 1.0, 0.1), (50.0, 10.0, -3.0))})
    states = _drive(env, lambda k: {"car_0": np.array([0.0, 1.0]), "car_1": COAST}, 10)
    np.testing.assert_array_equal(states[:, 0, 3], 0.1)
    np.testing.assert_array_equal(states[:, 0, 2], 1.0)
    assert np.all(states[:, 0, 1] == 0.0)


def test_slow_car_turns_no_tighter_than_its_steering_allows(straight_env):
    """At 3 m/s with full lateral jerk, |ay| stays within V^2 / min_turn_radius and the
    heading turns at most V dt / min_turn_radius per step (on a straight, V constant:
    |dchi/dt| = |ay| / V <= V / R). The point mass alone would spin at up to rho / V."""
    env = straight_env
    veh = env.game.vehicles
    radius, dt, v0 = float(veh.min_turn_radius[0]), env.game.dt, 3.0
    env.reset(seed=0, options={"x0": _x0((100.0, v0, 0.0), (50.0, 10.0, -3.0))})
    states = _drive(env, lambda k: {"car_0": np.array([0.0, 1.0]), "car_1": COAST}, 30)
    v, chi, ay = states[:, 0, 1], states[:, 0, 3], states[:, 0, 5]
    np.testing.assert_array_equal(v, v0)
    cap = v0**2 / radius
    assert np.max(np.abs(ay)) <= cap * (1 + 1e-12)
    assert np.max(np.abs(ay)) == pytest.approx(cap, rel=1e-12)  # the limit was reached
    # Rounding only: the in-step ay is linear in time and below the cap throughout.
    assert np.max(np.abs(np.diff(chi))) <= v0 * dt / radius * (1 + 1e-9)
    assert np.max(np.abs(np.diff(chi))) == pytest.approx(v0 * dt / radius, rel=1e-9)


# --- incidents ---------------------------------------------------------------------------------
def test_overlapping_cars_collide(env2):
    """Overlapping footprints are reported to both cars, with contact_with and the penalty."""
    env2.reset(seed=0, options={"x0": _x0((100.0, 10.0, 0.0), (101.0, 10.0, 0.5))})
    _, rewards, _, _, infos = env2.step({"car_0": COAST, "car_1": COAST})
    assert infos["car_0"]["collided"] and infos["car_1"]["collided"]
    assert infos["car_0"]["contact_with"] == ["car_1"] and infos["car_1"]["contact_with"] == ["car_0"]
    assert infos["car_0"]["reward_terms"]["collision"] == env2.config.reward.collision
    assert env2.agents == ["car_0", "car_1"]  # default on_collision="penalty" keeps them racing


def test_far_apart_cars_do_not_collide(env2):
    """Cars 50 m apart, or side by side with a lateral gap, are not in contact."""
    for x0 in (_x0((100.0, 10.0, 0.0), (150.0, 10.0, 0.0)), _x0((100.0, 1.0, 0.0), (100.0, 1.0, 2.3))):
        env2.reset(seed=0, options={"x0": x0})
        _, _, _, _, infos = env2.step({"car_0": COAST, "car_1": COAST})
        for agent in ("car_0", "car_1"):
            assert not infos[agent]["collided"] and infos[agent]["contact_with"] == []
            assert infos[agent]["reward_terms"]["collision"] == 0.0


def test_rotated_footprints_collide(env2):
    """Side by side 2.3 m apart (width 2 m): a yawed car (chi = 0.3) sweeps into its neighbour."""
    env2.reset(seed=0, options={"x0": _x0((100.0, 1.0, 0.0), (100.0, 1.0, 2.3, -0.3))})
    _, _, _, _, infos = env2.step({"car_0": COAST, "car_1": COAST})
    assert infos["car_0"]["collided"] and infos["car_1"]["contact_with"] == ["car_0"]


def test_off_track_detection(env2, trefoil):
    """A car whose centre is beyond the boundary is off track; one on the centre line is not."""
    w = float(trefoil.width_left_at(300.0))
    env2.reset(seed=0, options={"x0": _x0((300.0, 10.0, w + 0.5), (200.0, 10.0, 0.0))})
    _, _, _, _, infos = env2.step({"car_0": COAST, "car_1": COAST})
    assert infos["car_0"]["off_track"] and not infos["car_1"]["off_track"]
    assert infos["car_0"]["reward_terms"]["off_track"] == env2.config.reward.off_track
    env2.reset(seed=0, options={"x0": _x0((300.0, 10.0, -w - 0.5), (200.0, 10.0, w - 1.0))})
    _, _, _, _, infos = env2.step({"car_0": COAST, "car_1": COAST})
    assert infos["car_0"]["off_track"] and not infos["car_1"]["off_track"]


def test_terminate_on_collision_retires_the_colliding_cars(trefoil):
    """With on_collision='terminate' the two colliding cars terminate and leave env.agents
    (ghost cars: the reward is the progress of a car that nothing pushed)."""
    env = racing_env.parallel_env(track=trefoil, num_agents=3, on_collision="terminate", contact="ghost")
    env.reset(seed=0, options={"x0": _x0((100.0, 10.0, 0.0), (101.0, 10.0, 0.5), (300.0, 10.0, 0.0))})
    observations, rewards, terms, truncs, infos = env.step({a: COAST for a in env.agents})
    assert terms == {"car_0": True, "car_1": True, "car_2": False}
    # the observations of this very step already flag the retired cars as out of the race
    np.testing.assert_array_equal(cars_racing(observations["car_2"], 2, 3), [False, False, True])
    np.testing.assert_array_equal(cars_racing(observations["car_0"], 0, 3), [True, False, True])
    assert not any(truncs.values())
    assert env.agents == ["car_2"]
    assert infos["car_0"]["out"] and infos["car_1"]["out"] and not infos["car_2"]["out"]
    # no collision penalty in terminate mode, just the progress of ~1 m (V dt on a gentle curve)
    assert infos["car_0"]["reward_terms"]["collision"] == 0.0
    assert rewards["car_0"] == pytest.approx(env.config.reward.progress * 1.0, rel=1e-3)
    with pytest.raises(KeyError, match="no longer racing"):
        env.step({"car_0": COAST, "car_2": COAST})
    _, _, terms, _, _ = env.step({"car_2": COAST})
    assert set(terms) == {"car_2"}


# --- finishing ----------------------------------------------------------------------------------
def test_faster_car_finishes_first(long_straight):
    """On a short race the faster car finishes first: position 1, interpolated finish_time, terminated."""
    env = racing_env.parallel_env(track=long_straight, num_agents=2, race_distance=150.0)
    # Coasting on a straight: s(t) = s0 + V t exactly, so the crossing times are known.
    env.reset(seed=0, options={"x0": _x0((101.5, 10.0, 2.0), (101.0, 20.0, -2.0))})
    t_fast, t_slow = (150.0 - 101.0) / 20.0, (150.0 - 101.5) / 10.0
    results = {}
    step = 0
    while env.agents:
        _, rewards, terms, truncs, infos = env.step({a: COAST for a in env.agents})
        step += 1
        for agent, done in terms.items():
            if done:
                results[agent] = (step, rewards[agent], infos[agent])
        if step == 1:
            assert rewards["car_0"] == pytest.approx(0.1 * 10.0 * 0.1, rel=1e-9)  # progress 0.1 / m
            assert infos["car_0"]["finish_time"] is None and not infos["car_0"]["finished"]
        assert not any(truncs.values())
    (k1, r1, fast), (k0, r0, slow) = results["car_1"], results["car_0"]
    assert k1 < k0
    assert fast["position"] == 1 and slow["position"] == 2
    assert fast["finished"] and slow["finished"]
    # Linear interpolation inside the step is exact for constant speed (rounding only).
    assert fast["finish_time"] == pytest.approx(t_fast, abs=1e-9)
    assert slow["finish_time"] == pytest.approx(t_slow, abs=1e-9)
    assert (k1 - 1) * 0.1 < fast["finish_time"] <= k1 * 0.1
    assert fast["reward_terms"]["finish"] == env.config.reward.finish
    assert slow["reward_terms"]["finish"] == 0.0


def test_the_lead_reward_sums_to_the_margin_at_the_finish(long_straight):
    """Only the lead term (weight 1): coasting on a straight, s(t) = s0 + V t, so its sum over
    each car's race is known. The fast car (20 m/s from 101.0 m) crosses the line at 2.45 s,
    when the slow one (10 m/s from 101.5 m) is at 126.0 m: a lead of 24.0 m, from 0.5 m
    behind at the start, +24.5. The slow car crosses at 4.85 s, when the fast one, carried on
    at 20 m/s from the line, stands at 150 + 20 (4.85 - 2.45) = 198.0 m: a lead of -48.0 m
    (the 2.4 s it lost times the winner's speed), from +0.5 m, -48.5."""
    from racing_env import RewardConfig

    reward = RewardConfig(progress=0.0, position=0.0, collision=0.0, off_track=0.0, finish=0.0, lead=1.0)
    env = racing_env.parallel_env(track=long_straight, num_agents=2, race_distance=150.0, reward=reward)
    env.reset(seed=0, options={"x0": _x0((101.5, 10.0, 2.0), (101.0, 20.0, -2.0))})
    returns = {"car_0": 0.0, "car_1": 0.0}
    while env.agents:
        _, rewards, _, _, _ = env.step({a: COAST for a in env.agents})
        for agent, r in rewards.items():
            returns[agent] += r
    assert returns["car_1"] == pytest.approx(24.5, abs=1e-9)
    assert returns["car_0"] == pytest.approx(-48.5, abs=1e-9)


def test_the_time_reward_sums_to_the_finish_time(long_straight):
    """Only the time term (weight -1 per second), the race of the lead test above: the fast
    car crosses the line at 2.45 s and the slow one at 4.85 s, and each is charged exactly
    its time, though neither crosses at the end of a step."""
    from racing_env import RewardConfig

    reward = RewardConfig(progress=0.0, position=0.0, collision=0.0, off_track=0.0, finish=0.0, time=-1.0)
    env = racing_env.parallel_env(track=long_straight, num_agents=2, race_distance=150.0, reward=reward)
    env.reset(seed=0, options={"x0": _x0((101.5, 10.0, 2.0), (101.0, 20.0, -2.0))})
    returns, finish_times = {"car_0": 0.0, "car_1": 0.0}, {}
    while env.agents:
        _, rewards, _, _, infos = env.step({a: COAST for a in env.agents})
        for agent, r in rewards.items():
            returns[agent] += r
            finish_times[agent] = infos[agent]["finish_time"]
    assert finish_times == pytest.approx({"car_1": 2.45, "car_0": 4.85}, abs=1e-12)
    assert returns["car_1"] == pytest.approx(-2.45, abs=1e-9)
    assert returns["car_0"] == pytest.approx(-4.85, abs=1e-9)


# --- bad input ---------------------------------------------------------------------------------
BAD_ACTIONS = [
    ({"car_0": np.array([np.nan, 0.0]), "car_1": COAST}, ValueError, "car_0 must be finite"),
    ({"car_0": np.array([0.0, np.inf]), "car_1": COAST}, ValueError, "car_0 must be finite"),
    ({"car_0": np.zeros(3), "car_1": COAST}, ValueError, r"car_0 must have shape \(2,\)"),
    ({"car_0": 0.5, "car_1": COAST}, ValueError, r"must have shape \(2,\)"),
    ({"car_0": COAST, "car_1": COAST, "car_9": COAST}, KeyError, "unknown agent"),
    ({"car_0": COAST}, KeyError, r"missing action\(s\) for \['car_1'\]"),
    ([COAST, COAST], TypeError, "actions must be a mapping"),
    (np.zeros((2, 2)), TypeError, "actions must be a mapping"),
    ({"car_0": ["0.5", "1"], "car_1": COAST}, TypeError, "car_0 must hold real numbers"),
    ({"car_0": COAST, "car_1": [True, False]}, TypeError, "car_1 must hold real numbers"),
    ({"car_0": np.array([True, False]), "car_1": COAST}, TypeError, "car_0 must hold real numbers"),
    ({"car_0": [0.5, True], "car_1": COAST}, TypeError, "car_0 must hold real numbers"),
    ({"car_0": np.array([None, 1.0]), "car_1": COAST}, TypeError, "car_0 must hold real numbers"),
]


@pytest.mark.parametrize("actions, error, message", BAD_ACTIONS)
def test_bad_actions_are_refused_without_side_effects(env2, actions, error, message):
    """NaN/inf, wrong shapes, non-numeric values (which NumPy would turn into floats), a
    container other than a mapping, unknown and missing agents raise; state, agents, step
    count unchanged."""
    env2.reset(seed=5)
    env2.step({"car_0": COAST, "car_1": COAST})
    before = (env2.state(), list(env2.agents), env2._steps)
    with pytest.raises(error, match=message):
        env2.step(actions)
    assert env2.state().tobytes() == before[0].tobytes()
    assert env2.agents == before[1] and env2._steps == before[2]
    env2.step({"car_0": COAST, "car_1": COAST})  # the env still works
    assert env2._steps == before[2] + 1


def test_numeric_lists_and_jax_arrays_are_accepted_as_actions(env2):
    """Lists of Python numbers and JAX arrays act like the equal float64 NumPy arrays."""
    results = []
    for a0, a1 in ((np.array([0.5, 1.0]), np.array([-1.0, 0.0])), ([0.5, 1], (-1, 0.0)),
                   (jnp.asarray([0.5, 1.0]), np.array([-1.0, 0.0], dtype=np.float32))):
        env2.reset(seed=4)
        env2.step({"car_0": a0, "car_1": a1})
        results.append(env2.state())
    assert all(r.tobytes() == results[0].tobytes() for r in results)


def test_out_of_box_actions_are_clipped(env2):
    """A finite action outside [-1, 1]^2 acts like the clipped one (documented behaviour)."""
    x0 = _x0((100.0, 10.0, 0.0), (200.0, 10.0, 0.0))
    env2.reset(seed=0, options={"x0": x0})
    env2.step({"car_0": np.array([5.0, -7.0]), "car_1": COAST})
    big = env2.state()
    env2.reset(seed=0, options={"x0": x0})
    env2.step({"car_0": np.array([1.0, -1.0]), "car_1": COAST})
    assert big.tobytes() == env2.state().tobytes()


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: racing_env.parallel_env(num_agents=0), r"num_agents must be an integer in \[1, 20\]"),
        (lambda: tr.straight(width_left=-1.0), r"Track.width_left must be > 0"),
        (lambda: tr.straight(width_right=0.0), r"Track.width_right must be > 0"),
        (lambda: tr.from_centerline(np.arange(20.0), np.zeros(20), np.full(20, 3.0), np.full(20, -1.0),
                                    closed=False), "width_left must be > 0"),
        (lambda: VehicleParams(v_max=0.0), "VehicleParams.v_max must be > 0"),
        (lambda: VehicleParams(v_max=-5.0), "VehicleParams.v_max must be > 0"),
        (lambda: racing_env.parallel_env(scenario="monaco"), "unknown scenario 'monaco'"),
        (lambda: racing_env.parallel_env(render_mode="ascii"), "render_mode must be None, 'rgb_array' or 'human'"),
        (lambda: racing_env.parallel_env(on_collision="explode"), "on_collision must be one of"),
        (lambda: racing_env.parallel_env(track="no_such_track"), "unknown track 'no_such_track'"),
        (lambda: racing_env.parallel_env(scenario="paper", num_agents=3), "exactly 2 cars"),
        (lambda: RaceConfig(vehicles=[VehicleParams()] * 3, num_agents=2), "3 VehicleParams for num_agents=2"),
        (lambda: RaceConfig(race_distance=math.inf), "race_distance must be a finite number > 0"),
        (lambda: RaceConfig(race_distance=math.nan), "race_distance must be a finite number > 0"),
        (lambda: RaceConfig(preview_distances=(0.0, math.nan)), "preview_distances must be non-empty, finite"),
        (lambda: RaceConfig(preview_distances=(0.0, math.inf)), "preview_distances must be non-empty, finite"),
        # the default finish line of an open track, 20 m before its end, lies behind the grid
        (lambda: racing_env.parallel_env(track=tr.straight(length=15.0), num_agents=1),
         r"finish line at s = -5 m is not ahead of every start"),
        (lambda: racing_env.parallel_env(track="straight", race_distance=8.0),
         r"finish line at s = 8 m is not ahead of every start"),
        (lambda: racing_env.parallel_env(track="straight", race_distance=300.5),
         r"finish line at s = 300.5 m lies beyond the end of the open track 'straight' \(300 m\)"),
    ],
)
def test_bad_configuration_is_refused(make, message):
    """Invalid tracks, vehicles and race configurations raise ValueError with a helpful message."""
    with pytest.raises(ValueError, match=message):
        make()


def test_bad_reset_x0_is_refused(env2):
    """reset(options={'x0': ...}) refuses a wrong shape or non-finite entries."""
    for x0 in (np.zeros((3, 6)), np.zeros(12), np.full((2, 6), np.nan)):
        with pytest.raises(ValueError, match=r"options\['x0'\] must be a finite array of shape \(2, 6\)"):
            env2.reset(seed=0, options={"x0": x0})


def test_step_after_the_race_is_over_raises(trefoil):
    """Stepping a finished race (no live agents) raises until reset()."""
    env = racing_env.parallel_env(track=trefoil, num_agents=2, max_steps=2)
    env.reset(seed=0)
    for _ in range(2):
        env.step({a: COAST for a in env.agents})
    assert env.agents == []
    with pytest.raises(RuntimeError, match="call reset"):
        env.step({})


# --- spaces ------------------------------------------------------------------------------------
def test_spaces_are_cached_and_match_observations(env2):
    """observation_space/action_space return one object per agent; observations and state fit them."""
    for agent in env2.possible_agents:
        assert env2.observation_space(agent) is env2.observation_space(agent)
        assert env2.action_space(agent) is env2.action_space(agent)
    with pytest.raises(KeyError, match="unknown agent"):
        env2.observation_space("car_5")
    observations, _ = env2.reset(seed=0)
    obs_after, *_ = env2.step({"car_0": COAST, "car_1": COAST})
    for obs in (observations, obs_after):
        for agent, o in obs.items():
            space = env2.observation_space(agent)
            assert o.dtype == space.dtype == np.float32 and o.shape == space.shape
            assert space.contains(o)
    # 8 own + 7 per other car + 3 per preview distance
    assert env2.observation_space("car_0").shape == (8 + 7 + 3 * len(env2.config.preview_distances),)
    state = env2.state()
    assert state.shape == (2, 6) and state.dtype == np.float64 and env2.state_space.contains(state)
    assert env2.action_space("car_0").shape == (2,)
    assert np.all(env2.action_space("car_0").low == -1.0) and np.all(env2.action_space("car_0").high == 1.0)


def test_step_returns_plain_python_values_and_writable_observations(env2):
    """Rewards, flags and info entries are Python scalars (JSON-ready, no NumPy 0-d arrays);
    observations are the caller's own arrays (RL code may normalise them in place)."""
    observations, infos = env2.reset(seed=0)
    for step in range(2):
        if step:
            observations, rewards, terminations, truncations, infos = env2.step({"car_0": COAST, "car_1": COAST})
            assert all(type(r) is float for r in rewards.values())
            assert all(type(f) is bool for f in (*terminations.values(), *truncations.values()))
        for agent, o in observations.items():
            assert o.flags.writeable
            o *= 2.0  # in-place normalisation, as RL wrappers do
        info = infos["car_0"]
        assert (type(info["s"]), type(info["lap"]), type(info["position"])) == (float, int, int)
        assert all(type(info[k]) is bool for k in ("collided", "off_track", "finished", "out"))
        assert all(type(v) is float for v in info["reward_terms"].values())
    obs_again, *_ = env2.step({"car_0": COAST, "car_1": COAST})
    assert np.all(np.isfinite(obs_again["car_0"]))


# --- rendering ---------------------------------------------------------------------------------
@pytest.mark.parametrize("track_name, size", [("trefoil", 128), ("straight", 96)])
def test_rgb_array_render(trefoil, track_name, size):
    """render_mode='rgb_array' returns a uint8 (size, size, 3) frame that shows track and cars."""
    track = trefoil if track_name == "trefoil" else "straight"
    env = racing_env.parallel_env(track=track, num_agents=2, render_mode="rgb_array", render_size=size,
                                  race_distance=100.0)
    env.reset(seed=0)
    frame = env.render()
    assert isinstance(frame, np.ndarray) and frame.dtype == np.uint8 and frame.shape == (size, size, 3)
    colours = {tuple(c) for c in frame.reshape(-1, 3)}
    assert len(colours) >= 4  # grass, asphalt, boundary lines, cars


def test_plot_race_and_save_gif_write_files(env2, tmp_path):
    """plot_race writes a PNG and save_gif a GIF with one image per frame."""
    from PIL import Image

    from racing_env.render import Renderer

    env2.reset(seed=0)
    states = [env2.state()] + list(_drive(env2, lambda k: {"car_0": COAST, "car_1": COAST}, 5))
    xs = np.array(states)
    png = tmp_path / "plots" / "race.png"
    fig = plot_race(env2.track, xs, title="test", path=png)
    assert fig is not None and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    renderer = Renderer(env2.track, env2.game.vehicles, size=64, camera="follow")
    frames = [renderer.frame(x) for x in xs]
    gif = save_gif(frames, tmp_path / "race.gif", fps=5)
    assert gif.read_bytes()[:6] in (b"GIF87a", b"GIF89a")
    with Image.open(gif) as image:
        assert image.n_frames == len(frames) and image.size == (64, 64)


# --- scenarios -----------------------------------------------------------------------------------
def test_paper_scenario_start(long_straight):
    """The 'paper' scenario: ego v_max 20 at 20 m/s ahead on the centre line; opponent v_max 25 at
    23 m/s, 2 m to the left."""
    env = racing_env.parallel_env(track=long_straight, scenario="paper")
    env.reset(seed=0)
    x = env.state()
    np.testing.assert_array_equal(np.asarray(env.game.vehicles.v_max), [20.0, 25.0])
    ego, opp = x
    assert ego[1] == 20.0 and ego[2] == 0.0
    assert opp[1] == 23.0 and opp[2] == 2.0
    assert ego[0] > opp[0]
    np.testing.assert_array_equal(x[:, 3:], 0.0)
    env.reset(seed=99)
    assert env.state().tobytes() == x.tobytes()  # a fixed scene, independent of the seed


def test_grid_starts_are_seeded(env2):
    """The seeded 'grid' start is identical for the same seed and differs across seeds."""
    starts = {}
    for seed in (1, 1, 2):
        obs, _ = env2.reset(seed=seed)
        starts.setdefault(seed, []).append((env2.state(), obs))
    (x_a, obs_a), (x_b, obs_b) = starts[1]
    assert x_a.tobytes() == x_b.tobytes() and _same(obs_a, obs_b)
    assert not np.array_equal(starts[2][0][0], x_a)
    # Unseeded resets continue the seeded stream: reproducible from the seed, and new each time.
    def two_unseeded_resets():
        env2.reset(seed=1)
        states = []
        for _ in range(2):
            env2.reset()
            states.append(env2.state())
        return states

    after, again = two_unseeded_resets(), two_unseeded_resets()
    assert all(a.tobytes() == b.tobytes() for a, b in zip(after, again))
    assert not np.array_equal(after[0], after[1])


def test_random_scenes_are_seeded_inside_the_track_and_apart(trefoil, long_straight):
    """Random scenes: reproducible from the seed, every car inside the track by the margin at
    its own arc length, within the speed range (capped below v_max), no two cars in contact
    by the env's own test, spread over the lap; an open track keeps every car at s >= 0."""
    import jax

    from racing_env.scenarios import random_scenes
    from racing_env.dynamics import N_LAT, S, V
    from racing_env.physics import footprint_overlap
    from racing_env.vehicle import stack_vehicles

    vehicles = [VehicleParams(v_max=20.0), VehicleParams(v_max=25.0), VehicleParams(v_max=12.0)]
    scenes = random_scenes(trefoil, vehicles, 200, seed=5, margin=1.5)
    assert scenes.shape == (200, 3, 6)
    assert scenes.tobytes() == random_scenes(trefoil, vehicles, 200, seed=5, margin=1.5).tobytes()
    assert not np.array_equal(scenes, random_scenes(trefoil, vehicles, 200, seed=4, margin=1.5))
    s, n, v = scenes[..., S], scenes[..., N_LAT], scenes[..., V]
    assert np.all(n <= np.asarray(trefoil.width_left_at(s)) - 1.5)
    assert np.all(-n <= np.asarray(trefoil.width_right_at(s)) - 1.5)
    assert np.all((v >= 10.0) & (v <= 19.0)) and np.all(v[:, 2] <= 0.95 * 12.0)
    # seed 5 draws 4 of these 200 scenes in contact if the (s, n) footprints ignore the
    # 1 - n kappa scaling of the env's contact test
    contact = jax.vmap(footprint_overlap, in_axes=(0, None, None))(scenes, stack_vehicles(vehicles), trefoil)
    assert not np.any(contact)
    assert np.all(s.max(axis=1) - s.min(axis=1) <= 15.0)
    assert np.ptp(np.asarray(trefoil.wrap_s(s[:, 0]))) > 0.9 * trefoil.length  # all over the lap
    np.testing.assert_array_equal(scenes[..., 3:], 0.0)
    assert np.all(random_scenes(long_straight, vehicles, 50, seed=0)[..., S] >= 0.0)
    with pytest.raises(ValueError, match="no room"):
        random_scenes(trefoil, vehicles, 1, margin=20.0)
    with pytest.raises(ValueError, match="speed"):
        random_scenes(trefoil, vehicles, 1, speed=(19.0, 10.0))
    with pytest.raises(ValueError, match="not longer than spread"):
        random_scenes(long_straight, vehicles, 1, spread=2 * long_straight.length)


def test_random_scenes_stay_below_s_max(trefoil):
    """``s_max`` bounds the reference arc length, so no car starts beyond it; a bound at or
    below the lowest reference point leaves no room and is refused."""
    from racing_env.dynamics import S
    from racing_env.scenarios import random_scenes

    vehicles = [VehicleParams()] * 2
    s = random_scenes(trefoil, vehicles, 200, seed=2, s_max=300.0)[..., S]
    assert np.all(s.max(axis=1) < 300.0) and s.max() > 250.0  # the bound is used, not undershot
    with pytest.raises(ValueError, match=r"no room for a scene on track 'trefoil'.*\[0, 0\) m"):
        random_scenes(trefoil, vehicles, 1, s_max=0.0)


def test_anywhere_starts_seeded_scenes_all_over_the_lap_short_of_the_finish(trefoil, long_straight):
    """Scenario ``anywhere``: each reset draws a close-quarters scene from its seed (the same
    seed, the same scene), inside the track, at 5-19 m/s, with every car at least ANYWHERE_MIN_RUN metres
    before the finish line (here a race_distance shorter than the lap) and the scenes spread
    over the whole allowed stretch; a finish too close to the start is refused by name."""
    from racing_env.dynamics import N_LAT, S, V
    from racing_env.scenarios import ANYWHERE_MIN_RUN

    env = racing_env.parallel_env(track=trefoil, num_agents=2, scenario="anywhere", race_distance=700.0)
    starts = []
    for seed in range(40):
        env.reset(seed=seed)
        starts.append(env.state())
    starts = np.stack(starts)
    env.reset(seed=7)
    assert env.state().tobytes() == starts[7].tobytes()
    s, n = starts[..., S], starts[..., N_LAT]
    assert np.all(s <= 700.0 - ANYWHERE_MIN_RUN)
    assert s.max() > 500.0 and s.min() < 100.0  # over the stretch, not bunched
    assert np.all(n <= np.asarray(trefoil.width_left_at(s)) - 1.5)
    assert np.all(-n <= np.asarray(trefoil.width_right_at(s)) - 1.5)
    assert np.all(np.ptp(s, axis=1) <= 15.0)
    speeds = starts[..., V]
    assert np.all((speeds >= 5.0) & (speeds <= 19.0)) and speeds.min() < 8.0 and speeds.max() > 16.0
    # an open track: every car at s >= 0, short of its default finish 20 m before the end
    straight = racing_env.parallel_env(track=long_straight, num_agents=2, scenario="anywhere")
    for seed in range(10):
        straight.reset(seed=seed)
        assert np.all(straight.state()[:, S] >= 0.0)
        assert np.all(straight.state()[:, S] <= long_straight.length - 20.0 - ANYWHERE_MIN_RUN)
    with pytest.raises(ValueError, match="scenario 'anywhere' places its scenes at least 100 m before the finish"):
        racing_env.parallel_env(track=trefoil, num_agents=2, scenario="anywhere", race_distance=80.0)


def test_a_race_from_anywhere_charges_the_time_from_its_own_start(trefoil):
    """A lone car started anywhere races to the same finish line; the time term (weight -1)
    sums to its finish time, which counts from its own start, and the progress term to the
    distance it covered from there (both to float rounding)."""
    from racing_env.config import RewardConfig
    from racing_env.dynamics import S

    env = racing_env.parallel_env(track=trefoil, num_agents=1, scenario="anywhere", race_distance=600.0,
                                  reward=RewardConfig(progress=1.0, time=-1.0, finish=0.0, off_track=0.0))
    env.reset(seed=3)
    start = float(env.state()[0, S])
    sums = {"progress": 0.0, "time": 0.0}
    while env.agents:
        _, _, _, _, infos = env.step({"car_0": np.array([0.3, 0.0])})
        for name in sums:
            sums[name] += infos["car_0"]["reward_terms"][name]
    assert infos["car_0"]["finished"]
    assert sums["time"] == pytest.approx(-infos["car_0"]["finish_time"], abs=1e-9)
    assert sums["progress"] == pytest.approx(float(env.state()[0, S]) - start, abs=1e-9)
    assert 0.0 < infos["car_0"]["finish_time"] < (600.0 - start) / 5.0  # it started rolling, at >= 5 m/s


def test_four_car_grid(trefoil):
    """A 4-car grid starts on the track without contacts and races."""
    env = racing_env.parallel_env(track=trefoil, num_agents=4)
    observations, infos = env.reset(seed=3)
    assert env.possible_agents == ["car_0", "car_1", "car_2", "car_3"] and len(observations) == 4
    x = env.state()
    assert x.shape == (4, 6)
    assert len(set(np.round(x[:, 0], 6))) == 4  # four distinct grid slots
    assert np.all(np.abs(x[:, 2]) < trefoil.width_left[0])
    _, rewards, terms, _, infos = env.step({a: COAST for a in env.agents})
    assert not any(terms.values())
    assert not any(info["collided"] or info["off_track"] for info in infos.values())
    assert sorted(info["position"] for info in infos.values()) == [1, 2, 3, 4]
    assert all(r > 0 for r in rewards.values())  # progress reward, no penalties


def test_envs_of_one_size_share_one_compiled_step():
    from racing_env import RewardConfig
    from racing_env.env import _race_step

    def race(**config):
        env = racing_env.parallel_env(track="trefoil", num_agents=2, **config)
        env.reset(seed=0)
        env.step({a: np.array([0.5, 0.0]) for a in env.agents})

    race()
    compiled = _race_step._cache_size()
    # other rules, rewards and finish lines are data, not compile-time constants
    race(race_distance=150.0, on_collision="terminate", reward=RewardConfig(progress=1.0, finish=3.0))
    race(laps=3, on_off_track="both")
    assert _race_step._cache_size() == compiled


def test_fields_of_up_to_twenty_cars_start_legally_and_refuse_more():
    from racing_env.config import MAX_CARS
    from racing_env.physics import footprint_overlap
    from racing_env.track import straight

    for scenario in ("grid", "anywhere"):
        env = RacingParallelEnv(RaceConfig(track="trefoil", num_agents=MAX_CARS, scenario=scenario))
        env.reset(seed=1)
        x = env.state()
        assert not np.any(np.asarray(footprint_overlap(x, env.game.vehicles, env.track)))
        half = np.stack([env.track.width_left_at(x[:, 0]), env.track.width_right_at(x[:, 0])])
        assert np.all(x[:, 2] < half[0]) and np.all(-x[:, 2] < half[1])
    with pytest.raises(ValueError, match=r"num_agents must be an integer in \[1, 20\]"):
        RaceConfig(num_agents=21)
    angle = np.linspace(0.0, 2.0 * np.pi, 200, endpoint=False)
    loop = tr.from_centerline(20.0 * np.cos(angle), 20.0 * np.sin(angle), np.full(200, 4.0), np.full(200, 4.0),
                              closed=True, name="loop")  # a circle of about 126 m
    most = int((0.5 * float(loop.length) - 5.0) // 4.0) + 1  # slots 4 m apart within half the lap, less 5 m
    with pytest.raises(ValueError, match=f"at most {most} cars here"):
        RacingParallelEnv(RaceConfig(track=loop, num_agents=20))


def test_the_nearest_rivals_observation_has_one_size_whatever_the_field():
    """Four cars on the straight, car 0 between car 3 (2 m behind) and car 1 (5 m ahead), car 2
    far: with two observed rivals car 0 sees car 3 then car 1; a two-car race's observation
    has the same size, its missing rival a zero block that is not racing."""
    from racing_env.observation import OTHER_FEATURES, OWN_FEATURES

    x0 = np.zeros((4, 6))
    x0[:, 0] = [50.0, 55.0, 120.0, 48.0]
    x0[:, 1] = 10.0
    env = RacingParallelEnv(RaceConfig(track="straight", num_agents=4, observed_rivals=2,
                                       observation_units="physical"))
    observations, _ = env.reset(seed=0, options={"x0": x0})
    rivals = observations["car_0"][OWN_FEATURES:OWN_FEATURES + 2 * OTHER_FEATURES].reshape(2, OTHER_FEATURES)
    np.testing.assert_allclose(rivals[:, 0], [-2.0, 5.0], atol=1e-5)  # ds of car 3, then car 1
    duel = RacingParallelEnv(RaceConfig(track="straight", num_agents=2, observed_rivals=2))
    duel_obs, _ = duel.reset(seed=0)
    assert duel_obs["car_0"].shape == observations["car_0"].shape == env.observation_space("car_0").shape
    assert np.all(duel_obs["car_0"][OWN_FEATURES + OTHER_FEATURES:OWN_FEATURES + 2 * OTHER_FEATURES] == 0.0)
    with pytest.raises(ValueError, match="observed_rivals"):
        RaceConfig(observed_rivals=0)


def test_a_ten_car_field_passes_the_api_checks_and_the_camera_follows_a_chosen_car():
    from gymnasium.utils.env_checker import check_env

    from racing_env.dynamics import N_LAT, S
    from racing_env.render import FOLLOW_MAX_SPAN

    config = dict(track="trefoil", num_agents=10, observed_rivals=3, max_steps=30)
    parallel_api_test(RacingParallelEnv(RaceConfig(**config)), num_cycles=5)
    check_env(racing_env.RaceEnv(**config), skip_render_check=True)
    env = RacingParallelEnv(RaceConfig(**config, render_mode="rgb_array", camera="follow", follow_car=7))
    env.reset(seed=2)
    x = env.state()
    centre, side = env.renderer.view(env.scene())
    cx, cy, _ = env.track.to_cartesian(x[:, S], x[:, N_LAT])
    xy = np.stack([cx, cy], axis=-1)
    pack = np.hypot(*(xy - xy[7]).T) <= 0.5 * FOLLOW_MAX_SPAN
    assert np.all(np.abs(xy[pack] - centre) <= 0.5 * side)  # car 7 and the cars around it are in the window
    assert env.render().shape == (512, 512, 3)
