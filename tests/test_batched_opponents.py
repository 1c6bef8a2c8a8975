"""Batched opponents (planners.agents.batched): one object driving one car in B races acts in
each race as a single agent of the same spec would, never returns NaN, and draws a pool's
drivers per race from the race's own seed."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import racing_env
from planners import BatchedOpponent, make_agent, make_batched_opponent
from planners.agents import BatchedPlanner, BatchedPool, BatchedScripted, LaneKeepingAgent, LoopedOpponent
from planners.scripted import BRAKE_ACTION, ConstantSpeed, LaneKeeping, jax_curvature, jax_policy
from racing_env import track as tracks
from racing_env.dynamics import N_LAT, V
from racing_env.observation import OTHER_FEATURES, OWN_FEATURES, cars_racing
from racing_env.physics import drive

CAR = 1  # the car the batched opponent drives; car 0 is driven by a single lane keeper per race

PLANNER_TOLERANCE = 1e-9
"""Batched against single planner actions. Each member of a batched solve is the single
agent's solve on the same inputs (``batching="map"`` runs the very same computation, and
``"vmap"`` the same operations in another order, which gave differences of ~1e-15 per
action), and both follow the same plan. The tolerance leaves that rounding, carried through
a few warm-started re-plans, six orders of magnitude; a wrong gain, shift or game gives
differences of 1e-3 and more."""

SCRIPTED_TOLERANCE = 1e-12
"""JAX against NumPy scripted laws (float64). The laws perform the same ~30 IEEE operations,
except that XLA fuses multiply-adds into one rounding and has its own ``sin``: each differs
by at most an ulp, 2.2e-16 relative, on terms up to ~100 (``kappa V^2``, accelerations
[m/s^2], speeds [m/s]), scaled by ACCEL_GAIN / jerk_max = 5 / 30 into the normalised action:
~1e-14. The NumPy law rounds its action to float32, so the JAX action must round to the same
float32 unless it lies within the tolerance of a rounding midpoint."""


def _single_action(agent, observation: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The single agent's action in float64, before its cast to float32: the planned jerk it
    follows (the same number as ``agent.act`` returns, rounded), or its braking action."""
    rounded = agent.act(observation, x)
    if agent.diagnostics()["fallback_kind"] == "brake":
        return rounded.astype(np.float64)
    action = np.clip(agent._follow(x, agent._age) / agent.jerk_max, -1.0, 1.0)
    np.testing.assert_array_equal(action.astype(np.float32), rounded)
    return action


