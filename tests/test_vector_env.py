"""Tests of the vectorised race (racing_env.vector): made by gymnasium.make_vec, it races as
Gymnasium's own SyncVectorEnv of the single env does, with its autoreset and seeding; bad
input is refused before any race changes; the gymnax face is pure and jit/vmap-able."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env, data_equivalence
from gymnasium.vector import AutoresetMode

import gymnasium
import racing_env
from racing_env import race
from racing_env.vector import GymnaxRace, RaceVectorEnv

# XLA:CPU evaluates sin and cos with a vectorised kernel across races and elementwise for one:
# the results differ in the last bit, a few ulps per step (tests/test_race_core.py).
BATCH_TOLERANCE = 1e-9
RACE = dict(track="trefoil", max_steps=60)


def _vector(num_envs, **kwargs):
    return gymnasium.make_vec("racing_env/Race-v0", num_envs=num_envs, vectorization_mode="vector_entry_point",
                              **{**RACE, **kwargs})


def _sync(num_envs, **kwargs):
    return gymnasium.make_vec("racing_env/Race-v0", num_envs=num_envs, vectorization_mode="sync",
                              **{**RACE, **kwargs})


def test_make_vec_gives_the_vectorised_env_with_batched_spaces():
    envs = _vector(3)
    assert isinstance(envs.unwrapped, RaceVectorEnv) and envs.num_envs == 3
    assert envs.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    single = gymnasium.make("racing_env/Race-v0", **RACE)
    assert envs.single_observation_space == single.observation_space
    assert envs.single_action_space == single.action_space
    obs, infos = envs.reset(seed=0)
    assert obs.shape == (3,) + single.observation_space.shape and obs.dtype == np.float32
    assert envs.observation_space.contains(obs)
    obs, rewards, terminated, truncated, infos = envs.step(envs.action_space.sample())
    assert envs.observation_space.contains(obs)
    assert rewards.shape == terminated.shape == truncated.shape == (3,)
    assert terminated.dtype == truncated.dtype == np.bool_
    assert all(infos[f"_{key}"].shape == (3,) for key in ("s", "position", "reward_terms"))


def test_the_wrapped_single_env_still_passes_gymnasiums_checker():
    check_env(gymnasium.make("racing_env/Race-v0", **RACE).unwrapped, skip_render_check=True)


# short races that retire cars off the track: many autoresets, at different steps per race
SHORT = dict(max_steps=12, on_off_track="terminate")


@pytest.mark.parametrize("num_envs, mode, race, min_ends, min_contacts", [
    (1, AutoresetMode.NEXT_STEP, RACE, 2, 0),
    (4, AutoresetMode.NEXT_STEP, RACE, 8, 0),
    pytest.param(4, AutoresetMode.NEXT_STEP, dict(track="trefoil", num_agents=3, **SHORT), 32, 0,
                 marks=pytest.mark.slow),  # the default run's budget: the 4-race rows cover the autoresets
    (4, AutoresetMode.SAME_STEP, dict(track="Monza", scenario="anywhere", **SHORT), 32, 5),
])
def test_every_race_is_the_single_envs_race_over_several_episodes(num_envs, mode, race, min_ends, min_contacts):
    """Same seeds and actions: the vectorised env and Gymnasium's SyncVectorEnv of the single
    env agree in every race, across the autoresets (in the same mode in both), starts drawn
    in the compiled step included; the close-quarters scenes collide (at least
    ``min_contacts`` steps of a learner in contact), so the faces agree through contact
    physics and the steward's penalties too."""
    vector = gymnasium.make_vec("racing_env/Race-v0", num_envs=num_envs, vectorization_mode="vector_entry_point",
                                autoreset_mode=mode, **race)
    sync = gymnasium.make_vec("racing_env/Race-v0", num_envs=num_envs, vectorization_mode="sync",
                              vector_kwargs={"autoreset_mode": mode}, **race)
    obs_v, _ = vector.reset(seed=7)
    obs_s, _ = sync.reset(seed=7)
    np.testing.assert_array_equal(obs_v, obs_s)  # the same starts, drawn as the single env draws them
    actions = np.random.default_rng(0).uniform(-1.3, 1.3, (130, num_envs, 2))
    ends = contacts = 0
    for a in actions:
        obs_v, rew_v, term_v, trunc_v, info_v = vector.step(a)
        obs_s, rew_s, term_s, trunc_s, info_s = sync.step(a)
        np.testing.assert_allclose(obs_v, obs_s, rtol=0, atol=BATCH_TOLERANCE)
        np.testing.assert_allclose(rew_v, rew_s, rtol=0, atol=BATCH_TOLERANCE)
        np.testing.assert_array_equal(term_v, term_s)
        np.testing.assert_array_equal(trunc_v, trunc_s)
        done = np.flatnonzero(term_v | trunc_v)
        # same_step: a race that ended reports its last step's infos here, Gymnasium's
        # SyncVectorEnv its new start's; both give the last ones in final_info
        compared = np.arange(num_envs) if mode == AutoresetMode.NEXT_STEP else np.setdiff1d(np.arange(num_envs), done)
        for key in ("position", "lap", "collided", "off_track", "finished", "out"):
            np.testing.assert_array_equal(info_v[key][compared],
                                          np.asarray(info_s[key], dtype=info_v[key].dtype)[compared])
        if mode == AutoresetMode.SAME_STEP and done.size:
            np.testing.assert_allclose(np.stack(info_v["final_obs"][done]), np.stack(info_s["final_obs"][done]),
                                       rtol=0, atol=BATCH_TOLERANCE)
        np.testing.assert_allclose(np.asarray(info_v["penalty"])[compared],
                                   np.asarray(info_s["penalty"], dtype=float)[compared], rtol=0, atol=BATCH_TOLERANCE)
        ends += done.size
        contacts += int(np.sum(info_v["collided"][compared]))
    assert ends >= min_ends  # the races ended and restarted
    assert contacts >= min_contacts


