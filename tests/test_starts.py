"""Tests of the starts drawn with JAX (racing_env.starts): every scenario's draws lie in its
distribution's support on built and real circuits; a seed gives the same episodes in the
PettingZoo env, make_scenario and random_scenes; a step in which every race restarts draws
each race's own start; a million race-steps through tens of thousands of autoresets stay
finite. The vectorised env's agreement with the single env through many autoresets, in both
of Gymnasium's modes: tests/test_vector_env.py."""

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import racing_env
from racing_env import race
from racing_env.dynamics import N_LAT, S, V
from racing_env.physics import footprint_overlap
from racing_env.scenarios import ANYWHERE_MIN_RUN, ANYWHERE_SPEED, make_scenario, random_scenes
from racing_env.starts import MAX_TRIES, key_from_seed
from racing_env.track import get_track
from racing_env.vector import restart_batch
from racing_env.vehicle import VehicleParams

DRAWS = 256


def test_a_seeds_key_is_jaxs_threefry_key_and_bad_seeds_are_refused():
    for seed in (0, 1, 2**31 - 1, 2**32 + 7, 2**63 + 5):
        np.testing.assert_array_equal(key_from_seed(seed), np.asarray(jax.random.PRNGKey(np.uint64(seed))))
    for bad in (-1, 2**64, 1.5, True, "3"):
        with pytest.raises(ValueError, match="seed"):
            key_from_seed(bad)
    env = racing_env.parallel_env(track="trefoil")
    with pytest.raises(ValueError, match="seed"):
        env.reset(seed=-1)


def _draws(env) -> tuple[np.ndarray, np.ndarray]:
    """:data:`DRAWS` starts ``(DRAWS, N, 6)`` of the env's scenario and whether each is free."""
    keys = jax.random.split(jax.random.key(0), DRAWS)
    params = env.params
    draw = jax.jit(jax.vmap(lambda k: race.next_start(k, params)[1:3]))
    x0, free = draw(keys)
    return np.asarray(x0), np.asarray(free)


def _assert_legal(env, x0: np.ndarray, margin: float = 0.0) -> None:
    """On the track (``margin`` inside its edges), behind the finish line, no two cars in contact."""
    track, vehicles = env.track, env.game.vehicles
    s, n = x0[..., S], x0[..., N_LAT]
    assert np.all(n <= np.asarray(track.width_left_at(s)) - margin + 1e-9)
    assert np.all(-n <= np.asarray(track.width_right_at(s)) - margin + 1e-9)
    assert np.all(s < env.finish_s)
    overlap = jax.jit(jax.vmap(lambda x: footprint_overlap(x, vehicles, track)))(jnp.asarray(x0))
    assert not np.asarray(overlap).any()


@pytest.mark.parametrize("track, cars", [("trefoil", 3), ("Monza", 4)])
def test_grid_draws_shuffle_and_jitter_the_slots_within_their_bounds(track, cars):
    env = racing_env.parallel_env(track=track, num_agents=cars)
    x0, free = _draws(env)
    assert free.all()
    _assert_legal(env, x0)
    slots = np.asarray(env.params.starts.slots)
    v_cap = 0.95 * np.asarray(env.game.vehicles.v_max)
    orders = set()
    for start in x0:
        # each car within the jitter of a slot of its own: +-1 m in s, +-0.3 m in n, +-1 m/s
        slot_of = np.argmin(np.abs(slots[None, :, S] - start[:, None, S]), axis=1)
        assert sorted(slot_of.tolist()) == list(range(cars))
        assert np.all(np.abs(start[:, S] - slots[slot_of, S]) <= 1.0)
        assert np.all(np.abs(start[:, N_LAT] - slots[slot_of, N_LAT]) <= 0.3)
        assert np.all(np.abs(start[:, V] - slots[slot_of, V]) <= 1.0) and np.all(start[:, V] <= v_cap)
        orders.add(tuple(slot_of.tolist()))
    if cars == 3:
        assert len(orders) == 6  # every order of three cars over the slots, in 256 draws


@pytest.mark.parametrize("track, cars", [("Monza", 3), ("Budapest", 2)])
def test_anywhere_draws_close_quarters_scenes_inside_the_track_and_short_of_the_finish(track, cars):
    env = racing_env.parallel_env(track=track, num_agents=cars, scenario="anywhere")
    starts = env.params.starts
    x0, free = _draws(env)
    assert free.all()
    _assert_legal(env, x0, margin=float(starts.margin))
    s = x0[..., S]
    lo, hi = np.asarray(starts.s_range)
    assert hi == min(env.track.length, env.finish_s - ANYWHERE_MIN_RUN)
    assert np.all(s.max(axis=1) < hi) and np.all(s.min(axis=1) >= lo - float(starts.spread))
    assert np.all(s.max(axis=1) - s.min(axis=1) <= float(starts.spread))
    v_cap = 0.95 * np.asarray(env.game.vehicles.v_max)
    assert np.all(x0[..., V] >= ANYWHERE_SPEED[0]) and np.all(x0[..., V] <= np.minimum(ANYWHERE_SPEED[1], v_cap))
    # the scenes cover the lap: the reference points spread over most of [lo, hi)
    assert np.ptp(s.max(axis=1)) > 0.8 * (hi - lo)


