"""The game protocol of the iterative LQ solvers: :class:`GameProblem`, and game types.

A :class:`GameProblem` is an N-player discrete-time game written as pure functions of a
pytree ``params``. The solvers (:mod:`planners.ilq`, :mod:`planners.ilq_batch`,
:mod:`planners.nash`) know only this protocol. Other game types (a
:class:`racing_env.RaceGame`) become problems through a converter that their adapter
module registers with :func:`register_game_type` (:mod:`planners.race_problem`), so the
solvers accept such games directly without importing them.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import jax
import jax.numpy as jnp

Array = jax.Array

__all__ = [
    "GameProblem",
    "GameType",
    "as_problem",
    "game_type_of",
    "is_concrete",
    "register_game_type",
    "rollout",
    "total_costs",
]


@dataclasses.dataclass(frozen=True)
class GameProblem:
    """An N-player discrete-time game for :func:`planners.ilq.solve` (a pytree: ``params`` is its data).

    The functions are static and receive ``params`` as their first argument, so new
    weights or new initial states re-use the compiled solver::

        dynamics(params, t, x, u) -> x_next        x (n,), u (N, m), t int stage index
        stage_cost(params, t, i, x, u_i) -> scalar  player i's g_t^i; depends on its own input only
        terminal_cost(params, i, x) -> scalar       player i's g_T^i

    Attributes:
        dynamics: ``(params, t, x (n,), u (N, m)) -> (n,)``.
        stage_cost: ``(params, t, i, x (n,), u_i (m,)) -> ()``, player ``i``'s stage cost.
        terminal_cost: ``(params, i, x (n,)) -> ()``.
        num_players, state_dim, input_dim, horizon: ``N, n, m, T`` (static ints).
        params: pytree of arrays passed to the functions (traced inside the solver).
        stage_gauss_newton: optional ``(params, t, i, x, u_i) -> (r (k,), g (k,), h (k,))``:
            player i's stage cost written as ``sum_k rho_k(r_k(x, u_i))`` with scalar outer
            functions ``rho_k``; ``g_k = rho_k'(r_k)`` and a curvature weight ``h_k >= 0``
            (``rho_k''(r_k)`` where that is non-negative). Enables the Gauss-Newton
            quadratisation (:func:`planners.local_game.quadratize`); ``g`` and ``h`` are not differentiated.
        terminal_gauss_newton: optional ``(params, i, x) -> (r, g, h)``, the same for
            ``terminal_cost`` (both hooks are needed for Gauss-Newton).
        stage_curvature: optional ``(params, t, i, x) -> (n,)``: a diagonal curvature
            (``>= 0``; negative entries are clipped) that player i's local game at stage t
            should have in the state but that quadratising its costs misses, because iLQ
            drops the dynamics' second derivatives (e.g. the curvature of a linear terminal
            reward through the dynamics; RaceGame:
            :func:`planners.race_problem.race_stage_curvature`). Added to the diagonal of
            ``Q_t^i`` (``SolverOptions.dynamics_curvature``); the gradients, and so the
            open-loop fixed points, stay those of the costs.
        dynamics_jacobians: optional ``(params, t, x, u) -> (A (n, n), B (n, N, m))``, the
            Jacobians of ``dynamics`` (e.g. exploiting structure); default ``jax.jacfwd``.

    The functions are compared by identity for jit caching: define them once (module
    level), not as fresh lambdas per call, to avoid recompiling.
    """

    dynamics: Callable[..., Array]
    stage_cost: Callable[..., Array]
    terminal_cost: Callable[..., Array]
    num_players: int
    state_dim: int
    input_dim: int
    horizon: int
    params: Any = None
    stage_gauss_newton: Callable[..., tuple[Array, Array, Array]] | None = None
    terminal_gauss_newton: Callable[..., tuple[Array, Array, Array]] | None = None
    dynamics_jacobians: Callable[..., tuple[Array, Array]] | None = None
    stage_curvature: Callable[..., Array] | None = None

    @property
    def has_gauss_newton(self) -> bool:
        return self.stage_gauss_newton is not None and self.terminal_gauss_newton is not None

    def replace(self, **changes) -> "GameProblem":
        return dataclasses.replace(self, **changes)


jax.tree_util.register_dataclass(
    GameProblem,
    data_fields=["params"],
    meta_fields=[
        "dynamics",
        "stage_cost",
        "terminal_cost",
        "num_players",
        "state_dim",
        "input_dim",
        "horizon",
        "stage_gauss_newton",
        "terminal_gauss_newton",
        "dynamics_jacobians",
        "stage_curvature",
    ],
)


def rollout(problem: GameProblem, x0: Array, us: Array) -> Array:
    """Simulate ``us (T, N, m)`` from ``x0 (n,)``: ``xs (T+1, n)``."""
    params = problem.params

    def body(x, inp):
        t, u = inp
        x_next = problem.dynamics(params, t, x, u)
        return x_next, x_next

    ts = jnp.arange(us.shape[0])
    _, xs = jax.lax.scan(body, x0, (ts, us))
    return jnp.concatenate([x0[None], xs], axis=0)


def total_costs(problem: GameProblem, xs: Array, us: Array) -> Array:
    """Total cost of every player along ``xs (T+1, n)``, ``us (T, N, m)``: ``(N,)``."""
    params = problem.params
    players = jnp.arange(problem.num_players)
    ts = jnp.arange(us.shape[0])

    def stage(t, x, u):
        return jax.vmap(lambda i, u_i: problem.stage_cost(params, t, i, x, u_i))(players, u)

    running = jax.vmap(stage)(ts, xs[:-1], us).sum(axis=0)
    terminal = jax.vmap(lambda i: problem.terminal_cost(params, i, xs[-1]))(players)
    return running + terminal


# --------------------------------------------------------------------------------------
# Game types that the solvers accept in place of a GameProblem.
# --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class GameType:
    """How the solvers treat a registered game type (see :func:`register_game_type`).

    Attributes:
        to_problem: ``game -> GameProblem``; the solvers return states in the game's own
            shape (``state_shape``), flattened to ``(n,)`` inside.
        state_shape: ``game -> tuple``, the shape of one joint state in the game's layout
            (RaceGame: ``(N, 6)``).
        validate: optional ``(game, control_regularization) -> None`` raising ValueError
            when the game's own-input Hessians ``R^{ii}`` (plus that regularisation) are
            not positive definite; it may return without checking a traced game.
        costs_of_inputs: optional ``(game, x0, us (T, N, m)) -> (N,)``, every player's total
            cost of the inputs from ``x0`` (game layout) by the game's own simulation:
            :func:`planners.nash.nash_residual` differentiates it (an oracle independent of
            the solver's problem functions). Default: the converted problem's.
    """

    to_problem: Callable[[Any], GameProblem]
    state_shape: Callable[[Any], tuple[int, ...]]
    validate: Callable[[Any, float], None] | None = None
    costs_of_inputs: Callable[[Any, Array, Array], Array] | None = None


# The game types planners ships register on import (``import planners`` imports
# planners.race_problem, which registers racing_env.RaceGame).
_GAME_TYPES: dict[type, GameType] = {}


def register_game_type(cls: type, game_type: GameType) -> None:
    """Let the solvers accept instances of ``cls`` (and its subclasses) as games."""
    _GAME_TYPES[cls] = game_type


def game_type_of(obj) -> GameType | None:
    """The :class:`GameType` registered for ``obj``'s class (or a base class); ``None``
    for a :class:`GameProblem` or an unregistered object."""
    if isinstance(obj, GameProblem):
        return None
    return next((_GAME_TYPES[cls] for cls in type(obj).__mro__ if cls in _GAME_TYPES), None)


def is_concrete(*trees: Any) -> bool:
    """Whether every leaf of ``trees`` is at hand (no tracer inside jit or vmap): checks that
    read values run only then."""
    return not any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(trees))


def as_problem(problem_or_game) -> tuple[GameProblem, GameType | None]:
    """``(problem, game_type)``: a :class:`GameProblem` as it is (``game_type`` None), or a
    registered game converted by its :class:`GameType`.

    Raises:
        TypeError: for anything else.
    """
    if isinstance(problem_or_game, GameProblem):
        return problem_or_game, None
    game_type = game_type_of(problem_or_game)
    if game_type is None:
        raise TypeError(
            f"expected a GameProblem or a registered game type (e.g. racing_env.RaceGame), "
            f"got {type(problem_or_game).__name__}"
        )
    return game_type.to_problem(problem_or_game), game_type
