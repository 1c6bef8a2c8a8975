"""The JAX learner (`racing train --learner jax`): PPO compiled with the races, its model file,
determinism, exact resumption, and its policy racing in tournaments as it acted in training."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments.rl import ppo_jax
from experiments.rl.train import TrainConfig, run_training
from experiments.rl.train_jax import compiled_races, latest_state, make_races, ppo_settings
from planners.agents import make_agent
from planners.agents.jax_policy import JaxPolicyAgent, ObsNormalizer, load_model
from tests.interrupting import ctrl_c_when, start_racing

# 8 races x 16 steps = 128 steps per update, 2 minibatches of 64, 2 epochs
TINY = dict(opponents=("lane-keeping",), envs=8, learner="jax", eval_every=0, eval_grids=1, checkpoint_every=128,
            hyperparameters=(("n_steps", 16), ("batch_size", 64), ("n_epochs", 2)), race_distance=60.0,
            max_steps=200)


def _params(folder):
    model = load_model(folder / "model.npz")
    return jax.tree_util.tree_leaves(model.params), model.obs_mean, model.obs_var


def test_a_tiny_run_is_deterministic_for_a_seed_and_differs_across_seeds(tmp_path):
    reports = [run_training(TrainConfig(timesteps=384, seed=seed, **TINY), tmp_path / name, progress=False)
               for name, seed in (("a", 0), ("b", 0), ("c", 1))]
    assert [r["status"] for r in reports] == ["completed"] * 3
    assert reports[0]["races"] == "compiled" and reports[0]["timesteps"] == 384
    assert reports[0]["learn"]["nonfinite_actions"] == 0
    a, b, c = (_params(tmp_path / name) for name in "abc")
    for x, y in zip(a[0], b[0]):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(a[1], b[1])
    assert (tmp_path / "a" / "episodes.jsonl").read_text() == (tmp_path / "b" / "episodes.jsonl").read_text()
    assert any(not np.array_equal(x, y) for x, y in zip(a[0], c[0]))
    for name in ("train.json", "evaluations.jsonl", "learning_curve.png", "checkpoints/step_000000384.npz",
                 "checkpoints/resume.pkl"):
        assert (tmp_path / "a" / name).exists(), name
    evaluation = json.loads((tmp_path / "a" / "evaluations.jsonl").read_text().splitlines()[-1])
    assert evaluation["timesteps"] == 384 and evaluation["races"] == 2  # 1 grid x 2 slots


def test_a_run_resumed_from_its_checkpoint_equals_an_uninterrupted_one(tmp_path):
    """Train 256 steps, then the same folder to 512 (it resumes from resume.pkl): the model
    and the episode log are those of a run that trained 512 steps at once, bit for bit."""
    run_training(TrainConfig(timesteps=256, **TINY), tmp_path / "resumed", progress=False)
    assert latest_state(tmp_path / "resumed")["timesteps"] == 256
    report = run_training(TrainConfig(timesteps=512, **TINY), tmp_path / "resumed", progress=False)
    assert report["learn"]["updates"] == 2  # only the remaining ones
    run_training(TrainConfig(timesteps=512, **TINY), tmp_path / "straight", progress=False)
    resumed, straight = _params(tmp_path / "resumed"), _params(tmp_path / "straight")
    for x, y in zip(resumed[0], straight[0]):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(resumed[2], straight[2])
    episodes = [(tmp_path / name / "episodes.jsonl").read_text() for name in ("resumed", "straight")]
    assert episodes[0] == episodes[1] and episodes[0]


@pytest.mark.slow
def test_ctrl_c_checkpoints_the_last_update_and_the_same_command_resumes_exactly(tmp_path):
    """A real `racing train --learner jax` process interrupted (SIGINT to its group) after its
    first checkpoint: it exits 130 with a checkpoint at an update's step count, and the same
    command with more steps ends with the very model of a run never interrupted."""
    args = ["train", "--learner", "jax", "--envs", "8", "--race-distance", "60", "--max-steps", "200",
            "--hyperparameter", "n_steps=16", "--hyperparameter", "batch_size=64", "--hyperparameter", "n_epochs=2",
            "--eval-every", "0", "--eval-grids", "1", "--checkpoint-every", "128"]
    out, reference = tmp_path / "run", tmp_path / "reference"
    process = start_racing([*args, "--out", str(out), "--timesteps", "100000000"])
    err = ctrl_c_when(process, (out / "checkpoints" / "step_000000256.npz").exists)
    assert process.returncode == 130, err
    stopped = json.loads((out / "train.json").read_text())["timesteps"]
    assert stopped >= 256 and stopped % 128 == 0
    assert latest_state(out)["timesteps"] == stopped
    target = str(stopped + 256)
    from experiments.cli import main

    assert main([*args, "--out", str(out), "--timesteps", target]) == 0
    assert main([*args, "--out", str(reference), "--timesteps", target]) == 0
    for x, y in zip(_params(out)[0], _params(reference)[0]):
        np.testing.assert_array_equal(x, y)
    assert (out / "episodes.jsonl").read_text() == (reference / "episodes.jsonl").read_text()


def test_the_saved_policy_acts_as_in_training_and_races_in_a_tournament(tmp_path):
    from experiments.tournament import TournamentConfig, run_tournament

    config = TrainConfig(timesteps=256, **TINY)
    run_training(config, tmp_path / "run", progress=False)
    state = latest_state(tmp_path / "run")
    learner = jax.tree_util.tree_map(jnp.asarray, state["learner"])
    settings = ppo_settings(config)
    # observations spread over the statistics' range: the training's deterministic action is the clipped mean
    env = compiled_races(config)
    obs = np.random.default_rng(0).normal(size=(5, env.observation_space().shape[0])).astype(np.float32) * 3
    scaled = ppo_jax._scaled_obs(settings, learner, jnp.asarray(obs))
    mean, _, _ = settings.module.apply({"params": learner.params}, scaled)
    in_training = np.clip(np.asarray(mean, dtype=np.float64), -1, 1)
    agent = make_agent(f"rl:{tmp_path / 'run' / 'model.npz'}")
    assert isinstance(agent, JaxPolicyAgent)
    from racing_env import parallel_env

    race_env = parallel_env(num_agents=2, track="trefoil")
    agent.reset(0, 0, race_env)
    # float32 networks: one sample at a time and five at once round differently, by float32 ulps
    for row, expected in zip(obs, in_training):
        np.testing.assert_allclose(agent.model.act(row), expected, rtol=0, atol=1e-6)
    np.testing.assert_allclose(agent.predict_many(obs), in_training, rtol=0, atol=1e-6)

    board = run_tournament(TournamentConfig(agents=(f"rl:{tmp_path / 'run' / 'model.npz'}", "lane-keeping"),
                                            grids=1, race_distance=60.0), tmp_path / "tour", gif=False,
                           progress=False)
    records = [json.loads(line) for line in (tmp_path / "tour" / "results.jsonl").read_text().splitlines()]
    assert records and all(car["error"] is None for r in records for car in r["cars"])
    assert board is not None


def test_the_model_file_round_trips_and_foreign_files_are_refused(tmp_path):
    run_training(TrainConfig(timesteps=128, **TINY), tmp_path / "run", progress=False)
    model = load_model(tmp_path / "run" / "model.npz")
    assert model.hidden == (64, 64) and model.observation_size == model.obs_var.shape[0]
    (tmp_path / "other.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a readable"):
        make_agent(f"rl:{tmp_path / 'other.npz'}")
    np.savez(tmp_path / "foreign.npz", x=np.zeros(3))
    with pytest.raises(ValueError, match="not a JAX learner's model file"):
        make_agent(f"rl:{tmp_path / 'foreign.npz'}")
    agent = make_agent(f"rl:{tmp_path / 'run' / 'model.npz'}")
    from racing_env import parallel_env

    with pytest.raises(ValueError, match="observes"):
        agent.reset(0, 0, parallel_env(num_agents=3, track="trefoil"))


def test_running_statistics_match_numpys_over_batches():
    rng = np.random.default_rng(3)
    batches = [rng.normal(loc=2.0, scale=3.0, size=(k, 4)) for k in (5, 17, 1, 40)]
    stats = ObsNormalizer.init(4)
    for batch in batches:
        stats = ObsNormalizer.update(stats, jnp.asarray(batch))
    every = np.concatenate(batches)
    # the prior count 1e-4 (VecNormalize's) weighs the initial mean 0 and variance 1 in
    prior = 1e-4
    mean = every.sum(0) / (len(every) + prior)
    np.testing.assert_allclose(np.asarray(stats[0]), mean, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.asarray(stats[1]), every.var(0), rtol=1e-4)


def test_generalised_advantages_equal_a_direct_sum():
    """GAE against its definition: A_t = sum_k (gamma lambda)^k delta_{t+k}, cut at episode ends."""
    settings = ppo_jax.PPOSettings(gamma=0.9, gae_lambda=0.8)
    rng = np.random.default_rng(0)
    t, b = 7, 3
    reward, value, last = rng.normal(size=(t, b)), rng.normal(size=(t, b)), rng.normal(size=b)
    done = rng.random((t, b)) < 0.3
    rollout = ppo_jax.Rollout(None, None, None, jnp.asarray(value), jnp.asarray(reward), jnp.asarray(done))
    advantages, targets = ppo_jax._advantages(settings, rollout, jnp.asarray(last))
    next_value = np.vstack([value[1:], last[None]])
    delta = reward + 0.9 * next_value * ~done - value
    expected = np.zeros((t, b))
    for r in range(b):
        for s in range(t):
            total, factor = 0.0, 1.0
            for k in range(s, t):
                total += factor * delta[k, r]
                if done[k, r]:
                    break
                factor *= 0.9 * 0.8
            expected[s, r] = total
    np.testing.assert_allclose(np.asarray(advantages), expected, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(targets), expected + value, rtol=1e-12, atol=1e-12)


@pytest.mark.slow
def test_planner_opponents_train_on_the_host_races(tmp_path):
    """Against a planner the races step from Python (the SB3 learner's vectorised races),
    with the same outputs; the run resumes exactly from its checkpoint."""
    tiny = {**TINY, "opponents": ("ilqgame-fb:replan_every=5",), "envs": 4,
            "hyperparameters": (("n_steps", 16), ("batch_size", 32), ("n_epochs", 2)), "checkpoint_every": 64}
    report = run_training(TrainConfig(timesteps=64, **tiny), tmp_path / "resumed", progress=False)
    assert report["races"] == "host" and report["status"] == "completed"
    run_training(TrainConfig(timesteps=128, **tiny), tmp_path / "resumed", progress=False)
    run_training(TrainConfig(timesteps=128, **tiny), tmp_path / "straight", progress=False)
    for x, y in zip(_params(tmp_path / "resumed")[0], _params(tmp_path / "straight")[0]):
        np.testing.assert_array_equal(x, y)


# the compiled races (TINY's: the update the tests above compiled); the host races (two scenarios)
@pytest.mark.parametrize("start", ["grid", pytest.param("mixed", marks=pytest.mark.slow)])
def test_a_policy_whose_actions_are_not_finite_is_counted_and_the_races_stay_finite(start):
    """A policy with NaN parameters acts NaN in every race and step: each action is raced as
    zero jerk and counted in the update's metrics (train.json's ``learn.nonfinite_actions``),
    and the races' observations stay finite."""
    # the anywhere scenes of mixed starts lie at least 100 m before the finish
    config = TrainConfig(timesteps=128, **{**TINY, "start": start, **({"race_distance": 160.0} if start == "mixed" else {})})
    settings = ppo_settings(config)
    races = make_races(config, settings)
    assert races.kind == ("compiled" if start == "grid" else "host")
    learner = ppo_jax.init_learner(jax.random.PRNGKey(0), races.observation_size, config.envs, settings)
    learner, in_flight = races.start(learner, 0)
    broken = learner._replace(params=jax.tree_util.tree_map(lambda a: jnp.full_like(a, jnp.nan), learner.params))
    _, in_flight, _, metrics = races.update(broken, in_flight)
    assert metrics["nonfinite_actions"] == settings.n_steps * config.envs  # every action of the update
    obs = in_flight.obs if start == "grid" else in_flight["obs"]  # normalised: NaN where the race's were
    assert bool(jnp.isfinite(obs).all())
    races.close()


