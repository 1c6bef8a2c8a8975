"""Agents (planners.agents): races on a built-in and a real track, warm start, fallback,
the spec parser, diagnostics and a real (tiny) stable-baselines3 model."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import racing_env
from experiments.race import run_race
from planners import ilq
from planners.agents import (
    Agent,
    BaseAgent,
    ConstantSpeedAgent,
    FeedbackGameAgent,
    ILQRAgent,
    LaneKeepingAgent,
    OpenLoopGameAgent,
    RECOVERED_SPEED,
    SB3Agent,
    STOPPED_SPEED,
    make_agent,
    reset_agents,
)
from racing_env.costs import CostWeights

# races that run long: compiled with XLA's full optimisations (tests/conftest.py)
pytestmark = pytest.mark.optimized

GAME_SPECS = ["ilqr", "ilqgame-ol", "ilqgame-fb"]
ALL_SPECS = GAME_SPECS + ["lane-keeping", "constant-speed"]
# Recovery from a standstill and ghosts for cars out of the race are the receding-horizon
# agent's (planners/agents/receding_horizon.py), the same code for the three planners; the
# open-loop game differs from the feedback game only in its solver mode, iLQR in the problem
# it solves (the ego's, with the opponent predicted). Those tests run the feedback game by
# default, iLQR and the open-loop game in the slow run (iLQR races in the default run's short
# races and tournaments).
GAME_SPECS_DEFAULT_RUN = [pytest.param("ilqr", marks=pytest.mark.slow),
                          pytest.param("ilqgame-ol", marks=pytest.mark.slow), "ilqgame-fb"]


def _compile_listeners(compiles: list):
    """JAX event listeners that append to ``compiles`` every program XLA compiles and every
    program the run's on-disk compilation cache loads instead (a new program either way)."""

    def compiled(event, duration, **kwargs):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles.append(duration)

    def loaded(event, **kwargs):
        if event == "/jax/compilation_cache/cache_hits":
            compiles.append(0.0)

    return compiled, loaded


def _race(env, agent, seed=0):
    rival = make_agent("constant-speed", target_speed=12.0)
    reset_agents([agent, rival], env, seed)
    record = run_race(env, [agent, rival], seed=seed)
    actions = np.array([h["action"] for h in agent.history])
    return record, actions


def _check_race(record, agent, actions):
    assert len(agent.history) > 10
    assert np.all(np.isfinite(actions)) and np.all(np.abs(actions) <= 1.0)
    assert np.all(np.isfinite(record.xs))
    assert all(h["solve_time"] is not None and h["solve_time"] >= 0 for h in agent.history)
    assert record.summary[0]["distance"] > 50.0
    d = agent.diagnostics()
    assert {"solve_time", "iterations", "converged", "fallback", "error"} <= set(d)


@pytest.mark.parametrize("spec", [pytest.param(spec, marks=pytest.mark.slow) if spec == "ilqgame-ol" else spec
                                  for spec in ALL_SPECS])  # the open loop races the default run's tournaments
def test_short_race_trefoil(spec):
    env = racing_env.parallel_env(track="trefoil", num_agents=2, race_distance=150.0, max_steps=120)
    agent = make_agent(spec)
    record, actions = _race(env, agent)
    _check_race(record, agent, actions)
    assert record.summary[0]["finished"]
    if spec in GAME_SPECS:
        summary = agent.summary()
        assert summary["fallbacks"] == 0
        assert summary["replans"] == len(agent.history)
        assert record.summary[0]["time_off_track"] == 0.0


# the open-loop game and iLQR on Monza in the slow run: they race the trefoil above by
# default, the circuit's data reach the three planners through the same game (the feedback
# game races Monza here), and iLQR gets through Monza's chicane in test_prediction.py
@pytest.mark.parametrize("spec", [pytest.param(spec, marks=pytest.mark.slow) if spec in ("ilqgame-ol", "ilqr")
                                  else spec for spec in ALL_SPECS])
def test_short_race_monza(spec):
    env = racing_env.parallel_env(
        track="Monza", num_agents=2, race_distance=100.0, max_steps=60
    )
    agent = make_agent(spec)
    record, actions = _race(env, agent)
    _check_race(record, agent, actions)
    if spec in GAME_SPECS:
        assert agent.summary()["fallbacks"] == 0


