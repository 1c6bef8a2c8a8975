"""Receding-horizon planners: a game (or iLQR) solution re-planned from the current joint state.

:class:`FeedbackGameAgent`, :class:`OpenLoopGameAgent`, the leader-follower
:class:`LeaderGameAgent` and :class:`FollowerGameAgent` (:class:`StackelbergGameAgent`) and
:class:`ILQRAgent` re-solve the env's :class:`racing_env.RaceGame` from the current joint
state every ``replan_every`` steps,
warm-started from the previous solution shifted by the steps elapsed (the last input
repeated, or zeros). Between re-plans the feedback agent applies
``u = u_hat_t - K_t (x - x_hat_t)``, the others the planned ``u_hat_t``. A solve that raises
or returns non-finite values falls back to the previous plan (shifted) or, without one, to a
braking action with a lateral correction toward the centre line; actions are never NaN. Cars
that the observation flags as no longer racing (finished or retired: frozen by the env, which
no car collides with) are ghosts in the plan (``RaceGame.with_racing``): no collision cost
with them, and their progress does not count. The state's ``s`` is cumulative on closed
tracks; the game wraps it itself (curvature, widths and gaps), so the agents pass the joint
state through unchanged. With ``certify`` on, the game agents certify each adopted re-plan
(:func:`certificate_record`). See docs/agents.md.
"""

from __future__ import annotations

import dataclasses
import inspect
import time
import traceback
from typing import Any

import jax
import numpy as np

from planners import ilq, ilqr, leader_follower, prediction as prediction_models, rival_game
from planners.certificates import LOCAL_NASH, certify as certify_solution
from planners.agents.protocol import BaseAgent, empty_record
from planners.agents.warm_start import restore_accelerations
from planners.agents.weights import (
    PLACE_PREFIXES,
    WEIGHT_PREFIXES,
    checked_weight_changes,
    weight_names,
    weights_for,
    with_player_weights,
)
from planners.methods import (
    CONSTANT_VELOCITY,
    FEEDBACK,
    FEEDBACK_GAME,
    GAME_MODES,
    ILQR,
    LANE_KEEPING,
    OPEN_LOOP_GAME,
    STACKELBERG,
    STACKELBERG_FOLLOWER,
    STACKELBERG_LEADER,
)
from planners.precision import require_precision
from racing_env.costs import check_responsibility
from racing_env.dynamics import V
from racing_env.observation import cars_racing

__all__ = [
    "FeedbackGameAgent",
    "FollowerGameAgent",
    "ILQRAgent",
    "LeaderGameAgent",
    "OpenLoopGameAgent",
    "DEFAULT_RESPONSIBILITY",
    "DEFAULT_OBSTACLES",
    "DEFAULT_RIVALS",
    "RECOVERED_SPEED",
    "REPLAN_TOLERANCE",
    "RecedingHorizonAgent",
    "STOPPED_SPEED",
    "StackelbergGameAgent",
    "certificate_record",
    "stackelberg_certificate_record",
]


STOPPED_SPEED = 0.5  # [m/s] a car this slow at a re-plan is stuck: it plans in recovery (below)
RECOVERED_SPEED = 5.0  # [m/s] and it plans normally again once this fast
DEFAULT_RIVALS = 2
"""The rivals a game planner plays its game with in a field (``rivals``): the nearest car
ahead and behind, typically, and every car of a race of three."""
DEFAULT_OBSTACLES = 4
"""The cars beyond its rivals that a game planner's local game predicts as moving obstacles
(``obstacles``), the nearest first: two more ahead and behind, typically. The rest of a field
is left out, so a local game costs the same whatever N (:mod:`planners.rival_game`)."""
DEFAULT_RESPONSIBILITY = 2.0
"""The ratio of the collision weight a planner carries towards a car ahead of it to that
towards a car behind it (``responsibility``), in its plans of every car. The paper lets the
trailing car carry the larger weight because it bears the greater responsibility for avoiding
a collision, as the racing rules (and the steward) say: the car behind answers for a rear-end.
Measured (docs/agents.md): at 2, in the paper's scene the leader swerves less and the trailing
car more than with the symmetric cost, and the planners still win every race of the trefoil
gauntlet against the lane keeper by the symmetric cost's margins; at 3 the open-loop planner
lost the race it started behind."""
REPLAN_TOLERANCE = 1e-3
"""Convergence tolerance of a re-plan [state units: m, m/s, ...]: a millimetre is plenty for
a plan that is re-solved 0.1 s later, and more re-plans converge within their iteration cap
than at the solver's default (docs/agents.md)."""


def _finite(solution: tuple) -> bool:
    """Whether a solver's ``(us, xs, K or None, result)`` plan arrays are all finite."""
    return all(np.all(np.isfinite(part)) for part in solution[:3] if part is not None)


