"""A policy trained by the JAX learner, its model file, and the agent that races it (``rl:PATH.npz``).

The network is an actor-critic of two multilayer perceptrons (tanh hidden layers, no weights
shared), the shape stable-baselines3's PPO uses by default:

* the actor maps a normalised observation ``(O,)`` to the mean ``(2,)`` of a Gaussian over
  the normalised jerks, with a state-independent ``log_std (2,)``;
* the critic maps it to the value ``()`` (in units of the normalised reward).

Observations are normalised as stable-baselines3's ``VecNormalize`` does:
``clip((obs - mean) / sqrt(var + epsilon), -clip_obs, clip_obs)`` with running statistics
``mean, var (O,)`` gathered in training and frozen in the model file.

The model file is one ``.npz`` (NumPy's archive, readable without JAX):

* ``format``: :data:`MODEL_FORMAT`; ``hidden``: the hidden layer sizes ``(H,)`` int;
* ``obs_mean``, ``obs_var`` ``(O,)`` float64, ``clip_obs``, ``epsilon`` scalars;
* ``observation_units``: what the observations were in when it trained
  (:data:`racing_env.observation.OBSERVATION_UNITS`; a file without it, written before the
  units could be chosen, was trained on ``physical`` ones). A race observed in other units is
  converted exactly (:func:`planners.agents.protocol.units_conversion`);
* ``car_class``: the class of the car it trained in (:mod:`racing_env.car_classes`; a file
  without it does not say). Racing another class's car is warned about
  (:func:`planners.agents.protocol.warn_other_car`), not refused;
* ``params/<module>/<name>``: the network's weights (float32), flax's parameter tree flattened
  with ``/``.

A race drives with the deterministic action, the Gaussian's mean clipped to ``[-1, 1]``
(:func:`deterministic_action`), as the learner's evaluations do.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from planners.agents.protocol import BaseAgent, observation_space_of, units_conversion, warn_other_car
from planners.methods import RL

__all__ = ["JAX_MODEL_SUFFIX", "MODEL_FORMAT", "JaxPolicyAgent", "ObsNormalizer", "PolicyModel",
           "actor_critic", "deterministic_action", "is_jax_model", "load_model", "normalize_obs", "save_model"]

MODEL_FORMAT = "racing-games jax actor-critic 1"
UNITS_BEFORE_CHOICE = "physical"
"""The observation units of a model file that does not record them."""
JAX_MODEL_SUFFIX = ".npz"


def is_jax_model(path: str | Path) -> bool:
    """Whether ``path`` names a JAX learner's model file (by its suffix, ``.npz``)."""
    return str(path).lower().endswith(JAX_MODEL_SUFFIX)


def actor_critic(hidden: Sequence[int], log_std_init: float = 0.0):
    """The flax module ``obs (..., O) -> (mean (..., 2), log_std (2,), value (...))``.

    Orthogonal initialisation as stable-baselines3's: gain sqrt(2) in hidden layers, 0.01 on
    the action mean (the first actions are near zero whatever the observation), 1 on the
    value."""
    import flax.linen as nn
    import jax.numpy as jnp

    hidden = tuple(int(h) for h in hidden)

    class ActorCritic(nn.Module):
        @nn.compact
        def __call__(self, obs):
            obs = obs.astype(jnp.float32)

            def tower(name: str, outputs: int, gain: float):
                h = obs
                for k, size in enumerate(hidden):
                    h = nn.tanh(nn.Dense(size, kernel_init=nn.initializers.orthogonal(np.sqrt(2.0)),
                                         name=f"{name}_{k}")(h))
                return nn.Dense(outputs, kernel_init=nn.initializers.orthogonal(gain), name=f"{name}_out")(h)

            mean = tower("actor", 2, 0.01)
            value = tower("critic", 1, 1.0)[..., 0]
            log_std = self.param("log_std", nn.initializers.constant(log_std_init), (2,), jnp.float32)
            return mean, log_std, value

    return ActorCritic()


class ObsNormalizer:
    """Running observation statistics ``(mean (O,), var (O,), count)`` as a pytree-friendly
    tuple, updated with batches as ``VecNormalize`` updates them (parallel Welford)."""

    @staticmethod
    def init(size: int):
        import jax.numpy as jnp

        return (jnp.zeros(size), jnp.ones(size), jnp.asarray(1e-4))

    @staticmethod
    def update(stats, batch):
        """``stats`` after observing ``batch (K, O)``."""
        mean, var, count = stats
        batch = batch.astype(mean.dtype)
        b_mean, b_var, b_count = batch.mean(0), batch.var(0), batch.shape[0]
        delta = b_mean - mean
        total = count + b_count
        new_mean = mean + delta * b_count / total
        m2 = var * count + b_var * b_count + delta**2 * count * b_count / total
        return (new_mean, m2 / total, total)


def normalize_obs(obs, mean, var, clip_obs: float = 10.0, epsilon: float = 1e-8):
    """``clip((obs - mean) / sqrt(var + epsilon), -clip_obs, clip_obs)`` (float32)."""
    import jax.numpy as jnp

    return jnp.clip((obs - mean) / jnp.sqrt(var + epsilon), -clip_obs, clip_obs).astype(jnp.float32)


def deterministic_action(module, params, obs, mean, var, clip_obs: float = 10.0, epsilon: float = 1e-8):
    """The policy's action for raw observations ``obs (..., O)``: the Gaussian's mean, clipped
    to ``[-1, 1]`` (normalised jerks ``(..., 2)``)."""
    import jax.numpy as jnp

    action_mean, _, _ = module.apply({"params": params}, normalize_obs(obs, mean, var, clip_obs, epsilon))
    return jnp.clip(action_mean, -1.0, 1.0)


