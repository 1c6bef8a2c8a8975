"""The roofline rows of `racing bench --only solvers`: one feedback iteration against the machine.

At ``races`` perturbed copies of the paper's scene under ``jax.vmap`` (64 by default), the
parts of one feedback iLQGame iteration (linearisation, Gauss-Newton quadratisation, the
feedback LQ recursion, the step search) and the whole iteration (:func:`planners.ilq.iterate`)
are timed on one core, each inside a jitted loop, and their flops counted from the jaxprs
(:func:`planners.flops.count_flops`, per race, times the races: a part that runs one race
after another under ``vmap``, :func:`planners.batching.one_at_a_time`, holds the per-race
jaxpr once). Their rates are set against two references measured in the same process:

* ``gemm``: a 2048 x 2048 float64 matrix product by NumPy's BLAS on one thread, the core's
  practical arithmetic ceiling;
* ``small_matmul``: ``jax.vmap`` of 3,200 float64 12 x 12 matrix products (the size of a
  two-car game's state), what XLA:CPU makes of the small products the solver is built from.

Everything runs in a child process pinned to one CPU (its affinity set before it starts, so
XLA's and BLAS's threads share that core), with the ``racing`` commands' XLA settings
(:func:`racing_env.configure_for_racing`): the same conditions for the parts and the
references, whatever else the bench process runs. The float32 row times the whole iteration
with ``precision="float32"`` beside the float64 one.

Run alone: ``python -m experiments.bench_roofline [--races 64]`` prints the rows as JSON lines
(unpinned: pin it with ``taskset``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from typing import Any, Callable, Iterator

import numpy as np

#: The parts of one feedback iteration, in the order they run, and the whole.
PARTS = ("linearisation", "quadratisation", "lq_recursion", "step_search", "whole_iteration")

_SMALL = 12  # the small-matmul reference's matrix size: the two-car game's state
_SMALL_COUNT = 3200  # how many of them per call (64 races x 50 stages)
_GEMM_SIZE = 2048


def roofline_rows(races: int = 64, timeout_s: float = 900.0) -> Iterator[dict[str, Any]]:
    """The roofline rows, measured in a child process pinned to this process's first CPU."""
    cpu = min(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    # The child pins itself before it imports anything that starts threads (no preexec_fn:
    # forking a process that runs JAX's threads is unsafe).
    pin = f"import os; os.sched_setaffinity(0, {{{cpu}}}); " if cpu is not None else ""
    code = f"{pin}import runpy; runpy.run_module('experiments.bench_roofline', run_name='__main__')"
    done = subprocess.run([sys.executable, "-c", code, "--races", str(races)],
                          env=env, capture_output=True, text=True, timeout=timeout_s, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"the roofline measurement failed (exit {done.returncode}):\n{done.stderr[-3000:]}")
    for line in done.stdout.splitlines():
        if line.startswith("{"):
            row = json.loads(line)
            row["cpu_pinned"] = cpu
            yield row


def gemm_reference(repeats: int = 5, n: int = _GEMM_SIZE) -> float:
    """GFLOP/s of an ``n x n`` float64 product by NumPy's BLAS (the best of ``repeats``; one
    core when BLAS runs one thread, as in :func:`roofline_rows`' child)."""
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(n, n)), rng.normal(size=(n, n))
    a @ b  # warm up
    best = min(_seconds(lambda: a @ b) for _ in range(repeats))
    return 2 * n**3 / best / 1e9


def small_matmul_reference(dtype: Any, rounds: int = 7, calls: int = 20) -> float:
    """GFLOP/s of ``jax.vmap`` of :data:`_SMALL_COUNT` products of ``12 x 12`` matrices in
    ``dtype``, chained ``calls`` times inside one jitted loop (``X <- X M``, ``M`` orthogonal
    so the values stay bounded); the median of ``rounds``, a loop of one call subtracted."""
    import jax
    import jax.numpy as jnp

    rng = np.random.default_rng(0)
    M = np.linalg.qr(rng.normal(size=(_SMALL_COUNT, _SMALL, _SMALL)))[0]
    X = jnp.asarray(rng.normal(size=(_SMALL_COUNT, _SMALL, _SMALL)), dtype)
    M = jnp.asarray(M, dtype)

    def chain(count):
        return jax.jit(lambda X: jax.lax.fori_loop(0, count, lambda _, X: jax.vmap(jnp.matmul)(X, M), X))

    many, one = chain(calls + 1), chain(1)
    jax.block_until_ready((many(X), one(X)))
    diffs = [_seconds(lambda: jax.block_until_ready(many(X))) - _seconds(lambda: jax.block_until_ready(one(X)))
             for _ in range(rounds)]
    return 2 * _SMALL**3 * _SMALL_COUNT * calls / float(np.median(diffs)) / 1e9