class RecedingHorizonAgent(BaseAgent):
    """Re-plans a game (or iLQR) solution from the current joint state.

    Args:
        max_iterations: solver iteration cap per re-plan.
        replan_every: re-plan every this many steps (1: every step); in between the stored
            plan is followed (with its feedback law for the feedback game).
        belief_weights: the agent's belief of the cost weights (see
            :func:`planners.agents.weights.weights_for`); default the game's true weights.
        pad: how the shifted warm start is padded at the end: ``"repeat"`` the last input
            or ``"zeros"``.
        warm_start: warm start from the previous solution (else zeros every re-plan).
        restore_accelerations: correct the shifted warm start's first jerks so that the
            accelerations are back on the previous plan after one step
            (:func:`planners.agents.warm_start.restore_accelerations`): the environment
            projects a plan that leans on an acceleration limit back onto it, and the
            uncorrected warm start then starts its re-plan with a long LQ step that the
            trust region cuts short. Default (None): on for real-time re-plans (with
            ``iterations`` or ``budget_ms``), off for re-plans that iterate to convergence,
            where it saves iterations but changes which equilibrium the open-loop game
            settles in, to its cost in races (docs/agents.md).
        iterations: a real-time re-plan: at most this many solver iterations, after which
            the last iterate is adopted, converged or not (as ``max_iterations``, which it
            replaces: give one of the two). The solver option ``best_iterate=true`` adopts
            the iterate with the smallest merit instead; it races worse (docs/agents.md).
        budget_ms: a wall-clock budget per re-plan [ms]: the solver stops iterating once it
            has run out (after at least one iteration) and the last iterate is adopted. With
            ``iterations`` too, whichever ends first. Game agents, and iLQR with the
            constant-velocity or lane-keeping prediction (whose re-plan is one solve).
        require_converged: treat a non-converged solve as a failure (fallback); by default
            the last iterate is used (it is a dynamically feasible, finite plan).
        recovery_track_scale: factor on the car's own track weight ``c_track`` in the
            re-plans of a recovery: from a re-plan at which the car is slower than
            :data:`STOPPED_SPEED` until one at which it is at least :data:`RECOVERED_SPEED`.
            A car that has stopped at the edge facing out (it cannot reverse or turn on the
            spot) can only rejoin across the boundary; over a 5 s horizon standing still is
            cheaper at full weight, so without this it stands for good. ``0`` (the default)
            drops the track term while recovering: a car stopped across the track in a
            tight corner may need several metres of run-off to turn, which even a small
            track weight prices above standing still. ``1`` turns it off.
        own_weights: :class:`racing_env.CostWeights` fields ``{name: value}`` that replace
            the agent's own weights in its plans. They are private: the other cars plan
            with the race's weights for this car, as they would against an unknown driver.
        leading_weights, trailing_weights: own weights used (on top of ``own_weights``) for
            re-plans made while the car is ahead of every other car still racing (as the
            observation's flags say) in race distance, or behind at least one (the paper's
            outlook: aggression that depends on place).
        opponent_weights: ``{name: value}`` changes to the race's weights of every other
            car in this agent's plans: what it believes the others' costs are (e.g.
            ``{"c_collision": 100.0}``: they will do much to avoid contact). Applied on top
            of ``belief_weights``.
        responsibility: the ratio (a finite number >= 1) of the collision weight every car
            carries, in this agent's plans, towards a car ahead of it to that towards a car
            behind it, judged from the joint state each re-plan starts from
            (:meth:`racing_env.RaceGame.with_responsibility`); 1: the paper's symmetric cost,
            bit for bit. Default :data:`DEFAULT_RESPONSIBILITY`.
        solver_options: further :class:`planners.ilq.SolverOptions` fields; the
            ``tolerance`` defaults to :data:`REPLAN_TOLERANCE`, and ``player_steps`` (a step
            size per car) to true for the real-time re-plans (``iterations`` or
            ``budget_ms``) of the feedback game agent: with one step size, a rival far off the track,
            whose boundary cost asks for a step of hundreds of metres, cuts the ego's step
            to a few percent and the ego's plan lags behind until it leaves the track
            (docs/experiments/cheap-replans.md). Checked here, so a bad
            option fails when the agent is made.
    """

    name = "receding-horizon"
    feedback = False
    mode = FEEDBACK  # the solver mode of its plans (iLQR's is a one-player feedback solve)
    planned_players = 1  # players of its own solve: 1 for iLQR, 2 (or more) for a game
    # whether its real-time re-plans (iterations, budget_ms) take a step size per player by
    # default (SolverOptions.player_steps): the feedback game's do
    realtime_player_steps = False

    def __init__(
        self,
        max_iterations: int = 30,
        replan_every: int = 1,
        belief_weights=None,
        pad: str = "repeat",
        warm_start: bool = True,
        restore_accelerations: bool | None = None,
        iterations: int | None = None,
        budget_ms: float | None = None,
        require_converged: bool = False,
        recovery_track_scale: float = 0.0,
        own_weights: dict[str, float] | None = None,
        leading_weights: dict[str, float] | None = None,
        trailing_weights: dict[str, float] | None = None,
        opponent_weights: dict[str, float] | None = None,
        responsibility: float = DEFAULT_RESPONSIBILITY,
        **solver_options: Any,
    ) -> None:
        super().__init__()
        self.responsibility = check_responsibility(responsibility)
        if int(replan_every) < 1:
            raise ValueError(f"replan_every must be >= 1, got {replan_every!r}")
        if pad not in ("repeat", "zeros"):
            raise ValueError(f"pad must be 'repeat' or 'zeros', got {pad!r}")
        if iterations is not None:
            if int(max_iterations) != 30:
                raise ValueError("give iterations (an anytime re-plan) or max_iterations (a cap), not both")
            if isinstance(iterations, bool) or int(iterations) < 1:
                raise ValueError(f"iterations must be an integer >= 1, got {iterations!r}")
            max_iterations = int(iterations)
        if budget_ms is not None:
            ilq.check_budget_ms(budget_ms)
        self.iterations = None if iterations is None else int(iterations)
        self.budget_ms = None if budget_ms is None else float(budget_ms)
        if restore_accelerations is None:
            restore_accelerations = iterations is not None or budget_ms is not None
        self.restore_accelerations = bool(restore_accelerations)
        self.max_iterations = int(max_iterations)
        self.replan_every = int(replan_every)
        self.belief_weights = belief_weights
        self.pad = pad
        self.warm_start = bool(warm_start)
        self.require_converged = bool(require_converged)
        if not 0.0 <= float(recovery_track_scale) <= 1.0:
            raise ValueError(f"recovery_track_scale must be in [0, 1], got {recovery_track_scale!r}")
        self.recovery_track_scale = float(recovery_track_scale)
        self.own_weights = checked_weight_changes("own_weights", own_weights)
        self.leading_weights = checked_weight_changes("leading_weights", leading_weights)
        self.trailing_weights = checked_weight_changes("trailing_weights", trailing_weights)
        self.opponent_weights = checked_weight_changes("opponent_weights", opponent_weights)
        self.solver_options = {"tolerance": REPLAN_TOLERANCE, **solver_options}
        if "player_steps" not in solver_options and self.realtime_player_steps and (
                iterations is not None or budget_ms is not None):
            # real-time feedback re-plans: a rival whose own plan needs a long step (a car far
            # off the track) must not cut the ego's step to a few percent (docs/solvers.md)
            self.solver_options["player_steps"] = True
        unknown = sorted(set(self.solver_options) - set(self._solver_option_types()) - {"mode"})
        if unknown:
            raise ValueError(f"unknown solver options {unknown}; allowed: {sorted(self._solver_option_types())}")
        # refuses bad values (max_iterations too) now, not at the first solve
        options = ilq.SolverOptions(**{"mode": self.mode, "max_iterations": self.max_iterations,
                                       **self.solver_options})
        ilq.check_adaptive_regularization(options, self.planned_players)

    @staticmethod
    def _solver_option_types() -> dict[str, type]:
        # leader: the Stackelberg mode's; the leader-follower agents choose it by ordering
        # their game's players (planners.leader_follower), never as an option
        return {f.name: type(f.default) for f in dataclasses.fields(ilq.SolverOptions)
                if f.name not in ("mode", "max_iterations", "leader")}

    @classmethod
    def spec_options(cls) -> dict[str, type]:
        options = {"max_iterations": int, "replan_every": int, "pad": str, "warm_start": bool,
                   "restore_accelerations": bool, "iterations": int, "budget_ms": float,
                   "require_converged": bool, "recovery_track_scale": float, "responsibility": float,
                   **cls._solver_option_types()}
        for name in weight_names():
            options[name] = float
            options.update({f"{prefix}.{name}": float for prefix in WEIGHT_PREFIXES})
        return options

    @classmethod
    def spec_defaults(cls) -> dict[str, Any]:
        defaults = {f.name: f.default for f in dataclasses.fields(ilq.SolverOptions) if f.name != "leader"}
        loop = inspect.signature(RecedingHorizonAgent.__init__).parameters  # the loop's own defaults
        defaults.update({name: loop[name].default for name in
                         ("max_iterations", "replan_every", "pad", "warm_start", "restore_accelerations",
                          "iterations", "budget_ms", "require_converged", "recovery_track_scale",
                          "responsibility")})
        defaults["tolerance"] = REPLAN_TOLERANCE
        defaults["restore_accelerations"] = "true with iterations or budget_ms, else false"
        if cls.realtime_player_steps:
            defaults["player_steps"] = "true with iterations or budget_ms, else false"
        for name in weight_names():
            defaults[name] = "the race's"
            defaults.update({f"{place}.{name}": name for place in PLACE_PREFIXES})
            defaults[f"belief.{name}"] = "the race's"
        return defaults

    @classmethod
    def from_spec_options(cls, options: dict[str, Any], **kwargs: Any) -> "RecedingHorizonAgent":
        grouped: dict[str, Any] = {"own_weights": {}, **{name: {} for name in WEIGHT_PREFIXES.values()}}
        for key, value in options.items():
            prefix, dot, field = key.partition(".")
            if dot:
                grouped[WEIGHT_PREFIXES[prefix]][field] = value
            elif key in weight_names():
                grouped["own_weights"][key] = value
            else:
                grouped[key] = value
        return cls(**{**grouped, **kwargs})

    def reset(self, seed: int | None, index: int, env_info: Any) -> None:
        # float64 solves need x64 (their tolerances); before any work of the race
        require_precision(self.solver_options.get("precision", "float64"), f"the planner {self.spec!r}")
        super().reset(seed, index, env_info)
        weights = weights_for(self.game, self.index, self.belief_weights)
        others = [j for j in range(self.game.num_players) if j != self.index]
        weights = with_player_weights(weights, others, self.opponent_weights)
        weights = with_player_weights(weights, self.index, self.own_weights)
        self.planning_game = self.game.replace(weights=weights)
        self._games_by_place = None  # {leading?: game} when the weights depend on the place
        if self.leading_weights or self.trailing_weights:
            self._games_by_place = {
                True: self.game.replace(weights=with_player_weights(weights, self.index, self.leading_weights)),
                False: self.game.replace(weights=with_player_weights(weights, self.index, self.trailing_weights)),
            }
        self._plan: dict | None = None  # {"us": (T,N,2), "xs": (T+1,N,6), "K": the ego's gains (T,2,6N) | None}
        self._prepared: dict | None = None  # a re-plan set up for a solve elsewhere (prepare_replan)
        # the env's nearest-rival observation layout, whose blocks do not say which car is out
        self._observed_rivals = getattr(getattr(env_info, "config", None), "observed_rivals", None)
        self._age = 0  # steps since the stored plan was made
        self._recovering = False  # from a standstill until RECOVERED_SPEED (recovery_track_scale)

    def _is_leading(self, x: np.ndarray, racing: np.ndarray | None = None) -> bool:
        """Ahead of every other car still racing in race distance (``s`` is cumulative, laps
        included); ``racing (N,)`` bool, None: all. A car that finished or retired is out of
        the contest: the others race for the places behind it."""
        rivals = [j for j in range(x.shape[0]) if j != self.index and (racing is None or racing[j])]
        return bool(np.all(x[self.index, 0] > x[rivals, 0]))

    # the solve itself (subclasses) -> (us (T,N,2), xs (T+1,N,6), the ego's gains K (T,2,6N) or None, result)
    def _solve(self, game, x0: np.ndarray, init: np.ndarray | None):
        raise NotImplementedError

    def _adopted(self, game: Any, x0: np.ndarray, result: Any, record: dict) -> None:
        """Called with a re-plan's game, start state ``x0 (N, 6)`` and solver result when
        its plan is adopted (not at a fallback), before the step's action; it may add to
        the step's ``record``. The base loop adds nothing."""

    def _game_at_speed(self, x: np.ndarray, record: dict) -> Any:
        """The planning game, with this car's own track weight scaled by
        ``recovery_track_scale`` while it recovers from a standstill (recorded as
        ``record["recovering"]`` when recovery is on)."""
        game = self.planning_game
        if self.recovery_track_scale >= 1.0:
            return game
        speed = x[self.index, V]
        self._recovering = speed < STOPPED_SPEED or (self._recovering and speed < RECOVERED_SPEED)
        record["recovering"] = self._recovering
        if not self._recovering:
            return game
        c_track = float(np.broadcast_to(np.asarray(game.weights.c_track), (game.num_players,))[self.index])
        changes = {"c_track": c_track * self.recovery_track_scale}
        return game.replace(weights=with_player_weights(game.weights, self.index, changes))

    def _shifted(self, us: np.ndarray, by: int) -> np.ndarray:
        T = us.shape[0]
        by = min(by, T)
        out = np.empty_like(us)
        out[: T - by] = us[by:]
        fill = us[-1] if self.pad == "repeat" else np.zeros_like(us[-1])
        out[T - by :] = fill
        return out

    def _follow(self, x: np.ndarray, t: int) -> np.ndarray | None:
        """The ego's physical jerk at ``t`` steps into the stored plan (None if exhausted)."""
        plan = self._plan
        if plan is None or t >= plan["us"].shape[0]:
            return None
        u = plan["us"][t, self.index].copy()
        if self.feedback and plan["K"] is not None:
            dx = (x - plan["xs"][t]).reshape(-1)
            if np.all(np.isfinite(dx)):
                u = u - plan["K"][t] @ dx
        return u

    def current_plan(self) -> np.ndarray | None:
        """The plan the last action followed, from that step on: the joint trajectory
        ``(H, N, 6)`` of the last adopted solution (this car's plan in its own row; in the
        others' rows what it expects of them: the equilibrium's other players for a game,
        the prediction it planned against for iLQR). None before the first plan and after a
        braking fallback. A view into the stored plan, not a copy."""
        if self._plan is None or self._age >= self._plan["xs"].shape[0]:
            return None
        return self._plan["xs"][self._age:]

    def diagnostics(self) -> dict:
        """The last step's record, with ``plan``: :meth:`current_plan` (kept out of the
        history, so a race's diagnostics do not hold every plan)."""
        return {**super().diagnostics(), "plan": self.current_plan()}

    def _replan_due(self) -> bool:
        """Whether the next action re-plans (no plan, ``replan_every`` reached, or the plan used up)."""
        return self._plan is None or self._age + 1 >= self.replan_every or self._age + 1 >= self._plan["us"].shape[0]

    def _warm_start_now(self, x: np.ndarray) -> np.ndarray | None:
        """The next re-plan's warm start ``(T, N, 2)`` from joint state ``x``: the stored plan
        shifted by the steps elapsed (its accelerations restored), or None."""
        if not self.warm_start or self._plan is None:
            return None
        init = self._shifted(self._plan["us"], self._age + 1)
        if self.restore_accelerations and self._age + 1 < self._plan["xs"].shape[0]:
            init = restore_accelerations(init, self._plan["xs"][self._age + 1], x, self.game.dt)
        return init

    def _game_now(self, observation: np.ndarray | None, x: np.ndarray, record: dict) -> Any:
        """The game of a re-plan from ``x (N, 6)``: the planning game for the car's place and
        speed, with the cars the observation flags as out of the race as ghosts."""
        if x.shape != (self.game.num_players, 6):
            raise ValueError(f"joint state must have shape ({self.game.num_players}, 6), got {x.shape}")
        racing = cars_racing(observation, self.index, self.game.num_players, self._observed_rivals)
        if self._games_by_place is not None:
            record["leading"] = self._is_leading(x, racing)
            self.planning_game = self._games_by_place[record["leading"]]
        # cars that finished or retired are ghosts in the plan, as in the env; who is ahead is
        # judged at x, a constant of the plan (the solvers treat weights as constants)
        return self._game_at_speed(x, record).with_racing(racing).with_responsibility(x, self.responsibility)

    def prepare_replan(self, observation: np.ndarray | None, joint_state: np.ndarray,
                       predicted: np.ndarray | None = None) -> Any:
        """Set up the re-plan the next :meth:`act` makes with these arguments, for a solve made
        elsewhere (:mod:`planners.agents.field`: the field's re-plans solved as one batch).

        Returns what :meth:`_batchable` makes of it (a :class:`planners.rival_game.LocalGame`
        for a game agent playing a local game), or None when the next action does not
        re-plan, or the re-plan cannot be solved elsewhere; then :meth:`act` solves as usual.
        Otherwise the solution must be handed over with :meth:`take_solution` before the
        :meth:`act` of this step.
        """
        self._require_reset()
        self._prepared = None
        if not self._replan_due():
            return None
        x = np.asarray(joint_state, dtype=np.float64)
        record: dict[str, Any] = {}
        try:
            game = self._game_now(observation, x, record)
        except Exception:  # noqa: BLE001 - act() makes the same call and turns it into a fallback
            return None
        init = self._warm_start_now(x)
        request = self._batchable(game, x, init, predicted)
        if request is not None:
            self._prepared = {"step": self._steps, "game": game, "record": record, "request": request,
                              "init": init, "solution": None}
        return request

    def take_solution(self, result: Any, solve_time: float) -> None:
        """Hand over the solver result of the request :meth:`prepare_replan` returned (a
        single :class:`planners.ilq.SolverResult` in NumPy, or the exception the solve raised)
        and the seconds [s] of the solve charged to this car."""
        if self._prepared is None:
            raise RuntimeError("take_solution without a prepared re-plan (prepare_replan returned None)")
        self._prepared["solution"] = result
        self._prepared["solve_time"] = float(solve_time)

    def _batchable(self, game: Any, x0: np.ndarray, init: np.ndarray | None, predicted: np.ndarray | None) -> Any:
        """The re-plan as a problem another solve can take (None: this agent solves it)."""
        return None

    def _from_result(self, request: Any, result: Any, init: np.ndarray | None):
        """``(us, xs, K, result)`` of a solution of :meth:`_batchable`'s ``request``."""
        raise NotImplementedError

    def act(self, observation: np.ndarray, joint_state: np.ndarray) -> np.ndarray:
        self._require_reset()
        x = np.asarray(joint_state, dtype=np.float64)
        record = empty_record()
        record["step"] = self._steps
        prepared, self._prepared = getattr(self, "_prepared", None), None
        if prepared is not None and (prepared["step"] != self._steps or prepared["solution"] is None):
            prepared = None  # set up for another step, or never solved: solve here
        if self._replan_due():
            record["replanned"] = True
            error = None
            t0 = time.perf_counter()
            try:
                if prepared is not None:
                    record.update(prepared["record"])
                    game, init = prepared["game"], prepared["init"]
                    if isinstance(prepared["solution"], BaseException):
                        raise prepared["solution"]
                    solution = self._from_result(prepared["request"], prepared["solution"], init)
                else:
                    init = self._warm_start_now(x)
                    game = self._game_now(observation, x, record)
                    solution = self._solve(game, x, init)
                us, xs, K, res = solution
                record["iterations"] = int(res.iterations)
                record["converged"] = bool(res.converged)
                record["status"] = ilq.status_message(res.status)
                if not _finite(solution):
                    error = "solver returned non-finite values"
                elif self.require_converged and not record["converged"]:
                    error = f"solver did not converge ({record['status']})"
            except Exception as exc:  # noqa: BLE001 - any solver failure becomes a fallback
                error = f"{type(exc).__name__}: {exc}"
                record["traceback"] = traceback.format_exc(limit=3)
            record["solve_time"] = time.perf_counter() - t0 + (prepared["solve_time"] if prepared else 0.0)
            if error is None:
                self._adopted(game, x, res, record)
                self._plan = {"us": us, "xs": xs, "K": K}
                self._age = 0
                u = self._follow(x, 0)
            else:
                record["fallback"] = True
                record["error"] = error
                self._age += 1
                u = self._follow(x, self._age)
                if u is not None and np.all(np.isfinite(u)):
                    record["fallback_kind"] = "previous_plan"
                else:
                    self._plan = None
                    record["fallback_kind"] = "brake"
                    return self._finish(self._safe_action(x), x, record)
        else:
            self._age += 1
            u = self._follow(x, self._age)
        return self._finish(np.asarray(u) / self.jerk_max, x, record)


