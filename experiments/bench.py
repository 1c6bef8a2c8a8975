"""`racing bench`: performance figures as JSON and a table.

Sections: ``env`` (PettingZoo steps per second), ``solvers`` (iLQGame iterations, solves,
batches), ``agents`` (re-plan times of the game agents), ``rl`` (the vectorised env, batched
opponents and training: :mod:`experiments.bench_rl`). Compile time is measured apart from run
time; each figure is the median over repeats so a noisy shared machine disturbs it less, and
the solver iterations and the batches are timed in turns with what they are compared to.
"""

from __future__ import annotations

import platform
import time
import timeit
from pathlib import Path
from typing import Any, Callable, Iterator, NamedTuple

import numpy as np

from experiments.bench_scenes import BENCH_V_MAX, perturbed_scenes, solver_game

from experiments.files import write_json_atomically


def _median_rate(run: Callable[[], int], repeats: int) -> tuple[float, list[float]]:
    rates = []
    for _ in range(repeats):
        start = time.perf_counter()
        count = run()
        rates.append(count / (time.perf_counter() - start))
    return float(np.median(rates)), rates


def bench_env(steps: int = 3000, repeats: int = 3, cars: tuple[int, ...] = (2, 4)) -> Iterator[dict[str, Any]]:
    """PettingZoo ``step`` calls per second (random actions, one core's worth of Python), then
    the Gymnasium view against a lane-keeping opponent (:func:`_gym_view_row`)."""
    from racing_env import parallel_env

    for num in cars:
        env = parallel_env(track="trefoil", num_agents=num, max_steps=10**9, laps=1000)
        rng = np.random.default_rng(0)
        actions = rng.uniform(-1, 1, size=(steps, num, 2)).astype(np.float32)
        env.reset(seed=0)
        start = time.perf_counter()
        env.step({a: actions[0, i] for i, a in enumerate(env.agents)})
        compile_s = time.perf_counter() - start

        def run() -> int:
            env.reset(seed=0)
            for k in range(steps):
                env.step({a: actions[k, i] for i, a in enumerate(env.possible_agents)})
            return steps

        rate, rates = _median_rate(run, repeats)
        yield {
            "name": f"env_step_{num}_cars",
            "cars": num,
            "steps_per_s": rate,
            "us_per_step": 1e6 / rate,
            "compile_s": compile_s,
            "repeats": [round(r, 1) for r in rates],
            "target_steps_per_s": 5000 if num == 2 else None,
        }
    yield _gym_view_row(steps, repeats)


def _gym_view_row(steps: int, repeats: int) -> dict[str, Any]:
    """Steps per second of the Gymnasium view (``racing_env/Race-v0``), the loop an RL
    learner trains in: random learner actions against a lane-keeping opponent."""
    from planners.scripted import LaneKeeping
    from racing_env.single_agent import RaceEnv

    probe = RaceEnv(track="trefoil")
    rival = LaneKeeping(probe.race.track, index=1, vehicle=probe.race.game.vehicles.car(1))
    # leaving the track penalised, not retiring the learner: random actions race on, unending
    env = RaceEnv(opponents=[rival], track="trefoil", max_steps=10**9, laps=1000, on_off_track="penalty")
    actions = np.random.default_rng(0).uniform(-1, 1, size=(steps, 2)).astype(np.float32)
    env.reset(seed=0)

    def run() -> int:
        env.reset(seed=0)
        for k in range(steps):
            env.step(actions[k])
        return steps

    rate, rates = _median_rate(run, repeats)
    return {"name": "gym_step_vs_lane_keeper", "steps_per_s": rate, "us_per_step": 1e6 / rate,
            "repeats": [round(r, 1) for r in rates]}


def _interleaved_ms(parts: dict[str, tuple[Callable, Any]], rounds: int = 9, calls: int = 20) -> dict[str, float]:
    """Milliseconds per call of each ``fn(arg)`` in ``parts`` (name -> ``(fn, arg)``).

    Each part runs ``calls`` times inside one jitted loop, so dispatch is excluded; a loop
    of one call is subtracted. The parts are timed in turns, ``rounds`` times, and the
    median of the per-round differences is reported: on a shared machine a slow spell
    then hits every part alike instead of one part's figure.
    """
    import jax
    import jax.numpy as jnp

    def looped(fn, arg, count):
        def body(_, carry):
            out = fn(arg + carry * 1e-300)  # a data dependency between the calls
            return carry + 0.0 * sum(jnp.sum(leaf) for leaf in jax.tree_util.tree_leaves(out))
        return jax.jit(lambda: jax.lax.fori_loop(0, count, body, jnp.zeros((), arg.dtype)))

    def seconds(fn) -> float:
        start = time.perf_counter()
        jax.block_until_ready(fn())
        return time.perf_counter() - start

    loops = {name: (looped(fn, arg, calls + 1), looped(fn, arg, 1)) for name, (fn, arg) in parts.items()}
    for many, one in loops.values():  # compile
        jax.block_until_ready((many(), one()))
    diffs: dict[str, list[float]] = {name: [] for name in parts}
    for _ in range(rounds):
        for name, (many, one) in loops.items():
            diffs[name].append(seconds(many) - seconds(one))
    return {name: 1e3 * float(np.median(d)) / calls for name, d in diffs.items()}


def _component_times(game, x0) -> dict[str, float]:
    """Milliseconds per call of the parts of one feedback iteration (:func:`_interleaved_ms`)."""
    from planners import ilq, local_game, lq_game, race_problem

    problem = race_problem.problem_from_race_game(game)
    res = ilq.solve(game, x0, mode="feedback", max_iterations=5, tolerance=0.0)
    xs, us = res.xs.reshape(res.xs.shape[0], -1), res.us
    A, B = local_game.linearize(problem, xs, us)
    curvature = ilq.SolverOptions().dynamics_curvature  # as the solver quadratises by default
    Q, q, Rii, rii = local_game.quadratize(problem, xs, us, True, curvature)
    parts = {
        "linearize": lambda xs: local_game.linearize(problem, xs, us),
        "quadratize_gauss_newton": lambda xs: local_game.quadratize(problem, xs, us, True, curvature),
        "quadratize_exact_eig": lambda xs: ilq.regularize(
            *local_game.quadratize(problem, xs, us, False, curvature)[::2], ilq.SolverOptions(), "eig"),
        "lq_feedback": lambda xs: lq_game.solve_feedback_own(A + 0.0 * xs[0, 0], B, Q, q, Rii, rii),
        "forward_pass": lambda xs: ilq.forward(problem, xs, us, res.K, res.k, 0.5),
    }
    return _interleaved_ms({name: (fn, xs) for name, fn in parts.items()})


