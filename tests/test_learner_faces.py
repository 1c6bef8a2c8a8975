"""The learner faces take one set of keywords: ``gymnasium.make`` (the single env) and
``gymnasium.make_vec`` (the vectorised env) race the same with the same arguments, opponents
as specs or agent factories; what one face cannot serve is refused with how to give it."""

import functools

import numpy as np
import pytest

import gymnasium
from planners import LaneKeepingAgent
from racing_env.vector import GymnaxRace

ID = "racing_env/Race-v0"
RACE = dict(track="trefoil", num_agents=3)


def _vector(num_envs=1, **kwargs):
    return gymnasium.make_vec(ID, num_envs=num_envs, vectorization_mode="vector_entry_point", **kwargs)


@pytest.mark.parametrize("opponents", [["lane-keeping:target_n=1"], [functools.partial(LaneKeepingAgent, target_n=1.0)]],
                         ids=["spec", "factory"])
def test_make_and_make_vec_race_the_same_with_the_same_arguments(opponents):
    """100 steps of seeded random actions: the learner's observations, rewards and flags of
    ``gymnasium.make`` and of one race of ``make_vec`` agree, to the rounding of two
    compiled programs of one race core.

    The tolerances: both faces run the same race core from the same start (drawn from the
    same key), compiled into two programs (the single env's step, the vectorised env's
    vmapped step with its autoreset), which XLA may fuse differently: float64 results that
    differ in their last bits, a few ulps per step (as between batch sizes,
    tests/test_vector_env.py). Over 100 steps of values of order 10 that is ~1e-11, so the
    float64 rewards are compared to 1e-9. The float32 observations are those float64 values
    rounded: equal unless a value lies within that rounding of a float32 rounding point,
    then one float32 ulp apart, at most 2^-23 of the value (``rtol``). The opponents are the
    lane keeper's law in NumPy (the single env's agents) and in JAX (the vectorised env's),
    equal to ~1e-14 and both rounded to float32: the same action unless one lies within
    ~1e-14 of a float32 rounding midpoint (spacing ~6e-8), about one action in 10^6."""
    single = gymnasium.make(ID, opponents=opponents, **RACE)
    vector = _vector(opponents=opponents, **RACE)
    obs_single, _ = single.reset(seed=4)
    obs_vector, _ = vector.reset(seed=4)
    np.testing.assert_array_equal(obs_vector[0], obs_single)  # the same start
    ended, restarts = False, 0
    for action in np.random.default_rng(0).uniform(-1, 1, (100, 2)):
        obs_vector, reward_vector, terminated_v, truncated_v, _ = vector.step(action[None])
        if ended:  # make_vec's autoreset step starts the race's next episode, as reset() does
            obs_single, _ = single.reset()
            reward_single, terminated, truncated = 0.0, False, False
            restarts += 1
        else:
            obs_single, reward_single, terminated, truncated, _ = single.step(action)
        np.testing.assert_allclose(obs_vector[0], obs_single, rtol=2.0**-23, atol=0.0)
        np.testing.assert_allclose(reward_vector[0], reward_single, rtol=0.0, atol=1e-9)
        assert (terminated_v[0], truncated_v[0]) == (terminated, truncated)
        ended = terminated or truncated
    assert restarts >= 1  # random actions leave the track: the learner faces retire the learner


def test_the_learner_faces_default_to_the_rule_a_learner_learns_with():
    """Off the track a learner is out in every learner face (the rule `racing train` uses);
    the PettingZoo env keeps the penalty; a rule given is the rule raced."""
    from experiments.rl.config import TrainConfig
    from racing_env import parallel_env
    from racing_env.opponents import LEARNER_OFF_TRACK

    assert LEARNER_OFF_TRACK == "terminate" == TrainConfig().on_off_track
    faces = {"make": gymnasium.make(ID).unwrapped.race, "make_vec": _vector(2).unwrapped.race,
             "gymnax": GymnaxRace().race}
    assert {name: race.config.on_off_track for name, race in faces.items()} == dict.fromkeys(faces, "terminate")
    assert all(race.config.on_collision == "penalty" for race in faces.values())
    assert parallel_env().config.on_off_track == "penalty"
    given = [gymnasium.make(ID, on_off_track="penalty").unwrapped.race, _vector(2, on_off_track="both").unwrapped.race]
    assert [race.config.on_off_track for race in given] == ["penalty", "both"]
    env = gymnasium.make(ID, track="trefoil")
    env.reset(seed=0)
    for _ in range(200):  # full left jerk: the learner leaves the track and is out
        *_, terminated, truncated, info = env.step(np.array([0.0, 1.0], np.float32))
        if terminated:
            break
    assert terminated and info["out"] and info["off_track"]
    with pytest.raises(RuntimeError, match=r"call reset\(\) before step\(\)"):
        env.step(np.zeros(2, np.float32))


def test_unknown_keywords_are_refused_with_the_allowed_names_and_gymnasiums_own_are_taken():
    for make in (lambda **kw: gymnasium.make(ID, **kw), lambda **kw: _vector(2, **kw), GymnaxRace):
        with pytest.raises(TypeError, match=r"unknown keyword argument\(s\) \['trak'\]; allowed: .*'track'"):
            make(trak="trefoil")
    envs = _vector(2, disable_env_checker=True, max_episode_steps=None, track="trefoil")
    assert envs.num_envs == 2
    gymnasium.make(ID, disable_env_checker=True, track="trefoil").close()


def test_an_agent_object_drives_one_race_and_a_batch_names_the_way_to_give_it():
    """An agent keeps the state of the race it was reset for: one object for several races
    is refused (naming a spec or a factory), one race takes it."""
    hint = r"spec string .* zero-argument factory"
    with pytest.raises(ValueError, match=hint):
        _vector(2, opponents=[LaneKeepingAgent()], track="trefoil")
    with pytest.raises(ValueError, match=hint):
        gymnasium.make(ID, opponents=[LaneKeepingAgent()], **RACE)  # one object for two cars
    envs = _vector(1, opponents=[LaneKeepingAgent()], track="trefoil")
    envs.reset(seed=0)
    envs.step(np.zeros((1, 2)))


def test_the_number_of_cars_and_the_opponents_list_are_refused_clearly():
    for make in (lambda **kw: gymnasium.make(ID, **kw), _vector):
        with pytest.raises(ValueError, match=r"num_agents must be an integer in \[1, 20\] .* got 0"):
            make(num_agents=0)
        with pytest.raises(ValueError, match="opponents must have 2 entries for 3 cars"):
            make(num_agents=3, opponents=[None, None, None])
        with pytest.raises(TypeError, match="opponents must be a list"):
            make(opponents="lane-keeping")
