"""The names of the planning methods, defined once.

A method has one name, and it means the same thing everywhere: as an agent spec on the
command line and in config files (``racing tournament --agents ilqgame-fb``), as the
registry key of its agent class (:data:`planners.agents.AGENTS`, whose classes carry it as
their ``spec``), as a belief model of the opponents (``ilqr:prediction=ilqgame-fb``,
:mod:`planners.prediction`) and in the docs (docs/agents.md). The game methods also name the
solver mode they run (:attr:`planners.ilq.SolverOptions.mode`, :data:`GAME_MODES`).

It has no imports of its own, so every module of the package may use it.
"""

from __future__ import annotations

__all__ = [
    "AGENT_METHODS",
    "CONSTANT_SPEED",
    "CONSTANT_VELOCITY",
    "FEEDBACK",
    "FEEDBACK_GAME",
    "GAME_MODES",
    "ILQR",
    "LANE_KEEPING",
    "NASH_MODES",
    "OPEN_LOOP",
    "OPEN_LOOP_GAME",
    "PLANNERS",
    "PREDICTIONS",
    "RACELINE",
    "RANDOM",
    "RL",
    "SOLVER_MODES",
    "STACKELBERG",
    "STACKELBERG_FOLLOWER",
    "STACKELBERG_GAMES",
    "STACKELBERG_LEADER",
]

# Solver modes of the iterative LQ game solver (planners.ilq.SolverOptions.mode).
FEEDBACK = "feedback"
"""Feedback Nash equilibria of the local LQ games: strategies ``u = u_hat - K (x - x_hat)``."""
OPEN_LOOP = "open_loop"
"""Open-loop Nash equilibria of the local LQ games: input sequences ``u_hat``."""
STACKELBERG = "stackelberg"
"""Feedback (stage-wise) Stackelberg solutions of the local LQ games of two players, a leader
(:attr:`planners.ilq.SolverOptions.leader`) and a follower: strategies ``u = u_hat - K (x - x_hat)``."""
NASH_MODES = (FEEDBACK, OPEN_LOOP)
"""The solver modes whose solutions are Nash equilibria (what certificates and landscapes check)."""
SOLVER_MODES = (FEEDBACK, OPEN_LOOP, STACKELBERG)

# Agents (spec names). The strings are user-facing: never rename them.
FEEDBACK_GAME = "ilqgame-fb"
"""Feedback iLQGame, re-planned every step (:class:`planners.FeedbackGameAgent`)."""
OPEN_LOOP_GAME = "ilqgame-ol"
"""Open-loop iLQGame, re-planned every step (:class:`planners.OpenLoopGameAgent`)."""
STACKELBERG_LEADER = "ilqgame-leader"
"""Feedback Stackelberg iLQGame of the car and its nearest rival, the car leading by default
(:class:`planners.LeaderGameAgent`)."""
STACKELBERG_FOLLOWER = "ilqgame-follower"
"""Feedback Stackelberg iLQGame of the car and its nearest rival, the car following by default
(:class:`planners.FollowerGameAgent`)."""
STACKELBERG_GAMES = (STACKELBERG_LEADER, STACKELBERG_FOLLOWER)
"""The leader-follower game methods (agents only, not predictions)."""
ILQR = "ilqr"
"""iLQR against predictions of the opponents (:class:`planners.ILQRAgent`)."""
LANE_KEEPING = "lane-keeping"
"""The scripted lane keeper (:class:`planners.LaneKeepingAgent`)."""
CONSTANT_SPEED = "constant-speed"
"""The scripted constant-speed cruiser (:class:`planners.ConstantSpeedAgent`)."""
RACELINE = "raceline"
"""The scripted racing-line driver (:class:`planners.RacelineAgent`)."""
RANDOM = "random"
"""The random driver (:class:`planners.RandomAgent`): uniform random actions, seeded by its reset."""
RL = "rl"
"""A saved stable-baselines3 policy (:class:`planners.SB3Agent`): specs ``rl:PATH`` or ``rl:ALGO:PATH``."""
AGENT_METHODS = (ILQR, OPEN_LOOP_GAME, FEEDBACK_GAME, STACKELBERG_LEADER, STACKELBERG_FOLLOWER, RACELINE, LANE_KEEPING, CONSTANT_SPEED, RANDOM)
"""The agent names of the registry, in the order help text lists them (``rl:`` specs apart)."""

GAME_MODES = {FEEDBACK_GAME: FEEDBACK, OPEN_LOOP_GAME: OPEN_LOOP}
"""The solver mode each Nash game method runs, as an agent and as a prediction (the
leader-follower agents, :data:`STACKELBERG_GAMES`, run :data:`STACKELBERG`)."""

# Predictions of the opponents (the ``prediction`` option of an iLQR agent).
CONSTANT_VELOCITY = "constant-velocity"
"""The paper's prediction: every opponent at constant speed and lateral offset."""
PREDICTIONS = (CONSTANT_VELOCITY, LANE_KEEPING, ILQR, FEEDBACK_GAME, OPEN_LOOP_GAME)
"""The predictions an iLQR agent can plan against: the constant-velocity model, or a method above
in the opponents' place."""
PLANNERS = (ILQR, FEEDBACK_GAME, OPEN_LOOP_GAME)
"""The predictions that are planned (a solve per prediction), as opposed to rolled out."""