def test_fixed_starts_are_the_same_whatever_the_key_and_keep_their_speeds():
    for scenario, track in (("paper", "straight"), ("side_by_side", "trefoil")):
        env = racing_env.parallel_env(track=track, scenario=scenario)
        x0, free = _draws(env)
        fixed = make_scenario(scenario, env.track, 2, env.config.vehicles, seed=None).x0
        assert free.all() and np.array_equal(x0, np.broadcast_to(fixed, x0.shape))
    assert x0.shape[0] == DRAWS and make_scenario("paper", env.track, 2, seed=None).x0[0, V] == 20.0  # at v_max


def test_a_crowd_that_cannot_be_placed_apart_is_refused():
    track = get_track("trefoil")
    with pytest.raises(ValueError, match=f"no overlap-free start for 12 cars within spread=0.0 m in {MAX_TRIES}"):
        random_scenes(track, [VehicleParams()] * 12, 1, seed=0, spread=0.0)
    with pytest.raises(ValueError, match="margin=20.0 m leaves no room"):
        random_scenes(track, [VehicleParams()] * 2, 1, margin=20.0)


@pytest.mark.parametrize("scenario", ["grid", "anywhere"])
def test_make_scenario_and_random_scenes_are_the_starts_a_seeded_env_draws(scenario):
    env = racing_env.parallel_env(track="trefoil", num_agents=2, scenario=scenario)
    env.reset(seed=5)
    first = env.state()
    env.reset()
    second = env.state()
    np.testing.assert_array_equal(first, make_scenario(scenario, env.track, 2, seed=5, finish_s=env.finish_s).x0)
    if scenario == "anywhere":
        scenes = random_scenes(env.track, [VehicleParams()] * 2, 2, seed=5, speed=ANYWHERE_SPEED,
                               s_max=env.finish_s - ANYWHERE_MIN_RUN)
        np.testing.assert_array_equal(scenes, np.stack([first, second]))
    assert not np.array_equal(first, second)


# --- the vectorised env's autoresets (their agreement with the single env: tests/test_vector_env.py) ----
def test_a_step_in_which_every_race_restarts_draws_each_races_own_next_start():
    """All 4 races end together: they restart in four batches of one (an eighth of the races,
    rounded up), each from its own key."""
    num = 4
    assert restart_batch(num) == 1
    vector = gymnasium.make_vec("racing_env/Race-v0", num_envs=num, vectorization_mode="vector_entry_point",
                                track="trefoil", max_steps=3)
    vector.reset(seed=40)
    for _ in range(3):
        *_, truncated, _ = vector.step(np.zeros((num, 2)))
    assert truncated.all()
    vector.step(np.zeros((num, 2)))  # next_step: the races restart
    single = racing_env.parallel_env(track="trefoil")
    for b in range(num):
        single.reset(seed=40 + b)
        single.reset()
        np.testing.assert_array_equal(np.asarray(vector.unwrapped._state.x[b]), single.state())


@pytest.mark.slow
def test_a_million_race_steps_through_ten_thousand_autoresets_stay_finite():
    """1,024 races of 30 steps at most, anywhere on Monza, retired off the track: uniform and
    saturated (+-1) actions, about a million race-steps."""
    num = 1024
    envs = gymnasium.make_vec("racing_env/Race-v0", num_envs=num, vectorization_mode="vector_entry_point",
                              track="Monza", scenario="anywhere", max_steps=30, on_off_track="terminate",
                              opponents=["lane-keeping"])
    obs, _ = envs.reset(seed=0)
    rng = np.random.default_rng(0)
    ends = steps = 0
    while steps < 10**6:
        if (steps // num) % 2:
            actions = np.sign(rng.uniform(-1.0, 1.0, (num, 2)))
        else:
            actions = rng.uniform(-1.0, 1.0, (num, 2))
        obs, rewards, terminated, truncated, _ = envs.step(actions)
        assert np.isfinite(obs).all() and np.isfinite(rewards).all()
        ends += int(np.sum(terminated | truncated))
        steps += num
    assert np.isfinite(envs.unwrapped.state()).all()
    assert ends >= 10**4
