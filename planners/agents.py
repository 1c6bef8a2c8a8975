"""Competitors: one small protocol for every driver (game planners, scripted, RL).

Every agent implements :class:`Agent`::

    agent = make_agent("ilqgame-fb")
    agent.reset(seed=0, index=1, env_info=env)       # env: RacingParallelEnv (or its RaceGame)
    action = agent.act(observation, env.state())      # normalised jerks in [-1, 1]^2
    agent.diagnostics()                               # the last step: solve time, iterations, ...

and is a callable ``agent(observation, joint_state) -> action``, so it plugs into
``experiments.race.run_race`` and into the Gymnasium view as an opponent.

Receding-horizon planners (:class:`ILQRAgent`, :class:`OpenLoopGameAgent`,
:class:`FeedbackGameAgent`) re-solve the env's :class:`racing_env.RaceGame` from the current
joint state every ``replan_every`` steps, warm-started from the previous solution shifted by
the steps elapsed (the last input repeated, or zeros). Between re-plans the feedback agent
applies ``u = u_hat_t - K_t (x - x_hat_t)``, the others the planned ``u_hat_t``. A solve that
raises or returns non-finite values falls back to the previous plan (shifted) or, without
one, to a braking action with a lateral correction toward the centre line; actions are never
NaN. Cars that the observation flags as no longer racing (finished or retired: frozen by
the env, which no car collides with) are ghosts in the plan (``RaceGame.with_racing``): no
collision cost with them, and their progress does not count. The state's ``s`` is
cumulative on closed tracks; the game wraps it itself (curvature, widths and gaps), so the
agents pass the joint state through unchanged.
"""

from __future__ import annotations

import dataclasses
import inspect
import time
import traceback
from pathlib import Path
from typing import Any, Iterable, Protocol, Sequence, runtime_checkable

import numpy as np

from planners import ilq, ilqr, prediction as prediction_models
from planners.agent_specs import convert_options, describe_options, split_spec
from planners.scripted import ConstantSpeed, LaneKeeping, check_targets
from racing_env.dynamics import V
from racing_env.observation import cars_racing

__all__ = [
    "Agent",
    "AGENT_SPECS",
    "AGENT_SUMMARIES",
    "BaseAgent",
    "ConstantSpeedAgent",
    "FeedbackGameAgent",
    "ILQRAgent",
    "LaneKeepingAgent",
    "OpenLoopGameAgent",
    "RecedingHorizonAgent",
    "SB3Agent",
    "agent_options",
    "check_specs",
    "game_of",
    "make_agent",
    "reset_agents",
    "vecnormalize_path",
]


@runtime_checkable
class Agent(Protocol):
    """What every competitor implements.

    ``reset(seed, index, env_info)``: start a race as car ``index``; ``env_info`` is the
    :class:`racing_env.RacingParallelEnv` (or the Gymnasium ``RaceEnv``, or just the
    :class:`racing_env.RaceGame`): from it the agent takes the game (track, vehicles,
    weights, ``dt``, horizon).
    ``act(observation, joint_state)``: the normalised action ``(2,)`` in ``[-1, 1]``.
    ``diagnostics()``: the last step's record (``solve_time`` [s], ``iterations``,
    ``converged``, ``fallback``, ``error``, ...).
    """

    name: str

    def reset(self, seed: int | None, index: int, env_info: Any) -> None: ...

    def act(self, observation: np.ndarray, joint_state: np.ndarray) -> np.ndarray: ...

    def diagnostics(self) -> dict: ...

    def __call__(self, observation: np.ndarray, joint_state: np.ndarray) -> np.ndarray: ...


def game_of(env_info: Any):
    """The :class:`racing_env.RaceGame` of an env (parallel or Gymnasium view) or a game."""
    from racing_env.game import RaceGame

    if isinstance(env_info, RaceGame):
        return env_info
    for attr in ("game", "race", "unwrapped"):
        inner = getattr(env_info, attr, None)
        if inner is None or inner is env_info:
            continue
        if isinstance(inner, RaceGame):
            return inner
        try:
            return game_of(inner)
        except TypeError:
            continue
    raise TypeError(
        f"env_info must be a RacingParallelEnv, a RaceEnv or a RaceGame, got {type(env_info).__name__}"
    )


def _observation_space_of(env_info: Any, index: int):
    """Car ``index``'s observation space in an env (parallel or Gymnasium view, found as
    :func:`game_of` finds the game), or None for a bare game, which has none."""
    if callable(getattr(env_info, "observation_space", None)) and hasattr(env_info, "possible_agents"):
        return env_info.observation_space(env_info.possible_agents[index])  # PettingZoo: one space per agent
    for attr in ("race", "unwrapped"):
        inner = getattr(env_info, attr, None)
        if inner is not None and inner is not env_info:
            return _observation_space_of(inner, index)
    return None


def _finite(solution: tuple) -> bool:
    """Whether a solver's ``(us, xs, K or None, result)`` plan arrays are all finite."""
    return all(np.all(np.isfinite(part)) for part in solution[:3] if part is not None)


def _empty_record() -> dict:
    return {
        "step": 0,
        "replanned": False,
        "solve_time": None,
        "iterations": None,
        "converged": None,
        "status": None,
        "fallback": False,
        "fallback_kind": None,
        "error": None,
        "clipped": False,
    }


