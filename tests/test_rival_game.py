"""Local games of a field (planners.rival_game) and the field's batched re-plans
(planners.agents.field)."""

from __future__ import annotations

import numpy as np
import pytest

from planners import ilq, rival_game
from planners.agents import make_agent
from planners.agents.field import solve_field
from racing_env import RaceConfig, RaceGame, VehicleParams
from racing_env.costs import racing_weights
from racing_env.env import RacingParallelEnv
from racing_env.track import get_track


def _field(s, n=None):
    x = np.zeros((len(s), 6))
    x[:, 0] = s
    x[:, 1] = 15.0
    if n is not None:
        x[:, 2] = n
    return x


def test_nearest_rivals_by_wrapped_track_distance_racing_cars_first():
    track = get_track("trefoil")
    L = float(track.length)
    # car 0 at the line; car 3 just behind it across the line (wrapped gap 2 m), car 1 5 m ahead,
    # car 2 5 m behind (a tie with car 1: the lower index first), car 4 far away
    x = _field([1.0, 6.0, -4.0, L - 1.0, 300.0])
    assert list(rival_game.nearest_rivals(track, x, 0, 4)) == [3, 1, 2, 4]
    assert list(rival_game.nearest_rivals(track, x, 0, 2)) == [3, 1]
    # a ghost (out of the race) comes after every racing car, however near
    racing = np.array([True, True, True, False, True])
    assert list(rival_game.nearest_rivals(track, x, 0, 4, racing)) == [1, 2, 4, 3]
    assert list(rival_game.nearest_rivals(track, x, 4, 1)) == [1]  # 294 m to car 1, 296 to car 0
    with pytest.raises(ValueError, match="1 <= k <= N - 1"):
        rival_game.nearest_rivals(track, x, 0, 5)


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "2"])
def test_rivals_below_one_or_not_an_integer_is_refused(bad):
    with pytest.raises(ValueError, match="rivals must be an integer >= 1"):
        make_agent("ilqgame-fb").__class__(rivals=bad)


def test_a_local_game_leaves_a_car_out_or_is_refused():
    game = RaceGame.create(get_track("straight"), [VehicleParams()] * 3, racing_weights(), horizon=5)
    with pytest.raises(ValueError, match="rivals must be <= N - 2 = 1"):
        rival_game.local_game(game, _field([30.0, 20.0, 10.0]), 0, 2)


def _contraction_bound(result) -> float:
    """How far the last iterate of a converged solve can be from the solution it converges
    to, in the solver's convergence measure (the largest state change of a full step): the
    steps left form a geometric series with the ratio ``q`` of the last steps, so at most
    ``h q / (1 - q)`` after the last step ``h``."""
    steps = np.asarray(result.history)[: int(result.iterations)]
    q = float(np.max(steps[-3:] / steps[-4:-1]))
    assert q < 0.5, f"the iteration is not contracting near the solution (ratio {q})"
    return float(steps[-1] * q / (1.0 - q))


@pytest.mark.parametrize("mode", ["feedback", pytest.param("open_loop", marks=pytest.mark.slow)])
def test_the_local_game_is_the_whole_game_when_the_other_cars_are_far(mode):
    """Two cars side by side and two more 80 m ahead (4 cars on the straight): car 0's local
    game with its nearest rival (the two far cars predicted at constant velocity) has the
    whole game's solution for the two near cars.

    The far cars reach the near cars' costs only through the collision terms
    ``c_c exp(2 (1 - a))`` with ``a >= (gap / l)^2`` (their progress enters linearly and
    does not depend on the near cars' inputs): at the smallest gap in either solution that
    is below the rounding of ``c_c`` itself, so the two games' conditions for the near cars
    agree in float64, and the solutions differ by no more than each solve's distance to its own
    solution (:func:`_contraction_bound`)."""
    game = RaceGame.create(get_track("straight"), [VehicleParams()] * 4, racing_weights(), horizon=50)
    x0 = _field([50.0, 44.0, 130.0, 138.0], [1.0, -1.0, 1.0, -1.0])
    options = dict(mode=mode, max_iterations=200, tolerance=1e-9)
    whole = ilq.solve(game, x0, **options)
    local = rival_game.local_game(game, x0, 0, 1)
    assert list(local.order) == [0, 1, 2, 3]
    res = ilq.solve(local.problem, local.x0, init=local.init, validate=False, **options)
    assert bool(whole.converged) and bool(res.converged)
    xs, us, _ = rival_game.to_field(local, res.xs, res.us, None)

    whole_xs = np.asarray(whole.xs)
    gaps = [np.min(np.min(sol[:, 2:, 0], axis=1) - np.max(sol[:, :2, 0], axis=1)) for sol in (whole_xs, xs)]
    lengths = np.asarray(game.vehicles.length)
    c = float(np.asarray(game.weights.c_collision)[0])
    # below the rounding of the weight itself: invisible in float64
    assert c * np.exp(2.0 * (1.0 - (min(gaps) / lengths.max()) ** 2)) < np.finfo(float).eps * c
    bound = _contraction_bound(whole) + _contraction_bound(res)
    assert np.max(np.abs(whole_xs[:, :2] - xs[:, :2])) <= bound
    # the far cars are the prediction in the local solution
    np.testing.assert_array_equal(xs[:, 2:, 0], x0[2:, 0] + 15.0 * game.dt * np.arange(51)[:, None])


