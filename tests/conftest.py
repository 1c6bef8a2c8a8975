"""Shared test configuration: float64 everywhere, two CPU devices, no on-disk compilation
cache."""

import os

import jax

from planners.devices import use_cpu_cores

jax.config.update("jax_enable_x64", True)
# Two CPU devices (before any JAX computation): solve_batch splits its batches across them,
# so every batched-solve test runs the multi-device path. Everything else uses device 0.
use_cpu_cores(2)
# The `racing` commands keep compiled solvers in ~/.cache; tests must not read or write it
# (test_compile_cache.py runs the cache in its own directories). Inherited by subprocesses.
os.environ["RACING_COMPILE_CACHE"] = "off"
