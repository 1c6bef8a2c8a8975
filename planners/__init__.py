"""planners: game-theoretic and single-agent planners for the racing arena, in JAX.

Agents race in the environment of :mod:`racing_env`; each is named by one string, the same in
Python, on the command line (``racing tournament --agents ...``) and in the docs::

    import racing_env
    from planners import make_agent, reset_agents
    from racing_env.xla_setup import configure_for_racing

    configure_for_racing()   # float64 (the planners need it) and the commands' XLA settings
    env = racing_env.parallel_env(track="trefoil", num_agents=2)
    agents = [make_agent("ilqgame-fb"), make_agent("ilqr")]   # or FeedbackGameAgent(), ILQRAgent()
    observations, _ = env.reset(seed=0)
    reset_agents(agents, env, seed=0)                           # agent i drives car i
    while env.agents:
        actions = {name: agent(observations[name], env.state())
                   for name, agent in zip(env.possible_agents, agents) if name in env.agents}
        observations, rewards, terminations, truncations, infos = env.step(actions)

=====================  ==============================  ==========================================
name                   class                           what it does
=====================  ==============================  ==========================================
``ilqgame-fb``         :class:`FeedbackGameAgent`      feedback Nash iLQGame, re-planned every step
``ilqgame-ol``         :class:`OpenLoopGameAgent`      open-loop Nash iLQGame, re-planned every step
``ilqgame-leader``     :class:`LeaderGameAgent`        feedback Stackelberg iLQGame with the nearest rival, leading
``ilqgame-follower``   :class:`FollowerGameAgent`      the same, following (``role=auto``: the car ahead leads)
``ilqr``               :class:`ILQRAgent`              iLQR against predictions of the opponents
``raceline``           :class:`RacelineAgent`          scripted: the racing line at the lap-time limit
``lane-keeping``       :class:`LaneKeepingAgent`       scripted: an offset at a cruise speed
``constant-speed``     :class:`ConstantSpeedAgent`     scripted: the centre line at a constant speed
``random``             :class:`RandomAgent`            uniform random actions, seeded by its reset
``rl:PATH``            :class:`SB3Agent`               a saved stable-baselines3 policy
``rl:PATH.npz``        :class:`JaxPolicyAgent`         a policy saved by the JAX learner
=====================  ==============================  ==========================================

For vectorised race envs, :func:`make_batched_opponent` makes one :class:`BatchedOpponent`
that drives one car in B races of the same game at once (``opponent.act(observations, x,
racing) -> (actions (B, 2), diagnostics)``), from the same specs or a list of them (a pool).

A spec may carry options, ``"ilqgame-fb:max_iterations=100,c_collision=1"``
(:func:`agent_options` lists them); :data:`AGENTS` maps each name to its class, whose
``spec`` attribute is that name (the names themselves: :mod:`planners.methods`). Every agent
implements :class:`Agent` (``reset``, ``act``, ``diagnostics``). ``SB3Agent`` loads
stable-baselines3 (and torch) when it is first used, not at ``import planners``.

The solvers take a game (a :class:`racing_env.RaceGame`, or any :class:`GameProblem`) and a
joint start state ``x0 (N, 6)``::

    from racing_env.scenarios import paper_game
    from planners import nash_residual, solve

    game, x0 = paper_game()                          # the paper's overtaking scene
    result = solve(game, x0, mode="feedback")        # SolverResult: xs (T+1, N, 6), us (T, N, 2), K, ...
    nash_residual(game, x0, result.us)               # (N,): |dJ^i/du^i|, ~0 at an open-loop equilibrium
    certify(game, x0, result, "feedback").verdict    # "local Nash equilibrium", "saddle" or "not stationary"

:func:`solve` is the iterative LQ game solver (feedback or open-loop Nash, options in
:class:`SolverOptions`), :func:`solve_batch` solves many start states in one compiled call,
:func:`solve_ilqr` is the sequential baseline (one player against predictions), and
:func:`solve_feedback` / :func:`solve_open_loop` solve LQ games exactly.
:func:`problem_from_race_game` is the racing game's Gauss-Newton form as a :class:`GameProblem`.
:func:`certify` tells a local Nash equilibrium from a saddle (second-order conditions and
best responses, :mod:`planners.certificates`); :func:`find_equilibria` solves a scene from many
starts and certifies every distinct solution (:mod:`planners.landscape`).

Importing ``planners`` changes nothing in JAX. The solvers, the certificates and the game
agents need 64-bit floats and refuse to run without them (a ``RuntimeError`` that says how to
turn them on); :func:`racing_env.xla_setup.configure_for_racing`, at the top of a script and
before the first JAX computation, sets them with the rest of what the ``racing`` commands use
(the solvers' loops compiled as single XLA:CPU kernels, inline dispatch). See
docs/solvers.md and docs/agents.md.
"""

from __future__ import annotations

import importlib
from typing import Any

from planners.agents import (
    AGENTS,
    Agent,
    BaseAgent,
    BatchedOpponent,
    ConstantSpeedAgent,
    FeedbackGameAgent,
    FollowerGameAgent,
    ILQRAgent,
    JaxPolicyAgent,
    LaneKeepingAgent,
    LeaderGameAgent,
    OpenLoopGameAgent,
    RacelineAgent,
    RandomAgent,
    agent_options,
    make_agent,
    make_batched_opponent,
    reset_agents,
)
from planners.certificates import Certificate, certify
from planners.game_problem import GameProblem
from planners.ilq import SolverOptions, SolverResult, solve
from planners.ilq_batch import solve_batch
from planners.ilqr import solve_ilqr
from planners.landscape import find_equilibria
from planners.lq_game import solve_feedback, solve_open_loop
from planners.nash import nash_residual
from planners.race_problem import problem_from_race_game  # also lets the solvers take a RaceGame

__all__ = [
    "AGENTS",
    "Agent",
    "BaseAgent",
    "BatchedOpponent",
    "Certificate",
    "ConstantSpeedAgent",
    "FeedbackGameAgent",
    "FollowerGameAgent",
    "GameProblem",
    "ILQRAgent",
    "JaxPolicyAgent",
    "LaneKeepingAgent",
    "LeaderGameAgent",
    "OpenLoopGameAgent",
    "RacelineAgent",
    "RandomAgent",
    "SB3Agent",
    "SolverOptions",
    "SolverResult",
    "agent_options",
    "certify",
    "find_equilibria",
    "make_agent",
    "make_batched_opponent",
    "nash_residual",
    "problem_from_race_game",
    "reset_agents",
    "solve",
    "solve_batch",
    "solve_feedback",
    "solve_ilqr",
    "solve_open_loop",
]


def __getattr__(name: str) -> Any:
    """``SB3Agent`` on first access: the RL layer is loaded only where it is used."""
    if name == "SB3Agent":
        return importlib.import_module("planners.agents.sb3").SB3Agent
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | {"SB3Agent"})
