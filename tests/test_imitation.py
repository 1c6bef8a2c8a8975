"""Behaviour cloning (`racing train --imitate`): the demonstrations, the returns and statistics
the fit uses, and a clone of the lane keeper that laps the trefoil as the lane keeper does."""

from __future__ import annotations

import dataclasses
import json

import gymnasium
import numpy as np
import pytest

from experiments.cli import main
from experiments.rl.imitation import (Demonstrations, _split, collect_demonstrations, discounted_returns,
                                      fit_normalizer, running_returns)
from experiments.jsonl import read_jsonl
from experiments.rl.train import TrainConfig, demonstrations_source
from experiments.tournament import race_lineup
from planners.agents import make_agent
from racing_env.single_agent import RaceEnv

from interrupting import ctrl_c_when, start_racing

REWARDS = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
EPISODE = np.array([0, 0, 0, 1, 1])


def test_returns_sum_within_each_episode():
    # gamma 0.5, by hand: episode 0 ahead 1 + 0.5 (2 + 0.5 * 3), 2 + 0.5 * 3, 3; episode 1 ahead 4 + 0.5 * 5, 5
    assert discounted_returns(REWARDS, EPISODE, 0.5) == pytest.approx([2.75, 3.5, 3.0, 6.5, 5.0], abs=1e-12)
    # so far: 1, 0.5 * 1 + 2, 0.5 * 2.5 + 3; 4, 0.5 * 4 + 5
    assert running_returns(REWARDS, EPISODE, 0.5) == pytest.approx([1.0, 2.5, 4.25, 4.0, 7.0], abs=1e-12)


def test_the_normaliser_takes_the_demonstrations_statistics():
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    venv = VecNormalize(DummyVecEnv([lambda: gymnasium.make("Pendulum-v1")]), gamma=0.5)
    observations = np.random.default_rng(0).normal(size=(5, 3)).astype(np.float32)
    demonstrations = Demonstrations(observations=observations, actions=np.zeros((5, 1), np.float32),
                                    rewards=REWARDS, episode=EPISODE, finished=np.array([True, False]))
    fit_normalizer(venv, demonstrations)
    mean, std = observations.astype(float).mean(axis=0), observations.astype(float).std(axis=0)
    assert venv.normalize_obs(observations) == pytest.approx((observations - mean) / np.sqrt(std**2 + venv.epsilon),
                                                              abs=1e-6)  # float32 observations
    # rewards are divided by the spread of the running returns 1, 2.5, 4.25, 4, 7 (gamma 0.5)
    spread = np.sqrt(np.var([1.0, 2.5, 4.25, 4.0, 7.0]) + venv.epsilon)
    assert venv.normalize_reward(REWARDS) == pytest.approx(REWARDS / spread, rel=1e-7)  # returned in float32


def test_the_last_tenth_of_the_episodes_is_held_out():
    for episodes, held in [(1, 0), (2, 1), (10, 1), (11, 2)]:
        episode = np.repeat(np.arange(episodes), 3)
        demonstrations = Demonstrations(np.zeros((len(episode), 1)), np.zeros((len(episode), 2)),
                                        np.zeros(len(episode)), episode, np.zeros(episodes, bool))
        fitted, holdout = _split(demonstrations)
        assert set(episode[holdout]) == set(range(episodes - held, episodes)) and not (fitted & holdout).any()


def test_demonstrations_survive_a_save_under_any_name(tmp_path):
    rng = np.random.default_rng(1)
    demonstrations = Demonstrations(rng.normal(size=(4, 3)).astype(np.float32), rng.normal(size=(4, 2)),
                                    rng.normal(size=4), np.array([0, 0, 1, 1]), np.array([True, False]))
    demonstrations = dataclasses.replace(demonstrations, source='{"imitate": "ilqr"}')
    path = tmp_path / "demonstrations.npz.partial"  # as written before its atomic rename
    demonstrations.save(path)
    loaded = Demonstrations.load(path)
    _assert_same(loaded, demonstrations)
    assert loaded.source == '{"imitate": "ilqr"}' and isinstance(loaded.source, str)


def _assert_same(found: Demonstrations, expected: Demonstrations) -> None:
    for field in dataclasses.fields(Demonstrations):
        assert np.array_equal(getattr(found, field.name), getattr(expected, field.name)), field.name


class _Logged:
    """Wraps an agent (or an env's step) and keeps what went through it."""

    def __init__(self, inner):
        self.inner, self.log = inner, []
        self.name = getattr(inner, "name", "logged")

    def reset(self, *args):
        self.inner.reset(*args)

    def __call__(self, observation, state):
        action = np.asarray(self.inner(observation, state), dtype=np.float32)
        self.log.append(action)
        return action


