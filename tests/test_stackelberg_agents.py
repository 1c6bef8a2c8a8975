"""The leader-follower planners ``ilqgame-leader`` and ``ilqgame-follower``
(planners.agents.receding_horizon.StackelbergGameAgent, planners.leader_follower): their
options, the choice of the leader, a race against the feedback Nash planner, and their
batched and compiled forms against the single agent."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import racing_env
from planners import ilq, make_agent, make_batched_opponent
from planners.agents import BatchedPlanner, FollowerGameAgent, LeaderGameAgent
from planners.leader_follower import ego_leads, ego_rows, pair_game, pair_orders, to_field_batch
from racing_env.observation import cars_racing

CAR = 1  # the leader-follower planner's car; car 0 is a feedback Nash planner
SPEC = "ilqgame-follower:role=auto,iterations=2"
"""The recorded races' planner: real-time re-plans (the compiled races' kind), the leader
chosen by place, so that races in which car 1 is ahead and behind solve in one batch."""
RIVAL = "ilqgame-fb:iterations=2"
SEEDS = (3, 1)  # car 1 behind in seed 3's grid, ahead in seed 1's
STEPS = 6

TOLERANCE = 1e-9
"""Batched and compiled against single planner actions (float64): each solves the same pair
game from the same state and warm start with the same operations, differing in how XLA
compiles and orders them (~1e-15 per action, as for the Nash planners in
tests/test_batched_opponents.py); a wrong leader, gain row or warm start moves an action by
1e-3 and more."""


# --------------------------------------------------------------------------------------
# Options and the choice of the leader.
# --------------------------------------------------------------------------------------


def test_a_role_other_than_leader_follower_or_auto_is_refused_with_the_allowed_values():
    for spec in ("ilqgame-leader:role=boss", "ilqgame-follower:role=Leader"):
        with pytest.raises(ValueError, match="role must be one of leader, follower, auto"):
            make_agent(spec)
    with pytest.raises(ValueError, match="role must be one of leader, follower, auto"):
        LeaderGameAgent(role=1)
    with pytest.raises(ValueError, match="no option 'rivals'"):
        make_agent("ilqgame-leader:rivals=2")  # the game has two players: no rivals to choose
    with pytest.raises(ValueError, match="exactly 2 players"):
        FollowerGameAgent(rivals=2)
    assert make_agent("ilqgame-leader").role == "leader" and make_agent("ilqgame-follower").role == "follower"
    assert {make_agent(f"ilqgame-{name}:role=auto").role for name in ("leader", "follower")} == {"auto"}
    assert make_agent("ilqgame-leader").mode == "stackelberg"


def _field(s: list[float]) -> np.ndarray:
    """A field ``(1, N, 6)`` with the cars at distances ``s`` [m], 15 m/s, side by side."""
    x = np.zeros((1, len(s), 6))
    x[0, :, 0], x[0, :, 1] = s, 15.0
    return x


@pytest.mark.parametrize("xp", [np, jnp], ids=["numpy", "jax"])
def test_auto_makes_the_car_ahead_the_leader_whichever_car_plans(xp):
    """Two cars, each ahead in turn, each the ego in turn: with ``auto`` the car with the larger
    race distance leads the pair game; equal distances go to the lower index, so both cars'
    games have the same leader. ``leader`` and ``follower`` fix the ego's part."""
    track = racing_env.parallel_env(track="trefoil", num_agents=2).game.track
    for s, ahead in (([40.0, 30.0], 0), ([30.0, 40.0], 1), ([35.0, 35.0], 0)):
        x = xp.asarray(_field(s))
        for ego in (0, 1):
            egos = xp.asarray([ego])
            order = np.asarray(pair_orders(track, x, egos, "auto"))
            assert order[0, 0] == ahead and sorted(order[0]) == [0, 1]
            assert np.asarray(ego_rows(order, egos))[0] == (0 if ego == ahead else 1)
            assert bool(np.asarray(ego_leads("auto", x, egos, xp.asarray([1 - ego])))[0]) == (ego == ahead)
            assert np.asarray(pair_orders(track, x, egos, "leader"))[0, 0] == ego
            assert np.asarray(pair_orders(track, x, egos, "follower"))[0, 0] == 1 - ego


def test_in_a_field_the_pair_game_is_the_ego_and_its_nearest_rival_the_others_predicted():
    """Four cars: car 2's nearest rival is car 1 (5 m ahead), so with ``auto`` car 1 leads and
    car 2 follows; cars 3 and 0 are next, the nearest first, and ``obstacles=1`` predicts
    only car 3."""
    env = racing_env.parallel_env(track="trefoil", num_agents=4)
    x = _field([10.0, 40.0, 35.0, 28.0])[0]
    local = pair_game(env.game, x, 2, "auto", obstacles=1)
    assert list(local.order) == [1, 2, 3, 0]
    assert local.problem.num_players == 2 and local.x0.shape == (12,)
    np.testing.assert_array_equal(local.x0.reshape(2, 6), x[[1, 2]])
    assert local.problem.params.predicted.shape == (env.game.horizon + 1, 1, 6)
    np.testing.assert_array_equal(local.problem.params.predicted[0, 0], x[3])
    assert list(pair_game(env.game, x, 2, "leader", obstacles=1).order) == [2, 1, 3, 0]