def _lq_state_size_row(state_dims: tuple[int, ...] = (1, 4, 12, 24), horizon: int = 50) -> dict[str, Any]:
    """Microseconds per stage of the feedback LQ recursion (N = 2, m = 2) on random games
    with state size n: the same kernels per stage for every n, so the n = 1 figure is
    their fixed cost and the growth beyond it is arithmetic (the racing games: n = 12)."""
    import jax.numpy as jnp

    from planners import lq_game

    N, m = 2, 2
    rng = np.random.default_rng(0)
    parts = {}
    for n in state_dims:
        A = jnp.asarray(np.eye(n) + 0.05 * rng.normal(size=(horizon, n, n)))
        B = jnp.asarray(0.1 * rng.normal(size=(horizon, N, n, m)))
        L = rng.normal(size=(horizon + 1, N, n, n))
        Q = jnp.asarray(np.einsum("tiab,ticb->tiac", L, L) / n)
        q = jnp.asarray(rng.normal(size=(horizon + 1, N, n)))
        R = jnp.asarray(np.broadcast_to(np.eye(m), (horizon, N, m, m)))
        r = jnp.asarray(rng.normal(size=(horizon, N, m)))
        parts[f"n{n}"] = ((lambda B, Q, q, R, r: lambda A: lq_game.solve_feedback_own(A, B, Q, q, R, r))(B, Q, q, R, r), A)
    per_call = _interleaved_ms(parts)
    return {"name": f"lq_feedback_us_per_stage_by_state_size_N{N}",
            **{name: round(1e3 * ms / horizon, 3) for name, ms in per_call.items()}}


def _reference_operands(rng: np.random.Generator):
    """``M (12, 12)`` and ``b (12,)`` of the machine references' step ``x <- tanh(M x + b)``,
    drawn from ``rng`` (the references seed it with 0, so every run times the same workload)."""
    import jax.numpy as jnp

    return jnp.asarray(rng.normal(size=(12, 12)) / 12.0), jnp.asarray(rng.normal(size=12))


def _machine_reference(repeats: int = 5, steps: int = 2000) -> dict[str, Any]:
    """A fixed workload that does not change with the project's code, to compare solver
    figures taken on different days (this shared machine's speed varies by 2x or more).

    A jitted scan of ``steps`` dependent steps ``x <- tanh(M x + b)``, ``M`` 12 x 12: a few
    small XLA:CPU kernels per step, the regime of the solvers' sequential loops.
    """
    import jax
    import jax.numpy as jnp

    from experiments.timing import time_jax_call

    M, b = _reference_operands(np.random.default_rng(0))

    @jax.jit
    def scan(x0):
        return jax.lax.scan(lambda x, _: (jnp.tanh(M @ x + b), None), x0, None, length=steps)[0]

    _, first, run = time_jax_call(lambda: scan(b), repeats)
    return {"name": "machine_reference_scan", "us_per_step": 1e6 * run / steps, "compile_s": first - run}


def _machine_reference_batched(repeats: int = 5, lanes: int = 4096, steps: int = 50) -> dict[str, Any]:
    """The arithmetic counterpart of :func:`_machine_reference`: the same step
    ``x <- tanh(M x + b)`` for ``lanes`` independent 12-vectors at once, so each kernel
    has thousands of rows to work on (the regime of the batched linearisation and of
    ``solve_batch``). Hosts differ more in this figure than in the scan's, where the
    fixed cost of each small kernel dominates."""
    import jax
    import jax.numpy as jnp

    from experiments.timing import time_jax_call

    rng = np.random.default_rng(0)
    M, b = _reference_operands(rng)
    X = jnp.asarray(rng.normal(size=(lanes, 12)))

    @jax.jit
    def run(X):
        return jax.lax.fori_loop(0, steps, lambda _, X: jnp.tanh(X @ M.T + b), X)

    _, first, run_s = time_jax_call(lambda: run(X), repeats)
    return {"name": "machine_reference_batched", "ns_per_lane_step": 1e9 * run_s / (lanes * steps),
            "compile_s": first - run_s}


def _machine_reference_dgemm(repeats: int = 5, n: int = 1000) -> dict[str, Any]:
    """The machine's practical arithmetic ceiling: GFLOP/s of an ``n x n`` float64 matrix
    product by NumPy's BLAS on its default threads (every core), the best of ``repeats``.

    Tuned BLAS on large matrices is about as close to the cores' peak as float64 code gets,
    so a target that would need a rate near this one is out of reach for any batching of
    the solvers (the batch row states the rate its target needs)."""
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(n, n)), rng.normal(size=(n, n))
    a @ b  # let BLAS start its threads
    best = min(timeit.repeat(lambda: a @ b, repeat=repeats, number=1))
    return {"name": "machine_reference_dgemm", "gflop_per_s": 2 * n**3 / best / 1e9}


def _iteration_flops(game, x0: np.ndarray, mode: str) -> int:
    """Flops of one iteration of :func:`planners.ilq.solve` on ``game`` from zero inputs,
    counted from its jaxpr (:mod:`planners.flops`; a step-size search of one trial).
    The count depends on the shapes only (N, T, the state size), not on ``x0``'s values."""
    import jax.numpy as jnp

    from planners import ilq, race_problem
    from planners.flops import count_flops

    problem = race_problem.problem_from_race_game(game)
    options = ilq.SolverOptions(mode=mode)
    us0 = jnp.zeros((game.horizon, game.num_players, problem.input_dim))
    carry = ilq.initial_carry(problem, jnp.asarray(x0).reshape(-1), us0, options)
    flops = count_flops(lambda c: ilq.iterate(problem, c, options), carry)
    if flops.uncounted:
        raise RuntimeError(f"the iteration calls {sorted(flops.uncounted)}, which the flop count cannot see into")
    return flops.total


