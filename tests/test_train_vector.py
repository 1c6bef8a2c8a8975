"""`racing train` on the vectorised races (experiments.rl.vec_env.RaceVecEnv): SB3's VecEnv
contract, the same races as a DummyVecEnv of Gymnasium copies, PPO's defaults for many
copies, and training that resumes after Ctrl-C exactly as if it had not stopped."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from experiments.jsonl import read_jsonl
from experiments.rl import train as train_rl
from experiments.rl.train import TrainConfig, default_hyperparameters, model_settings, run_training
from experiments.rl.vec_env import INFO_KEYWORDS, RaceVecEnv
from interrupting import ctrl_c_when, start_racing
from planners.agents import make_agent

# A short race; 8 copies x 64 steps = one PPO update per 512 steps.
TINY = dict(opponents=("lane-keeping",), timesteps=1024, race_distance=150.0, max_steps=200, envs=8,
            checkpoint_every=512, eval_every=0, eval_grids=1,
            hyperparameters=(("n_steps", 64), ("batch_size", 128), ("n_epochs", 2)))
TINY_ARGS = ["train", "--race-distance", "150", "--max-steps", "200", "--eval-grids", "1", "--envs", "8",
             "--hyperparameter", "n_steps=64", "--hyperparameter", "batch_size=128",
             "--hyperparameter", "n_epochs=2", "--no-compile-cache", "--eval-every", "0",
             "--checkpoint-every", "512"]


def _policy_parameters(path):
    return make_agent(f"rl:ppo:{path}").model.policy.state_dict()


def _same_parameters(a, b) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def _float32_ulps(a, b) -> None:
    """The float32 roundings of float64 values that agree to a few float64 ulps (the
    vectorised sin and cos, docs/env.md) are equal or one float32 ulp apart."""
    np.testing.assert_array_max_ulp(np.asarray(a, np.float32), np.asarray(b, np.float32), maxulp=1)


# mixed starts with the slow tests (the default run's budget)
@pytest.mark.parametrize("race", [dict(envs=4), pytest.param(dict(start="mixed", envs=4), marks=pytest.mark.slow),
                                  dict(opponents=(), envs=2)],
                         ids=["duel", "duel-mixed-starts", "time-trial"])
def test_the_races_are_those_of_a_dummy_vec_env_of_single_env_copies(race):
    """Copy k of both runs the same episodes, seeded as SB3 seeds a VecEnv (seed + k):
    the learner as car k mod N (car 1 in the odd copies of a duel, which start anywhere with
    start="mixed"), the same observations, rewards, dones, terminal observations, truncation
    flags and Monitor episode records, through many autoresets."""
    config = TrainConfig(**{**TINY, "max_steps": 25, **race})
    vector, single = (train_rl.make_training_env(dataclasses.replace(config, vector=v)) for v in (True, False))
    try:
        groups = {(k % config.cars, config.scenario(k)) for k in range(config.envs)}
        assert isinstance(vector, RaceVecEnv) and len(vector.groups) == len(groups)
        assert vector.get_attr("learner") == [k % config.cars for k in range(config.envs)]
        assert single.get_attr("learner") == [f"car_{k % config.cars}" for k in range(config.envs)]
        assert vector.seed(7) == single.seed(7) == [7 + k for k in range(config.envs)]
        _float32_ulps(vector.reset(), single.reset())
        rng = np.random.default_rng(0)
        ended = {"terminated": 0, "truncated": 0}
        for _ in range(150):
            actions = rng.uniform(-1.0, 1.0, (config.envs, 2)).astype(np.float32)
            obs, rewards, dones, infos = vector.step(actions)
            obs_1, rewards_1, dones_1, infos_1 = single.step(actions)
            assert obs.dtype == obs_1.dtype == np.float32 and rewards.dtype == rewards_1.dtype == np.float32
            _float32_ulps(obs, obs_1)
            _float32_ulps(rewards, rewards_1)
            np.testing.assert_array_equal(dones, dones_1)
            for k, (info, info_1) in enumerate(zip(infos, infos_1)):
                for key in ("lap", "position", "collided", "off_track", "finished", "out", "TimeLimit.truncated"):
                    assert info[key] == info_1[key], (k, key)
                # float64 values of the vectorised core: equal to a few ulps
                assert info["s"] == pytest.approx(info_1["s"], rel=1e-12, abs=1e-12)
                assert info["reward_terms"] == pytest.approx(info_1["reward_terms"], rel=1e-9, abs=1e-12)
                assert (info["finish_time"] is None) == (info_1["finish_time"] is None)
                assert ("episode" in info) == ("episode" in info_1) == bool(dones[k])
                if not dones[k]:
                    continue
                ended["truncated" if info["TimeLimit.truncated"] else "terminated"] += 1
                _float32_ulps(info["terminal_observation"], info_1["terminal_observation"])
                assert not np.array_equal(info["terminal_observation"], obs[k])  # the next episode's start is apart
                episode, episode_1 = info["episode"], info_1["episode"]
                assert set(episode) == set(episode_1) == {"r", "l", "t", *INFO_KEYWORDS}
                assert episode["l"] == episode_1["l"]
                # Monitor rounds the float64 return to 6 decimals: returns a few ulps apart round alike or 1e-6 apart
                assert abs(episode["r"] - episode_1["r"]) <= 1e-6 + 1e-9
                for key in ("finished", "position", "out"):
                    assert episode[key] == episode_1[key]
        assert ended["terminated"] > 0 and ended["truncated"] > 0, ended
    finally:
        vector.close()
        single.close()


@pytest.fixture
def training_threads():
    """torch on the threads training uses (train_rl.TORCH_THREADS), as run_training sets them."""
    threads = torch.get_num_threads()
    torch.set_num_threads(train_rl.TORCH_THREADS)
    yield
    torch.set_num_threads(threads)


def test_the_vec_env_passes_sb3s_checks_under_its_wrappers(training_threads):
    """SB3's space checks and its NaN, Monitor and normalising wrappers over the VecEnv;
    PPO and SAC take it; the attribute and method calls reach the races' groups."""
    from stable_baselines3 import PPO, SAC
    from stable_baselines3.common.env_checker import _check_obs
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.utils import check_for_correct_spaces
    from stable_baselines3.common.vec_env import VecCheckNan, VecMonitor, VecNormalize

    config = TrainConfig(**{**TINY, "envs": 4, "max_steps": 40})
    env = train_rl.make_training_env(config)
    assert env.env_is_wrapped(Monitor) == [True] * 4  # it writes Monitor's episode records itself
    with pytest.warns(UserWarning, match="already wrapped with a `Monitor`"):
        monitored = VecMonitor(env)
    wrapped = VecCheckNan(VecNormalize(monitored), raise_exception=True)
    check_for_correct_spaces(wrapped, env.observation_space, env.action_space)
    obs = env.reset()
    for k in range(env.num_envs):
        _check_obs(obs[k], env.observation_space, "reset")
    wrapped.seed(3)
    wrapped.reset()
    lengths = []
    for _ in range(100):
        actions = np.stack([env.action_space.sample() for _ in range(env.num_envs)])
        _, rewards, dones, infos = wrapped.step(actions)
        assert rewards.shape == (4,) and dones.dtype == bool
        for k in np.flatnonzero(dones):  # VecMonitor's episode record, in place of this env's own
            assert infos[k]["episode"]["l"] >= 1
            lengths.append(infos[k]["episode"]["l"])
            _check_obs(infos[k]["terminal_observation"], env.observation_space, "step")
    assert lengths

    assert env.get_attr("render_mode") == [None] * 4 and env.render_mode is None
    assert env.get_attr("learner", indices=[1, 3]) == [1, 1]
    assert env.get_attr("num_envs") == [2] * 4  # two groups (learner car 0, car 1) of two races
    # once per group, handed to each race asked, in the order asked
    assert env.env_method("__getattribute__", "learner", indices=[0, 1, 2, 3]) == [0, 1, 0, 1]
    assert env.has_attr("config") and not env.has_attr("no_such_attribute")
    env.set_attr("marker", "x", indices=[0, 2])  # the races of group car 0
    assert env.get_attr("marker", indices=[0, 2]) == ["x", "x"]
    with pytest.raises(ValueError, match="share one env"):
        env.set_attr("marker", "y", indices=[1])
    for algo in (PPO, SAC):
        model = algo("MlpPolicy", VecNormalize(train_rl.make_training_env(config)), seed=0, device="cpu",
                     policy_kwargs={"net_arch": [32, 32]},
                     **({"n_steps": 16, "batch_size": 32} if algo is PPO else {"learning_starts": 64}))
        model.learn(128)
        assert model.num_timesteps >= 128
        model.get_env().close()
    wrapped.close()


