"""First-order Nash checks of a solution: every player's gradient of its own total cost.

At an open-loop Nash equilibrium no player can lower its total cost ``J^i`` by changing its
own input sequence ``u^i`` alone, so ``dJ^i/du^i = 0`` for every player (the first-order
condition; a saddle point satisfies it too). A feedback equilibrium generally does not
satisfy it when the players interact. The gradients are taken with ``jax.jacrev``
(reverse mode) through the rollout: for a :class:`racing_env.RaceGame` through
``RaceGame.rollout`` and ``RaceGame.costs``, independent of the solver's problem functions.
"""

from __future__ import annotations

import functools
from typing import Callable

import jax
import jax.numpy as jnp

from planners.game_problem import GameProblem, as_problem, game_type_of, rollout, total_costs

Array = jax.Array

__all__ = ["costs_of_inputs", "nash_residual", "own_gradient_norms", "own_gradients"]


def costs_of_inputs(problem: GameProblem, x0: Array) -> Callable[[Array], Array]:
    """``us (T, N, m) -> (N,)`` every player's total cost of the rollout from ``x0 (n,)``."""
    return lambda us: total_costs(problem, rollout(problem, x0, us), us)


def own_gradients(G: Array) -> Array:
    """``G (N, T, N, m)`` = dJ^i/du^j -> ``(N, T, m)``, every player's dJ^i/du^i."""
    idx = jnp.arange(G.shape[0])
    return G[idx, :, idx, :]


def own_gradient_norms(G: Array) -> Array:
    """``G (N, T, N, m)`` = dJ^i/du^j -> ``(N,)`` norms of dJ^i/du^i."""
    return jnp.sqrt(jnp.sum(own_gradients(G) ** 2, axis=(1, 2)))


def _problem_costs(problem: GameProblem, x0: Array, us: Array) -> Array:
    return costs_of_inputs(problem, x0)(us)


@functools.partial(jax.jit, static_argnums=0)
def _residual(costs: Callable, params, x0: Array, us: Array) -> Array:
    """Own-gradient norms of ``costs(params, x0, us) (N,)`` with respect to ``us``."""
    return own_gradient_norms(jax.jacrev(lambda U: costs(params, x0, U))(us))


def nash_residual(problem_or_game, x0, us) -> Array:
    """First-order open-loop Nash residual: ``|| dJ^i / du^i ||_2`` for every player, ``(N,)``.

    ``J^i(u)`` is player i's total cost of the trajectory simulated from ``x0`` with the
    joint inputs ``us (T, N, m)`` (an array or a result with ``us``); the gradient w.r.t.
    its own input sequence is taken in reverse mode through the rollout. For a RaceGame
    this goes through ``RaceGame.rollout`` and ``RaceGame.costs`` (``x0 (N, 6)``). It
    vanishes at an open-loop Nash equilibrium (and at its iLQ fixed point); a feedback
    equilibrium generally does not satisfy it when the players interact.
    """
    us = jnp.asarray(getattr(us, "us", us))
    game_type = game_type_of(problem_or_game)
    if game_type is not None and game_type.costs_of_inputs is not None:
        return _residual(game_type.costs_of_inputs, problem_or_game, jnp.asarray(x0, us.dtype), us)
    problem, _ = as_problem(problem_or_game)
    return _residual(_problem_costs, problem, jnp.asarray(x0, us.dtype).reshape(-1), us)
