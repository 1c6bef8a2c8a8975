"""Real-time re-plans: the restored warm start, anytime solves (best iterate, wall-clock budget)
and the agents' options for them."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import racing_env  # noqa: F401  (float64: tests/conftest.py)
from planners import ilq
from planners.agents import make_agent, reset_agents
from planners.agents.batched_planners import unbatchable
from planners.agents.warm_start import restore_accelerations
from planners.game_problem import as_problem
from racing_env import CostWeights, RaceGame, VehicleParams, parallel_env
from racing_env.costs import racing_weights
from racing_env.dynamics import AX, AY
from racing_env.track import straight

X0 = np.array([[10.0, 20.0, 0.0, 0.0, 0.0, 0.0], [0.0, 23.0, 2.0, 0.0, 0.0, 0.0]])


@pytest.fixture(scope="module")
def game() -> RaceGame:
    track = straight(length=300.0, width_left=6.0, width_right=6.0, ds=1.0)
    vehicles = [VehicleParams(v_max=20.0), VehicleParams(v_max=25.0)]
    return RaceGame.create(track, vehicles, CostWeights(r_jx=1.0, r_jy=1.0), dt=0.1, horizon=50)


@pytest.fixture(scope="module")
def shifted_problem(game):
    """A converged feedback plan, shifted by one step, and a start whose accelerations the
    limits moved: the warm start of the next re-plan."""
    plan = ilq.solve(game, X0, mode="feedback")
    us = np.concatenate([np.asarray(plan.us)[1:], np.asarray(plan.us)[-1:]])
    x1 = np.asarray(plan.xs)[1].copy()
    x1[:, AX] -= 0.3
    x1[:, AY] += 0.2
    return x1, us


def test_restored_warm_start_is_back_on_the_planned_accelerations_after_one_step(game):
    rng = np.random.default_rng(0)
    planned = X0 + rng.normal(0.0, 0.5, X0.shape)
    measured = planned.copy()
    measured[:, [AX, AY]] += rng.normal(0.0, 0.3, (2, 2))
    us = rng.normal(0.0, 2.0, (game.horizon, 2, 2))
    restored = restore_accelerations(us, planned, measured, game.dt)
    from_planned = np.asarray(game.step(planned, us[0]))
    from_measured = np.asarray(game.step(measured, restored[0]))
    # the jerk integrates exactly into the acceleration: equal to rounding
    np.testing.assert_allclose(from_measured[:, [AX, AY]], from_planned[:, [AX, AY]], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(restored[1:], us[1:])  # only the first stage changes
    # batched: the same per race
    both = restore_accelerations(np.stack([us, us]), np.stack([planned, planned]), np.stack([measured, planned]), game.dt)
    np.testing.assert_array_equal(both[0], restored)
    np.testing.assert_array_equal(both[1], us)


def _first_stage_merit(game, xs, us, options):
    problem, _ = as_problem(game)
    K, k = ilq._lq_step(problem, np.asarray(xs).reshape(xs.shape[0], -1), np.asarray(us), options,
                        options.control_regularization)
    return float(np.max(np.abs(np.asarray(k)[0]))), np.asarray(K), np.asarray(k)


# feedback with the slow tests (the default run's budget)
@pytest.mark.parametrize("mode, cap", [pytest.param("feedback", 2, marks=pytest.mark.slow), ("open_loop", 1)])
def test_an_anytime_solve_is_never_worse_than_its_warm_start_by_its_merit(game, shifted_problem, mode, cap):
    x1, us = shifted_problem
    options = ilq.SolverOptions(mode=mode, max_iterations=cap, best_iterate=True, tolerance=1e-9)
    res = ilq.solve(game, x1, init=us, options=options)
    assert int(res.status) == ilq.MAX_ITERATIONS
    start_xs = np.asarray(ilq.rollout(as_problem(game)[0], x1.reshape(-1), us)).reshape(-1, 2, 6)
    warm_merit, _, _ = _first_stage_merit(game, start_xs, us, options)
    merit, K, k = _first_stage_merit(game, np.asarray(res.xs), np.asarray(res.us), options)
    assert merit <= warm_merit
    # the returned LQ game is the one around the returned iterate
    np.testing.assert_allclose(np.asarray(res.k), k, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(res.K), K, rtol=0, atol=1e-9)


def test_best_iterate_changes_nothing_in_a_converged_solve(game, shifted_problem):
    x1, us = shifted_problem
    plain = ilq.solve(game, x1, init=us, mode="feedback")
    best = ilq.solve(game, x1, init=us, mode="feedback", best_iterate=True)
    assert bool(plain.converged) and bool(best.converged)
    np.testing.assert_array_equal(np.asarray(best.xs), np.asarray(plain.xs))
    np.testing.assert_array_equal(np.asarray(best.K), np.asarray(plain.K))


def test_a_spent_budget_stops_after_one_iteration(game, shifted_problem):
    x1, us = shifted_problem
    res = ilq.solve(game, x1, init=us, mode="feedback", budget_ms=1e-9)
    assert int(res.status) == ilq.BUDGET_EXHAUSTED and int(res.iterations) == 1
    assert ilq.status_message(res.status) == "wall-clock budget ran out before convergence"
    capped = ilq.solve(game, x1, init=us, mode="feedback", max_iterations=1)
    np.testing.assert_array_equal(np.asarray(res.xs), np.asarray(capped.xs))
    # a generous budget runs the solve to its end, as without one
    free = ilq.solve(game, x1, init=us, mode="feedback", budget_ms=1e6)
    plain = ilq.solve(game, x1, init=us, mode="feedback")
    assert int(free.status) == ilq.CONVERGED and int(free.iterations) == int(plain.iterations)
    np.testing.assert_allclose(np.asarray(free.xs), np.asarray(plain.xs), rtol=0, atol=1e-12)


@pytest.mark.parametrize("budget", [0, -1.0, float("nan"), float("inf"), "fast", True])
def test_bad_budgets_are_refused(game, budget):
    with pytest.raises(ValueError, match="budget_ms must be a finite number of milliseconds > 0"):
        ilq.solve(game, X0, budget_ms=budget)
    with pytest.raises(ValueError, match="budget_ms must be"):
        make_agent("ilqgame-fb", budget_ms=budget)


def test_iterations_caps_the_re_plans_and_a_budget_is_not_batched():
    agent = make_agent("ilqgame-fb:iterations=2")
    assert agent.max_iterations == 2 and "best_iterate" not in agent.solver_options
    # the restored warm start goes with real-time re-plans unless it is switched off
    assert agent.restore_accelerations and make_agent("ilqr:budget_ms=3").restore_accelerations
    assert not make_agent("ilqgame-fb").restore_accelerations
    assert not make_agent("ilqgame-fb:iterations=2,restore_accelerations=false").restore_accelerations
    assert "budget_ms" in unbatchable(make_agent("ilqgame-fb:budget_ms=2"))
    assert unbatchable(agent) is None


def _race_iterations(spec: str, steps: int) -> list[int]:
    env = parallel_env(track="trefoil", num_agents=2, max_steps=steps, weights=racing_weights())
    drivers = [make_agent(spec), make_agent(spec)]
    reset_agents(drivers, env, seed=0)
    observations, _ = env.reset(seed=0)
    iterations = []
    while env.agents:
        state = env.state()
        actions = {a: drivers[i].act(observations[a], state) for i, a in enumerate(env.possible_agents)
                   if a in env.agents}
        iterations.append(drivers[0].diagnostics()["iterations"])
        observations, *_ = env.step(actions)
    return iterations[1:]  # warm re-plans only


def test_the_restored_warm_start_saves_iterations_in_a_race():
    """The agents bench's race (open-loop iLQGame against itself on the trefoil, racing
    weights): the same re-plans, warm-started with and without the restored accelerations."""
    restored = _race_iterations("ilqgame-ol:restore_accelerations=true", 30)
    plain = _race_iterations("ilqgame-ol", 30)
    assert sum(restored) < sum(plain)
    assert np.median(restored) < np.median(plain)


# --- a step size per player (SolverOptions.player_steps) ------------------------------------

X_FAR_OFF = np.array([[10.0, 20.0, 0.0, 0.0, 0.0, 0.0], [-150.0, 10.0, -60.0, 0.3, 0.0, 0.0]])
"""The ego on a 12 m wide straight, the rival 150 m behind and 54 m beyond its right edge:
the rival's boundary cost asks for a step of tens of metres, the ego's for a short one."""


def _own_changes(game, result, x0) -> np.ndarray:
    """Each car's largest change of its own states from the zero-input rollout, ``(N,)``."""
    warm = np.asarray(game.rollout(x0, np.zeros((game.horizon, game.num_players, 2))))
    return np.abs(np.asarray(result.xs) - warm).max(axis=(0, 2))


