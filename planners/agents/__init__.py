"""Competitors: one small protocol for every driver (game planners, scripted drivers, RL policies).

Every agent implements :class:`Agent` (``reset``, ``act``, ``diagnostics``) and is a callable
``agent(observation, joint_state) -> action`` (:mod:`~planners.agents.protocol` shows the loop).

The modules, one job each:

* :mod:`~planners.agents.protocol`: :class:`Agent`, :class:`BaseAgent` (shared bookkeeping),
  :func:`game_of`, :func:`reset_agents`;
* :mod:`~planners.agents.receding_horizon`: :class:`RecedingHorizonAgent` and the planners
  :class:`FeedbackGameAgent`, :class:`OpenLoopGameAgent`, :class:`ILQRAgent`
  (:mod:`~planners.agents.weights`: their beliefs and private cost weights);
* :mod:`~planners.agents.scripted`: :class:`RacelineAgent`, :class:`LaneKeepingAgent`, :class:`ConstantSpeedAgent`,
  :class:`RandomAgent` (uniform random actions, seeded by its reset);
* :mod:`~planners.agents.sb3`: :class:`SB3Agent` (loaded on first use: the RL layer);
* :mod:`~planners.agents.jax_policy`: :class:`JaxPolicyAgent`, a JAX learner's policy
  (flax loaded when one is built);
* :mod:`~planners.agents.registry`: :data:`AGENTS` (name -> class), :func:`make_agent`,
  :func:`check_specs`, :func:`agent_options`, the spec parser and the options' help text;
* :mod:`~planners.agents.batched`: :class:`BatchedOpponent`, one object driving one car in B
  races at once (:func:`make_batched_opponent`; the planners' form in
  :mod:`~planners.agents.batched_planners`), for vectorised race envs.

See docs/agents.md.
"""

from __future__ import annotations

import importlib
from typing import Any

from planners.agents.batched import (
    BatchedOpponent,
    BatchedPool,
    BatchedRandom,
    BatchedSB3,
    BatchedScripted,
    LoopedOpponent,
    make_batched_opponent,
)
from planners.agents.batched_planners import BatchedPlanner
from planners.agents.protocol import Agent, BaseAgent, game_of, reset_agents
from planners.agents.receding_horizon import (
    RECOVERED_SPEED,
    REPLAN_TOLERANCE,
    STOPPED_SPEED,
    FeedbackGameAgent,
    FollowerGameAgent,
    ILQRAgent,
    LeaderGameAgent,
    OpenLoopGameAgent,
    RecedingHorizonAgent,
    StackelbergGameAgent,
)
from planners.agents.registry import (
    AGENT_SPECS,
    AGENT_SUMMARIES,
    AGENTS,
    agent_options,
    check_specs,
    make_agent,
    split_spec,
    split_spec_list,
    with_options,
)
from planners.agents.jax_policy import JaxPolicyAgent
from planners.agents.scripted import ConstantSpeedAgent, LaneKeepingAgent, RacelineAgent, RandomAgent

_SB3_NAMES = ("SB3Agent", "SB3_ALGOS", "VECNORMALIZE_SUFFIX", "vecnormalize_path")

__all__ = [
    "AGENTS",
    "AGENT_SPECS",
    "AGENT_SUMMARIES",
    "Agent",
    "BaseAgent",
    "BatchedOpponent",
    "BatchedPlanner",
    "BatchedPool",
    "BatchedRandom",
    "BatchedSB3",
    "BatchedScripted",
    "ConstantSpeedAgent",
    "FeedbackGameAgent",
    "FollowerGameAgent",
    "ILQRAgent",
    "JaxPolicyAgent",
    "LaneKeepingAgent",
    "LeaderGameAgent",
    "RacelineAgent",
    "RandomAgent",
    "LoopedOpponent",
    "OpenLoopGameAgent",
    "RECOVERED_SPEED",
    "REPLAN_TOLERANCE",
    "RecedingHorizonAgent",
    "SB3Agent",
    "SB3_ALGOS",
    "STOPPED_SPEED",
    "StackelbergGameAgent",
    "VECNORMALIZE_SUFFIX",
    "agent_options",
    "check_specs",
    "game_of",
    "make_agent",
    "make_batched_opponent",
    "reset_agents",
    "split_spec",
    "split_spec_list",
    "vecnormalize_path",
    "with_options",
]


def __getattr__(name: str) -> Any:
    """The RL adapter's names, from :mod:`planners.agents.sb3` on first access."""
    if name in _SB3_NAMES:
        return getattr(importlib.import_module("planners.agents.sb3"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_SB3_NAMES))