@pytest.mark.parametrize("noise", [0.0, 0.3])
def test_the_expert_drives_with_noise_and_its_own_actions_are_recorded(noise):
    env = RaceEnv(opponents=[], learner=0, num_agents=1, track="trefoil", race_distance=150.0, max_steps=400)
    stepped = []
    step = env.step
    env.step = lambda action: (stepped.append(np.array(action)), step(action))[1]
    expert = _Logged(make_agent("lane-keeping"))
    demonstrations = collect_demonstrations([env], expert, episodes=2, seed=7, noise=noise, progress=False)

    assert np.array_equal(demonstrations.actions, np.clip(np.array(expert.log), -1, 1))
    assert demonstrations.finished.tolist() == [True, True]  # the lane keeper finishes 150 m, noise or not
    first = [np.flatnonzero(demonstrations.episode == k)[0] for k in (0, 1)]
    for k, start in enumerate(first):  # episode k starts from reset(seed=7 + k)
        assert np.array_equal(demonstrations.observations[start], env.reset(seed=7 + k)[0])
    difference = np.array(stepped) - demonstrations.actions
    if noise == 0.0:
        assert not difference.any()
    else:  # hundreds of draws: their spread within 15% (several standard errors) of the noise asked for
        assert difference.size > 200 and np.std(difference) == pytest.approx(noise, rel=0.15)


def test_a_clone_of_the_lane_keeper_laps_the_trefoil_as_it_does(tmp_path):
    """The lane keeper's driving (3 noisy laps) cloned into a fresh PPO policy: the fit cuts
    the action error on the held-out lap at least five-fold, and the clone laps the
    evaluation grid without leaving the track within 2% of the lane keeper's own time."""
    command = ["train", "--time-trial", "--imitate", "lane-keeping", "--imitate-episodes", "3", "--timesteps", "512",
               "--eval-every", "0", "--eval-grids", "1", "--hyperparameter", "n_steps=256", "--hyperparameter",
               "batch_size=64", "--hyperparameter", "n_epochs=2", "--no-compile-cache", "--out", str(tmp_path)]
    assert main(command) == 0
    report = json.loads((tmp_path / "imitation.json").read_text())
    assert report["expert"] == "lane-keeping" and report["episodes"] == 3 and report["expert_finished"] == 3
    fit = report["fit"]
    assert fit["steps_fitted"] + fit["steps_held_out"] == report["steps"] and fit["steps_held_out"] > 0
    assert fit["after"]["held_out"]["action_rmse"] * 5 <= fit["before"]["held_out"]["action_rmse"]
    assert fit["after"]["held_out"]["value_rmse"] < fit["before"]["held_out"]["value_rmse"]
    assert fit["action_std"] == pytest.approx([0.2, 0.2], rel=1e-6)  # the demonstrations' noise, not fitted

    evaluations = read_jsonl(tmp_path / "evaluations.jsonl")
    assert [e["timesteps"] for e in evaluations] == [0, 512] and evaluations[0] == report["evaluation"]
    config = TrainConfig(opponents=(), eval_grids=1)
    expert, _ = race_lineup(config.race_config(training=False), ["lane-keeping"], seed=1_000_000)
    lap = expert["cars"][0]["finish_time"]
    assert evaluations[0]["finished"] == 1 and evaluations[0]["time_off_track_s"] == 0.0
    assert evaluations[0]["mean_finish_time_s"] == pytest.approx(lap, rel=0.02)
    saved = json.loads((tmp_path / "train.json").read_text())["config"]
    assert (saved["imitate"], saved["imitate_episodes"], saved["imitate_noise"]) == ("lane-keeping", 3, 0.2)

    # the same command again finds the run complete: nothing is collected or cloned again
    before = {name: (tmp_path / name).stat().st_mtime_ns for name in ("demonstrations.npz", "imitation.zip")}
    assert main(command) == 0
    assert {name: (tmp_path / name).stat().st_mtime_ns for name in before} == before


def test_the_clone_explores_with_the_spread_asked_for_or_the_noise():
    assert TrainConfig(imitate="ilqr").clone_spread == 0.2  # the default noise
    assert TrainConfig(imitate="ilqr", imitate_noise=0.5, imitate_spread=0.05).clone_spread == 0.05
    assert TrainConfig(imitate="ilqr", imitate_noise=0.0, imitate_spread=0.1).clone_spread == 0.1
    assert TrainConfig(imitate="ilqr", imitate_noise=0.0).clone_spread is None  # PPO's own


def test_the_clone_spread_is_the_noise_or_the_policys_own():
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    from experiments.rl.imitation import clone

    rng = np.random.default_rng(2)
    demonstrations = Demonstrations(rng.normal(size=(40, 3)).astype(np.float32),
                                    rng.uniform(-1, 1, size=(40, 1)).astype(np.float32), rng.normal(size=40),
                                    np.repeat(np.arange(4), 10), np.zeros(4, bool))
    for spread, expected in [(None, 1.0), (0.3, 0.3)]:  # None: PPO's initial log_std = 0
        model = PPO("MlpPolicy", VecNormalize(DummyVecEnv([lambda: gymnasium.make("Pendulum-v1")])), seed=0,
                    device="cpu")
        report = clone(model, demonstrations, spread=spread, epochs=2)
        assert report["action_std"] == pytest.approx([expected], rel=1e-6)
    with pytest.raises(ValueError, match="spread must be a finite standard deviation > 0, got 0.0"):
        clone(model, demonstrations, spread=0.0)