def test_with_rivals_at_least_the_field_the_agent_solves_the_whole_game():
    """Bit for bit the solve of the whole game: ``rivals`` >= N - 1 is today's re-plan."""
    env = RacingParallelEnv(RaceConfig(track="trefoil", num_agents=2, max_steps=3))
    observations, _ = env.reset(seed=0)
    state = env.state()
    agent = make_agent("ilqgame-fb:rivals=3,iterations=2,trust_radius=10")
    agent.reset(0, 0, env)
    agent.act(observations["car_0"], state)
    assert agent.prepare_replan(observations["car_0"], state) is None  # nothing to batch: the whole game
    game = agent.planning_game.with_racing(np.ones(2, bool)).with_responsibility(state, agent.responsibility)
    expected = ilq.solve(game, state, mode="feedback", max_iterations=2, **agent.solver_options)
    np.testing.assert_array_equal(agent._plan["us"], np.asarray(expected.us))
    np.testing.assert_array_equal(agent._plan["K"], np.asarray(expected.K)[:, 0])


def test_a_fields_batched_replans_are_each_cars_own(monkeypatch):
    """Four game planners with one rival each: the field's one batched solve gives every car
    the plan its own solve makes (the same iterations; a batch member is compiled in another
    program, so equal to rounding: 1e-9 of the plans' size), and the cars race on it. When a
    car has left the race the batch keeps its size (no new compile)."""
    from planners import ilq_batch

    sizes = []
    real_solve_batch = ilq_batch.solve_batch
    monkeypatch.setattr(ilq_batch, "solve_batch", lambda p, x0s, *a, **k: sizes.append(len(x0s)) or
                        real_solve_batch(p, x0s, *a, **k))
    env = RacingParallelEnv(RaceConfig(track="trefoil", num_agents=4, max_steps=3))
    observations, _ = env.reset(seed=1)
    state = env.state()
    spec = "ilqgame-fb:rivals=1,iterations=2,trust_radius=10"
    batched, alone = [make_agent(spec) for _ in range(4)], [make_agent(spec) for _ in range(4)]
    for i in range(4):
        batched[i].reset(1, i, env)
        alone[i].reset(1, i, env)
    names = env.possible_agents
    stats = solve_field(batched, [observations[a] for a in names], state)
    assert (stats["batches"], stats["members"]) == (1, 4)
    for i, name in enumerate(names):
        u_batched = batched[i].act(observations[name], state)
        u_alone = alone[i].act(observations[name], state)
        for key in ("us", "xs", "K"):
            a, b = batched[i]._plan[key], alone[i]._plan[key]
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-9 * max(1.0, np.abs(b).max()))
        np.testing.assert_allclose(u_batched, u_alone, rtol=0, atol=1e-9)
        record = batched[i].diagnostics()
        assert record["replanned"] and not record["fallback"] and record["iterations"] == 2
        # car i's local game: itself and its nearest rival
        nearest = rival_game.nearest_rivals(env.track, state, i, 1)[0]
        moved = np.any(batched[i]._plan["us"][:, [i, nearest]] != 0.0, axis=(0, 2))
        assert moved.all()
    solve_field(batched[:3], [observations[a] for a in names[:3]], state)  # car 3 out of the race
    assert sizes == [4, 4]


def _field_races(seeds, cars=4):
    envs = [RacingParallelEnv(RaceConfig(track="trefoil", num_agents=cars, max_steps=20)) for _ in seeds]
    observations = [env.reset(seed=seed)[0] for env, seed in zip(envs, seeds)]
    return envs, observations