def test_the_egos_gains_come_from_its_own_row_of_the_pair_game():
    """Two cars, car 1 the ego: leading (order [1, 0], its row 0) and following (order [0, 1],
    its row 1). Its field gains are that row, the columns of each car's states moved from the
    car's place in the pair game to its place in the field."""
    rng = np.random.default_rng(0)
    T = 3
    orders, egos = np.array([[1, 0], [0, 1]]), np.array([1, 1])
    K = rng.normal(size=(2, T, 2, 2, 12))
    xs, us = rng.normal(size=(2, T + 1, 12)), rng.normal(size=(2, T, 2, 2))
    _, _, field_K = to_field_batch(orders, egos, xs, us, K, np.zeros((2, T, 2, 2)), np.zeros((2, T + 1, 0, 6)))
    for race, row in enumerate((0, 1)):
        ego_K = K[race, :, row].reshape(T, 2, 2, 6)  # (T, inputs, player, state)
        for place, car in enumerate(orders[race]):
            np.testing.assert_array_equal(field_K[race, :, :, 6 * car:6 * car + 6], ego_K[:, :, place])


# --------------------------------------------------------------------------------------
# Races.
# --------------------------------------------------------------------------------------


from test_batched_opponents import _single_action as _action  # noqa: E402 - the single agent's float64 action


def _race(spec: str, seed: int, steps: int, rivals: tuple[str, ...] = (RIVAL,)) -> dict:
    """A race of ``rivals`` (car 0, then cars 2, ...) against ``spec`` (car :data:`CAR`) on the
    trefoil: every step's joint state, racing flags, observation, action and diagnostics of
    car 1."""
    env = racing_env.parallel_env(track="trefoil", num_agents=len(rivals) + 1)
    observations, _ = env.reset(seed=seed)
    agents = [make_agent(rivals[0]), make_agent(spec), *(make_agent(rival) for rival in rivals[1:])]
    for index, agent in enumerate(agents):
        agent.reset(seed, index, env)
    out = {key: [] for key in ("x", "racing", "observation", "action", "record")}
    for _ in range(steps):
        x = env.state()
        observation = observations[f"car_{CAR}"]
        action = _action(agents[CAR], observation, x)
        out["x"].append(x)
        out["racing"].append(cars_racing(observation, CAR, len(agents)))
        out["observation"].append(observation)
        out["action"].append(action)
        out["record"].append(agents[CAR].diagnostics())
        actions = {f"car_{i}": agent(observations[f"car_{i}"], x) for i, agent in enumerate(agents) if i != CAR}
        observations, *_ = env.step({**actions, f"car_{CAR}": np.float32(action)})
    return {key: np.stack(value) if key != "record" else value for key, value in out.items()}


@pytest.fixture(scope="module")
def recorded() -> dict:
    """The races of :data:`SEEDS`, stacked ``(R, STEPS, ...)``; the records as lists."""
    races = [_race(SPEC, seed, STEPS) for seed in SEEDS]
    out = {key: np.stack([race[key] for race in races]) for key in ("x", "racing", "observation", "action")}
    out["record"] = [race["record"] for race in races]
    return out


def test_the_recorded_races_plan_with_the_car_ahead_leading(recorded):
    """Car 1 is behind at seed 3's start and ahead at seed 1's: its games are led by car 0 and
    by itself; every re-plan is adopted."""
    for race, seed in enumerate(SEEDS):
        x0 = recorded["x"][race, 0]
        ahead = 0 if x0[0, 0] > x0[1, 0] else 1
        records = recorded["record"][race]
        assert records[0]["leader"] == ahead
        assert all(not record["fallback"] for record in records)
    assert {records[0]["leader"] for records in recorded["record"]} == {0, 1}


def test_a_leader_races_the_feedback_nash_planner_without_a_fallback():
    """``ilqgame-leader`` (leading its games) against ``ilqgame-fb``: finite actions
    within the action box, every re-plan adopted and led by itself, and it drives forward."""
    race = _race("ilqgame-leader:iterations=2", 2, 10)
    assert np.all(np.isfinite(race["action"])) and np.all(np.abs(race["action"]) <= 1.0)
    assert all(not record["fallback"] and record["leader"] == CAR for record in race["record"])
    assert race["x"][-1, CAR, 0] > race["x"][0, CAR, 0] + 10.0  # [m] in 0.5 s from 15 m/s or more


