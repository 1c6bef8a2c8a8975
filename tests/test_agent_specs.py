"""Agent specs with options (planners.agents.registry, make_agent): parsing, refusal of bad
options, private cost weights, weights by race position, and `racing agents`."""

from __future__ import annotations

import numpy as np
import pytest

import racing_env
from experiments.cli import main
from experiments.race import run_race
from planners.agents import (
    AGENTS,
    FeedbackGameAgent,
    ILQRAgent,
    LaneKeepingAgent,
    agent_options,
    make_agent,
    reset_agents,
    split_spec,
    split_spec_list,
    with_options,
)
from racing_env.config import RaceConfig
from racing_env.costs import CostWeights
from racing_env.observation import cars_racing, observe



def test_split_spec():
    assert split_spec("ilqgame-fb") == ("ilqgame-fb", {})
    assert split_spec(" ILQR:max_iterations = 5, pad=zeros ") == ("ilqr", {"max_iterations": "5", "pad": "zeros"})
    for bad, message in [(":x=1", "no agent name"), ("ilqr:", "no options"), ("ilqr:x", "not key=value"),
                         ("ilqr:x=", "not key=value"), ("ilqr:x=1,x=2", "twice")]:
        with pytest.raises(ValueError, match=message):
            split_spec(bad)


def test_split_spec_list_keeps_options_with_their_spec():
    words = ["ilqr,ilqgame-fb:max_iterations=100,pad=zeros", "lane-keeping:target_n=1", "rl:a,b.zip"]
    assert split_spec_list(words) == ["ilqr", "ilqgame-fb:max_iterations=100,pad=zeros", "lane-keeping:target_n=1",
                                      "rl:a", "b.zip"]
    with pytest.raises(ValueError, match="no agent spec before it"):
        split_spec_list(["max_iterations=5,ilqr"])
    with pytest.raises(ValueError, match="no agent spec before it"):
        split_spec_list(["ilqr,pad=zeros"])  # "ilqr" has no options, so this is not a continuation


def test_with_options():
    assert with_options("ilqgame-fb", {}) == "ilqgame-fb"
    assert with_options("ilqgame-fb:pad=zeros", {"max_iterations": 100, "warm_start": False}) == \
        "ilqgame-fb:pad=zeros,max_iterations=100,warm_start=false"
    assert with_options("ilqr:max_iterations=5", {"max_iterations": 7}) == "ilqr:max_iterations=7"


def test_spec_options_reach_the_agent():
    agent = make_agent("ilqgame-fb:max_iterations=100,replan_every=2,warm_start=false,tolerance=1e-4,"
                       "c_gap=2,leading.c_collision=20,trailing.c_collision=1")
    assert isinstance(agent, FeedbackGameAgent)
    assert (agent.max_iterations, agent.replan_every, agent.warm_start) == (100, 2, False)
    assert agent.solver_options["tolerance"] == 1e-4
    assert agent.own_weights == {"c_gap": 2.0}
    assert agent.leading_weights == {"c_collision": 20.0} and agent.trailing_weights == {"c_collision": 1.0}
    lane = make_agent("lane-keeping:target_speed=20,target_n=-1.5")
    assert isinstance(lane, LaneKeepingAgent) and lane.kwargs == {"target_speed": 20.0, "target_n": -1.5}
    damped = make_agent("ilqgame-fb:control_regularization=0.3,adaptive_regularization=true,"
                        "feedforward_regularization=true")
    assert damped.solver_options == {"tolerance": 1e-3, "control_regularization": 0.3,
                                     "adaptive_regularization": True, "feedforward_regularization": True}
    # keyword arguments win over the spec's options
    assert make_agent("ilqr:max_iterations=7", max_iterations=9).max_iterations == 9


