"""A random LQ game written through the GameProblem protocol, for the solver and certificate tests.

``random_lq_game(seed)`` returns ``(problem, params, x0, us0)``: linear dynamics
``x_{t+1} = A_t x_t + sum_j B^j_t u^j_t``, every player's cost quadratic with a positive
semi-definite state weight ``Q`` and a positive definite own input weight ``R^ii``, so both
Nash equilibria (feedback and open loop) are unique and the solvers' first full step lands
on them.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from planners import ilq


def _lq_dynamics(p, t, x, u):
    return p["A"][t] @ x + jnp.einsum("jam,jm->a", p["B"][t], u)


def _lq_stage_cost(p, t, i, x, u_i):
    Q, q, R, r = p["Q"][t, i], p["q"][t, i], p["R"][t, i, i], p["r"][t, i, i]
    return 0.5 * x @ Q @ x + q @ x + 0.5 * u_i @ R @ u_i + r @ u_i


def _lq_terminal_cost(p, i, x):
    T = p["A"].shape[0]
    return 0.5 * x @ p["Q"][T, i] @ x + p["q"][T, i] @ x


def random_lq_game(seed: int, T: int = 6, N: int = 2, n: int = 4, m: int = 2):
    rng = np.random.default_rng(seed)
    A = np.eye(n) + 0.2 * rng.standard_normal((T, n, n))
    B = 0.5 * rng.standard_normal((T, N, n, m))
    L = rng.standard_normal((T + 1, N, n, n))
    Q = np.einsum("tiab,ticb->tiac", L, L) / n  # PSD
    q = rng.standard_normal((T + 1, N, n))
    R = np.zeros((T, N, N, m, m))
    r = np.zeros((T, N, N, m))
    for i in range(N):
        M = rng.standard_normal((T, m, m))
        R[:, i, i] = np.einsum("tab,tcb->tac", M, M) + np.eye(m)
        r[:, i, i] = rng.standard_normal((T, m))
    params = {k: jnp.asarray(v) for k, v in dict(A=A, B=B, Q=Q, q=q, R=R, r=r).items()}
    problem = ilq.GameProblem(
        dynamics=_lq_dynamics,
        stage_cost=_lq_stage_cost,
        terminal_cost=_lq_terminal_cost,
        num_players=N,
        state_dim=n,
        input_dim=m,
        horizon=T,
        params=params,
    )
    x0 = jnp.asarray(rng.standard_normal(n))
    us0 = jnp.asarray(3.0 * rng.standard_normal((T, N, m)))  # an arbitrary start
    return problem, params, x0, us0
