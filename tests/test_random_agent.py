"""The random driver (``random``, planners.agents.RandomAgent) and its batched form: actions
uniform in the action box (or ``scale`` of it), the same race for the same seed, different
draws for two cars of one race, bad options and seeds refused, the batched form drawing the
single agent's numbers, and the tournament's off-track count."""

from __future__ import annotations

import numpy as np
import pytest

import racing_env
from experiments.race import run_race
from planners import RandomAgent, make_agent, make_batched_opponent
from planners.agents import BatchedRandom, agent_options
from racing_env.vector import GymnaxRace


def _race(seed: int, scale: float = 1.0, distance: float = 60.0):
    env = racing_env.parallel_env(track="trefoil", num_agents=2, race_distance=distance)
    agents = [make_agent(f"random:scale={scale}"), make_agent("lane-keeping")]
    for i, agent in enumerate(agents):
        agent.reset(seed, i, env)
    record = run_race(env, agents, seed=seed)
    return np.array([r["action"] for r in agents[0].history]), record


def test_the_registry_makes_it_with_its_option():
    agent = make_agent("random")
    assert isinstance(agent, RandomAgent) and agent.scale == 1.0 and agent.spec == "random"
    assert make_agent("random:scale=0.25").scale == 0.25
    assert {row[0]: row[2] for row in agent_options("random")} == {"scale": "1.0"}


def test_a_negative_seed_is_refused_at_reset():
    env = racing_env.parallel_env(track="trefoil", num_agents=2, race_distance=60.0)
    with pytest.raises(ValueError, match="integer >= 0 or None"):
        make_agent("random").reset(-1, 0, env)


def test_actions_are_uniform_in_the_box_and_the_race_is_reproducible_for_a_seed():
    actions, record = _race(seed=3)
    again, record_again = _race(seed=3)
    other, _ = _race(seed=4)
    assert actions.shape[1] == 2 and len(actions) == record.steps
    assert np.all(np.abs(actions) <= 1.0)
    np.testing.assert_array_equal(actions, again)
    np.testing.assert_array_equal(record.xs, record_again.xs)
    assert not np.array_equal(actions[:10], other[:10])
    # uniform on [-1, 1]: mean 0 and variance 1/3; over n draws the mean's standard error is sqrt(1/(3n))
    n = actions.size
    assert abs(actions.mean()) < 5 * np.sqrt(1 / (3 * n))
    assert actions.min() < -0.9 and actions.max() > 0.9  # P(none beyond 0.9 in n draws) = 0.95^n


def test_scale_shrinks_the_box():
    actions, _ = _race(seed=1, scale=0.2)
    assert np.all(np.abs(actions) <= np.float32(0.2)) and np.abs(actions).max() > 0.15


def test_two_random_cars_of_one_race_draw_different_actions():
    env = racing_env.parallel_env(track="trefoil", num_agents=2, race_distance=30.0)
    agents = [make_agent("random"), make_agent("random")]
    for i, agent in enumerate(agents):
        agent.reset(0, i, env)
    env.reset(seed=0)
    first = [agent.act(None, env.state()) for agent in agents]
    assert not np.array_equal(first[0], first[1])


def test_the_batched_form_draws_the_single_agents_actions_in_every_race():
    env = racing_env.parallel_env(track="trefoil", num_agents=2, race_distance=60.0)
    opponent = make_batched_opponent("random:scale=0.5", env.game, 1, 3)
    assert isinstance(opponent, BatchedRandom) and opponent.jax_policy is None
    seeds = np.array([0, 7, 7])
    opponent.reset(np.ones(3, dtype=bool), seeds)
    singles = [make_agent("random:scale=0.5") for _ in seeds]
    for agent, seed in zip(singles, seeds):
        agent.reset(int(seed), 1, env)
    env.reset(seed=0)
    x = np.repeat(env.state()[None], 3, axis=0)
    racing = np.ones((3, 2), dtype=bool)
    racing[2, 1] = False  # the third race's car is out: no draw there
    for _ in range(4):
        actions, diagnostics = opponent.act(np.zeros((3, 5)), x, racing)
        for r in (0, 1):
            np.testing.assert_allclose(actions[r], singles[r].act(None, x[r]), atol=1e-7)  # singles round to float32
        np.testing.assert_array_equal(actions[2], 0.0)
        assert not diagnostics["fallback"].any()
    # the third race, racing again, draws the first numbers of seed 7
    racing[2, 1] = True
    actions, _ = opponent.act(np.zeros((3, 5)), x, racing)
    fresh = make_agent("random:scale=0.5")
    fresh.reset(7, 1, env)
    np.testing.assert_allclose(actions[2], fresh.act(None, x[2]), atol=1e-7)


def test_a_compiled_race_refuses_it_with_what_it_takes():
    with pytest.raises(ValueError, match="neither a JAX policy"):
        GymnaxRace(opponents=["random"], track="trefoil", race_distance=60.0)


def test_a_tournament_counts_each_agents_off_track_steps(tmp_path):
    from experiments.tournament import TournamentConfig, run_tournament

    config = TournamentConfig(agents=("random", "lane-keeping"), versus="lane-keeping", grids=1, race_distance=150.0)
    board = run_tournament(config, tmp_path, gif=False, progress=False, report=False)
    rows = {row["agent"]: row for row in board["rows"]}
    from experiments.tournament import load_results

    records = load_results(tmp_path)
    for name, row in rows.items():
        cars = [car for record in records for car in record["cars"] if car["agent"] == name]
        steps = [car["off_track_steps"] for car in cars]
        assert row["off_track_steps"] == sum(steps) and row["off_track_races"] == sum(s > 0 for s in steps)
        for car in cars:  # the seconds are the steps times dt (0.1 s)
            assert car["time_off_track"] == pytest.approx(0.1 * car["off_track_steps"])
