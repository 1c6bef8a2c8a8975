"""float32 as a solver and agent option (``precision="float32"``): its refusals, a float32
iteration that computes in float32 only, convergence where float64 converges (the
tolerance floor of :func:`planners.precision.rounding_floor`), and real-time agents whose
float32 decisions are their float64 ones to a derived tolerance."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import racing_env
from experiments.bench_scenes import perturbed_scenes
from experiments.paper import paper_game
from planners import ilq, precision, race_problem
from planners.agents import make_agent

REALTIME = "ilqgame-fb:iterations=2,trust_radius=10"  # the real-time planner (docs/experiments/cheap-replans.md)


@pytest.fixture(scope="module")
def paper():
    return paper_game()


def test_an_unknown_precision_is_refused_with_the_allowed_values():
    for bad in ("float16", "double", 32, None):
        with pytest.raises(ValueError, match=r"precision must be one of \('float64', 'float32'\)"):
            ilq.SolverOptions(precision=bad)
    with pytest.raises(ValueError, match="precision must be one of"):
        make_agent(REALTIME + ",precision=half")


def test_a_float32_tolerance_below_its_resolution_is_refused():
    eps32 = float(np.finfo(np.float32).eps)
    with pytest.raises(ValueError, match=r"below the resolution of float32 \(1\.19e-07\).*tolerance = 0.*>= 1\.19e-07"):
        ilq.SolverOptions(precision="float32", tolerance=1e-8)
    with pytest.raises(ValueError, match="below the resolution of float32"):
        make_agent(REALTIME + ",precision=float32,tolerance=1e-9")
    ilq.SolverOptions(precision="float32", tolerance=eps32)  # its resolution itself is allowed
    ilq.SolverOptions(precision="float32", tolerance=0.0)  # 0: run every iteration
    ilq.SolverOptions(precision="float64", tolerance=1e-8)


def _dtypes_out(jaxpr) -> set:
    """The dtypes of every equation's outputs in ``jaxpr`` and its inner jaxprs."""
    found = set()
    for eqn in jaxpr.eqns:
        found |= {str(v.aval.dtype) for v in eqn.outvars if hasattr(v.aval, "dtype")}
        for value in eqn.params.values():
            for item in value if isinstance(value, (tuple, list)) else (value,):
                inner = getattr(item, "jaxpr", item)
                if hasattr(inner, "eqns"):
                    found |= _dtypes_out(inner)
    return found


def test_a_float32_iteration_computes_nothing_in_float64(paper):
    game, x0 = paper
    problem = race_problem.problem_from_race_game(game)
    options = ilq.SolverOptions(precision="float32")
    us0 = np.zeros((game.horizon, 2, 2))

    def one_iteration(x0, us0):  # as the jitted solver does: the cast inside the trace
        p = ilq.at_precision(problem, options)
        return ilq.iterate(p, ilq.initial_carry(p, x0, us0, options), options)

    jaxpr = jax.make_jaxpr(one_iteration)(jnp.asarray(x0.reshape(-1)), jnp.asarray(us0))
    assert "float64" not in _dtypes_out(jaxpr.jaxpr)
    assert "float32" in _dtypes_out(jaxpr.jaxpr)


def test_float32_solves_converge_where_float64_does(paper):
    """The paper's scene, and the perturbed copy that ran a float32 solve to the 100-iteration
    cap at tolerance 1e-6 before the rounding floor (its convergence measure stalled at
    2^-19, float32's spacing of speeds near 20 m/s)."""
    game, x0 = paper
    stalled = perturbed_scenes(x0, 64)[52]
    for scene in (x0, stalled):
        r64 = ilq.solve(game, scene, mode="feedback", tolerance=1e-6)
        r32 = ilq.solve(game, scene, mode="feedback", tolerance=1e-6, precision="float32")
        assert bool(r64.converged) and bool(r32.converged), (int(r64.iterations), int(r32.iterations))
        assert r32.xs.dtype == jnp.float32 and r64.xs.dtype == jnp.float64
        # a float32 solve stops once its steps are within its rounding: no later than float64
        assert int(r32.iterations) <= int(r64.iterations)
        # Both are within tolerance + rounding of their fixed point, which float32's rounding
        # moves by about its resolution at the trajectory's scale: the floor bounds the gap
        # (measured 4e-5 m against 2.2e-4 m).
        xs32 = np.asarray(r32.xs).reshape(r32.xs.shape[0], -1)
        bound = float(precision.rounding_floor(jnp.asarray(xs32))) + 1e-6
        assert np.max(np.abs(np.asarray(r64.xs) - np.asarray(r32.xs))) <= bound