def test_the_jax_learner_refuses_what_it_cannot_do(tmp_path):
    with pytest.raises(ValueError, match="drop algo other than ppo"):
        TrainConfig(learner="jax", algo="sac")
    with pytest.raises(ValueError, match="has no hyperparameter 'policy_kwargs'"):
        TrainConfig(learner="jax", hyperparameters=(("policy_kwargs", {}),))
    with pytest.raises(ValueError, match="learner must be one of"):
        TrainConfig(learner="torch")
    with pytest.raises(ValueError, match="batch_size 100 must divide"):
        ppo_settings(TrainConfig(learner="jax", envs=8, hyperparameters=(("n_steps", 16), ("batch_size", 100))))
    assert compiled_races(TrainConfig(learner="jax", opponents=("ilqr",))) is None
    assert compiled_races(TrainConfig(learner="jax", opponents=(), start="grid")) is not None
    assert compiled_races(TrainConfig(learner="jax", opponents=(), start="anywhere")) is not None
    assert compiled_races(TrainConfig(learner="jax", opponents=(), start="mixed")) is None


@pytest.mark.slow
def test_the_jax_learner_reaches_the_sb3_learners_time_trial_at_the_same_budget(tmp_path):
    """The known answer: alone on the trefoil, 100,000 steps over 64 copies (PPO's defaults
    for 64 copies in both), both learners finish every evaluation lap. Over seeds 0-2 of each
    learner the final mean lap was 57.58-57.90 s, so seed 0's laps must agree within 0.5 s,
    and the last fifth of training's episode returns within a factor of 3 (SB3 53-136, JAX
    130-153 over those seeds)."""
    results = {}
    for learner in ("jax", "sb3"):
        config = TrainConfig(opponents=(), envs=64, timesteps=100_000, learner=learner, eval_every=0,
                             checkpoint_every=0, seed=0)
        report = run_training(config, tmp_path / learner, progress=False)
        episodes = [json.loads(line) for line in (tmp_path / learner / "episodes.jsonl").read_text().splitlines()]
        late = [e["return"] for e in episodes if e["timesteps"] > 80_000]
        results[learner] = report["final_evaluation"], float(np.mean(late))
    for evaluation, _ in results.values():
        assert evaluation["finished"] == evaluation["races"] == 2
    laps = [evaluation["mean_finish_time_s"] for evaluation, _ in results.values()]
    assert abs(laps[0] - laps[1]) < 0.5, laps
    returns = [late for _, late in results.values()]
    assert max(returns) < 3 * min(returns), returns