@pytest.mark.parametrize("compiled", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_a_batched_planner_plays_each_races_local_game_as_the_single_agent(compiled):
    """Car 1 of three 4-car races (the others coasting) driven by one batched planner with
    one rival (every race's local game in one batched solve; ``compiled``: its pure-JAX step,
    vmapped over the races, as compiled races use it) takes the single agents' actions, to
    the rounding of batched solves (tests/test_batched_opponents.py's tolerance)."""
    from planners.agents.batched import make_batched_opponent
    from racing_env.observation import cars_racing

    seeds = [0, 1, 2]
    spec = "ilqgame-fb:rivals=1,iterations=2,trust_radius=10"
    envs, observations = _field_races(seeds)
    opponent = make_batched_opponent(spec, envs[0].game, 1, len(seeds))
    opponent.reset(np.ones(len(seeds), dtype=bool), np.asarray(seeds, dtype=np.int64))
    assert opponent.rivals == 1
    singles = [make_agent(spec) for _ in seeds]
    for agent, env, seed in zip(singles, envs, seeds):
        agent.reset(seed, 1, env)
    if compiled:
        import jax

        planner = opponent.jax_planner
        plans = jax.tree_util.tree_map(lambda leaf: np.stack([leaf] * len(seeds)), planner.initial())
        step = jax.jit(jax.vmap(planner.act))
    for _ in range(3):
        x = np.array([env.state() for env in envs])
        obs = np.array([o["car_1"] for o in observations])
        racing = np.array([cars_racing(o, 1, 4) for o in obs])
        if compiled:
            actions, plans = step(plans, x, racing)
            actions = np.asarray(actions)
        else:
            actions, diagnostics = opponent.act(obs, x, racing)
            assert diagnostics["replanned"].all() and (diagnostics["iterations"] == 2).all()
        expected = np.array([agent.act(o, xb) for agent, o, xb in zip(singles, obs, x)])
        np.testing.assert_allclose(actions, expected, rtol=0, atol=1e-6)  # the single agent's are float32
        for b, env in enumerate(envs):
            moves = {name: np.zeros(2) for name in env.agents}
            moves["car_1"] = actions[b]
            observations[b], *_ = env.step(moves)


def test_the_batched_planners_of_a_field_solve_their_races_in_one_batch(monkeypatch):
    """Cars 1-3 of three 4-car races, each a batched feedback planner with one rival: acting
    together they make one batched solve per step (of all 9 local games) and take the
    actions each takes alone, to the rounding of batched solves (1e-9); the vectorised env
    steps such a field through the same call."""
    from planners.agents import batched_planners
    from planners.agents.batched import make_batched_opponent
    from planners.agents.batched_planners import BatchedPlanner
    from racing_env.observation import cars_racing
    from racing_env.vector import RaceVectorEnv

    seeds = [0, 1, 2]
    spec = "ilqgame-fb:rivals=1,iterations=2,trust_radius=10"
    envs, observations = _field_races(seeds)

    def opponents():
        made = [make_batched_opponent(spec, envs[0].game, j, len(seeds)) for j in (1, 2, 3)]
        for opponent in made:
            opponent.reset(np.ones(len(seeds), dtype=bool), np.asarray(seeds, dtype=np.int64))
        return made

    together, alone = opponents(), opponents()
    calls = []
    real_solve_batch = batched_planners.solve_batch
    monkeypatch.setattr(batched_planners, "solve_batch", lambda *a, **k: calls.append(1) or real_solve_batch(*a, **k))
    for _ in range(2):
        x = np.array([env.state() for env in envs])
        obs = [np.array([o[f"car_{j}"] for o in observations]) for j in (1, 2, 3)]
        racing = np.array([cars_racing(o["car_1"], 1, 4) for o in observations])
        calls.clear()
        joined = BatchedPlanner.act_together(together, obs, x, racing)
        assert len(calls) == 1  # the field's one batch
        for (actions, diagnostics), opponent, o in zip(joined, alone, obs):
            expected, _ = opponent.act(o, x, racing)
            np.testing.assert_allclose(actions, expected, rtol=0, atol=1e-9)
            assert diagnostics["replanned"].all() and not diagnostics["fallback"].any()
        for b, env in enumerate(envs):
            moves = {"car_0": np.zeros(2), **{f"car_{j}": joined[j - 1][0][b] for j in (1, 2, 3)}}
            observations[b], *_ = env.step(moves)

    vector = RaceVectorEnv(num_envs=2, opponents=[spec], num_agents=4, track="trefoil", max_steps=20)
    vector.reset(seed=0)
    calls.clear()
    vector.step(np.zeros((2, 2)))
    assert len(calls) == 1


def test_a_local_game_with_fewer_obstacles_is_the_same_game_when_the_rest_are_far():
    """Six cars on the straight: car 0 and its rival side by side, a car 30 m ahead, three
    more 450-550 m ahead. Car 0's local game predicting only the nearest other car
    (``obstacles=1``) has the solution of the one predicting all four, for the same reason
    as above: the far cars' collision terms are below the rounding of ``c_c`` over the whole
    horizon, so both games' conditions agree in float64, and the solutions differ by no more
    than each solve's distance to its own solution. The cars left out keep their predictions
    in the field's shapes."""
    game = RaceGame.create(get_track("straight"), [VehicleParams()] * 6, racing_weights(), horizon=50)
    x0 = _field([50.0, 44.0, 80.0, 500.0, 550.0, 600.0], [1.0, -1.0, 0.5, 0.0, 1.0, -1.0])
    options = dict(mode="feedback", max_iterations=200, tolerance=1e-9)
    solutions = []
    for obstacles in (None, 1):
        local = rival_game.local_game(game, x0, 0, 1, obstacles=obstacles)
        assert list(local.order) == [0, 1, 2, 3, 4, 5]
        assert local.problem.params.predicted.shape == (51, 4 if obstacles is None else 1, 6)
        res = ilq.solve(local.problem, local.x0, init=local.init, validate=False, **options)
        assert bool(res.converged)
        solutions.append((res, rival_game.to_field(local, res.xs, res.us, None)[0]))
    (whole, whole_xs), (fewer, fewer_xs) = solutions
    gap = np.min(np.min(whole_xs[:, 3:, 0], axis=1) - np.max(whole_xs[:, :3, 0], axis=1))
    c, length = float(np.asarray(game.weights.c_collision)[0]), float(np.max(game.vehicles.length))
    assert c * np.exp(2.0 * (1.0 - (gap / length) ** 2)) < np.finfo(float).eps * c
    bound = _contraction_bound(whole) + _contraction_bound(fewer)
    assert np.max(np.abs(whole_xs[:, :2] - fewer_xs[:, :2])) <= bound
    np.testing.assert_array_equal(fewer_xs[:, 2:], whole_xs[:, 2:])  # the predictions of every other car


def test_a_local_games_size_does_not_depend_on_the_field():
    """With ``obstacles`` the local game of a car and its two rivals has the same players,
    predicted cars and stage residuals in a field of 8 cars as in one of 20."""
    import jax

    shapes = []
    for cars in (8, 20):
        game = RaceGame.create(get_track("trefoil"), [VehicleParams()] * cars, racing_weights(), horizon=10)
        x0 = _field(10.0 * np.arange(cars))
        local = rival_game.local_game(game, x0, 3, 2, obstacles=2)
        problem = local.problem
        residuals = jax.eval_shape(lambda x, u: problem.stage_gauss_newton(problem.params, 0, 0, x, u),
                                   local.x0, local.init[0, 0])
        shapes.append((problem.num_players, problem.params.predicted.shape,
                       jax.tree_util.tree_map(lambda leaf: leaf.shape, residuals)))
    assert shapes[0] == shapes[1]
    assert shapes[0][1] == (11, 2, 6)


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, None])
def test_obstacles_below_one_or_not_an_integer_is_refused(bad):
    with pytest.raises(ValueError, match="obstacles must be"):
        make_agent("ilqgame-fb").__class__(obstacles=bad)
    if bad is not None:
        with pytest.raises(ValueError, match="obstacles must be None"):
            rival_game.check_obstacles(bad)


def test_a_local_game_of_cars_with_limit_tables_takes_each_players_own_car():
    """Stacked limit tables (N, K) are gathered per car, not broadcast: the local game's cars
    are the field's cars in the local game's order, knots and all."""
    import jax

    from racing_env.car_classes import get_car

    cars = [get_car("av21"), get_car("paper"), get_car("tum"), get_car("av21")]
    game = RaceGame.create(get_track("straight"), cars, racing_weights(), horizon=5)
    local = rival_game.local_game(game, _field([30.0, 50.0, 10.0, 120.0]), 2, 1, obstacles=1)
    ordered = rival_game.ordered_game(local.problem.params, 2)
    order = np.asarray(local.order)[:3]
    for mine, field in zip(jax.tree_util.tree_leaves(ordered.vehicles), jax.tree_util.tree_leaves(game.vehicles)):
        np.testing.assert_array_equal(np.asarray(mine), np.asarray(field)[order])
    step = local.problem.dynamics(local.problem.params, 0, local.x0, np.zeros((2, 2)))
    assert np.all(np.isfinite(np.asarray(step)))