@pytest.mark.slow  # a long end: the default run stays within its budget
def test_float32_real_time_agents_take_the_float64_agents_decisions_on_a_recorded_race():
    """A race of the real-time planner (float64) against the lane keeper is recorded; a
    float64 and a float32 agent then act on the recorded states, each warm-started from its
    own plans.

    The tolerance, to first order: the float32 re-plan is the float64 re-plan from states
    known only to float32's rounding at the trajectory's scale, ``delta =
    rounding_floor(xs)`` (8 units of 2^-23 times the largest state entry, the cars'
    positions), and the first planned jerk answers a state change through the feedback
    gains: ``|du_0| <= ||K_0||_inf delta``; an action is that jerk over the jerk limit, and
    an action is a float32 (one more unit of its resolution)."""
    env = racing_env.parallel_env(track="trefoil", num_agents=2, race_distance=150.0)
    observations, _ = env.reset(seed=0)
    drivers = [make_agent(REALTIME), make_agent("lane-keeping")]
    for index, driver in enumerate(drivers):
        driver.reset(0, index, env)
    states, seen = [], []
    for _ in range(30):
        state = env.state()
        states.append(np.array(state))
        seen.append(observations["car_0"])
        actions = {car: drivers[j].act(observations[car], state) for j, car in enumerate(env.agents)}
        observations, *_ = env.step(actions)
    jerk_max = np.asarray(env.game.vehicles.jerk_max)[0]

    agents = {p: make_agent(REALTIME + f",precision={p}") for p in precision.PRECISIONS}
    for agent in agents.values():
        agent.reset(0, 0, env)
    eps32 = float(np.finfo(np.float32).eps)
    for step, (state, observation) in enumerate(zip(states, seen)):
        actions = {p: np.asarray(agent.act(observation, state), np.float64) for p, agent in agents.items()}
        plan = agents["float64"]._plan  # the ego's gains of the re-plan just made
        delta = float(precision.rounding_floor(jnp.asarray(np.asarray(plan["xs"], np.float32).reshape(len(plan["xs"]), -1))))
        gain = np.max(np.sum(np.abs(plan["K"][0]), axis=-1) / jerk_max)  # per unit of the action
        tolerance = gain * delta + eps32
        difference = np.max(np.abs(actions["float32"] - actions["float64"]))
        assert difference <= tolerance, (step, difference, tolerance)


@pytest.mark.slow  # a vectorised env and a GymnaxRace with a planner compiled into its step (about 40 s)
def test_float32_planner_opponents_race_in_the_vectorised_faces_without_changing_the_races_dtype():
    """The batched opponent (host races) and the compiled planner (GymnaxRace) take
    ``precision=float32``: their solves run in float32, the race stays in its own float64."""
    import gymnasium

    from racing_env.vector import GymnaxRace

    spec = REALTIME + ",precision=float32"
    envs = gymnasium.make_vec("racing_env/Race-v0", num_envs=2, vectorization_mode="vector_entry_point",
                              opponents=[spec], track="trefoil")
    observations, _ = envs.reset(seed=0)
    for _ in range(3):
        observations, *_ = envs.step(np.zeros((2, 2), np.float32))
    assert np.all(np.isfinite(observations))
    race = GymnaxRace(opponents=[spec], track="trefoil")
    params = race.default_params
    _, state = race.reset(jax.random.PRNGKey(0), params)
    step = jax.jit(race.step)
    for i in range(3):
        observation, state, *_ = step(jax.random.PRNGKey(i), state, jnp.zeros(2), params)
    assert np.all(np.isfinite(np.asarray(observation)))
    floats = {str(leaf.dtype) for leaf in jax.tree_util.tree_leaves(state) if jnp.issubdtype(leaf.dtype, jnp.floating)}
    assert floats == {"float64"}, floats
