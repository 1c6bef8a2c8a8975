"""Predictions of the opponents for iLQR (planners.prediction, solve_ilqr(predicted=...)):
the rollout is the environment's own physics, iLQR plans a best response to the
prediction it is given, the agent option, checked against the lane keeper on Monza, and
the planners' predictions: exact against an iLQR agent, the open-loop equilibrium a
fixed point of predicting and best-responding where the feedback one is not, and the
levels of reasoning, which approach that fixed point."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import racing_env
from planners import ilq
from planners.agents import make_agent, reset_agents
from planners.ilqr import ego_problem, predict_constant_velocity, solve_ilqr
from planners.prediction import PREDICTIONS, PlannerPrediction, PolicyRollout, make_predictor
from planners.scripted import LaneKeeping
from racing_env.scenarios import paper_game

GAME, X0 = paper_game()  # the paper's scene: the opponent 10 m behind, 2 m to the left, faster


def test_the_rollout_is_the_environments_trajectory():
    """Car 1 driven by the lane keeper, car 0 without a driver (zero jerk): the rollout
    from the env's start state equals 50 env steps with the same actions. Same physics
    function, compiled in another program: equal up to rounding. Ghost cars: contact is the
    env's, not the car model's that a rollout predicts with."""
    env = racing_env.parallel_env(track="trefoil", num_agents=2, max_steps=60, contact="ghost")
    env.reset(seed=3)
    game = env.game
    x0 = env.state()
    keeper = LaneKeeping(game.track, 1, game.vehicles.car(1))
    predicted = PolicyRollout(game, {1: lambda x: keeper(None, x)})(x0)
    assert predicted.shape == (51, 2, 6)
    driven = [x0]
    for _ in range(50):
        state = env.state()
        env.step({"car_0": np.zeros(2, np.float32), "car_1": keeper(None, state)})
        driven.append(env.state())
    driven = np.stack(driven)
    assert np.ptp(driven[:, 1, 1]) > 1.0  # the keeper changed speed: not a trivial rollout
    np.testing.assert_allclose(predicted, driven, rtol=0, atol=1e-9)


def test_rollout_and_predictor_refuse_bad_input():
    game = GAME
    with pytest.raises(ValueError, match="driver car indices"):
        PolicyRollout(game, {2: lambda x: np.zeros(2)})
    with pytest.raises(ValueError, match=r"shape \(N, 6\)"):
        PolicyRollout(game, {})(np.zeros((3, 6)))
    with pytest.raises(ValueError, match="unknown prediction 'oracle'"):
        make_predictor("oracle", game, 0)
    assert make_predictor("constant-velocity", game, 0) is None
    assert set(PREDICTIONS) == {"constant-velocity", "lane-keeping", "ilqr", "ilqgame-fb", "ilqgame-ol"}
    with pytest.raises(ValueError, match="planner must be one of"):
        PlannerPrediction("lane-keeping", 0)
    with pytest.raises(ValueError, match="tolerance"):
        make_predictor("ilqr", game, 0, tolerance=-1.0)


def test_ilqr_plans_a_best_response_to_the_prediction_it_is_given():
    """A prediction passed in replaces the constant-velocity one: the opponent rows are
    that prediction, and the plan zeroes the gradient of the ego's cost against it."""
    game = GAME
    default = solve_ilqr(game, X0, ego=0)
    explicit = solve_ilqr(game, X0, ego=0, predicted=predict_constant_velocity(game, X0))
    np.testing.assert_array_equal(explicit.xs, default.xs)  # the default, passed in: the same solve

    # The opponent brakes from 23 to 13 m/s behind the ego instead of passing it.
    predicted = np.array(predict_constant_velocity(game, X0))
    t = np.arange(51) * game.dt
    speed = np.maximum(23.0 - 2.0 * t, 13.0)
    predicted[:, 1, 1] = speed
    predicted[1:, 1, 0] = X0[1, 0] + np.cumsum(0.5 * (speed[1:] + speed[:-1]) * game.dt)
    res = solve_ilqr(game, X0, ego=0, predicted=predicted)
    assert bool(res.converged), ilq.status_message(res.status)
    np.testing.assert_allclose(res.xs[:, 1], predicted[:, 1])
    ego = ego_problem(game, X0, 0, predicted)
    grad = jax.jit(jax.grad(lambda u: ilq.total_costs(ego, ilq.rollout(ego, X0[0], u), u)[0]))
    assert float(jnp.linalg.norm(grad(res.plan.us))) < 1e-6
    # Nothing comes alongside (closest 7.75 m behind), so the ego stays within half a car
    # width of its line, where against the default prediction it swerves 4.0 m right.
    assert float(np.min(default.xs[:, 0, 2])) < -1.0
    assert float(np.max(np.abs(res.xs[:, 0, 2]))) < 1.0  # measured 0.05 m


