"""XLA:CPU settings the project's jitted loops rely on, applied when ``racing_env`` is imported.

The game solvers are sequential loops (``lax.scan`` over the horizon) of many tiny
operations: the Riccati recursion of an LQ game, the forward rollouts. XLA:CPU's default
runtime runs every operation of a loop body as a separate kernel, and for operands of a
few hundred numbers that fixed cost is most of the run time. XLA can instead compile a
whole loop into one function (its "small while loop" hoisting), but only for loops whose
memory traffic per iteration is below ``xla_cpu_small_while_loop_byte_threshold``, which
defaults to about a kilobyte. Raising it to :data:`LOOP_KERNEL_BYTES` makes every loop of
the solvers a single kernel: the N = 2 feedback LQ recursion runs about twice as fast, and
so does the forward pass (``racing bench --only solvers``; README, Benchmarks). Results are
unchanged: the same operations in the same order.

XLA reads its flags (the ``XLA_FLAGS`` environment variable) once, when JAX's backend
starts, i.e. at the first JAX computation of the process. :func:`configure_loop_kernels`
therefore runs on import, and only adds the option if JAX has not started yet and the
user has not set it. ``RACING_XLA_LOOP_KERNELS=off`` keeps XLA's default.
"""

from __future__ import annotations

import os
import warnings

__all__ = ["LOOP_KERNEL_BYTES", "LOOP_KERNEL_OPTION", "configure_loop_kernels", "with_loop_kernels"]

LOOP_KERNEL_OPTION = "xla_cpu_small_while_loop_byte_threshold"
# 128 MiB per loop iteration: every solver loop up to far larger games than the paper's
# (the batch of 64 games needs about 10 MB), while loops that stream bigger arrays keep
# XLA's default multi-kernel execution.
LOOP_KERNEL_BYTES = 1 << 27
_EXTRA_OPTIONS_FLAG = "--xla_backend_extra_options="
_OFF = {"0", "off", "false", "no"}


def with_loop_kernels(xla_flags: str, threshold_bytes: int = LOOP_KERNEL_BYTES) -> str:
    """``xla_flags`` (an ``XLA_FLAGS`` string) with the loop-kernel option added.

    A value the flags already give for the option is kept. The option joins an existing
    ``--xla_backend_extra_options=`` list (comma-separated ``key=value`` pairs) or starts one.
    """
    if threshold_bytes < 0:
        raise ValueError(f"threshold_bytes must be >= 0, got {threshold_bytes}")
    if LOOP_KERNEL_OPTION in xla_flags:
        return xla_flags
    option = f"{LOOP_KERNEL_OPTION}={int(threshold_bytes)}"
    tokens = xla_flags.split()
    for k, token in enumerate(tokens):
        if token.startswith(_EXTRA_OPTIONS_FLAG):
            existing = token[len(_EXTRA_OPTIONS_FLAG):]
            tokens[k] = _EXTRA_OPTIONS_FLAG + (f"{existing},{option}" if existing else option)
            return " ".join(tokens)
    return " ".join(tokens + [_EXTRA_OPTIONS_FLAG + option])


def _backend_started() -> bool:
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):  # a JAX without this (private) query: assume not
        return False


def configure_loop_kernels() -> str:
    """Add the loop-kernel option to ``XLA_FLAGS`` if it can still take effect.

    Returns what happened: ``"set"``, ``"user"`` (the flags already name the option),
    ``"off"`` (``RACING_XLA_LOOP_KERNELS`` is ``off``/``0``/``false``/``no``) or
    ``"too late"`` (JAX already started; a warning says how to get the faster loops).
    """
    if os.environ.get("RACING_XLA_LOOP_KERNELS", "").strip().lower() in _OFF:
        return "off"
    flags = os.environ.get("XLA_FLAGS", "")
    if LOOP_KERNEL_OPTION in flags:
        return "user"
    if _backend_started():
        warnings.warn(
            "JAX started before racing_env was imported, so XLA:CPU runs the solvers' loops "
            "as many small kernels (about 1.5x slower iterations). Import racing_env or "
            "planners before the first JAX computation, or set XLA_FLAGS="
            f"'{with_loop_kernels('')}' (RACING_XLA_LOOP_KERNELS=off silences this).",
            RuntimeWarning,
            stacklevel=3,
        )
        return "too late"
    os.environ["XLA_FLAGS"] = with_loop_kernels(flags)
    return "set"
