"""The batched opponents' protocol: :class:`BatchedOpponent`, the base class of every
driver of one car in B races at once, and the per-race diagnostics each returns
(:data:`DIAGNOSTIC_FIELDS`, :func:`empty_diagnostics`).

The implementations build on it: the scripted, SB3, pool and looped opponents in
:mod:`planners.agents.batched` (with :func:`planners.agents.batched.make_batched_opponent`)
and the receding-horizon planners in :mod:`planners.agents.batched_planners`. It imports
neither of them.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from planners.agents.protocol import BaseAgent, game_of

__all__ = ["BatchedOpponent", "DIAGNOSTIC_FIELDS", "empty_diagnostics"]

DIAGNOSTIC_FIELDS: dict[str, type] = {
    "replanned": bool,  # a solve was made for the race this step
    "converged": bool,  # that solve met its tolerance
    "iterations": np.int64,  # that solve's iterations (0 without one)
    "fallback": bool,  # the action is a fallback: the previous plan, or braking
    "brake": bool,  # the action is the braking fallback
}
"""The per-race diagnostics every batched opponent returns, ``{name: dtype}``; each array
is ``(B,)``, zero (False) for races that the step did not concern."""


class BatchedOpponent:
    """Drives car ``index`` in ``num_races`` races of one game (the base class).

    Subclasses implement :meth:`_act_rows` (and :meth:`_reset_rows` if they keep per-race
    state); the checks, the races in which the car is no longer racing and the braking
    fallback are here.

    Attributes:
        spec: the agent spec it was made from (a pool: ``"pool(spec; spec; ...)"``).
        index: the car it drives (row of the joint state).
        num_races: B.
        game: the races' :class:`racing_env.RaceGame`.
        jax_policy: a pure JAX ``policy(x (N, 6)) -> action (2,)`` for drivers that are one
            (scripted), else None.
        jax_planner: for planners, their step as pure JAX functions of a plan state
            (:class:`planners.agents.compiled_planner.CompiledPlanner`), else None.
        diagnostic_fields: ``{name: dtype}`` of the diagnostics :meth:`act` returns.
    """

    jax_policy: Callable | None = None
    jax_planner: Any = None
    diagnostic_fields: dict[str, type] = DIAGNOSTIC_FIELDS

    def __init__(self, spec: str, game: Any, index: int, num_races: int) -> None:
        self.game = game_of(game)
        n = self.game.num_players
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not 0 <= index < n:
            raise ValueError(f"index must be a car index in [0, {n}), got {index!r}")
        if isinstance(num_races, bool) or not isinstance(num_races, (int, np.integer)) or num_races < 1:
            raise ValueError(f"num_races must be an integer >= 1, got {num_races!r}")
        self.spec = str(spec)
        self.index = int(index)
        self.num_races = int(num_races)
        self._started = np.zeros(self.num_races, dtype=bool)
        self._brake_law = BaseAgent()  # the single agents' braking fallback, for this car
        self._brake_law.reset(None, self.index, self.game)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(spec={self.spec!r}, index={self.index}, num_races={self.num_races})"

    # --- the interface --------------------------------------------------------------------
    def reset(self, races: np.ndarray, seeds: np.ndarray) -> None:
        """(Re)start the races flagged in ``races (B,)`` bool; ``seeds (B,)`` int64 are the
        races' episode seeds (a pool draws each race's driver from its own). The races'
        plans are forgotten; the others are untouched. Every race must be started once
        before :meth:`act`."""
        races = self._checked(races, "races", (self.num_races,), bool)
        seeds = self._checked(seeds, "seeds", (self.num_races,), np.int64)
        rows = np.flatnonzero(races)
        self._started[rows] = True
        if rows.size:
            self._reset_rows(rows, seeds[rows])

    def act(self, observations: np.ndarray, x: np.ndarray,
            racing: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Actions for every race.

        Args:
            observations: ``(B, obs_dim)``, this car's env observation in each race.
            x: ``(B, N, 6)`` joint states ``[s, V, n, chi, ax, ay]``.
            racing: ``(B, N)`` bool, the cars still racing. A race in which this car's own
                entry is False is idle: its action is zero and nothing of it changes.

        Returns:
            ``actions (B, 2)`` float64 in ``[-1, 1]`` (normalised jerks, never NaN) and
            ``{name: (B,)}`` diagnostics (:attr:`diagnostic_fields`).
        """
        return run_steps(self.act_steps(observations, x, racing), self._solve_request)

    @classmethod
    def act_together(cls, opponents: list["BatchedOpponent"], observations: list[np.ndarray], x: np.ndarray,
                     racing: np.ndarray) -> list[tuple[np.ndarray, dict[str, np.ndarray]]]:
        """:meth:`act` of several cars of the same races (``opponents`` of this class, each
        with its ``observations``), in car order. The base class acts for each in turn; a
        subclass may share work between them (the planners solve their re-plans together)."""
        return [opponent.act(obs, x, racing) for opponent, obs in zip(opponents, observations)]

    def act_steps(self, observations: np.ndarray, x: np.ndarray, racing: np.ndarray):
        """:meth:`act` as a generator: it may yield one solve request (what
        :meth:`_solve_request` takes), receives its solution (or the exception the solve
        raised), and returns ``(actions, diagnostics)``. Lets a caller solve the requests
        of several cars together (:meth:`act_together`)."""
        observations, x, racing = self._checked_step(observations, x, racing)
        if not self._started.all():
            missing = np.flatnonzero(~self._started)[:5].tolist()
            raise RuntimeError(f"reset(races, seeds) must start every race before act; races {missing}... were never "
                               "started")
        actions = np.zeros((self.num_races, 2))
        diagnostics = empty_diagnostics(self.diagnostic_fields, self.num_races)
        rows = np.flatnonzero(racing[:, self.index])
        if rows.size == self.num_races:  # the usual case: no copies
            return (yield from self._act_rows_steps(rows, observations, x, racing))
        if rows.size:
            part, part_diagnostics = yield from self._act_rows_steps(rows, observations[rows], x[rows], racing[rows])
            actions[rows] = part
            for name, values in part_diagnostics.items():
                diagnostics[name][rows] = values
        return actions, diagnostics

    # --- for subclasses -------------------------------------------------------------------
    def _reset_rows(self, rows: np.ndarray, seeds: np.ndarray) -> None:
        """Forget the plans of the races ``rows (R,)`` (global race indices)."""

    def _act_rows(self, rows: np.ndarray, observations: np.ndarray, x: np.ndarray,
                  racing: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Actions ``(R, 2)`` and diagnostics ``{name: (R,)}`` of the races ``rows (R,)``,
        whose observations, states and racing flags are given (``(R, ...)``)."""
        raise NotImplementedError

    def _act_rows_steps(self, rows: np.ndarray, observations: np.ndarray, x: np.ndarray, racing: np.ndarray):
        """:meth:`_act_rows` as a generator (:meth:`act_steps`); by default it asks for no solve."""
        return self._act_rows(rows, observations, x, racing)
        yield  # noqa: unreachable - makes this a generator that yields nothing

    def _solve_request(self, request: Any) -> Any:
        """The solution of a request :meth:`_act_rows_steps` yielded (subclasses that yield)."""
        raise NotImplementedError

    def _finish(self, actions: np.ndarray, x: np.ndarray, diagnostics: dict[str, np.ndarray]) -> np.ndarray:
        """``actions (R, 2)`` with every non-finite row replaced by the single agents' braking
        action (flagged ``fallback`` and ``brake``), clipped to ``[-1, 1]``."""
        actions = np.array(actions, dtype=np.float64)
        bad = ~np.all(np.isfinite(actions), axis=1)
        for r in np.flatnonzero(bad):
            actions[r] = self._brake_law._safe_action(x[r])
        diagnostics["fallback"] |= bad
        diagnostics["brake"] |= bad
        return np.clip(actions, -1.0, 1.0)

    # --- checks ---------------------------------------------------------------------------
    @staticmethod
    def _checked(values: Any, name: str, shape: tuple[int, ...], dtype) -> np.ndarray:
        array = np.asarray(values)
        if array.shape != shape:
            raise ValueError(f"{name} must have shape {shape}, got {array.shape}")
        if dtype is bool and array.dtype != bool:
            raise ValueError(f"{name} must be booleans, got dtype {array.dtype}")
        if dtype is np.int64 and array.dtype.kind not in "iu":
            raise ValueError(f"{name} must be integers, got dtype {array.dtype}")
        return array.astype(dtype, copy=False)

    def _checked_step(self, observations, x, racing) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n, b = self.game.num_players, self.num_races
        observations = np.asarray(observations)
        if observations.ndim != 2 or observations.shape[0] != b:
            raise ValueError(f"observations must have shape (B, obs_dim) with B = {b}, got {observations.shape}")
        x = self._checked(x, "x", (b, n, 6), np.float64)
        racing = self._checked(racing, "racing", (b, n), bool)
        return observations, x, racing


def run_steps(steps, solve: Callable[[Any], Any]) -> Any:
    """Run a generator of :meth:`BatchedOpponent.act_steps` to its end, solving the request it
    yields (if any) with ``solve``; an exception of the solve is sent in, for the generator to
    treat as a failed solve. Returns the generator's return value."""
    try:
        request = next(steps)
    except StopIteration as done:
        return done.value
    try:
        solution = solve(request)
    except Exception as exc:  # noqa: BLE001 - the opponent falls back as after its own failed solve
        solution = exc
    try:
        steps.send(solution)
    except StopIteration as done:
        return done.value
    raise RuntimeError("an opponent's act_steps asked for more than one solve")


def empty_diagnostics(fields: dict[str, type], count: int) -> dict[str, np.ndarray]:
    """``{name: zeros (count,) of its dtype}``."""
    return {name: np.zeros(count, dtype=dtype) for name, dtype in fields.items()}
