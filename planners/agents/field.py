"""A field's re-plans as one batched solve per step.

In a race of N game planners (:class:`planners.agents.receding_horizon.FeedbackGameAgent`
and :class:`~planners.agents.receding_horizon.OpenLoopGameAgent` with ``rivals < N - 1``, and
the leader-follower :class:`~planners.agents.receding_horizon.StackelbergGameAgent` with
``N > 2``: its pair game, :mod:`planners.leader_follower`) every car solves its local game
(:mod:`planners.rival_game`) at every re-plan. Those games
have the same shapes, and the cars with the same solver options the same compiled solver:
:func:`solve_field` solves them as one :func:`planners.ilq_batch.solve_batch` per group of
such cars (in lock step for real-time re-plans and on accelerators, else one member after
another inside one compiled call: :func:`field_batching`), split over the local devices,
instead of N solves, each with its own dispatch. Each agent then adopts its
member in its own :meth:`act`, which does everything else as it would alone (fallbacks,
diagnostics, following the plan between re-plans): the plans are those of the agents' own
solves, to the last few bits (a batch member is compiled in a program of its own).

The race loop calls :func:`solve_field` with the agents still racing before it asks them
for their actions (``experiments.race.run_race`` does); agents that cannot take part (other
methods, a ``budget_ms``, a race small enough for the whole game) are left alone.
"""

from __future__ import annotations

import time
from typing import Any, Sequence

import jax
import numpy as np

from planners import ilq_batch, rival_game
from planners.ilqr import predict_constant_velocity

__all__ = ["field_batching", "solve_field"]


_LARGEST: dict[tuple, int] = {}
"""The largest batch solved per group key (:func:`_group_key`) in this process: a group's
batch is padded to it, so that a car that finishes or retires does not cost a compile.
Padding costs next to nothing when the members are solved one after another
(:func:`_solve_group`), a duplicate solve each in lock step."""


def field_batching(agent: Any, devices) -> str:
    """How a field's batch is solved (:func:`planners.ilq_batch.solve_batch`'s ``batching``):
    in lock step (``"vmap"``) for real-time re-plans (``iterations``), whose members all stop
    at the same iteration cap, so that none waits for another, and which XLA:CPU then runs
    faster than one after another (docs/performance.md,
    "Fields (`racing bench --only field`)"); otherwise the solver's default for the devices
    (on CPU one after another, each member stopping at its own convergence)."""
    if getattr(agent, "iterations", None) is not None:
        return "vmap"
    return ilq_batch.resolve_batching("auto", devices)


def _group_key(agent: Any, local: rival_game.LocalGame) -> tuple:
    """Agents whose local games one batch can solve: the same solver options (structure and
    numbers: a batch shares them), the same players, cars and horizon, the same track and
    cars' parameters (the batch shares them), and collision scales in all or none (the games'
    structure)."""
    options = agent.batch_options()
    game = local.problem.params.game
    return (type(agent), options, local.problem.num_players, game.num_players, local.problem.horizon,
            id(game.track), id(game.vehicles), game.collision_scale is None)


def solve_field(agents: Sequence[Any], observations: Sequence[Any], joint_state: np.ndarray) -> dict[str, Any]:
    """Solve the re-plans that ``agents`` make this step, one batch per group of agents that
    share a solver (module docstring); every agent then adopts its solution in its next
    :meth:`act` with the same observation and ``joint_state (N, 6)``.

    Args:
        agents: the policies of the cars still racing (anything; only agents with
            ``prepare_replan`` take part).
        observations: each agent's observation, in the same order.
        joint_state: the race's joint state ``(N, 6)``.

    Returns:
        ``{"batches": number of batched solves, "members": re-plans solved in them,
        "seconds": their wall time [s], "charged": {position in agents: seconds [s]}}``. Each
        member is charged an equal share of its batch's time (``charged``, and in its
        diagnostics' ``solve_time``). A batch that raises hands the
        exception to each of its members, which fall back as after a failed solve of their own.
    """
    if len(agents) != len(observations):
        raise ValueError(f"got {len(agents)} agents and {len(observations)} observations")
    groups: dict[tuple, list[tuple[int, Any, rival_game.LocalGame]]] = {}
    predicted: dict[tuple, np.ndarray] = {}  # the field's constant-velocity prediction, per (dt, horizon)
    for position, (agent, observation) in enumerate(zip(agents, observations)):
        prepare = getattr(agent, "prepare_replan", None)
        if prepare is None:
            continue
        game = getattr(agent, "game", None)
        key = None if game is None else (game.dt, game.horizon)
        if key is not None and key not in predicted:
            try:
                predicted[key] = np.asarray(predict_constant_velocity(game, np.asarray(joint_state, dtype=np.float64)))
            except Exception:  # noqa: BLE001 - a bad state: each agent's own act says what is wrong
                predicted[key] = None
        local = prepare(observation, joint_state, predicted.get(key))
        if local is not None:
            groups.setdefault(_group_key(agent, local), []).append((position, agent, local))
    stats: dict[str, Any] = {"batches": 0, "members": 0, "seconds": 0.0, "charged": {}}
    for key, members in groups.items():
        t0 = time.perf_counter()
        size = _LARGEST[key] = max(len(members), _LARGEST.get(key, 0))
        try:
            results = _solve_group(members, size)
        except Exception as exc:  # noqa: BLE001 - each agent falls back as after its own failed solve
            results = [exc] * len(members)
        seconds = time.perf_counter() - t0
        for (position, agent, _), result in zip(members, results):
            agent.take_solution(result, seconds / len(members))
            stats["charged"][position] = seconds / len(members)
        stats["batches"] += 1
        stats["members"] += len(members)
        stats["seconds"] += seconds
    return stats


def _solve_group(members: list[tuple[int, Any, rival_game.LocalGame]], size: int) -> list[Any]:
    """The single results (NumPy :class:`planners.ilq.SolverResult`) of one group's local games."""
    locals_ = [local for _, _, local in members]
    devices = jax.local_devices()
    count = len(locals_)
    size = -(-size // len(devices)) * len(devices)  # each device's part the same size
    # the members spread evenly over the devices' parts, so that no part holds only padding
    k = np.arange(count)
    slots = (k % len(devices)) * (size // len(devices)) + k // len(devices)
    padded = [locals_[0]] * size
    for slot, local in zip(slots, locals_):
        padded[slot] = local
    x0s = np.stack([local.x0 for local in padded])
    batching = field_batching(members[0][1], devices)
    if batching == "map":
        # members solved one after another: a NaN start stops a padding member before its
        # first iteration (in lock step it would keep every step search going: repeat instead)
        x0s[np.setdiff1d(np.arange(size), slots)] = np.nan
    problem = locals_[0].problem.replace(params=rival_game.stack_params(padded))
    options = members[0][1].batch_options()
    result = ilq_batch.solve_batch(problem, x0s, init=np.stack([local.init for local in padded]),
                                   params_axes=rival_game.batch_axes(locals_[0]), options=options, devices=devices,
                                   batching=batching, validate=False)
    result = jax.device_get(result)
    return [jax.tree_util.tree_map(lambda leaf, b=b: leaf[b], result) for b in slots]
