"""Where independent jobs run: this process, a pool of local worker processes, or a Ray
cluster. Sweeps and tournaments hand their races to :func:`run_jobs` and get the results
back as the races end, in whatever order that is.

A job's function must be importable by name (a module-level function, or a
``functools.partial`` of one) so that worker processes and Ray tasks can run it. Workers
use the caller's compilation cache (:mod:`planners.compile_cache`), so a planner compiled by
an earlier run is loaded, not compiled again.
"""

from __future__ import annotations

import functools
import signal
from typing import Any, Callable, Iterable, Iterator

BACKENDS = ("local", "ray")
JOBS_PER_WORKER = 50
"""Jobs a worker process runs before a fresh one takes its place: a bound on whatever a
worker keeps from job to job, beside :data:`MAP_BUDGET`."""
MAP_BUDGET = 20_000
"""Memory maps a process may hold after a job before its compiled programs are let go. A
process keeps every program it compiles (a planner per circuit, car class and field size:
1,500-2,000 maps for a duel of a game planner on a new circuit, more for a field), and near
the kernel's limit (``vm.max_map_count``, 65,530 by default) it fails to compile. Programs let
go are loaded from the compilation cache when they are needed again."""


def check_backend(backend: str, workers: int) -> None:
    """Refuse an unknown backend or a worker count below one."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be an integer >= 1, got {workers!r}")


def run_jobs(function: Callable[[Any], Any], jobs: Iterable[Any], backend: str = "local", workers: int = 1,
             address: str | None = None, jobs_per_worker: int = JOBS_PER_WORKER) -> Iterator[Any]:
    """Yield ``function(job)`` for every job as each finishes.

    ``local`` with one worker runs the jobs here, in order; with more, in a pool of spawned
    processes. ``ray`` runs each job as a task of one CPU on the cluster at ``address``, or
    on a local Ray instance of ``workers`` CPUs started and stopped here. A worker process
    runs at most ``jobs_per_worker`` jobs before a fresh one replaces it
    (:data:`JOBS_PER_WORKER`). Closing the iterator early (e.g. at Ctrl-C) terminates the
    workers or cancels the pending tasks.
    """
    from planners.compile_cache import compile_cache_dir

    check_backend(backend, workers)
    if not isinstance(jobs_per_worker, int) or jobs_per_worker < 1:
        raise ValueError(f"jobs_per_worker must be an integer >= 1, got {jobs_per_worker!r}")
    jobs = list(jobs)
    if backend == "local" and workers == 1:
        return (_released_after(function(job)) for job in jobs)
    task = functools.partial(_in_worker, function, compile_cache_dir())
    if backend == "local":
        return _run_pool(task, jobs, workers, jobs_per_worker)
    return _run_ray(task, jobs, workers, address, jobs_per_worker)


def _in_worker(function, compile_cache: str | None, job):
    """Run one job in a worker: the commands' JAX settings
    (:func:`racing_env.xla_setup.configure_for_racing`: float64, loop kernels, inline
    dispatch; a spawned process or a Ray worker starts with JAX's defaults) and the
    caller's compilation cache first."""
    from racing_env.xla_setup import configure_for_racing

    configure_for_racing()  # before any JAX work; a later job in the same worker finds it set

    if compile_cache is not None:
        from planners.compile_cache import enable_compile_cache

        enable_compile_cache(compile_cache)
    return _released_after(function(job))


def _released_after(result: Any, budget: int = MAP_BUDGET) -> Any:
    """``result``, after letting go of this process's compiled programs if it holds more than
    ``budget`` memory maps (:data:`MAP_BUDGET`; where ``/proc/self/maps`` cannot be read, the
    worker's job count bounds them, :data:`JOBS_PER_WORKER`)."""
    try:
        with open("/proc/self/maps") as maps:
            count = sum(1 for _ in maps)
    except OSError:
        return result
    if count > budget:
        import gc

        import jax

        jax.clear_caches()
        gc.collect()
    return result


def _ignore_interrupts() -> None:
    """Pool initialiser: Ctrl-C reaches the whole process group, and the parent stops the
    workers itself (a worker interrupted mid-job would only print a traceback)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _run_pool(task, jobs, workers: int, jobs_per_worker: int) -> Iterator[Any]:
    import multiprocessing

    pool = multiprocessing.get_context("spawn").Pool(workers, initializer=_ignore_interrupts,
                                                     maxtasksperchild=jobs_per_worker)
    finished = False
    try:
        yield from pool.imap_unordered(task, jobs)
        finished = True
    finally:
        # After the last job the workers are let go; terminating them then could kill one
        # mid-exit and leave a semaphore for the resource tracker to warn about.
        if finished:
            pool.close()
        else:  # closed early (Ctrl-C, an error): stop them now
            pool.terminate()
        pool.join()


def _run_ray(task, jobs, workers: int, address: str | None, jobs_per_worker: int) -> Iterator[Any]:
    import ray

    started = not ray.is_initialized()
    if started:
        try:
            ray.init(address=address, num_cpus=None if address else workers, include_dashboard=False,
                     log_to_driver=False)
        except ConnectionError as err:
            raise ValueError(f"could not join the Ray cluster at {address!r}: {err}") from None
    try:
        remote = ray.remote(num_cpus=1, max_calls=jobs_per_worker)(_call)
        pending = [remote.remote(task, job) for job in jobs]
        try:
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                yield ray.get(done[0])
        except BaseException:
            for ref in pending:
                ray.cancel(ref, force=True)
            raise
    finally:
        if started:
            ray.shutdown()


def _call(task, job):
    """The Ray task: ``task(job)`` (Ray wants a plain function to make remote)."""
    return task(job)
