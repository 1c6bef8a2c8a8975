"""Receding-horizon planners for B races at once: one batched, warm-started solve per step.

:class:`BatchedPlanner` is :meth:`planners.agents.RecedingHorizonAgent.act` for B races of
one game (``ilqgame-fb``, ``ilqgame-ol``, ``ilqgame-leader``, ``ilqgame-follower``, ``ilqr``
with the constant-velocity prediction).
Each race keeps its own plan ``(us (T, N, 2), xs (T+1, N, 6), K (T, 2, 6N))`` and plan age,
since races restart at different times. A step:

1. the races due (no plan, ``replan_every`` steps since the last re-plan, or the plan used
   up) are gathered, padded to one of a few sizes (``solve_sizes``, powers of two: each size
   compiles once; the padding is inert, see :meth:`BatchedPlanner._padded`), and solved by
   one :func:`planners.ilq_batch.solve_batch` call, warm-started from their plans shifted
   by the steps elapsed. Each race's game is the agent's planning game with that race's
   racing flags (:meth:`racing_env.RaceGame.with_racing`) and cost weights: the agent's
   own, belief and opponent weights, the leading or trailing weights by the race's place,
   and the own track weight scaled by ``recovery_track_scale`` while the car recovers from
   a standstill (on by default, so the weights differ per race), and the collision scales
   of its ``responsibility`` from the race's state;
2. the other races follow their plans: ``u = u_hat_t - K_t (x - x_hat_t)`` for the
   feedback game, the planned ``u_hat_t`` otherwise;
3. a race whose solve fails (non-finite output, an exception, or not converged under
   ``require_converged``) follows its previous plan shifted, else brakes with the single
   agent's braking law. Actions are never NaN.

Every step of this is the single agent's, so a race's actions are the single agent's to
rounding (tests/test_batched_opponents.py), as long as both make the same number of
iterations. The solves of one batch run one member after another (``batching="map"``, each
stopping at its own convergence) or in lock step (``"vmap"``); ``"auto"`` is ``"map"`` on
CPU and ``"vmap"`` elsewhere. On CPU the mapped batch was the faster in every configuration
measured (64 races on the trefoil, feedback iLQGame re-planned every step or every fifth,
5 or 30 iterations at most: 1.7 to 3.3 times the lock-step rate), since XLA:CPU vectorises
nothing across the members and a lock-step batch waits for its slowest member.
"""

from __future__ import annotations

import functools
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from planners import ilq, ilqr, leader_follower, rival_game
from planners.agents.batched_protocol import BatchedOpponent, DIAGNOSTIC_FIELDS, empty_diagnostics, run_steps
from planners.agents.protocol import BaseAgent
from planners.agents.compiled_planner import CompiledPlanner
from planners.agents.warm_start import restore_accelerations
from planners.agents.receding_horizon import (
    RECOVERED_SPEED,
    STOPPED_SPEED,
    FeedbackGameAgent,
    FollowerGameAgent,
    ILQRAgent,
    LeaderGameAgent,
    OpenLoopGameAgent,
    StackelbergGameAgent,
)
from planners.agents.weights import weight_names, with_player_weights
from planners.ilq_batch import resolve_batching, solve_batch
from planners.methods import CONSTANT_VELOCITY, FEEDBACK
from racing_env.costs import CostWeights, responsibility_scale
from racing_env.dynamics import STATE_DIM, V

__all__ = ["BATCHABLE_AGENTS", "BatchedPlanner", "default_solve_sizes", "predict_constant_velocity_batch",
           "unbatchable"]

BATCHABLE_AGENTS = (FeedbackGameAgent, OpenLoopGameAgent, LeaderGameAgent, FollowerGameAgent, ILQRAgent)
"""The planner classes whose loop :class:`BatchedPlanner` batches (exactly these classes:
a subclass may solve differently)."""


def unbatchable(agent: BaseAgent) -> str | None:
    """Why ``agent`` cannot be a :class:`BatchedPlanner` (None: it can)."""
    if type(agent) not in BATCHABLE_AGENTS:
        return f"{type(agent).__name__} is not one of the batched planners"
    if agent.budget_ms is not None:
        return "a wall-clock budget (budget_ms) is not batched: a batch's members cannot stop at their own times; use iterations=K"
    if isinstance(agent, ILQRAgent) and agent.prediction != CONSTANT_VELOCITY:
        return (f"the iLQR prediction {agent.prediction!r} is not batched (only prediction={CONSTANT_VELOCITY} "
                "is)")
    return None