def test_a_race_does_not_depend_on_the_batch_it_is_in():
    """Race b's episodes depend on its seed alone: batches of 2 and 5 seeded 3 race the same
    first two races (to the vectorised kernels' rounding)."""
    small, large = _vector(2), _vector(5)
    obs_small, _ = small.reset(seed=3)
    obs_large, _ = large.reset(seed=3)
    np.testing.assert_array_equal(obs_small, obs_large[:2])
    actions = np.random.default_rng(1).uniform(-1, 1, (70, 5, 2))
    for a in actions:
        out_small, out_large = small.step(a[:2]), large.step(a)
        np.testing.assert_allclose(out_small[0], out_large[0][:2], rtol=0, atol=BATCH_TOLERANCE)
        np.testing.assert_array_equal(out_small[3], out_large[3][:2])


def test_the_same_seed_gives_the_same_races_bit_for_bit():
    runs = []
    for _ in range(2):
        envs = _vector(3)
        obs, _ = envs.reset(seed=11)
        out = [obs]
        for a in np.random.default_rng(2).uniform(-1, 1, (40, 3, 2)):
            out.append(envs.step(a)[:4])
        runs.append(out)
    assert data_equivalence(runs[0], runs[1], exact=True)


def test_same_step_autoreset_returns_the_new_race_and_keeps_the_last_observation():
    next_step, same_step = _vector(2, max_steps=5), _vector(2, max_steps=5, autoreset_mode="same_step")
    assert same_step.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    next_step.reset(seed=4)
    same_step.reset(seed=4)
    coast = np.zeros((2, 2))
    for _ in range(4):
        np.testing.assert_array_equal(next_step.step(coast)[0], same_step.step(coast)[0])
    last, _, _, truncated, _ = next_step.step(coast)
    assert truncated.all()
    restarted = next_step.step(coast)  # the next step's reset
    obs, rewards, terminated, truncated, infos = same_step.step(coast)
    assert truncated.all() and infos["_final_obs"].all()
    np.testing.assert_array_equal(np.stack(infos["final_obs"]), last)
    np.testing.assert_array_equal(obs, restarted[0])  # the second episode's start
    assert np.all(restarted[1] == 0.0) and not restarted[3].any()


@pytest.mark.parametrize(
    "bad, error",
    [
        (np.zeros((3, 2)), ValueError),  # wrong batch
        (np.zeros((2,)), ValueError),  # one action for the batch
        (np.array([[0.0, np.nan], [0.0, 0.0]]), ValueError),
        (np.array([[0.0, 0.0], [np.inf, 0.0]]), ValueError),
        (np.array([["0.5", "0"], ["0", "0"]]), TypeError),
        (np.array([[True, False], [False, False]]), TypeError),
    ],
)
def test_bad_actions_are_refused_and_no_race_changes(bad, error):
    envs = _vector(2)
    envs.reset(seed=0)
    envs.step(np.zeros((2, 2)))
    before = jax.tree_util.tree_map(np.asarray, envs.unwrapped._state)
    with pytest.raises(error):
        envs.step(bad)
    after = jax.tree_util.tree_map(np.asarray, envs.unwrapped._state)
    jax.tree_util.tree_map(np.testing.assert_array_equal, before, after)  # NaN-aware (finish times)