def _replay_batched(recorded: dict, seeds) -> None:
    """The recorded states replayed to one batched opponent of :data:`SPEC`: its actions are
    the single agent's."""
    races, num_cars = recorded["x"].shape[0], recorded["x"].shape[2]
    game = racing_env.parallel_env(track="trefoil", num_agents=num_cars).game
    opponent = make_batched_opponent(SPEC, game, CAR, races)
    assert isinstance(opponent, BatchedPlanner) and opponent.role == "auto"
    opponent.reset(np.ones(races, dtype=bool), np.asarray(seeds, dtype=np.int64))
    for step in range(recorded["x"].shape[1]):
        actions, diagnostics = opponent.act(recorded["observation"][:, step], recorded["x"][:, step],
                                            recorded["racing"][:, step])
        np.testing.assert_allclose(actions, recorded["action"][:, step], rtol=0.0, atol=TOLERANCE)
        assert not diagnostics["fallback"].any()


def _replay_compiled(recorded: dict) -> None:
    """The compiled step of :data:`SPEC` (vmapped over the races, the leader a traced choice)
    on the recorded states: the single agent's actions."""
    races, num_cars = recorded["x"].shape[0], recorded["x"].shape[2]
    game = racing_env.parallel_env(track="trefoil", num_agents=num_cars).game
    planner = make_batched_opponent(SPEC, game, CAR, races).jax_planner
    step = jax.jit(jax.vmap(planner.act))
    plans = jax.tree_util.tree_map(lambda a: jnp.stack([a] * races), planner.initial())
    for k in range(recorded["x"].shape[1]):
        actions, plans = step(plans, jnp.asarray(recorded["x"][:, k]), jnp.asarray(recorded["racing"][:, k]))
        np.testing.assert_allclose(np.asarray(actions), recorded["action"][:, k], rtol=0.0, atol=TOLERANCE)


def test_the_batched_planner_takes_the_single_agents_actions(recorded):
    """Both races, one led by car 0 and one by car 1, in the same batched solves."""
    _replay_batched(recorded, SEEDS)


def test_the_compiled_planner_takes_the_single_agents_actions(recorded):
    _replay_compiled(recorded)


@pytest.mark.slow
def test_in_a_field_the_batched_and_compiled_planners_take_the_single_agents_actions():
    """Three cars (two lane keepers): the pair game with the third car predicted as an obstacle,
    batched and compiled, against the single agent."""
    seeds = (4, 5)
    races = [_race(SPEC, seed, 4, rivals=("lane-keeping", "lane-keeping")) for seed in seeds]
    recorded = {key: np.stack([race[key] for race in races]) for key in ("x", "racing", "observation", "action")}
    assert all(record["leader"] in (0, 1, 2) and not record["fallback"] for race in races for record in race["record"])
    _replay_batched(recorded, seeds)
    _replay_compiled(recorded)


@pytest.mark.slow
def test_the_pair_game_of_a_two_car_race_is_the_races_stackelberg_game():
    """In a race of two the pair game is the race's game with its players reordered, leader
    first: the agent's plan is ``ilq.solve(game, mode="stackelberg", leader=ego)``'s, to the
    rounding of the reordered sums (measured: 3e-14 m, 3e-13 in the gains, after 30
    iterations of either)."""
    env = racing_env.parallel_env(track="trefoil", num_agents=2)
    env.reset(seed=0)
    x = env.state()
    for role, leader in (("leader", CAR), ("follower", 1 - CAR)):
        agent = make_agent(f"ilqgame-leader:role={role}")
        agent.reset(0, CAR, env)
        game = agent.planning_game.with_responsibility(x, agent.responsibility)
        us, xs, K, res = agent._solve(game, x, None)
        ref = ilq.solve(game, x, mode="stackelberg", leader=leader, max_iterations=agent.max_iterations,
                        **agent.solver_options)
        assert int(res.iterations) == int(ref.iterations)
        np.testing.assert_allclose(xs, np.asarray(ref.xs), rtol=0, atol=1e-9)
        np.testing.assert_allclose(us, np.asarray(ref.us), rtol=0, atol=1e-9)
        np.testing.assert_allclose(K, np.asarray(ref.K)[:, CAR], rtol=0, atol=1e-9)


@pytest.mark.slow
def test_certified_re_plans_are_local_stackelberg_solutions():
    """``certify=true``: every adopted re-plan carries the Stackelberg certificate's verdict;
    converged re-plans of the trefoil's start are local Stackelberg solutions."""
    race = _race("ilqgame-leader:role=auto,certify=true", 0, 3)
    records = race["record"]
    assert all(record["verdict"] is not None and record["certify_time"] > 0 for record in records)
    converged = [record for record in records if record["converged"]]
    assert converged and all(record["certified"] for record in converged)