class Races:
    """B PettingZoo races on a track: car 0 driven by a single lane keeper in each, car
    :data:`CAR` by the actions passed to :meth:`step`."""

    def __init__(self, seeds, track: str = "trefoil", x0s=None) -> None:
        self.envs = [racing_env.parallel_env(track=track, num_agents=2) for _ in seeds]
        self.rivals = [LaneKeepingAgent() for _ in seeds]
        self.observations: list = [None] * len(seeds)
        for b, seed in enumerate(seeds):
            self.restart(b, seed, None if x0s is None else x0s[b])

    @property
    def game(self):
        return self.envs[0].game

    def restart(self, b: int, seed: int, x0=None) -> None:
        options = None if x0 is None else {"x0": x0}
        self.observations[b], _ = self.envs[b].reset(seed=seed, options=options)
        self.rivals[b].reset(seed, 0, self.envs[b])

    def batch(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """This step's ``observations (B, obs)`` of car :data:`CAR`, ``x (B, 2, 6)`` and
        ``racing (B, 2)`` (as the observations flag them)."""
        observations = np.array([o[f"car_{CAR}"] for o in self.observations])
        x = np.array([env.state() for env in self.envs])
        racing = np.array([cars_racing(o, CAR, 2) for o in observations])
        return observations, x, racing

    def step(self, actions: np.ndarray) -> None:
        for b, env in enumerate(self.envs):
            rival = self.rivals[b](self.observations[b]["car_0"], env.state())
            self.observations[b], *_ = env.step({"car_0": rival, f"car_{CAR}": actions[b]})


def _start(spec: str, races: Races, seeds, **options) -> tuple[BatchedOpponent, list]:
    """The batched opponent of ``spec`` for the races, and one single agent per race."""
    opponent = make_batched_opponent(spec, races.game, CAR, len(seeds), **options)
    opponent.reset(np.ones(len(seeds), dtype=bool), np.asarray(seeds, dtype=np.int64))
    singles = [make_agent(spec) for _ in seeds]
    for b, seed in enumerate(seeds):
        singles[b].reset(seed, CAR, races.envs[b])
    return opponent, singles


def _restart(b: int, seed: int, races: Races, opponent: BatchedOpponent, singles: list, x0=None) -> None:
    races.restart(b, seed, x0)
    mask = np.zeros(opponent.num_races, dtype=bool)
    mask[b] = True
    opponent.reset(mask, np.full(opponent.num_races, seed, dtype=np.int64))
    singles[b].reset(seed, CAR, races.envs[b])


def _compare_step(opponent, singles, races) -> tuple[np.ndarray, dict, list[dict]]:
    """One step of the batched opponent and of the single agents on the same states; checks
    the actions and the re-plan diagnostics agree, returns them."""
    observations, x, racing = races.batch()
    actions, diagnostics = opponent.act(observations, x, racing)
    expected = np.array([_single_action(agent, observations[b], x[b]) for b, agent in enumerate(singles)])
    records = [agent.diagnostics() for agent in singles]
    assert actions.dtype == np.float64 and np.all(np.isfinite(actions)) and np.all(np.abs(actions) <= 1.0)
    np.testing.assert_allclose(actions, expected, rtol=0.0, atol=PLANNER_TOLERANCE)
    for b, record in enumerate(records):
        assert diagnostics["replanned"][b] == record["replanned"]
        assert diagnostics["fallback"][b] == record["fallback"]
        assert diagnostics["brake"][b] == (record["fallback_kind"] == "brake")
        if record["replanned"] and record["iterations"] is not None:
            assert diagnostics["iterations"][b] == record["iterations"]
            assert diagnostics["converged"][b] == record["converged"]
    return actions, diagnostics, records


# --------------------------------------------------------------------------------------
# Planners.
# --------------------------------------------------------------------------------------


# iLQR and feedback iLQGame re-planning every step, and feedback iLQGame following its plans
# in between (the path the three share); the rest run with the slow tests. The open-loop game
# is the feedback game's agent with the solver's other mode (planners/agents/receding_horizon.py:
# the mode enters only the solver options); the batched open-loop solve is each single solve in
# tests/test_ilq.py::test_batch_matches_individual_solves[open_loop-all devices-auto].
# The re-plans weigh collisions by responsibility (the default: per-race collision scales from
# each race's state), but those of the planners re-planning every third step, which take the
# symmetric cost (responsibility=1: no scales), so that both forms are checked (and these races
# keep re-plans that converge below the iteration cap).
@pytest.mark.parametrize("method, replan_every", [
    ("ilqgame-fb", 1), pytest.param("ilqgame-ol", 1, marks=pytest.mark.slow), ("ilqr", 1), ("ilqgame-fb", 3),
    pytest.param("ilqgame-ol", 3, marks=pytest.mark.slow), pytest.param("ilqr", 3, marks=pytest.mark.slow),
])
def test_a_batched_planner_takes_the_single_agents_actions(method, replan_every):
    """Three races, two of which restart mid-way (each race has its own plan age), driven
    forward by the batched actions; every step's actions equal the single agents'."""
    spec = f"{method}:replan_every={replan_every}" + (",responsibility=1" if replan_every == 3 else "")
    seeds = [3, 1, 2]  # car 1 behind in seed 3's grid, ahead in the others'
    races = Races(seeds)
    opponent, singles = _start(spec, races, seeds)
    assert isinstance(opponent, BatchedPlanner) and opponent.jax_policy is None
    restarts = {3: (1, 11), 5: (2, 12)}  # step: (race, seed)
    below_cap = 0
    for step in range(8):
        if step in restarts:
            _restart(*restarts[step], races, opponent, singles)
        actions, diagnostics, _ = _compare_step(opponent, singles, races)
        cap = singles[0].max_iterations
        below_cap += int(np.sum(diagnostics["replanned"] & (diagnostics["iterations"] < cap)))
        races.step(actions)
    assert below_cap > 0  # re-plans that stopped at their own convergence, not at the cap


def test_vmap_batching_takes_the_single_agents_actions():
    """Lock-step solves (``batching="vmap"``) compute the same solves in another order."""
    seeds = [3, 4, 5]
    races = Races(seeds)
    opponent, singles = _start("ilqgame-fb", races, seeds, batching="vmap")
    assert opponent.batching == "vmap"
    for step in range(4):
        if step == 2:
            _restart(0, 13, races, opponent, singles)
        actions, _, _ = _compare_step(opponent, singles, races)
        races.step(actions)


def test_each_race_plans_with_the_weights_of_its_own_place_and_recovery():
    """Leading / trailing weights and the recovery track scale (on by default) make the
    races' games differ: car 1 ahead in one race, behind in another, stopped in a third."""
    spec = "ilqgame-fb:leading.c_collision=20,trailing.c_collision=2"
    stopped = np.array([[-9.3, 15.0, -2.0, 0.0, 0.0, 0.0], [-5.0, 0.0, 1.7, 0.0, 0.0, 0.0]])
    seeds = [1, 3, 2]  # car 1 starts ahead in seed 1's grid, behind in seed 3's
    races = Races(seeds, x0s=[None, None, stopped])
    opponent, singles = _start(spec, races, seeds)
    leading, recovering = [], []
    for _ in range(3):
        actions, diagnostics, records = _compare_step(opponent, singles, races)
        assert diagnostics["leading"].tolist() == [r["leading"] for r in records]
        assert diagnostics["recovering"].tolist() == [r["recovering"] for r in records]
        leading.append(diagnostics["leading"])
        recovering.append(diagnostics["recovering"])
        races.step(actions)
    assert leading[0].tolist() == [True, False, True] and recovering[0].tolist() == [False, False, True]


def test_a_car_out_of_one_race_is_a_ghost_in_that_races_plan_only():
    """The racing flags differ per race (the env's for the batched opponent, the
    observation's for the single agent): car 0 out of race 1 only."""
    seeds = [0, 1, 2]
    races = Races(seeds)
    opponent, singles = _start("ilqgame-fb", races, seeds)
    flag = OWN_FEATURES + OTHER_FEATURES - 1  # car 1's observation: whether car 0 still races
    for _ in range(3):
        observations, x, racing = races.batch()
        observations[1, flag] = 0.0
        racing[1, 0] = False
        assert cars_racing(observations[1], CAR, 2).tolist() == [False, True]
        actions, _ = opponent.act(observations, x, racing)
        expected = np.array([_single_action(agent, observations[b], x[b]) for b, agent in enumerate(singles)])
        np.testing.assert_allclose(actions, expected, rtol=0.0, atol=PLANNER_TOLERANCE)
        races.step(actions)


def test_a_race_whose_solve_fails_falls_back_as_the_single_agent_does():
    """NaN or inf in one race's state fails that race's solve only: it follows its previous
    plan, or brakes without one, exactly as the single agent; the other races plan as usual."""
    seeds = [0, 1, 2]
    races = Races(seeds)
    opponent, singles = _start("ilqgame-fb", races, seeds)

    def step_with(corrupt) -> dict:
        observations, x, racing = races.batch()
        for b, index, value in corrupt:
            x[b][index] = value
        actions, diagnostics = opponent.act(observations, x, racing)
        expected = np.array([_single_action(agent, observations[b], x[b]) for b, agent in enumerate(singles)])
        assert np.all(np.isfinite(actions))
        np.testing.assert_allclose(actions, expected, rtol=0.0, atol=PLANNER_TOLERANCE)
        races.step(actions)
        kinds = [agent.diagnostics()["fallback_kind"] for agent in singles]
        assert diagnostics["fallback"].tolist() == [k is not None for k in kinds]
        assert diagnostics["brake"].tolist() == [k == "brake" for k in kinds]
        return kinds

    assert step_with([]) == [None, None, None]
    # race 1: an opponent's lateral offset is NaN -> its previous plan, shifted
    assert step_with([(1, (0, N_LAT), np.nan)]) == [None, "previous_plan", None]
    # race 2 restarts (no plan) with an infinite opponent speed -> the braking law
    _restart(2, 22, races, opponent, singles)
    assert step_with([(1, (0, N_LAT), np.nan), (2, (0, V), np.inf)]) == [None, "previous_plan", "brake"]
    # race 0: the car's own state is NaN -> the constant braking action
    _restart(0, 20, races, opponent, singles)
    observations, x, racing = races.batch()
    x[0, CAR] = np.nan
    actions, diagnostics = opponent.act(observations, x, racing)
    np.testing.assert_array_equal(actions[0], BRAKE_ACTION)
    assert diagnostics["brake"].tolist() == [True, False, False] and np.all(np.isfinite(actions))


# --------------------------------------------------------------------------------------
# Scripted drivers.
# --------------------------------------------------------------------------------------


def _random_states(track, count: int, seed: int = 0) -> np.ndarray:
    """Joint states ``(count, 2, 6)`` over the track and beyond its ends (s wraps on closed
    tracks), at speeds from a slight reverse to above v_max."""
    rng = np.random.default_rng(seed)
    x = np.empty((count, 2, 6))
    length = track.length
    low, high = (-length, 3 * length) if track.closed else (-20.0, length + 20.0)
    x[..., 0] = rng.uniform(low, high, (count, 2))
    x[..., 1] = rng.uniform(-1.0, 35.0, (count, 2))
    x[..., 2] = rng.uniform(-6.0, 6.0, (count, 2))
    x[..., 3] = rng.uniform(-0.5, 0.5, (count, 2))
    x[..., 4] = rng.uniform(-10.0, 8.0, (count, 2))
    x[..., 5] = rng.uniform(-12.0, 12.0, (count, 2))
    return x


def _assert_law_matches(jax_actions: np.ndarray, numpy_actions: np.ndarray) -> None:
    """float64 JAX actions against the NumPy law's float32 ones (see SCRIPTED_TOLERANCE)."""
    rounded = jax_actions.astype(np.float32)
    below = np.nextafter(rounded, np.float32(-np.inf)).astype(np.float64)
    above = np.nextafter(rounded, np.float32(np.inf)).astype(np.float64)
    midpoint_gap = np.minimum(np.abs(jax_actions - (rounded + below) / 2), np.abs(jax_actions - (rounded + above) / 2))
    decided = midpoint_gap > SCRIPTED_TOLERANCE
    np.testing.assert_array_equal(rounded[decided], numpy_actions[decided])
    half_ulp = np.spacing(np.abs(numpy_actions)).astype(np.float64) / 2
    assert np.all(np.abs(jax_actions - numpy_actions) <= half_ulp + SCRIPTED_TOLERANCE)


@pytest.mark.parametrize("track_name", ["trefoil", "straight"])
def test_the_scripted_jax_laws_equal_the_numpy_laws(track_name):
    track = tracks.get_track(track_name)
    x = _random_states(track, 3000)
    controllers = [LaneKeeping(track, CAR, target_n=1.5), LaneKeeping(track, CAR, target_speed=18.0),
                   ConstantSpeed(track, CAR, target_speed=12.0)]
    for controller in controllers:
        jax_actions = np.asarray(jax.jit(jax.vmap(jax_policy(controller)))(x))
        numpy_actions = np.array([controller(None, state) for state in x])
        assert jax_actions.dtype == np.float64 and np.mean(np.abs(numpy_actions) < 1.0) > 0.3  # not all clipped
        _assert_law_matches(jax_actions, numpy_actions)


@pytest.mark.parametrize("track_name", ["trefoil", "straight"])
def test_the_jax_curvature_preview_is_numpys_interpolation(track_name):
    """The lookup behind the preview, wrap included: np.interp's numbers, but for XLA's fused
    multiply-add (one rounding of ``slope (s - s_j) + kappa_j`` where NumPy rounds twice: at
    most eps (|slope (s - s_j)| + |kappa|) <= eps (2 max|kappa| + |kappa|))."""
    track = tracks.get_track(track_name)
    controller = LaneKeeping(track, 0)
    s = _random_states(track, 4000, seed=1)[:, :, 0].ravel()
    s = np.concatenate([s, [0.0, -0.0, track.length, 2 * track.length, -track.length, track.length - 1e-12]])
    got = np.asarray(jax.jit(jax_curvature(controller))(s))
    expected = controller._kappa(s)
    bound = np.finfo(np.float64).eps * (2 * np.max(np.abs(track.kappa)) + np.abs(expected))
    assert np.all(np.abs(got - expected) <= bound)


def test_a_batched_scripted_driver_acts_with_its_jax_law_in_every_race():
    game = racing_env.parallel_env(track="trefoil", num_agents=2).game
    opponent = make_batched_opponent("lane-keeping:target_n=1.5", game, CAR, 5)
    assert isinstance(opponent, BatchedScripted)
    opponent.reset(np.ones(5, dtype=bool), np.arange(5))
    x = _random_states(game.track, 5, seed=2)
    x[3, CAR] = np.nan  # the car's own state: the constant braking action
    racing = np.ones((5, 2), dtype=bool)
    racing[4, CAR] = False  # no longer racing: idle
    actions, diagnostics = opponent.act(np.zeros((5, 30), np.float32), x, racing)
    single = make_agent("lane-keeping:target_n=1.5")
    single.reset(0, CAR, game)
    for b in range(3):
        _assert_law_matches(actions[b:b + 1], single.act(None, x[b])[None])
    np.testing.assert_array_equal(actions[3], single.act(None, x[3]))
    np.testing.assert_array_equal(actions[3], BRAKE_ACTION)
    np.testing.assert_array_equal(actions[4], [0.0, 0.0])
    assert diagnostics["brake"].tolist() == [False, False, False, True, False]
    # the law as the vector env uses it: fused into a jitted, vmapped step with the physics
    fused = jax.jit(jax.vmap(lambda state: drive(game, state, jax.numpy.stack([state[0, :2] * 0.0,
                                                                                opponent.jax_policy(state)]))))
    assert np.all(np.isfinite(np.asarray(fused(x[:3]))))


# --------------------------------------------------------------------------------------
# Pools, the looped fallback, RL policies.
# --------------------------------------------------------------------------------------


def test_a_pool_draws_each_races_driver_from_its_own_seed_whatever_the_batch_size():
    specs = ["lane-keeping", "constant-speed:target_speed=12", "lane-keeping:target_n=2"]
    game = racing_env.parallel_env(track="trefoil", num_agents=2).game
    seeds = np.array([5, 1, 11, 99, 42, 7, 8, 1000])
    drawn = [int(np.random.default_rng(seed).integers(len(specs))) for seed in seeds]
    assert len(set(drawn)) == len(specs)
    x = _random_states(game.track, 8, seed=3)
    results = []
    for size in (3, 8):
        pool = make_batched_opponent(specs, game, CAR, size)
        assert isinstance(pool, BatchedPool) and pool.jax_policy is None
        pool.reset(np.ones(size, dtype=bool), seeds[:size])
        actions, diagnostics = pool.act(np.zeros((size, 30), np.float32), x[:size], np.ones((size, 2), dtype=bool))
        assert diagnostics["driver"].tolist() == drawn[:size]
        results.append(actions)
        for b in range(size):
            single = make_agent(specs[drawn[b]])
            single.reset(int(seeds[b]), CAR, game)
            _assert_law_matches(actions[b:b + 1], single.act(None, x[b])[None])
    np.testing.assert_array_equal(results[0], results[1][:3])
    # a reset draws again for the races reset only
    pool.reset(np.arange(8) == 2, np.full(8, 4, dtype=np.int64))
    assert pool.driver.tolist() == drawn[:2] + [int(np.random.default_rng(4).integers(3))] + drawn[3:]


def test_a_pool_with_a_planner_plans_in_the_races_that_drew_it_only():
    seeds = [1, 0, 3]  # draws over two entries: 0, 1, 1
    specs = ["ilqgame-fb", "lane-keeping"]
    assert [int(np.random.default_rng(s).integers(2)) for s in seeds] == [0, 1, 1]
    races = Races(seeds)
    pool = make_batched_opponent(specs, races.game, CAR, 3)
    pool.reset(np.ones(3, dtype=bool), np.array(seeds))
    singles = [make_agent(specs[d]) for d in (0, 1, 1)]
    for b, seed in enumerate(seeds):
        singles[b].reset(seed, CAR, races.envs[b])
    for _ in range(3):
        observations, x, racing = races.batch()
        actions, diagnostics = pool.act(observations, x, racing)
        assert diagnostics["replanned"].tolist() == [True, False, False]
        np.testing.assert_allclose(actions[0], _single_action(singles[0], observations[0], x[0]),
                                   rtol=0.0, atol=PLANNER_TOLERANCE)
        for b in (1, 2):
            _assert_law_matches(actions[b:b + 1], singles[b].act(observations[b], x[b])[None])
        races.step(actions)


def test_an_option_that_cannot_be_batched_races_as_looped_single_agents():
    spec = "ilqr:prediction=lane-keeping"
    seeds = [0, 1]
    races = Races(seeds)
    with pytest.warns(UserWarning, match="prediction 'lane-keeping' is not batched"):
        opponent, singles = _start(spec, races, seeds)
    assert isinstance(opponent, LoopedOpponent)
    for _ in range(2):
        observations, x, racing = races.batch()
        actions, diagnostics = opponent.act(observations, x, racing)
        np.testing.assert_array_equal(actions, [agent.act(observations[b], x[b]) for b, agent in enumerate(singles)])
        assert diagnostics["replanned"].all()
        races.step(actions)


def test_a_saved_sb3_policy_acts_for_every_race_as_the_single_agent(tmp_path):
    """An untrained PPO policy with saved observation statistics: the batched predictions
    equal the single agent's. float32 network: a batch and a single row may sum the
    products of a layer in another order, at most n eps32 |terms| per layer (n <= 64
    inputs, eps32 = 6e-8, terms of order 1, three layers): 2e-5."""
    gymnasium = pytest.importorskip("gymnasium")
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    from planners.agents import BatchedSB3, vecnormalize_path

    def make_env():
        return gymnasium.make("racing_env/Race-v0", track="straight")

    model = PPO("MlpPolicy", make_env(), seed=0, device="cpu")
    path = tmp_path / "ppo.zip"
    model.save(path)
    statistics = VecNormalize(DummyVecEnv([make_env]), norm_reward=False)
    rng = np.random.default_rng(0)
    statistics.obs_rms.mean = rng.normal(size=statistics.obs_rms.mean.shape)
    statistics.obs_rms.var = rng.uniform(0.5, 4.0, size=statistics.obs_rms.var.shape)
    statistics.save(str(vecnormalize_path(path)))

    seeds = [0, 1, 2, 3]
    races = Races(seeds, track="straight")
    opponent = make_batched_opponent(f"rl:{path}", races.game, CAR, len(seeds))
    assert isinstance(opponent, BatchedSB3) and opponent.agent.normalizer is not None
    opponent.reset(np.ones(len(seeds), dtype=bool), np.array(seeds))
    single = make_agent(f"rl:{path}")
    single.reset(0, CAR, races.envs[0])
    for _ in range(3):
        observations, x, racing = races.batch()
        actions, _ = opponent.act(observations, x, racing)
        expected = np.array([single.act(observations[b], x[b]) for b in range(len(seeds))])
        np.testing.assert_allclose(actions, expected, rtol=0.0, atol=2e-5)
        races.step(actions)


# --------------------------------------------------------------------------------------
# Bad input.
# --------------------------------------------------------------------------------------


def test_bad_specs_options_and_inputs_are_refused_with_what_is_allowed():
    game = racing_env.parallel_env(track="trefoil", num_agents=2).game
    with pytest.raises(ValueError, match="has no option 'bogus'"):
        make_batched_opponent("ilqgame-fb:bogus=1", game, CAR, 2)
    with pytest.raises(ValueError, match="unknown agent spec"):
        make_batched_opponent("rocket", game, CAR, 2)
    with pytest.raises(ValueError, match=r"index must be a car index in \[0, 2\)"):
        make_batched_opponent("lane-keeping", game, 2, 2)
    with pytest.raises(ValueError, match="num_races must be an integer >= 1"):
        make_batched_opponent("lane-keeping", game, CAR, 0)
    with pytest.raises(ValueError, match="batching must be 'auto', 'map' or 'vmap'"):
        make_batched_opponent("ilqgame-ol", game, CAR, 2, batching="pmap")
    with pytest.raises(ValueError, match="solve_sizes must be multiples"):
        make_batched_opponent("ilqr", game, CAR, 4, solve_sizes=[3], devices=jax.devices()[:1])
    with pytest.raises(ValueError, match="a pool needs a non-empty list"):
        make_batched_opponent([], game, CAR, 2)
    opponent = make_batched_opponent("ilqgame-fb", game, CAR, 2)
    x, observations, racing = np.zeros((2, 2, 6)), np.zeros((2, 30), np.float32), np.ones((2, 2), dtype=bool)
    with pytest.raises(RuntimeError, match="must start every race"):
        opponent.act(observations, x, racing)
    with pytest.raises(ValueError, match="races must be booleans"):
        opponent.reset(np.ones(2), np.zeros(2, dtype=np.int64))
    opponent.reset(np.ones(2, dtype=bool), np.zeros(2, dtype=np.int64))
    with pytest.raises(ValueError, match=r"x must have shape \(2, 2, 6\)"):
        opponent.act(observations, x[:, :1], racing)
    pool = make_batched_opponent(["lane-keeping"], game, CAR, 2)
    with pytest.raises(ValueError, match="must be >= 0"):
        pool.reset(np.ones(2, dtype=bool), np.array([1, -1]))
