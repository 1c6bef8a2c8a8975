"""The iterative Stackelberg solver (``planners.ilq.solve(mode="stackelberg")``) and its
certificate (``planners.stackelberg``).

On an LQ game one full step lands on the LQ feedback Stackelberg solution
(:mod:`planners.lq_stackelberg`, verified on its own in ``test_lq_stackelberg.py``); on the
paper's racing scene (slow) the solve converges with either car leading and the
certificate holds, while the feedback Nash solution fails it (its leader is not
stationary along the follower's reaction).
"""

from __future__ import annotations

import numpy as np
import pytest

import racing_env  # noqa: F401  (float64: tests/conftest.py)
from planners import ilq, ilq_batch, lq_game, lq_stackelberg
from planners.stackelberg import STACKELBERG_SOLUTION, certify_stackelberg
from racing_env.scenarios import paper_game

from lq_games import random_lq_game


@pytest.mark.parametrize("leader", [0, pytest.param(1, marks=pytest.mark.slow)])
def test_one_step_lands_on_the_lq_stackelberg_solution(leader):
    problem, p, x0, us0 = random_lq_game(seed=3)
    args = (p["A"], p["B"], p["Q"], p["q"], p["R"], p["r"])
    K, k = lq_stackelberg.solve_feedback_stackelberg(*args, leader=leader)
    xs_ref, us_ref = lq_game.lq_rollout_feedback(p["A"], p["B"], K, k, x0)
    res = ilq.solve(problem, x0, us0, mode="stackelberg", leader=leader, step_control="none", max_iterations=2)
    assert bool(res.converged) and int(res.iterations) == 2
    assert float(res.history[0]) > 1e-1  # the first step moved far ...
    assert float(res.history[1]) < 1e-9  # ... straight onto the solution
    np.testing.assert_allclose(res.xs, xs_ref, atol=1e-9)
    np.testing.assert_allclose(res.us, us_ref, atol=1e-9)
    np.testing.assert_allclose(res.K, K, atol=1e-9)  # the gains of the LQ game itself
    if leader == 0:
        # the feedback Nash solution of the same game is another point
        K_n, k_n = lq_game.solve_feedback(*args)
        _, us_nash = lq_game.lq_rollout_feedback(p["A"], p["B"], K_n, k_n, x0)
        assert np.max(np.abs(np.asarray(us_nash) - np.asarray(res.us))) > 1e-3


@pytest.mark.slow
@pytest.mark.parametrize("batching", ["vmap", "map"])
def test_a_batch_equals_its_single_solves(batching):
    """Batched Stackelberg solves (both batchings) equal the single ones, members that need
    different numbers of iterations included (trust region: the first steps are cut)."""
    problem, _, x0, us0 = random_lq_game(seed=5)
    x0s = np.stack([np.asarray(x0) * s for s in (1.0, 4.0, -2.0)])
    batch = ilq_batch.solve_batch(problem, x0s, us0, mode="stackelberg", leader=1, trust_radius=1.0,
                                  batching=batching)
    iterations = set()
    for b, x in enumerate(x0s):
        single = ilq.solve(problem, x, us0, mode="stackelberg", leader=1, trust_radius=1.0)
        assert bool(batch.converged[b]) and bool(single.converged)
        np.testing.assert_allclose(batch.us[b], single.us, atol=1e-9)
        np.testing.assert_allclose(batch.K[b], single.K, atol=1e-9)
        iterations.add(int(single.iterations))
    assert len(iterations) > 1


def test_stackelberg_mode_refuses_what_it_is_not_for():
    problem, p, x0, _ = random_lq_game(seed=4, N=3)
    with pytest.raises(ValueError, match=r"mode='stackelberg' needs a game of exactly 2 players.*got 3"):
        ilq.solve(problem, x0, mode="stackelberg")
    for bad in (2, -1, True, "1"):
        with pytest.raises(ValueError, match=r"leader must be one of \(0, 1\)"):
            ilq.SolverOptions(mode="stackelberg", leader=bad)
    with pytest.raises(ValueError, match="mode must be one of"):
        ilq.SolverOptions(mode="leader")
    with pytest.raises(ValueError, match="adaptive_regularization is for open-loop games"):
        ilq.check_adaptive_regularization(
            ilq.SolverOptions(mode="stackelberg", control_regularization=0.1, adaptive_regularization=True), 2)
    with pytest.raises(ValueError, match="feedforward_regularization is for feedback games"):
        ilq.SolverOptions(mode="stackelberg", control_regularization=0.1, feedforward_regularization=True)
    with pytest.raises(ValueError, match="mode='stackelberg'"):
        certify_stackelberg(problem, x0, None, options=ilq.SolverOptions(mode="feedback"))


@pytest.mark.slow
@pytest.mark.parametrize("leader", [0, 1])
def test_paper_scene_converges_and_is_certified(leader):
    """The paper's scene (racing_env.scenarios.paper_game) solved with car ``leader``
    leading: converged (13 iterations when written), the follower a best response to the
    leader's feedback law and the leader stationary along the follower's reaction
    (certificate), the leader's cost lower than in the feedback Nash solution there; the
    feedback Nash solution is no Stackelberg solution."""
    game, x0 = paper_game()
    options = ilq.SolverOptions(mode="stackelberg", leader=leader)
    res = ilq.solve(game, x0, options=options)
    assert bool(res.converged) and int(res.iterations) <= 30, (res.status, res.iterations)
    assert float(np.abs(res.k).max()) < 1e-5
    c = certify_stackelberg(game, x0, res, options=options, checks="full")
    assert c.verdict == STACKELBERG_SOLUTION, c.reasons
    assert c.leader_stationarity < 1e-6 and c.follower_stationarity < 1e-6
    assert c.leader_stage_min_eigenvalue > 0 and c.follower_min_eigenvalue > 0
    nash = ilq.solve(game, x0, mode="feedback")
    assert float(res.costs[leader]) < float(nash.costs[leader])
    c_nash = certify_stackelberg(game, x0, nash, options=options, checks="cheap")
    assert c_nash.verdict == "not stationary" and c_nash.leader_stationarity > 1e-3
