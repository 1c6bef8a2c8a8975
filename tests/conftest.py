"""Shared test configuration: the ``racing`` commands' JAX settings (float64, the solvers'
loop kernels, inline dispatch: ``configure_for_racing``, which importing the packages does
not do), two CPU devices, XLA's quick compile in the default run, and one on-disk
compilation cache per test run. The loop-kernel flag reaches the subprocesses tests start
through ``XLA_FLAGS``; x64 and dispatch do not (a fresh process has JAX's defaults).

Quick compile: most of the default run's time is XLA compiling solvers that then run for
milliseconds, so the default run compiles with XLA's backend optimisations mostly off
(``jax_disable_most_optimizations``; ``JAX_DISABLE_MOST_OPTIMIZATIONS=1`` for the
subprocesses tests start). The JAX programs are the same; XLA's code for them is slower
and may round differently in the last bits, which no tolerance of the math notices. A test
module whose races run long enough that the slower code costs more than the quicker compile
saves is marked ``pytestmark = pytest.mark.optimized``: it compiles with the full
optimisations (the worker's compiled programs are cleared on the way in and out, so no
program crosses the setting; ``--dist loadfile`` keeps a module in one worker). The recorded races'
replay (bits the optimised program wrote) is such a module.
``make test-all`` sets ``RACING_TEST_OPTIMIZED=1``: every test then runs the optimised
programs users run.

Legacy emitters: the quick run also compiles with XLA:CPU's fusion emitters off
(``--xla_cpu_use_fusion_emitters=false`` in ``XLA_FLAGS``, so the subprocesses too, set
before JAX starts): XLA then emits its fusions with its older elemental code generator,
which compiles a program in about 60% of the time (a thousand small eager operations: 20 s
-> 12 s; the solver tests of ``test_ilq.py``: -27%). The same HLO is computed, its
rounding may differ in the last bits; ``make test-all`` keeps XLA's default. Set only
for the jaxlib series checked to know the flag (0.10), since XLA aborts on an unknown one.

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
import pytest

from planners.compile_cache import ENV_VAR, MAX_BYTES, enable_compile_cache
from planners.devices import use_cpu_cores
from racing_env.xla_setup import _jaxlib_in_series, configure_for_racing

QUICK_COMPILE_VAR = "JAX_DISABLE_MOST_OPTIMIZATIONS"  # what tells subprocesses to compile quickly
OPTIMIZED_VAR = "RACING_TEST_OPTIMIZED"  # 1: the whole run compiles with XLA's full optimisations
LEGACY_EMITTERS_FLAG = "--xla_cpu_use_fusion_emitters=false"  # quicker XLA:CPU compiles (module docstring)
# XLA aborts on a flag its version does not know: set only for the jaxlib series checked to have it
_LEGACY_EMITTERS_JAXLIB = ("0.10.",)


def optimized_run() -> bool:
    """Whether this run compiles with XLA's full optimisations (``RACING_TEST_OPTIMIZED``)."""
    return os.environ.get(OPTIMIZED_VAR, "").strip().lower() in {"1", "true", "yes", "on"}


# XLA reads XLA_FLAGS when its backend starts: before the first JAX computation.
if (not optimized_run() and _jaxlib_in_series(_LEGACY_EMITTERS_JAXLIB)
        and "xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", "")):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {LEGACY_EMITTERS_FLAG}".strip()
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
_MIN_COMPILE_SECONDS = 0.2  # store programs that took this long to compile (the solvers, quickly compiled)


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


@pytest.fixture(scope="module", autouse=True)
def _optimized_module(request):
    """A module marked ``optimized`` compiles with XLA's full optimisations in a quick run
    (module docstring); other modules keep the run's setting."""
    if optimized_run() or request.node.get_closest_marker("optimized") is None:
        yield
        return
    jax.clear_caches()
    jax.config.update("jax_disable_most_optimizations", False)
    quick = os.environ.pop(QUICK_COMPILE_VAR, None)
    try:
        yield
    finally:
        jax.clear_caches()
        jax.config.update("jax_disable_most_optimizations", True)
        if quick is not None:
            os.environ[QUICK_COMPILE_VAR] = quick
