"""GymnaxRace as a gymnax environment: the params' step limit, float32 at the face, JAX
spaces, the installed gymnax's step and wrappers, params of another race refused, the race
in float32 with ``jax_enable_x64`` off, and rejax's learners training on it unmodified."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from racing_env.vector import GYMNAX_INSTALLED, LEARNER_OFF_TRACK, SIX_VALUE_STEP, Box, GymnaxRace

ROOT = Path(__file__).resolve().parents[1]
INFO_KEYS = {"terminated", "truncated", "position", "finished", "out", "finish_time", "collided", "off_track",
             "nonfinite_action"}


@pytest.fixture(scope="module")
def env() -> GymnaxRace:
    return GymnaxRace(opponents=["lane-keeping"], track="trefoil", max_steps=6)


def test_a_learner_that_leaves_the_track_is_out_unless_the_config_says_otherwise(env):
    """GymnaxRace's one default of its own: off the track the learner's race ends (the rule
    ``racing train`` trains with); the config's word wins."""
    assert env.race.config.on_off_track == LEARNER_OFF_TRACK == "terminate"
    params = env.default_params
    assert bool(params.rules.retire_off_track)
    penalised = GymnaxRace(opponents=["lane-keeping"], track="trefoil", max_steps=6, on_off_track="penalty")
    assert penalised.race.config.on_off_track == "penalty" and not bool(penalised.default_params.rules.retire_off_track)


def test_the_params_carry_gymnax_step_limit_and_replace_it(env):
    params = env.default_params
    assert int(params.max_steps_in_episode) == int(params.max_steps) == 6
    longer = params.replace(max_steps_in_episode=9)
    assert int(longer.max_steps) == int(longer.max_steps_in_episode) == 9 and longer.max_steps.dtype == jnp.int32
    assert int(params.replace(max_steps=7).max_steps_in_episode) == 7
    with pytest.raises(ValueError, match="not both"):
        params.replace(max_steps=7, max_steps_in_episode=8)
    # a pytree under jit: the step limit is a traced value, one compiled reset serves both
    steps = jax.jit(lambda p: p.max_steps_in_episode + 0)(longer)
    assert int(steps) == 9


def test_the_spaces_sample_with_a_key_eagerly_under_jit_and_under_vmap(env):
    space = env.action_space(env.default_params)
    observations = env.observation_space(env.default_params)
    assert isinstance(space, Box) and space.shape == (2,) and space.dtype == np.float32
    eager = space.sample(jax.random.key(1))
    jitted = jax.jit(space.sample)(jax.random.key(1))
    batch = jax.vmap(observations.sample)(jax.random.split(jax.random.key(2), 8))
    raw = space.sample(jax.random.PRNGKey(3))  # a raw uint32 key too
    assert eager.dtype == jitted.dtype == batch.dtype == raw.dtype == jnp.float32
    np.testing.assert_array_equal(np.asarray(eager), np.asarray(jitted))
    assert batch.shape == (8,) + observations.shape and len(np.unique(np.asarray(batch)[:, 0])) == 8
    assert bool(space.contains(eager)) and bool(jax.vmap(observations.contains)(batch).all())
    assert not bool(space.contains(jnp.array([1.5, 0.0]))) and not bool(space.contains(jnp.zeros(3)))
    for bad in ((), (None,), (0,), (np.zeros(2),)):
        with pytest.raises(TypeError, match="needs a JAX random key"):
            space.sample(*bad)
    if GYMNAX_INSTALLED:
        from gymnax.environments import spaces

        assert isinstance(space, spaces.Box)


def test_the_step_is_the_installed_gymnax_step_with_float32_at_the_face(env):
    params = env.default_params
    obs, state = env.reset(jax.random.key(0), params)
    assert obs.dtype == jnp.float32 and obs.shape == env.observation_space(params).shape
    outputs = []
    step = jax.jit(env.step)
    for k in range(6):  # the sixth step truncates the race, which restarts within the step
        out = step(jax.random.key(k + 1), state, jnp.array([0.5, 0.0], jnp.float32), params)
        state = out[1]
        outputs.append(out)
    obs, state, reward, *flags, info = outputs[-1]
    assert len(outputs[-1]) == (6 if SIX_VALUE_STEP else 5)
    assert reward.dtype == jnp.float32 and info["finish_time"].dtype == jnp.float32
    assert INFO_KEYS <= set(info) and bool(info["truncated"]) and not bool(info["terminated"])
    done = flags[0] | flags[1] if SIX_VALUE_STEP else flags[0]
    assert bool(done) and not any(bool(o[3]) for o in outputs[:-1])
    assert int(state.steps) == 0  # obs and state are the new race's
    np.testing.assert_array_equal(np.asarray(obs), np.asarray(env.reset_env(jax.random.split(jax.random.key(6))[1],
                                                                            params)[0]))
    if SIX_VALUE_STEP:
        assert not bool(flags[0]) and bool(flags[1]) and "final_observation" in info
    if GYMNAX_INSTALLED:  # race_step is the five-value step whatever gymnax is installed (without: step)
        from gymnax.environments.environment import Environment

        assert isinstance(env, Environment)
        five = jax.jit(env.race_step)(jax.random.key(1), env.reset(jax.random.key(0), params)[1], jnp.zeros(2),
                                      params)
        assert len(five) == 5 and five[2].dtype == jnp.float32


