"""RaceGame: the N-player racing game, the one definition used by the env and every planner."""

from __future__ import annotations

import dataclasses
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from racing_env import costs as _costs
from racing_env.costs import CostWeights, stack_weights
from racing_env.dynamics import INPUT_DIM, SLIPSTREAM, STATE_DIM, Aero, Slipstream, joint_step
from racing_env.track import Track
from racing_env.vehicle import VehicleParams, is_concrete, stack_vehicles


@dataclasses.dataclass(frozen=True, eq=False)
class RaceGame:
    """The dynamic game of N cars on a track (a JAX pytree; pass it into jitted functions).

    Attributes:
        track: the track (curvature and widths as functions of arc length).
        vehicles: per-car parameters, fields of shape ``(N,)``.
        weights: per-player cost weights, fields of shape ``(N,)``.
        dt: time step [s] (static).
        horizon: number of stages K of a planning problem (static).
        racing: which cars are still in the race, bool ``(N,)``; ``None`` (the default):
            all. The env freezes a car that finished or retired, and nothing collides with
            it any more. In the game such a car is a ghost: no collision cost to or from
            it, and its progress is not in the others' terminal costs. It keeps its own
            dynamics and costs, so the game keeps its N players and a planner its compiled
            solver when a car drops out. Set it with :meth:`with_racing`.
        collision_scale: ``(N, N)`` factors on the collision weights, player i's towards car
            j ``c_c^i * collision_scale[i, j]``; ``None`` (the default): 1, the paper's
            symmetric cost. Constants of the game, never functions of the planned states:
            :meth:`with_responsibility` sets them from the start of a plan.
        slipstream: the wake model of the cars with drag (:class:`racing_env.dynamics.Slipstream`,
            static), or None: their drag is never reduced. Default
            :data:`racing_env.dynamics.SLIPSTREAM`. It acts on cars with drag only.
        drag: whether some car has drag (``vehicles.c_drag > 0``), static: then the step is the
            coupled joint step (:func:`racing_env.dynamics.joint_step` with an
            :class:`racing_env.dynamics.Aero`), else the paper's per-car step. Set from the
            cars whenever they are concrete numbers (a value passed in is then overridden);
            a traced game keeps the flag of the game it was made from.

    Arrays: joint state ``x (N, 6)``, joint input ``u (N, 2)``, input sequences
    ``U (K, N, 2)``, state trajectories ``xs (K + 1, N, 6)``. All functions are pure JAX.
    """

    track: Track
    vehicles: VehicleParams
    weights: CostWeights
    dt: float = 0.1
    horizon: int = 50
    racing: jax.Array | None = None
    collision_scale: jax.Array | None = None
    slipstream: Slipstream | None = SLIPSTREAM
    drag: bool = False

    def __post_init__(self) -> None:
        c_drag = getattr(self.vehicles, "c_drag", None)
        if is_concrete(c_drag):
            object.__setattr__(self, "drag", bool(np.any(np.asarray(c_drag) > 0)))
        if self.slipstream is not None and not isinstance(self.slipstream, Slipstream):
            raise ValueError(f"slipstream must be a racing_env.dynamics.Slipstream or None, got {self.slipstream!r}")

    @staticmethod
    def create(
        track: Track,
        vehicles: VehicleParams | Sequence[VehicleParams],
        weights: CostWeights | Sequence[CostWeights] | None = None,
        dt: float = 0.1,
        horizon: int = 50,
        slipstream: Slipstream | None = SLIPSTREAM,
    ) -> "RaceGame":
        """Build a game, broadcasting single parameter sets to all players.

        ``vehicles`` fixes N: a sequence of ``VehicleParams`` (one per car). ``weights`` is
        one ``CostWeights`` for everybody, a sequence of N, or ``None`` for the defaults.
        ``slipstream``: the wake model of the cars with drag, or None (drag alone).
        """
        if isinstance(vehicles, VehicleParams):
            raise ValueError("RaceGame.create needs a sequence of VehicleParams, one per car")
        num_cars = len(vehicles)
        if num_cars < 1:
            raise ValueError(f"a race needs at least 1 car, got {num_cars}")
        if weights is None:
            weights = CostWeights()
        if isinstance(weights, CostWeights):
            weights = [weights] * num_cars
        if len(weights) != num_cars:
            raise ValueError(f"got {len(weights)} CostWeights for {num_cars} cars")
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be a positive number of seconds, got {dt!r}")
        if int(horizon) < 1:
            raise ValueError(f"horizon must be >= 1 stage, got {horizon!r}")
        return RaceGame(
            track=track,
            vehicles=stack_vehicles(vehicles),
            weights=stack_weights(weights),
            dt=float(dt),
            horizon=int(horizon),
            slipstream=slipstream,
        )

    @property
    def num_players(self) -> int:
        return int(np.shape(self.vehicles.v_max)[0])

    @property
    def state_dim(self) -> int:
        return STATE_DIM

    @property
    def input_dim(self) -> int:
        return INPUT_DIM

    def replace(self, **changes) -> "RaceGame":
        return dataclasses.replace(self, **changes)

    def with_racing(self, racing: Sequence[bool] | np.ndarray | None) -> "RaceGame":
        """The game with the cars out of the race marked: ``racing (N,)`` bool, ``None``: all
        cars race (see the ``racing`` attribute)."""
        if racing is None:
            return self.replace(racing=None)
        flags = np.array(racing)  # a copy: the game is immutable, the caller's array is not
        if flags.shape != (self.num_players,) or flags.dtype != bool:
            raise ValueError(
                f"racing must be {self.num_players} booleans (one per car), got {racing!r}"
            )
        return self.replace(racing=flags)

    def with_responsibility(self, x0: np.ndarray, ratio: float | np.ndarray) -> "RaceGame":
        """The game whose collision weights follow responsibility from the joint state ``x0
        (N, 6)`` a plan starts from: each player carries ``ratio`` (>= 1; one for all or
        ``(N,)``) times its collision weight towards a car ahead of it at ``x0``, its weight
        towards a car behind (:func:`racing_env.costs.responsibility_scale`). A ratio of 1 for
        every car is the symmetric cost (``collision_scale=None``, bit for bit)."""
        ratio = np.broadcast_to(np.asarray(ratio, dtype=np.float64), (self.num_players,))
        if np.all(ratio == 1.0):
            return self.replace(collision_scale=None)
        if not np.all(np.isfinite(ratio) & (ratio >= 1.0)):
            _costs.check_responsibility(float(ratio[~(np.isfinite(ratio) & (ratio >= 1.0))][0]))  # raises, naming it
        x0 = np.asarray(x0, dtype=np.float64)
        if x0.shape != (self.num_players, STATE_DIM):
            raise ValueError(f"x0 must have shape ({self.num_players}, {STATE_DIM}), got {x0.shape}")
        scale = _costs.responsibility_scale(self.track, x0[:, 0], np.asarray(self.vehicles.length), ratio)
        return self.replace(collision_scale=scale)

    # --- dynamics ---------------------------------------------------------------------
    def aero(self, dtype=None) -> Aero | None:
        """What the joint step of cars with drag needs (:class:`racing_env.dynamics.Aero`), in
        ``dtype`` (default: float64 where enabled); None when no car has drag. A car out of the
        race (``racing``) leaves no wake."""
        if not self.drag:
            return None
        dtype = jnp.result_type(float) if dtype is None else dtype
        n_cars = self.num_players
        field = lambda value: jnp.broadcast_to(jnp.asarray(value, dtype), (n_cars,))
        wake = jnp.ones(n_cars, dtype) if self.racing is None else jnp.asarray(self.racing).astype(dtype)
        return Aero(field(self.vehicles.c_drag), field(self.vehicles.length), field(self.vehicles.width), wake,
                    self.track.wrap_ds, self.slipstream)

    def step(self, x: jax.Array, u: jax.Array) -> jax.Array:
        """Joint RK4 step: ``x (N, 6)``, ``u (N, 2)`` [m/s^3] -> ``(N, 6)`` (coupled through
        the slipstream when some car has drag)."""
        return joint_step(x, u, self.dt, self.track.kappa_at, self.aero(jnp.result_type(x)))

    def rollout(self, x0: jax.Array, U: jax.Array) -> jax.Array:
        """Simulate ``U (K, N, 2)`` from ``x0 (N, 6)``: returns ``xs (K + 1, N, 6)``."""

        def body(x, u):
            x_next = self.step(x, u)
            return x_next, x_next

        _, xs = jax.lax.scan(body, x0, U)
        return jnp.concatenate([x0[None], xs], axis=0)

    # --- costs ------------------------------------------------------------------------
    def stage_costs(self, x: jax.Array, u: jax.Array) -> jax.Array:
        """Stage cost of every player, ``(N,)``."""
        return _costs.stage_costs(x, u, self.vehicles, self.weights, self.track, self.racing, self.collision_scale)

    def stage_cost(self, i: int, x: jax.Array, u_i: jax.Array) -> jax.Array:
        """Stage cost g^i of player ``i`` at joint state ``x (N, 6)`` with its input ``u_i (2,)``.

        Player i's stage cost depends on its own input only (the paper's structure), so the
        other players' inputs are not arguments.
        """
        return _costs.player_stage_cost(self.stage_residuals(i, x, u_i))

    def stage_residuals(self, i: int, x: jax.Array, u_i: jax.Array) -> _costs.StageResiduals:
        """Player ``i``'s stage cost as residuals (:class:`racing_env.costs.StageResiduals`),
        the form its cost and the solvers' Gauss-Newton terms are both computed from."""
        return _costs.stage_residuals(i, x, u_i, self.vehicles, self.weights, self.track, self.racing,
                                      self.collision_scale)

    def terminal_costs(self, x: jax.Array) -> jax.Array:
        """Terminal cost of every player, ``(N,)``."""
        return _costs.terminal_costs(x, self.weights, self.racing)

    def terminal_cost(self, i: int, x: jax.Array) -> jax.Array:
        """Terminal cost g_K^i of player ``i``."""
        return self.terminal_costs(x)[i]

    def costs(self, xs: jax.Array, U: jax.Array) -> jax.Array:
        """Total cost of every player along a trajectory: ``xs (K+1, N, 6)``, ``U (K, N, 2)`` -> ``(N,)``."""
        running = jax.vmap(self.stage_costs)(xs[:-1], U).sum(axis=0)
        return running + self.terminal_costs(xs[-1])


jax.tree_util.register_dataclass(
    RaceGame,
    data_fields=["track", "vehicles", "weights", "racing", "collision_scale"],
    meta_fields=["dt", "horizon", "slipstream", "drag"],
)