class _Saturating(BaseAgent):
    """Asks for 3x the longitudinal jerk limit on every other step."""

    def act(self, observation, joint_state):
        wanted = np.array([3.0, 0.2]) if self._steps % 2 == 0 else np.array([0.3, -0.2])
        return self._act_guarded(lambda o, x: wanted, observation, joint_state)


def test_actions_beyond_the_jerk_limits_are_clipped_and_counted():
    env = racing_env.parallel_env(track="trefoil", num_agents=2)
    agent = _Saturating()
    agent.reset(0, 0, env)
    obs, _ = env.reset(seed=0)
    actions = [agent.act(obs["car_0"], env.state()) for _ in range(4)]
    np.testing.assert_allclose(actions[0], [1.0, 0.2], rtol=1e-6)
    np.testing.assert_allclose(actions[1], [0.3, -0.2], rtol=1e-6)
    assert [h["clipped"] for h in agent.history] == [True, False, True, False]
    assert agent.summary()["clipped_fraction"] == 0.5


def test_crossing_the_line_of_a_closed_track():
    """s is cumulative over laps: the planner goes on through s = L without special handling."""
    env = racing_env.parallel_env(track="trefoil", num_agents=2, laps=2, max_steps=40)
    L = env.track.length
    x0 = np.array([[L - 30.0, 18.0, 0.0, 0.0, 0.0, 0.0], [L - 45.0, 15.0, 2.0, 0.0, 0.0, 0.0]])
    agent, rival = FeedbackGameAgent(), ConstantSpeedAgent(target_speed=15.0)
    reset_agents([agent, rival], env, 0)
    obs, _ = env.reset(seed=0, options={"x0": x0})
    for _ in range(30):
        state = env.state()
        obs, *_ = env.step({"car_0": agent(obs["car_0"], state), "car_1": rival(obs["car_1"], state)})
    x = env.state()
    assert x[0, 0] > L + 15  # went through the line, s kept counting
    assert agent.summary()["fallbacks"] == 0
    assert abs(x[0, 2]) < 5.0  # still on the 12 m wide track


def test_warm_start_reduces_iterations():
    """The shifted previous plan needs fewer iterations than a cold start from the same states.

    Self-play (the rival plays the same feedback game), so the rival moves as predicted;
    against a scripted rival the equilibrium moves between steps and the gain is smaller.
    """
    env = racing_env.parallel_env(track="trefoil", num_agents=2, max_steps=8)
    warm, cold = FeedbackGameAgent(), FeedbackGameAgent(warm_start=False)
    rival = FeedbackGameAgent()
    reset_agents([warm, rival], env, 0)
    cold.reset(0, 0, env)
    # a grid in which the first solve needs the whole budget (30 iterations, cold or warm) and
    # the warm re-plans after it converge; on some grids the second re-plan still needs 30
    obs, _ = env.reset(seed=6)
    for _ in range(6):
        state = env.state()
        cold(obs["car_0"], state)
        obs, *_ = env.step({"car_0": warm(obs["car_0"], state), "car_1": rival(obs["car_1"], state)})
    w = [h["iterations"] for h in warm.history]
    c = [h["iterations"] for h in cold.history]
    assert w[0] == c[0]  # same cold first solve
    assert all(wi < w[0] for wi in w[1:]), w
    assert sum(w[1:]) < 0.7 * sum(c[1:]), (w, c)


# the receding-horizon agent's warm start is one code for every planner: the feedback game
# by default, the others and the regularised solver in the slow run
@pytest.mark.parametrize("spec", [pytest.param(spec, marks=pytest.mark.slow) for spec in (
    "ilqr", "ilqgame-ol", "ilqgame-fb:control_regularization=0.3,adaptive_regularization=true,"
    "feedforward_regularization=true")] + ["ilqgame-fb"])
def test_only_the_first_action_compiles(spec):
    """The first re-plan compiles the solver; warm-started re-plans after it must not.

    Counts XLA compilations (JAX's backend-compile events) from the second step on. A
    horizon no other test uses makes the compile cache cold for this game's shapes.
    """
    env = racing_env.parallel_env(track="trefoil", num_agents=2, max_steps=10, horizon=23)
    agent, rival = make_agent(spec), LaneKeepingAgent()
    reset_agents([agent, rival], env, 0)
    obs, _ = env.reset(seed=0)
    compiles = []
    listener, loaded = _compile_listeners(compiles)

    for step in range(4):
        if step == 1:
            jax.monitoring.register_event_duration_secs_listener(listener)
            jax.monitoring.register_event_listener(loaded)
        state = env.state()
        obs, *_ = env.step({"car_0": agent(obs["car_0"], state), "car_1": rival(obs["car_1"], state)})
    jax.monitoring.unregister_event_duration_listener(listener)
    jax.monitoring.unregister_event_listener(loaded)
    assert agent.summary()["replans"] == 4
    assert compiles == [], f"{len(compiles)} compilations after the first step ({sum(compiles):.1f} s)"