def _seconds(fn: Callable[[], Any]) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def _looped(fn: Callable, args: tuple, count: int) -> Callable[[], Any]:
    """A jitted loop of ``count`` calls of ``fn(*args)``, each call's floating-point inputs
    shifted by zero times the previous call's (finite) outputs: a value XLA cannot know, so
    no call is hoisted out of the loop or folded away."""
    import jax
    import jax.numpy as jnp

    leaves, tree = jax.tree_util.tree_flatten(args)

    def floating(leaf):
        return jnp.issubdtype(jnp.asarray(leaf).dtype, jnp.floating)

    def body(_, acc):  # acc stays 0, which XLA cannot know
        shifted = [leaf + acc.astype(leaf.dtype) if floating(leaf) else leaf for leaf in leaves]
        out = fn(*jax.tree_util.tree_unflatten(tree, shifted))
        total = sum(jnp.sum(leaf).astype(acc.dtype) for leaf in jax.tree_util.tree_leaves(out) if floating(leaf))
        return acc + 0.0 * jnp.where(jnp.isfinite(total), total, 0.0)

    return jax.jit(lambda: jax.lax.fori_loop(0, count, body, jnp.zeros((), jnp.float64)))


def _time_parts(parts: dict[str, tuple[Callable, tuple]], rounds: int, calls: int) -> dict[str, float]:
    """Seconds per call of each ``fn(*args)`` in ``parts``: ``calls`` calls in one jitted loop
    less a loop of one, the parts in turns, the median of ``rounds``."""
    import jax

    loops = {name: (_looped(fn, args, calls + 1), _looped(fn, args, 1)) for name, (fn, args) in parts.items()}
    for many, one in loops.values():
        jax.block_until_ready((many(), one()))  # compile
    diffs: dict[str, list[float]] = {name: [] for name in parts}
    for _ in range(rounds):
        for name, (many, one) in loops.items():
            diffs[name].append(_seconds(lambda: jax.block_until_ready(many()))
                               - _seconds(lambda: jax.block_until_ready(one())))
    return {name: float(np.median(d)) / calls for name, d in diffs.items()}