def default_solve_sizes(num_races: int, num_devices: int = 1) -> tuple[int, ...]:
    """Batch sizes a re-plan is padded to: ``num_devices * 2^k`` below ``num_races``, then
    ``num_races`` rounded up to a multiple of ``num_devices`` (each part of a batch split
    across devices gets the same number of members)."""
    sizes, size = [], num_devices
    while size < num_races:
        sizes.append(size)
        size *= 2
    sizes.append(-(-num_races // num_devices) * num_devices)
    return tuple(sizes)


def predict_constant_velocity_batch(x0s: np.ndarray, horizon: int, dt: float) -> np.ndarray:
    """:func:`planners.ilqr.predict_constant_velocity` of every start state ``x0s (R, N, 6)``
    at once, with the same operations (bit-identical): ``(R, T+1, N, 6)``."""
    t = np.arange(horizon + 1, dtype=x0s.dtype)[:, None] * dt  # (T+1, 1)
    s = x0s[:, None, :, 0] + x0s[:, None, :, 1] * t  # (R, T+1, N)
    held = [np.broadcast_to(x0s[:, None, :, k], s.shape) for k in (1, 2)]
    zeros = np.zeros_like(s)
    return np.stack([s, *held, zeros, zeros, zeros], axis=-1)


def _shifted(us: np.ndarray, by: np.ndarray, pad: str) -> np.ndarray:
    """Each plan ``us (R, T, N, 2)`` shifted by ``by (R,)`` steps, the end padded by its last
    input (``"repeat"``) or zeros: :meth:`RecedingHorizonAgent._shifted` per race."""
    horizon = us.shape[1]
    steps = np.arange(horizon)[None, :] + np.minimum(by, horizon)[:, None]  # (R, T)
    out = us[np.arange(us.shape[0])[:, None], np.minimum(steps, horizon - 1)]
    if pad == "zeros":
        out[steps >= horizon] = 0.0
    return out


def _solve_local_games(planner: "BatchedPlanner", game, x0s: np.ndarray, egos: np.ndarray, init: np.ndarray):
    """The local games of the cars ``egos (R,)`` in the fields ``x0s (R, N, 6)`` (with
    ``game``'s per-member weights and racing flags, warm starts ``init (R, T, N, 2)``) in one
    batched solve with ``planner``'s solver: ``(us, xs, K or None, result)`` in the field's
    shapes (:func:`planners.rival_game.to_field_batch`)."""
    predicted = predict_constant_velocity_batch(x0s, planner.game.horizon, planner.game.dt)
    if planner.role is not None:  # a leader-follower planner's pair games (planners.leader_follower)
        problem, x0, local_init, orders, others = leader_follower.pair_games(game, x0s, egos, planner.role, init,
                                                                             predicted, planner.obstacles)
    else:
        problem, x0, local_init, orders, others = rival_game.local_games(game, x0s, egos, planner.rivals, init,
                                                                         predicted, planner.obstacles)
    axes = rival_game.RivalParams(game=planner._game_axes, order=0, predicted=0)
    res = solve_batch(problem, x0, local_init, params_axes=axes, devices=planner.devices, batching=planner.batching,
                      options=planner.options, validate=False)
    res = jax.device_get(res)
    K = res.K if planner.feedback else None
    if planner.role is not None:
        xs, us, K = leader_follower.to_field_batch(orders, egos, res.xs, res.us, K, init, others)
    else:
        xs, us, K = rival_game.to_field_batch(orders, res.xs, res.us, K, init, others)
    return us, xs, K, res


def _solve_joined(planners: list["BatchedPlanner"], requests: list[tuple]) -> list[tuple]:
    """The solve requests ``(x, racing, variant, init)`` of several cars' planners
    (:meth:`BatchedPlanner._replan`; the same :meth:`BatchedPlanner._field_key`) as one
    batched solve of all their local games; each planner's solution as its own
    :meth:`BatchedPlanner._solve` returns it."""
    first = planners[0]
    counts = [request[0].shape[0] for request in requests]
    total = sum(counts)
    sizes = default_solve_sizes(total, len(first.devices))
    size = next(s for s in sizes if s >= total)
    per_device = size // len(first.devices)
    k = np.arange(total)
    slots = (k % len(first.devices)) * per_device + k // len(first.devices)  # spread over the devices' parts

    def joined(parts, inert=None):
        return first._padded(np.concatenate(parts), size, slots, inert)

    x0s = joined([request[0] for request in requests], inert=np.nan)
    racing = joined([request[1] for request in requests])
    init = joined([request[3] for request in requests])
    egos = joined([np.full(count, planner.index) for planner, count in zip(planners, counts)])
    weights = {name: joined([planner._weights[name][request[2]] for planner, request in zip(planners, requests)])
               for name in first._weights}
    scales = [planner._collision_scales(request[0]) for planner, request in zip(planners, requests)]
    scales = None if scales[0] is None else joined(scales)
    game = first._solve_game.replace(weights=CostWeights(**weights), racing=racing, collision_scale=scales)
    us, xs, K, res = _solve_local_games(first, game, x0s, egos, init)
    iterations, converged = np.asarray(res.iterations), np.asarray(res.converged)
    out, start = [], 0
    for count in counts:
        part = slots[start:start + count]
        start += count
        out.append((us[part], xs[part], None if K is None else K[part], iterations[part], converged[part]))
    return out


def _all_finite(a: np.ndarray) -> np.ndarray:
    """Per leading-axis member: whether all its entries are finite, ``(R,)``."""
    return np.all(np.isfinite(a.reshape(a.shape[0], -1)), axis=1)


class BatchedPlanner(BatchedOpponent):
    """A receding-horizon planner (:class:`FeedbackGameAgent`, :class:`OpenLoopGameAgent`, the
    leader-follower :class:`LeaderGameAgent` and :class:`FollowerGameAgent`, :class:`ILQRAgent`
    with the constant-velocity prediction) driving one car in B races.

    Args:
        agent: the single agent whose options it takes (from :func:`planners.agents.make_agent`);
            it is reset as this car and lends its planning games, weights and braking law.
        game, index, num_races: as :class:`planners.agents.batched.BatchedOpponent`.
        spec: the spec it was made from (default: the agent's name).
        batching: ``"auto"``, ``"map"`` or ``"vmap"``: how a batch of re-plans is solved
            (:func:`planners.ilq_batch.solve_batch`): ``"map"`` one member after another,
            each stopping at its own convergence (a slow member holds no other up),
            ``"vmap"`` in lock step; ``"auto"``: ``"map"`` on CPU, ``"vmap"`` elsewhere.
        devices: the devices a batch is split across (default: every local device).
        solve_sizes: the batch sizes re-plans are padded to (each compiles once); default
            :func:`default_solve_sizes`. Each must be a multiple of the device count, and the
            largest at least ``num_races``.

    Raises:
        ValueError: for an agent it cannot batch, or one with ``certify`` on (its
            certificates are not batched).

    Diagnostics per race: ``replanned``, ``converged``, ``iterations`` (of this step's
    solve; False / 0 without one), ``fallback``, ``brake``, ``recovering`` (planned in
    recovery from a standstill) and ``leading`` (planned with the leading weights).
    """

    diagnostic_fields = {**DIAGNOSTIC_FIELDS, "recovering": bool, "leading": bool}

    def __init__(self, agent: BaseAgent, game: Any, index: int, num_races: int, *, spec: str | None = None,
                 batching: str = "auto", devices: Sequence[Any] | None = None,
                 solve_sizes: Sequence[int] | None = None) -> None:
        if getattr(agent, "certify", False):
            raise ValueError(f"{spec or agent.spec!r}: the option certify is not supported by batched opponents "
                             "(certify single agents' re-plans, e.g. in a tournament); drop certify=true")
        reason = unbatchable(agent)
        if reason is not None:
            raise ValueError(f"{reason}; use planners.agents.LoopedOpponent")
        if batching not in ("auto", "map", "vmap"):
            raise ValueError(f"batching must be 'auto', 'map' or 'vmap', got {batching!r}")
        super().__init__(spec or agent.spec, game, index, num_races)
        agent.reset(None, self.index, self.game)
        self.agent = agent
        self.devices = tuple(jax.local_devices() if devices is None else devices)
        self.batching = resolve_batching(batching, self.devices)
        self.solve_sizes = self._checked_sizes(solve_sizes)
        self.is_ilqr = isinstance(agent, ILQRAgent)
        self.feedback = bool(agent.feedback)
        mode = FEEDBACK if self.is_ilqr else agent.mode
        self.options = ilq.resolve_options(None, {"mode": mode, "max_iterations": agent.max_iterations,
                                                  **{k: v for k, v in agent.solver_options.items() if k != "mode"}})
        self._weights, self._place_count, self._recovery_count = self._weight_variants()
        self._solve_game = agent.planning_game.replace(racing=None)
        if agent.responsibility != 1.0:  # every solve's game has its collision scales
            self._solve_game = self._solve_game.replace(collision_scale=np.ones((self.game.num_players,) * 2))
        self._game_axes = rival_game.game_axes(self._solve_game)
        # a leader-follower planner: its pair games, in a race of two too (planners.leader_follower)
        self.role = agent.role if isinstance(agent, StackelbergGameAgent) else None
        # a game agent in a field larger than its game: local games (planners.rival_game)
        self.rivals = None if self.is_ilqr or (self.role is None and agent.rivals >= self.game.num_players - 1) \
            else agent.rivals
        self.obstacles = None if self.rivals is None else agent.obstacles
        if self.is_ilqr:
            self._ego_template = ilqr.ego_problem(self._solve_game, np.zeros((self.game.num_players, STATE_DIM)),
                                                  self.index)
        self._allocate()

    @functools.cached_property
    def jax_planner(self) -> CompiledPlanner:
        """This planner's step for one race as pure JAX functions
        (:class:`planners.agents.compiled_planner.CompiledPlanner`), for compiled races."""
        return CompiledPlanner(self)

    # --- construction ---------------------------------------------------------------------
    def _checked_sizes(self, sizes: Sequence[int] | None) -> tuple[int, ...]:
        count = len(self.devices)
        if sizes is None:
            return default_solve_sizes(self.num_races, count)
        sizes = tuple(sorted({int(s) for s in sizes}))
        if not sizes or sizes[0] < 1 or any(s % count for s in sizes) or sizes[-1] < self.num_races:
            raise ValueError(f"solve_sizes must be multiples of the {count} device(s), the largest at least "
                             f"num_races = {self.num_races}; got {sizes}")
        return sizes

    def _weight_variants(self) -> tuple[dict[str, np.ndarray], int, int]:
        """Every cost-weight set a race may plan with, stacked ``{field: (V, N)}``: the place
        (leading, trailing; or one) times recovery (off, on; or off only), the agent's
        choices made as :meth:`RecedingHorizonAgent._game_at_speed` makes them. Each is
        validated once here (the single agent validates every solve)."""
        agent, n = self.agent, self.game.num_players
        places = [agent.planning_game] if agent._games_by_place is None else [
            agent._games_by_place[True], agent._games_by_place[False]]
        recovery = agent.recovery_track_scale < 1.0
        variants = []
        for game in places:
            variants.append(game.weights)
            if recovery:
                c_track = float(np.broadcast_to(np.asarray(game.weights.c_track), (n,))[self.index])
                changes = {"c_track": c_track * agent.recovery_track_scale}
                variants.append(with_player_weights(game.weights, self.index, changes))
        for weights in variants:
            ilq.validate_problem(self.game.replace(weights=weights),
                                 control_regularization=self.options.guaranteed_control_regularization)
        table = {name: np.stack([np.broadcast_to(np.asarray(getattr(w, name), dtype=np.float64), (n,))
                                 for w in variants]) for name in weight_names()}
        return table, len(places), 2 if recovery else 1

    def _collision_scales(self, x: np.ndarray) -> np.ndarray | None:
        """The collision scales ``(R, N, N)`` of the races' re-plans from ``x (R, N, 6)`` by the
        agent's ``responsibility`` (:meth:`racing_env.RaceGame.with_responsibility`, per race),
        None for the symmetric cost."""
        if self.agent.responsibility == 1.0:
            return None
        return responsibility_scale(self.game.track, x[..., 0], np.asarray(self.game.vehicles.length),
                                    self.agent.responsibility)

    def _allocate(self) -> None:
        b, t, n = self.num_races, self.game.horizon, self.game.num_players
        self._has_plan = np.zeros(b, dtype=bool)
        self._age = np.zeros(b, dtype=np.int64)  # steps since the race's stored plan was made
        self._recovering = np.zeros(b, dtype=bool)
        self._us = np.zeros((b, t, n, 2))
        self._xs = np.zeros((b, t + 1, n, STATE_DIM))
        self._K = np.zeros((b, t, 2, n * STATE_DIM)) if self.feedback else None  # this car's gains

    def _reset_rows(self, rows, seeds):
        self._has_plan[rows] = False
        self._age[rows] = 0
        self._recovering[rows] = False

    # --- a step ---------------------------------------------------------------------------
    def _act_rows(self, rows, observations, x, racing):
        return run_steps(self._act_rows_steps(rows, observations, x, racing), self._solve_request)

    def _act_rows_steps(self, rows, observations, x, racing):
        horizon = self.game.horizon
        diagnostics = empty_diagnostics(self.diagnostic_fields, rows.size)
        age = self._age[rows]
        due = ~self._has_plan[rows] | (age + 1 >= self.agent.replan_every) | (age + 1 >= horizon)
        u = np.empty((rows.size, 2))
        follow = np.flatnonzero(~due)
        if follow.size:
            self._age[rows[follow]] += 1
            u[follow] = self._follow(rows[follow], x[follow], self._age[rows[follow]])
        replan = np.flatnonzero(due)
        if replan.size:
            u[replan] = yield from self._replan(rows[replan], x[replan], racing[replan], diagnostics, replan)
        return self._finish(u / self.agent.jerk_max, x, diagnostics), diagnostics

    def _follow(self, rows: np.ndarray, x: np.ndarray, t: np.ndarray) -> np.ndarray:
        """This car's physical jerks ``(R, 2)`` at ``t (R,)`` (< T) steps into the races' plans:
        the feedback law where the state deviation is finite (feedback game), else ``u_hat``."""
        u = self._us[rows, t, self.index]
        if self._K is None:
            return u
        dx = (x - self._xs[rows, t]).reshape(rows.size, -1)
        finite = _all_finite(dx)
        correction = np.einsum("rij,rj->ri", self._K[rows, t], np.where(finite[:, None], dx, 0.0))
        return np.where(finite[:, None], u - correction, u)

    def _replan(self, rows: np.ndarray, x: np.ndarray, racing: np.ndarray, diagnostics: dict, at: np.ndarray):
        """Re-plan the races ``rows`` (a generator: it yields the solve request
        ``(x, racing, variant, init)`` of :meth:`_solve` and receives its solution); returns
        their jerks ``(R, 2)`` (NaN: brake). Fills the diagnostics' entries ``at``."""
        racing = racing.copy()
        racing[:, self.index] = True  # as the observation's flags say of the car itself
        variant = self._variants(rows, x, racing, diagnostics, at)
        diagnostics["replanned"][at] = True
        solution = yield (x, racing, variant, self._warm_starts(rows, x))
        try:
            if isinstance(solution, BaseException):
                raise solution
            us, xs, K, iterations, converged = solution
            diagnostics["iterations"][at] = iterations
            diagnostics["converged"][at] = converged
            ok = _all_finite(us) & _all_finite(xs) & (_all_finite(K) if K is not None else True)
            if self.agent.require_converged:
                ok &= converged
        except Exception:  # noqa: BLE001 - any solver failure becomes a fallback, as in the single agent
            ok = np.zeros(rows.size, dtype=bool)
        u = np.full((rows.size, 2), np.nan)
        good, bad = np.flatnonzero(ok), np.flatnonzero(~ok)
        if good.size:
            self._store(rows[good], us[good], xs[good], None if K is None else K[good])
            u[good] = self._follow(rows[good], x[good], np.zeros(good.size, dtype=np.int64))
        if bad.size:
            diagnostics["fallback"][at[bad]] = True
            u[bad] = self._previous_plan(rows[bad], x[bad])
        return u

    def _solve_request(self, request):
        return self._solve(*request)

    def _field_key(self) -> tuple | None:
        """What planners of one field must share to solve their re-plans in one batch (local
        games of the same shapes, solver, game and devices); None: this one solves alone."""
        if self.rivals is None:
            return None
        game = self.game
        return (type(self), self.options, self.rivals, self.obstacles, self.role, self.feedback, self.num_races,
                game.num_players,
                game.horizon,
                id(game.track), id(game.vehicles), self.devices, self.batching, self.agent.responsibility == 1.0)

    @classmethod
    def act_together(cls, opponents, observations, x, racing):
        """:meth:`act` of several cars of the same races: the planners that play local games of
        the same shapes with the same solver (:meth:`_field_key`) solve the re-plans due of all
        their cars and races in one batched solve; each then acts as it would alone."""
        results: list[Any] = [None] * len(opponents)
        groups: dict[Any, list[int]] = {}
        for m, opponent in enumerate(opponents):
            key = opponent._field_key()
            groups.setdefault(("alone", m) if key is None else key, []).append(m)
        for members in groups.values():
            if len(members) == 1:
                m = members[0]
                results[m] = opponents[m].act(observations[m], x, racing)
                continue
            steps = {m: opponents[m].act_steps(observations[m], x, racing) for m in members}
            requests = {}
            for m in members:
                try:
                    requests[m] = next(steps[m])
                except StopIteration as done:  # nothing to re-plan in any race
                    results[m] = done.value
            if not requests:
                continue
            try:
                solutions = _solve_joined([opponents[m] for m in requests], list(requests.values()))
            except Exception as exc:  # noqa: BLE001 - each car falls back as after its own failed solve
                solutions = [exc] * len(requests)
            for m, solution in zip(requests, solutions):
                try:
                    steps[m].send(solution)
                except StopIteration as done:
                    results[m] = done.value
        return results

    def _warm_starts(self, rows: np.ndarray, x: np.ndarray) -> np.ndarray:
        """The initial inputs ``(R, T, N, 2)`` of the races' re-plans from the joint states
        ``x (R, N, 6)``: their plans shifted by the steps elapsed (with ``warm_start``; with
        ``restore_accelerations`` corrected as the single agent's,
        :func:`~planners.agents.warm_start.restore_accelerations`), zeros without a plan."""
        init = np.zeros((rows.size,) + self._us.shape[1:])
        if self.agent.warm_start:
            warm = np.flatnonzero(self._has_plan[rows])
            by = self._age[rows[warm]] + 1
            init[warm] = _shifted(self._us[rows[warm]], by, self.agent.pad)
            if self.agent.restore_accelerations:
                inside = np.flatnonzero(by < self._xs.shape[1])
                warm, by = warm[inside], by[inside]
                init[warm] = restore_accelerations(init[warm], self._xs[rows[warm], by], x[warm], self.game.dt)
        return init

    def _variants(self, rows: np.ndarray, x: np.ndarray, racing: np.ndarray, diagnostics: dict,
                  at: np.ndarray) -> np.ndarray:
        """Which cost weights (row of the weight table) each race plans with ``(R,)``: its
        place, and whether the car recovers from a standstill (updated here, as the single
        agent updates it at each re-plan)."""
        variant = np.zeros(rows.size, dtype=np.int64)
        if self._place_count == 2:
            leading = self._leading(x, racing)
            diagnostics["leading"][at] = leading
            variant += np.where(leading, 0, 1) * self._recovery_count
        if self._recovery_count == 2:
            speed = x[:, self.index, V]
            recovering = (speed < STOPPED_SPEED) | (self._recovering[rows] & (speed < RECOVERED_SPEED))
            self._recovering[rows] = recovering
            diagnostics["recovering"][at] = recovering
            variant += recovering
        return variant

    def _store(self, rows: np.ndarray, us: np.ndarray, xs: np.ndarray, K: np.ndarray | None) -> None:
        """New plans of the races ``rows``: ``us (R, T, N, 2)``, ``xs (R, T+1, N, 6)``, this
        car's gains ``K (R, T, 2, 6N)`` (feedback game), age 0."""
        self._us[rows], self._xs[rows] = us, xs
        if self._K is not None:
            self._K[rows] = K
        self._has_plan[rows] = True
        self._age[rows] = 0

    def _previous_plan(self, rows: np.ndarray, x: np.ndarray) -> np.ndarray:
        """After a failed re-plan: the stored plans one step on ``(R, 2)``; NaN (brake, plan
        dropped) where there is none, it is used up or its jerk is not finite."""
        self._age[rows] += 1
        t = self._age[rows]
        usable = self._has_plan[rows] & (t < self.game.horizon)
        u = np.full((rows.size, 2), np.nan)
        if usable.any():
            u[usable] = self._follow(rows[usable], x[usable], t[usable])
        dropped = ~_all_finite(u)
        self._has_plan[rows[dropped]] = False
        return u

    def _leading(self, x: np.ndarray, racing: np.ndarray) -> np.ndarray:
        """Whether the car is ahead of every other car still racing, ``(R,)``
        (:meth:`RecedingHorizonAgent._is_leading` per race)."""
        rivals = racing.copy()
        rivals[:, self.index] = False
        ahead = x[:, self.index, 0][:, None] > x[:, :, 0]
        return np.all(ahead | ~rivals, axis=1)

    # --- the batched solve ----------------------------------------------------------------
    def _layout(self, count: int) -> tuple[int, np.ndarray]:
        """The padded batch size for ``count`` re-plans and the slot of each: spread evenly
        over the device parts, so no part holds only padding."""
        size = next(s for s in self.solve_sizes if s >= count)
        per_device = size // len(self.devices)
        k = np.arange(count)
        return size, (k % len(self.devices)) * per_device + k // len(self.devices)

    def _solve(self, x, racing, variant, init):
        """One batched solve of the races' games from ``x (R, N, 6)``; returns the plans
        ``us (R, T, N, 2)``, ``xs (R, T+1, N, 6)``, this car's gains ``K (R, T, 2, 6N)`` or None,
        and the ``iterations``, ``converged`` ``(R,)``."""
        size, slots = self._layout(x.shape[0])
        x0s = self._padded(x, size, slots, inert=np.nan)
        init, racing, variant = (self._padded(a, size, slots) for a in (init, racing, variant))
        weights = CostWeights(**{name: column[variant] for name, column in self._weights.items()})
        scales = self._collision_scales(x)
        scales = None if scales is None else self._padded(scales, size, slots)
        game = self._solve_game.replace(weights=weights, racing=racing, collision_scale=scales)
        K = None
        if self.is_ilqr:
            us, xs, res = self._solve_ilqr(game, x0s, init)
        elif self.rivals is not None:
            us, xs, K, res = self._solve_local(game, x0s, init)
        else:
            res = solve_batch(game, x0s, init, params_axes=self._game_axes, devices=self.devices,
                              batching=self.batching, options=self.options, validate=False)
            us, xs = np.asarray(res.us), np.asarray(res.xs)
            K = np.asarray(res.K)[:, :, self.index] if self.feedback else None
        K = None if K is None else K[slots]
        return us[slots], xs[slots], K, np.asarray(res.iterations)[slots], np.asarray(res.converged)[slots]

    def _solve_local(self, game, x0s, init):
        """Each member's local game (this car and its ``rivals`` nearest, the other cars
        predicted at constant velocity: the single agent's re-plan) in one batched solve;
        the plans in the field's shapes, this car's gains on the field's state, the result."""
        return _solve_local_games(self, game, x0s, np.full(x0s.shape[0], self.index), init)

    def _padded(self, values: np.ndarray, size: int, slots: np.ndarray, inert: float | None = None) -> np.ndarray:
        """``values (R, ...)`` at ``slots`` of a batch of ``size``; the other members copy the
        first race, except that mapped solves start them at ``inert`` (if given): a NaN start
        state stops a member before its first iteration, so padding costs next to nothing
        when members run one after another. Lock-step members pay for every member in every
        iteration, and a NaN member would keep each iteration's step-size search going to its
        last trial: there the padding repeats a real race, whose solve ends with it."""
        out = np.empty((size,) + values.shape[1:], dtype=values.dtype)
        out[...] = values[0] if inert is None or self.batching == "vmap" else inert
        out[slots] = values
        return out

    def _solve_ilqr(self, game, x0s, init):
        """:func:`planners.ilqr.solve_ilqr` of every member against the constant-velocity
        prediction, batched: the ego's one-player problems with the game and the prediction
        as batched params. Returns the joint plans as the single agent stores them (the
        prediction with the ego's row planned; zero jerks for the others) and the result."""
        predicted = predict_constant_velocity_batch(x0s, self.game.horizon, self.game.dt)
        params = self._ego_template.params._replace(game=game, predicted=jnp.asarray(predicted))
        axes = self._ego_template.params._replace(game=self._game_axes, predicted=0, ego=None)
        problem = self._ego_template.replace(params=params)
        res = solve_batch(problem, x0s[:, self.index], init[:, :, self.index][:, :, None], params_axes=axes,
                          devices=self.devices, batching=self.batching, options=self.options, validate=False)
        xs = predicted
        xs[:, :, self.index] = np.asarray(res.xs)
        us = np.zeros(init.shape)
        us[:, :, self.index] = np.asarray(res.us)[:, :, 0]
        return us, xs, res
