"""Batches of games: :func:`solve_batch` solves many initial states (and parameters) at once.

A batch is split evenly across devices (``shard_map``, no communication: each device's
part stops when its own members are done). On a device the members are solved in lock
step (``"vmap"``, the vectorised form an accelerator wants) or one after another
(``"map"``, a ``lax.map`` of the whole solver, which XLA:CPU compiles like a single
solve). A lock-step batch can be regrouped between blocks of iterations so that the
members still running go on in a smaller batch. Every member's result is its single
:func:`planners.ilq.solve` either way.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from planners import ilq
from planners.batching import one_at_a_time
from planners.game_problem import GameProblem, as_problem
from planners.precision import require_precision

Array = jax.Array

__all__ = ["resolve_batching", "solve_batch"]

_BATCHING = ("auto", "map", "vmap")


def resolve_batching(batching: str, devices) -> str:
    """The batching ``"auto"`` stands for on these devices: ``"map"`` if all are CPUs, else ``"vmap"``."""
    if batching != "auto":
        return batching
    return "map" if all(d.platform == "cpu" for d in devices) else "vmap"


def solve_batch(
    problem_or_game,
    x0s,
    init=None,
    *,
    params_axes=None,
    devices=None,
    batching: str = "auto",
    regroup_every: int | None = None,
    options: ilq.SolverOptions | None = None,
    validate: bool = True,
    **overrides,
) -> ilq.SolverResult:
    """:func:`planners.ilq.solve` over a batch of initial states ``x0s (B, ...)``.

    ``init``: ``None``, inputs shared by the batch ``(T, N, m)``, or batched ``(B, T, N, m)``
    (or a batched result). ``params_axes``: vmap axes of the problem's ``params`` (a pytree
    prefix, e.g. a RaceGame whose ``weights`` leaves are batched: build the game with
    stacked weights and pass ``params_axes=game.replace(track=None, vehicles=None, racing=None,
    weights=0)``); ``None`` shares the params. The result has a leading batch axis.

    ``devices``: the batch is split evenly across these devices and the parts run in
    parallel, each part stopping when its own members are done; the default is every
    local device of JAX's default backend. On CPU that is one device
    unless :func:`planners.devices.use_cpu_cores` was called. Every member's result is the
    same either way. Compiled once per shapes, :class:`~planners.ilq.SolverOptions` structure
    (its numbers are traced), ``params_axes``, devices and ``batching``.

    ``batching``: how a device solves its part. ``"vmap"``: all members at once, in lock
    step (the vectorised form an accelerator wants). ``"map"``: one member after another,
    each a whole single solve that stops at its own convergence (a ``lax.map`` of the
    solver, which XLA:CPU compiles like a single solve). ``"auto"`` (default): ``"map"`` on
    CPU devices, where XLA:CPU vectorises nothing across the members and a lock-step
    batch only waits for its slowest member (docs/performance.md), ``"vmap"`` on any
    other platform.

    ``regroup_every`` (for ``batching="vmap"``): a vmapped solve computes every member until
    the slowest one is done, so one member that needs ``max_iterations`` makes the whole
    batch pay for them. With
    ``regroup_every=k`` the batch runs ``k`` iterations at a time and, in between, only the
    members still running go on, gathered into a smaller batch (sizes are powers of two
    times the device count, and every new size compiles once). Each member's result is the
    same as without regrouping. Worth it when a few members run much longer than the rest
    and the process solves many batches (or the compilation cache is on). With ``"map"``
    no member waits for another, and ``regroup_every`` is ignored.

    Needs 64-bit floats (``jax_enable_x64``) in float64, as :func:`planners.ilq.solve`
    (``precision="float32"`` solves in float32 either way).
    """
    if batching not in _BATCHING:
        raise ValueError(f"batching must be one of {_BATCHING}, got {batching!r}")
    options = ilq.resolve_options(options, overrides)
    require_precision(options.precision, "planners.ilq_batch.solve_batch")
    problem, game_type = as_problem(problem_or_game)
    ilq.check_adaptive_regularization(options, problem.num_players)
    x0s = jnp.asarray(x0s)
    if not jnp.issubdtype(x0s.dtype, jnp.floating):
        x0s = x0s.astype(jnp.result_type(float))
    if x0s.ndim < 2 or x0s[0].size != problem.state_dim:
        raise ValueError(
            f"x0s must be a batch (B, ...) of initial states with {problem.state_dim} entries "
            f"each, got shape {x0s.shape}"
        )
    if regroup_every is not None and not (
        isinstance(regroup_every, (int, np.integer)) and not isinstance(regroup_every, bool) and regroup_every >= 1
    ):
        raise ValueError(f"regroup_every must be None or an integer >= 1, got {regroup_every!r}")
    shape = (problem.horizon, problem.num_players, problem.input_dim)
    us0 = jnp.zeros(shape, x0s.dtype) if init is None else jnp.asarray(getattr(init, "us", init))
    us_axis = None if us0.shape == shape else 0
    if us_axis == 0 and us0.shape != (x0s.shape[0],) + shape:
        raise ValueError(f"init must have shape {shape} or {(x0s.shape[0],) + shape}, got {us0.shape}")
    if validate and params_axes is None and game_type is not None:
        ilq.validate_problem(problem_or_game, control_regularization=options.guaranteed_control_regularization)
    elif validate and params_axes is None:
        ilq.validate_problem(problem, x0s[0].reshape(-1), us0 if us_axis is None else us0[0],
                             options.guaranteed_control_regularization)

    from jax.sharding import Mesh

    mesh = Mesh(np.asarray(jax.local_devices() if devices is None else list(devices)), ("batch",))
    batching = resolve_batching(batching, mesh.devices.flat)
    leaf_axes = _leaf_axes(params_axes, problem.params)
    if us_axis is None:
        us0 = jnp.broadcast_to(us0, (x0s.shape[0],) + shape)
    batch = (x0s.reshape(x0s.shape[0], -1), us0)
    structure, numbers = ilq.jit_arguments(options)  # numbers traced: they share the compiled solver
    if regroup_every is None or batching == "map":  # mapped members never wait: nothing to regroup
        result = _map_split("solve", problem, batch, numbers, leaf_axes=leaf_axes, structure=structure, mesh=mesh,
                            batching=batching)
    else:
        result = _solve_regrouped(problem, batch, leaf_axes, structure, numbers, mesh, int(regroup_every))
    return result._replace(xs=result.xs.reshape(result.xs.shape[:2] + x0s.shape[1:]))


def _solve_regrouped(problem: GameProblem, batch, leaf_axes, structure, numbers, mesh, every: int
                     ) -> ilq.SolverResult:
    """A vmapped :func:`solve_batch` in blocks of ``every`` iterations, each block on the
    members still running (see ``regroup_every``); the options as ``structure`` and
    ``numbers`` (:meth:`planners.ilq.SolverOptions.split`)."""
    def run(kind, problem, batch, **kwargs):
        return _map_split(kind, problem, batch, numbers, leaf_axes=leaf_axes, structure=structure, mesh=mesh,
                          batching="vmap", **kwargs)

    carry = run("start", problem, batch)
    batch_size = int(carry.status.shape[0])
    while True:
        active = np.flatnonzero(np.asarray(carry.status) == ilq.RUNNING)
        if active.size == 0:
            break
        size = mesh.size * 2 ** int(np.ceil(np.log2(max(1.0, active.size / mesh.size))))
        size = min(size, batch_size + (-batch_size % mesh.size))
        # Padding repeats the last active member; its copies compute the same values, so
        # writing them all back is writing that member's result.
        rows = jnp.asarray(np.concatenate([active, np.repeat(active[-1:], size - active.size)]))
        part_problem, part = _gather_members(problem, carry, rows, leaf_axes)
        part = run("continue", part_problem, part, steps=every)
        carry = _write_members(carry, rows, part)
    return run("finish", problem, carry)


@functools.partial(jax.jit, static_argnames=("leaf_axes",))
def _gather_members(problem: GameProblem, carry: ilq.SolverCarry, rows: Array, leaf_axes):
    """The batch members ``rows`` of the solver states and of the batched params."""
    leaves, treedef = jax.tree_util.tree_flatten(problem.params)
    leaves = [leaf if axis is None else jnp.take(leaf, rows, axis=axis) for leaf, axis in zip(leaves, leaf_axes)]
    part = jax.tree_util.tree_map(lambda leaf: leaf[rows], carry)
    return problem.replace(params=jax.tree_util.tree_unflatten(treedef, leaves)), part


@jax.jit
def _write_members(carry: ilq.SolverCarry, rows: Array, part: ilq.SolverCarry) -> ilq.SolverCarry:
    """``carry`` with its members ``rows`` replaced by ``part``."""
    return jax.tree_util.tree_map(lambda whole, new: whole.at[rows].set(new), carry, part)


def _leaf_axes(params_axes, params) -> tuple:
    """The vmap axis (or None) of every leaf of ``params``, from the prefix ``params_axes``."""
    if params_axes is None:
        return (None,) * len(jax.tree_util.tree_leaves(params))
    axes, prefix = jax.tree_util.tree_flatten(params_axes, is_leaf=lambda a: a is None or isinstance(a, int))
    subtrees = prefix.flatten_up_to(params)  # the part of params each prefix axis covers
    return tuple(axis for axis, sub in zip(axes, subtrees) for _ in jax.tree_util.tree_leaves(sub))


def _member(kind: str, problem: GameProblem, args, options: ilq.SolverOptions, steps: int | None):
    """One batch member's share of a batched solve: ``kind`` is ``"solve"`` (``args`` =
    ``(x0, us0)``, returns a result), ``"start"`` (returns the initial solver state),
    ``"continue"`` (``args`` = a state; at most ``steps`` iterations) or ``"finish"``."""
    if kind == "solve":
        return ilq.solve_arrays(problem, *args, options)
    problem = ilq.at_precision(problem, options)
    if kind == "start":
        return ilq.initial_carry(problem, *args, options)
    if kind == "continue":
        return ilq.iterate_while_running(problem, args, options, steps)
    return ilq.result(problem, ilq.finish(problem, args, options), (args.xs.shape[-1],))


@functools.partial(jax.jit, static_argnames=("kind", "leaf_axes", "structure", "mesh", "batching", "steps"))
def _map_split(kind: str, problem: GameProblem, batch, numbers: ilq.SolverNumbers, *, leaf_axes, structure, mesh,
               batching, steps=None):
    """:func:`_member` over axis 0 of every leaf of ``batch`` (and over the params leaves
    whose ``leaf_axes`` entry is not None), with the batch split evenly across ``mesh``'s
    devices; on each device vmapped (``batching="vmap"``) or one member after another
    (``"map"``). The options are ``structure`` (static) with the traced ``numbers``
    (:meth:`planners.ilq.SolverOptions.split`), shared by the members.

    The batch is padded to a multiple of the device count by repeating its last member;
    every device runs its part (``shard_map``: no communication, so each part's while loops
    end with its own members) and the padding is cut off again.
    """
    from jax.sharding import PartitionSpec

    leaves, treedef = jax.tree_util.tree_flatten(problem.params)
    size = jax.tree_util.tree_leaves(batch)[0].shape[0]
    pad = -size % mesh.size

    def padded(leaf, axis):
        if axis is None or pad == 0:
            return leaf
        last = jax.lax.slice_in_dim(leaf, leaf.shape[axis] - 1, leaf.shape[axis], axis=axis)
        return jnp.concatenate([leaf] + [last] * pad, axis=axis)

    def spec(leaf, axis):
        return PartitionSpec() if axis is None else PartitionSpec(*([None] * (axis % leaf.ndim)), "batch")

    batch_def = jax.tree_util.tree_structure(batch)
    numbers_def = jax.tree_util.tree_structure(numbers)

    def one(*flat):
        """One member from flat arrays: the params leaves, the numbers, then the leaves of ``batch``."""
        p = problem.replace(params=jax.tree_util.tree_unflatten(treedef, flat[: len(leaves)]))
        rest = flat[len(leaves):]
        options = structure.with_numbers(jax.tree_util.tree_unflatten(numbers_def, rest[: numbers_def.num_leaves]))
        return _member(kind, p, jax.tree_util.tree_unflatten(batch_def, rest[numbers_def.num_leaves:]), options, steps)

    # "map": under vmap, one_at_a_time runs the members one after another (a lax.map).
    member = one if batching == "vmap" else one_at_a_time(one)

    def part(leaves, numbers, batch):
        flat = (*leaves, *jax.tree_util.tree_leaves(numbers), *jax.tree_util.tree_leaves(batch))
        in_axes = (*leaf_axes, *[None] * numbers_def.num_leaves, *[0] * batch_def.num_leaves)
        return jax.vmap(member, in_axes=in_axes)(*flat)

    leaves = [padded(leaf, axis) for leaf, axis in zip(leaves, leaf_axes)]
    batch = jax.tree_util.tree_map(lambda leaf: padded(leaf, 0), batch)
    in_specs = ([spec(leaf, axis) for leaf, axis in zip(leaves, leaf_axes)],
                jax.tree_util.tree_map(lambda leaf: PartitionSpec(), numbers),
                jax.tree_util.tree_map(lambda leaf: spec(leaf, 0), batch))
    # check_vma=False: the solver's loop carries start as constants and become per-device.
    result = jax.shard_map(part, mesh=mesh, in_specs=in_specs, out_specs=PartitionSpec("batch"),
                           check_vma=False)(leaves, numbers, batch)
    return jax.tree_util.tree_map(lambda leaf: leaf[:size], result) if pad else result
