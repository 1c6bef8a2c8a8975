"""A receding-horizon planner as a pure JAX function: a planner opponent inside a compiled race.

:class:`CompiledPlanner` is :class:`planners.agents.batched_planners.BatchedPlanner`'s step
for one race written as pure functions of ``(plan state, joint state)``, so that a race core
that is itself compiled (:class:`racing_env.vector.GymnaxRace`, the JAX learner's update)
can step planner opponents inside its program, and vmap them over races::

    planner = make_batched_opponent("ilqgame-fb:iterations=2", game, 1, 1).jax_planner   # or ilqgame-leader, ...
    plan = planner.initial()                                  # a race start: no plan yet
    action, plan = planner.act(plan, x, racing)               # x (N, 6), racing (N,) bool

A step is the batched planner's (and so the single agent's):

1. due to re-plan (no plan yet, ``replan_every`` steps since the last re-plan, or the plan
   used up): the game with this race's racing flags, cost weights (place, recovery from
   a standstill) and collision scales (``responsibility``, from the race's state) is solved by :func:`planners.ilq.solve_arrays` from the shifted, restored
   warm start, or from zero inputs at the first re-plan of a race (the cold plan of a
   reset); its iteration budget is the agent's ``iterations`` (or ``max_iterations``);
2. otherwise the plan is followed: ``u = u_hat_t - K_t (x - x_hat_t)`` for the feedback
   game, ``u_hat_t`` for the others;
3. a re-plan with non-finite output (or not converged under ``require_converged``) follows
   the previous plan one step on, else brakes with the agents' braking law.

The action is the normalised jerk ``(2,)`` in ``[-1, 1]``; a race in which the car is no
longer racing gets a zero action and keeps its plan state. Under ``jax.vmap`` both branches
of step 1/2 run for every race (a vmapped ``cond`` is a select) and the re-plans run in
lock step: a step costs one batched solve whether one race re-plans or all do (none when no
race re-plans: the races not due solve from a NaN state, which ends at once). Its actions
equal the host planner's with the same options to rounding (tests/test_compiled_planner.py).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from planners import ilq, ilqr, leader_follower, rival_game
from planners.agents.receding_horizon import RECOVERED_SPEED, STOPPED_SPEED
from planners.agents.warm_start import restore_accelerations
from planners.game_problem import as_problem
from planners.precision import cast_floating, require_precision
from racing_env.costs import CostWeights, responsibility_scale
from racing_env.dynamics import AX, AY, CHI, N_LAT, S, STATE_DIM, V

__all__ = ["CompiledPlanner", "PlanState"]


class PlanState(NamedTuple):
    """A compiled planner's state in one race (a pytree; leading race axes under vmap).

    Attributes:
        us: ``(T, N, 2)`` the plan's jerks [m/s^3] (the other cars' rows: what it expects of them).
        xs: ``(T+1, N, 6)`` the plan's joint states.
        K: ``(T, 2, 6N)`` this car's feedback gains (zeros for open loop and iLQR).
        has_plan: bool, a plan is stored.
        age: int, steps since the plan was made.
        recovering: bool, the car plans in recovery from a standstill.
    """

    us: jax.Array
    xs: jax.Array
    K: jax.Array
    has_plan: jax.Array
    age: jax.Array
    recovering: jax.Array


def _finite(a: jax.Array) -> jax.Array:
    return jnp.all(jnp.isfinite(a))


class CompiledPlanner:
    """The pure-JAX step of a batched planner (module docstring); made by
    :attr:`planners.agents.batched_planners.BatchedPlanner.jax_planner`, whose agent, games,
    weight variants and solver options it shares."""

    def __init__(self, planner: Any) -> None:
        require_precision(planner.options.precision, f"the compiled planner {planner.spec!r}")
        agent = planner.agent
        self.index = planner.index
        self.game = planner.game
        self.horizon = planner.game.horizon
        self.num_cars = planner.game.num_players
        self.options = planner.options
        self.feedback = planner.feedback
        self.is_ilqr = planner.is_ilqr
        self.replan_every = agent.replan_every
        self.pad = agent.pad
        self.warm_start = agent.warm_start
        self.restore = agent.restore_accelerations
        self.require_converged = agent.require_converged
        self.jerk_max = jnp.asarray(agent.jerk_max)
        self.weights = {name: jnp.asarray(column) for name, column in planner._weights.items()}
        self.place_count, self.recovery_count = planner._place_count, planner._recovery_count
        self.solve_game = planner._solve_game
        self.responsibility = agent.responsibility
        self.ego_template = planner._ego_template if self.is_ilqr else None
        self.rivals = planner.rivals  # local games (planners.rival_game), or None: the whole game
        self.role = planner.role  # a leader-follower planner's role in its pair games, or None
        self.obstacles = planner.obstacles  # the predicted cars of a local game (None: all)
        self.vehicle = planner._brake_law.vehicle

    # --- the interface --------------------------------------------------------------------
    def initial(self, dtype=jnp.float64) -> PlanState:
        """The state at a race start: no plan (the first step re-plans cold)."""
        T, N = self.horizon, self.num_cars
        return PlanState(us=jnp.zeros((T, N, 2), dtype), xs=jnp.zeros((T + 1, N, STATE_DIM), dtype),
                         K=jnp.zeros((T, 2, N * STATE_DIM), dtype), has_plan=jnp.asarray(False),
                         age=jnp.asarray(0, jnp.int32), recovering=jnp.asarray(False))

    def act(self, plan: PlanState, x: jax.Array, racing: jax.Array) -> tuple[jax.Array, PlanState]:
        """The normalised jerks ``(2,)`` of this car from the joint state ``x (N, 6)`` with the
        cars still racing ``racing (N,)`` bool, and the new plan state. Pure; vmap it over races."""
        x = jnp.asarray(x, plan.xs.dtype)
        due = ~plan.has_plan | (plan.age + 1 >= self.replan_every) | (plan.age + 1 >= self.horizon)
        followed = plan._replace(age=plan.age + 1)
        u_follow = self._follow(followed, x, followed.age)
        u_replan, replanned = self._replan(plan, x, racing, due)
        u = jnp.where(due, u_replan, u_follow)
        new = jax.tree_util.tree_map(lambda a, b: jnp.where(due, a, b), replanned, followed)
        action = self._finish(u / self.jerk_max, x)
        active = racing[self.index]
        action = jnp.where(active, action, jnp.zeros_like(action))
        new = jax.tree_util.tree_map(lambda a, b: jnp.where(active, a, b), new, plan)
        return action, new

    # --- the parts --------------------------------------------------------------------------
    def _follow(self, plan: PlanState, x: jax.Array, t: jax.Array) -> jax.Array:
        """This car's jerks at ``t`` steps into the plan (NaN where the plan is used up)."""
        t_safe = jnp.minimum(t, self.horizon - 1)
        u = plan.us[t_safe, self.index]
        if self.feedback:
            dx = (x - plan.xs[t_safe]).reshape(-1)
            u = jnp.where(_finite(dx), u - plan.K[t_safe] @ dx, u)
        return jnp.where(plan.has_plan & (t < self.horizon), u, jnp.nan)

    def _variant(self, plan: PlanState, x: jax.Array, racing: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The row of the weight table this re-plan uses, and the new recovery flag."""
        variant = jnp.asarray(0)
        recovering = plan.recovering
        if self.place_count == 2:
            rivals = racing & (jnp.arange(self.num_cars) != self.index)
            leading = jnp.all((x[self.index, S] > x[:, S]) | ~rivals)
            variant = variant + jnp.where(leading, 0, 1) * self.recovery_count
        if self.recovery_count == 2:
            speed = x[self.index, V]
            recovering = (speed < STOPPED_SPEED) | (plan.recovering & (speed < RECOVERED_SPEED))
            variant = variant + recovering.astype(variant.dtype)
        return variant, recovering

    def _warm_start(self, plan: PlanState, x: jax.Array) -> jax.Array:
        """The re-plan's initial inputs ``(T, N, 2)``: the plan shifted by the steps elapsed
        (padded as the agent pads, accelerations restored), zeros without a plan."""
        T = self.horizon
        zeros = jnp.zeros_like(plan.us)
        if not self.warm_start:
            return zeros
        by = jnp.minimum(plan.age + 1, T)
        steps = jnp.arange(T) + by
        shifted = plan.us[jnp.minimum(steps, T - 1)]
        if self.pad == "zeros":
            shifted = jnp.where((steps >= T)[:, None, None], 0.0, shifted)
        if self.restore:
            shifted = restore_accelerations(shifted, plan.xs[by], x, self.game.dt)
        return jnp.where(plan.has_plan, shifted, zeros)

    def _solve_arrays(self, problem, x0: jax.Array, us0: jax.Array, dtype) -> ilq.SolverResult:
        """:func:`planners.ilq.solve_arrays` with the planner's options, its floats in the race's
        ``dtype`` (a ``precision="float32"`` solve inside a float64 race)."""
        return cast_floating(ilq.solve_arrays(problem, x0, us0, self.options), dtype)

    def _solve(self, game, x: jax.Array, init: jax.Array):
        """``(us (T, N, 2), xs (T+1, N, 6), K (T, 2, 6N), converged)`` of one re-plan."""
        if self.is_ilqr:
            predicted = ilqr.predict_constant_velocity(game, x)
            template = self.ego_template
            problem = template.replace(params=template.params._replace(game=game, predicted=predicted))
            res = self._solve_arrays(problem, x[self.index], init[:, self.index][:, None], x.dtype)
            xs = predicted.at[:, self.index].set(res.xs)
            us = jnp.zeros_like(init).at[:, self.index].set(res.us[:, 0])
            return us, xs, jnp.zeros((self.horizon, 2, self.num_cars * STATE_DIM), xs.dtype), res.converged
        if self.rivals is not None:
            return self._solve_local(game, x, init)
        problem, _ = as_problem(game)
        res = self._solve_arrays(problem, x, init, x.dtype)
        K = res.K[:, self.index] if self.feedback else jnp.zeros((self.horizon, 2, x.size), x.dtype)
        return res.us, res.xs, K, res.converged

    def _solve_local(self, game, x: jax.Array, init: jax.Array):
        """:meth:`_solve` of a local game: this car and its ``rivals`` nearest, the others
        predicted at constant velocity (:mod:`planners.rival_game`, traced)."""
        if self.role is not None:
            return self._solve_pair(game, x, init)
        k, P = self.rivals, self.rivals + 1
        order = rival_game.field_orders(game.track, x[None], jnp.asarray([self.index]), k, game.racing[None])[0]
        others = ilqr.predict_constant_velocity(game, x)[:, order[P:]]
        params = rival_game.RivalParams(game=game, order=order, predicted=others[:, :self.obstacles])
        problem = rival_game.local_problem(P, STATE_DIM, game.input_dim, self.horizon, params)
        res = self._solve_arrays(problem, x[order[:P]].reshape(-1), init[:, order[:P]], x.dtype)
        xs, us, K = rival_game.to_field_batch(order[None], res.xs[None], res.us[None],
                                              res.K[None] if self.feedback else None, init[None], others[None])
        K = K[0] if self.feedback else jnp.zeros((self.horizon, 2, x.size), x.dtype)
        return us[0], xs[0], K, res.converged

    def _solve_pair(self, game, x: jax.Array, init: jax.Array):
        """:meth:`_solve` of a leader-follower planner: its pair game
        (:func:`planners.leader_follower.pair_games`, traced: with ``role="auto"`` the leader
        is chosen by a ``where`` on the race's state), the ego's gains from its own row."""
        ego = jnp.asarray([self.index])
        predicted = ilqr.predict_constant_velocity(game, x)[None]
        problem, x0, local_init, order, others = leader_follower.pair_games(
            game, x[None], ego, self.role, init[None], predicted, self.obstacles, game.racing[None])
        params = problem.params
        problem = problem.replace(params=params._replace(order=params.order[0], predicted=params.predicted[0]))
        res = self._solve_arrays(problem, x0[0], local_init[0], x.dtype)
        xs, us, K = leader_follower.to_field_batch(order, ego, res.xs[None], res.us[None], res.K[None], init[None],
                                                   others)
        return us[0], xs[0], K[0], res.converged

    def _replan(self, plan: PlanState, x: jax.Array, racing: jax.Array, due: jax.Array
                ) -> tuple[jax.Array, PlanState]:
        """The jerks and plan state of a re-plan (used where ``due``). A race that is not
        due solves from a NaN state, which stops its solve before the first iteration: a
        step in which no race re-plans costs no iterations, also under vmap."""
        racing = racing.at[self.index].set(True)  # as the observation's flags say of the car itself
        variant, recovering = self._variant(plan, x, racing)
        weights = CostWeights(**{name: column[variant] for name, column in self.weights.items()})
        game = self.solve_game.replace(weights=weights, racing=racing, collision_scale=self._collision_scale(x))
        us, xs, K, converged = self._solve(game, jnp.where(due, x, jnp.nan), self._warm_start(plan, x))
        ok = _finite(us) & _finite(xs) & _finite(K)
        if self.require_converged:
            ok = ok & converged
        fresh = PlanState(us=us, xs=xs, K=K, has_plan=jnp.asarray(True), age=jnp.zeros_like(plan.age),
                          recovering=recovering)
        u_fresh = self._follow(fresh, x, fresh.age)
        # a failed re-plan: the previous plan one step on (dropped when it gives no finite jerk)
        old = plan._replace(age=plan.age + 1, recovering=recovering)
        u_old = self._follow(old, x, old.age)
        old = old._replace(has_plan=old.has_plan & _finite(u_old))
        new = jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), fresh, old)
        return jnp.where(ok, u_fresh, u_old), new

    def _collision_scale(self, x: jax.Array) -> jax.Array | None:
        """The re-plan's collision scales ``(N, N)`` from ``x (N, 6)`` by the agent's
        ``responsibility`` (traced :func:`racing_env.costs.responsibility_scale`), None for
        the symmetric cost."""
        if self.responsibility == 1.0:
            return None
        return responsibility_scale(self.game.track, x[:, S], jnp.asarray(self.game.vehicles.length),
                                    self.responsibility, xp=jnp)

    def _finish(self, action: jax.Array, x: jax.Array) -> jax.Array:
        """``action (2,)`` clipped to ``[-1, 1]``, or the agents' braking action where it is
        not finite (:meth:`planners.agents.protocol.BaseAgent._safe_action`)."""
        return jnp.clip(jnp.where(_finite(action), action, self._brake(x)), -1.0, 1.0)

    def _brake(self, x: jax.Array) -> jax.Array:
        """The agents' braking law in JAX: jerk toward ``ax = -0.3 rho(V)`` (at most half the
        jerk limit), the lane keeper's law toward the centre line laterally."""
        own = x[self.index]
        s, v, n, chi, ax, ay = (own[k] for k in (S, V, N_LAT, CHI, AX, AY))
        v_pos = jnp.maximum(v, 0.0)
        ax_des = jnp.where(v_pos > 0.5, -0.3 * self.vehicle.rho(v_pos), 0.0)
        ay_des = self.game.track.kappa_at(s) * v**2 + 1.0 * (0.0 - n) - 2.0 * v * jnp.sin(chi)
        a = 5.0 * jnp.stack([ax_des - ax, ay_des - ay]) / self.jerk_max
        a = a.at[0].set(jnp.clip(a[0], -0.5, 0.5))
        a = jnp.clip(a, -1.0, 1.0)
        fixed = jnp.asarray([-0.5, 0.0], a.dtype)
        return jnp.where(_finite(a) & _finite(own), a, fixed).astype(jnp.float32).astype(a.dtype)
