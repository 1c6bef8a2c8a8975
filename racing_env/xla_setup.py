"""The JAX settings the ``racing`` commands run with, and one call to get them in a script.

Importing the package changes nothing in JAX. :func:`configure_for_racing`, which every
``racing`` command calls at its start (and its worker processes at theirs), sets three
things process-wide: 64-bit floats (the game solvers' and certificates' tolerances assume
float64), the loop kernels below, and inline dispatch. Call it at the top of a script,
before the first JAX computation, to run exactly as the commands do::

    from racing_env.xla_setup import configure_for_racing

    configure_for_racing()   # {"x64": "set", "loop_kernels": "set", "inline_dispatch": "set"}

Without it, the race, the envs and the JAX learner run in the caller's precision (float32
with JAX's default), and the solvers refuse to start with a ``RuntimeError`` that says how
to turn float64 on (:func:`racing_env.precision.require_x64`).

The game solvers are sequential loops (``lax.scan`` over the horizon) of many tiny
operations: the Riccati recursion of an LQ game, the forward rollouts. XLA:CPU's default
runtime runs every operation of a loop body as a separate kernel, and for operands of a
few hundred numbers that fixed cost is most of the run time. XLA can instead compile a
whole loop into one function (its "small while loop" hoisting), but only for loops whose
memory traffic per iteration is below ``xla_cpu_small_while_loop_byte_threshold``, which
defaults to about a kilobyte, and that contain no library calls (LAPACK, and the YNNPACK
fusions jaxlib 0.10 makes of dot products). Raising the limit to :data:`LOOP_KERNEL_BYTES`
makes every loop of the two-car solvers a single kernel, and a feedback iteration much
faster (docs/performance.md, "XLA settings and dispatch"). The three-car recursions hold dot products,
laid out so that YNNPACK does not take them (``planners.lq_game._sandwich``): their loops
are single kernels too. The quadratisation's products are such a loop as well
(``planners.local_game._stagewise_gauss_newton_products``), so a single solve holds no library
call at all, and its outer loop (the iterations) compiles into one kernel too: faster
iterations at a longer compile (one large function for LLVM; the loops are not unrolled,
which inside a kernel saves nothing). A batched solve keeps batched products, so its outer
loop stays with the runtime.
``RACING_XLA_LOOP_KERNELS=dots`` also turns every YNNPACK fusion off
(:data:`YNN_FUSION_FLAG`, jaxlib 0.10 only), which makes the outer loop of batched solves
one kernel as well. Results agree to rounding: the same operations (with ``dots``, XLA's
own code for the dot products).

XLA reads its flags (the ``XLA_FLAGS`` environment variable) once, when JAX's backend
starts, i.e. at the first JAX computation of the process. :func:`configure_loop_kernels`
only adds the option if JAX has not started yet and the user has not set it: call it
(through :func:`configure_for_racing`) before the first JAX computation; after, it warns
and changes nothing. ``RACING_XLA_LOOP_KERNELS=off`` keeps XLA's default.

:func:`configure_inline_dispatch` makes JAX run single-device CPU computations on the
calling thread instead of handing them to a worker thread (``jax_cpu_enable_async_dispatch
= False``, also read when the backend starts). An env step is one small jitted call whose
result is needed at once, so the hand-off between threads is pure overhead: inline, an
env step is faster and the solvers, whose results are also used at once, are unchanged
(docs/performance.md). Computations over several devices
(``solve_batch`` split across cores) stay asynchronous. ``RACING_INLINE_DISPATCH=off``
keeps JAX's default, and so does ``jax.config.update("jax_cpu_enable_async_dispatch", True)``
after :func:`configure_for_racing` and before the first computation.
"""

from __future__ import annotations

import os
import warnings

__all__ = [
    "LOOP_KERNEL_BYTES",
    "LOOP_KERNEL_OPTION",
    "YNN_FUSION_FLAG",
    "configure_for_racing",
    "configure_inline_dispatch",
    "configure_loop_kernels",
    "configure_x64",
    "with_loop_kernels",
]

LOOP_KERNEL_OPTION = "xla_cpu_small_while_loop_byte_threshold"
# jaxlib 0.10 hands dot products to YNNPACK as library fusions, which a single-kernel loop
# cannot contain either; with no YNNPACK fusion types XLA emits the dots itself. Opt-in
# (RACING_XLA_LOOP_KERNELS=dots): hoisted loops become large functions that compile
# slowly. Set only for the jaxlib series that has the flag: XLA aborts on a flag its
# version does not know.
YNN_FUSION_FLAG = "--xla_cpu_experimental_ynn_fusion_type"
_YNN_FLAG_JAXLIB = ("0.10.",)
# 128 MiB per loop iteration: every solver loop up to far larger games than the paper's
# (the batch of 64 games needs about 10 MB), while loops that stream bigger arrays keep
# XLA's default multi-kernel execution.
LOOP_KERNEL_BYTES = 1 << 27
_EXTRA_OPTIONS_FLAG = "--xla_backend_extra_options="
_OFF = {"0", "off", "false", "no"}