@pytest.mark.slow  # vmapped seeds do not pay on a CPU (docs/rl.md); the runner trains one seed at a time
def test_seeds_train_as_one_vmapped_program_each_as_it_would_alone():
    """`compiled_update` is pure: vmapped over two stacked learners and their races, each
    seed's update is its own. The networks are float32 and a batched matmul may add in
    another order than a single one, so policies agree to float32 rounding (1e-5 relative)
    after an update, and the races (float64, driven by those actions) to the same."""
    config = TrainConfig(timesteps=128, **TINY)
    settings, env = ppo_settings(config), compiled_races(config)
    update = ppo_jax.compiled_update(env, settings)
    size = env.observation_space().shape[0]
    singles = []
    for seed in (0, 1):
        learner = ppo_jax.init_learner(jax.random.PRNGKey(seed), size, config.envs, settings)
        singles.append(ppo_jax.start_races(env, settings, learner, jax.random.PRNGKey(100 + seed), config.envs))
    stacked = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), *singles)
    batched = jax.jit(jax.vmap(update))(*stacked)
    for seed, (learner, races) in enumerate(singles):
        alone = update(learner, races)
        for mine, together in zip(jax.tree_util.tree_leaves(alone[:2]), jax.tree_util.tree_leaves(batched[:2])):
            np.testing.assert_allclose(np.asarray(together[seed]), np.asarray(mine), rtol=1e-5, atol=1e-6)