def test_bad_arguments_are_refused_with_a_clear_error():
    with pytest.raises(ValueError, match="num_envs"):
        RaceVectorEnv(num_envs=0)
    with pytest.raises(ValueError, match="autoreset_mode"):
        RaceVectorEnv(num_envs=2, autoreset_mode="disabled")
    with pytest.raises(ValueError, match="opponents"):
        RaceVectorEnv(num_envs=2, opponents=[None, None], num_agents=2)
    with pytest.raises(ValueError, match="seed"):
        RaceVectorEnv(num_envs=2).reset(seed=[1, 2, 3])
    with pytest.raises(RuntimeError, match="reset"):
        RaceVectorEnv(num_envs=2).step(np.zeros((2, 2)))


def test_a_partial_reset_restarts_only_the_masked_races():
    envs = _vector(3)
    envs.reset(seed=5)
    for _ in range(10):
        obs, *_ = envs.step(np.full((3, 2), 0.5))
    first, _ = _vector(3).reset(seed=5)
    again, _ = envs.reset(options={"reset_mask": np.array([False, True, False])})
    np.testing.assert_array_equal(again[[0, 2]], obs[[0, 2]])
    assert not np.array_equal(again[1], obs[1])
    assert not np.array_equal(again[1], first[1])  # race 1's second start, from its own generator


def test_a_plain_callable_opponent_drives_every_race():
    def hold_left(observation, joint_state):
        return np.array([0.3, 0.2])

    envs = _vector(2, opponents=[hold_left])
    single = gymnasium.make("racing_env/Race-v0", opponents=[hold_left], **RACE)
    obs, _ = envs.reset(seed=[9, 9])
    obs_single, _ = single.reset(seed=9)
    for _ in range(20):
        obs, *_ = envs.step(np.zeros((2, 2)))
        obs_single, *_ = single.step(np.zeros(2))
    np.testing.assert_allclose(obs[0], obs_single, rtol=0, atol=BATCH_TOLERANCE)
    np.testing.assert_allclose(obs[1], obs_single, rtol=0, atol=BATCH_TOLERANCE)


# --- the gymnax face ---------------------------------------------------------------------
def test_the_gymnax_face_jits_vmaps_and_resets_a_race_that_ends():
    env = GymnaxRace(track="trefoil", max_steps=8)
    params = env.default_params
    keys = jax.random.split(jax.random.key(0), 16)
    obs, state = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)
    assert obs.shape == (16,) + env.observation_space(params).shape
    step = jax.jit(jax.vmap(env.race_step, in_axes=(0, 0, 0, None)))
    done_seen = np.zeros(16, dtype=bool)
    for k in range(8):
        actions = jnp.full((16, 2), 0.5)
        obs, state, reward, done, info = step(jax.random.split(jax.random.key(k + 1), 16), state, actions, params)
        done_seen |= np.asarray(done)
    assert done_seen.all() and np.asarray(info["truncated"]).all()
    assert np.all(np.asarray(state.steps) == 0)  # every race restarted
    # deterministic for a key
    obs_again, _ = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)
    _, first = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)
    np.testing.assert_array_equal(np.asarray(first.x), np.asarray(jax.vmap(env.reset, in_axes=(0, None))(keys, params)[1].x))
    assert obs_again.shape == obs.shape


def test_the_gymnax_face_draws_every_scenario_as_the_race_core_does():
    env = GymnaxRace(track="trefoil", scenario="anywhere", race_distance=300.0)
    params = env.default_params
    keys = jax.random.split(jax.random.key(5), 4)
    _, state = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)
    drawn = jax.vmap(race.draw_start, in_axes=(0, None))(keys, params)
    np.testing.assert_array_equal(np.asarray(state.x), np.asarray(drawn))
    assert np.ptp(np.asarray(state.x)[:, 0, 0]) > 10.0  # scenes anywhere on the lap, not a grid


def test_the_gymnax_face_refuses_what_it_cannot_run():
    with pytest.raises(ValueError, match="neither a JAX policy .* nor a planner with a compiled step"):
        GymnaxRace(opponents=[lambda observation, joint_state: np.zeros(2)])
    with pytest.raises(ValueError, match="nor a planner with a compiled step"):
        GymnaxRace(opponents=["ilqr:prediction=ilqr"])  # no batched (and so no compiled) form