def test_reset_takes_a_seed_for_every_race_or_none():
    env = train_rl.make_training_env(TrainConfig(**{**TINY, "envs": 2}))
    try:
        env._seeds = [1, None]
        with pytest.raises(ValueError, match="seed every race or none"):
            env.reset()
        env.seed(1)
        env.set_options({"x0": np.zeros((2, 6))})
        with pytest.raises(ValueError, match="no reset options"):
            env.reset()
        env.set_options(None)
        with pytest.raises(RuntimeError, match="reset"):
            env.step(np.zeros((2, 2), np.float32))
        assert env.reset().shape == (2, env.observation_space.shape[0])
    finally:
        env.close()


# slow (the default run's budget): tests/test_batched_opponents.py draws pools' drivers by default
@pytest.mark.slow
def test_a_pool_names_each_episodes_driver():
    """With a pool every race draws each opponent car's driver per episode; every step's info
    names the episode's driver, its last step included (when the next one is drawn)."""
    pool = ("lane-keeping", "constant-speed:target_speed=10")
    config = TrainConfig(**{**TINY, "opponents": pool, "pool": True, "envs": 8, "max_steps": 30})
    env = train_rl.make_training_env(config)
    try:
        env.seed(0)
        env.reset()
        current = [info["opponents"] for info in env.reset_infos]
        drivers = []
        for _ in range(120):
            _, _, dones, infos = env.step(np.zeros((8, 2), np.float32))
            assert [info["opponents"] for info in infos] == current  # this episode's, ended or not
            assert all(len(names) == 1 and names[0] in pool for names in current)
            drivers += [current[k][0] for k in np.flatnonzero(dones)]
            for k in np.flatnonzero(dones):  # the next episode's driver, as the next step names it
                (group,) = [g for g in env.groups if k in g.races]
                row = int(np.flatnonzero(group.races == k)[0])
                current[k] = [pool[int(drawn[row])] for drawn in group.drivers().values()]
        assert set(drivers) == set(pool)
    finally:
        env.close()


