"""Shared test configuration: float64 everywhere, two CPU devices, and one on-disk
compilation cache per test run.

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

jax.config.update("jax_enable_x64", True)
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
