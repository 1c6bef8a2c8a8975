"""Batching rules for the solvers' building blocks on CPU."""

from __future__ import annotations

import functools
from typing import Callable

import jax

__all__ = ["one_at_a_time"]


def one_at_a_time(fn: Callable) -> Callable:
    """``fn`` with a batching rule that runs it on one batch member after another.

    Under ``jax.vmap`` the wrapped function becomes a ``lax.map`` over the batched
    arguments (unbatched ones are shared, not copied), and nested ``vmap``s nest the maps,
    so ``fn`` itself is only ever traced on unbatched arguments (derivatives are taken of
    ``fn`` directly, batched as usual). Two reasons on CPU:

    * speed: measured on a 2-core CPU for the racing games (N = 2, n = 12, T = 50), the
      fused single-game LQ recursions in a ``lax.map`` cost what one game costs alone,
      while the vmapped formulations cost more per game (batched dots and LAPACK calls:
      1.3-1.5x; the fused code vmapped, or with the batch as the innermost axis: worse
      still), because XLA:CPU vectorises none of them across games;
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

    # custom_vmap has no reverse-mode rule; derivatives are those of fn itself.
    @jax.custom_jvp
    def wrapped(*args):
        return mapped(*args)

    @wrapped.defjvp
    def _jvp(primals, tangents):
        return jax.jvp(fn, primals, tangents)

    return functools.wraps(fn)(wrapped)