def test_an_interrupted_collection_goes_on_as_if_it_had_not_stopped():
    """Episodes collected in two goes (the second from the first's saved episodes) equal one
    uninterrupted collection bit for bit, noise included; every episode is handed over to be
    saved as it ends."""
    env = RaceEnv(opponents=[], learner=0, num_agents=1, track="trefoil", race_distance=60.0, max_steps=200)
    expert = make_agent("lane-keeping")
    kwargs = dict(seed=3, noise=0.3, progress=False, source="lane keeper, 60 m")
    whole = collect_demonstrations([env], expert, episodes=3, **kwargs)
    saved = []
    first = collect_demonstrations([env], expert, episodes=1, on_episode=saved.append, **kwargs)
    rest = collect_demonstrations([env], expert, episodes=3, collected=first, on_episode=saved.append, **kwargs)
    assert whole.episodes == 3 and whole.source == "lane keeper, 60 m"
    _assert_same(rest, whole)
    assert [d.episodes for d in saved] == [1, 2, 3]
    _assert_same(saved[-1], whole)
    _assert_same(collect_demonstrations([env], expert, episodes=2, collected=whole, **kwargs), whole.first(2))
    assert whole.first(2).episodes == 2 and set(whole.first(2).episode) == {0, 1}
    with pytest.raises(ValueError, match="come from 'lane keeper, 60 m', not 'ilqr'"):
        collect_demonstrations([env], expert, episodes=3, collected=first, **{**kwargs, "source": "ilqr"})


def test_saved_demonstrations_belong_to_the_settings_that_drive_them():
    base = TrainConfig(opponents=(), imitate="ilqr")
    same = [dict(timesteps=5), dict(imitate_episodes=3), dict(algo="a2c"), dict(eval_grids=4),
            dict(hyperparameters=(("learning_rate", 1e-4),)), dict(subprocesses=True)]
    for change in same:
        assert demonstrations_source(dataclasses.replace(base, **change)) == demonstrations_source(base), change
    other = [dict(imitate="lane-keeping"), dict(imitate_noise=0.5), dict(seed=1), dict(track="oval"),
             dict(start="anywhere"), dict(reward=(("time", -1.0),)), dict(max_steps=10), dict(envs=1)]
    for change in other:
        assert demonstrations_source(dataclasses.replace(base, **change)) != demonstrations_source(base), change


@pytest.mark.slow  # the default run's budget
def test_ctrl_c_while_the_expert_drives_keeps_its_episodes(tmp_path):
    """Ctrl-C on a real `racing train --imitate` while the expert drives: exit 130 with the
    finished episodes saved; the same command then drives only the missing ones, and keeps
    the saved ones as they were. Demonstrations saved in other settings are driven again."""
    def command(out, episodes):
        return ["train", "--time-trial", "--imitate", "lane-keeping", "--imitate-episodes", str(episodes),
                "--race-distance", "60", "--max-steps", "200", "--timesteps", "256", "--eval-every", "0",
                "--eval-grids", "1", "--hyperparameter", "n_steps=128", "--hyperparameter", "batch_size=64",
                "--hyperparameter", "n_epochs=1", "--no-compile-cache", "--out", str(out)]

    out = tmp_path / "run"
    path = out / "demonstrations.npz"
    process = start_racing(command(out, 100_000))
    err = ctrl_c_when(process, path.exists)
    assert process.returncode == 130, err
    assert "interrupted while lane-keeping drove" in err
    assert json.loads((out / "train.json").read_text())["status"] == "interrupted"
    interrupted = Demonstrations.load(path)
    kept = interrupted.episodes
    assert 1 <= kept < 100_000 and set(interrupted.episode) == set(range(kept))

    assert main([*command(out, kept + 1), "--imitate-spread", "0.3"]) == 0  # the spread is not the driving's
    went_on = Demonstrations.load(path)
    assert went_on.episodes == kept + 1 and went_on.source == interrupted.source
    _assert_same(went_on.first(kept), interrupted)
    report = json.loads((out / "imitation.json").read_text())
    assert report["episodes"] == kept + 1 and report["fit"]["action_std"] == pytest.approx([0.3, 0.3], rel=1e-6)

    other = tmp_path / "other"  # a folder holding another run's demonstrations (zero actions, another source)
    other.mkdir()
    foreign = interrupted.first(1)
    dataclasses.replace(foreign, actions=np.zeros_like(foreign.actions), source="another run").save(
        other / "demonstrations.npz")
    assert main(command(other, 1)) == 0
    _assert_same(Demonstrations.load(other / "demonstrations.npz"), foreign)  # driven again, as the first run did
