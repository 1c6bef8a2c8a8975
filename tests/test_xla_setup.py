"""The XLA:CPU loop-kernel setting applied on import (racing_env.xla_setup)."""

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from racing_env.xla_setup import LOOP_KERNEL_BYTES, LOOP_KERNEL_OPTION, YNN_FUSION_FLAG, with_loop_kernels

OPTION = f"{LOOP_KERNEL_OPTION}={LOOP_KERNEL_BYTES}"


def test_flags_gain_the_option():
    assert with_loop_kernels("", no_ynn_fusions=False) == f"--xla_backend_extra_options={OPTION}"
    assert with_loop_kernels("--xla_cpu_enable_fast_math=false", no_ynn_fusions=True) == (
        f"--xla_cpu_enable_fast_math=false {YNN_FUSION_FLAG}= --xla_backend_extra_options={OPTION}"
    )


def test_an_existing_extra_options_list_is_extended():
    flags = "--xla_dump_to=/tmp/d --xla_backend_extra_options=xla_cpu_disable_slp_vectorizer=true"
    assert with_loop_kernels(flags, no_ynn_fusions=False) == (
        "--xla_dump_to=/tmp/d --xla_backend_extra_options="
        f"xla_cpu_disable_slp_vectorizer=true,{OPTION}"
    )


def test_values_the_user_set_are_kept():
    flags = f"--xla_backend_extra_options={LOOP_KERNEL_OPTION}=0"
    assert with_loop_kernels(flags) == flags
    assert with_loop_kernels(flags, no_ynn_fusions=True) == f"{flags} {YNN_FUSION_FLAG}="
    mine = f"{YNN_FUSION_FLAG}=individual"
    assert with_loop_kernels(mine, no_ynn_fusions=True) == f"{mine} --xla_backend_extra_options={OPTION}"


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
    # Two players with 6 states: small products only. Three with 18: the recursion's
    # largest products are dot operations (planners.lq_game._sandwich).
    T, m = 10, 2
    N, n = (3, 18) if sys.argv[2] == "three" else (2, 6)
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


def _child(mode: str, players: str = "two", **env) -> dict:
    environ = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "RACING_XLA_LOOP_KERNELS")}
    environ.update(env)
    out = subprocess.run([sys.executable, "-c", _CHILD, mode, players], env=environ, capture_output=True,
                         text=True, timeout=240, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def _assert_same_gains(a: dict, b: dict) -> None:
    # The same operations (with "dots", the dots summed by other code): the gains agree to
    # rounding (float64 eps times the growth of errors through ten stages of the recursion).
    for name in ("K", "k"):
        x, y = np.asarray(a[name]), np.asarray(b[name])
        assert np.max(np.abs(x - y)) <= 1e-12 * np.max(np.abs(y))


def test_importing_planners_compiles_the_lq_recursion_as_one_kernel_with_the_same_result():
    fast = _child("import_first")
    default = _child("import_first", RACING_XLA_LOOP_KERNELS="off")
    # The import set the option (a second call finds it set); XLA made the recursion's loop
    # one kernel, and did not with the opt-out.
    assert fast["status"] == "user" and fast["single_kernel_loop"] and not fast["warnings"]
    assert default["status"] == "off" and not default["single_kernel_loop"]
    _assert_same_gains(fast, default)


def test_three_player_recursion_with_dot_products_is_one_kernel_too():
    """Its largest products are dots laid out so that jaxlib 0.10's YNNPACK dot fusion does
    not take them (a library fusion would keep the loop from becoming one kernel)."""
    plain = _child("import_first", "three")
    dots = _child("import_first", "three", RACING_XLA_LOOP_KERNELS="dots")
    off = _child("import_first", "three", RACING_XLA_LOOP_KERNELS="off")
    assert plain["single_kernel_loop"] and dots["single_kernel_loop"]
    assert not off["single_kernel_loop"]
    _assert_same_gains(plain, off)
    _assert_same_gains(dots, off)


@pytest.mark.parametrize("cars", [2, 3])
def test_gauss_newton_quadratization_holds_no_library_call(cars):
    """The quadratisation's products run as a loop kernel with no YNNPACK fusion (fused code
    for two cars, XLA's own dots for three): a library call anywhere in a solver iteration
    would keep the solver's outer loop from becoming one kernel (docs/performance.md, Loop kernels)."""
    import jax
    import jax.numpy as jnp

    from experiments.bench import _solver_game
    from planners import local_game, race_problem

    game, x0 = _solver_game(cars)
    problem = race_problem.problem_from_race_game(game)
    xs = jnp.tile(jnp.asarray(x0).reshape(1, -1), (game.horizon + 1, 1))
    us = jnp.zeros((game.horizon, cars, 2))
    quadratize = lambda xs, us: local_game.quadratize(problem, xs, us, gauss_newton=True, dynamics_curvature=True)
    text = jax.jit(quadratize).lower(xs, us).compile().as_text()
    assert "__ynn_fusion" not in text
    assert "xla_cpu_small_call" in text  # the loop over the stages is one kernel


def test_jax_started_before_the_import_is_reported():
    late = _child("jax_first")
    assert late["status"] == "too late" and not late["single_kernel_loop"]
    assert len(late["warnings"]) == 1 and "before the first JAX computation" in late["warnings"][0]


_ENV_CHILD = textwrap.dedent(
    """
    import json, sys
    if sys.argv[1] == "jax_first":
        import jax.numpy as jnp
        jnp.ones(1).block_until_ready()
    import jax, numpy as np
    import racing_env
    env = racing_env.parallel_env(track="trefoil", num_agents=2)
    observations, _ = env.reset(seed=3)
    actions = np.random.default_rng(0).uniform(-1, 1, size=(40, 2, 2))
    for k in range(40):
        observations, rewards, *_ = env.step({a: actions[k, i] for i, a in enumerate(env.agents)})
    print(json.dumps({
        "async_dispatch": jax.config.values["jax_cpu_enable_async_dispatch"],
        "state": env.state().tolist(),
        "observations": {a: o.tolist() for a, o in observations.items()},
        "rewards": rewards,
    }))
    """
)


def _env_child(mode: str, **env) -> dict:
    environ = {k: v for k, v in os.environ.items() if k != "RACING_INLINE_DISPATCH"}
    environ.update(env)
    out = subprocess.run([sys.executable, "-c", _ENV_CHILD, mode], env=environ, capture_output=True,
                         text=True, timeout=240, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_inline_dispatch_is_set_on_import_and_changes_no_result():
    inline = _env_child("import_first")
    queued = _env_child("import_first", RACING_INLINE_DISPATCH="off")
    late = _env_child("jax_first")
    assert inline["async_dispatch"] is False
    assert queued["async_dispatch"] is True and late["async_dispatch"] is True
    # Only which thread runs the computation differs: the race is bit-for-bit the same.
    for other in (queued, late):
        assert {k: v for k, v in other.items() if k != "async_dispatch"} == {
            k: v for k, v in inline.items() if k != "async_dispatch"
        }
