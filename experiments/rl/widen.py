"""Carry a saved SB3 policy into a race with more cars than it was trained in.

A car's observation (:mod:`racing_env.observation`) is its own features, then 7 features per
other car, then the track preview; a policy trained in a time trial (one car) therefore
takes fewer inputs than one racing an opponent. :func:`widen_saved_model` gives the saved
networks zero weights on the new cars' features: the widened policy and value function
start out computing exactly what the saved ones did, ignoring the new cars, and training
learns what the new inputs are worth. The saved ``VecNormalize`` statistics are widened to
match by :func:`widen_normalizer`; the new features' mean and variance are then measured
in the new race by :func:`measure_new_features` (the widened policy ignores them, so what
it drives while they are measured does not depend on their placeholder statistics).
"""

from __future__ import annotations

import dataclasses
import pickle
from pathlib import Path

import numpy as np

from racing_env.observation import OTHER_FEATURES, OWN_FEATURES, observation_size


@dataclasses.dataclass(frozen=True)
class Widening:
    """Where new inputs go: ``extra`` features inserted before input ``at``."""

    at: int
    extra: int

    @property
    def new_columns(self) -> slice:
        return slice(self.at, self.at + self.extra)


def observation_widening(old_size: int, new_size: int, cars: int, num_preview: int) -> Widening | None:
    """How a policy observing ``old_size`` inputs fits a race of ``cars`` cars (``new_size``
    inputs): None if the sizes agree; else the other-car features to add after the ones it
    has. Raises ValueError when ``old_size`` is no race's observation with this preview,
    or one of more cars."""
    if old_size == new_size:
        return None
    extra = new_size - old_size
    old_cars = cars - extra // OTHER_FEATURES
    if extra < 0 or extra % OTHER_FEATURES or old_cars < 1 or observation_size(old_cars, num_preview) != old_size:
        raise ValueError(f"a policy observing {old_size} inputs cannot be carried into a {cars}-car race "
                         f"({new_size} inputs): only a policy of fewer cars with the same preview "
                         f"({observation_size(1, num_preview)} inputs alone, +{OTHER_FEATURES} per other car) can")
    return Widening(at=OWN_FEATURES + OTHER_FEATURES * (old_cars - 1), extra=extra)


def _widened_state(old: dict, new: dict, widening: Widening, old_size: int) -> dict:
    """``old``'s tensors in ``new``'s shapes: a weight reading the observation gets zero
    columns for the new inputs; every other tensor must keep its shape."""
    import torch

    state = {}
    for key, tensor in old.items():
        target = new[key].shape
        if tensor.shape == target:
            state[key] = tensor
        # a weight reading the observation first (a critic may append the action to it)
        elif (tensor.ndim == 2 and target[0] == tensor.shape[0] and tensor.shape[1] >= old_size
              and target[1] == tensor.shape[1] + widening.extra):
            zeros = tensor.new_zeros(tensor.shape[0], widening.extra)
            state[key] = torch.cat([tensor[:, : widening.at], zeros, tensor[:, widening.at:]], dim=1)
        else:
            raise ValueError(f"cannot widen {key} from {tuple(tensor.shape)} to {tuple(target)}")
    return state


def widen_saved_model(model, observation_space, widening: Widening, dest: Path) -> Path:
    """Write ``dest`` (a ``.zip``): ``model`` (loaded, and changed in place) observing
    ``observation_space``, with zero weights on the new inputs (:class:`Widening`). Its
    hyperparameters are kept; the optimizer starts afresh (its moments are per weight)."""
    old_size = model.observation_space.shape[0]
    old_state = model.policy.state_dict()
    model.observation_space = observation_space
    model._setup_model()  # rebuilds the networks (and buffers) for the new observation
    model.policy.load_state_dict(_widened_state(old_state, model.policy.state_dict(), widening, old_size))
    dest.parent.mkdir(parents=True, exist_ok=True)
    model.save(dest)
    return dest


def widen_normalizer(stats_path: str | Path, venv, widening: Widening):
    """The ``VecNormalize`` saved at ``stats_path`` wrapped around ``venv`` (which observes
    ``widening.extra`` more inputs): the saved statistics for the old inputs, mean 0 and
    variance 1 as placeholders for the new ones (see :func:`measure_new_features`)."""
    with open(stats_path, "rb") as file:
        normalizer = pickle.load(file)
    rms = normalizer.obs_rms
    rms.mean = np.insert(rms.mean, widening.at, np.zeros(widening.extra))
    rms.var = np.insert(rms.var, widening.at, np.ones(widening.extra))
    normalizer.observation_space = venv.observation_space
    normalizer.set_venv(venv)
    return normalizer


def measure_new_features(model, normalizer, widening: Widening, steps: int) -> None:
    """Drive ``model`` (widened, so blind to the new inputs) for ``steps`` steps of its env in
    all, without updating the normaliser, and set the new inputs' mean and variance in
    ``normalizer.obs_rms`` to those of the raw observations seen."""
    training = normalizer.training
    normalizer.training = False
    observations = normalizer.reset()
    seen = [normalizer.get_original_obs()[:, widening.new_columns]]
    for _ in range(max(1, steps // normalizer.num_envs)):
        actions, _ = model.predict(observations, deterministic=False)
        observations, _, _, _ = normalizer.step(actions)
        seen.append(normalizer.get_original_obs()[:, widening.new_columns])
    normalizer.training = training
    raw = np.concatenate(seen)
    normalizer.obs_rms.mean[widening.new_columns] = raw.mean(axis=0)
    normalizer.obs_rms.var[widening.new_columns] = raw.var(axis=0)