def test_params_of_another_race_are_refused(env):
    for other in (GymnaxRace(opponents=["lane-keeping", None], track="trefoil"),  # three cars
                  GymnaxRace(opponents=["lane-keeping"], track="straight")):
        with pytest.raises(ValueError, match="params of another race"):
            env.reset(jax.random.key(0), other.default_params)


@pytest.mark.parametrize("action, error", [
    (jnp.float32(0.5), ValueError),  # a scalar is not broadcast to both jerks
    (jnp.zeros(3, jnp.float32), ValueError),
    (jnp.zeros((1, 2), jnp.float32), ValueError),
    (jnp.array([True, False]), TypeError),
])
def test_an_action_of_another_shape_or_dtype_is_refused_when_the_step_is_traced(env, action, error):
    params = env.default_params
    _, state = env.reset(jax.random.key(0), params)
    for step in (env.step, env.race_step):
        with pytest.raises(error, match=r"learner's action must .*shape \(2,\)"):
            jax.jit(step)(jax.random.key(1), state, action, params)
    batch = jnp.broadcast_to(action, (4,) + jnp.shape(action))  # each race's action is the bad one
    states = jax.tree_util.tree_map(lambda leaf: jnp.broadcast_to(leaf, (4,) + jnp.shape(leaf)), state)
    with pytest.raises(error, match=r"shape \(2,\)"):
        jax.vmap(env.race_step, in_axes=(0, 0, 0, None))(jax.random.split(jax.random.key(1), 4), states, batch, params)


def test_a_nonfinite_action_is_zero_jerk_and_flagged(env):
    """A NaN or inf in the learner's action steps the race as zero jerk does, bit for bit,
    with ``info["nonfinite_action"]``; the race stays finite."""
    params = env.default_params
    _, state = env.reset(jax.random.key(0), params)
    step = jax.jit(env.race_step)
    zero = step(jax.random.key(1), state, jnp.zeros(2, jnp.float32), params)
    assert not bool(zero[4]["nonfinite_action"])
    for bad in ([jnp.nan, 0.3], [0.2, jnp.inf], [-jnp.inf, jnp.nan]):
        out = step(jax.random.key(1), state, jnp.array(bad, jnp.float32), params)
        assert bool(out[4]["nonfinite_action"])
        for got, expected in zip(jax.tree_util.tree_leaves(out[:4]), jax.tree_util.tree_leaves(zero[:4])):
            np.testing.assert_array_equal(np.asarray(got), np.asarray(expected))
        assert bool(jnp.isfinite(out[0]).all()) and bool(jnp.isfinite(out[2]))


@pytest.mark.skipif(not GYMNAX_INSTALLED, reason="gymnax is not installed (pip install racing-games[jaxrl])")
def test_gymnax_wrappers_run_on_the_race(env):
    from gymnax.wrappers.purerl import FlattenObservationWrapper, LogWrapper

    wrapped = LogWrapper(FlattenObservationWrapper(env))
    params = env.default_params
    obs, state = wrapped.reset(jax.random.key(0), params)

    def body(state, key):
        out = wrapped.step(key, state, jnp.array([0.5, 0.0], jnp.float32), params)
        return out[1], out[2]

    state, rewards = jax.lax.scan(body, state, jax.random.split(jax.random.key(1), 7))
    assert rewards.dtype == jnp.float32 and bool(jnp.isfinite(rewards).all())
    assert int(state.returned_episode_lengths) == 6  # one race of max_steps ended and was logged
    assert wrapped.observation_space(params).shape == obs.shape


def _run(code: str, *args: str, timeout: int = 600) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code), *args], capture_output=True, text=True,
                          timeout=timeout, env=env, cwd=ROOT)


