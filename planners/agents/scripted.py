"""The scripted drivers as agents: the racing-line driver, the lane keeper, the constant-speed
cruiser and the random driver.

The drivers themselves (their control laws) live in :mod:`planners.scripted`, which the
opponent predictions (:mod:`planners.prediction`) use as well; here they get the agent
protocol (:class:`planners.agents.protocol.BaseAgent`): reset for a car of a race, options from
a spec (``lane-keeping:target_speed=20,target_n=1.5``), diagnostics and a braking fallback.
:class:`RandomAgent` has no control law: it draws its actions from a generator seeded at its
reset, a rival whose moves no planner can predict.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from planners.agents.protocol import BaseAgent
from planners.methods import CONSTANT_SPEED, LANE_KEEPING, RACELINE, RANDOM
from planners.scripted import RACELINE_MARGIN, ConstantSpeed, LaneKeeping, RacelineDriver, check_raceline_options, \
    check_targets
from planners.traffic import RACELINE_STANDSTILL, RACELINE_TIME_GAP
from racing_env.observation import cars_racing

__all__ = ["ConstantSpeedAgent", "LaneKeepingAgent", "RacelineAgent", "RandomAgent", "check_random_scale", "random_generator"]


class _ScriptedAgent(BaseAgent):
    """A scripted driver of :mod:`planners.scripted` as an agent: its ``controller_class``
    is built for the car at every reset, with the agent's options."""

    controller_class: type = LaneKeeping

    def __init__(self, **kwargs: Any) -> None:
        super().__init__()
        unknown = sorted(set(kwargs) - set(self.spec_options()))
        if unknown:
            raise ValueError(f"{self.name} has no option {unknown}; its options: {sorted(self.spec_options())}")
        self.check_options(**kwargs)  # before the race, not at the controller's reset
        self.kwargs = kwargs
        self.controller = None

    @staticmethod
    def check_options(**kwargs: Any) -> None:
        check_targets(**kwargs)

    @classmethod
    def spec_options(cls) -> dict[str, type]:
        return {"target_speed": float, "target_n": float}

    @classmethod
    def spec_defaults(cls) -> dict[str, Any]:
        return {"target_speed": "v_max", "target_n": 0.0}

    def reset(self, seed: int | None, index: int, env_info: Any) -> None:
        super().reset(seed, index, env_info)
        self.controller = self.controller_class(
            self.game.track, self.index, self.game.vehicles.car(self.index), **self._controller_kwargs()
        )

    def _controller_kwargs(self) -> dict[str, Any]:
        """The controller's keyword arguments: the agent's options."""
        return dict(self.kwargs)

    def act(self, observation: np.ndarray, joint_state: np.ndarray) -> np.ndarray:
        return self._act_guarded(self.controller, observation, joint_state)


class LaneKeepingAgent(_ScriptedAgent):
    """:class:`planners.scripted.LaneKeeping` (kwargs: ``target_speed``, ``target_n``)."""

    spec = name = LANE_KEEPING
    controller_class = LaneKeeping


class ConstantSpeedAgent(_ScriptedAgent):
    """:class:`planners.scripted.ConstantSpeed` (kwargs: ``target_speed``)."""

    spec = name = CONSTANT_SPEED
    controller_class = ConstantSpeed

    @classmethod
    def spec_options(cls) -> dict[str, type]:
        return {"target_speed": float}

    @classmethod
    def spec_defaults(cls) -> dict[str, Any]:
        return {"target_speed": 15.0}