def with_loop_kernels(xla_flags: str, threshold_bytes: int = LOOP_KERNEL_BYTES, no_ynn_fusions: bool = False) -> str:
    """``xla_flags`` (an ``XLA_FLAGS`` string) with the loop-kernel settings added.

    The threshold option joins an existing ``--xla_backend_extra_options=`` list
    (comma-separated ``key=value`` pairs) or starts one; with ``no_ynn_fusions``,
    ``--xla_cpu_experimental_ynn_fusion_type=`` (empty: no YNNPACK fusions) is added too.
    Values the flags already give for either are kept.
    """
    if threshold_bytes < 0:
        raise ValueError(f"threshold_bytes must be >= 0, got {threshold_bytes}")
    tokens = xla_flags.split()
    if no_ynn_fusions and not any(t.startswith(YNN_FUSION_FLAG) for t in tokens):
        tokens.append(YNN_FUSION_FLAG + "=")
    if LOOP_KERNEL_OPTION in xla_flags:
        return " ".join(tokens)
    option = f"{LOOP_KERNEL_OPTION}={int(threshold_bytes)}"
    for k, token in enumerate(tokens):
        if token.startswith(_EXTRA_OPTIONS_FLAG):
            existing = token[len(_EXTRA_OPTIONS_FLAG):]
            tokens[k] = _EXTRA_OPTIONS_FLAG + (f"{existing},{option}" if existing else option)
            return " ".join(tokens)
    return " ".join(tokens + [_EXTRA_OPTIONS_FLAG + option])


def _jaxlib_in_series(series: tuple[str, ...]) -> bool:
    """Whether the installed jaxlib's version starts with one of ``series`` (e.g. ``("0.10.",)``):
    XLA aborts on a flag its version does not know, so version-bound flags are set only there."""
    try:
        import jaxlib

        return jaxlib.__version__.startswith(series)
    except (ImportError, AttributeError):
        return False


def _jaxlib_knows_ynn_flag() -> bool:
    return _jaxlib_in_series(_YNN_FLAG_JAXLIB)


def _backend_started() -> bool:
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):  # a JAX without this (private) query: assume not
        return False


def configure_loop_kernels() -> str:
    """Add the loop-kernel option to ``XLA_FLAGS`` if it can still take effect.

    Returns what happened: ``"set"``, ``"user"`` (the flags already hold every setting),
    ``"off"`` (``RACING_XLA_LOOP_KERNELS`` is ``off``/``0``/``false``/``no``) or
    ``"too late"`` (JAX already started; a warning says how to get the faster loops).
    ``RACING_XLA_LOOP_KERNELS=dots`` adds the YNNPACK flag as well (on jaxlib 0.10).
    """
    choice = os.environ.get("RACING_XLA_LOOP_KERNELS", "").strip().lower()
    if choice in _OFF:
        return "off"
    flags = os.environ.get("XLA_FLAGS", "")
    wanted = with_loop_kernels(flags, no_ynn_fusions=choice == "dots" and _jaxlib_knows_ynn_flag())
    if wanted == flags:
        return "user"
    if _backend_started():
        warnings.warn(
            "JAX started before racing_env.xla_setup.configure_for_racing() was called, so XLA:CPU "
            "runs the solvers' loops as many small kernels (slower iterations). Call it before "
            f"the first JAX computation, or set XLA_FLAGS='{wanted}' "
            "(RACING_XLA_LOOP_KERNELS=off silences this).",
            RuntimeWarning,
            stacklevel=3,
        )
        return "too late"
    os.environ["XLA_FLAGS"] = wanted
    return "set"


def configure_inline_dispatch() -> str:
    """Run single-device CPU computations on the calling thread, if it can still take effect.

    Returns ``"set"``, ``"user"`` (dispatch is inline already: an earlier call, or the
    user's own setting), ``"off"`` (``RACING_INLINE_DISPATCH`` is ``off``/``0``/``false``/``no``)
    or ``"too late"`` (JAX already started: dispatch stays as it is; results are the same
    either way, only env steps are slower).
    """
    if os.environ.get("RACING_INLINE_DISPATCH", "").strip().lower() in _OFF:
        return "off"
    import jax

    if not jax.config.read("jax_cpu_enable_async_dispatch"):
        return "user"
    if _backend_started():
        return "too late"
    jax.config.update("jax_cpu_enable_async_dispatch", False)
    return "set"


def configure_x64() -> str:
    """Turn on 64-bit floats (``jax_enable_x64``): ``"set"``, or ``"user"`` where they were on.

    JAX reads this setting at every operation, so it works at any time; arrays made before
    keep their float32.
    """
    import jax

    if jax.config.read("jax_enable_x64"):
        return "user"
    jax.config.update("jax_enable_x64", True)
    return "set"


def configure_for_racing() -> dict[str, str]:
    """Set what the ``racing`` commands run with; returns what each setting did.

    The commands (:func:`experiments.cli.main`) and their worker processes call this at
    their start; call it at the top of a script, before the first JAX computation, for the
    same settings. Process-wide, and idempotent:

    * ``"x64"``: 64-bit floats (:func:`configure_x64`), which the game solvers and the
      certificates need (they refuse float32 with a ``RuntimeError``);
    * ``"loop_kernels"``: each solver loop one XLA:CPU kernel (:func:`configure_loop_kernels`;
      ``RACING_XLA_LOOP_KERNELS=off`` opts out, ``XLA_FLAGS`` you set win);
    * ``"inline_dispatch"``: single-device CPU computations on the calling thread
      (:func:`configure_inline_dispatch`; ``RACING_INLINE_DISPATCH=off`` opts out).

    Each value is ``"set"``, ``"user"`` (already so), ``"off"`` (opted out) or ``"too late"``
    (JAX had started: XLA flags and dispatch stay as they are, with a ``RuntimeWarning`` for
    the loops; results are the same, only slower). x64 is ``"set"`` or ``"user"``.
    """
    return {
        "x64": configure_x64(),
        "loop_kernels": configure_loop_kernels(),
        "inline_dispatch": configure_inline_dispatch(),
    }
