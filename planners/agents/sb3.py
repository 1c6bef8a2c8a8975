"""A saved stable-baselines3 policy as an agent (:class:`SB3Agent`, specs ``rl:PATH``).

The RL layer's face in the agent protocol. stable-baselines3 (and with it torch) is
imported when an :class:`SB3Agent` is built, not when this module is: a user who races only
planners never loads it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from planners.agents.protocol import BaseAgent, observation_space_of, units_conversion, warn_other_car
from planners.methods import RL

__all__ = ["SB3Agent", "SB3_ALGOS", "VECNORMALIZE_SUFFIX", "vecnormalize_path"]

SB3_ALGOS = ("ppo", "sac", "td3", "a2c", "ddpg")
"""The stable-baselines3 algorithms a saved model may come from, in the order they are tried."""

VECNORMALIZE_SUFFIX = ".vecnormalize.pkl"


def vecnormalize_path(model_path) -> Path:
    """Where the observation statistics of a model trained under ``VecNormalize`` are kept:
    beside the model, ``model.zip`` -> ``model.vecnormalize.pkl``."""
    path = Path(model_path)
    stem = path.name[: -len(".zip")] if path.name.endswith(".zip") else path.name
    return path.with_name(stem + VECNORMALIZE_SUFFIX)


def _observation_normalizer(path: Path, model):
    """The saved ``VecNormalize`` of a model, frozen (statistics no longer updated), used
    through its public ``normalize_obs``; it wraps a stand-in env that only has the spaces."""
    import gymnasium
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    class _Spaces(gymnasium.Env):
        observation_space, action_space = model.observation_space, model.action_space

    normalizer = VecNormalize.load(str(path), DummyVecEnv([_Spaces]))
    normalizer.training = False
    normalizer.norm_reward = False
    return normalizer


class SB3Agent(BaseAgent):
    """A saved stable-baselines3 model acting with ``predict(obs, deterministic=True)``.

    If the model was trained under ``VecNormalize`` (as ``racing train`` does by default),
    its observation statistics are loaded from beside the model
    (:func:`vecnormalize_path`) and applied to every observation. A model that records the
    units it was trained on (its ``observation_units`` attribute, which ``racing train`` sets)
    reads them in any race: a race observed in the other units is converted exactly
    (:func:`planners.agents.protocol.units_conversion`); a model that does not say reads the
    race's observations as they come. A model that records the class of the car it trained
    in (its ``car_class`` attribute, which ``racing train`` sets) warns when it drives a car
    of another class (:func:`planners.agents.protocol.warn_other_car`).

    Args:
        path: the ``.zip`` written by ``model.save``.
        algo: ``ppo``, ``sac``, ``td3``, ``a2c``, ``ddpg``; ``None`` tries them in this order.
        device: torch device for the policy (``cpu`` by default).
    """

    spec = name = RL  # the instance's name becomes "rl:<algo>" once loaded

    def __init__(self, path, algo: str | None = None, device: str = "cpu") -> None:
        super().__init__()
        import stable_baselines3 as sb3

        self.path = str(path)
        if algo is not None and algo.lower() not in SB3_ALGOS:
            raise ValueError(f"algo must be one of {SB3_ALGOS}, got {algo!r}")
        if not (Path(self.path).is_file() or Path(self.path + ".zip").is_file()):  # SB3 adds .zip when missing
            raise ValueError(f"no model file at {self.path} (a stable-baselines3 model saved by model.save, "
                             "e.g. runs/ppo/model.zip)")
        candidates = [algo.lower()] if algo else list(SB3_ALGOS)
        errors = []
        self.model = None
        for name in candidates:
            try:
                self.model = getattr(sb3, name.upper()).load(self.path, device=device)
                self.algo = name
                break
            except Exception as exc:  # noqa: BLE001 - try the next algorithm
                errors.append(f"{name}: {type(exc).__name__}: {exc}")
        if self.model is None:
            raise ValueError(f"could not load a stable-baselines3 model from {self.path}: " + "; ".join(errors))
        self.name = f"rl:{self.algo}"
        stats = vecnormalize_path(self.path)
        self.normalizer = _observation_normalizer(stats, self.model) if stats.exists() else None
        self.observation_units = getattr(self.model, "observation_units", None)
        self.car_class = getattr(self.model, "car_class", None)
        self.to_model_units: np.ndarray | None = None  # (O,) factors, set by reset

    def reset(self, seed: int | None, index: int, env_info: Any) -> None:
        """As every agent's; also refuses a race whose observations the model cannot read
        (another number of cars or preview), which would otherwise only brake each step."""
        super().reset(seed, index, env_info)
        space = observation_space_of(env_info, self.index)
        expected = self.model.observation_space.shape
        if space is not None and space.shape != expected:
            raise ValueError(
                f"{self.path} reads observations of shape {expected}, and car {self.index} of this "
                f"{self.game.num_players}-car race observes {space.shape}: trained with another number of cars "
                "or preview distances? (A time-trial model races alone, racing tournament --cars 1; "
                "racing train --init-model carries it into a race with more cars.)"
            )
        self.to_model_units = units_conversion(env_info, self.index, self.observation_units)
        warn_other_car(self.path, self.car_class, self.game, self.index)
        if seed is not None:
            try:
                self.model.set_random_seed(seed)
            except Exception:  # noqa: BLE001 - seeding is best effort
                pass

    def _predict(self, observation: np.ndarray, joint_state: np.ndarray) -> np.ndarray:
        obs = np.asarray(observation, dtype=np.float32)
        expected = self.model.observation_space.shape
        if obs.shape != expected:
            raise ValueError(
                f"observation shape {obs.shape} does not match the model's {expected} "
                "(trained with a different number of cars or preview distances?)"
            )
        return self.predict_raw(obs)

    def predict_raw(self, observations: np.ndarray) -> np.ndarray:
        """The model's deterministic actions for the race's observations ``(..., O)``: in its
        own units, normalised by its saved statistics."""
        obs = np.asarray(observations, dtype=np.float32)
        if self.to_model_units is not None:
            obs = (obs * self.to_model_units).astype(np.float32)
        if self.normalizer is not None:
            obs = self.normalizer.normalize_obs(obs)
        action, _ = self.model.predict(obs, deterministic=True)
        return action

    def act(self, observation: np.ndarray, joint_state: np.ndarray) -> np.ndarray:
        return self._act_guarded(self._predict, observation, joint_state)