def test_a_step_size_per_player_keeps_each_cars_change_in_the_trust_region_and_frees_the_ego(game):
    radius = 2.0
    joint = ilq.solve(game, X_FAR_OFF, mode="feedback", max_iterations=1, trust_radius=radius)
    own = ilq.solve(game, X_FAR_OFF, mode="feedback", max_iterations=1, trust_radius=radius, player_steps=True)
    joint_changes, own_changes = _own_changes(game, joint, X_FAR_OFF), _own_changes(game, own, X_FAR_OFF)
    assert np.all(joint_changes <= radius) and np.all(own_changes <= radius)
    # the rival's step is the same one (its eta is cut as the joint one was; 150 m away, it
    # hardly reacts to the ego's change through its gains) ...
    assert own_changes[1] == pytest.approx(joint_changes[1], rel=1e-3)
    # ... and no longer cuts the ego's: one eta holds the ego's change to a few percent of the radius
    assert joint_changes[0] < 0.1 * radius < 0.5 * radius < own_changes[0]
    assert float(own.eta) == float(joint.eta)  # the reported eta is the smallest player's


def test_a_step_size_per_player_changes_nothing_where_no_step_is_cut(game):
    joint = ilq.solve(game, X0, mode="feedback")
    own = ilq.solve(game, X0, mode="feedback", player_steps=True)
    assert bool(joint.converged) and bool(own.converged) and int(own.iterations) == int(joint.iterations)
    np.testing.assert_array_equal(np.asarray(own.xs), np.asarray(joint.xs))


