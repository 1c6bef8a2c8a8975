"""Tests of the Gymnasium single-agent view (racing_env.single_agent)."""

import warnings

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import racing_env
from racing_env import track as tr
from racing_env.single_agent import ENV_ID, RaceEnv


@pytest.fixture(scope="module")
def trefoil() -> tr.Track:
    return tr.trefoil()


def test_gymnasium_check_env_passes_without_space_warnings(trefoil):
    """gymnasium's check_env accepts RaceEnv and warns about nothing (spaces included)."""
    env = gymnasium.make(ENV_ID, track=trefoil, max_steps=30)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)
    messages = [str(w.message) for w in caught]
    assert not any("space" in m.lower() for m in messages), messages
    assert messages == [], messages  # no other warning either


def test_make_registered_id_with_opponents(trefoil):
    """gymnasium.make('racing_env/Race-v0', opponents=[...]) works after `import racing_env`."""
    assert ENV_ID in gymnasium.registry
    env = gymnasium.make(ENV_ID, opponents=[lambda obs, state: np.array([1.0, 0.0])], track=trefoil)
    assert isinstance(env.unwrapped, RaceEnv)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs) and "position" in info
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert env.observation_space.contains(obs)
    assert isinstance(reward, float) and terminated is False and truncated is False
    env.close()


@pytest.mark.parametrize("num_agents", [1, 3])
def test_default_opponents_are_one_coasting_car_per_opponent(trefoil, num_agents):
    """Without opponents, num_agents sets the field: a lone learner, or N - 1 coasting cars."""
    env = gymnasium.make(ENV_ID, num_agents=num_agents, track=trefoil, max_steps=5)
    race = env.unwrapped.race
    assert race.num_cars == num_agents and len(env.unwrapped._opponents) == num_agents - 1
    env.reset(seed=0)
    x0 = race.state()
    env.step(np.array([1.0, 0.0], dtype=np.float32))
    # the opponents coast: zero jerk keeps their accelerations at zero
    np.testing.assert_array_equal(race.state()[1:, 4:], x0[1:, 4:])
    env.close()


def test_opponents_are_called_with_observation_and_joint_state(trefoil):
    """Each opponent is called with its own observation and the joint state before the step,
    and its action drives its car (checked against the PettingZoo env driven by hand)."""
    calls = []

    def opponent(observation, joint_state):
        calls.append((np.array(observation), np.array(joint_state)))
        return np.array([1.0, -0.5])

    env = RaceEnv(opponents=[opponent], track=trefoil, race_distance=500.0)
    reference = racing_env.parallel_env(track=trefoil, race_distance=500.0)
    env.reset(seed=11)
    ref_obs, _ = reference.reset(seed=11)
    learner_actions = [np.array([0.3, 0.1]), np.array([-0.2, 0.4]), np.array([1.0, 0.0])]
    for k, action in enumerate(learner_actions):
        ref_state = reference.state()
        obs, reward, *_ = env.step(action)
        assert len(calls) == k + 1
        seen_obs, seen_state = calls[-1]
        assert seen_obs.tobytes() == ref_obs["car_1"].tobytes()
        assert seen_state.tobytes() == ref_state.tobytes() and seen_state.shape == (2, 6)
        ref_obs, ref_rewards, *_ = reference.step({"car_0": action, "car_1": np.array([1.0, -0.5])})
        assert obs.tobytes() == ref_obs["car_0"].tobytes() and reward == ref_rewards["car_0"]
    assert env.unwrapped.race.state().tobytes() == reference.state().tobytes()


def test_wrong_number_of_opponent_policies_raises(trefoil):
    """A policy list that does not match the number of cars, or an entry of no known kind,
    is refused with ValueError."""
    coast = lambda obs, state: np.zeros(2)  # noqa: E731
    with pytest.raises(ValueError, match="opponents must have 1 entry for 2 cars .*, got 2"):
        RaceEnv(opponents=[coast, coast], num_agents=2, track=trefoil)
    with pytest.raises(ValueError, match="opponents must have 3 entries for 4 cars .*, got 2"):
        gymnasium.make(ENV_ID, opponents=[coast, coast], num_agents=4, track=trefoil)
    with pytest.raises(ValueError, match="unknown agent spec 'not a spec'"):
        RaceEnv(opponents=["not a spec"], track=trefoil)
    with pytest.raises(ValueError, match="callable"):
        RaceEnv(opponents=[3.0], track=trefoil)
    with pytest.raises(ValueError, match="learner must be a car index"):
        RaceEnv(opponents=[coast], learner=2, track=trefoil)


