"""Carrying a saved policy into a race with more cars (experiments.rl.widen): the layout
arithmetic, and a real time-trial PPO policy trained further against an opponent."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from experiments.rl import train as train_rl
from experiments.rl.train import TrainConfig, run_training
from experiments.rl.widen import Widening, observation_widening
from planners.agents import make_agent
from racing_env.observation import observation_size

TINY = dict(timesteps=512, race_distance=150.0, max_steps=200, envs=2, checkpoint_every=0, eval_every=0,
            eval_grids=1, hyperparameters=(("n_steps", 256), ("batch_size", 64), ("n_epochs", 2)))


def test_the_new_cars_features_go_after_the_ones_the_policy_has():
    alone, duel, three = (observation_size(n, 5) for n in (1, 2, 3))
    assert observation_widening(duel, duel, 2, 5) is None
    assert observation_widening(alone, duel, 2, 5) == Widening(at=8, extra=7)
    assert observation_widening(alone, three, 3, 5) == Widening(at=8, extra=14)
    assert observation_widening(duel, three, 3, 5) == Widening(at=15, extra=7)
    for old, new, cars, preview in [(three, duel, 2, 5),  # more cars than the race
                                    (observation_size(1, 4), duel, 2, 5),  # another preview
                                    (alone + 1, duel, 2, 5)]:
        with pytest.raises(ValueError, match="cannot be carried into a 2-car race"):
            observation_widening(old, new, cars, preview)


@pytest.mark.slow  # two trainings; the widening's feature layout: the test above
def test_a_time_trial_policy_is_trained_further_against_an_opponent(tmp_path):
    """The widened policy acts and values exactly as the time-trial one, whatever the new
    car's features; the saved statistics are kept for the old features and measured in the
    new race for the new ones; and the run then trains."""
    solo = tmp_path / "solo"
    run_training(TrainConfig(opponents=(), **TINY), solo, progress=False)
    old = make_agent(f"rl:{solo / 'model.zip'}")
    config = TrainConfig(opponents=("lane-keeping",), init_model=str(solo / "model.zip"), **TINY)
    model = train_rl._build_model(config, tmp_path / "duel", None)
    assert model.observation_space.shape == (observation_size(2, 5),) and model.num_timesteps == 0

    # weights: the old columns as saved, zeros for the new car's features
    widened, saved = model.policy.state_dict(), old.model.policy.state_dict()
    for key in ("mlp_extractor.policy_net.0.weight", "mlp_extractor.value_net.0.weight"):
        assert torch.equal(widened[key][:, 8:15], torch.zeros_like(widened[key][:, 8:15]))
        assert torch.equal(torch.cat([widened[key][:, :8], widened[key][:, 15:]], dim=1), saved[key])

    # behaviour: the same mean action and value for any values of the new features
    rng = np.random.default_rng(0)
    normalised = rng.normal(size=(64, observation_size(1, 5))).astype(np.float32)
    with_car = np.insert(normalised, 8, rng.normal(scale=5.0, size=(7, 64)).astype(np.float32), axis=1)
    with torch.no_grad():
        old_mean = old.model.policy.get_distribution(torch.as_tensor(normalised)).distribution.mean
        new_mean = model.policy.get_distribution(torch.as_tensor(with_car)).distribution.mean
        old_value = old.model.policy.predict_values(torch.as_tensor(normalised))
        new_value = model.policy.predict_values(torch.as_tensor(with_car))
    # float32: the same products, summed in an order the matrix kernel may change
    np.testing.assert_allclose(new_mean.numpy(), old_mean.numpy(), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(new_value.numpy(), old_value.numpy(), rtol=1e-5, atol=1e-6)

    # statistics: the saved ones for the old features; measured ones for the new car's
    stats, saved_stats = model.get_env().obs_rms, old.normalizer.obs_rms
    np.testing.assert_array_equal(np.delete(stats.mean, np.s_[8:15]), saved_stats.mean)
    np.testing.assert_array_equal(np.delete(stats.var, np.s_[8:15]), saved_stats.var)
    assert stats.count == saved_stats.count
    # measured, not the placeholders (mean 0, variance 1): the gap to the lane keeper varies by
    # metres, and its racing flag (1 until it finishes the 150 m race) has the variance of a
    # 0/1 feature, p (1 - p) (float32 observations)
    assert stats.var[8] > 1.0
    racing = stats.mean[14]
    assert 0.5 < racing <= 1.0 and stats.var[14] == pytest.approx(racing * (1.0 - racing), abs=1e-6)
    # the widened model races as an agent with these statistics
    widened_agent = make_agent(f"rl:{tmp_path / 'duel' / 'init_model_widened.zip'}")
    np.testing.assert_array_equal(widened_agent.normalizer.obs_rms.mean, stats.mean)
    np.testing.assert_array_equal(widened_agent.normalizer.obs_rms.var, stats.var)
    model.get_env().close()

    report = run_training(config, tmp_path / "duel", progress=False)
    assert report["status"] == "completed" and report["timesteps"] == 512