def test_replan_every_follows_the_plan_in_between():
    env = racing_env.parallel_env(track="trefoil", num_agents=2, max_steps=8)
    agent, rival = FeedbackGameAgent(replan_every=3), ConstantSpeedAgent()
    reset_agents([agent, rival], env, 0)
    obs, _ = env.reset(seed=0)
    for _ in range(7):
        state = env.state()
        obs, *_ = env.step({"car_0": agent(obs["car_0"], state), "car_1": rival(obs["car_1"], state)})
    assert [h["replanned"] for h in agent.history] == [True, False, False, True, False, False, True]
    between = [h for h in agent.history if not h["replanned"]]
    assert all(h["solve_time"] is None and not h["fallback"] for h in between)


def _drive_from_rest(agent, track: str, start, rival_speed: float, rival_s: float, steps: int) -> float:
    """Race ``agent`` from ``start`` (its ``[s, V, n, chi]``) for ``steps`` steps against a
    constant-speed car ahead on the centre line; the agent's speed at the end [m/s]."""
    env = racing_env.parallel_env(track=track, num_agents=2, max_steps=steps + 10)
    rival = make_agent("constant-speed", target_speed=rival_speed)
    reset_agents([agent, rival], env, 0)
    x0 = np.zeros((2, 6))
    x0[0, :4] = start
    x0[1, :2] = [rival_s, rival_speed]
    obs, _ = env.reset(seed=0, options={"x0": x0})
    for _ in range(steps):
        state = env.state()
        obs, *_ = env.step({"car_0": agent(obs["car_0"], state), "car_1": rival(obs["car_1"], state)})
    return float(env.state()[0, 1])


@pytest.mark.parametrize("spec", GAME_SPECS_DEFAULT_RUN)
def test_a_car_stopped_at_the_edge_facing_out_rejoins_in_recovery(spec):
    """A car at rest on the right edge of the straight, heading 0.6 rad into it, can only
    leave across the boundary (no reverse gear, no turning on the spot). At full track
    weight standing still is its best 5 s plan and it stands for good; in recovery (its
    own c_track scaled by recovery_track_scale until 5 m/s) it drives off. Racing jerk
    weights (r = 0.01) as in races."""
    speeds = {}
    for scale in (None, 1e-3, 1.0):  # None: the default (0)
        option = "" if scale is None else f",recovery_track_scale={scale}"
        agent = make_agent(f"{spec}:r_jx=0.01,r_jy=0.01{option}")
        # usable half-width: 6 m - 1 m (half the car)
        speeds[scale] = _drive_from_rest(agent, "straight", [100.0, 0.0, -5.0, -0.6], 10.0, 200.0, 20)
        recovering = [h.get("recovering") for h in agent.history]
        if scale is None or scale < 1.0:
            assert recovering[0] and agent.summary()["recovery_replans"] == sum(recovering)
        else:
            assert "recovering" not in agent.history[0] and "recovery_replans" not in agent.summary()
    assert speeds[1.0] == 0.0  # at full track weight it never moves
    assert speeds[1e-3] > 5.0  # measured 10.4 m/s after 2 s (12 re-plans in recovery) for all three
    assert speeds[None] > 5.0


# slow (the default run's budget): the car stopped at the edge facing out rejoins by default
@pytest.mark.slow
def test_a_car_stopped_across_monzas_first_chicane_rejoins_in_recovery():
    """The standstill of a Monza race (iLQR after a spin in the first chicane):
    at rest 3.5 m right of the centre line, heading 1.43 rad to the right of it, in the
    chicane's 12 m left-hand bend. Turning round needs metres of run-off: with the track
    term at 1e-3 of its weight standing still is still the best 5 s plan and the car
    stands; without it (the default) the car drives off and rejoins."""
    speeds = {}
    for option in ("", ",recovery_track_scale=0.001"):
        agent = make_agent(f"ilqr:r_jx=0.01,r_jy=0.01{option}")
        speeds[option] = _drive_from_rest(agent, "Monza", [964.5, 0.0, -3.47, -1.428],
                                          20.0, 1100.0, 40)
    assert speeds[",recovery_track_scale=0.001"] < STOPPED_SPEED
    assert speeds[""] > RECOVERED_SPEED