def certificate_record(game: Any, x0: np.ndarray, result: Any, mode: str) -> dict[str, Any]:
    """The cheap certificate of a re-plan (:func:`planners.certificates.certify` with
    ``checks="cheap"``) as diagnostics: ``certified`` (the verdict is a local Nash
    equilibrium), ``verdict`` and ``certify_time`` [s]. A certificate that raises is not
    certified: ``verdict`` None and the exception in ``certify_error``.

    Args:
        game: the :class:`racing_env.RaceGame` that was solved.
        x0: the joint state it was solved from, ``(N, 6)``.
        result: the :class:`planners.ilq.SolverResult` of the solve.
        mode: ``"feedback"`` or ``"open_loop"``: the strategies the players are tested against.
    """
    t0 = time.perf_counter()
    try:
        verdict = certify_solution(game, x0, result, mode, checks="cheap").verdict
    except Exception as exc:  # noqa: BLE001 - a diagnostic must not stop the race
        return {"certified": False, "verdict": None, "certify_error": f"{type(exc).__name__}: {exc}",
                "certify_time": time.perf_counter() - t0}
    return {"certified": verdict == LOCAL_NASH, "verdict": verdict, "certify_time": time.perf_counter() - t0}


def stackelberg_certificate_record(problem: Any, x0: np.ndarray, result: Any,
                                   options: ilq.SolverOptions) -> dict[str, Any]:
    """The cheap Stackelberg certificate of a re-plan
    (:func:`planners.stackelberg.certify_stackelberg` with ``checks="cheap"``) as diagnostics,
    as :func:`certificate_record`: ``certified`` (the verdict is a local Stackelberg
    solution), ``verdict`` and ``certify_time`` [s], or ``certify_error``.

    Args:
        problem: the pair game solved (:func:`planners.leader_follower.pair_game`'s problem).
        x0: its start ``(12,)``; result: its :class:`planners.ilq.SolverResult`.
        options: the solve's options (``mode="stackelberg"``).
    """
    from planners.stackelberg import STACKELBERG_SOLUTION, certify_stackelberg  # the certificate's module, only when certifying

    t0 = time.perf_counter()
    try:
        verdict = certify_stackelberg(problem, x0, result, options=options, checks="cheap").verdict
    except Exception as exc:  # noqa: BLE001 - a diagnostic must not stop the race
        return {"certified": False, "verdict": None, "certify_error": f"{type(exc).__name__}: {exc}",
                "certify_time": time.perf_counter() - t0}
    return {"certified": verdict == STACKELBERG_SOLUTION, "verdict": verdict,
            "certify_time": time.perf_counter() - t0}


