"""The compiled planner (planners.agents.compiled_planner) against the host batched planner."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import racing_env
from planners.agents.batched import make_batched_opponent
from racing_env.costs import racing_weights
from racing_env.physics import drive
from racing_env.vector import GymnaxRace, PlannedRace

RACES, STEPS = 3, 9


def _starts(env, races: int) -> np.ndarray:
    starts = []
    for seed in range(races):
        env.reset(seed=seed)
        starts.append(env.state())
    return np.stack(starts)


@pytest.mark.parametrize("spec", [
    "ilqgame-fb:iterations=2",
    pytest.param("ilqgame-ol:iterations=2,replan_every=3", marks=pytest.mark.slow),
    pytest.param("ilqr:iterations=3", marks=pytest.mark.slow),
])
def test_the_compiled_planner_takes_the_host_planners_actions(spec):
    """The same joint states and racing flags, step after step, with a race restarted and cars
    out of the race on the way: the compiled planner (vmapped over the races) acts as the host
    batched planner to rounding."""
    env = racing_env.parallel_env(track="trefoil", num_agents=2, weights=racing_weights())
    game = env.game
    host = make_batched_opponent(spec, game, 1, RACES)
    planner = host.jax_planner
    host.reset(np.ones(RACES, dtype=bool), np.arange(RACES))
    x = _starts(env, RACES)
    rng = np.random.default_rng(0)
    step = jax.jit(jax.vmap(planner.act))
    physics = jax.jit(jax.vmap(lambda x, a: drive(game, x, a)))
    initial = planner.initial()
    plans = jax.tree_util.tree_map(lambda a: jnp.stack([a] * RACES), initial)
    for k in range(STEPS):
        racing = np.ones((RACES, 2), dtype=bool)
        if k in (4, 5):
            racing[2, 0] = False  # the rival is out of race 2: a ghost in the plans
        if k == 6:
            racing[1, 1] = False  # the planner's own car is idle in race 1 for a step
        if k == 5:  # race 0 restarts: both forget its plan
            host.reset(np.array([True, False, False]), np.arange(RACES))
            plans = jax.tree_util.tree_map(lambda p, i: p.at[0].set(i), plans, initial)
        expected, _ = host.act(np.zeros((RACES, 1), np.float32), x, racing)
        actions, plans = step(plans, jnp.asarray(x), jnp.asarray(racing))
        np.testing.assert_allclose(np.asarray(actions), expected, rtol=0, atol=1e-9)
        assert np.all(np.asarray(actions)[racing[:, 1]] != 0.0)  # it drives where it races
        joint = np.zeros((RACES, 2, 2), np.float32)
        joint[:, 0] = rng.uniform(-1.0, 1.0, (RACES, 2))
        joint[:, 1] = np.float32(expected)
        x = np.asarray(physics(jnp.asarray(x), jnp.asarray(joint)))


def test_planner_opponents_race_inside_the_gymnax_step_and_re_plan_cold_after_a_restart():
    env = GymnaxRace(opponents=["ilqgame-fb:iterations=1"], track="trefoil", max_steps=3)
    params = env.default_params
    keys = jax.random.split(jax.random.key(0), 2)
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
    assert isinstance(state, PlannedRace) and not np.asarray(state.plans[0].has_plan).any()
    step = jax.jit(jax.vmap(env.race_step, in_axes=(0, 0, 0, None)))
    start = np.asarray(state.race.x)
    for k in range(2):
        obs, state, reward, done, info = step(jax.random.split(jax.random.key(k + 1), 2), state,
                                              jnp.zeros((2, 2)), params)
        assert np.asarray(state.plans[0].has_plan).all() and np.all(np.isfinite(np.asarray(obs)))
    # the planner's car drives its plan: its position, speed and heading after two steps are
    # its plan's, up to the env's float32 actions and its projection onto the acceleration
    # limits (sub-millimetre over one step)
    plan, kinematic = state.plans[0], [0, 1, 2, 3]
    np.testing.assert_allclose(np.asarray(state.race.x)[:, 1, kinematic], np.asarray(plan.xs)[:, 1, 1, kinematic],
                               rtol=0, atol=1e-4)
    assert not np.allclose(np.asarray(state.race.x)[:, 1], start[:, 1])
    obs, state, reward, done, info = step(jax.random.split(jax.random.key(9), 2), state, jnp.zeros((2, 2)), params)
    assert np.asarray(done).all()  # truncated at max_steps: restarted, and the plans forgotten
    assert not np.asarray(state.plans[0].has_plan).any() and np.all(np.asarray(state.race.steps) == 0)


def test_the_jax_learner_compiles_planners_with_a_fixed_budget_only():
    from experiments.rl.config import TrainConfig
    from experiments.rl.train_jax import compiled_races

    assert isinstance(compiled_races(TrainConfig(learner="jax", opponents=("ilqgame-fb:iterations=2",))), GymnaxRace)
    assert compiled_races(TrainConfig(learner="jax", opponents=("ilqgame-fb",))) is None
    assert compiled_races(TrainConfig(learner="jax", opponents=("ilqgame-fb:iterations=2,replan_every=5",))) is None
