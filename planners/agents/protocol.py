"""The agent protocol: what every competitor (game planner, scripted driver, RL policy) implements.

Every agent implements :class:`Agent`::

    agent = make_agent("ilqgame-fb")
    agent.reset(seed=0, index=1, env_info=env)       # env: RacingParallelEnv (or its RaceGame)
    action = agent.act(observation, env.state())      # normalised jerks in [-1, 1]^2
    agent.diagnostics()                               # the last step: solve time, iterations, ...

and is a callable ``agent(observation, joint_state) -> action``, so it plugs into
``experiments.race.run_race`` and into the Gymnasium view as an opponent.
:class:`BaseAgent` holds what they share: the car index and game of a race, the jerk limits
that normalise actions, a braking fallback that keeps every action finite, and the per-step
diagnostics. See docs/agents.md.
"""

from __future__ import annotations

import time
from typing import Any, Protocol, Sequence, runtime_checkable

import numpy as np

__all__ = ["Agent", "BaseAgent", "empty_record", "game_of", "observation_space_of", "reset_agents", "units_conversion",
           "warn_other_car"]


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


def observation_space_of(env_info: Any, index: int):
    """Car ``index``'s observation space in an env (parallel or Gymnasium view, found as
    :func:`game_of` finds the game), or None for a bare game, which has none."""
    if callable(getattr(env_info, "observation_space", None)) and hasattr(env_info, "possible_agents"):
        return env_info.observation_space(env_info.possible_agents[index])  # PettingZoo: one space per agent
    for attr in ("race", "unwrapped"):
        inner = getattr(env_info, attr, None)
        if inner is not None and inner is not env_info:
            return observation_space_of(inner, index)
    return None


def _race_config_of(env_info: Any):
    """The :class:`racing_env.config.RaceConfig` of an env (parallel, Gymnasium or vectorised
    view), or None for a bare game."""
    from racing_env.config import RaceConfig

    config = getattr(env_info, "config", None)
    if isinstance(config, RaceConfig):
        return config
    for attr in ("race", "unwrapped"):
        inner = getattr(env_info, attr, None)
        if inner is not None and inner is not env_info:
            return _race_config_of(inner)
    return None


def units_conversion(env_info: Any, index: int, model_units: str | None) -> np.ndarray | None:
    """The factors ``(O,)`` that turn car ``index``'s observations in ``env_info`` into the
    units a model was trained in (``model_units``, one of
    :data:`racing_env.observation.OBSERVATION_UNITS`), or None where nothing is to convert:
    the same units, a model that does not say (``None``), or a bare game (its observations'
    units unknown). Exact, as both units are fixed weights on the same features
    (:func:`racing_env.observation.observation_scale`)."""
    from racing_env.observation import check_observation_units, observation_scale

    config = _race_config_of(env_info)
    if model_units is None or config is None or model_units == config.observation_units:
        return None
    check_observation_units(model_units)
    game = game_of(env_info)
    scale = {units: observation_scale(game.track, game.vehicles, len(config.preview_distances),
                                      config.observed_rivals, units)[index]
             for units in (model_units, config.observation_units)}
    return scale[model_units] / scale[config.observation_units]


def warn_other_car(model: str, trained_car: str | None, game: Any, index: int) -> str | None:
    """Warn (``UserWarning``) when a model trained in a car of class ``trained_car`` drives
    car ``index`` of ``game``, a car of another class (:func:`racing_env.car_classes.class_of`;
    a car of no class counts as another); returns the warning's text, or None where the
    classes agree or the model does not say (``trained_car`` None). Not refused: the
    observations are scaled by each car's own top speed and grip, so a policy may carry over,
    but its dynamics are another car's."""
    import warnings

    from racing_env.car_classes import class_of

    if trained_car is None or game is None:
        return None
    driven = class_of(game.vehicles.car(index))
    if driven == trained_car:
        return None
    text = (f"{model} was trained in a car of class {trained_car!r} and drives car {index}, "
            f"{'a car of class ' + repr(driven) if driven else 'a car of no class'}: its observations are scaled by "
            f"this car's top speed and grip, but the car is another (give the agent car={trained_car} to race it "
            f"in its own car)")
    warnings.warn(text, UserWarning, stacklevel=3)
    return text


def empty_record() -> dict:
    """A step's diagnostics record with nothing recorded yet (the keys every agent fills)."""
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
    """Common bookkeeping: index, game, jerk limits, the per-step diagnostics history.

    A subclass sets ``spec``, its name in the registry (:data:`planners.methods`), and
    implements ``act``; one that takes options from a spec (``name:option=value``) lists
    them in :meth:`spec_options`.
    """

    spec: str | None = None  # the registry name (planners.methods); None: not in the registry
    name = "agent"  # the name diagnostics and race records show (the spec, or more)

    @classmethod
    def spec_options(cls) -> dict[str, type]:
        """The options an agent spec may set (``name:option=value,...``) and their types."""
        return {}

    @classmethod
    def spec_defaults(cls) -> dict[str, Any]:
        """The value each spec option has when the spec leaves it out (for help text)."""
        return {}

    @classmethod
    def from_spec_options(cls, options: dict[str, Any], **kwargs: Any) -> "BaseAgent":
        """The agent with converted spec options (keyword arguments win over them)."""
        return cls(**{**options, **kwargs})

    def __init__(self) -> None:
        self.index: int | None = None
        self.game = None
        self.history: list[dict] = []
        self._last: dict = empty_record()
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
        self._last = empty_record()
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
        record = empty_record()
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
        """Aggregates over the steps since reset: re-plans, solve-time percentiles, iterations
        (mean, median, 95th percentile), fallbacks, shares of converged (and, where certified, locally Nash) re-plans."""
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
        certified = [bool(r["certified"]) for r in self.history if r.get("certified") is not None]
        if certified:  # a game agent with certify on: share of its certified re-plans at a local Nash equilibrium
            out["certified_share"] = float(np.mean(certified))
        leading = [bool(r["leading"]) for r in self.history if r.get("leading") is not None]
        if leading:  # place-dependent weights: share of re-plans made in the lead
            out["leading_fraction"] = float(np.mean(leading))
        if times.size:
            out.update(
                solve_time_median=float(np.median(times)),
                solve_time_p95=float(np.percentile(times, 95)),
                solve_time_max=float(times.max()),
                iterations_mean=float(np.mean(iters)) if iters else None,
                iterations_median=float(np.median(iters)) if iters else None,
                iterations_p95=float(np.percentile(iters, 95)) if iters else None,
            )
        return out


def reset_agents(agents: Sequence[Agent], env_info: Any, seed: int | None = None) -> None:
    """Reset ``agents[i]`` as car ``i`` of ``env_info`` (before ``run_race``)."""
    for i, agent in enumerate(agents):
        agent.reset(seed, i, env_info)