def _checked_obstacles(obstacles) -> int:
    """An agent's ``obstacles``: an integer >= 1 (an agent always has a number of them)."""
    if obstacles is None:
        raise ValueError("obstacles must be an integer >= 1 (the nearest other cars a local game predicts); "
                         "a number at least the field's size predicts every car")
    return rival_game.check_obstacles(obstacles)


class _GameAgent(RecedingHorizonAgent):
    """A game method: the game solved by :func:`planners.ilq.solve` in the solver mode that
    the method's name stands for (:data:`planners.methods.GAME_MODES`).

    Args:
        rivals: the rivals ``k`` it plays its game with: in a race of more than ``k + 1``
            cars it solves its local game (:mod:`planners.rival_game`) with the ``k`` cars
            nearest by track distance, chosen afresh at every re-plan, every other car
            predicted at constant speed and lateral offset and avoided as a moving obstacle;
            with ``k + 1`` cars or fewer, the whole game (bit for bit the solve without this
            option). A rival's warm start is its row of the stored plan, kept while it is not
            among the nearest.
        obstacles: the cars of a local game predicted as moving obstacles: the ``obstacles``
            nearest after its rivals (integer >= 1); the cars further away are left out of
            its costs, so its cost does not grow with the field.
        certify: certify every adopted re-plan in the cheap form (:func:`certificate_record`,
            about 17 ms for two cars at T = 50 on one CPU core; of the local game when it
            plays one): its diagnostics carry ``certified``, ``verdict`` and
            ``certify_time``, and :meth:`summary` the ``certified_share`` of the certified
            re-plans. Off: none of these.
        kwargs: as :class:`RecedingHorizonAgent`.
    """

    planned_players = 2  # at least: every car of the race

    def __init__(self, rivals: int = DEFAULT_RIVALS, obstacles: int = DEFAULT_OBSTACLES, certify: bool = False,
                 **kwargs: Any) -> None:
        self.rivals = rival_game.check_rivals(rivals)  # before the solver options are checked
        self.obstacles = _checked_obstacles(obstacles)
        super().__init__(**kwargs)
        self.certify = bool(certify)

    @classmethod
    def spec_options(cls) -> dict[str, type]:
        return {**super().spec_options(), "rivals": int, "obstacles": int, "certify": bool}

    @classmethod
    def spec_defaults(cls) -> dict[str, Any]:
        return {**super().spec_defaults(), "rivals": DEFAULT_RIVALS, "obstacles": DEFAULT_OBSTACLES,
                "certify": False}

    def _adopted(self, game, x0, result, record):
        if self.certify:
            solved, start = getattr(self, "_solved", None) or (game, x0)
            record.update(certificate_record(solved, start, result, self.mode))

    def _plays_local_game(self, game) -> bool:
        return self.rivals < game.num_players - 1

    def _batchable(self, game, x0, init, predicted):
        if not self._plays_local_game(game) or self.budget_ms is not None:
            return None  # the whole game (today's solve), or a wall-clock budget: solved by act()
        self._validate(game)
        return rival_game.local_game(game, x0, self.index, self.rivals, init, predicted, self.obstacles)

    def _validate(self, game) -> None:
        """Refuse input weights that make a player's LQ game undefined (NumPy; the local
        problem's own check would evaluate its costs). Weights checked once are not checked
        again (the planning games of a race share a few weight objects)."""
        if getattr(self, "_validated_weights", None) is game.weights:
            return
        ilq.validate_problem(game, control_regularization=self.batch_options().guaranteed_control_regularization)
        self._validated_weights = game.weights

    def batch_options(self) -> ilq.SolverOptions:
        """The solver options of its re-plans (those of a batch solved for it)."""
        return ilq.SolverOptions(mode=self.mode, max_iterations=self.max_iterations, **self.solver_options)

    def _from_result(self, local, result, init):
        self._solved = (local.problem, local.x0)
        xs, us, K = rival_game.to_field(local, result.xs, result.us, result.K if self.feedback else None, init)
        return us, xs, K, result

    def _solve(self, game, x0, init):
        self._solved = None
        options = dict(mode=self.mode, max_iterations=self.max_iterations, budget_ms=self.budget_ms,
                       **self.solver_options)
        if not self._plays_local_game(game):
            res = ilq.solve(game, x0, init=init, **options)
            us, xs, K = (np.asarray(a) for a in (res.us, res.xs, res.K))
            return us, xs, (K[:, self.index] if self.feedback else None), res
        local = rival_game.local_game(game, x0, self.index, self.rivals, init, obstacles=self.obstacles)
        self._validate(game)
        res = ilq.solve(local.problem, local.x0, init=local.init, validate=False, **options)
        return self._from_result(local, jax.device_get(res), init)


