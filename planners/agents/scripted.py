"""The scripted drivers as agents: the racing-line driver, the lane keeper and the constant-speed
cruiser.

The drivers themselves (their control laws) live in :mod:`planners.scripted`, which the
opponent predictions (:mod:`planners.prediction`) use as well; here they get the agent
protocol (:class:`planners.agents.protocol.BaseAgent`): reset for a car of a race, options from
a spec (``lane-keeping:target_speed=20,target_n=1.5``), diagnostics and a braking fallback.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from planners.agents.protocol import BaseAgent
from planners.methods import CONSTANT_SPEED, LANE_KEEPING, RACELINE
from planners.scripted import RACELINE_MARGIN, ConstantSpeed, LaneKeeping, RacelineDriver, check_raceline_options, \
    check_targets

__all__ = ["ConstantSpeedAgent", "LaneKeepingAgent", "RacelineAgent"]


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
            self.game.track, self.index, self.game.vehicles.car(self.index), **self.kwargs
        )

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
    of its lap-time limit (kwargs: ``pace`` in ``(0, 1]``, ``margin`` [m], ``line``). It does
    not avoid other cars beyond what its tracking controller does."""

    spec = name = RACELINE
    controller_class = RacelineDriver

    @staticmethod
    def check_options(**kwargs: Any) -> None:
        check_raceline_options(**kwargs)

    @classmethod
    def spec_options(cls) -> dict[str, type]:
        return {"pace": float, "margin": float, "line": str}

    @classmethod
    def spec_defaults(cls) -> dict[str, Any]:
        return {"pace": 1.0, "margin": RACELINE_MARGIN, "line": "raceline"}
