"""`racing train`: real stable-baselines3 training against the racing agents, its outputs,
determinism, resumption after Ctrl-C, and refused settings."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from experiments.rl import evaluation
from experiments.rl import train as train_rl
from experiments.cli import main
from experiments.jsonl import read_jsonl
from experiments.tournament import race_lineup
from experiments.rl.train import TrainConfig, run_training
from racing_env.config import RewardConfig
from interrupting import ctrl_c_when, start_racing
from planners.agents import SB3Agent, make_agent, vecnormalize_path

# A short race and small PPO rollouts: 2 copies x 256 steps = one update per 512 steps. The
# copies are single Gymnasium envs in a DummyVecEnv (vector=False), which these tests reach
# into (venv.envs) and compare with worker processes; the vectorised races (the default):
# tests/test_train_vector.py.
TINY = dict(opponents=("lane-keeping",), timesteps=1024, race_distance=150.0, max_steps=200, envs=2,
            vector=False, checkpoint_every=512, eval_every=512, eval_grids=1,
            hyperparameters=(("n_steps", 256), ("batch_size", 64), ("n_epochs", 2)))
TINY_ARGS = ["train", "--race-distance", "150", "--max-steps", "200", "--eval-grids", "1",
             "--hyperparameter", "n_steps=256", "--hyperparameter", "batch_size=64",
             "--hyperparameter", "n_epochs=2", "--no-compile-cache", "--no-vector"]


def _policy_parameters(path):
    return make_agent(f"rl:ppo:{path}").model.policy.state_dict()


def test_training_writes_checkpoints_logs_and_a_model_that_races(tmp_path):
    report = run_training(TrainConfig(**TINY), tmp_path, progress=False)
    assert report["status"] == "completed" and report["timesteps"] == 1024
    assert json.loads((tmp_path / "train.json").read_text()) == json.loads(json.dumps(report))
    steps = [p.name for p in sorted((tmp_path / "checkpoints").glob("step_*.zip"))]
    assert steps == ["step_000000512.zip", "step_000001024.zip"]
    assert all(vecnormalize_path(tmp_path / "checkpoints" / name).exists() for name in steps)

    episodes = read_jsonl(tmp_path / "episodes.jsonl")
    assert episodes, "no training episode ended in 1,024 steps"
    for copy in (0, 1):  # each copy's episodes: in order, as its own car, no more steps than it took
        mine = [e for e in episodes if e["env"] == copy]
        assert all(e["car"] == copy for e in mine)
        assert [e["timesteps"] for e in mine] == sorted(e["timesteps"] for e in mine)
        assert sum(e["length"] for e in mine) <= 1024 // 2
    assert all(e["out"] or e["finished"] or e["truncated"] for e in episodes)

    evaluations = read_jsonl(tmp_path / "evaluations.jsonl")
    assert [e["timesteps"] for e in evaluations] == [512, 1024]
    assert all(e["races"] == 2 and e["errors"] == [] for e in evaluations)
    assert report["final_evaluation"] == evaluations[-1]
    # an evaluation is a function of the saved policy: re-running it gives the same record
    assert train_rl.evaluate(TrainConfig(**TINY), tmp_path / "checkpoints" / steps[-1], 1024) == evaluations[-1]
    assert (tmp_path / "learning_curve.png").stat().st_size > 0

    # the final model is the last checkpoint, and as an agent it applies the saved
    # VecNormalize statistics exactly as SB3's own VecNormalize.load does on the training env
    final = _policy_parameters(tmp_path / "model.zip")
    last = _policy_parameters(tmp_path / "checkpoints" / steps[-1])
    assert all(torch.equal(final[k], last[k]) for k in final)
    from stable_baselines3.common.vec_env import VecNormalize

    agent = make_agent(f"rl:{tmp_path / 'model.zip'}")
    assert isinstance(agent, SB3Agent) and agent.normalizer is not None
    assert agent.observation_units == "scaled"  # recorded in the model: a physical race is converted
    reference = VecNormalize.load(str(vecnormalize_path(tmp_path / "model.zip")),
                                  train_rl.make_training_env(TrainConfig(**TINY)))
    reference.training = False
    env = reference.venv.envs[0]
    obs, _ = env.reset(seed=3)
    agent.reset(3, 0, env.unwrapped)
    for _ in range(20):
        expected, _ = agent.model.predict(reference.normalize_obs(obs), deterministic=True)
        action = agent.act(obs, env.unwrapped.race.state())
        np.testing.assert_array_equal(action, np.clip(expected, -1, 1).astype(np.float32))
        obs, *_ = env.step(action)
    assert not any(h["fallback"] for h in agent.history)


# slow (the default run's budget): the interrupted training's resume is checked bit for bit by default
@pytest.mark.slow
def test_training_is_deterministic_in_one_process_or_several(tmp_path):
    config = TrainConfig(**{**TINY, "timesteps": 512, "eval_every": 0})
    run_training(config, tmp_path / "a", progress=False)
    run_training(dataclasses.replace(config, subprocesses=True), tmp_path / "b", progress=False)
    assert (tmp_path / "a" / "episodes.jsonl").read_text() == (tmp_path / "b" / "episodes.jsonl").read_text()
    assert (tmp_path / "a" / "evaluations.jsonl").read_text() == (tmp_path / "b" / "evaluations.jsonl").read_text()
    a, b = _policy_parameters(tmp_path / "a" / "model.zip"), _policy_parameters(tmp_path / "b" / "model.zip")
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_a_checkpoint_cut_short_while_saving_is_not_resumed_from(tmp_path):
    """A kill while a checkpoint's statistics are written leaves no .zip of it: the run
    resumes from the checkpoint before, whose statistics are whole."""
    config = TrainConfig(**{**TINY, "hyperparameters": (("n_steps", 64), ("batch_size", 32))})
    model = train_rl._build_model(config, tmp_path, None)
    first = train_rl.checkpoint(model, tmp_path)
    model.num_timesteps = 512

    def killed(path):
        raise KeyboardInterrupt

    model.get_env().save = killed  # the VecNormalize statistics are written before the model
    with pytest.raises(KeyboardInterrupt):
        train_rl.checkpoint(model, tmp_path)
    assert train_rl.latest_checkpoint(tmp_path) == (0, first)
    assert vecnormalize_path(first).exists()


# in worker processes with the slow tests (test_sweep's Ctrl-C test stops worker processes)
@pytest.mark.parametrize("subprocesses", [False, pytest.param(True, marks=pytest.mark.slow)],
                         ids=["one-process", "worker-processes"])
def test_interrupted_training_process_resumes(tmp_path, subprocesses):
    """Ctrl-C (SIGINT to the process group, as a terminal sends it) on a real `racing train`
    after its first checkpoint: it saves a checkpoint where it stopped, exits with 130 and
    leaves no process behind; the same command with a larger --timesteps resumes from
    there; other settings are refused."""
    out = tmp_path / "run"
    args = [*TINY_ARGS, "--eval-every", "0", "--checkpoint-every", "512", "--out", str(out)]
    extra = ["--subprocesses"] if subprocesses else []
    process = start_racing([*args, *extra, "--timesteps", "200000"])
    err = ctrl_c_when(process, (out / "checkpoints" / "step_000000512.zip").exists)
    assert process.returncode == 130, err
    report = json.loads((out / "train.json").read_text())
    assert report["status"] == "interrupted"
    stopped = report["timesteps"]
    assert stopped >= 512
    assert train_rl.latest_checkpoint(out)[0] == stopped
    assert all(e["timesteps"] <= stopped for e in read_jsonl(out / "episodes.jsonl"))

    assert main([*args, "--seed", "1"]) == 2  # another seed is another run
    target = stopped + 512
    assert main([*args, "--timesteps", str(target)]) == 0
    report = json.loads((out / "train.json").read_text())
    assert report["status"] == "completed" and report["timesteps"] >= target
    assert train_rl.latest_checkpoint(out)[0] == report["timesteps"]
    # run again: nothing left to train, nothing re-run
    before = (out / "episodes.jsonl").read_text()
    assert main([*args, "--timesteps", str(target)]) == 0
    assert (out / "episodes.jsonl").read_text() == before


@pytest.mark.parametrize("bad, message", [
    (dict(opponents=(), pool=True), "a pool needs at least one opponent"),
    (dict(algo="dqn"), "algo"),
    (dict(timesteps=0), "timesteps"),
    (dict(envs=0), "envs"),
    (dict(eval_every=-1), "eval_every"),
    (dict(on_off_track="bounce"), "on_off_track"),
    (dict(eval_off_track="bounce"), "eval_off_track"),
    (dict(jerk_weight=0.0), "jerk_weight"),
    (dict(laps=0), "laps"),
    (dict(hyperparameters=(("nsteps", 64),)), "no hyperparameter 'nsteps'"),
    (dict(pool=True, pool_cars=1), "pool_cars"),
    (dict(seed=-1), r"seed \(--seed\) must be an integer >= 0"),
    (dict(start="pitlane"), r"start must be one of \('grid', 'anywhere', 'mixed'\), got 'pitlane'"),
    (dict(imitate="ilqr", algo="sac"), r"algo must be one of \('ppo', 'a2c'\), got 'sac'"),
    (dict(imitate="ilqr", init_model="tests/conftest.py"), "give one of them"),
    (dict(imitate="ilqr", imitate_noise=-0.1), "imitate_noise must be a finite standard deviation >= 0"),
    (dict(imitate="ilqr", imitate_episodes=0), "imitate_episodes must be an integer >= 1"),
    (dict(imitate="ilqr", imitate_spread=0.0), r"imitate_spread must be a finite standard deviation > 0"),
])
def test_bad_settings_are_refused(bad, message):
    with pytest.raises(ValueError, match=message):
        TrainConfig(**{**TINY, **bad})


def test_bad_command_lines_fail_before_training(tmp_path, capsys):
    cases = [
        (["--opponents", "wizard"], "unknown agent spec 'wizard'"),
        (["--opponents", f"rl:{tmp_path / 'missing.zip'}"], f"no model file at {tmp_path / 'missing.zip'} "),
        (["--hyperparameter", "n_steps"], "NAME=VALUE"),
        (["--hyperparameter", "n_steps=-4"], "ppo refused the model settings (hyperparameters {'n_steps': -4, "),
        (["--seed", "-1"], "seed (--seed) must be an integer >= 0, got -1"),
        (["--track", str(tmp_path / "nowhere.csv")], "nowhere.csv"),
        (["--time-trial", "--opponents", "ilqr"], "--time-trial races the learner alone: give no --opponents"),
        (["--reward", "pace=-1"], "unknown reward term 'pace'"),
        (["--imitate", "wizard"], "unknown agent spec 'wizard'"),
    ]
    for extra, message in cases:
        out = tmp_path / "out"
        assert main([*TINY_ARGS, "--timesteps", "512", "--out", str(out), *extra]) == 2, extra
        assert message in capsys.readouterr().err, extra
        assert not (out / "checkpoints").exists()


def test_a_refused_model_without_hyperparameters_does_not_blame_them(tmp_path, monkeypatch):
    """An error building the model names the hyperparameters only if some were given, and keeps its own message."""
    import stable_baselines3

    def refuse(*args, **kwargs):
        raise ValueError("the env's observations are not a Box")

    plain, tuned = TrainConfig(**{**TINY, "hyperparameters": ()}), TrainConfig(**TINY)
    monkeypatch.setattr(stable_baselines3, "PPO", refuse)
    with pytest.raises(ValueError) as info:
        train_rl._build_model(plain, tmp_path, None)
    assert str(info.value) == "ppo refused the model settings: ValueError: the env's observations are not a Box"
    with pytest.raises(ValueError, match=r"model settings \(hyperparameters \{'n_steps': 256.*not a Box"):
        train_rl._build_model(tuned, tmp_path, None)


def test_training_against_a_pool_draws_both_drivers_and_evaluates_each(tmp_path):
    """With --pool every episode's opponent is drawn from the specs; the episodes log who
    it was, and each evaluation races every driver of the pool and reports them apart."""
    pool = ("lane-keeping", "constant-speed:target_speed=10")
    code = main([*TINY_ARGS, "--timesteps", "1024", "--opponents", *pool, "--pool", "--out", str(tmp_path)])
    assert code == 0
    episodes = read_jsonl(tmp_path / "episodes.jsonl")
    assert {e["opponents"][0] for e in episodes} == set(pool)
    assert all(len(e["opponents"]) == 1 for e in episodes)  # two cars: one opponent
    final = read_jsonl(tmp_path / "evaluations.jsonl")[-1]
    assert final["races"] == 4 and set(final["by_opponent"]) == set(pool)
    for part in final["by_opponent"].values():
        assert part["races"] == 2  # one grid, both slots
    assert final["wins"] == sum(part["wins"] for part in final["by_opponent"].values())
    config = json.loads((tmp_path / "train.json").read_text())["config"]
    assert config["pool"] is True and config["pool_cars"] == 2


def test_a_time_trial_trains_the_learner_alone_and_reports_its_finish_time(tmp_path):
    """--time-trial: one car per race, in training (every copy's learner is car 0) and in the
    evaluations, which report the mean finish time of the races it finished and no margin."""
    code = main([*TINY_ARGS, "--timesteps", "1024", "--time-trial", "--reward", "time=-1", "--out", str(tmp_path)])
    assert code == 0
    report = json.loads((tmp_path / "train.json").read_text())
    assert report["config"]["opponents"] == [] and report["config"]["reward"] == {"time": -1.0}
    episodes = read_jsonl(tmp_path / "episodes.jsonl")
    assert episodes and all(e["car"] == 0 and e["place"] == 1 for e in episodes)
    config = TrainConfig(**{**TINY, "opponents": (), "reward": (("time", -1.0),)})
    assert config.cars == 1 and config.time_trial and config.description() == "time trial"
    for record in read_jsonl(tmp_path / "evaluations.jsonl"):
        assert record["races"] == 1 and record["races_by_start_place"] == [1] and record["mean_margin_s"] is None
    race, _ = race_lineup(config.race_config(training=False), [f"rl:ppo:{tmp_path / 'model.zip'}"], seed=1_000_000)
    assert race["gap"] is None and race["cars"][0]["place"] == 1
    # the final evaluation is the final model's lap on the evaluation grid
    assert report["final_evaluation"]["finished"] == (race["cars"][0]["finish_time"] is not None)
    assert report["final_evaluation"]["mean_finish_time_s"] == race["cars"][0]["finish_time"]
    assert report["final_evaluation"]["wins"] == report["final_evaluation"]["finished"]


def test_training_starts_anywhere_and_evaluates_on_the_grid():
    """start="anywhere": every training episode starts from its own scene, spread over the
    stretch before the finish line (150 m here, so the scenes' front is below 50 m and
    their cars up to 15 m behind it); the evaluation race keeps the grid."""
    from racing_env.dynamics import S

    from experiments.cli import START_CHOICES

    assert START_CHOICES == train_rl.TRAINING_STARTS  # the command line offers what the config takes
    config = TrainConfig(**{**TINY, "start": "anywhere"})
    assert config.race_config().scenario == "anywhere"
    assert config.race_config(training=False).scenario == "grid"
    venv = train_rl.make_training_env(config)
    try:
        race = venv.envs[1].unwrapped.race
        starts = []
        for seed in range(20):
            venv.envs[1].reset(seed=seed)
            starts.append(race.state()[:, S])
        starts = np.array(starts)
        assert np.all(starts < 50.0) and np.all(starts >= -15.0)
        assert starts.max() > 30.0 and starts.min() < 5.0
        assert len({row.tobytes() for row in starts}) == 20
    finally:
        venv.close()


def test_mixed_starts_put_the_even_copies_on_the_grid_and_the_odd_ones_anywhere():
    """start="mixed": copy 0 (and every even copy) of the race starts on the seeded grid,
    behind the line, and copy 1 from scenes anywhere before the finish."""
    from racing_env.dynamics import S

    config = TrainConfig(**{**TINY, "start": "mixed", "envs": 3})
    assert [config.scenario(copy) for copy in range(3)] == ["grid", "anywhere", "grid"]
    venv = train_rl.make_training_env(config)
    try:
        for copy, scenario in enumerate(["grid", "anywhere", "grid"]):
            env = venv.envs[copy]
            assert env.unwrapped.race.config.scenario == scenario
            starts = []
            for seed in range(10):
                env.reset(seed=seed)
                starts.append(env.unwrapped.race.state()[:, S])
            starts = np.array(starts)
            if scenario == "grid":  # two cars, 4 m apart, behind the line at s = 0 (jittered by up to 1 m)
                assert np.all(starts < 0.0) and np.all(starts > -11.0)
            else:
                assert starts.max() > 10.0
    finally:
        venv.close()


def test_a_run_saved_before_training_starts_existed_resumes_as_a_grid_run(tmp_path, capsys):
    """train.json of a run saved before the ``start`` setting existed lacks it: the run
    resumes as the grid run it was, and starting it anywhere instead is refused."""
    out = tmp_path / "run"
    args = [*TINY_ARGS, "--eval-every", "0", "--checkpoint-every", "512", "--out", str(out)]
    assert main([*args, "--timesteps", "512"]) == 0
    report = json.loads((out / "train.json").read_text())
    del report["config"]["start"]
    (out / "train.json").write_text(json.dumps(report))
    assert main([*args, "--timesteps", "1024", "--start", "anywhere"]) == 2
    assert "holds a training run with other settings (start)" in capsys.readouterr().err
    assert main([*args, "--timesteps", "1024"]) == 0
    report = json.loads((out / "train.json").read_text())
    assert report["status"] == "completed" and report["timesteps"] == 1024 and report["config"]["start"] == "grid"


def test_parse_hyperparameter():
    assert train_rl.parse_hyperparameter("n_steps=1024") == ("n_steps", 1024)
    assert train_rl.parse_hyperparameter("learning-rate=3e-4") == ("learning_rate", 3e-4)
    assert train_rl.parse_hyperparameter("policy_kwargs={'net_arch': [64, 64]}") == (
        "policy_kwargs", {"net_arch": [64, 64]})
    assert train_rl.parse_hyperparameter("device=cpu") == ("device", "cpu")


def test_summarize_evaluation_counts_the_learner_slot():
    def car(start, place, finish, distance, contact=0, off=0.0, error=None, faults=0):
        return {"start_place": start, "place": place, "finish_time": finish, "distance": distance,
                "collision_steps": contact, "time_off_track": off, "error": error, "faults": faults}

    races = [  # (learner's slot, race)
        (0, {"cars": [car(2, 1, 60.0, 500.0, contact=2, faults=1), car(1, 2, 61.5, 500.0, contact=2)]}),  # from behind, wins by 1.5 s
        (1, {"cars": [car(2, 1, 59.0, 500.0), car(1, 2, None, 420.0, off=3.0)]}),    # from the front, not finished
    ]
    record = evaluation.summarize_evaluation(races, timesteps=4096)
    assert record == {"timesteps": 4096, "races": 2, "wins": 1, "win_rate": 0.5, "races_by_start_place": [1, 1],
                      "wins_by_start_place": [0, 1], "mean_place": 1.5,
                      "finished": 1, "mean_finish_time_s": 60.0, "mean_limit_ratio": None, "mean_margin_s": 1.5,
                      "mean_distance": 460.0, "contact_steps": 2, "faults": 1, "time_off_track_s": 3.0, "errors": []}


def test_summarize_evaluation_of_a_time_trial_reports_finish_times_and_no_margin():
    def lap(finish, distance):
        return {"cars": [{"start_place": 1, "place": 1, "finish_time": finish, "distance": distance,
                          "limit_ratio": None if finish is None else finish / 50.0,
                          "collision_steps": 0, "time_off_track": 0.0, "error": None}]}

    record = evaluation.summarize_evaluation([(0, lap(56.0, 1427.0)), (0, lap(None, 300.0)), (0, lap(57.0, 1427.0))],
                                           timesteps=10)
    assert record["mean_finish_time_s"] == 56.5 and record["mean_margin_s"] is None
    assert record["mean_limit_ratio"] == pytest.approx(56.5 / 50.0, rel=1e-15)
    assert "(1.130x the limit)" in evaluation.evaluation_line(record)
    assert record["wins"] == record["finished"] == 2 and record["races_by_start_place"] == [3]


def test_init_model_is_trained_further(tmp_path):
    """--init-model starts from the saved policy and its VecNormalize statistics, counts
    its own steps from zero, and refuses a model it cannot continue."""
    first = tmp_path / "first"
    run_training(TrainConfig(**{**TINY, "timesteps": 512, "eval_every": 0}), first, progress=False)
    saved = first / "model.zip"
    config = TrainConfig(**{**TINY, "timesteps": 512, "eval_every": 0, "init_model": str(saved)})
    model = train_rl._build_model(config, tmp_path / "second", None)
    start, reference = model.policy.state_dict(), _policy_parameters(saved)
    assert model.num_timesteps == 0 and all(torch.equal(start[k], reference[k]) for k in start)
    stats = make_agent(f"rl:{saved}").normalizer.obs_rms
    np.testing.assert_array_equal(model.get_env().obs_rms.mean, stats.mean)
    model.get_env().close()

    with pytest.raises(ValueError, match="trained with VecNormalize"):
        train_rl._build_model(TrainConfig(**{**TINY, "init_model": str(saved), "normalize": False}), tmp_path, None)
    # a race of fewer cars (one with more: tests/test_widen_policy.py)
    with pytest.raises(ValueError, match="cannot train .* further in this race .* observing 30 inputs cannot be "
                                         "carried into a 1-car race"):
        train_rl._build_model(TrainConfig(**{**TINY, "init_model": str(saved), "opponents": ()}), tmp_path, None)
    with pytest.raises(ValueError, match="does not exist"):
        TrainConfig(**{**TINY, "init_model": str(tmp_path / "none.zip")})
    with pytest.raises(ValueError, match="sac cannot train .* further"):
        train_rl._build_model(TrainConfig(**{**TINY, "hyperparameters": (), "algo": "sac",
                                             "init_model": str(saved)}), tmp_path, None)


def test_evaluations_race_under_tournament_rules_unless_told_otherwise():
    """Training terminates off track by default; the evaluations count it only, unless
    eval_off_track sets their rule (e.g. terminate, to retire a learner that runs wide)."""
    default = TrainConfig(**TINY)
    assert default.race_config().on_off_track == "terminate"
    assert default.race_config(training=False).on_off_track == "penalty"
    strict = TrainConfig(**TINY, eval_off_track="terminate").race_config(training=False)
    assert strict.on_off_track == "terminate"
    assert strict.reward == RewardConfig()  # the training's reward weights stay out of evaluations