# slow (the default run's budget): tests/test_ilq.py checks by default that each car plans as if
# alone with the other out of the race
@pytest.mark.slow
@pytest.mark.parametrize("spec", GAME_SPECS)
def test_a_planner_drives_through_cars_out_of_the_race_as_the_env_does(spec):
    """Two cars collide at the first step and retire (``on_collision="terminate"``); the env
    freezes them 55 m ahead on the planner's line, and nothing collides with them any more.
    The planner treats them as ghosts once its observation flags them and drives straight
    through at speed, without recompiling. Planning against them as live cars instead, all
    three swerved (by 1.9, 0.8 and 2.7 m for ilqgame-fb, -ol and ilqr) and the feedback
    planner slowed to 14.7 m/s."""
    env = racing_env.parallel_env(track="straight", num_agents=3, race_distance=120.0, max_steps=100,
                                  on_collision="terminate",
                                  weights=CostWeights(r_jx=0.01, r_jy=0.01))
    agent = make_agent(spec)
    wreck = [make_agent("lane-keeping"), make_agent("lane-keeping")]
    reset_agents([agent, *wreck], env, 0)
    x0 = np.zeros((3, 6))
    x0[:, :3] = [[5.0, 15.0, 0.0], [60.0, 15.0, 0.5], [61.0, 15.0, -0.5]]  # cars 1 and 2 overlap
    obs, _ = env.reset(seed=0, options={"x0": x0})
    compiles = []
    listener, loaded = _compile_listeners(compiles)

    xs, last_info = [], {}
    try:
        while "car_0" in env.agents:
            if len(xs) == 1:
                jax.monitoring.register_event_duration_secs_listener(listener)
                jax.monitoring.register_event_listener(loaded)
            state = env.state()
            actions = {"car_0": agent(obs["car_0"], state)}
            actions.update({name: wreck[int(name[-1]) - 1](obs[name], state) for name in env.agents if name != "car_0"})
            obs, _, _, _, infos = env.step(actions)
            last_info.update(infos)
            xs.append(env.state()[0])
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
        jax.monitoring.unregister_event_listener(loaded)
    xs = np.array(xs)
    assert last_info["car_1"]["out"] and last_info["car_2"]["out"] and last_info["car_0"]["finished"]
    assert np.all(np.abs(env.state()[1:, 0] - [60.0, 61.0]) < 2.0)  # frozen where they met
    passing = (xs[:, 0] > 20.0) & (xs[:, 0] < 70.0)
    assert passing.sum() > 10
    # The planner keeps its line (n = 0: the optimum alone) and its speed
    assert np.abs(xs[passing, 2]).max() < 0.05
    assert xs[passing, 1].min() > 15.0
    assert compiles == [], f"{len(compiles)} compilations after the first step ({sum(compiles):.1f} s)"


@pytest.mark.parametrize("spec", ["ilqr:max_iterations=2", "ilqr:max_iterations=2,leading.c_collision=10"])
def test_a_joint_state_of_the_wrong_shape_brakes_with_or_without_place_weights(spec):
    env = racing_env.parallel_env(track="trefoil", num_agents=2)
    agent = make_agent(spec)
    agent.reset(0, 0, env)
    obs, _ = env.reset(seed=0)
    a = agent.act(obs["car_0"], env.state().reshape(-1))  # (12,) instead of (2, 6)
    d = agent.diagnostics()
    assert d["fallback_kind"] == "brake" and "joint state must have shape (2, 6)" in d["error"]
    assert a[0] < 0