def iteration_parts(races: int) -> tuple[dict[str, tuple[Callable, tuple]], dict[str, int]]:
    """``(parts, flops)``: per part of one feedback iteration (and ``whole_iteration``,
    ``whole_iteration_float32`` and ``lq_recursion_batched``, the LQ recursion as batched
    products across the races, :func:`planners.lq_game.solve_feedback_own_batched`) the
    function over ``races`` perturbed paper scenes (vmapped where it is per race) with its
    batched arguments, and the flops of one race's share (counted from the jaxprs). The
    nominal trajectories are each scene's iterate after 5 iterations."""
    import jax
    import jax.numpy as jnp

    from experiments.bench_scenes import perturbed_scenes, solver_game
    from planners import ilq, ilq_batch, local_game, lq_game, race_problem
    from planners.flops import count_flops

    game, x0 = solver_game(2)
    problem = race_problem.problem_from_race_game(game)
    options = ilq.SolverOptions(mode="feedback")
    x0s = perturbed_scenes(x0, races)
    res = ilq_batch.solve_batch(game, x0s, mode="feedback", max_iterations=5, tolerance=0.0)
    xs = jnp.asarray(res.xs).reshape(races, game.horizon + 1, -1)
    us, K, k = jnp.asarray(res.us), jnp.asarray(res.K), jnp.asarray(res.k)
    curvature = options.dynamics_curvature
    A, B = jax.vmap(lambda xs, us: local_game.linearize(problem, xs, us))(xs, us)
    Q, q, Rii, rii = jax.vmap(lambda xs, us: local_game.quadratize(problem, xs, us, True, curvature))(xs, us)
    carries = jax.vmap(lambda x0, us: ilq.initial_carry(problem, x0, us, options))(xs[:, 0], us)
    options32 = ilq.SolverOptions(mode="feedback", precision="float32")
    carries32 = jax.vmap(lambda x0, us: ilq.initial_carry(problem, x0, us, options32))(xs[:, 0], us)

    def step(xs, us, K, k):
        return ilq._step(problem, xs, us, K, k, options.initial_step, jnp.nan, options)[:4]

    per_race = {
        "linearisation": (lambda xs, us: local_game.linearize(problem, xs, us), (xs, us)),
        "quadratisation": (lambda xs, us: local_game.quadratize(problem, xs, us, True, curvature), (xs, us)),
        "lq_recursion": (lq_game.solve_feedback_own, (A, B, Q, q, Rii, rii)),
        "step_search": (step, (xs, us, K, k)),
        "whole_iteration": (lambda c: ilq.iterate(problem, c, options), (carries,)),
        # cast inside the trace (a concrete RaceGame keeps float64 tables)
        "whole_iteration_float32": (lambda c: ilq.iterate(ilq.at_precision(problem, options32), c, options32),
                                    (carries32,)),
    }
    parts, flops = {}, {}
    for name, (fn, args) in per_race.items():
        one = jax.tree_util.tree_map(lambda leaf: leaf[0], args)
        count = count_flops(fn, *one)
        if count.uncounted:
            raise RuntimeError(f"{name} calls {sorted(count.uncounted)}, which the flop count cannot see into")
        flops[name] = count.total
        parts[name] = (jax.vmap(fn), args)
    # the LQ recursion with the races as a batch dimension of its products
    lq_args = (A, B, Q, q, Rii, rii)
    flops["lq_recursion_batched"] = count_flops(lq_game.solve_feedback_own_batched, *lq_args).total // races
    parts["lq_recursion_batched"] = (lq_game.solve_feedback_own_batched, lq_args)
    return parts, flops


def measure(races: int = 64, rounds: int = 7, calls: int = 5) -> list[dict[str, Any]]:
    """The roofline rows (in this process: :func:`roofline_rows` runs it pinned to one core).

    One row per reference and per part: microseconds per race, its share of the whole
    iteration's time, Mflop per race, GFLOP/s, the share of the one-core GEMM rate and the
    multiple of the small-matmul rate; the float32 row adds its speed-up over float64, the
    batched LQ recursion's row its speed-up over the per-race one (``vmap``, which runs the
    races one after another)."""
    from racing_env import configure_for_racing

    configure_for_racing()
    import jax.numpy as jnp

    gemm = gemm_reference()
    small64 = small_matmul_reference(jnp.float64)
    small32 = small_matmul_reference(jnp.float32)
    parts, flops = iteration_parts(races)
    seconds = _time_parts(parts, rounds, calls)
    whole = seconds["whole_iteration"]
    rows = [{"name": "roofline_reference_gemm_one_core", "gflop_per_s": gemm, "size": _GEMM_SIZE, "dtype": "float64"},
            {"name": "roofline_reference_small_matmul", "gflop_per_s": small64, "gflop_per_s_float32": small32,
             "size": _SMALL, "count": _SMALL_COUNT}]
    for name in (*PARTS, "lq_recursion_batched", "whole_iteration_float32"):
        rate = flops[name] * races / seconds[name] / 1e9
        small = small32 if name.endswith("float32") else small64
        row = {"name": f"roofline_{name}_B{races}", "us_per_race": 1e6 * seconds[name] / races,
               "share_of_iteration": seconds[name] / whole, "mflop_per_race": flops[name] / 1e6,
               "gflop_per_s": rate, "gemm_share": rate / gemm, "x_small_matmul": rate / small}
        if name.endswith("float32"):
            row["speedup_over_float64"] = whole / seconds[name]
        if name == "lq_recursion_batched":
            row["speedup_over_per_race"] = seconds["lq_recursion"] / seconds[name]
        if name == "whole_iteration":  # what the parts timed alone leave out (selects, status, loops)
            row["share_outside_parts"] = 1.0 - sum(seconds[part] for part in PARTS[:-1]) / whole
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--races", type=int, default=64)
    args = parser.parse_args(argv)
    for row in measure(args.races):
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
