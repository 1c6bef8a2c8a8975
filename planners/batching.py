"""Batching rules for the solvers' building blocks on CPU."""

from __future__ import annotations

import functools
from typing import Callable

import jax
import jax.numpy as jnp

__all__ = ["one_at_a_time", "with_batched_form"]


def one_at_a_time(fn: Callable) -> Callable:
    """``fn`` with a batching rule that runs it on one batch member after another.

    Under ``jax.vmap`` the wrapped function becomes a ``lax.map`` over the batched
    arguments (unbatched ones are shared, not copied), and nested ``vmap``s nest the maps,
    so ``fn`` itself is only ever traced on unbatched arguments (derivatives are taken of
    ``fn`` directly, batched as usual). Two reasons on CPU:

    * speed: for games as small as the racing games, the fused single-game LQ recursions
      in a ``lax.map`` cost what one game costs alone, while the vmapped formulations
      (batched dots and LAPACK calls, the fused code vmapped, or with the batch as the
      innermost axis) cost more per game, because XLA:CPU vectorises none of them across
      games (docs/performance.md);
    * no deadlock: jaxlib 0.10's CPU LAPACK kernels split a large batch of matrices over
      XLA's intra-op thread pool and wait for the parts. When every pool thread is itself
      running such a kernel (one per CPU device in a batch split across devices), nothing
      is left to run the parts and the process hangs. A ``fn`` that calls LAPACK on one
      matrix at a time stays one matrix at a time under ``vmap``.
    """
    mapped = jax.custom_batching.custom_vmap(fn)

    @mapped.def_vmap
    def _rule(axis_size, in_batched, *args):
        del axis_size
        batched = tuple(a for a, b in zip(args, in_batched) if b)

        def one(member_args):
            it = iter(member_args)
            return wrapped(*(next(it) if b else a for a, b in zip(args, in_batched)))

        out = jax.lax.map(one, batched)
        return out, jax.tree_util.tree_map(lambda _: True, out)

    wrapped = _differentiable_as(fn, mapped)  # the rule's members call it: nested maps
    return wrapped


def with_batched_form(fn: Callable, batched_fn: Callable) -> Callable:
    """``fn`` with a batching rule that calls ``batched_fn`` on the whole batch.

    ``batched_fn`` takes and returns ``fn``'s arrays with one more leading axis and must
    compute the same function member by member. Under ``jax.vmap`` every argument gets the
    batch axis in front (unbatched ones are broadcast) and ``batched_fn`` runs once; outer
    ``vmap``s of a nest batch ``batched_fn`` as usual. For building blocks whose best
    single-problem form (e.g. a loop that XLA compiles into one kernel) is a poor batched
    form on CPU. Derivatives are those of ``fn``.
    """
    batched = jax.custom_batching.custom_vmap(fn)

    @batched.def_vmap
    def _rule(axis_size, in_batched, *args):
        args = [a if b else jnp.broadcast_to(a, (axis_size,) + jnp.shape(a)) for a, b in zip(args, in_batched)]
        out = batched_fn(*args)
        return out, jax.tree_util.tree_map(lambda _: True, out)

    return _differentiable_as(fn, batched)


def _differentiable_as(fn: Callable, custom: Callable) -> Callable:
    """``custom`` (a ``custom_vmap`` of ``fn``) with ``fn``'s derivatives: custom_vmap has no
    reverse-mode rule of its own."""

    @jax.custom_jvp
    def wrapped(*args):
        return custom(*args)

    @wrapped.defjvp
    def _jvp(primals, tangents):
        return jax.jvp(fn, primals, tangents)

    return functools.wraps(fn)(wrapped)