@pytest.mark.parametrize("spec", GAME_SPECS)
def test_fallback_on_nan_state(spec):
    """A real solver failure: a NaN in the joint state gives non-finite solver output."""
    env = racing_env.parallel_env(track="trefoil", num_agents=2)
    agent = make_agent(spec)
    agent.reset(0, 0, env)
    obs, _ = env.reset(seed=0)
    x = env.state()
    # an opponent's state is NaN: no previous plan -> braking with a lateral correction
    bad = x.copy()
    bad[1, 2] = np.nan
    a = agent.act(obs["car_0"], bad)
    d = agent.diagnostics()
    assert np.all(np.isfinite(a)) and np.all(np.abs(a) <= 1)
    assert d["fallback"] and d["fallback_kind"] == "brake" and d["error"]
    assert a[0] < 0  # braking
    # a good solve, then a failing one: the previous plan (shifted) is followed
    agent.act(obs["car_0"], x)
    assert not agent.diagnostics()["fallback"]
    a = agent.act(obs["car_0"], bad)
    d = agent.diagnostics()
    assert np.all(np.isfinite(a)) and d["fallback"] and d["fallback_kind"] == "previous_plan"
    # the own state is NaN: the constant braking action
    bad[0] = np.nan
    agent2 = make_agent(spec)
    agent2.reset(0, 0, env)
    a = agent2.act(obs["car_0"], bad)
    np.testing.assert_array_equal(a, np.array([-0.5, 0.0], np.float32))


def test_fallback_when_the_solver_raises(monkeypatch):
    env = racing_env.parallel_env(track="trefoil", num_agents=2, race_distance=120.0, max_steps=200)
    agent = OpenLoopGameAgent()
    reset_agents([agent, LaneKeepingAgent()], env, 0)
    obs, _ = env.reset(seed=0)
    agent.act(obs["car_0"], env.state())  # a good plan first

    def broken(*args, **kwargs):
        raise RuntimeError("solver exploded")

    monkeypatch.setattr(ilq, "solve", broken)
    rival = LaneKeepingAgent()
    rival.reset(0, 1, env)
    kinds = []
    while env.agents:
        state = env.state()
        actions = {"car_1": rival(obs["car_1"], state)} if "car_1" in env.agents else {}
        if "car_0" in env.agents:
            actions["car_0"] = agent(obs["car_0"], state)
            d = agent.diagnostics()
            assert d["fallback"] and "solver exploded" in d["error"]
            kinds.append(d["fallback_kind"])
        obs, *_ = env.step(actions)
    acts = np.array([h["action"] for h in agent.history])
    assert np.all(np.isfinite(acts))
    # the stored plan (50 steps) is used up first, then the agent brakes
    assert kinds[:10] == ["previous_plan"] * 10
    assert len(kinds) > 60 and kinds[-1] == "brake"


def test_belief_weights():
    env = racing_env.parallel_env(track="trefoil", num_agents=2)
    agent = FeedbackGameAgent(belief_weights=CostWeights(c_collision=50.0, c_gap=0.0))
    agent.reset(0, 1, env)
    w = agent.planning_game.weights
    assert float(w.c_collision[0]) == 50.0 and float(w.c_gap[0]) == 0.0  # the opponent
    assert float(w.c_collision[1]) == float(env.game.weights.c_collision[1])  # own: true
    per_car = [CostWeights(c_gap=1.0), CostWeights(c_gap=0.2)]
    agent = ILQRAgent(belief_weights=per_car)
    agent.reset(0, 0, env)
    np.testing.assert_allclose(np.asarray(agent.planning_game.weights.c_gap), [1.0, 0.2])
    with pytest.raises(ValueError):
        ILQRAgent(belief_weights=[CostWeights()]).reset(0, 0, env)


def test_make_agent_specs(tmp_path):
    expected = {
        "ilqr": ILQRAgent,
        "ilqgame-ol": OpenLoopGameAgent,
        "ilqgame-fb": FeedbackGameAgent,
        "lane-keeping": LaneKeepingAgent,
        "constant-speed": ConstantSpeedAgent,
    }
    for spec, cls in expected.items():
        agent = make_agent(spec)
        assert type(agent) is cls and agent.name == spec
        assert isinstance(agent, Agent)
    assert make_agent("ilqgame-fb", max_iterations=5, replan_every=2).replan_every == 2
    for bad in ["ilqgame", "", "rl:", "lane-keeper"]:
        with pytest.raises(ValueError, match="ilqgame-fb"):
            make_agent(bad)
    with pytest.raises(ValueError, match="no model file at .*missing.zip"):
        make_agent(f"rl:{tmp_path / 'missing.zip'}")


