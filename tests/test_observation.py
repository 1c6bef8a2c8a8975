"""The observation's units (racing_env.observation): scaled observations are the physical ones
times fixed weights, the weights are the stated scales of the car and the track, and a model
trained in one unit reads a race observed in the other exactly."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import racing_env
from experiments.race_spec import RaceSpec
from racing_env.config import RaceConfig
from racing_env.observation import GAP_SECONDS, OTHER_FEATURES, OWN_FEATURES, observation_scale
from racing_env.vehicle import VehicleParams, stack_vehicles

STEPS = 30
# Two float32 roundings apart at most: the env casts each observation (computed in float64
# under the tests' x64) to float32 once, in either unit; scaled = float32(p w) against
# float32(p) w differs by at most 2^-24 relative from each cast.
FLOAT32_TWO_ROUNDINGS = 2.0**-23


def _race(units: str, actions: np.ndarray) -> tuple[list[dict], list[np.ndarray], racing_env.RacingParallelEnv]:
    env = racing_env.parallel_env(track="trefoil", num_agents=3, observation_units=units)
    obs, _ = env.reset(seed=3)
    observations, states = [obs], [env.state()]
    for a in actions:
        obs, *_ = env.step({agent: a[i] for i, agent in enumerate(env.possible_agents) if agent in env.agents})
        observations.append(obs)
        states.append(env.state())
    return observations, states, env


def test_scaled_observations_are_the_physical_ones_times_their_weights():
    """The same race in both units: the same states bit for bit (the units change what a car
    is told, not the race), and every scaled observation the physical one times the race's
    weights."""
    actions = np.random.default_rng(0).uniform(-1.0, 1.0, (STEPS, 3, 2))
    scaled, scaled_states, env = _race("scaled", actions)
    physical, physical_states, physical_env = _race("physical", actions)
    np.testing.assert_array_equal(np.asarray(physical_env.params.obs_scale), 1.0)
    weights = np.asarray(env.params.obs_scale)
    for a, b in zip(scaled_states, physical_states):
        np.testing.assert_array_equal(a, b)
    for step_scaled, step_physical in zip(scaled, physical):
        for i, agent in enumerate(env.possible_agents):
            expected = step_physical[agent].astype(np.float64) * weights[i]
            np.testing.assert_allclose(step_scaled[agent], expected, rtol=FLOAT32_TWO_ROUNDINGS, atol=0)


def test_the_weights_are_the_stated_scales_of_the_car_and_the_track():
    """The paper's car on the trefoil (half-width 6 m): speeds over 25 m/s, accelerations over
    rho(25) = 12 + 0.004 * 625 = 14.5 m/s^2, lateral offsets over 6 m, the gap over
    25 m/s * GAP_SECONDS, curvature times 25^2 / 14.5 m; a car twice as fast has half the
    speed weight. Headings, the fraction to go and the racing flags stay as they are."""
    track = racing_env.parallel_env(track="trefoil").track
    cars = stack_vehicles([VehicleParams(), VehicleParams(v_max=50.0)])
    weights = observation_scale(track, cars, num_preview=2)
    a = 12.0 + 0.004 * 625.0
    own = [1 / 25, 1 / 6, 1, 1 / a, 1 / a, 1 / 6, 1 / 6, 1]
    rival = [1 / (25 * GAP_SECONDS), 1 / 6, 1 / 25, 1, 1 / a, 1 / a, 1]
    ahead = [625 / a, 1 / 6, 1 / 6] * 2
    np.testing.assert_allclose(weights[0], own + rival + ahead, rtol=1e-15)
    assert weights[1, 0] == pytest.approx(weights[0, 0] / 2, rel=1e-15)
    assert weights.shape == (2, OWN_FEATURES + OTHER_FEATURES + 6)
    np.testing.assert_array_equal(observation_scale(track, cars, 2, units="physical"), 1.0)
    assert observation_scale(track, cars, 2, observed_rivals=3).shape == (2, OWN_FEATURES + 3 * OTHER_FEATURES + 6)


def test_unknown_units_are_refused_with_the_allowed_ones_named():
    for make in (lambda: RaceConfig(observation_units="si"), lambda: RaceSpec(observation_units="si")):
        with pytest.raises(ValueError, match="observation_units must be one of .*scaled.*physical"):
            make()


def test_a_model_trained_on_physical_observations_reads_a_scaled_race_exactly(tmp_path):
    """A JAX learner's model file that says it trained on physical units (and one that does
    not say, as every file written before the choice) acts in a scaled race as it acts on
    the same race's physical observations; converted back, the observation differs by the
    float32 roundings above, far below what moves a tanh network's action by 1e-5."""
    from planners.agents import make_agent
    from planners.agents.jax_policy import actor_critic, save_model

    env = racing_env.parallel_env(track="trefoil", num_agents=2)
    physical_env = racing_env.parallel_env(track="trefoil", num_agents=2, observation_units="physical")
    size = env.observation_space("car_0").shape[0]
    params = actor_critic((16,)).init(jax.random.PRNGKey(0), np.zeros(size, np.float32))["params"]
    rng = np.random.default_rng(0)  # weights of order one: actions far from the initialisation's ~0
    params = jax.tree_util.tree_map(lambda p: (0.3 * rng.normal(size=p.shape)).astype(np.float32), params)
    path = save_model(tmp_path / "physical.npz", (16,), params, np.zeros(size), np.full(size, 25.0),
                      observation_units="physical")
    with np.load(path) as data:  # a file from before the choice: no observation_units
        np.savez(tmp_path / "old.npz", **{k: data[k] for k in data.files if k != "observation_units"})
    obs, _ = env.reset(seed=1)
    physical_obs, _ = physical_env.reset(seed=1)
    for name in ("physical.npz", "old.npz"):
        agent = make_agent(f"rl:{tmp_path / name}")
        agent.reset(0, 1, physical_env)
        assert agent.to_model_units is None  # the model's own units: nothing to convert
        expected = agent.model.act(physical_obs["car_1"])
        agent.reset(0, 1, env)
        np.testing.assert_allclose(agent.to_model_units, 1.0 / np.asarray(env.params.obs_scale[1]), rtol=1e-15)
        np.testing.assert_allclose(agent.predict_many(obs["car_1"][None])[0], expected, rtol=0, atol=1e-5)
        assert np.all((np.abs(expected) > 1e-2) & (np.abs(expected) < 1))  # not zero, not clipped


def test_a_batched_model_opponent_in_the_vectorised_env_converts_as_the_single_agent(tmp_path):
    """The vectorised env hands a model opponent the race env (not only its game), so a model
    trained on physical units converts the scaled races' observations, as the single agent
    does."""
    from planners.agents.jax_policy import actor_critic, save_model
    from racing_env.vector import RaceVectorEnv

    size = racing_env.parallel_env(track="trefoil", num_agents=2).observation_space("car_1").shape[0]
    params = actor_critic((8,)).init(jax.random.PRNGKey(0), np.zeros(size, np.float32))["params"]
    path = save_model(tmp_path / "physical.npz", (8,), params, np.zeros(size), np.ones(size),
                      observation_units="physical")
    envs = RaceVectorEnv(num_envs=2, opponents=[f"rl:{path}"], track="trefoil")
    factors = envs.opponents[1].agent.to_model_units
    np.testing.assert_allclose(factors, 1.0 / np.asarray(envs.params.obs_scale[1]), rtol=1e-15)
    physical = RaceVectorEnv(num_envs=2, opponents=[f"rl:{path}"], track="trefoil", observation_units="physical")
    assert physical.opponents[1].agent.to_model_units is None