class PolicyModel:
    """A loaded model file: ``hidden``, ``params`` (flax tree of float32 arrays), the frozen
    observation statistics, and its compiled :func:`deterministic_action`."""

    def __init__(self, hidden: Sequence[int], params: dict, obs_mean: np.ndarray, obs_var: np.ndarray,
                 clip_obs: float = 10.0, epsilon: float = 1e-8, observation_units: str = "scaled",
                 car_class: str | None = None) -> None:
        import jax

        self.hidden = tuple(int(h) for h in hidden)
        self.params = params
        self.obs_mean = np.asarray(obs_mean, dtype=np.float64)
        self.obs_var = np.asarray(obs_var, dtype=np.float64)
        self.clip_obs, self.epsilon = float(clip_obs), float(epsilon)
        self.observation_units = observation_units
        self.car_class = car_class
        self.module = actor_critic(self.hidden)
        module, clip, eps = self.module, self.clip_obs, self.epsilon
        self._act = jax.jit(lambda p, o, m, v: deterministic_action(module, p, o, m, v, clip, eps))

    @property
    def observation_size(self) -> int:
        return int(self.obs_mean.shape[0])

    def act(self, observations: np.ndarray) -> np.ndarray:
        """Actions ``(..., 2)`` float64 for raw observations ``(..., O)``."""
        obs = np.asarray(observations, dtype=np.float32)
        if obs.shape[-1] != self.observation_size:
            raise ValueError(f"the model reads observations of {self.observation_size} numbers, got {obs.shape[-1]}")
        return np.asarray(self._act(self.params, obs, self.obs_mean, self.obs_var), dtype=np.float64)


def save_model(path: str | Path, hidden: Sequence[int], params: dict, obs_mean, obs_var, clip_obs: float = 10.0,
               epsilon: float = 1e-8, observation_units: str = "scaled", car_class: str | None = None) -> Path:
    """Write the model file (module docstring) to ``path`` atomically; returns the path.
    ``car_class``: the class of the car it trained in (None: left out, the file does not say)."""
    import os

    from flax import traverse_util

    path = Path(path)
    flat = {"params/" + "/".join(key): np.asarray(value) for key, value in
            traverse_util.flatten_dict(params).items()}
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, format=np.asarray(MODEL_FORMAT), hidden=np.asarray(hidden, dtype=np.int64),
             obs_mean=np.asarray(obs_mean, dtype=np.float64), obs_var=np.asarray(obs_var, dtype=np.float64),
             clip_obs=np.asarray(clip_obs), epsilon=np.asarray(epsilon),
             observation_units=np.asarray(observation_units),
             **({} if car_class is None else {"car_class": np.asarray(car_class)}), **flat)
    os.replace(tmp, path)
    return path


def load_model(path: str | Path) -> PolicyModel:
    """Read a model file written by :func:`save_model`; ValueError if it is not one."""
    import jax.numpy as jnp
    from flax import traverse_util

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"no model file at {path}")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
    except Exception as exc:  # noqa: BLE001 - a corrupt or foreign file
        raise ValueError(f"{path} is not a readable .npz model file: {type(exc).__name__}: {exc}") from exc
    if str(arrays.get("format", "")) != MODEL_FORMAT:
        raise ValueError(f"{path} is not a JAX learner's model file (format {MODEL_FORMAT!r})")
    params = traverse_util.unflatten_dict({tuple(key.split("/")[1:]): jnp.asarray(value)
                                           for key, value in arrays.items() if key.startswith("params/")})
    units = str(arrays.get("observation_units", UNITS_BEFORE_CHOICE))
    car_class = str(arrays["car_class"]) if "car_class" in arrays else None
    return PolicyModel(arrays["hidden"].tolist(), params, arrays["obs_mean"], arrays["obs_var"],
                       float(arrays["clip_obs"]), float(arrays["epsilon"]), units, car_class)


class JaxPolicyAgent(BaseAgent):
    """A JAX learner's saved policy (``rl:PATH.npz``), acting with its deterministic action.

    Args:
        path: the model file (module docstring).
    """

    spec = name = RL

    def __init__(self, path: str | Path) -> None:
        super().__init__()
        self.path = str(path)
        self.model = load_model(self.path)
        self.name = f"{RL}:jax-ppo"

    def reset(self, seed: int | None, index: int, env_info: Any) -> None:
        """As every agent's; also refuses a race whose observations the model cannot read."""
        super().reset(seed, index, env_info)
        space = observation_space_of(env_info, self.index)
        if space is not None and space.shape != (self.model.observation_size,):
            raise ValueError(
                f"{self.path} reads observations of shape ({self.model.observation_size},), and car {self.index} "
                f"of this {self.game.num_players}-car race observes {space.shape}: trained with another number "
                "of cars or preview distances?")
        self.to_model_units = units_conversion(env_info, self.index, self.model.observation_units)
        warn_other_car(self.path, self.model.car_class, self.game, self.index)

    def predict_many(self, observations: np.ndarray) -> np.ndarray:
        """Actions ``(R, 2)`` for the race's observations ``(R, O)`` (the batched opponents'
        call), in the model's units."""
        if self.to_model_units is not None:
            observations = np.asarray(observations, dtype=np.float64) * self.to_model_units
        return self.model.act(observations)

    def act(self, observation: np.ndarray, joint_state: np.ndarray) -> np.ndarray:
        return self._act_guarded(lambda obs, _: self.predict_many(obs), observation, joint_state)
