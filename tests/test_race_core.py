"""Tests of the functional race core (racing_env.race): the PettingZoo env over it replays
races recorded before the rules moved into the core bit for bit, and the core is pure
(jit, vmap) and agrees with the env step for step."""

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import racing_env
from racing_env import race
from recorded_races import (CONTACT_RACES, CONTACT_RECORDING, CONTACT_STARTS, NEW_INFO_KEYS, NEW_TERMS, RACES,
                            RECORDING, replay)

# replays, bit for bit, races the optimised program recorded: compiled with XLA's full
# optimisations (tests/conftest.py)
pytestmark = pytest.mark.optimized


@pytest.fixture(scope="module")
def recording() -> dict:
    return json.loads(RECORDING.read_text())


@pytest.mark.parametrize("name", sorted(RACES))
def test_the_env_replays_the_recorded_races_bit_for_bit(recording, name):
    """Ghost cars without penalties race as the env did before contact physics and the
    steward: the recording's every value, bit for bit (the infos' and terms' new keys aside)."""
    recorded = recording[name]
    # through JSON, as the recording was written: floats keep every bit (repr round-trips)
    now = json.loads(json.dumps(replay(name)))
    assert len(now) == len(recorded)
    for frame in now:
        for info in frame["infos"].values():
            for key in NEW_INFO_KEYS:
                info.pop(key)
            for term in NEW_TERMS:
                assert info["reward_terms"].pop(term, 0.0) == 0.0
    for k, (a, b) in enumerate(zip(now, recorded)):
        assert a == b, f"race {name!r} differs at step {k}"


# The contact recording was written with XLA:CPU's legacy emitters, as the default test run
# compiles (tests/conftest.py). XLA's newer emitters round the contact's square roots and arc
# tangents differently in the last bit; under them (``make test-all``) the replay is held to
# the same verdicts and to states within BATCH_TOLERANCE, for the reason given there.
RECORDED_WITH = "--xla_cpu_use_fusion_emitters=false"


@pytest.mark.parametrize("name", sorted(CONTACT_RACES))
def test_a_race_with_contact_replays_bit_for_bit(name):
    recorded = json.loads(CONTACT_RECORDING.read_text())[name]
    now = json.loads(json.dumps(replay(name, CONTACT_RACES, CONTACT_STARTS)))
    assert len(now) == len(recorded)
    same_compiler = RECORDED_WITH in os.environ.get("XLA_FLAGS", "")
    for k, (a, b) in enumerate(zip(now, recorded)):
        if same_compiler:
            assert a == b, f"race {name!r} differs at step {k}"
        else:
            if k:
                np.testing.assert_allclose(a["state"], b["state"], rtol=0, atol=BATCH_TOLERANCE)
            assert [[i["verdict"], i["at_fault"]] for info in a["infos"].values() for i in info["incidents"]] == \
                [[i["verdict"], i["at_fault"]] for info in b["infos"].values() for i in info["incidents"]]
    verdicts = [incident for frame in now for info in frame["infos"].values() for incident in info["incidents"]]
    assert verdicts, f"race {name!r} has no incident to replay"


def test_the_recordings_cover_every_rule(recording):
    steps = [frame for frames in recording.values() for frame in frames[1:]]
    infos = [info for frame in steps for info in frame["infos"].values()]
    assert any(info["collided"] for info in infos)
    assert any(info["off_track"] for info in infos)
    assert any(info["out"] for info in infos)
    assert sum(info["finished"] and info["finish_time"] is not None for info in infos) >= 2
    assert any(any(frame["truncations"].values()) for frame in steps)
    assert any(info["reward_terms"]["lead"] != 0.0 for info in infos)


def _env_race(env, seed, actions):
    """The env's race: per step the joint state, rewards and termination flags of all cars."""
    env.reset(seed=seed)
    x0 = env.state()
    out = []
    for a in actions:
        if not env.agents:
            break
        _, rewards, terms, truncs, _ = env.step({agent: a[env.possible_agents.index(agent)] for agent in env.agents})
        out.append((env.state(), rewards, terms, truncs))
    return x0, out