def test_a_saved_state_goes_on_as_the_races_it_was_taken_from():
    """get_state in one env, set_state in a new one: both then run the same races bit for bit,
    the drivers a pool drew and the episodes' returns so far included."""
    pool = ("lane-keeping", "constant-speed:target_speed=10")
    config = TrainConfig(**{**TINY, "opponents": pool, "pool": True, "envs": 6, "start": "mixed", "max_steps": 30})
    first, second = train_rl.make_training_env(config), train_rl.make_training_env(config)
    try:
        assert first.exact_state
        rng = np.random.default_rng(1)
        first.seed(4)
        first.reset()
        for _ in range(37):
            first.step(rng.uniform(-1.0, 1.0, (6, 2)).astype(np.float32))
        second.seed(99)  # dropped: set_state puts the races where they were
        second.set_state(first.get_state())
        for _ in range(60):
            actions = rng.uniform(-1.0, 1.0, (6, 2)).astype(np.float32)
            obs, rewards, dones, infos = first.step(actions)
            obs_2, rewards_2, dones_2, infos_2 = second.step(actions)
            np.testing.assert_array_equal(obs, obs_2)
            np.testing.assert_array_equal(rewards, rewards_2)
            np.testing.assert_array_equal(dones, dones_2)
            for info, info_2 in zip(infos, infos_2):
                assert info.get("episode", {}).keys() == info_2.get("episode", {}).keys()
                assert info["opponents"] == info_2["opponents"]
                if "episode" in info:
                    assert info["episode"]["r"] == info_2["episode"]["r"]
                    assert info["episode"]["l"] == info_2["episode"]["l"]
        with pytest.raises(ValueError, match="cannot be put into"):
            train_rl.make_training_env(dataclasses.replace(config, envs=2)).set_state(first.get_state())
    finally:
        first.close()
        second.close()


@pytest.mark.parametrize("envs", [1, 2, 3, 16, 64, 100, 256, 1024])
def test_ppo_defaults_keep_a_rollout_of_about_4096_steps_in_8_minibatches(envs):
    settings = default_hyperparameters("ppo", envs)
    n_steps, batch = settings["n_steps"], settings["batch_size"]
    assert n_steps % 8 == 0 and train_rl.PPO_MIN_STEPS <= n_steps <= 2048
    rollout = n_steps * envs
    assert rollout % batch == 0 and rollout // batch == 8
    if 1 < envs <= 4096 // train_rl.PPO_MIN_STEPS:  # n_steps is neither at its floor nor at SB3's 2048
        assert 4096 - 8 * envs < rollout <= 4096
    assert default_hyperparameters("sac", envs) == {}