def test_single_policy_is_reused_and_learner_can_be_any_car(trefoil):
    """With num_agents given, one policy drives every opponent; the learner may be car_1."""
    seen = []

    def opponent(observation, joint_state):
        seen.append(joint_state.shape)
        return np.zeros(2)

    env = RaceEnv(opponents=[opponent], num_agents=3, learner=1, track=trefoil)
    env.reset(seed=0)
    env.step(np.zeros(2))
    assert env.learner == "car_1" and seen == [(3, 6), (3, 6)]  # car_0 and car_2


def test_agent_opponents_are_reset_as_their_cars_every_episode(trefoil):
    """Agents (planners.agents) need no reset of their own: the view resets each as its car
    at every reset, so its history starts over; one agent object cannot drive two cars."""
    from planners.agents import LaneKeepingAgent

    first, second = LaneKeepingAgent(), LaneKeepingAgent()
    env = RaceEnv(opponents=[first, second], learner=1, track=trefoil)
    env.reset(seed=4)
    assert (first.index, second.index) == (0, 2) and first.game is env.race.game
    for _ in range(3):
        env.step(np.zeros(2, np.float32))
    assert len(first.history) == len(second.history) == 3
    assert not any(h["fallback"] for h in first.history + second.history)
    env.reset(seed=5)
    assert first.history == [] and first.seed == 5
    with pytest.raises(ValueError, match="drives one car; pass its spec string .* or a zero-argument factory"):
        RaceEnv(opponents=[first], num_agents=3, track=trefoil)


def test_an_opponent_pool_draws_a_seeded_driver_every_episode(trefoil):
    """Each reset drives the pooled car with one of the pool's drivers, drawn from the
    env's seeded generator: the same seed gives the same drivers, both get drawn, only the
    drawn one is called and reset, and the learner's info names it."""
    from planners.agents import ConstantSpeedAgent, LaneKeepingAgent
    from racing_env.single_agent import OpponentPool

    def make_env():
        fast, slow = LaneKeepingAgent(), ConstantSpeedAgent(target_speed=5.0)
        return RaceEnv(opponents=[OpponentPool([fast, slow], names=["fast", "slow"])], track=trefoil), fast, slow

    env, fast, slow = make_env()
    drawn = []
    for episode in range(12):
        _, info = env.reset(seed=7 if episode == 0 else None)
        (name,) = info["opponents"]
        driver, other = (fast, slow) if name == "fast" else (slow, fast)
        sat_out = len(other.history)
        for _ in range(3):
            *_, info = env.step(np.zeros(2, np.float32))
        assert info["opponents"] == [name]
        drawn.append(name)
        assert len(driver.history) == 3 and driver.index == 1  # reset as car 1, then driving
        assert len(other.history) == sat_out  # the other one was not called
    assert set(drawn) == {"fast", "slow"}
    again, *_ = make_env()
    repeat = []
    for episode in range(12):
        _, info = again.reset(seed=7 if episode == 0 else None)
        repeat.append(info["opponents"][0])
    assert repeat == drawn
    plain = RaceEnv(opponents=[LaneKeepingAgent()], track=trefoil)
    assert "opponents" not in plain.reset(seed=0)[1]  # no pool, no extra info


def test_bad_opponent_pools_are_refused(trefoil):
    from planners.agents import LaneKeepingAgent
    from racing_env.single_agent import OpponentPool

    with pytest.raises(ValueError, match="at least one"):
        OpponentPool([])
    with pytest.raises(ValueError, match="callable"):
        OpponentPool([3])
    with pytest.raises(ValueError, match="2 names for 1 drivers"):
        OpponentPool([LaneKeepingAgent()], names=["a", "b"])
    pool = OpponentPool([LaneKeepingAgent()])
    with pytest.raises(ValueError, match="one pool per opponent"):
        RaceEnv(opponents=[pool], num_agents=3, track=trefoil)
    shared = LaneKeepingAgent()
    with pytest.raises(ValueError, match="drives one car; pass its spec string .* or a zero-argument factory"):
        RaceEnv(opponents=[OpponentPool([shared]), OpponentPool([shared])], track=trefoil)


def test_one_callable_may_drive_several_cars_beside_a_pool(trefoil):
    from planners.agents import LaneKeepingAgent
    from racing_env.single_agent import OpponentPool

    def cruise(observation, joint_state):
        return np.zeros(2, np.float32)

    env = RaceEnv(opponents=[cruise, cruise, OpponentPool([LaneKeepingAgent()])], track=trefoil)
    assert env.reset(seed=0)[1]["opponents"] == [None, None, "lane-keeping"]
