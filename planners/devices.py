"""Use every CPU core for batched solves.

JAX shows one CPU device by default, and one compiled solve runs on one core. With
several CPU devices, :func:`planners.ilq_batch.solve_batch` splits its batch across them and the
parts run in parallel (one device per core). JAX fixes the number of CPU devices when its
backend starts, i.e. at the first JAX computation of the process, so call
:func:`use_cpu_cores` right after the imports::

    import planners.devices
    planners.devices.use_cpu_cores()     # all cores; `racing bench` does this itself

Single solves, the environment and the agents keep running on the first device.

A caveat for custom problems: jaxlib 0.10's CPU LAPACK kernels (``jnp.linalg.eigh`` and
others) split a batch of matrices over XLA's intra-op threads and wait for the parts, and
with one device per core every such thread may be running one of those calls at once: the
batch then hangs. The solvers call LAPACK on one matrix at a time; a ``GameProblem`` whose
dynamics or costs call ``jnp.linalg`` should do the same
(:func:`planners.batching.one_at_a_time` keeps a function unbatched under ``vmap``).
"""

from __future__ import annotations

import os

import jax

__all__ = ["use_cpu_cores"]


def use_cpu_cores(count: int | None = None) -> int:
    """Expose ``count`` CPU devices to JAX (default: the cores this process may use).

    Returns the number of CPU devices in effect. Raises ``RuntimeError`` if JAX has already
    started with a different number (set it before the first JAX computation), and
    ``ValueError`` for ``count < 1``.
    """
    if count is None:
        count = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    if count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    try:
        jax.config.update("jax_num_cpu_devices", int(count))
    except RuntimeError as error:  # the backend is already running
        have = len(jax.devices("cpu"))
        if have == count:
            return have
        raise RuntimeError(
            f"JAX already started with {have} CPU device(s); call use_cpu_cores({count}) before "
            "the first JAX computation of the process (right after the imports)"
        ) from error
    return len(jax.devices("cpu"))