def test_the_users_hyperparameters_win_over_the_defaults(tmp_path):
    config = TrainConfig(**{**TINY, "envs": 64, "hyperparameters": (("batch_size", 256),)})
    assert model_settings(config) == {"n_steps": 64, "batch_size": 256}
    model = train_rl._build_model(config, tmp_path, None)
    assert (model.n_steps, model.batch_size, model.n_envs) == (64, 256, 64)
    model.get_env().close()


def test_training_on_the_vectorised_races_logs_checkpoints_and_resume_states(tmp_path):
    report = run_training(TrainConfig(**TINY), tmp_path, progress=False)
    assert report["status"] == "completed" and report["timesteps"] == 1024
    assert report["model_settings"] == {"n_steps": 64, "batch_size": 128, "n_epochs": 2}
    learn = report["learn"]
    assert learn["steps"] == 1024 and learn["rollout_s"] > 0 and learn["update_s"] > 0
    checkpoints = tmp_path / "checkpoints"
    assert sorted(p.name for p in checkpoints.glob("step_*.zip")) == ["step_000000512.zip", "step_000001024.zip"]
    assert [p.name for p in checkpoints.glob("*.resume.pkl")] == ["step_000001024.resume.pkl"]  # the latest only
    episodes = read_jsonl(tmp_path / "episodes.jsonl")
    assert episodes and {e["env"] for e in episodes} <= set(range(8))
    assert all(e["car"] == e["env"] % 2 for e in episodes)
    for copy in range(8):
        assert sum(e["length"] for e in episodes if e["env"] == copy) <= 1024 // 8
    assert all(e["out"] or e["finished"] or e["truncated"] for e in episodes)


def test_subprocesses_race_single_env_copies_whatever_vector_says():
    config = TrainConfig(**{**TINY, "subprocesses": True})
    assert config.vector and not config.vectorised
    assert TrainConfig(**TINY).vectorised and not TrainConfig(**{**TINY, "vector": False}).vectorised
    with pytest.raises(ValueError, match="vector must be True or False"):
        TrainConfig(**{**TINY, "vector": "yes"})


def _racing_train(args: list[str]) -> None:
    """``racing train ARGS`` in a process of its own, to the end."""
    process = start_racing(["train", *args])
    _, err = process.communicate(timeout=600)
    assert process.returncode == 0, err


@pytest.mark.slow  # three real trainings; test_train.py interrupts real processes by default
def test_a_run_interrupted_by_ctrl_c_resumes_exactly_as_if_it_had_not_stopped(tmp_path):
    """Ctrl-C (SIGINT to the process group) on a real `racing train` after its first
    checkpoint, wherever it lands (a rollout, an update, a save): the run rewinds to its last
    update, and the same command with more --timesteps ends with the very model, episodes
    and evaluation of a run that was never interrupted. (Every run is a `racing train`
    process: each splits the races over the machine's cores, as any run there does.)"""
    out, reference = tmp_path / "run", tmp_path / "reference"
    process = start_racing([*TINY_ARGS, "--out", str(out), "--timesteps", "200000"])
    err = ctrl_c_when(process, (out / "checkpoints" / "step_000000512.zip").exists)
    assert process.returncode == 130, err
    stopped = json.loads((out / "train.json").read_text())["timesteps"]
    assert stopped >= 512 and stopped % 512 == 0  # an update's step count
    assert (out / "checkpoints" / f"step_{stopped:09d}.resume.pkl").exists()

    target = stopped + 1024
    _racing_train([*TINY_ARGS[1:], "--out", str(out), "--timesteps", str(target)])
    _racing_train([*TINY_ARGS[1:], "--out", str(reference), "--timesteps", str(target)])
    assert json.loads((out / "train.json").read_text())["timesteps"] == target
    assert _same_parameters(_policy_parameters(out / "model.zip"), _policy_parameters(reference / "model.zip"))
    for name in ("episodes.jsonl", "evaluations.jsonl"):
        assert (out / name).read_text() == (reference / name).read_text(), name
    stats = [make_agent(f"rl:{folder / 'model.zip'}").normalizer for folder in (out, reference)]
    np.testing.assert_array_equal(stats[0].obs_rms.mean, stats[1].obs_rms.mean)
    np.testing.assert_array_equal(stats[0].obs_rms.var, stats[1].obs_rms.var)