def test_the_race_runs_in_float32_with_x64_off():
    """In a fresh process (the tests' own runs with x64 on): GymnaxRace with the lane keeper
    and a coasting car (the race core inside), reset and a jitted lax.scan of steps through
    a restart, all float32 and finite, and a planner opponent refused."""
    result = _run("""
        import racing_env, warnings
        import jax, jax.numpy as jnp
        jax.config.update("jax_enable_x64", False)
        warnings.filterwarnings("error", message="Explicitly requested dtype")  # no float64 request truncated
        from racing_env.vector import GymnaxRace
        # off the track at full throttle, and still racing: the race ends at max_steps
        env = GymnaxRace(opponents=["lane-keeping", None], track="trefoil", max_steps=30, on_off_track="penalty")
        params = env.default_params
        obs0, state = env.reset(jax.random.key(2), params)
        def face(state, key):
            obs, state, reward, done, info = env.race_step(key, state, jnp.array([1.0, 0.0]), params)
            return state, (obs, reward, info["finish_time"], done, state.x)
        final, (obs, reward, finish_time, done, x) = jax.jit(
            lambda s: jax.lax.scan(face, s, jax.random.split(jax.random.key(3), 40)))(state)
        assert finish_time.dtype == final.status.finish_time.dtype == jnp.float32  # NaN until finished
        out = [obs0, state.x, obs, reward, x]
        assert all(a.dtype == jnp.float32 for a in out), [a.dtype for a in out]
        assert all(bool(jnp.isfinite(a).all()) for a in out)
        assert int(done.sum()) == 1 and int(final.steps) == 10  # the race of 30 steps restarted
        try:
            GymnaxRace(opponents=["ilqgame-fb:iterations=1"], track="trefoil")
        except RuntimeError as error:
            assert "jax_enable_x64" in str(error), error
        else:
            raise AssertionError("a planner opponent was accepted with x64 off")
        print("ok")
    """)
    assert result.returncode == 0 and result.stdout.strip().endswith("ok"), result.stderr[-3000:]


def _rejax_runs() -> bool:
    """Whether rejax can train here: installed, on a gymnax whose step it unpacks (rejax 0.1.x
    unpacks gymnax 0.0.x's five values; gymnax 1.x returns six)."""
    return importlib.util.find_spec("rejax") is not None and GYMNAX_INSTALLED and not SIX_VALUE_STEP


@pytest.mark.slow
@pytest.mark.skipif(not _rejax_runs(), reason="needs rejax on gymnax 0.0.x (pip install racing-games[jaxrl])")
@pytest.mark.parametrize("x64", ["on", "off"])
def test_rejax_learners_train_on_the_race_unmodified(x64):
    """rejax's PPO, SAC and TD3, with and without observation normalisation: a few thousand
    steps each against the lane keeper, finite metrics and finite evaluation returns.

    With x64 on, rejax 0.1.3's own code mixes float64 into float32 carries on any environment
    (its normalisation statistics start float32 and its observation wrapper casts to Python's
    float; TD3's exploration noise is drawn in float64 while its uniform warm-up actions are
    the space's float32: the same errors on gymnax's Pendulum), so with x64 on PPO and SAC
    run without normalisation; with x64 off everything runs."""
    runs = ["ppo", "ppo:normalize", "sac", "td3:normalize", "td3"] if x64 == "off" else ["ppo", "sac"]
    result = subprocess.run([sys.executable, str(ROOT / "tests" / "rejax_train.py"), x64, *runs],
                            capture_output=True, text=True, timeout=1800, cwd=ROOT,
                            env={**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])})
    assert result.returncode == 0, result.stderr[-3000:]
    reports = [json.loads(line) for line in result.stdout.splitlines() if line.startswith("{")]
    assert [r["algo"] + (":normalize" if r["normalize"] else "") for r in reports] == runs
    for report in reports:
        assert report["x64"] == (x64 == "on") and report["finite"], report
        assert len(report["eval_returns"]) == 3 and np.all(np.isfinite(report["eval_returns"]))
        assert all(length > 0 for length in report["eval_lengths"])


@pytest.mark.slow
@pytest.mark.skipif(not _rejax_runs(), reason="needs rejax on gymnax 0.0.x (pip install racing-games[jaxrl])")
@pytest.mark.parametrize("opponents", [[], ["lane-keeping"]], ids=["time-trial", "lane-keeper"])
def test_rejax_ppo_learns_to_finish_the_default_race(tmp_path, opponents):
    """rejax's PPO at its defaults plus observation normalisation, 2 M steps on the trefoil,
    alone and against the lane keeper, in GymnaxRace's default race (leaving the track ends
    it; python -m experiments.rl.third_party, JAX's default float32, in a process of its
    own): seed 0's trained policy, sampled as rejax samples it, finishes at least 90% of 32
    races (it finished 32 and 30 of 32 in docs/experiments/rl-third-party.md, other seeds
    27-32: it drives at the limit of the track, and a sampled action now and then takes it
    off), and it races rather than crawls: the 1,420 m lap in under 90 s, a mean speed
    above the grid's 15 m/s start speed."""
    out = tmp_path / "third_party.jsonl"
    command = [sys.executable, "-m", "experiments.rl.third_party", "--seeds", "0", "--json", str(out)]
    if opponents:
        command += ["--opponents", *opponents]
    result = subprocess.run(command, capture_output=True, text=True, timeout=1800, cwd=ROOT,
                            env={k: v for k, v in os.environ.items() if k != "JAX_DISABLE_MOST_OPTIMIZATIONS"})
    assert result.returncode == 0, result.stderr[-3000:]
    races = json.loads(out.read_text().splitlines()[0])["races"]
    assert races["finished"] >= 0.9 and races["finish_time_s"] < 90.0, races
