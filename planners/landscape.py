"""The equilibrium landscape of a scene: many solves from seeded starts, clustered and certified.

A game has as many stationary points as its cost landscape allows, and which one a solve
lands on depends on its initial inputs. :func:`find_equilibria` solves the scene from
``starts`` initial input sequences as one batch (:func:`planners.ilq_batch.solve_batch`),
groups the converged solutions whose trajectories agree within ``cluster_tolerance``, and
certifies one member of each group (:func:`planners.certificates.certify`). The share of the
starts that reached a solution is a rough measure of its basin of attraction under that
solver; it is not a probability that players would play it.

The initial input sequences (:func:`initial_guesses`), ``(starts, T, N, m)``:

1. zero inputs (the paper's initialisation);
2. structured pulses: for every input channel ``d`` and every sign pattern
   ``s in {-1, 0, +1}^N`` other than zero, player ``j`` applies ``+s_j a`` for the first
   fifth of the horizon and ``-s_j a`` for the second fifth (a shift that straightens out
   again; on the racing game channel 1 is the lateral jerk, so these are lane changes of
   every combination of cars and directions);
3. seeded Gaussian inputs with standard deviation ``random_scale``, for the rest.

Structured guesses come first and are cut off when ``starts`` is smaller than their number
(``1 + m (3^N - 1)``: 17 for two cars).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from planners import methods
from planners.certificates import Certificate, CertificateTolerances, certify
from planners.game_problem import as_problem

__all__ = ["Equilibrium", "Landscape", "cluster_trajectories", "find_equilibria", "initial_guesses"]


@dataclasses.dataclass(frozen=True)
class Equilibrium:
    """One distinct converged solution of a landscape.

    Attributes:
        xs: ``(T+1, ...)`` its trajectory (the game's state layout, e.g. ``(T+1, N, 6)``).
        us: ``(T, N, m)`` its inputs.
        costs: ``(N,)`` every player's total cost.
        count: how many starts converged to it; ``share`` = ``count / starts``.
        share: fraction of all starts.
        starts: the indices of those starts (into :func:`initial_guesses`).
        certificate: :class:`planners.certificates.Certificate` of its first member.
        spread: largest state difference [state units] between its members and the first.
    """

    xs: np.ndarray
    us: np.ndarray
    costs: np.ndarray
    count: int
    share: float
    starts: tuple[int, ...]
    certificate: Certificate
    spread: float

    def as_dict(self, trajectories: bool = True) -> dict[str, Any]:
        out = {"share": self.share, "count": self.count, "starts": list(self.starts), "spread": self.spread,
               "costs": self.costs.tolist(), "certificate": self.certificate.as_dict()}
        if trajectories:
            out.update(xs=self.xs.tolist(), us=self.us.tolist())
        return out


@dataclasses.dataclass(frozen=True)
class Landscape:
    """What :func:`find_equilibria` found.

    Attributes:
        mode: ``"open_loop"`` or ``"feedback"``.
        starts: number of initial guesses solved.
        seed: seed of the random guesses.
        kinds: ``(starts,)`` ``"zero"``, ``"pulse"`` or ``"random"`` per start.
        converged: ``(starts,)`` bool, per start.
        labels: ``(starts,)`` the index into ``equilibria`` of each start's solution, -1 where
            the solve did not converge.
        equilibria: the distinct solutions, most frequent first.
    """

    mode: str
    starts: int
    seed: int
    kinds: tuple[str, ...]
    converged: np.ndarray
    labels: np.ndarray
    equilibria: tuple[Equilibrium, ...]

    @property
    def converged_share(self) -> float:
        return float(np.mean(self.converged))

    def share_with_verdict(self, verdict: str) -> float:
        """Fraction of all starts that reached a solution certified with ``verdict``."""
        return float(sum(e.share for e in self.equilibria if e.certificate.verdict == verdict))

    def as_dict(self, trajectories: bool = True) -> dict[str, Any]:
        return {"mode": self.mode, "starts": self.starts, "seed": self.seed, "converged_share": self.converged_share,
                "kinds": list(self.kinds), "labels": self.labels.tolist(),
                "equilibria": [e.as_dict(trajectories) for e in self.equilibria]}


def initial_guesses(horizon: int, num_players: int, input_dim: int, starts: int, seed: int = 0,
                    amplitude: float = 2.0, random_scale: float = 0.5) -> tuple[np.ndarray, tuple[str, ...]]:
    """``(guesses (starts, T, N, m), kinds)``: zero, structured pulses, then seeded random
    inputs (see the module docstring). ``amplitude`` and ``random_scale`` are in input units
    (racing game: m/s^3)."""
    if starts < 1:
        raise ValueError(f"starts must be >= 1, got {starts}")
    T, N, m = horizon, num_players, input_dim
    guesses, kinds = [np.zeros((T, N, m))], ["zero"]
    fifth = max(T // 5, 1)
    for d in range(m):
        for signs in np.ndindex(*(3,) * N):
            s = np.asarray(signs) - 1
            if not s.any():
                continue
            u = np.zeros((T, N, m))
            u[:fifth, :, d] = amplitude * s
            u[fifth:2 * fifth, :, d] = -amplitude * s
            guesses.append(u)
            kinds.append("pulse")
    guesses, kinds = guesses[:starts], kinds[:starts]
    rest = starts - len(guesses)
    if rest:
        guesses.extend(random_scale * np.random.default_rng(seed).standard_normal((rest, T, N, m)))
        kinds.extend(["random"] * rest)
    return np.stack(guesses), tuple(kinds)


def cluster_trajectories(xs: np.ndarray, mask: np.ndarray, tolerance: float) -> np.ndarray:
    """Greedy clustering of ``xs (B, T+1, ...)``: each masked member joins the first cluster
    whose first member differs from it by at most ``tolerance`` in every state entry at
    every stage, else starts a new one. Returns labels ``(B,)`` (-1 where ``mask`` is False),
    clusters numbered in order of their first member."""
    flat = np.asarray(xs, float).reshape(len(xs), -1)
    labels = np.full(len(flat), -1)
    heads: list[int] = []
    for b in np.flatnonzero(mask):
        for label, head in enumerate(heads):
            if np.max(np.abs(flat[b] - flat[head])) <= tolerance:
                labels[b] = label
                break
        else:
            labels[b] = len(heads)
            heads.append(b)
    return labels


def find_equilibria(problem_or_game, x0, mode: str = methods.OPEN_LOOP, starts: int = 64, seed: int = 0, *,
                    options=None, cluster_tolerance: float = 0.05, tolerances: CertificateTolerances | None = None,
                    checks: str = "full", amplitude: float = 2.0, random_scale: float = 0.5,
                    **overrides) -> Landscape:
    """Solve a scene from ``starts`` initial guesses, cluster and certify what converged.

    Args:
        problem_or_game: a :class:`planners.game_problem.GameProblem` or a RaceGame.
        x0: the start state (``(n,)``, or the game's layout, e.g. ``(N, 6)``).
        mode: ``"open_loop"`` or ``"feedback"``.
        starts, seed: number of initial guesses and the seed of the random ones
            (:func:`initial_guesses`, with ``amplitude`` and ``random_scale``).
        options, overrides: :class:`planners.ilq.SolverOptions` and field overrides of the
            solves (e.g. the paper's algorithm: ``convexify="none", step_control="none",
            initial_step=0.1, dynamics_curvature=False``).
        cluster_tolerance: solutions whose trajectories differ by at most this much in
            every state entry [state units: m, m/s, rad, ...] are one solution.
        tolerances, checks: of the certificates (:func:`planners.certificates.certify`).

    Returns:
        :class:`Landscape`; deterministic for a seed.
    """
    from planners import ilq
    from planners.ilq_batch import solve_batch

    if mode not in methods.NASH_MODES:
        raise ValueError(f"mode must be one of {methods.NASH_MODES}, got {mode!r}")
    if not cluster_tolerance >= 0:
        raise ValueError(f"cluster_tolerance must be >= 0, got {cluster_tolerance!r}")
    problem, _ = as_problem(problem_or_game)
    options = ilq.resolve_options(options, {**overrides, "mode": mode})
    guesses, kinds = initial_guesses(problem.horizon, problem.num_players, problem.input_dim, starts, seed,
                                     amplitude, random_scale)
    x0 = np.asarray(x0, float)
    batch = solve_batch(problem_or_game, np.repeat(x0[None], starts, axis=0), guesses, options=options)
    batch = ilq.SolverResult(*(np.asarray(leaf) for leaf in batch))
    xs, us = batch.xs, batch.us
    converged = batch.converged
    labels = cluster_trajectories(xs, converged, cluster_tolerance)
    found = []
    for label in range(labels.max() + 1):
        members = np.flatnonzero(labels == label)
        head = members[0]
        solution = ilq.SolverResult(*(leaf[head] for leaf in batch))
        certificate = certify(problem_or_game, x0, solution, mode, checks=checks, tolerances=tolerances)
        spread = float(np.max(np.abs(xs[members] - xs[head])))
        found.append(Equilibrium(xs[head], us[head], batch.costs[head], len(members),
                                 len(members) / starts, tuple(int(b) for b in members), certificate, spread))
    order = sorted(range(len(found)), key=lambda k: (-found[k].count, found[k].starts[0]))
    relabel = np.full(len(found) + 1, -1)  # the last entry keeps -1 for the unconverged (label -1)
    relabel[order] = np.arange(len(found))
    return Landscape(mode, starts, seed, kinds, converged, relabel[labels], tuple(found[k] for k in order))