@pytest.mark.parametrize("spec, message", [
    ("ilqgame-fb:colour=red", "has no option 'colour'"),
    ("ilqgame-fb:max_iterations=1.5", "expected an integer"),
    ("ilqgame-fb:max_iterations=0", "max_iterations must be >= 1"),
    ("ilqgame-fb:replan_every=0", "replan_every must be >= 1"),
    ("ilqgame-fb:warm_start=maybe", "expected true or false"),
    ("ilqgame-fb:c_collision=-1", "c_collision must be >= 0"),
    ("ilqgame-fb:r_jx=0", "must be > 0"),
    ("ilqgame-fb:trailing.c_gap=x", "expected a number"),
    ("ilqgame-fb:middle.c_gap=1", "belief.<weight>, leading.<weight>, trailing.<weight>"),
    ("ilqgame-fb:step_control=magic", "step_control must be one of"),
    ("ilqgame-fb:step_control=residual", "needs mode='open_loop'"),
    ("ilqr:step_control=residual", "needs mode='open_loop'"),
    ("ilqgame-fb:adaptive_regularization=true,control_regularization=0.3", "open-loop games and one-player"),
    ("ilqr:prediction=ilqgame-fb,adaptive_regularization=true,control_regularization=0.3",
     "open-loop games and one-player"),
    ("ilqgame-ol:adaptive_regularization=true", "needs control_regularization > 0"),
    ("ilqgame-ol:feedforward_regularization=true,control_regularization=0.3", "is for feedback games"),
    ("ilqr:prediction=ilqgame-ol,feedforward_regularization=true,control_regularization=0.3",
     "is for feedback games"),
    ("ilqgame-fb:feedforward_regularization=true", "needs control_regularization > 0"),
    ("ilqgame-fb:trust_radius=0", "trust_radius"),
    ("ilqr:pad=ones", "pad must be"),
    ("lane-keeping:target_speed=0", "target_speed must be a finite speed > 0"),
    ("lane-keeping:target_speed=inf", "target_speed must be a finite speed > 0"),
    ("lane-keeping:target_n=nan", "target_n must be a finite"),
    ("lane-keeping:max_iterations=3", "has no option 'max_iterations'"),
    ("constant-speed:target_n=1", "has no option 'target_n'"),
    ("wizard:x=1", "unknown agent spec"),
    ("random:scale=0", r"scale must be a number in \(0, 1\]"),
    ("random:scale=1.5", r"scale must be a number in \(0, 1\]"),
    ("random:scale=nan", r"scale must be a number in \(0, 1\]"),
    ("random:scale=-1", r"scale must be a number in \(0, 1\]"),
    ("random:scale=big", "expected a number"),
    ("random:target_speed=3", "has no option 'target_speed'"),
    ("ilqgame-fb:iterations=0", "iterations must be an integer >= 1"),
    ("ilqgame-ol:iterations=2,max_iterations=10", "give iterations"),
    ("ilqr:prediction=ilqr,budget_ms=2", "budget_ms bounds one solve"),
])
def test_bad_options_are_refused_when_the_agent_is_made(spec, message):
    with pytest.raises(ValueError, match=message):
        make_agent(spec)


@pytest.mark.parametrize("spec", ["rl:{}/nonexistent.zip", "rl:sac:{}/nonexistent.zip", "rl:{}/nonexistent"])
def test_a_missing_model_file_is_named_once_as_given(tmp_path, spec):
    """One error naming the path the user gave (not the path with .zip added, once per algorithm)."""
    pytest.importorskip("stable_baselines3")
    spec = spec.format(tmp_path)
    path = spec.rpartition(":")[2]
    with pytest.raises(ValueError) as raised:
        make_agent(spec)
    message = str(raised.value)
    assert message.startswith(f"no model file at {path} ") and message.count(path) == 1
    assert ".zip.zip" not in message


def test_own_weights_are_private_to_the_agent():
    env = racing_env.parallel_env(track="trefoil", num_agents=3)
    agent = make_agent("ilqr:c_collision=50,c_gap=0")
    agent.reset(0, 1, env)
    planned, race = agent.planning_game.weights, env.game.weights
    np.testing.assert_array_equal(np.asarray(planned.c_collision), [10.0, 50.0, 10.0])
    np.testing.assert_array_equal(np.asarray(planned.c_gap), [0.5, 0.0, 0.5])
    np.testing.assert_array_equal(np.asarray(race.c_collision), [10.0] * 3)  # the race is unchanged
    for name in ("r_jx", "c_track", "c_ax", "c_acc"):
        np.testing.assert_array_equal(np.asarray(getattr(planned, name)), np.asarray(getattr(race, name)))