class RacelineAgent(_ScriptedAgent):
    """:class:`planners.scripted.RacelineDriver`: the circuit's racing line at the speed profile
    of its lap-time limit, keeping to the rules of :mod:`planners.traffic` (kwargs: ``pace``
    in ``(0, 1]``, ``margin`` [m], ``line``, ``time_gap`` [s], ``standstill`` [m], and
    ``yield``: ``False`` is the driver without the rules, which drives its line whoever is on
    it). It reads which cars still race from its observation, as the planners do."""

    spec = name = RACELINE
    controller_class = RacelineDriver

    @staticmethod
    def check_options(**kwargs: Any) -> None:
        check_raceline_options(**_driver_kwargs(kwargs))

    @classmethod
    def spec_options(cls) -> dict[str, type]:
        return {"pace": float, "margin": float, "line": str, "yield": bool, "time_gap": float, "standstill": float}

    @classmethod
    def spec_defaults(cls) -> dict[str, Any]:
        return {"pace": 1.0, "margin": RACELINE_MARGIN, "line": "raceline", "yield": True,
                "time_gap": RACELINE_TIME_GAP, "standstill": RACELINE_STANDSTILL}

    def _controller_kwargs(self) -> dict[str, Any]:
        return {**_driver_kwargs(self.kwargs), "fleet": self.game.vehicles}

    def reset(self, seed: int | None, index: int, env_info: Any) -> None:
        super().reset(seed, index, env_info)
        # the env's nearest-rival observation layout, whose blocks do not say which car is out
        self._observed_rivals = getattr(getattr(env_info, "config", None), "observed_rivals", None)

    def act(self, observation: np.ndarray, joint_state: np.ndarray) -> np.ndarray:
        racing = cars_racing(observation, self.index, self.game.num_players, self._observed_rivals)
        return self._act_guarded(lambda o, x: self.controller(o, x, racing), observation, joint_state)


def _driver_kwargs(options: dict[str, Any]) -> dict[str, Any]:
    """The spec's options as :class:`RacelineDriver` arguments (``yield``, a Python keyword,
    is its ``yielding``)."""
    kwargs = dict(options)
    if "yield" in kwargs:
        kwargs["yielding"] = kwargs.pop("yield")
    return kwargs


def check_random_scale(scale: Any) -> float:
    """``scale`` as a float in ``(0, 1]`` (the fraction of the action box the random driver
    draws from); a ``ValueError`` that says so otherwise."""
    if isinstance(scale, bool) or not isinstance(scale, (int, float, np.integer, np.floating)):
        raise ValueError(f"scale must be a number in (0, 1], got {scale!r}")
    value = float(scale)
    if not (np.isfinite(value) and 0.0 < value <= 1.0):
        raise ValueError(f"scale must be a number in (0, 1] (the fraction of the action box), got {scale!r}")
    return value


def random_generator(seed: int | None, index: int) -> np.random.Generator:
    """The random driver's generator for car ``index`` of a race with episode seed ``seed``:
    ``np.random.default_rng([seed, index])``, so that the same seed replays the same actions
    and two random cars of one race draw different ones; ``seed=None`` draws fresh entropy
    (not reproducible). A seed must be an integer >= 0."""
    if seed is None:
        return np.random.default_rng()
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or int(seed) < 0:
        raise ValueError(f"the random driver's seed must be an integer >= 0 or None, got {seed!r}")
    return np.random.default_rng([int(seed), int(index)])


class RandomAgent(BaseAgent):
    """A driver that acts uniformly at random: each step's action is drawn independently and
    uniformly from ``[-scale, scale]^2`` of the normalised action box (jerks of up to
    ``scale`` times the car's jerk limits [m/s^3]).

    It is the rival no planner can predict: a planner's prediction of it (the game's
    equilibrium, a constant-velocity or lane-keeping model) is wrong at every step, by a
    jerk of up to the car's limit. The draws come from :func:`random_generator` seeded by
    :meth:`reset`'s ``seed`` and the car's index, so a race is reproducible for a seed; the
    batched form (:class:`planners.agents.batched.BatchedRandom`) draws the same numbers in
    each race from the race's seed.

    Args:
        scale: the fraction of the action box, in ``(0, 1]`` (default 1: the whole box).
    """

    spec = name = RANDOM

    def __init__(self, scale: float = 1.0) -> None:
        super().__init__()
        self.scale = check_random_scale(scale)
        self.rng: np.random.Generator | None = None

    @classmethod
    def spec_options(cls) -> dict[str, type]:
        return {"scale": float}

    @classmethod
    def spec_defaults(cls) -> dict[str, Any]:
        return {"scale": 1.0}

    def reset(self, seed: int | None, index: int, env_info: Any) -> None:
        super().reset(seed, index, env_info)
        self.rng = random_generator(seed, self.index)

    def _draw(self, observation: np.ndarray, joint_state: np.ndarray) -> np.ndarray:
        return self.rng.uniform(-self.scale, self.scale, size=2)

    def act(self, observation: np.ndarray, joint_state: np.ndarray) -> np.ndarray:
        return self._act_guarded(self._draw, observation, joint_state)