class BaseAgent:
    """Common bookkeeping: index, game, jerk limits, the per-step diagnostics history."""

    name = "agent"

    @classmethod
    def spec_options(cls) -> dict[str, type]:
        """The options an agent spec may set (``name:option=value,...``) and their types."""
        return {}

    @classmethod
    def spec_defaults(cls) -> dict[str, Any]:
        """The value each spec option has when the spec leaves it out (for help text)."""
        return {}

    @classmethod
    def spec_help(cls) -> dict[str, str]:
        """One line on what each spec option does (for help text)."""
        return {}

    @classmethod
    def from_spec_options(cls, options: dict[str, Any], **kwargs: Any) -> "BaseAgent":
        """The agent with converted spec options (keyword arguments win over them)."""
        return cls(**{**options, **kwargs})

    def __init__(self) -> None:
        self.index: int | None = None
        self.game = None
        self.history: list[dict] = []
        self._last: dict = _empty_record()
        self._steps = 0

    def reset(self, seed: int | None, index: int, env_info: Any) -> None:
        game = game_of(env_info)
        n = game.num_players
        if not 0 <= int(index) < n:
            raise ValueError(f"index must be a car index in [0, {n}), got {index!r}")
        self.seed = seed
        self.index = int(index)
        self.game = game
        self.dt = float(game.dt)
        self.vehicle = game.vehicles.car(self.index)
        self.jerk_max = np.array([self.vehicle.jx_max, self.vehicle.jy_max], dtype=np.float64)
        self.history = []
        self._last = _empty_record()
        self._steps = 0

    def _require_reset(self) -> None:
        if self.index is None:
            raise RuntimeError(f"{type(self).__name__}.reset(seed, index, env_info) must be called first")

    def _safe_action(self, joint_state: np.ndarray | None) -> np.ndarray:
        """Brake gently and steer back toward the centre line (finite for any input).

        Longitudinal: jerk toward ``ax = -0.3 rho(V)`` (a third of the grip: firm but leaves
        room to corner), at most half the jerk limit, zero target at standstill. Lateral: the
        lane keeper's law toward ``n = 0`` (curvature feed-forward plus a critically damped
        correction). Falls back to ``[-0.5, 0]`` if the car's own state is not finite.
        """
        fixed = np.array([-0.5, 0.0], dtype=np.float32)
        try:
            x = np.asarray(joint_state, dtype=np.float64)[self.index]
        except Exception:  # noqa: BLE001 - any malformed state: the constant braking action
            return fixed
        if x.shape != (6,) or not np.all(np.isfinite(x)):
            return fixed
        s, v, n, chi, ax, ay = x
        v_pos = max(v, 0.0)
        rho = float(self.vehicle.rho(v_pos))
        ax_des = -0.3 * rho if v_pos > 0.5 else 0.0
        kappa = float(self.game.track.kappa_at(s))
        ay_des = kappa * v**2 + 1.0 * (0.0 - n) - 2.0 * v * np.sin(chi)
        jerk = 5.0 * np.array([ax_des - ax, ay_des - ay])
        a = jerk / self.jerk_max
        a[0] = np.clip(a[0], -0.5, 0.5)
        a = np.clip(a, -1.0, 1.0)
        return a.astype(np.float32) if np.all(np.isfinite(a)) else fixed

    def _finish(self, action, joint_state, record: dict) -> np.ndarray:
        a = np.asarray(action, dtype=np.float64).reshape(-1)
        if a.shape != (2,) or not np.all(np.isfinite(a)):
            record["fallback"] = True
            record["fallback_kind"] = "brake"
            record["error"] = (record.get("error") or "") + "; non-finite action replaced by braking"
            a = self._safe_action(joint_state).astype(np.float64)
        # a planned jerk beyond the car's limits is driven at the limit: say so
        record["clipped"] = bool(np.any(np.abs(a) > 1.0))
        a = np.clip(a, -1.0, 1.0).astype(np.float32)
        record["action"] = a.tolist()
        self._last = record
        self.history.append(record)
        self._steps += 1
        return a

    def act(self, observation: np.ndarray, joint_state: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _act_guarded(self, policy, observation: np.ndarray, joint_state: np.ndarray) -> np.ndarray:
        """Act with ``policy(observation, joint_state)``, timed; braking if it raises."""
        self._require_reset()
        record = _empty_record()
        record["step"] = self._steps
        t0 = time.perf_counter()
        try:
            action = policy(observation, joint_state)
        except Exception as exc:  # noqa: BLE001 - any policy failure: brake, and say why
            record.update(fallback=True, fallback_kind="brake", error=f"{type(exc).__name__}: {exc}")
            action = self._safe_action(joint_state)
        record["solve_time"] = time.perf_counter() - t0
        return self._finish(action, joint_state, record)

    def __call__(self, observation: np.ndarray, joint_state: np.ndarray) -> np.ndarray:
        return self.act(observation, joint_state)

    def diagnostics(self) -> dict:
        """The last step's record (a copy)."""
        return dict(self._last)

    def summary(self) -> dict:
        """Aggregates over the steps since reset: re-plans, solve-time percentiles, fallbacks."""
        times = np.array([r["solve_time"] for r in self.history if r.get("solve_time") is not None])
        iters = [r["iterations"] for r in self.history if r.get("iterations") is not None]
        converged = [bool(r["converged"]) for r in self.history if r.get("converged") is not None]
        out = {
            "steps": len(self.history),
            "replans": int(sum(bool(r.get("replanned")) for r in self.history)),
            "fallbacks": int(sum(bool(r.get("fallback")) for r in self.history)),
            # share of re-plans that met the solver's tolerance (the rest use the last iterate)
            "converged_fraction": float(np.mean(converged)) if converged else None,
            # share of steps whose action exceeded the jerk limits and was clipped to them
            "clipped_fraction": float(np.mean([bool(r.get("clipped")) for r in self.history]))
            if self.history else None,
        }
        recovering = [bool(r["recovering"]) for r in self.history if r.get("recovering") is not None]
        if any(recovering):  # re-plans made in recovery from a standstill (recovery_track_scale)
            out["recovery_replans"] = int(sum(recovering))
        leading = [bool(r["leading"]) for r in self.history if r.get("leading") is not None]
        if leading:  # place-dependent weights: share of re-plans made in the lead
            out["leading_fraction"] = float(np.mean(leading))
        if times.size:
            out.update(
                solve_time_median=float(np.median(times)),
                solve_time_p95=float(np.percentile(times, 95)),
                solve_time_max=float(times.max()),
                iterations_mean=float(np.mean(iters)) if iters else None,
            )
        return out


# --------------------------------------------------------------------------------------
# Receding-horizon game planners.
# --------------------------------------------------------------------------------------


STOPPED_SPEED = 0.5  # [m/s] a car this slow at a re-plan is stuck: it plans in recovery (below)
RECOVERED_SPEED = 5.0  # [m/s] and it plans normally again once this fast
REPLAN_TOLERANCE = 1e-3
"""Convergence tolerance of a re-plan [state units: m, m/s, ...]: a millimetre is plenty for
a plan that is re-solved 0.1 s later. Measured (feedback iLQGame vs the lane keeper, a lap of
the trefoil, r = 0.01): with the solver's default 1e-6 two thirds of the re-plans converge
within 30 iterations (mean 24), with 1e-3 three quarters (mean 20), same race result."""


def _weights_for(game, index: int, belief) -> Any:
    """The game's weights with the agent's belief about the others (``None``: the truth).

    ``belief`` is one ``CostWeights`` (scalars) assumed for every opponent (the agent keeps
    its own true weights), a sequence of N ``CostWeights`` (one per car, used as given), or a
    stacked ``CostWeights`` with ``(N,)`` fields.
    """
    from racing_env.costs import CostWeights, stack_weights

    if belief is None:
        return game.weights
    n = game.num_players
    if isinstance(belief, CostWeights):
        if np.ndim(belief.r_jx) == 0:  # one belief for every opponent, own weights kept
            names = [f.name for f in dataclasses.fields(CostWeights)]
            own = CostWeights(**{k: float(np.asarray(getattr(game.weights, k))[index]) for k in names})
            return stack_weights([own if j == index else belief for j in range(n)])
        if np.shape(belief.r_jx) != (n,):
            raise ValueError(f"stacked belief_weights must have fields of shape ({n},)")
        return belief
    belief = list(belief)
    if len(belief) != n:
        raise ValueError(f"belief_weights needs {n} CostWeights (one per car), got {len(belief)}")
    return stack_weights(belief)


def _weight_names() -> list[str]:
    from racing_env.costs import CostWeights

    return [f.name for f in dataclasses.fields(CostWeights)]


def _checked_weight_changes(label: str, changes: Any) -> dict[str, float]:
    """``{field: value}`` of :class:`racing_env.CostWeights` changes, checked like the weights."""
    from racing_env.costs import CostWeights

    changes = dict(changes or {})
    unknown = sorted(set(changes) - set(_weight_names()))
    if unknown:
        raise ValueError(f"{label}: unknown cost weights {unknown}; the fields are {_weight_names()}")
    values = {k: float(v) for k, v in changes.items()}
    try:
        CostWeights(**values)  # refuses e.g. a negative collision weight, with the field's rule
    except ValueError as err:
        raise ValueError(f"{label}: {err}") from None
    return values


def _with_player_weights(weights, players: int | Sequence[int], changes: dict[str, float]):
    """Stacked weights ``(N,)`` with the fields in ``changes`` replaced for ``players``."""
    if not changes:
        return weights
    n = np.shape(weights.r_jx)[0]
    fields = {}
    for name in _weight_names():
        column = np.array(np.broadcast_to(np.asarray(getattr(weights, name), dtype=np.float64), (n,)))
        if name in changes:
            column[players] = changes[name]
        fields[name] = column
    return type(weights)(**fields)


_PLACE_PREFIXES = ("leading", "trailing")
_WEIGHT_PREFIXES = {"leading": "leading_weights", "trailing": "trailing_weights", "belief": "opponent_weights"}


class RecedingHorizonAgent(BaseAgent):
    """Re-plans a game (or iLQR) solution from the current joint state.

    Args:
        max_iterations: solver iteration cap per re-plan.
        replan_every: re-plan every this many steps (1: every step); in between the stored
            plan is followed (with its feedback law for the feedback game).
        belief_weights: the agent's belief of the cost weights (see :func:`_weights_for`);
            default the game's true weights.
        pad: how the shifted warm start is padded at the end: ``"repeat"`` the last input
            or ``"zeros"``.
        warm_start: warm start from the previous solution (else zeros every re-plan).
        require_converged: treat a non-converged solve as a failure (fallback); by default
            the last iterate is used (it is a dynamically feasible, finite plan).
        recovery_track_scale: factor on the car's own track weight ``c_track`` in the
            re-plans of a recovery: from a re-plan at which the car is slower than
            :data:`STOPPED_SPEED` until one at which it is at least :data:`RECOVERED_SPEED`.
            A car that has stopped at the edge facing out (it cannot reverse or turn on the
            spot) can only rejoin across the boundary; over a 5 s horizon standing still is
            cheaper at full weight, so without this it stands for good. ``0`` (the default)
            drops the track term while recovering: a car stopped across the track in a
            tight corner may need several metres of run-off to turn, which 1e-3 (the
            earlier default) still priced above standing still. ``1`` turns it off.
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
        solver_options: further :class:`planners.ilq.SolverOptions` fields; the
            ``tolerance`` defaults to :data:`REPLAN_TOLERANCE`. Checked here, so a bad
            option fails when the agent is made.
    """

    name = "receding-horizon"
    feedback = False
    mode = "feedback"  # the solver mode of its plans (iLQR's is a one-player feedback solve)
    planned_players = 1  # players of its own solve: 1 for iLQR, 2 (or more) for a game

    def __init__(
        self,
        max_iterations: int = 30,
        replan_every: int = 1,
        belief_weights=None,
        pad: str = "repeat",
        warm_start: bool = True,
        require_converged: bool = False,
        recovery_track_scale: float = 0.0,
        own_weights: dict[str, float] | None = None,
        leading_weights: dict[str, float] | None = None,
        trailing_weights: dict[str, float] | None = None,
        opponent_weights: dict[str, float] | None = None,
        **solver_options: Any,
    ) -> None:
        super().__init__()
        if int(replan_every) < 1:
            raise ValueError(f"replan_every must be >= 1, got {replan_every!r}")
        if pad not in ("repeat", "zeros"):
            raise ValueError(f"pad must be 'repeat' or 'zeros', got {pad!r}")
        self.max_iterations = int(max_iterations)
        self.replan_every = int(replan_every)
        self.belief_weights = belief_weights
        self.pad = pad
        self.warm_start = bool(warm_start)
        self.require_converged = bool(require_converged)
        if not 0.0 <= float(recovery_track_scale) <= 1.0:
            raise ValueError(f"recovery_track_scale must be in [0, 1], got {recovery_track_scale!r}")
        self.recovery_track_scale = float(recovery_track_scale)
        self.own_weights = _checked_weight_changes("own_weights", own_weights)
        self.leading_weights = _checked_weight_changes("leading_weights", leading_weights)
        self.trailing_weights = _checked_weight_changes("trailing_weights", trailing_weights)
        self.opponent_weights = _checked_weight_changes("opponent_weights", opponent_weights)
        self.solver_options = {"tolerance": REPLAN_TOLERANCE, **solver_options}
        unknown = sorted(set(self.solver_options) - set(self._solver_option_types()) - {"mode"})
        if unknown:
            raise ValueError(f"unknown solver options {unknown}; allowed: {sorted(self._solver_option_types())}")
        # refuses bad values (max_iterations too) now, not at the first solve
        options = ilq.SolverOptions(**{"mode": self.mode, "max_iterations": self.max_iterations,
                                       **self.solver_options})
        ilq.check_adaptive_regularization(options, self.planned_players)

    @staticmethod
    def _solver_option_types() -> dict[str, type]:
        return {f.name: type(f.default) for f in dataclasses.fields(ilq.SolverOptions)
                if f.name not in ("mode", "max_iterations")}

    @classmethod
    def spec_options(cls) -> dict[str, type]:
        options = {"max_iterations": int, "replan_every": int, "pad": str, "warm_start": bool,
                   "require_converged": bool, "recovery_track_scale": float,
                   **cls._solver_option_types()}
        for name in _weight_names():
            options[name] = float
            options.update({f"{prefix}.{name}": float for prefix in _WEIGHT_PREFIXES})
        return options

    @classmethod
    def spec_defaults(cls) -> dict[str, Any]:
        defaults = {f.name: f.default for f in dataclasses.fields(ilq.SolverOptions)}
        loop = inspect.signature(RecedingHorizonAgent.__init__).parameters  # the loop's own defaults
        defaults.update({name: loop[name].default for name in
                         ("max_iterations", "replan_every", "pad", "warm_start", "require_converged",
                          "recovery_track_scale")})
        defaults["tolerance"] = REPLAN_TOLERANCE
        for name in _weight_names():
            defaults[name] = "the race's"
            defaults.update({f"{place}.{name}": name for place in _PLACE_PREFIXES})
            defaults[f"belief.{name}"] = "the race's"
        return defaults

    @classmethod
    def spec_help(cls) -> dict[str, str]:
        lines = {
            "max_iterations": "solver iterations per re-plan; the last iterate is used if it has not converged",
            "replan_every": "re-plan every this many steps and follow the stored plan in between",
            "pad": "end of the shifted warm start: repeat (the last input) or zeros",
            "warm_start": "start each re-plan from the previous plan (false: from zero inputs)",
            "require_converged": "treat a re-plan that did not converge as a failure (previous plan, else brake)",
            "recovery_track_scale": f"factor on own c_track from a standstill (< {STOPPED_SPEED} m/s) until "
                                    f"{RECOVERED_SPEED} m/s, to rejoin across the edge (0: no track term then; 1: off)",
            "tolerance": "convergence: largest state change of a full step [m, m/s, ...]",
            "step_control": ("trust_region (shrink the step to stay inside trust_radius), residual (ilqgame-ol "
                             "only: also until the open-loop Nash residual decreases) or none (fixed step)"),
            "trust_radius": "largest accepted change of the state trajectory per iteration",
            "initial_step": "the first step size tried, in (0, 1]",
            "step_decay": "factor by which the step size shrinks per trial, in (0, 1)",
            "max_backtracks": "step-size trials after the first before the search gives up",
            "oscillation_damping": "start shorter after a step that reverses the recent direction",
            "damping_memory": "decay of the running sum of step directions, in [0, 1)",
            "state_regularization": "added to the diagonal of every Q",
            "control_regularization": ("added to the diagonal of every R^ii, or with feedforward_regularization "
                                       "to the feed-forward rows of the step (with adaptive_regularization: "
                                       "its start and floor after a reversal)"),
            "adaptive_regularization": ("shrink control_regularization while the iterates keep their "
                                        "direction, raise it when they reverse (ilqgame-fb: with "
                                        "feedforward_regularization only)"),
            "feedforward_regularization": ("ilqgame-fb and ilqr (not ilqgame-ol): control_regularization "
                                           "damps the feed-forward terms only, so the plans stay feedback "
                                           "equilibria"),
            "regularization_factor": "factor of each change of the adaptive regularization, > 1",
            "convexify": "auto, gauss_newton, eig, diag or none: how the cost Hessians are made convex",
            "dynamics_curvature": ("give each car's local game the curvature of its progress in its "
                                   "heading, which linearising the dynamics drops (false: the plain iLQ model)"),
        }
        weights = {"r_jx": "longitudinal jerk weight", "r_jy": "lateral jerk weight",
                   "c_collision": "collision weight c_c", "c_track": "track-boundary weight c_w",
                   "c_ax": "weight on exceeding ax_max(V)",
                   "c_acc": "weight on exceeding the gg radius and the turn limit",
                   "c_gap": "weight c_g of the others' progress at the horizon",
                   "c_reverse": "weight on negative speed (the cars have no reverse gear)"}
        lines.update({name: f"{weights.get(name, name)} of this car in its own plans only"
                      for name in _weight_names()})
        for place in _PLACE_PREFIXES:
            lines.update({f"{place}.{name}": f"{name} in re-plans made while the car is {place}"
                          for name in _weight_names()})
        lines.update({f"belief.{name}": f"the {name} this agent believes every other car has"
                      for name in _weight_names()})
        return lines

    @classmethod
    def from_spec_options(cls, options: dict[str, Any], **kwargs: Any) -> "RecedingHorizonAgent":
        grouped: dict[str, Any] = {"own_weights": {}, **{name: {} for name in _WEIGHT_PREFIXES.values()}}
        for key, value in options.items():
            prefix, dot, field = key.partition(".")
            if dot:
                grouped[_WEIGHT_PREFIXES[prefix]][field] = value
            elif key in _weight_names():
                grouped["own_weights"][key] = value
            else:
                grouped[key] = value
        return cls(**{**grouped, **kwargs})

    def reset(self, seed: int | None, index: int, env_info: Any) -> None:
        super().reset(seed, index, env_info)
        weights = _weights_for(self.game, self.index, self.belief_weights)
        others = [j for j in range(self.game.num_players) if j != self.index]
        weights = _with_player_weights(weights, others, self.opponent_weights)
        weights = _with_player_weights(weights, self.index, self.own_weights)
        self.planning_game = self.game.replace(weights=weights)
        self._games_by_place = None  # {leading?: game} when the weights depend on the place
        if self.leading_weights or self.trailing_weights:
            self._games_by_place = {
                True: self.game.replace(weights=_with_player_weights(weights, self.index, self.leading_weights)),
                False: self.game.replace(weights=_with_player_weights(weights, self.index, self.trailing_weights)),
            }
        self._plan: dict | None = None  # {"us": (T,N,2), "xs": (T+1,N,6), "K": (T,N,2,6N) | None}
        self._age = 0  # steps since the stored plan was made
        self._recovering = False  # from a standstill until RECOVERED_SPEED (recovery_track_scale)

    def _is_leading(self, x: np.ndarray, racing: np.ndarray | None = None) -> bool:
        """Ahead of every other car still racing in race distance (``s`` is cumulative, laps
        included); ``racing (N,)`` bool, None: all. A car that finished or retired is out of
        the contest: the others race for the places behind it."""
        rivals = [j for j in range(x.shape[0]) if j != self.index and (racing is None or racing[j])]
        return bool(np.all(x[self.index, 0] > x[rivals, 0]))

    # the solve itself (subclasses) -> (us, xs, K or None, result)
    def _solve(self, game, x0: np.ndarray, init: np.ndarray | None):
        raise NotImplementedError

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
        return game.replace(weights=_with_player_weights(game.weights, self.index, changes))

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
                u = u - plan["K"][t, self.index] @ dx
        return u

    def act(self, observation: np.ndarray, joint_state: np.ndarray) -> np.ndarray:
        self._require_reset()
        x = np.asarray(joint_state, dtype=np.float64)
        record = _empty_record()
        record["step"] = self._steps
        if self._plan is None or self._age + 1 >= self.replan_every or self._age + 1 >= self._plan["us"].shape[0]:
            record["replanned"] = True
            init = None
            if self.warm_start and self._plan is not None:
                init = self._shifted(self._plan["us"], self._age + 1)
            error = None
            t0 = time.perf_counter()
            try:
                if x.shape != (self.game.num_players, 6):
                    raise ValueError(f"joint state must have shape ({self.game.num_players}, 6), got {x.shape}")
                racing = cars_racing(observation, self.index, self.game.num_players)
                if self._games_by_place is not None:
                    record["leading"] = self._is_leading(x, racing)
                    self.planning_game = self._games_by_place[record["leading"]]
                # cars that finished or retired are ghosts in the plan, as in the env
                game = self._game_at_speed(x, record).with_racing(racing)
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
            record["solve_time"] = time.perf_counter() - t0
            if error is None:
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


class _GameAgent(RecedingHorizonAgent):
    planned_players = 2  # at least: every car of the race

    def _solve(self, game, x0, init):
        res = ilq.solve(
            game,
            x0,
            init=init,
            mode=self.mode,
            max_iterations=self.max_iterations,
            **self.solver_options,
        )
        us, xs, K = (np.asarray(a) for a in (res.us, res.xs, res.K))
        return us, xs, (K if self.feedback else None), res


class FeedbackGameAgent(_GameAgent):
    """Feedback Nash iLQGame; between re-plans ``u = u_hat_t - K_t (x - x_hat_t)``."""

    name = "ilqgame-fb"
    mode = "feedback"
    feedback = True


class OpenLoopGameAgent(_GameAgent):
    """Open-loop Nash iLQGame; applies the planned ``u_hat_t``."""

    name = "ilqgame-ol"
    mode = "open_loop"
    feedback = False


class ILQRAgent(RecedingHorizonAgent):
    """iLQR against predictions of the opponents (``planners.ilqr``).

    Args:
        prediction: how the opponents are predicted (:data:`planners.prediction.PREDICTIONS`):
            ``"constant-velocity"`` (the paper's: constant speed and lateral offset),
            ``"lane-keeping"`` (each opponent driven by the scripted lane keeper's law
            through the environment's physics: exact against the lane keeper), ``"ilqr"``
            (each opponent's own iLQR plan against constant-velocity predictions: exact
            against an ``ilqr`` agent with the same weights and solver options), or
            ``"ilqgame-fb"`` / ``"ilqgame-ol"`` (the opponents' trajectories of the feedback
            / open-loop Nash equilibrium). The planned predictions use this agent's solver
            options and beliefs of the opponents' weights, are warm-started from the last
            prediction, and count in its ``solve_time``.
        levels: levels of reasoning of the ``"ilqr"`` prediction (see
            :class:`planners.prediction.PlannerPrediction`): ``1`` predicts each opponent's
            plan against constant velocity, ``k`` its plan against everyone's level-``k - 1``
            plans, this agent's included. The agent itself then plans at level ``k + 1``.
        kwargs: as :class:`RecedingHorizonAgent`.
    """

    name = "ilqr"
    feedback = False

    def __init__(self, prediction: str = prediction_models.CONSTANT_VELOCITY, levels: int = 1,
                 **kwargs: Any) -> None:
        prediction_models.check_prediction(prediction)  # when the agent is made, not at its reset
        prediction_models.check_levels(prediction, levels)
        super().__init__(**kwargs)
        prediction_models.check_solver_options(prediction, max_iterations=self.max_iterations, **self.solver_options)
        self.prediction = prediction
        self.levels = int(levels)

    @classmethod
    def spec_options(cls) -> dict[str, type]:
        return {**super().spec_options(), "prediction": str, "levels": int}

    @classmethod
    def spec_defaults(cls) -> dict[str, Any]:
        return {**super().spec_defaults(), "prediction": prediction_models.CONSTANT_VELOCITY, "levels": 1}

    @classmethod
    def spec_help(cls) -> dict[str, str]:
        return {**super().spec_help(),
                "prediction": "how the opponents are predicted: constant-velocity (the paper's), "
                              "lane-keeping (driven by the scripted lane keeper's law), ilqr (each one's own "
                              "iLQR plan), ilqgame-fb or ilqgame-ol (the game's feedback / open-loop Nash "
                              "equilibrium)",
                "levels": "levels of reasoning of prediction=ilqr: each opponent's plan against everyone's plans "
                          "one level down, level 0 being constant velocity"}

    def reset(self, seed: int | None, index: int, env_info: Any) -> None:
        super().reset(seed, index, env_info)
        # A rollout predictor compiles its physics step at its first call (about 0.5 s):
        # it is kept over resets in the same game as the same car (predictors are stateless).
        made_for = getattr(self, "_predictor_for", None)
        if made_for is None or made_for[0] is not self.game or made_for[1] != self.index:
            self._predict = prediction_models.make_predictor(
                self.prediction, self.game, self.index, levels=self.levels, max_iterations=self.max_iterations,
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
            **self.solver_options,
        )
        us = np.asarray(res.us)
        if others_us is not None:
            # the opponents' rows of the stored plan carry their predicted jerks: shifted,
            # they warm-start the next prediction (the ego follows only its own row)
            us = np.array(others_us)
            us[:, self.index] = np.asarray(res.us[:, self.index])
        return us, np.asarray(res.xs), None, res


# --------------------------------------------------------------------------------------
# Scripted baselines.
# --------------------------------------------------------------------------------------


class _ScriptedAgent(BaseAgent):
    controller_class: type = LaneKeeping

    def __init__(self, **kwargs: Any) -> None:
        super().__init__()
        unknown = sorted(set(kwargs) - set(self.spec_options()))
        if unknown:
            raise ValueError(f"{self.name} has no option {unknown}; its options: {sorted(self.spec_options())}")
        check_targets(**kwargs)  # before the race, not at the controller's reset
        self.kwargs = kwargs
        self.controller = None

    @classmethod
    def spec_options(cls) -> dict[str, type]:
        return {"target_speed": float, "target_n": float}

    @classmethod
    def spec_defaults(cls) -> dict[str, Any]:
        return {"target_speed": "v_max", "target_n": 0.0}

    @classmethod
    def spec_help(cls) -> dict[str, str]:
        return {"target_speed": "cruise speed [m/s]", "target_n": "lateral offset to hold [m], positive left"}

    def reset(self, seed: int | None, index: int, env_info: Any) -> None:
        super().reset(seed, index, env_info)
        self.controller = self.controller_class(
            self.game.track, self.index, self.game.vehicles.car(self.index), **self.kwargs
        )

    def act(self, observation: np.ndarray, joint_state: np.ndarray) -> np.ndarray:
        return self._act_guarded(self.controller, observation, joint_state)


class LaneKeepingAgent(_ScriptedAgent):
    """:class:`planners.scripted.LaneKeeping` (kwargs: ``target_speed``, ``target_n``)."""

    name = "lane-keeping"
    controller_class = LaneKeeping


class ConstantSpeedAgent(_ScriptedAgent):
    """:class:`planners.scripted.ConstantSpeed` (kwargs: ``target_speed``)."""

    name = "constant-speed"
    controller_class = ConstantSpeed

    @classmethod
    def spec_options(cls) -> dict[str, type]:
        return {"target_speed": float}

    @classmethod
    def spec_defaults(cls) -> dict[str, Any]:
        return {"target_speed": 15.0}


# --------------------------------------------------------------------------------------
# Reinforcement learning.
# --------------------------------------------------------------------------------------

SB3_ALGOS = ("ppo", "sac", "td3", "a2c", "ddpg")


VECNORMALIZE_SUFFIX = ".vecnormalize.pkl"


def vecnormalize_path(model_path) -> Path:
    """Where the observation statistics of a model trained under ``VecNormalize`` are kept:
    beside the model, ``model.zip`` -> ``model.vecnormalize.pkl``."""
    path = Path(model_path)
    stem = path.name[: -len(".zip")] if path.name.endswith(".zip") else path.name
    return path.with_name(stem + VECNORMALIZE_SUFFIX)


def _observation_normalizer(path: Path, model):
    """The saved ``VecNormalize`` of a model, frozen (statistics no longer updated), used
    through its public ``normalize_obs``; it wraps a stand-in env that only has the spaces."""
    import gymnasium
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    class _Spaces(gymnasium.Env):
        observation_space, action_space = model.observation_space, model.action_space

    normalizer = VecNormalize.load(str(path), DummyVecEnv([_Spaces]))
    normalizer.training = False
    normalizer.norm_reward = False
    return normalizer


class SB3Agent(BaseAgent):
    """A saved stable-baselines3 model acting with ``predict(obs, deterministic=True)``.

    If the model was trained under ``VecNormalize`` (as ``racing train`` does by default),
    its observation statistics are loaded from beside the model
    (:func:`vecnormalize_path`) and applied to every observation.

    Args:
        path: the ``.zip`` written by ``model.save``.
        algo: ``ppo``, ``sac``, ``td3``, ``a2c``, ``ddpg``; ``None`` tries them in this order.
        device: torch device for the policy (``cpu`` by default).
    """

    name = "rl"

    def __init__(self, path, algo: str | None = None, device: str = "cpu") -> None:
        super().__init__()
        import stable_baselines3 as sb3

        self.path = str(path)
        if algo is not None and algo.lower() not in SB3_ALGOS:
            raise ValueError(f"algo must be one of {SB3_ALGOS}, got {algo!r}")
        candidates = [algo.lower()] if algo else list(SB3_ALGOS)
        errors = []
        self.model = None
        for name in candidates:
            try:
                self.model = getattr(sb3, name.upper()).load(self.path, device=device)
                self.algo = name
                break
            except Exception as exc:  # noqa: BLE001 - try the next algorithm
                errors.append(f"{name}: {type(exc).__name__}: {exc}")
        if self.model is None:
            raise ValueError(f"could not load a stable-baselines3 model from {self.path}: " + "; ".join(errors))
        self.name = f"rl:{self.algo}"
        stats = vecnormalize_path(self.path)
        self.normalizer = _observation_normalizer(stats, self.model) if stats.exists() else None

    def reset(self, seed: int | None, index: int, env_info: Any) -> None:
        """As every agent's; also refuses a race whose observations the model cannot read
        (another number of cars or preview), which would otherwise only brake each step."""
        super().reset(seed, index, env_info)
        space = _observation_space_of(env_info, self.index)
        expected = self.model.observation_space.shape
        if space is not None and space.shape != expected:
            raise ValueError(
                f"{self.path} reads observations of shape {expected}, and car {self.index} of this "
                f"{self.game.num_players}-car race observes {space.shape}: trained with another number of cars "
                "or preview distances? (A time-trial model races alone, racing tournament --cars 1; "
                "racing train --init-model carries it into a race with more cars.)"
            )
        if seed is not None:
            try:
                self.model.set_random_seed(seed)
            except Exception:  # noqa: BLE001 - seeding is best effort
                pass

    def _predict(self, observation: np.ndarray, joint_state: np.ndarray) -> np.ndarray:
        obs = np.asarray(observation, dtype=np.float32)
        expected = self.model.observation_space.shape
        if obs.shape != expected:
            raise ValueError(
                f"observation shape {obs.shape} does not match the model's {expected} "
                "(trained with a different number of cars or preview distances?)"
            )
        if self.normalizer is not None:
            obs = self.normalizer.normalize_obs(obs)
        action, _ = self.model.predict(obs, deterministic=True)
        return action

    def act(self, observation: np.ndarray, joint_state: np.ndarray) -> np.ndarray:
        return self._act_guarded(self._predict, observation, joint_state)


# --------------------------------------------------------------------------------------
# Factory.
# --------------------------------------------------------------------------------------

AGENT_SPECS = {
    "ilqr": ILQRAgent,
    "ilqgame-ol": OpenLoopGameAgent,
    "ilqgame-fb": FeedbackGameAgent,
    "lane-keeping": LaneKeepingAgent,
    "constant-speed": ConstantSpeedAgent,
}

AGENT_SUMMARIES = {
    "ilqr": "iLQR against predictions of the opponents (the paper's: constant velocity and offset)",
    "ilqgame-ol": "open-loop Nash iLQGame, re-planned every step",
    "ilqgame-fb": "feedback Nash iLQGame, re-planned every step, its feedback law applied in between",
    "lane-keeping": "scripted: holds a lateral offset at a cruise speed, slowing for curves within grip",
    "constant-speed": "scripted: the centre line at a constant speed (slowing only for curves)",
}
"""One line per agent name, for help text."""


def make_agent(spec: str, **kwargs: Any) -> Agent:
    """An agent from a spec: ``ilqr``, ``ilqgame-ol``, ``ilqgame-fb``, ``lane-keeping``,
    ``constant-speed`` or ``rl:path/to/model.zip`` (``rl:sac:path`` names the algorithm).

    A non-RL spec may carry options, ``name:option=value,...`` (see
    :mod:`planners.agent_specs` and :func:`agent_options`), e.g.
    ``ilqgame-fb:max_iterations=100,c_collision=1``. ``kwargs`` go to the agent's
    constructor and win over the spec's options. Raises ``ValueError`` for an unknown spec,
    an unknown option or a bad value.
    """
    valid = list(AGENT_SPECS) + ["rl:<path/to/model.zip>", "rl:<algo>:<path>"]
    if not isinstance(spec, str):
        raise ValueError(f"agent spec must be a string, one of {valid}; got {spec!r}")
    key = spec.strip()
    if not key:
        raise ValueError(f"agent spec is empty; valid specs: {', '.join(valid)}")
    if key.lower().startswith("rl:"):
        rest = key[3:]
        head, sep, tail = rest.partition(":")
        if sep and head.lower() in SB3_ALGOS:
            kwargs.setdefault("algo", head.lower())
            rest = tail
        if not rest:
            raise ValueError(
                f"agent spec {spec!r} needs a model path (rl:path/to/model.zip); valid specs: {', '.join(valid)}"
            )
        return SB3Agent(rest, **kwargs)
    name, raw = split_spec(key)
    if name not in AGENT_SPECS:
        raise ValueError(f"unknown agent spec {spec!r}; valid specs: {', '.join(valid)}")
    cls = AGENT_SPECS[name]
    return cls.from_spec_options(convert_options(name, raw, cls.spec_options()), **kwargs)


def check_specs(specs: Iterable[str]) -> None:
    """Make each distinct spec once, so an unknown spec, a bad option or a missing model
    raises before any race or training step."""
    for spec in dict.fromkeys(specs):
        make_agent(spec)


def agent_options(name: str) -> list[tuple[str, str, str, str]]:
    """``(option, type, default, meaning)`` rows of the options a spec of agent ``name`` may set."""
    if name not in AGENT_SPECS:
        raise ValueError(f"unknown agent {name!r}; agents with options: {', '.join(AGENT_SPECS)}")
    cls = AGENT_SPECS[name]
    return describe_options(cls.spec_options(), cls.spec_defaults(), cls.spec_help())


def reset_agents(agents: Sequence[Agent], env_info: Any, seed: int | None = None) -> None:
    """Reset ``agents[i]`` as car ``i`` of ``env_info`` (before ``run_race``)."""
    for i, agent in enumerate(agents):
        agent.reset(seed, i, env_info)