# XLA:CPU evaluates sin and cos (the dynamics' heading terms, the footprints) with a vectorised
# kernel across a batch of races and elementwise for one race; the two round differently in
# the last bit. A batched race therefore follows the env's to a few ulps per step (2e-15 m
# over these 40 steps); 1e-9 leaves room for the dynamics to amplify that over a race while
# any real difference (a wrong rule, a wrong step) is many orders of magnitude larger.
BATCH_TOLERANCE = 1e-9


def test_the_core_under_jit_and_vmap_races_as_the_env():
    env = racing_env.parallel_env(track="trefoil", num_agents=3, max_steps=40)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1.0, 1.0, (2, 40, 3, 2))
    starts, races = zip(*(_env_race(env, seed, actions[b]) for b, seed in enumerate((4, 9))))

    step = jax.jit(jax.vmap(race.step, in_axes=(None, 0, 0, None)))
    state, obs, _ = jax.vmap(race.start, in_axes=(0, None))(jnp.asarray(np.stack(starts)), env.params)
    for k in range(40):
        state, obs, rewards, terms, truncs, info = step(None, state, jnp.asarray(actions[:, k]), env.params)
        for b in range(2):
            x, env_rewards, env_terms, env_truncs = races[b][k]
            np.testing.assert_allclose(np.asarray(state.x[b]), x, rtol=0, atol=BATCH_TOLERANCE)
            for agent, reward in env_rewards.items():
                i = env.possible_agents.index(agent)
                assert float(rewards[b, i]) == pytest.approx(reward, rel=0, abs=BATCH_TOLERANCE)
                assert bool(terms[b, i]) == env_terms[agent] and bool(truncs[b, i]) == env_truncs[agent]
    assert bool(np.all(np.asarray(truncs) | np.asarray(terms)))  # every car done at max_steps


def test_the_core_alone_is_the_env_step_bit_for_bit():
    env = racing_env.parallel_env(track="trefoil", num_agents=3, max_steps=40)
    actions = np.random.default_rng(1).uniform(-1.0, 1.0, (40, 3, 2))
    x0, steps = _env_race(env, 4, actions)
    step = jax.jit(race.step)
    state, _, _ = jax.jit(race.start)(jnp.asarray(x0), env.params)
    for a, (x, rewards, _, _) in zip(actions, steps):
        state, _, reward, *_ = step(None, state, jnp.asarray(a), env.params)
        np.testing.assert_array_equal(np.asarray(state.x), x)
        assert np.asarray(reward).tolist() == [rewards[agent] for agent in env.possible_agents]


def test_reset_draws_the_grid_deterministically_from_the_key():
    env = racing_env.parallel_env(track="trefoil", num_agents=3)
    reset = jax.jit(race.reset)
    (a, obs_a), (b, _), (c, _) = (reset(jax.random.key(k), env.params) for k in (0, 0, 1))
    np.testing.assert_array_equal(np.asarray(a.x), np.asarray(b.x))
    assert not np.array_equal(np.asarray(a.x), np.asarray(c.x))
    assert obs_a.shape == (3, env.observation_space("car_0").shape[0]) and obs_a.dtype == jnp.float32
    # the grid's slots, shuffled and jittered within their bounds
    slots = np.asarray(env.params.starts.slots)
    x = np.asarray(a.x)
    for car in range(3):
        slot = np.argmin(np.abs(slots[:, 0] - x[car, 0]))
        assert abs(x[car, 0] - slots[slot, 0]) <= 1.0 and abs(x[car, 2] - slots[slot, 2]) <= 0.3
    assert np.all(x[:, 1] <= 0.95 * float(env.game.vehicles.car(0).v_max))
