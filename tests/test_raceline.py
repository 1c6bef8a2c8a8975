"""The racing-line driver (``raceline``, :class:`planners.RacelineAgent`): alone it laps a circuit
on the track within 3% of the lap-time limit; it races as a JAX law in the vectorised env and
as a compiled opponent of the JAX learner; its options are checked."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import racing_env
from planners import RacelineAgent, make_agent
from planners.agents.batched import BatchedScripted, make_batched_opponent
from planners.scripted import BRAKE_ACTION, RacelineDriver, jax_policy
from racing_env import limits
from racing_env.track import circuit_names


def time_trial(track: str, spec: str = "raceline", max_steps: int = 4000) -> tuple[float | None, int, float]:
    """One lap alone from the grid: (finish time [s], steps off the track, the lap-time limit [s]
    of the default car on the shipped racing line, or the centre line where none is shipped)."""
    env = racing_env.parallel_env(track=track, num_agents=1, laps=1, max_steps=max_steps)
    observations, infos = env.reset(seed=0)
    agent = make_agent(spec)
    agent.reset(0, 0, env)
    off = 0
    finish = None
    while env.agents:
        action = agent.act(observations["car_0"], env.state())
        observations, _, _, _, infos = env.step({"car_0": action})
        off += int(infos["car_0"]["off_track"])
        finish = infos["car_0"]["finish_time"]
    line = "raceline" if limits.has_raceline(env.track) else "centerline"
    return finish, off, limits.lap_time_limit(env.track, line=line)


@pytest.mark.parametrize("track", ["Monza", "Suzuka"])
def test_alone_it_laps_a_circuit_on_the_track_within_3_percent_of_the_limit(track):
    """The limit is a flying lap; the driver starts rolling at about 15 m/s from the grid (about
    0.3% of a lap) and lags the limit by its acceleration lag and jerk limits."""
    finish, off, limit = time_trial(track)
    assert finish is not None and off == 0
    assert limit < finish < 1.03 * limit


@pytest.mark.slow
@pytest.mark.parametrize("track", circuit_names() + ["trefoil"])
def test_alone_it_laps_every_shipped_circuit_on_the_track_within_3_percent_of_the_limit(track):
    finish, off, limit = time_trial(track)
    assert finish is not None and off == 0
    assert limit < finish < 1.03 * limit


def test_a_slower_pace_laps_slower():
    """pace=0.9 drives 90% of the limit's speeds: about 1/0.9 of the lap time (the start and
    the controller's lag make it a little less or more)."""
    finish, off, limit = time_trial("trefoil", "raceline:pace=0.9")
    fast, _, _ = time_trial("trefoil")
    assert off == 0 and fast < finish
    assert finish == pytest.approx(limit / 0.9, rel=0.03)


def test_options_are_checked_before_the_race():
    for spec, match in (("raceline:pace=0", r"pace must be in \(0, 1\]"), ("raceline:pace=1.2", "pace must be"),
                        ("raceline:margin=-1", "margin must be a finite distance >= 0"),
                        ("raceline:line=apex", "line must be 'raceline' or 'centerline'"),
                        ("raceline:target_n=1", "has no option")):
        with pytest.raises(ValueError, match=match):
            make_agent(spec)
    assert isinstance(make_agent("raceline:pace=0.95,margin=1.5"), RacelineAgent)


def test_its_jax_law_is_its_action_and_races_vmapped_in_the_vector_env():
    game = racing_env.parallel_env(track="Monza", num_agents=2).game
    opponent = make_batched_opponent("raceline:pace=0.95", game, 1, 4)
    assert isinstance(opponent, BatchedScripted)
    driver = RacelineDriver(game.track, 1, game.vehicles.car(1), pace=0.95)
    rng = np.random.default_rng(0)
    x = np.zeros((4, 2, 6))
    x[:, :, 0] = rng.uniform(0, game.track.length, (4, 2))
    x[:, :, 1] = rng.uniform(5, 25, (4, 2))
    x[:, :, 2] = rng.uniform(-3, 3, (4, 2))
    x[:, :, 3:] = rng.uniform(-0.2, 0.2, (4, 2, 3)) * [1, 20, 20]
    x[2, 1, 1] = np.nan  # its own state not finite: it brakes
    batched = np.asarray(jax.jit(jax.vmap(opponent.jax_policy))(x))
    for b in range(4):
        single = np.asarray(jax.jit(jax_policy(driver))(x[b]))
        np.testing.assert_array_equal(batched[b], single)
        np.testing.assert_allclose(driver(None, x[b]), single, rtol=1e-6, atol=1e-7)  # float32 of the same law
    np.testing.assert_array_equal(batched[2], BRAKE_ACTION)
    assert np.all(np.abs(batched) <= 1.0)


def test_it_is_a_compiled_opponent_of_the_jax_learner():
    from experiments.rl.train import TrainConfig
    from experiments.rl.train_jax import compiled_races

    races = compiled_races(TrainConfig(learner="jax", opponents=("raceline",), track="Monza", race_distance=300.0))
    assert races is not None