def test_player_steps_needs_the_trust_region_and_a_stacked_state():
    with pytest.raises(ValueError, match="player_steps needs step_control='trust_region'"):
        ilq.SolverOptions(player_steps=True, step_control="none")
    with pytest.raises(ValueError, match="player_steps needs step_control='trust_region'"):
        make_agent("ilqgame-ol:player_steps=true,step_control=residual")
    from planners import GameProblem

    def dynamics(p, t, x, u):  # three states, two players: no stacked per-player state
        return x + 0.1 * jnp.concatenate([u[:, 0], u[:1, 0]])

    def stage_cost(p, t, i, x, u_i):
        return jnp.sum((x - 1.0) ** 2) + u_i @ u_i

    def terminal_cost(p, i, x):
        return jnp.sum(x ** 2)

    problem = GameProblem(dynamics, stage_cost, terminal_cost, num_players=2, state_dim=3, input_dim=1, horizon=5)
    with pytest.raises(ValueError, match="stacks the players' states"):
        ilq.solve(problem, np.zeros(3), player_steps=True)


def test_the_real_time_feedback_planner_takes_a_step_size_per_player_by_default():
    assert make_agent("ilqgame-fb:iterations=2").solver_options["player_steps"] is True
    assert make_agent("ilqgame-fb:budget_ms=5").solver_options["player_steps"] is True
    assert make_agent("ilqgame-fb:iterations=2,player_steps=false").solver_options["player_steps"] is False
    for spec in ("ilqgame-fb", "ilqgame-ol:iterations=2", "ilqr:iterations=2"):
        assert "player_steps" not in make_agent(spec).solver_options


@pytest.fixture(scope="module")
def race_against_random():
    """Car 0 at ``iterations=2,trust_radius=10`` against the random driver on the trefoil,
    grid seed 0, 25 s: the rival is tens of metres off the track from about 10 s on."""

    def race(spec: str) -> tuple[int, np.ndarray]:
        env = parallel_env(track="trefoil", num_agents=2, max_steps=220)
        agents = [make_agent(spec), make_agent("random")]
        observations, _ = env.reset(seed=0)
        reset_agents(agents, env, seed=0)
        off, far = 0, []
        while env.agents:
            state = env.state()
            actions = {car: agents[i].act(observations[car], state)
                       for i, car in enumerate(env.possible_agents) if car in env.agents}
            observations, _, _, _, infos = env.step(actions)
            off += bool(infos["car_0"]["off_track"])
            far.append(abs(env.state()[1, 2]))
        return off, np.array(far)

    return race


def test_the_real_time_feedback_planner_stays_on_the_track_against_a_random_rival(race_against_random):
    off, rival_offset = race_against_random("ilqgame-fb:iterations=2,trust_radius=10")
    assert rival_offset.max() > 30.0  # the rival was far off the track
    assert off == 0


@pytest.mark.slow
def test_with_one_step_size_the_real_time_feedback_planner_left_the_track_in_that_race(race_against_random):
    off, _ = race_against_random("ilqgame-fb:iterations=2,trust_radius=10,player_steps=false")
    assert off > 0