def test_reset_accepts_game_and_gym_view():
    env = racing_env.parallel_env(track="straight", num_agents=2)
    agent = LaneKeepingAgent()
    agent.reset(None, 1, env.game)
    assert agent.index == 1 and agent.game is env.game
    with pytest.raises(ValueError):
        agent.reset(None, 2, env)
    with pytest.raises(TypeError):
        agent.reset(None, 0, object())
    with pytest.raises(RuntimeError):
        ConstantSpeedAgent().act(None, env.state())
    # as an opponent in the Gymnasium view
    import gymnasium

    gym_env = gymnasium.make("racing_env/Race-v0", opponents=[agent], track="straight", max_steps=5)
    agent.reset(0, 1, gym_env)
    gym_env.reset(seed=0)
    for _ in range(5):
        gym_env.step(np.zeros(2, np.float32))
    assert len(agent.history) == 5


def test_sb3_agent_real_ppo(tmp_path):
    import gymnasium
    from stable_baselines3 import PPO

    train_env = gymnasium.make("racing_env/Race-v0", track="straight", max_steps=64)
    model = PPO("MlpPolicy", train_env, n_steps=128, batch_size=64, n_epochs=1, seed=0, device="cpu")
    model.learn(total_timesteps=256)
    path = tmp_path / "ppo.zip"
    model.save(path)

    agent = make_agent(f"rl:{path}")
    assert isinstance(agent, SB3Agent) and agent.algo == "ppo"
    env = racing_env.parallel_env(track="straight", num_agents=2, max_steps=20)
    rival = ConstantSpeedAgent()
    reset_agents([agent, rival], env, 0)
    record = run_race(env, [agent, rival], seed=0)
    acts = np.array([h["action"] for h in agent.history])
    assert record.steps == 20 and acts.shape == (20, 2)
    assert np.all(np.isfinite(acts)) and np.all(np.abs(acts) <= 1)
    assert not any(h["fallback"] for h in agent.history)
    # the same actions as the model's own deterministic predict
    obs, _ = env.reset(seed=0)
    expected, _ = model.predict(obs["car_0"], deterministic=True)
    np.testing.assert_allclose(agent.act(obs["car_0"], env.state()), np.clip(expected, -1, 1), atol=1e-6)
    # a race of another size (3 cars) is refused at reset, where a tournament records the error
    env3 = racing_env.parallel_env(track="straight", num_agents=3)
    with pytest.raises(ValueError, match=r"reads observations of shape \(30,\), and car 0 of this 3-car race "
                                         r"observes \(37,\)"):
        agent.reset(0, 0, env3)
    # reset with only the game cannot tell; an observation of the wrong size then falls back instead of crashing
    agent.reset(0, 0, env3.game)
    obs3, _ = env3.reset(seed=0)
    a = agent.act(obs3["car_0"], env3.state())
    assert np.all(np.isfinite(a)) and agent.diagnostics()["fallback"]
    assert "observation shape" in agent.diagnostics()["error"]


@pytest.mark.parametrize("track_name", ["trefoil", "straight", "Monza"])
def test_lane_keeper_curvature_lookup_equals_numpy_periodic_interp(track_name):
    """The lane keeper prepares np.interp's periodic grid once; its lookups must be the
    very numbers np.interp(..., period=length) gives, wrapped arc lengths included."""
    from planners.scripted import LaneKeeping
    from racing_env import track as tr

    track = tr.get_track(track_name)
    rng = np.random.default_rng(0)
    L = track.length
    if track.closed:
        s = np.concatenate([rng.uniform(-2 * L, 3 * L, 2000), [-1e-20, -0.0, 0.0, L, 2 * L, -L, L - 1e-12]])
        expected = np.interp(np.mod(s, L), track.s, track.kappa, period=L)
    else:
        s = np.concatenate([rng.uniform(-10.0, L + 10.0, 2000), [0.0, L]])
        expected = np.interp(s, track.s, track.kappa)
    np.testing.assert_array_equal(LaneKeeping(track, index=0)._kappa(s), expected)


def test_lane_keeper_preview_offsets_equal_numpy_linspace():
    from planners.scripted import PREVIEW_POINTS, _preview_offsets

    reaches = np.concatenate([[0.0, 15.0, 1e-300], np.random.default_rng(4).uniform(0.0, 200.0, 2000)])
    for reach in reaches:
        np.testing.assert_array_equal(_preview_offsets(reach), np.linspace(0.0, reach, PREVIEW_POINTS))