def test_constant_velocity_prediction_in_numpy_equals_its_traced_form():
    """A concrete start state is predicted in NumPy, a traced one in jax.numpy: the same
    formula, equal to rounding, with the same shape and dtype."""
    game = GAME
    concrete = predict_constant_velocity(game, X0)
    traced = jax.jit(predict_constant_velocity)(game, X0)
    assert isinstance(concrete, jax.Array) and concrete.shape == traced.shape == (51, 2, 6)
    assert concrete.dtype == traced.dtype == np.float64
    np.testing.assert_allclose(concrete, traced, rtol=1e-14, atol=1e-12)
    assert predict_constant_velocity(game, X0.astype(int)).dtype == np.float64


def test_ilqr_refuses_a_misshapen_or_non_finite_prediction():
    game = GAME
    with pytest.raises(ValueError, match=r"shape \(T\+1, N, 6\)"):
        solve_ilqr(game, X0, predicted=np.zeros((50, 2, 6)))
    bad = np.array(predict_constant_velocity(game, X0))
    bad[7, 1, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        solve_ilqr(game, X0, predicted=bad)


def _first_replan_against_the_lane_keeper(spec: str):
    """An agent made from ``spec`` as car 0 against the lane keeper on the trefoil, after
    its first action: ``(agent, keeper, env, start state)``."""
    # CostWeights' jerk weight 1, not the env's racing default: the solves here converge with it
    env = racing_env.parallel_env(track="trefoil", num_agents=2, max_steps=20, weights=racing_env.CostWeights())
    agent = make_agent(spec)
    keeper = make_agent("lane-keeping")
    reset_agents([agent, keeper], env, 0)
    obs, _ = env.reset(seed=0)
    state = env.state()
    agent(obs["car_0"], state)
    return agent, keeper, env, state


def test_the_agent_plans_against_the_lane_keeping_rollout():
    agent, keeper, env, state = _first_replan_against_the_lane_keeper("ilqr:prediction=lane-keeping")
    expected, jerks = make_predictor("lane-keeping", env.game, 0)(env.game, state, None)
    assert jerks is None
    np.testing.assert_array_equal(agent._plan["xs"][:, 1], expected[:, 1])
    predictor = agent._predict
    reset_agents([agent, keeper], env, 1)
    assert agent._predict is predictor  # same game, same car: kept, compiled once
    agent.reset(0, 1, env)
    assert agent._predict is not predictor
    assert agent.spec_defaults()["prediction"] == "constant-velocity"
    with pytest.raises(ValueError, match="unknown prediction"):
        make_agent("ilqr:prediction=oracle")
    with pytest.raises(ValueError, match="no option 'prediction'"):
        make_agent("ilqgame-fb:prediction=lane-keeping")


# slow (the default run's budget): the best response to a given prediction is checked by default
@pytest.mark.slow
def test_ilqr_with_the_lane_keeping_prediction_gets_through_monzas_chicane():
    """The trace behind the Monza lap of docs/agents.md: iLQR alongside the lane keeper into the
    first chicane (s = 850-980 m), 3.5 m to its left and 1.3 m ahead, both at 25 m/s.
    Predicting the lane keeper at constant speed, iLQR yields and ends 20 s later behind
    it (measured: 25 m); predicting it by the lane keeper's own law, iLQR takes the
    chicane and leaves it behind (measured: 118 m ahead). Racing jerk weights as in races."""
    ahead = {}
    for prediction in ("constant-velocity", "lane-keeping"):
        env = racing_env.parallel_env(track="Monza", num_agents=2, max_steps=210)
        agent = make_agent(f"ilqr:r_jx=0.01,r_jy=0.01,prediction={prediction}")
        keeper = make_agent("lane-keeping")
        reset_agents([agent, keeper], env, 0)
        x0 = np.zeros((2, 6))
        x0[:, :3] = [[780.0, 25.0, 3.5], [778.7, 25.0, 0.0]]
        obs, _ = env.reset(seed=0, options={"x0": x0})
        contact = 0
        for _ in range(200):
            state = env.state()
            obs, _, _, _, infos = env.step({"car_0": agent(obs["car_0"], state), "car_1": keeper(obs["car_1"], state)})
            contact += infos["car_0"]["collided"]
        assert contact == 0
        ahead[prediction] = env.state()[0, 0] - env.state()[1, 0]
    assert ahead["constant-velocity"] < 0.0 < ahead["lane-keeping"]


def test_the_ilqr_prediction_is_the_plan_of_an_ilqr_opponent():
    """Predicting the other car as an iLQR planner in its place, against an ``ilqr`` agent
    with the same weights and options: the same solve from the same state and the same
    (shifted) warm start, so the prediction is that agent's plan, bit for bit, at every
    re-plan. It is not the constant-velocity prediction: the opponent's plan changes speed."""
    env = racing_env.parallel_env(track="trefoil", num_agents=2, max_steps=30)
    agent = make_agent("ilqr:prediction=ilqr")
    opponent = make_agent("ilqr")
    reset_agents([agent, opponent], env, 0)
    obs, _ = env.reset(seed=0)
    speed_change = 0.0
    for _ in range(20):
        state = env.state()
        actions = {"car_0": agent(obs["car_0"], state), "car_1": opponent(obs["car_1"], state)}
        np.testing.assert_array_equal(agent._plan["xs"][:, 1], opponent._plan["xs"][:, 1])
        # the stored plan carries the opponent's predicted jerks (the next warm start)
        np.testing.assert_array_equal(agent._plan["us"][:, 1], opponent._plan["us"][:, 1])
        speed_change = max(speed_change, float(np.ptp(agent._plan["xs"][:, 1, 1])))
        obs, *_ = env.step(actions)
    assert speed_change > 1.0  # m/s over the horizon; constant velocity would give 0


@pytest.mark.parametrize("planner", ["ilqgame-ol", "ilqgame-fb"])
def test_open_loop_equilibrium_is_a_best_response_to_itself_and_feedback_is_not(planner):
    """Predict the opponent by an equilibrium of the paper's scene, then plan the ego's best
    response by iLQR from zero inputs. An open-loop Nash equilibrium is a pair of mutual
    best responses to fixed trajectories, so iLQR finds the ego's equilibrium trajectory
    again (to the solves' tolerance 1e-8; measured 2e-12 m). A feedback equilibrium is a
    best response to the opponent's feedback *law*, which reacts to the ego; against its
    trajectory alone the ego plans otherwise (measured 0.27 m apart)."""
    options = {"tolerance": 1e-8, "max_iterations": 200}
    predicted, jerks = PlannerPrediction(planner, 0, **options)(GAME, X0)
    mode = "open_loop" if planner == "ilqgame-ol" else "feedback"
    equilibrium = ilq.solve(GAME, X0, mode=mode, **options)
    assert bool(equilibrium.converged)
    np.testing.assert_array_equal(predicted, equilibrium.xs)
    np.testing.assert_array_equal(jerks, equilibrium.us)
    response = solve_ilqr(GAME, X0, ego=0, predicted=predicted, **options)
    assert bool(response.converged), ilq.status_message(response.status)
    gap = float(np.max(np.abs(response.xs[:, 0] - equilibrium.xs[:, 0])))
    if planner == "ilqgame-ol":
        assert gap < 10 * options["tolerance"]
    else:
        assert gap > 0.1


def test_the_agent_plans_against_a_game_prediction():
    """``ilqr:prediction=ilqgame-fb``: the stored plan holds the ego's own jerks and the
    opponent's equilibrium jerks, which warm-start the next game solve."""
    agent, _, _, state = _first_replan_against_the_lane_keeper("ilqr:prediction=ilqgame-fb")
    assert agent.diagnostics()["converged"]
    options = {"max_iterations": agent.max_iterations, **agent.solver_options}  # the agent's: 30, 1e-3
    game = agent.planning_game.with_responsibility(state, agent.responsibility)  # the re-plan's game
    equilibrium = ilq.solve(game, state, mode="feedback", **options)
    np.testing.assert_array_equal(agent._plan["xs"][:, 1], equilibrium.xs[:, 1])
    np.testing.assert_array_equal(agent._plan["us"][:, 1], equilibrium.us[:, 1])
    response = solve_ilqr(game, state, ego=0, predicted=equilibrium.xs, **options)
    np.testing.assert_array_equal(agent._plan["us"][:, 0], response.us[:, 0])  # its own plan: the best response
    assert not np.array_equal(response.us[:, 0], equilibrium.us[:, 0])


def test_each_level_of_the_ilqr_prediction_answers_every_plan_of_the_level_below():
    """Three cars, two levels, car 0 predicting: the level-1 plans of all three cars (car 0's
    too) against constant velocity, then cars 1 and 2 each against the level-1 profile, not
    against the other's half-updated level-2 plan, warm-started from their level-1 plans.
    Built here from ``solve_ilqr`` alone."""
    env = racing_env.parallel_env(track="trefoil", num_agents=3, max_steps=10)
    env.reset(seed=1)
    game, x0 = env.game, env.state()
    options = {"max_iterations": 30, "tolerance": 1e-3}
    level1 = np.array(predict_constant_velocity(game, x0))
    level1_us = {}
    for j in range(3):
        res = solve_ilqr(game, x0, ego=j, **options)
        level1[:, j], level1_us[j] = res.xs[:, j], res.us[:, j]
    predicted, jerks = PlannerPrediction("ilqr", 0, levels=2, **options)(game, x0)
    for j in (1, 2):
        level2 = solve_ilqr(game, x0, ego=j, U0=level1_us[j], predicted=level1, **options)
        np.testing.assert_array_equal(predicted[:, j], level2.xs[:, j])
        np.testing.assert_array_equal(jerks[:, j], level2.us[:, j])
    np.testing.assert_array_equal(predicted[:, 0], level1[:, 0])  # the agent's own level-1 plan
    assert np.max(np.abs(predicted[:, 1:] - level1[:, 1:])) > 0.1  # the second level changed something


def test_the_levels_of_the_ilqr_prediction_settle_on_the_open_loop_equilibrium():
    """Level-k reasoning is best-response iteration on trajectories. A profile where it
    stops is a set of mutual best responses to fixed trajectories: an open-loop Nash
    equilibrium. In the paper's scene the iteration contracts (measured: the largest state
    distance to the equilibrium shrinks by a factor of about 0.58 per level, from 2.4 m in
    n at level 1 to 1e-9 at level 40), so the predicted profile approaches the equilibrium
    that the open-loop iLQGame, a separate solver, finds from zero inputs. Both at
    tolerance 1e-8, so the bound is ten times that, as for the equilibrium's own best
    response above."""
    options = {"tolerance": 1e-8, "max_iterations": 200}
    equilibrium = ilq.solve(GAME, X0, mode="open_loop", **options)
    assert bool(equilibrium.converged)

    def distance(levels):
        predicted, _ = PlannerPrediction("ilqr", 0, levels=levels, **options)(GAME, X0)
        return float(np.max(np.abs(predicted - np.asarray(equilibrium.xs))))

    assert distance(1) > 1.0  # level 1 is not the equilibrium
    assert distance(40) < 10 * options["tolerance"]


def test_levels_are_refused_where_they_do_not_apply():
    with pytest.raises(ValueError, match="positive integer"):
        PlannerPrediction("ilqr", 0, levels=0)
    with pytest.raises(ValueError, match="'ilqr' prediction only"):
        make_predictor("ilqgame-ol", GAME, 0, levels=2)
    with pytest.raises(ValueError, match="'ilqr' prediction only"):
        make_agent("ilqr:levels=2")  # the constant-velocity prediction has no levels
    assert make_agent("ilqr:prediction=ilqr").spec_defaults()["levels"] == 1


def test_the_agent_plans_against_the_level_it_is_given():
    """``ilqr:prediction=ilqr,levels=2``: the opponent's row of the first plan is the
    level-2 prediction made with the agent's own game and solver options."""
    agent, _, _, state = _first_replan_against_the_lane_keeper("ilqr:prediction=ilqr,levels=2")
    options = {"max_iterations": agent.max_iterations, **agent.solver_options}
    game = agent.planning_game.with_responsibility(state, agent.responsibility)  # the re-plan's game
    level2, _ = PlannerPrediction("ilqr", 0, levels=2, **options)(game, state)
    level1, _ = PlannerPrediction("ilqr", 0, levels=1, **options)(game, state)
    np.testing.assert_array_equal(agent._plan["xs"][:, 1], level2[:, 1])
    assert not np.array_equal(level2[:, 1], level1[:, 1])
