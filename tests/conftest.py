"""Shared test configuration: the ``racing`` commands' JAX settings (float64, the solvers'
loop kernels, inline dispatch: ``configure_for_racing``, which importing the packages does
not do), two CPU devices, XLA's quick compile in the default run, and one on-disk
compilation cache per test run. The loop-kernel flag reaches the subprocesses tests start
through ``XLA_FLAGS``; x64 and dispatch do not (a fresh process has JAX's defaults).

Quick compile: most of the default run's time is XLA compiling solvers that then run for
milliseconds, so the default run compiles with XLA's backend optimisations mostly off
(``jax_disable_most_optimizations``; ``JAX_DISABLE_MOST_OPTIMIZATIONS=1`` for the
subprocesses tests start). The JAX programs are the same; XLA's code for them is slower
and may round differently in the last bits, which no tolerance of the math notices. The
few tests that compare against bits the optimised program wrote, or that race for minutes,
run their part in a fresh process with the users' settings (``tests/optimized.py``).
``make test-all`` sets ``RACING_TEST_OPTIMIZED=1``: every test then runs the optimised
programs users run.

The cache: every test process (the xdist workers and the subprocesses tests start:
``racing`` commands, the docs' code blocks) compiles many of the same solvers (the agents'
defaults on the same circuits and horizons). The controller process makes one fresh
directory per run, the workers and their subprocesses share it through the environment,
so a solver compiled once is loaded by every later process; the directory is deleted when
the run ends. Tests never read or write the user's cache in ``~/.cache``;
``tests/test_compile_cache.py`` runs the cache in directories of its own.
"""

import os
import shutil
import tempfile

import jax

from planners.compile_cache import ENV_VAR, MAX_BYTES, enable_compile_cache
from planners.devices import use_cpu_cores
from racing_env.xla_setup import configure_for_racing

from optimized import QUICK_COMPILE_VAR, optimized_run

# What the commands run with, before the first JAX computation: float64 (the tests' tolerances
# assume it), the loop kernels and inline dispatch.
configure_for_racing()
# Before the first compilation; the value travels to subprocesses through the environment.
if not optimized_run():
    os.environ[QUICK_COMPILE_VAR] = "1"
    jax.config.update("jax_disable_most_optimizations", True)
# Two CPU devices (before any JAX computation): solve_batch splits its batches across them,
# so every batched-solve test runs the multi-device path. Everything else uses device 0.
use_cpu_cores(2)

_RUN_CACHE = "RACING_TEST_RUN_COMPILE_CACHE"  # the run's directory, set by the controller
_MIN_COMPILE_SECONDS = 0.5  # store programs that took this long to compile (the solvers)


def pytest_configure(config) -> None:
    """The controller (or a run without workers) makes the run's cache directory; every
    process of the run turns the cache on there. Subprocesses inherit it: the ``racing``
    commands through ``RACING_COMPILE_CACHE``, plain scripts through JAX's own variables."""
    directory = os.environ.get(_RUN_CACHE)
    if directory is None or not hasattr(config, "workerinput"):
        directory = tempfile.mkdtemp(prefix="racing-test-jax-cache-")
        os.environ[_RUN_CACHE] = directory
        config._racing_owns_cache = directory
    os.environ[ENV_VAR] = directory
    os.environ["JAX_COMPILATION_CACHE_DIR"] = directory
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = str(_MIN_COMPILE_SECONDS)
    # The same size cap as enable_compile_cache's in every process: JAX keeps the entries'
    # access times only where a cap is set, and a capped process fails on entries without them.
    os.environ["JAX_COMPILATION_CACHE_MAX_SIZE"] = str(MAX_BYTES)
    enable_compile_cache(directory, min_compile_seconds=_MIN_COMPILE_SECONDS)


def pytest_unconfigure(config) -> None:
    directory = getattr(config, "_racing_owns_cache", None)
    if directory is not None:
        shutil.rmtree(directory, ignore_errors=True)
