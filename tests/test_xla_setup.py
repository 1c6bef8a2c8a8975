"""The XLA:CPU loop-kernel setting applied on import (racing_env.xla_setup)."""

import json
import os
import subprocess
import sys
import textwrap

import pytest

from racing_env.xla_setup import LOOP_KERNEL_BYTES, LOOP_KERNEL_OPTION, with_loop_kernels

OPTION = f"{LOOP_KERNEL_OPTION}={LOOP_KERNEL_BYTES}"


def test_flags_gain_the_option():
    assert with_loop_kernels("") == f"--xla_backend_extra_options={OPTION}"
    assert with_loop_kernels("--xla_cpu_enable_fast_math=false") == (
        f"--xla_cpu_enable_fast_math=false --xla_backend_extra_options={OPTION}"
    )


def test_an_existing_extra_options_list_is_extended():
    flags = "--xla_dump_to=/tmp/d --xla_backend_extra_options=xla_cpu_disable_slp_vectorizer=true"
    assert with_loop_kernels(flags) == (
        "--xla_dump_to=/tmp/d --xla_backend_extra_options="
        f"xla_cpu_disable_slp_vectorizer=true,{OPTION}"
    )


def test_a_value_the_user_set_is_kept():
    flags = f"--xla_backend_extra_options={LOOP_KERNEL_OPTION}=0"
    assert with_loop_kernels(flags) == flags


def test_negative_threshold_is_refused():
    with pytest.raises(ValueError, match="threshold_bytes"):
        with_loop_kernels("", -1)


_CHILD = textwrap.dedent(
    """
    import json, os, sys, warnings
    if sys.argv[1] == "jax_first":
        import jax.numpy as jnp
        jnp.ones(1).block_until_ready()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        import planners.lq_game as lq
    import jax, numpy as np
    from racing_env.xla_setup import configure_loop_kernels
    rng = np.random.default_rng(0)
    T, N, n, m = 20, 2, 6, 2
    L = rng.normal(size=(T + 1, N, n, n))
    game = (np.eye(n) + 0.1 * rng.normal(size=(T, n, n)), 0.3 * rng.normal(size=(T, N, n, m)),
            np.einsum("tiab,ticb->tiac", L, L), rng.normal(size=(T + 1, N, n)),
            np.broadcast_to(np.eye(m), (T, N, m, m)), rng.normal(size=(T, N, m)))
    compiled = lq.solve_feedback_own.lower(*game).compile()
    K, k = compiled(*game)
    print(json.dumps({
        "status": configure_loop_kernels(),
        "single_kernel_loop": "xla_cpu_small_call" in compiled.as_text(),
        "warnings": [str(w.message) for w in caught],
        "K": np.asarray(K).tolist(), "k": np.asarray(k).tolist(),
    }))
    """
)


def _child(mode: str, **env) -> dict:
    environ = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "RACING_XLA_LOOP_KERNELS")}
    environ.update(env)
    out = subprocess.run([sys.executable, "-c", _CHILD, mode], env=environ, capture_output=True,
                         text=True, timeout=240, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_importing_planners_compiles_the_lq_recursion_as_one_kernel_with_the_same_result():
    import numpy as np

    fast = _child("import_first")
    default = _child("import_first", RACING_XLA_LOOP_KERNELS="off")
    # The import set the option (a second call finds it set); XLA hoisted the recursion's
    # loop into one kernel, and did not with the opt-out.
    assert fast["status"] == "user" and fast["single_kernel_loop"] and not fast["warnings"]
    assert default["status"] == "off" and not default["single_kernel_loop"]
    # The same operations in the same order: the gains agree to rounding.
    np.testing.assert_allclose(fast["K"], default["K"], rtol=0, atol=1e-12)
    np.testing.assert_allclose(fast["k"], default["k"], rtol=0, atol=1e-12)


def test_jax_started_before_the_import_is_reported():
    late = _child("jax_first")
    assert late["status"] == "too late" and not late["single_kernel_loop"]
    assert len(late["warnings"]) == 1 and "before the first JAX computation" in late["warnings"][0]