def machine_info() -> dict[str, Any]:
    """What the figures were measured on: CPU model and count, load average at the start
    (this is a shared machine), Python, JAX and its devices, the XLA flags (e.g. whether the
    solvers' loops were single kernels, :mod:`racing_env.xla_setup`) and any compilation cache."""
    import os

    import jax

    from planners.compile_cache import compile_cache_dir

    return {"platform": platform.platform(), "cpu": cpu_model(), "cpu_count": os.cpu_count(),
            "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
            "python": platform.python_version(), "jax": jax.__version__,
            "devices": [str(d) for d in jax.devices()],
            "xla_flags": os.environ.get("XLA_FLAGS", ""),
            # compile_s figures are cache loads where a persistent cache already holds the program
            "compile_cache": compile_cache_dir()}


def cpu_model() -> str:
    """The CPU's model name: ``/proc/cpuinfo`` on Linux, else :func:`platform.processor`."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


# Rounds of the interleaved iteration timing: about 3 s for the four solver configurations.
_ITERATION_ROUNDS = 40


class _Interleaved(NamedTuple):
    """What :func:`_interleaved_calls` measured, per name: the first call's result and
    seconds (it compiles), and the seconds of the later calls, ``(rounds,)``."""

    results: dict[Any, Any]
    first_s: dict[Any, float]
    seconds: dict[Any, np.ndarray]

    def median_s(self, name: Any) -> float:
        """The median seconds of the later calls."""
        return float(np.median(self.seconds[name]))

    def compile_s(self, name: Any) -> float:
        """The first call's seconds less the median later call's (as
        :func:`experiments.timing.time_jax_call` counts compile time)."""
        return self.first_s[name] - self.median_s(name)


def _interleaved_calls(calls: dict[Any, Callable[[], Any]], rounds: int) -> _Interleaved:
    """Call each function in ``calls`` once (compiling it), then all of them in turns,
    ``rounds`` times, timing every call.

    In turns, so that a slow spell of the machine falls on every function alike.
    """
    import jax

    def timed(fn: Callable[[], Any]) -> tuple[Any, float]:
        start = time.perf_counter()
        result = jax.block_until_ready(fn())
        return result, time.perf_counter() - start

    results, first_s = {}, {}
    for name, fn in calls.items():
        results[name], first_s[name] = timed(fn)
    seconds: dict[Any, list[float]] = {name: [] for name in calls}
    for _ in range(rounds):
        for name, fn in calls.items():
            seconds[name].append(timed(fn)[1])
    return _Interleaved(results, first_s, {name: np.asarray(s) for name, s in seconds.items()})


def _iteration_rows(fixed_iterations: int, rounds: int) -> Iterator[dict[str, Any]]:
    """One row per solver configuration (N = 2, 3; feedback, open loop): a solve capped at
    ``fixed_iterations`` with tolerance 0, timed ``rounds`` times with the configurations
    in turns (:func:`_interleaved_calls`), in ms per iteration.

    ``ms_per_iter`` is the median; ``ms_per_iter_p10`` and ``ms_per_iter_min`` describe
    the fast end of the distribution. On a machine whose vCPUs share physical cores the
    same compiled solve runs at two speeds, depending on what else runs on the core
    (docs/performance.md, "Running the benchmarks"): the 10th percentile is the figure of
    the uncontended core whenever such a spell falls inside the run. The
    targets are judged on the median.
    """
    from planners import ilq

    calls, targets, flops = {}, {}, {}
    for num in (2, 3):
        game, x0 = solver_game(num)
        for mode in ("feedback", "open_loop"):
            name = f"{mode}_iteration_N{num}_T{game.horizon}"
            calls[name] = (lambda game=game, x0=x0, mode=mode:
                           ilq.solve(game, x0, mode=mode, max_iterations=fixed_iterations, tolerance=0.0))
            targets[name] = 0.25 if (num == 2 and mode == "feedback") else None
            flops[name] = _iteration_flops(game, x0, mode)
    timed = _interleaved_calls(calls, rounds)
    for name, seconds in timed.seconds.items():
        ms = 1e3 * seconds / fixed_iterations
        median = float(np.median(ms))
        yield {"name": name, "ms_per_iter": median, "ms_per_iter_p10": float(np.percentile(ms, 10)),
               "ms_per_iter_min": float(ms.min()), "calls": int(ms.size), "compile_s": timed.compile_s(name),
               "mflop_per_iter": flops[name] / 1e6, "gflop_per_s": flops[name] / median / 1e6,
               "target_ms": targets[name]}


def bench_solvers(repeats: int = 5, batch: int = 64) -> Iterator[dict[str, Any]]:
    """Per-iteration and per-solve times of feedback/open-loop iLQGame, and a batch of games.

    The first three rows are machine references (:func:`_machine_reference`,
    :func:`_machine_reference_batched`) for comparing days, and the machine's dgemm rate
    (:func:`_machine_reference_dgemm`) as its arithmetic ceiling; :func:`machine_info` names
    the CPU. Per iteration: a solve capped at 20 iterations with tolerance 0 (so all 20 run),
    divided by 20, the four configurations timed in turns (:func:`_iteration_rows`), with the
    flops of one iteration (:func:`_iteration_flops`) and the rate they run at. Per solve: a
    cold solve (zero inputs) to convergence. Components: the parts of one N = 2 feedback
    iteration, timed inside a jitted loop, and the LQ recursion's cost per stage against
    the state size (:func:`_lq_state_size_row`). Roofline: the parts of one feedback
    iteration and the whole at ``batch`` races under ``vmap`` on one core, their flops and
    rates against a one-core GEMM and vmapped 12 x 12 products measured in the same child
    process (:mod:`experiments.bench_roofline`). Batch: 64 perturbations of the
    paper's scene solved by :func:`planners.ilq_batch.solve_batch` vs one by one (64 calls of
    ``solve``), on one device and split across every local device (``racing bench`` exposes
    one CPU device per core, see :mod:`planners.devices`), in the default batching (on CPU
    one member after another) and vmapped (``batching="vmap"``, for comparison; its
    ``while_loop`` runs until the slowest member converges, so the row reports the
    members' iterations too); the batches and the sequential solves are timed in turns
    (:func:`_interleaved_calls`), so their ratios come from the same spells. Straggler: a
    batch in which one member runs to the iteration cap, vmapped lock-step against
    regrouped and against the default (:func:`_straggler_row`). float32: the lock-step batch
    in both precisions (:func:`_precision_batch_row`). Convergence: how often cold
    solves of random scenes on a circuit converge, and in how many iterations
    (:func:`convergence_rows`). The batch row also states
    the batch's arithmetic (``gflop``, a lower bound: one step-size trial per iteration), the
    rate the sequential solves and the batch run it at, and the rate the target ratio
    would need (``gflop_per_s_at_target``) as a share of the dgemm rate: a share near or
    above 1 means no batching can meet the target on this machine.
    """
    from experiments.bench_roofline import roofline_rows
    from experiments.timing import time_jax_call
    from planners import ilq, ilq_batch

    fixed_iterations = 20
    yield _machine_reference()
    yield _machine_reference_batched()
    dgemm = _machine_reference_dgemm()
    yield dgemm
    iteration_rows = list(_iteration_rows(fixed_iterations, rounds=max(repeats, _ITERATION_ROUNDS)))
    yield from iteration_rows
    for num in (2, 3):
        game, x0 = solver_game(num)
        # the open-loop solve also with the residual line search (no target: an option)
        for name, options in (("feedback", {"mode": "feedback"}), ("open_loop", {"mode": "open_loop"}),
                              ("open_loop_residual", {"mode": "open_loop", "step_control": "residual"})):
            res, first, run = time_jax_call(lambda: ilq.solve(game, x0, **options), repeats)
            yield {"name": f"{name}_cold_solve_N{num}_T{game.horizon}", "ms_per_solve": 1e3 * run,
                   "converged": bool(res.converged), "iterations": int(res.iterations),
                   "compile_s": first - run,
                   "target_ms": 50.0 if num == 2 and name != "open_loop_residual" else None}
    game, x0 = solver_game(2)
    parts = _component_times(game, x0)
    yield {"name": "feedback_iteration_components_N2_ms", **{k: round(v, 4) for k, v in parts.items()}}
    yield _lq_state_size_row()
    yield from roofline_rows(batch)
    x0s = perturbed_scenes(x0, batch)
    import jax

    devices = jax.local_devices()
    calls: dict[Any, Callable[[], Any]] = {}  # (batching, devices used), or "sequential"
    for batching in ("auto", "vmap"):
        for used in sorted({1, len(devices)}):
            calls[batching, used] = (lambda batching=batching, used=used: ilq_batch.solve_batch(
                game, x0s, mode="feedback", devices=devices[:used], batching=batching))
    calls["sequential"] = lambda: [ilq.solve(game, x, mode="feedback").xs for x in x0s]
    # In turns, so that the batches and the sequential solves share the machine's spells.
    timed = _interleaved_calls(calls, max(3, repeats // 2))
    run = {key: timed.median_s(key) for key in calls}
    res_b = timed.results["auto", len(devices)]
    run_seq, run_b, run_1 = run["sequential"], run["auto", len(devices)], run["auto", 1]
    run_v, run_v1 = run["vmap", len(devices)], run["vmap", 1]
    iterations_mean = float(np.mean(np.asarray(res_b.iterations)))
    # The arithmetic the 64 solves do, at least (one step-size trial per iteration; the
    # scenes have the shapes of the N = 2 iteration row's), and the rate at which the
    # target ratio would have the batch do it.
    mflop_per_iter = next(row["mflop_per_iter"] for row in iteration_rows
                          if row["name"] == f"feedback_iteration_N2_T{game.horizon}")
    gflop = batch * iterations_mean * mflop_per_iter / 1e3
    target_ratio = 10.0
    yield {"name": f"feedback_batch{batch}", "devices": len(devices), "ms_batch": 1e3 * run_b,
           "compile_s": timed.compile_s(("auto", len(devices))), "ms_batch_one_device": 1e3 * run_1,
           "compile_s_one_device": timed.compile_s(("auto", 1)),
           "converged": int(np.sum(np.asarray(res_b.converged))), "sequential_ms": 1e3 * run_seq,
           "iterations_mean": iterations_mean,
           "iterations_max": int(np.max(np.asarray(res_b.iterations))),
           "throughput_ratio": run_seq / run_b, "throughput_ratio_one_device": run_seq / run_1,
           "ms_batch_vmap": 1e3 * run_v, "ms_batch_vmap_one_device": 1e3 * run_v1,
           "compile_s_vmap": timed.compile_s(("vmap", len(devices))), "throughput_ratio_vmap": run_seq / run_v,
           "gflop": gflop, "gflop_per_s_sequential": gflop / run_seq, "gflop_per_s_batch": gflop / run_b,
           "gflop_per_s_at_target": target_ratio * gflop / run_seq,
           "dgemm_share_at_target": target_ratio * gflop / run_seq / dgemm["gflop_per_s"],
           "target_ratio": target_ratio}
    yield _straggler_row(game, x0, repeats)
    yield _precision_batch_row(game, x0, repeats)
    yield from convergence_rows(batch)


def solver_options_by_mode(modes, num_players: int, **fields: Any) -> dict[str, Any]:
    """The :class:`planners.ilq.SolverOptions` (``fields``) of every solver mode that
    :func:`convergence_rows` runs for ``modes`` on games of ``num_players``: ``"feedback"``,
    ``"open_loop"``, and for ``"open_loop_from_feedback"`` both (a feedback, then an
    open-loop solve). Building them checks the options in each of those modes, as the
    solver will (:func:`planners.ilq.check_adaptive_regularization` too)."""
    from planners import ilq

    solver_modes = {"feedback" if mode == "feedback" else "open_loop" for mode in modes}
    if "open_loop_from_feedback" in modes:
        solver_modes.add("feedback")
    options = {mode: ilq.SolverOptions(mode=mode, **fields) for mode in solver_modes}
    for mode_options in options.values():
        ilq.check_adaptive_regularization(mode_options, num_players)
    return options


def convergence_rows(count: int = 64, seed: int = 0, repeats: int = 3,
                     modes: tuple[str, ...] = ("feedback", "open_loop"),
                     track: Any = "trefoil", num_cars: int = 2, max_iterations: int = 100,
                     tolerance: float = 1e-6, jerk_weight: float | None = None,
                     per_scene: bool = False, spread: float = 15.0,
                     speed: tuple[float, float] = (10.0, 19.0), **solver_options: Any) -> Iterator[dict[str, Any]]:
    """How often, and in how many iterations, cold solves converge away from the paper's
    scene: ``count`` random close-quarters starts anywhere on ``track`` (a
    :class:`racing_env.Track`, a builder's name or a TUMFTM CSV path; by default the trefoil,
    with curves both ways) drawn by :func:`racing_env.scenarios.random_scenes` (up to
    ``spread`` [m] apart, speeds in ``speed`` [m/s]), one row per mode: ``"feedback"``,
    ``"open_loop"``, or ``"open_loop_from_feedback"`` (open loop initialised with the
    feedback solution of the same scene, the paper's experiment; its iterations and time
    are the open-loop solve's).
    The cars are the paper's two (v_max 20 and 25 m/s), then the three-car bench scene's
    third (24 m/s), then cars of 22 m/s. The scenes are solved by
    :func:`planners.ilq_batch.solve_batch` (its default batching), timed ``repeats`` (>= 1) times
    after a compiling call. Iteration figures are over the converged scenes; ``statuses``
    counts every outcome by its message. ``max_iterations``, ``tolerance`` and
    ``solver_options`` are the solver's (:class:`planners.ilq.SolverOptions`; the other
    options its defaults);
    ``jerk_weight`` is every car's jerk weight ``r`` (default: ``CostWeights``' default,
    as are the other cost weights). Open-loop rows also give the first-order open-loop Nash
    residual of every solve, ``max_i |dJ^i/du^i|`` (:func:`planners.nash.nash_residual`, the
    cost's units per m/s^3): its median, p90 and largest value. With ``per_scene`` a row
    also lists every scene's start state ``x0`` (N x 6), ``iterations``, ``status``
    (message) and, in open loop, ``residual``, in scene order."""
    from planners import ilq, ilq_batch, nash
    from experiments.timing import time_jax_call
    from racing_env import CostWeights, RaceGame, VehicleParams
    from racing_env.scenarios import random_scenes
    from racing_env.track import get_track

    if int(repeats) < 1 or int(num_cars) < 1:
        raise ValueError(f"need repeats >= 1 and num_cars >= 1, got {repeats!r} and {num_cars!r}")
    v_max = BENCH_V_MAX + (22.0,) * max(0, num_cars - 3)
    vehicles = [VehicleParams(v_max=v) for v in v_max[:num_cars]]
    weights = None if jerk_weight is None else CostWeights(r_jx=jerk_weight, r_jy=jerk_weight)
    # checked before the work
    options = solver_options_by_mode(modes, num_cars, max_iterations=max_iterations, tolerance=tolerance,
                                     **solver_options)
    track = get_track(track)
    game = RaceGame.create(track, vehicles, weights)
    x0s = random_scenes(track, vehicles, count, seed=seed, spread=spread, speed=tuple(speed))
    results = {}
    for mode in modes:
        if mode == "open_loop_from_feedback":
            feedback = (results["feedback"] if "feedback" in results
                        else ilq_batch.solve_batch(game, x0s, options=options["feedback"]))
            init = np.asarray(feedback.us)
            solve = lambda: ilq_batch.solve_batch(game, x0s, init, options=options["open_loop"])
        else:
            solve = lambda mode=mode: ilq_batch.solve_batch(game, x0s, options=options[mode])
        res, first, run = time_jax_call(solve, repeats)
        results[mode] = res
        status = np.asarray(res.status)
        converged = np.asarray(res.converged)
        all_iterations = np.asarray(res.iterations)
        iterations = all_iterations[converged]
        statuses, counts = np.unique(status, return_counts=True)
        row = {"name": f"{mode}_convergence_random{count}_N{num_cars}_{track.name}",
               "mode": mode, "track": track.name, "cars": int(num_cars), "scenes": int(count),
               "converged_fraction": float(converged.mean()),
               "statuses": {ilq.status_message(k): int(c) for k, c in zip(statuses, counts)},
               "iterations_median": float(np.median(iterations)) if iterations.size else None,
               "iterations_p90": float(np.percentile(iterations, 90)) if iterations.size else None,
               "iterations_max": int(iterations.max()) if iterations.size else None,
               "ms_batch": 1e3 * run, "compile_s": first - run}
        residuals = None
        if mode != "feedback":
            # how near an open-loop equilibrium each solve ended, converged or not (a
            # feedback equilibrium does not zero this residual, so feedback rows skip it)
            residuals = np.array([float(np.max(nash.nash_residual(game, x0, us)))
                                  for x0, us in zip(x0s, np.asarray(res.us))])
            row.update(residual_median=float(np.median(residuals)),
                       residual_p90=float(np.percentile(residuals, 90)), residual_max=float(residuals.max()))
        if per_scene:
            row["x0"] = x0s.tolist()
            row["iterations"] = all_iterations.tolist()
            row["status"] = [ilq.status_message(k) for k in status]
            if residuals is not None:
                row["residual"] = residuals.tolist()
        yield row


def _straggler_row(game, x0, repeats: int, batch: int = 63, every: int = 10) -> dict[str, Any]:
    """A batch with a straggler: of these 63 perturbed scenes one does not converge in the
    100 iterations (the others take 10-17). Vmapped lock-step ``solve_batch`` against
    ``regroup_every=10`` (the members still running regrouped every 10 iterations), and
    the default batching (on CPU one member after another, so nobody waits), all on every
    local device, timed in turns (:func:`_interleaved_calls`); compile time (including
    every regrouped size) apart."""
    from planners import ilq_batch

    x0s = perturbed_scenes(x0, batch)
    calls = {
        "lockstep": lambda: ilq_batch.solve_batch(game, x0s, mode="feedback", batching="vmap"),
        "regrouped": lambda: ilq_batch.solve_batch(game, x0s, mode="feedback", batching="vmap", regroup_every=every),
        "default": lambda: ilq_batch.solve_batch(game, x0s, mode="feedback"),
    }
    timed = _interleaved_calls(calls, max(1, repeats // 2))
    run = {name: timed.median_s(name) for name in calls}
    iterations = {name: np.asarray(res.iterations) for name, res in timed.results.items()}
    return {"name": f"feedback_batch{batch}_straggler_regroup{every}",
            "ms_lockstep": 1e3 * run["lockstep"], "compile_s_lockstep": timed.compile_s("lockstep"),
            "ms_regrouped": 1e3 * run["regrouped"], "compile_s_regrouped": timed.compile_s("regrouped"),
            "ms_default": 1e3 * run["default"], "compile_s_default": timed.compile_s("default"),
            "speedup": run["lockstep"] / run["regrouped"], "speedup_default": run["lockstep"] / run["default"],
            "converged": int(np.sum(np.asarray(timed.results["lockstep"].converged))),
            "iterations_median": float(np.median(iterations["lockstep"])),
            "iterations_max": int(iterations["lockstep"].max()),
            "same_iterations": all(np.array_equal(iterations["lockstep"], it) for it in iterations.values())}


def _precision_batch_row(game, x0, repeats: int, batch: int = 64) -> dict[str, Any]:
    """A lock-step batch (``batching="vmap"``) of ``batch`` perturbed paper scenes at the
    default tolerance (1e-6), solved in float64 and in float32 (``precision="float32"``),
    timed in turns: how many converge, their iterations (a lock-step batch runs until its
    slowest member stops, so ``iterations_max`` is what every member pays), the batch time
    and the largest gap between the two precisions' trajectories [m]."""
    from planners import ilq_batch

    x0s = perturbed_scenes(x0, batch)
    calls = {precision: (lambda precision=precision: ilq_batch.solve_batch(
        game, x0s, mode="feedback", batching="vmap", precision=precision)) for precision in ("float64", "float32")}
    timed = _interleaved_calls(calls, max(1, repeats // 2))
    row: dict[str, Any] = {"name": f"feedback_batch{batch}_lockstep_float32_vs_float64"}
    for precision, res in timed.results.items():
        iterations = np.asarray(res.iterations)
        row.update({f"converged_{precision}": int(np.sum(np.asarray(res.converged))),
                    f"iterations_max_{precision}": int(iterations.max()),
                    f"iterations_mean_{precision}": float(iterations.mean()),
                    f"ms_{precision}": 1e3 * timed.median_s(precision),
                    f"compile_s_{precision}": timed.compile_s(precision)})
    row["speedup"] = row["ms_float64"] / row["ms_float32"]
    row["max_trajectory_gap_m"] = float(np.max(np.abs(np.asarray(timed.results["float64"].xs)
                                                      - np.asarray(timed.results["float32"].xs))))
    return row


# The agents' adaptive control regularization in the agents bench (lambda_u from 0.3, the
# default factor 1.5).
_ADAPTIVE_REGULARIZATION = "control_regularization=0.3,adaptive_regularization=true"


def bench_agents(steps: int = 150) -> Iterator[dict[str, Any]]:
    """Re-plan time of each game agent racing a copy of itself (warm start) on the trefoil,
    with the tournaments' jerk weight (``RACING_JERK_WEIGHT``); iLQR also with the
    lane-keeping, iLQR (one and two levels) and feedback-game predictions (its re-plan
    includes making the prediction: a rollout, one or three iLQR solves, a feedback game
    solve); open-loop iLQGame also with the residual line search; both also with the
    adaptive control regularization, and feedback iLQGame with it on the feed-forward terms.

    Car 0's solve times over ``steps`` steps, the first (compiling) solve excluded, and the
    share of those re-plans that converged (``converged_share``).
    """
    from planners.agents import make_agent, reset_agents
    from racing_env import parallel_env
    from racing_env.costs import racing_weights

    specs = {"ilqr": "ilqr", "ilqr_lane_keeping_prediction": "ilqr:prediction=lane-keeping",
             "ilqr_ilqr_prediction": "ilqr:prediction=ilqr",
             "ilqr_ilqr_level2_prediction": "ilqr:prediction=ilqr,levels=2",
             "ilqr_feedback_game_prediction": "ilqr:prediction=ilqgame-fb",
             "ilqr_adaptive_regularization": f"ilqr:{_ADAPTIVE_REGULARIZATION}",
             "ilqgame-ol": "ilqgame-ol", "ilqgame-ol_residual": "ilqgame-ol:step_control=residual",
             "ilqgame-ol_adaptive_regularization": f"ilqgame-ol:{_ADAPTIVE_REGULARIZATION}",
             "ilqgame-fb": "ilqgame-fb",
             # the warm start with its accelerations restored, beside the default
             "ilqr_restored_warm_start": "ilqr:restore_accelerations=true",
             "ilqgame-ol_restored_warm_start": "ilqgame-ol:restore_accelerations=true",
             "ilqgame-fb_restored_warm_start": "ilqgame-fb:restore_accelerations=true",
             "ilqgame-fb_real_time": "ilqgame-fb:iterations=2,trust_radius=10",
             "ilqgame-fb_feedforward_regularization":
                 f"ilqgame-fb:{_ADAPTIVE_REGULARIZATION},feedforward_regularization=true"}
    for name, spec in specs.items():
        env = parallel_env(track="trefoil", num_agents=2, max_steps=steps,
                           weights=racing_weights())
        drivers = [make_agent(spec), make_agent(spec)]
        reset_agents(drivers, env, seed=0)
        observations, _ = env.reset(seed=0)
        times, iterations, converged, fallbacks = [], [], [], 0
        while env.agents:
            state = env.state()
            actions = {a: drivers[i].act(observations[a], state) for i, a in enumerate(env.possible_agents) if a in env.agents}
            record = drivers[0].diagnostics()
            if record["solve_time"] is not None:
                times.append(record["solve_time"])
                iterations.append(record["iterations"])
                converged.append(record["converged"])
            fallbacks += bool(record["fallback"])
            observations, *_ = env.step(actions)
        compile_s, runs = times[0], np.array(times[1:])
        yield {"name": f"{name}_replan", "ms_median": 1e3 * float(np.median(runs)),
               "ms_p95": 1e3 * float(np.percentile(runs, 95)), "compile_s": compile_s,
               "iterations_median": float(np.median(iterations[1:])),
               "iterations_p95": float(np.percentile(iterations[1:], 95)),
               "converged_share": float(np.mean(converged[1:])), "fallbacks": fallbacks,
               "target_ms_p95": 50.0 if spec == "ilqgame-fb" else None}


def bench_rl() -> Iterator[dict[str, Any]]:
    """The RL loops' throughput (:mod:`experiments.bench_rl`)."""
    from experiments import bench_rl as rl

    return rl.bench_rl()


def bench_real_time() -> Iterator[dict[str, Any]]:
    """The real-time planner in both precisions against the throughput targets
    (:func:`experiments.bench_rl.real_time_rows`)."""
    from experiments import bench_rl as rl

    return rl.real_time_rows()


def bench_field() -> Iterator[dict[str, Any]]:
    """Fields of game planners and the vectorised env with a field (:mod:`experiments.bench_field`)."""
    from experiments import bench_field as field

    return field.bench_field()


def bench_certificates(rounds: int = 7, cars: tuple[int, ...] = (2, 3)) -> Iterator[dict[str, Any]]:
    """The cost of a certificate (:func:`planners.certificates.certify`) beside the cost of a solve.

    Per number of cars (the scenes of :func:`solver_game`) and mode: a cold solve (zero
    inputs) to convergence, the cheap certificate (gradients, dense own-input Hessians, the
    stage-wise condition for feedback) and the full one (plus the best-response iLQR
    solves) of that solution, timed in turns (:func:`_interleaved_calls`); milliseconds per
    call, the full certificate's ratio to the solve, the verdict, and the compile seconds of
    the certificates' first calls (a mode's second row re-uses what the first compiled for
    the same shapes).
    """
    from planners import ilq
    from planners.certificates import certify

    for num in cars:
        game, x0 = solver_game(num)
        for mode in ("open_loop", "feedback"):
            solution = ilq.solve(game, x0, mode=mode)
            calls = {
                "solve": lambda: ilq.solve(game, x0, mode=mode).us,
                "cheap": lambda: certify(game, x0, solution, mode, checks="cheap").numbers.cost,
                "full": lambda: certify(game, x0, solution, mode).numbers.cost,
            }
            timed = _interleaved_calls(calls, rounds)
            yield {"name": f"certificate_{mode}_N{num}_T{game.horizon}",
                   "ms_solve": 1e3 * timed.median_s("solve"), "ms_cheap": 1e3 * timed.median_s("cheap"),
                   "ms_full": 1e3 * timed.median_s("full"),
                   "full_over_solve": timed.median_s("full") / timed.median_s("solve"),
                   "compile_s": timed.compile_s("cheap") + timed.compile_s("full"),
                   "verdict": certify(game, x0, solution, mode).verdict}


def _planned_scene(env, steps_ahead: int = 50):
    """The race's scene now, with every car's plan ``(steps_ahead + 1, N, 2)``: each car
    holding its speed and lateral offset (the drawing cost of a plan depends on its
    length and where it lies, not on how it was solved)."""
    from racing_env.dynamics import N_LAT, S, V

    x = env.state()
    ahead = np.arange(steps_ahead + 1)[:, None] * env.config.dt * x[None, :, V]
    plan = np.stack([x[None, :, S] + ahead, np.broadcast_to(x[:, N_LAT], ahead.shape)], axis=-1).astype(np.float32)
    return env.scene(plans=[plan] * env.num_cars)


def bench_render(rounds: int = 30, tracks: tuple[str, ...] = ("trefoil", "random")) -> Iterator[dict[str, Any]]:
    """What drawing costs, and what recording costs a race that is not drawn.

    Per track: milliseconds per 512 px frame of a duel mid-lap with the whole-track camera,
    the follow camera (inset map, labels, heads-up lines) and the follow camera with both
    cars' plans and predictions (51 steps each), timed in turns. Then a race of two lane
    keepers: steps per second of :func:`experiments.race.run_race` (which records the
    states, statuses and positions a replay needs) beside the bare env loop with the same
    drivers, in turns, and the milliseconds to make and write its replay.
    """
    import tempfile
    from pathlib import Path

    from experiments.race import run_race
    from experiments.replay import replay_of, save_replay
    from planners.agents import make_agent, reset_agents
    from racing_env import parallel_env
    from racing_env.render import Renderer

    for track in tracks:
        env = parallel_env(track=track, num_agents=2, laps=1)
        env.reset(seed=0)
        for _ in range(40):
            env.step({a: np.array([0.5, 0.0], dtype=np.float32) for a in env.agents})
        scene, planned = env.scene(), _planned_scene(env)
        renderers = {camera: Renderer(env.track, env.game.vehicles, size=512, camera=camera)
                     for camera in ("track", "follow")}
        calls = {"track": lambda: renderers["track"].draw(scene), "follow": lambda: renderers["follow"].draw(scene),
                 "follow_plans": lambda: renderers["follow"].draw(planned)}
        timed = _interleaved_calls(calls, rounds)
        yield {"name": f"frame_{track}", "track": track, "ms_track_camera": 1e3 * timed.median_s("track"),
               "ms_follow": 1e3 * timed.median_s("follow"), "ms_per_frame": 1e3 * timed.median_s("follow_plans"),
               "target_ms": 5.0}

    env = parallel_env(track="trefoil", num_agents=2, laps=1)
    drivers = [make_agent("lane-keeping"), make_agent("lane-keeping")]

    def bare() -> int:
        reset_agents(drivers, env, seed=0)
        observations, _ = env.reset(seed=0)
        steps = 0
        while env.agents:
            state = env.state()
            observations, *_ = env.step({a: drivers[i](observations[a], state)
                                         for i, a in enumerate(env.possible_agents) if a in env.agents})
            steps += 1
        return steps

    def recorded() -> int:
        reset_agents(drivers, env, seed=0)
        return run_race(env, drivers, seed=0).steps

    steps = bare()
    timed = _interleaved_calls({"bare": bare, "recorded": recorded}, rounds=3)
    record = run_race(env, drivers, seed=0)
    with tempfile.TemporaryDirectory() as folder:
        start = time.perf_counter()
        save_replay(replay_of(record, env), Path(folder) / "race.npz")
        write_ms = 1e3 * (time.perf_counter() - start)
    yield {"name": "race_recording_trefoil", "race_steps": steps,
           "bare_steps_per_s": steps / timed.median_s("bare"), "steps_per_s": steps / timed.median_s("recorded"),
           "throughput_ratio": timed.median_s("bare") / timed.median_s("recorded"), "ms_replay_write": write_ms}


SECTIONS: dict[str, Callable[[], Iterator[dict[str, Any]]]] = {
    "env": bench_env, "solvers": bench_solvers, "agents": bench_agents, "rl": bench_rl,
    "certificates": bench_certificates, "render": bench_render, "field": bench_field,
    "realtime": bench_real_time}


_FIGURE_KEYS = ("ms_per_frame", "steps_per_s", "exponent", "throughput_ratio", "speedup", "ms_per_iter", "ms_per_solve", "ms_p95",
                "us_per_step", "ns_per_lane_step", "gflop_per_s", "converged_fraction")


def _figure(row: dict[str, Any]) -> str:
    """The headline figure of a row, e.g. ``0.697 ms_per_iter``; for a row of parts (the
    iteration's components, the LQ cost by state size) every part, e.g. ``n1 1.1, n4 1.3``."""
    key = next((k for k in _FIGURE_KEYS if k in row), None)
    if key is not None:
        p10 = f" (p10 {row[key + '_p10']:.4g})" if key + "_p10" in row else ""
        return f"{row[key]:.4g} {key}{p10}"
    return ", ".join(f"{k} {v:.3g}" for k, v in row.items()
                     if k != "name" and not k.startswith("target")
                     and isinstance(v, (int, float)) and not isinstance(v, bool))


# A row's target key -> (the figure it bounds, True if the figure must reach at least the target).
_TARGETS = {
    "target_steps_per_s": ("steps_per_s", True),
    "target_ratio": ("throughput_ratio", True),
    "target_vs_endless": ("vs_endless", True),
    "target_vs_ghost": ("vs_ghost", True),
    "target_ms_p95": ("ms_p95", False),
    "target_exponent": ("exponent", False),
    "target_step_20_over_10": ("step_20_over_10", False),
    "target_speedup": ("speedup", True),
    "target_ms": (("ms_per_iter", "ms_per_solve", "ms_per_frame"), False),
}


def _target_verdict(row: dict[str, Any], suffix: str = "") -> tuple[str, bool] | None:
    """The row's target as text (e.g. ``<= 0.25 ms_per_iter``) and whether the figure meets it;
    ``None`` for a row without a target. With ``suffix`` (e.g. ``"_p10"``) the figure judged
    is ``figure + suffix`` (``ms_per_iter_p10``), ``None`` if the row has none."""
    for key, (figures, at_least) in _TARGETS.items():
        if row.get(key) is None:
            continue
        figures = (figures,) if isinstance(figures, str) else figures
        figure = next(f for f in figures if f in row)
        if figure + suffix not in row:
            return None
        target, value = row[key], row[figure + suffix]
        met = value >= target if at_least else value <= target
        return f"{'>=' if at_least else '<='} {target:g} {figure}", bool(met)
    return None


def _verdict_text(row: dict[str, Any], verdict: tuple[str, bool], missed: str = "MISSED") -> str:
    """``<= 0.25 ms_per_iter: met``; for a row with a 10th percentile (``ms_per_iter_p10``)
    also the verdict on it, e.g. ``...: MISSED (p10: met)`` (the median decides); for the
    batch row the arithmetic rate its target needs, against the dgemm reference."""
    text = f"{verdict[0]}: {'met' if verdict[1] else missed}"
    if "target_met_p10" in row:
        text += f" (p10: {'met' if row['target_met_p10'] else 'missed'})"
    if "dgemm_share_at_target" in row:
        text += (f" (the target needs {row['gflop_per_s_at_target']:.3g} GFLOP/s,"
                 f" {row['dgemm_share_at_target']:.0%} of dgemm)")
    return text


def run_bench(only: list[str] | None = None, out: Path | None = None) -> dict[str, Any]:
    """Run the sections ``only`` (default: all) and return the report.

    Each row is printed (stderr) as soon as it is measured and, with ``out``, the JSON
    file is rewritten after every row, so an interrupted run keeps what it measured: on
    Ctrl-C the report gets ``"interrupted": true`` and is returned instead of raising.
    """
    from rich.console import Console
    from rich.table import Table

    names = only or list(SECTIONS)
    unknown = [n for n in names if n not in SECTIONS]
    if unknown:
        raise ValueError(f"unknown bench section(s) {unknown}; choose from {sorted(SECTIONS)}")
    report: dict[str, Any] = {"machine": machine_info(), "results": {}}
    console = Console(stderr=True)

    def save() -> None:
        if out is not None:
            out.parent.mkdir(parents=True, exist_ok=True)
            write_json_atomically(report, out)

    seconds = report["section_seconds"] = {}
    try:
        for name in names:
            console.print(f"[bold]bench {name}[/] ...")
            rows = report["results"].setdefault(name, [])
            start = time.perf_counter()
            for row in SECTIONS[name]():
                verdict = _target_verdict(row)
                if verdict is not None:
                    row["target_met"] = verdict[1]
                    p10 = _target_verdict(row, "_p10")
                    if p10 is not None:
                        row["target_met_p10"] = p10[1]
                rows.append(row)
                seconds[name] = round(time.perf_counter() - start, 1)
                compile_s = f", compile {row['compile_s']:.2f} s" if "compile_s" in row else ""
                target = f", target {_verdict_text(row, verdict)}" if verdict else ""
                console.print(f"  {row['name']}: {_figure(row)}{compile_s}{target}")
                save()
            console.print(f"  ({name}: {seconds.get(name, 0.0):.0f} s)")
    except KeyboardInterrupt:
        report["interrupted"] = True
        console.print("[bold red]interrupted[/]: the report holds the rows measured so far")
    table = Table(title="racing bench" + (" (interrupted)" if report.get("interrupted") else ""))
    for column in ("section", "name", "figure", "compile [s]", "target"):
        table.add_column(column, overflow="fold")
    for section, rows in report["results"].items():
        for row in rows:
            verdict = _target_verdict(row)
            target = "" if verdict is None else _verdict_text(row, verdict, missed="[bold red]missed[/]")
            compile_s = f"{row['compile_s']:.2f}" if "compile_s" in row else ""
            table.add_row(section, row["name"], _figure(row), compile_s, target)
    console.print(table)
    save()
    return report