class FeedbackGameAgent(_GameAgent):
    """Feedback Nash iLQGame; between re-plans ``u = u_hat_t - K_t (x - x_hat_t)``."""

    spec = name = FEEDBACK_GAME
    mode = GAME_MODES[FEEDBACK_GAME]
    feedback = True
    realtime_player_steps = True


class OpenLoopGameAgent(_GameAgent):
    """Open-loop Nash iLQGame; applies the planned ``u_hat_t``."""

    spec = name = OPEN_LOOP_GAME
    mode = GAME_MODES[OPEN_LOOP_GAME]
    feedback = False


class StackelbergGameAgent(_GameAgent):
    """Feedback Stackelberg iLQGame of the car and its nearest rival: a leader announces its
    feedback strategy stage by stage and the follower answers it (``mode="stackelberg"``,
    docs/solvers.md); between re-plans ``u = u_hat_t - K_t (x - x_hat_t)`` with the car's own
    gains, as the feedback Nash agent.

    The game is the *pair game* of :mod:`planners.leader_follower`: the car and the nearest
    car still racing, the next ``obstacles`` cars predicted at constant speed and lateral
    offset as moving obstacles (in a race of two cars: the race's game). Registered twice,
    with the car's default role in the name: ``ilqgame-leader`` (:class:`LeaderGameAgent`)
    and ``ilqgame-follower`` (:class:`FollowerGameAgent`); with ``role="auto"`` the two are
    the same planner.

    Args:
        role: ``"leader"`` (the car leads), ``"follower"`` (its rival leads) or ``"auto"``
            (the car ahead in race distance leads, judged at every re-plan: the
            position-dependent responsibility of Cinar and Laine, arXiv:2402.09548; equal
            distances to the lower car index). None: the class's :attr:`default_role`.
        obstacles: the cars after the rival predicted as moving obstacles (integer >= 1).
        certify: certify every adopted re-plan with
            :func:`planners.stackelberg.certify_stackelberg` (cheap form): diagnostics'
            ``certified`` (a local Stackelberg solution), ``verdict``, ``certify_time``.
        kwargs: as :class:`RecedingHorizonAgent` (no ``rivals``: the game has two players).

    Each adopted re-plan's diagnostics carry ``leader``: the car index of its leader.
    """

    mode = STACKELBERG
    feedback = True
    realtime_player_steps = True
    default_role = leader_follower.LEADER

    def __init__(self, role: str | None = None, obstacles: int = DEFAULT_OBSTACLES, certify: bool = False,
                 **kwargs: Any) -> None:
        if "rivals" in kwargs:
            raise ValueError(f"{self.spec} plays a game of exactly {leader_follower.PLAYERS} players (a leader and a "
                             f"follower): the car and its nearest rival; it takes no rivals option")
        self.role = leader_follower.check_role(self.default_role if role is None else role)
        super().__init__(rivals=1, obstacles=obstacles, certify=certify, **kwargs)

    @classmethod
    def spec_options(cls) -> dict[str, type]:
        options = {**super().spec_options(), "role": str}
        del options["rivals"]
        return options

    @classmethod
    def spec_defaults(cls) -> dict[str, Any]:
        defaults = {**super().spec_defaults(), "role": cls.default_role}
        del defaults["rivals"]
        return defaults

    def _plays_local_game(self, game) -> bool:
        return True  # the pair game, also in a race of two

    def _pair_game(self, game, x0, init, predicted=None) -> rival_game.LocalGame:
        self._validate(game)
        return leader_follower.pair_game(game, x0, self.index, self.role, init, predicted, self.obstacles)

    def _batchable(self, game, x0, init, predicted):
        if self.budget_ms is not None or game.num_players <= leader_follower.PLAYERS:
            return None  # a wall-clock budget, or the race's own game: solved by act()
        return self._pair_game(game, x0, init, predicted)

    def _from_result(self, local, result, init):
        self._solved = (local.problem, local.x0)
        self._leader = int(local.order[0])
        T, N = result.us.shape[0], local.order.shape[0]
        init = np.zeros((T, N, result.us.shape[-1])) if init is None else np.asarray(init, dtype=np.float64)
        xs, us, K = leader_follower.to_field_batch(
            np.asarray(local.order)[None], np.array([self.index]), np.asarray(result.xs)[None],
            np.asarray(result.us)[None], np.asarray(result.K)[None], init[None], np.asarray(local.others)[None])
        return us[0], xs[0], K[0], result

    def _adopted(self, game, x0, result, record):
        record["leader"] = self._leader
        if self.certify:
            problem, start = self._solved
            record.update(stackelberg_certificate_record(problem, start, result, self.batch_options()))

    def _solve(self, game, x0, init):
        self._solved = None
        local = self._pair_game(game, x0, init)
        res = ilq.solve(local.problem, local.x0, init=local.init, validate=False, mode=self.mode,
                        max_iterations=self.max_iterations, budget_ms=self.budget_ms, **self.solver_options)
        return self._from_result(local, jax.device_get(res), init)


