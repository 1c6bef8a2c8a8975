"""Start grids, finish lines and rewards at the edges of the env's configuration space
(racing_env.env, racing_env.scenarios, racing_env.costs): what reaches the race is what
was configured, and what cannot be raced is refused."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import racing_env
from racing_env import track as tr
from racing_env.costs import CostWeights
from racing_env.dynamics import S, V
from racing_env.scenarios import grid, make_scenario
from racing_env.vehicle import VehicleParams


@pytest.fixture(scope="module")
def straight() -> tr.Track:
    return tr.straight()


def test_reset_starts_the_grid_with_the_configured_vehicles(straight):
    """reset() builds its grid with config.vehicles: slow cars start below their own cap
    (0.95 * v_max), not at the default cars' 15 m/s."""
    slow = VehicleParams(v_max=10.0)
    env = racing_env.parallel_env(track=straight, num_agents=2, vehicles=slow)
    for seed in range(3):
        env.reset(seed=seed)
        x = env.state()
        assert np.all(x[:, V] <= 0.95 * 10.0)
        expected = make_scenario("grid", env.track, 2, slow, seed).x0  # the start reset(seed) draws
        assert x.tobytes() == expected.tobytes()


def test_grid_caps_speed_after_the_jitter(straight):
    """The +-1 m/s jitter cannot lift a car above 0.95 * v_max; below the cap it still applies."""
    cap = 15.0
    fast_enough = VehicleParams(v_max=cap / 0.95)  # the cap equals the grid speed
    speeds = np.concatenate([grid(straight, 4, fast_enough, seed=seed).x0[:, V] for seed in range(10)])
    assert np.all(speeds <= 0.95 * fast_enough.v_max)
    assert np.any(speeds < cap - 0.1)  # jittered down
    assert np.any(speeds == 0.95 * fast_enough.v_max)  # jittered up, then capped


def test_default_grid_speeds_are_the_grid_speed_plus_jitter(straight):
    """With the default cars (v_max 25, cap 23.75 m/s) the cap never binds: 15 m/s plus a
    seeded jitter of up to 1 m/s, different for every car."""
    speeds = np.stack([grid(straight, 3, None, seed=seed).x0[:, V] for seed in range(8)])
    assert np.all(np.abs(speeds - 15.0) <= 1.0)
    assert len(np.unique(speeds)) == speeds.size


def test_a_grid_that_reaches_the_finish_line_is_refused_at_reset(straight):
    """A finish line just ahead of seed 0's grid passes the constructor's check; a seed whose
    jitter puts a car on or past the line is refused by reset() instead of finishing at once."""
    fronts = {seed: make_scenario("grid", straight, 1, None, seed).x0[0, S] for seed in range(40)}  # reset(seed)'s
    finish = 0.5 * (fronts[0] + max(fronts.values()))  # ahead of seed 0's grid, behind the furthest jitter
    env = racing_env.parallel_env(track=straight, num_agents=1, race_distance=finish)
    beyond = [seed for seed, front in fronts.items() if front >= finish]
    behind = [seed for seed, front in fronts.items() if front < finish]
    assert beyond and behind
    with pytest.raises(ValueError, match="not ahead of every start"):
        env.reset(seed=beyond[0])
    env.reset(seed=behind[0])
    assert env.state()[0, S] < finish


def test_every_race_length_of_the_repository_validates():
    """The race lengths the tests, the example sweeps and tournaments use are accepted."""
    for track, distance in (("trefoil", 500.0), ("trefoil", 60.0), ("straight", 120.0), ("straight", 150.0),
                            ("straight", None), ("straight", 300.0)):
        for num in (1, 2, 3):
            env = racing_env.parallel_env(track=track, num_agents=num, race_distance=distance)
            for seed in range(6):
                env.reset(seed=seed)


def test_a_lone_car_gets_the_whole_finish_reward(straight):
    """N = 1: crossing the line pays the full finish weight (the winner gets it all)."""
    env = racing_env.parallel_env(track=straight, num_agents=1)
    x0 = np.zeros((1, 6))
    x0[0, [S, V]] = env.finish_s - 1.0, 20.0
    env.reset(seed=0, options={"x0": x0})
    _, _, terminations, _, infos = env.step({"car_0": np.zeros(2)})
    assert terminations["car_0"] and infos["car_0"]["finished"]
    assert infos["car_0"]["reward_terms"]["finish"] == env.config.reward.finish


@pytest.mark.parametrize("num_agents", [1, 2])
def test_reward_terms_without_an_incident_are_positive_zero(straight, num_agents):
    """0.0, not -0.0 (a negative weight times 0; for one car XLA folded it to -0.0)."""
    env = racing_env.parallel_env(track=straight, num_agents=num_agents)
    env.reset(seed=0)
    _, _, _, _, infos = env.step({a: np.zeros(2) for a in env.agents})
    for info in infos.values():
        assert not info["collided"] and not info["off_track"]
        terms = info["reward_terms"]
        assert terms["collision"] == 0.0 and not np.signbit(terms["collision"])
        assert terms["off_track"] == 0.0 and not np.signbit(terms["off_track"])


@pytest.mark.parametrize("field, value", [("r_jx", -1.0), ("c_track", -0.5), ("c_gap", np.nan)])
def test_cost_weights_from_jax_values_are_validated(field, value):
    """Concrete JAX values are checked like NumPy ones; tracers (inside jit) are not."""
    with pytest.raises(ValueError, match=f"CostWeights.{field}"):
        CostWeights(**{field: jnp.asarray(value)})
    with pytest.raises(ValueError, match=f"CostWeights.{field}"):
        CostWeights(**{field: np.asarray(value)})
    traced = jax.jit(lambda w: getattr(CostWeights(**{field: w}), field))(jnp.asarray(value))
    np.testing.assert_array_equal(traced, value)