def test_beliefs_change_the_other_cars_weights_in_the_agents_plans_only():
    env = racing_env.parallel_env(track="trefoil", num_agents=3)
    agent = make_agent("ilqgame-fb:belief.c_collision=100,belief.c_gap=0,c_collision=1")
    assert agent.opponent_weights == {"c_collision": 100.0, "c_gap": 0.0}
    agent.reset(0, 2, env)
    planned = agent.planning_game.weights
    np.testing.assert_array_equal(np.asarray(planned.c_collision), [100.0, 100.0, 1.0])
    np.testing.assert_array_equal(np.asarray(planned.c_gap), [0.0, 0.0, 0.5])
    np.testing.assert_array_equal(np.asarray(planned.r_jx), np.asarray(env.game.weights.r_jx))  # the rest: the race's
    np.testing.assert_array_equal(np.asarray(env.game.weights.c_collision), [10.0] * 3)
    # on top of belief_weights (a full CostWeights for every opponent)
    agent = FeedbackGameAgent(belief_weights=CostWeights(c_gap=2.0), opponent_weights={"c_collision": 3.0})
    agent.reset(0, 0, env)
    planned = agent.planning_game.weights
    np.testing.assert_array_equal(np.asarray(planned.c_gap), [0.5, 2.0, 2.0])
    np.testing.assert_array_equal(np.asarray(planned.c_collision), [10.0, 3.0, 3.0])
    with pytest.raises(ValueError, match="opponent_weights: CostWeights.c_track must be >= 0"):
        make_agent("ilqr:belief.c_track=-1")


def _race_against_lane_keeper(spec: str, weights, steps: int = 40):
    env = racing_env.parallel_env(track="trefoil", num_agents=2, race_distance=300.0, max_steps=steps,
                                  weights=weights)
    agents = [make_agent(spec), make_agent("lane-keeping")]
    reset_agents(agents, env, 3)
    return run_race(env, agents, seed=3).xs


@pytest.mark.slow  # two planner races (the default run's budget)
def test_a_private_weight_drives_like_the_same_weight_set_in_the_race():
    """Against a scripted rival (which ignores weights), ``ilqgame-fb:c_gap=2`` in a race
    with default weights and ``ilqgame-fb`` in a race whose weights give its car c_gap = 2
    solve the same games: the trajectories agree to the bit."""
    default = CostWeights(r_jx=0.01, r_jy=0.01)
    private = _race_against_lane_keeper("ilqgame-fb:c_gap=2", default)
    public = _race_against_lane_keeper("ilqgame-fb", [default.replace(c_gap=2.0), default])
    plain = _race_against_lane_keeper("ilqgame-fb", default)
    np.testing.assert_array_equal(private, public)
    assert not np.array_equal(private, plain)  # and the weight does change the driving


def test_weights_follow_the_race_position():
    env = racing_env.parallel_env(track="straight", num_agents=2)
    agent = make_agent("ilqr:c_collision=5,leading.c_collision=20,trailing.c_collision=1,trailing.c_gap=0",
                       max_iterations=2)
    agent.reset(0, 0, env)
    x = np.array(env.reset(seed=0) and env.state(), dtype=np.float64)
    for lead, expected in ((5.0, (20.0, 0.5)), (-5.0, (1.0, 0.0))):
        x[0, 0], x[1, 0] = 50.0 + lead, 50.0
        agent.act(None, x)
        record = agent.diagnostics()
        assert record["leading"] is (lead > 0)
        weights = agent.planning_game.weights
        assert (float(weights.c_collision[0]), float(weights.c_gap[0])) == expected
        assert float(weights.c_collision[1]) == 10.0  # the rival keeps the race's weights
    assert agent.summary()["leading_fraction"] == 0.5
    # without place weights there is no place in the records
    plain = make_agent("ilqr:c_collision=5", max_iterations=2)
    plain.reset(0, 0, env)
    plain.act(None, x)
    assert "leading" not in plain.diagnostics() and "leading_fraction" not in plain.summary()