class LeaderGameAgent(StackelbergGameAgent):
    """:class:`StackelbergGameAgent`, the car leading by default (``role="leader"``)."""

    spec = name = STACKELBERG_LEADER
    default_role = leader_follower.LEADER


class FollowerGameAgent(StackelbergGameAgent):
    """:class:`StackelbergGameAgent`, the car following by default (``role="follower"``)."""

    spec = name = STACKELBERG_FOLLOWER
    default_role = leader_follower.FOLLOWER


_ONE_SOLVE_PREDICTIONS = frozenset({CONSTANT_VELOCITY, LANE_KEEPING})


class ILQRAgent(RecedingHorizonAgent):
    """iLQR against predictions of the opponents (``planners.ilqr``).

    Args:
        prediction: how the opponents are predicted (:data:`planners.methods.PREDICTIONS`):
            ``"constant-velocity"`` (the paper's: constant speed and lateral offset),
            ``"lane-keeping"`` (each opponent driven by the scripted lane keeper's law
            through the environment's physics: exact against the lane keeper), ``"ilqr"``
            (each opponent's own iLQR plan against constant-velocity predictions: exact
            against an ``ilqr`` agent with the same weights and solver options), or
            ``"ilqgame-fb"`` / ``"ilqgame-ol"`` (the opponents' trajectories of the feedback
            / open-loop Nash equilibrium). The planned predictions use this agent's solver
            options and beliefs of the opponents' weights, are warm-started from the last
            prediction, and count in its ``solve_time``.
        rivals: for the game predictions (``"ilqgame-fb"``, ``"ilqgame-ol"``), the rivals in
            the game solved: in a race of more than ``rivals + 1`` cars the local game of this
            car and its nearest rivals (:mod:`planners.rival_game`); the cars left out are
            predicted at constant velocity. Ignored by the other predictions.
        levels: levels of reasoning of the ``"ilqr"`` prediction (see
            :class:`planners.prediction.PlannerPrediction`): ``1`` predicts each opponent's
            plan against constant velocity, ``k`` its plan against everyone's level-``k - 1``
            plans, this agent's included. The agent itself then plans at level ``k + 1``.
        kwargs: as :class:`RecedingHorizonAgent`.
    """

    spec = name = ILQR
    feedback = False

    def __init__(self, prediction: str = CONSTANT_VELOCITY, levels: int = 1, rivals: int = DEFAULT_RIVALS,
                 obstacles: int = DEFAULT_OBSTACLES, **kwargs: Any) -> None:
        prediction_models.check_prediction(prediction)  # when the agent is made, not at its reset
        self.rivals = rival_game.check_rivals(rivals)
        self.obstacles = _checked_obstacles(obstacles)
        prediction_models.check_levels(prediction, levels)
        if kwargs.get("budget_ms") is not None and prediction not in _ONE_SOLVE_PREDICTIONS:
            raise ValueError(f"budget_ms bounds one solve: iLQR takes it with prediction in "
                             f"{sorted(_ONE_SOLVE_PREDICTIONS)}, not with the planned prediction {prediction!r}")
        super().__init__(**kwargs)
        prediction_models.check_solver_options(prediction, max_iterations=self.max_iterations, **self.solver_options)
        self.prediction = prediction
        self.levels = int(levels)

    @classmethod
    def spec_options(cls) -> dict[str, type]:
        return {**super().spec_options(), "prediction": str, "levels": int, "rivals": int, "obstacles": int}

    @classmethod
    def spec_defaults(cls) -> dict[str, Any]:
        return {**super().spec_defaults(), "prediction": CONSTANT_VELOCITY, "levels": 1, "rivals": DEFAULT_RIVALS,
                "obstacles": DEFAULT_OBSTACLES}

    def reset(self, seed: int | None, index: int, env_info: Any) -> None:
        super().reset(seed, index, env_info)
        # A rollout predictor compiles its physics step at its first call: it is kept over
        # resets in the same game as the same car (predictors are stateless).
        made_for = getattr(self, "_predictor_for", None)
        if made_for is None or made_for[0] is not self.game or made_for[1] != self.index:
            self._predict = prediction_models.make_predictor(
                self.prediction, self.game, self.index, levels=self.levels, rivals=self.rivals, obstacles=self.obstacles,
                max_iterations=self.max_iterations,
                **self.solver_options)
            self._predictor_for = (self.game, self.index)

    def _solve(self, game, x0, init):
        predicted = others_us = None
        if self._predict is not None:
            predicted, others_us = self._predict(game, x0, init)
        res = ilqr.solve_ilqr(
            game,
            x0,
            ego=self.index,
            U0=init,
            predicted=predicted,
            max_iterations=self.max_iterations,
            budget_ms=self.budget_ms,
            **self.solver_options,
        )
        us = np.asarray(res.us)
        if others_us is not None:
            # the opponents' rows of the stored plan carry their predicted jerks: shifted,
            # they warm-start the next prediction (the ego follows only its own row)
            us = np.array(others_us)
            us[:, self.index] = np.asarray(res.us[:, self.index])
        return us, np.asarray(res.xs), None, res
