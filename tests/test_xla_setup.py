"""The JAX settings of the racing commands (racing_env.xla_setup.configure_for_racing), which
importing the packages does not apply: the loop kernels, inline dispatch and float64, set by
the function and by a command's start, and the solvers' refusal of float32."""

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
    import planners.lq_game as lq
    from racing_env.xla_setup import configure_for_racing, configure_loop_kernels
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        first = configure_for_racing()
    import jax, numpy as np
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
        "first": first["loop_kernels"], "status": configure_loop_kernels(),
        "single_kernel_loop": "xla_cpu_small_call" in compiled.as_text(),
        "warnings": [str(w.message) for w in caught],
        "K": np.asarray(K).tolist(), "k": np.asarray(k).tolist(),
    }))
    """
)

# What a child process must not inherit from the test process, whose conftest applied the
# commands' settings (XLA_FLAGS travels through the environment) or from the caller's shell.
_SETTINGS_VARS = ("XLA_FLAGS", "RACING_XLA_LOOP_KERNELS", "RACING_INLINE_DISPATCH", "JAX_ENABLE_X64")


def _fresh_environment(**env: str) -> dict[str, str]:
    environ = {k: v for k, v in os.environ.items() if k not in _SETTINGS_VARS}
    environ.update(env)
    return environ


def _child(mode: str, players: str = "two", **env) -> dict:
    out = subprocess.run([sys.executable, "-c", _CHILD, mode, players], env=_fresh_environment(**env),
                         capture_output=True, text=True, timeout=240, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def _assert_same_gains(a: dict, b: dict) -> None:
    # The same operations (with "dots", the dots summed by other code): the gains agree to
    # rounding (float64 eps times the growth of errors through ten stages of the recursion).
    for name in ("K", "k"):
        x, y = np.asarray(a[name]), np.asarray(b[name])
        assert np.max(np.abs(x - y)) <= 1e-12 * np.max(np.abs(y))


def test_configure_for_racing_compiles_the_lq_recursion_as_one_kernel_with_the_same_result():
    fast = _child("configure_first")
    default = _child("configure_first", RACING_XLA_LOOP_KERNELS="off")
    # The call set the option (a second call finds it set); XLA made the recursion's loop
    # one kernel, and did not with the opt-out.
    assert fast["first"] == "set" and fast["status"] == "user" and fast["single_kernel_loop"]
    assert not fast["warnings"]
    assert default["first"] == default["status"] == "off" and not default["single_kernel_loop"]
    _assert_same_gains(fast, default)


def test_three_player_recursion_with_dot_products_is_one_kernel_too():
    """Its largest products are dots laid out so that jaxlib 0.10's YNNPACK dot fusion does
    not take them (a library fusion would keep the loop from becoming one kernel)."""
    plain = _child("configure_first", "three")
    dots = _child("configure_first", "three", RACING_XLA_LOOP_KERNELS="dots")
    off = _child("configure_first", "three", RACING_XLA_LOOP_KERNELS="off")
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

    from experiments.bench_scenes import solver_game
    from planners import local_game, race_problem

    game, x0 = solver_game(cars)
    problem = race_problem.problem_from_race_game(game)
    xs = jnp.tile(jnp.asarray(x0).reshape(1, -1), (game.horizon + 1, 1))
    us = jnp.zeros((game.horizon, cars, 2))
    quadratize = lambda xs, us: local_game.quadratize(problem, xs, us, gauss_newton=True, dynamics_curvature=True)
    text = jax.jit(quadratize).lower(xs, us).compile().as_text()
    assert "__ynn_fusion" not in text
    assert "xla_cpu_small_call" in text  # the loop over the stages is one kernel


def test_jax_started_before_the_call_is_reported():
    late = _child("jax_first")
    assert late["first"] == late["status"] == "too late" and not late["single_kernel_loop"]
    assert len(late["warnings"]) == 1 and "before the first JAX computation" in late["warnings"][0]


# Importing the three packages (and the modules the commands and their workers load) changes
# no JAX setting and starts no JAX backend; a command's start (the CLI's main, here `racing
# agents NAME`, which imports the agents and the solvers) sets everything; with x64 then
# switched off every solver entry refuses with the error that says how to turn it on.
_IMPORT_CHILD = textwrap.dedent(
    """
    import json, os, sys
    import jax
    from jax._src import xla_bridge

    def settings():
        return {"x64": bool(jax.config.read("jax_enable_x64")), "xla_flags": os.environ.get("XLA_FLAGS"),
                "async_dispatch": bool(jax.config.read("jax_cpu_enable_async_dispatch"))}

    report = {"before": settings()}
    import racing_env, planners, experiments
    import experiments.backends, experiments.cli, experiments.sweep, experiments.tournament, racing_env.vector
    report["after_import"] = settings()
    report["backend_started_by_import"] = bool(xla_bridge.backends_are_initialized())

    from experiments.cli import main
    report["cli_status"] = main(["agents", "lane-keeping"])  # before any JAX computation, as a command runs
    report["after_cli"] = settings()

    import numpy as np
    from planners.agents import BatchedPlanner
    from racing_env.scenarios import paper_game
    game, x0 = paper_game()
    built = BatchedPlanner(planners.make_agent("ilqgame-fb"), game, 1, 4)  # with x64 on
    jax.config.update("jax_enable_x64", False)  # a user's float32 after the commands' settings
    us = np.zeros((game.horizon, 2, 2))
    env = racing_env.parallel_env(track="trefoil", num_agents=2)
    refusals = {
        "solve": lambda: planners.solve(game, x0),
        "budgeted solve": lambda: planners.solve(game, x0, budget_ms=5.0),
        "solve_batch": lambda: planners.solve_batch(game, np.stack([x0, x0])),
        "solve_ilqr": lambda: planners.solve_ilqr(game, x0),
        "certify": lambda: planners.certify(game, x0, us, "open_loop"),
        "game agent": lambda: planners.make_agent("ilqgame-fb").reset(0, 0, env),
        "ilqr agent": lambda: planners.make_agent("ilqr").reset(0, 1, env),
        "batched planner": lambda: BatchedPlanner(planners.make_agent("ilqgame-ol"), game, 0, 4),
        "compiled planner": lambda: built.jax_planner,
    }
    report["refusals"] = {}
    for name, call in refusals.items():
        try:
            call()
            report["refusals"][name] = None
        except RuntimeError as error:
            report["refusals"][name] = str(error)
    print(json.dumps(report))
    """
)


def test_importing_changes_nothing_a_command_sets_everything_and_solvers_refuse_float32():
    out = subprocess.run([sys.executable, "-c", _IMPORT_CHILD], env=_fresh_environment(), capture_output=True,
                         text=True, timeout=240)
    assert out.returncode == 0, out.stderr[-3000:]
    report = json.loads(out.stdout.strip().splitlines()[-1])
    default = {"x64": False, "xla_flags": None, "async_dispatch": True}
    assert report["before"] == report["after_import"] == default
    assert not report["backend_started_by_import"]  # the settings can still all take effect after it
    for name, message in report["refusals"].items():
        assert message is not None, f"{name} ran with x64 off"
        assert "jax_enable_x64" in message and "configure_for_racing()" in message, (name, message)
    assert report["cli_status"] == 0
    assert report["after_cli"] == {"x64": True, "xla_flags": with_loop_kernels(""), "async_dispatch": False}


def test_configure_for_racing_reports_each_setting_and_is_idempotent():
    """In a fresh process: everything "set", then "user"; the opt-outs "off"."""
    code = textwrap.dedent(
        """
        import json, racing_env
        print(json.dumps([racing_env.configure_for_racing(), racing_env.configure_for_racing()]))
        """
    )
    runs = {}
    for name, env in (("default", {}), ("opted out", {"RACING_XLA_LOOP_KERNELS": "off", "RACING_INLINE_DISPATCH": "0"})):
        out = subprocess.run([sys.executable, "-c", code], env=_fresh_environment(**env), capture_output=True,
                             text=True, timeout=120, check=True)
        runs[name] = json.loads(out.stdout.strip().splitlines()[-1])
    assert runs["default"] == [dict.fromkeys(("x64", "loop_kernels", "inline_dispatch"), "set"),
                               dict.fromkeys(("x64", "loop_kernels", "inline_dispatch"), "user")]
    assert runs["opted out"][0] == {"x64": "set", "loop_kernels": "off", "inline_dispatch": "off"}
    assert runs["opted out"][1] == {"x64": "user", "loop_kernels": "off", "inline_dispatch": "off"}


_ENV_CHILD = textwrap.dedent(
    """
    import json, sys
    if sys.argv[1] == "jax_first":
        import jax.numpy as jnp
        jnp.ones(1).block_until_ready()
    import jax, numpy as np
    import racing_env
    status = racing_env.configure_for_racing()
    env = racing_env.parallel_env(track="trefoil", num_agents=2)
    observations, _ = env.reset(seed=3)
    actions = np.random.default_rng(0).uniform(-1, 1, size=(40, 2, 2))
    for k in range(40):
        observations, rewards, *_ = env.step({a: actions[k, i] for i, a in enumerate(env.agents)})
    print(json.dumps({
        "dispatch": status["inline_dispatch"],
        "async_dispatch": jax.config.values["jax_cpu_enable_async_dispatch"],
        "state": env.state().tolist(),
        "observations": {a: o.tolist() for a, o in observations.items()},
        "rewards": rewards,
    }))
    """
)


def _env_child(mode: str, **env) -> dict:
    out = subprocess.run([sys.executable, "-c", _ENV_CHILD, mode], env=_fresh_environment(**env),
                         capture_output=True, text=True, timeout=240, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.slow  # three child processes, each compiling a race (the default run's budget)
def test_inline_dispatch_is_set_by_the_call_and_changes_no_result():
    inline = _env_child("configure_first")
    queued = _env_child("configure_first", RACING_INLINE_DISPATCH="off")
    late = _env_child("jax_first")
    assert inline["dispatch"] == "set" and inline["async_dispatch"] is False
    assert queued["dispatch"] == "off" and queued["async_dispatch"] is True
    assert late["dispatch"] == "too late" and late["async_dispatch"] is True
    # Only which thread runs the computation differs: the race is bit-for-bit the same.
    keys = ("state", "observations", "rewards")
    for other in (queued, late):
        assert {k: other[k] for k in keys} == {k: inline[k] for k in keys}