def test_a_lead_counts_laps():
    """On a closed track s is cumulative: a car a lap down is behind even where its wrapped
    position is ahead."""
    env = racing_env.parallel_env(track="trefoil", num_agents=2)
    agent = ILQRAgent(leading_weights={"c_gap": 0.0}, max_iterations=1)
    agent.reset(0, 0, env)
    length = env.game.track.length
    x = np.array(env.reset(seed=0) and env.state(), dtype=np.float64)
    x[0, 0], x[1, 0] = 100.0, length + 50.0  # the rival is a lap up, 50 m behind on the track
    assert not agent._is_leading(x)
    x[0, 0] = length + 60.0
    assert agent._is_leading(x)


def test_cars_that_finished_or_retired_do_not_count_for_the_place():
    """Three cars: car 0 finished in front (or retired there), car 1 is ahead of car 2. Car 1
    leads the cars still racing, as its observation's flags say."""
    env = racing_env.parallel_env(track="straight", num_agents=3)
    agent = make_agent("ilqr:leading.c_collision=20", max_iterations=2)
    agent.reset(0, 1, env)
    observations, _ = env.reset(seed=0)
    x = np.array(env.state(), dtype=np.float64)
    x[:, 0] = [200.0, 150.0, 140.0]
    config = env.config
    active = np.array([False, True, True])
    observation = np.asarray(observe(x, active, env.game.track, 500.0,
                                     np.asarray(config.preview_distances, dtype=np.float64)))[1]
    assert observation.shape == observations["car_1"].shape
    agent.act(observation, x)
    assert agent.diagnostics()["leading"] is True
    agent.act(None, x)  # no observation: every car counts
    assert agent.diagnostics()["leading"] is False


@pytest.mark.parametrize("num_cars, num_preview", [(2, 0), (3, 3), (4, 1)])
def test_cars_racing_reads_the_flags_of_the_observation(num_cars, num_preview):
    rng = np.random.default_rng(num_cars)
    x = np.zeros((num_cars, 6))
    x[:, 0] = rng.uniform(0, 100, num_cars)
    x[:, 1] = 10.0
    track = racing_env.parallel_env(track="straight", num_agents=num_cars).game.track
    active = rng.random(num_cars) < 0.5
    obs = np.asarray(observe(x, active, track, 500.0, np.linspace(10.0, 30.0, num_preview)))
    for i in range(num_cars):
        expected = active.copy()
        expected[i] = True
        np.testing.assert_array_equal(cars_racing(obs[i], i, num_cars), expected)
    assert cars_racing(None, 0, num_cars).all()
    assert cars_racing(obs[0][:-1] if num_preview else obs[0][:-2], 0, num_cars).all()  # not this layout


def test_every_agent_lists_its_options(capsys):
    for name in AGENTS:
        rows = agent_options(name)
        assert rows and all(len(row) == 4 and row[3] for row in rows)  # every option has a meaning
        kinds = dict((option, kind) for option, kind, _, _ in rows)
        # what is listed is exactly what a spec accepts
        assert set(kinds) == set(AGENTS[name].spec_options())
    assert dict((r[0], r[2]) for r in agent_options("ilqgame-fb"))["max_iterations"] == "30"
    assert main(["agents"]) == 0
    out = capsys.readouterr().out
    assert "max_iterations" in out and "target_speed" in out and "leading.<weight>" in out
    assert "cruise speed [m/s]" in out  # units in brackets are text, not rich markup
    assert main(["agents", "ilqr"]) == 0
    assert "trailing.c_collision" in capsys.readouterr().out
    assert main(["agents", "wizard"]) == 2
    assert "unknown agent 'wizard'" in capsys.readouterr().err


def test_tournament_command_line_takes_specs_with_options(tmp_path, capsys):
    out = tmp_path / "t"
    code = main(["tournament", "--agents", "lane-keeping:target_speed=20,target_n=1,constant-speed:target_speed=12",
                 "--race-distance", "60", "--grids", "1", "--no-gif", "--out", str(out)])
    assert code == 0
    from experiments.tournament import load_results

    records = load_results(out)
    assert {car["agent"] for r in records for car in r["cars"]} == {
        "lane-keeping:target_speed=20,target_n=1", "constant-speed:target_speed=12"}
    code = main(["tournament", "--agents", "lane-keeping:target_speed=-3", "constant-speed",
                 "--out", str(tmp_path / "bad")])
    assert code == 2 and "target_speed must be a finite speed > 0" in capsys.readouterr().err
