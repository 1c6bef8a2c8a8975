"""`racing paper`: the paper's Figures 1-2 and its open-loop-from-feedback claim, reproduced.

Scenario (the paper's Section "Exemplary Results", :func:`racing_env.scenarios.paper_game`):
ego car_0 (v_max 20 m/s) ahead at 20 m/s on the centre line, opponent car_1 (v_max 25 m/s)
approaching at 23 m/s, 2 m to the left, on a straight; horizon 50 steps of 0.1 s; inputs
initialised at zero. Methods: iLQR (opponent predicted at constant speed and offset),
open-loop and feedback iLQGame, all with the same cost weights. Orchestration only: the math
lives in ``planners``, the scene in ``racing_env.scenarios``. Results: docs/experiments/paper.md.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from experiments.timing import time_jax_call
from planners import ilq, ilqr
from planners.nash import nash_residual
from racing_env.dynamics import N_LAT, S
from racing_env.game import RaceGame
from racing_env.scenarios import PAPER_WEIGHTS, paper_game  # noqa: F401  (the scene; re-exported here)

#: Opponent collision weights c_c^2 of Figure 2, as multiples of the ego's c_c^1.
FIG2_RATIOS = (1.0, 2.0, 5.0)


def left_guess(horizon: int = 50, amplitude: float = 2.0) -> np.ndarray:
    """Initial inputs ``(T, 2, 2)`` steering the ego left and the opponent right for 2 s.

    A lateral jerk pulse (+a for 1 s, -a for 1 s) that shifts a car sideways and
    straightens it again; used to show that the scene has a second equilibrium.
    """
    us = np.zeros((horizon, 2, 2))
    us[:10, 0, 1], us[10:20, 0, 1] = amplitude, -amplitude
    us[:10, 1, 1], us[10:20, 1, 1] = -amplitude, amplitude
    return us


def trajectory_metrics(game: RaceGame, xs: np.ndarray) -> dict[str, Any]:
    """Lateral extremes, final gap and closest approach of a 2-car trajectory ``(T+1, 2, 6)``."""
    ds = np.asarray(game.track.wrap_ds(xs[:, 1, S] - xs[:, 0, S]))
    dn = xs[:, 1, N_LAT] - xs[:, 0, N_LAT]
    return {
        "ego_n_min": float(xs[:, 0, N_LAT].min()),
        "ego_n_max": float(xs[:, 0, N_LAT].max()),
        "opponent_n_min": float(xs[:, 1, N_LAT].min()),
        "opponent_n_max": float(xs[:, 1, N_LAT].max()),
        "final_gap_s": float(xs[-1, 0, S] - xs[-1, 1, S]),  # > 0: ego still ahead
        "min_distance": float(np.min(np.hypot(ds, dn))),
    }


def _record(game, x0, method: str, res, first_s: float, run_s: float, nash: bool = True) -> dict[str, Any]:
    """One method's row of ``paper.json`` from its solver result (``ilq.SolverResult``, or an
    ``ilqr.ILQRResult``, whose single-player ``plan`` holds the iteration histories).

    ``convergence`` and ``step_sizes`` are the solver's convergence measure (the full-step
    state change [max abs state entry]) and accepted step size of every iteration.
    """
    xs, us = np.asarray(res.xs), np.asarray(res.us)
    iterations = int(res.iterations)
    plan = getattr(res, "plan", res)
    residual = np.asarray(nash_residual(game, x0, us)) if nash else None
    return {
        "method": method,
        "converged": bool(res.converged),
        "iterations": iterations,
        "solve_time_s": run_s,
        "compile_and_first_solve_s": first_s,
        **trajectory_metrics(game, xs),
        "nash_residual": None if residual is None else residual.tolist(),
        "convergence": np.asarray(plan.history)[:iterations].tolist(),
        "step_sizes": np.asarray(plan.step_history)[:iterations].tolist(),
        "xs": xs,
    }


def solve_methods(game: RaceGame, x0: np.ndarray) -> dict[str, dict[str, Any]]:
    """iLQR, feedback and open-loop iLQGame from zero inputs, and open loop from feedback."""
    out = {}
    res, first, run = time_jax_call(lambda: ilqr.solve_ilqr(game, x0, ego=0))
    # iLQR's residual is not a Nash quantity (the opponent is a prediction): not computed
    out["ilqr"] = _record(game, x0, "iLQR", res, first, run, nash=False)
    fb, first, run = time_jax_call(lambda: ilq.solve(game, x0, mode="feedback"))
    out["feedback"] = _record(game, x0, "feedback iLQGame", fb, first, run)
    ol, first, run = time_jax_call(lambda: ilq.solve(game, x0, mode="open_loop"))
    out["open_loop"] = _record(game, x0, "open-loop iLQGame", ol, first, run)
    olfb, first, run = time_jax_call(lambda: ilq.solve(game, x0, init=fb, mode="open_loop"))
    out["open_loop_from_feedback"] = _record(game, x0, "open-loop iLQGame from the feedback solution", olfb, first, run)
    out["open_loop_from_feedback"]["max_state_change_vs_feedback"] = float(np.max(np.abs(np.asarray(olfb.xs) - np.asarray(fb.xs))))
    guess = left_guess(game.horizon)
    for mode, label in (("open_loop", "open-loop"), ("feedback", "feedback")):
        res, first, run = time_jax_call(lambda: ilq.solve(game, x0, init=guess, mode=mode))
        out[f"{mode}_from_left_guess"] = _record(
            game, x0, f"{label} iLQGame from a left-steering initial guess", res, first, run
        )
    return out


def findings(methods: dict[str, dict], fig2: list[dict]) -> list[dict[str, Any]]:
    """The paper's qualitative claims, each checked against the numbers."""
    il, fb, ol, olfb = (methods[k] for k in ("ilqr", "feedback", "open_loop", "open_loop_from_feedback"))
    rows = [
        ("iLQR: the ego swerves to the right", il["ego_n_min"] < -0.1, f"ego min n = {il['ego_n_min']:.2f} m"),
        ("iLQR: the ego yields (the opponent ends ahead)", il["final_gap_s"] < 0, f"final gap s_ego - s_opp = {il['final_gap_s']:.2f} m"),
        ("feedback: the ego swerves right less than with iLQR", fb["ego_n_min"] > il["ego_n_min"], f"ego min n: feedback {fb['ego_n_min']:.2f} m vs iLQR {il['ego_n_min']:.2f} m"),
        ("open loop differs from feedback, the ego blocks (moves left, towards the opponent)", ol["ego_n_max"] > max(fb["ego_n_max"], 0.0) + 0.1, f"ego max n: open loop {ol['ego_n_max']:.2f} m vs feedback {fb['ego_n_max']:.2f} m"),
        ("open loop from the feedback solution stops after its first iteration", olfb["iterations"] <= 1 and olfb["converged"], f"{olfb['iterations']} iteration(s), converged={olfb['converged']}"),
        ("... with the same outcome as feedback", olfb["max_state_change_vs_feedback"] < 0.05, f"max |x_ol - x_fb| = {olfb['max_state_change_vs_feedback']:.3g}"),
    ]
    lo, hi = fig2[0], fig2[-1]
    rows += [
        ("higher c_c^2: the ego holds its line", abs(hi["ego_n_min"]) < abs(lo["ego_n_min"]), f"ego min n: {lo['ego_n_min']:.2f} m (x{lo['ratio']:g}) -> {hi['ego_n_min']:.2f} m (x{hi['ratio']:g})"),
        ("higher c_c^2: the opponent swerves further left", hi["opponent_n_max"] > lo["opponent_n_max"], f"opponent max n: {lo['opponent_n_max']:.2f} m -> {hi['opponent_n_max']:.2f} m"),
    ]
    oll, fbl = methods["open_loop_from_left_guess"], methods["feedback_from_left_guess"]
    rows.append(
        ("(not a paper claim) a second equilibrium: from a left-steering guess the ego ends left and ahead, in both modes",
         oll["converged"] and fbl["converged"] and min(oll["ego_n_max"], fbl["ego_n_max"]) > 1.0
         and min(oll["final_gap_s"], fbl["final_gap_s"]) > 0,
         f"ego max n: open loop {oll['ego_n_max']:.2f} m, feedback {fbl['ego_n_max']:.2f} m; final gap {oll['final_gap_s']:.2f} / {fbl['final_gap_s']:.2f} m")
    )
    return [{"claim": c, "reproduced": bool(ok), "evidence": e} for c, ok, e in rows]


def plot_methods(game: RaceGame, panels: list[tuple[str, np.ndarray]], path: Path, title: str) -> None:
    """Paper-style figure: one s-n panel per method, ego blue, opponent orange."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    from racing_env.render import car_colour

    fig, axes = plt.subplots(len(panels), 1, figsize=(8.5, 2.1 * len(panels)), sharex=True, squeeze=False)
    length = np.asarray(game.vehicles.length)
    width = np.asarray(game.vehicles.width)
    for ax, (label, xs) in zip(axes[:, 0], panels):
        ax.axhspan(-6.0, 6.0, color="0.93", zorder=0)
        for i, name in enumerate(("ego (car_0)", "opponent (car_1)")):
            colour = np.array(car_colour(i)) / 255
            ax.plot(xs[:, i, S], xs[:, i, N_LAT], color=colour, lw=1.8, label=name)
            for k in range(0, xs.shape[0], 10):
                ax.add_patch(Rectangle((xs[k, i, S] - length[i] / 2, xs[k, i, N_LAT] - width[i] / 2), length[i], width[i],
                                       facecolor=colour, alpha=0.25 + 0.5 * k / xs.shape[0], edgecolor="none"))
        ax.set_ylim(-6.0, 6.0)
        ax.set_ylabel("n [m]")
        ax.set_title(label, fontsize=10, loc="left")
    axes[0, 0].legend(loc="upper left", fontsize=8)
    axes[-1, 0].set_xlabel("s [m]")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def plot_convergence(records: list[dict[str, Any]], tolerance: float, path: Path) -> None:
    """Per iteration of every method: the convergence measure (log scale, with the
    tolerance) and the accepted step size, from the records' ``convergence`` and ``step_sizes``."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, (top, bottom) = plt.subplots(2, 1, figsize=(8.5, 6.0), sharex=True, height_ratios=(2, 1))
    for record in records:
        iterations = np.arange(1, len(record["convergence"]) + 1)
        (line,) = top.semilogy(iterations, record["convergence"], marker="o", ms=3, lw=1.2, label=record["method"])
        bottom.plot(iterations, record["step_sizes"], marker="o", ms=3, lw=1.2, color=line.get_color())
    top.axhline(tolerance, color="0.3", ls="--", lw=1.0)
    top.annotate(f"tolerance {tolerance:g}", (1, tolerance), textcoords="offset points", xytext=(2, 3), fontsize=8)
    top.set_ylabel("full-step state change\nmax |x_new - x_hat| [m, m/s, rad, ...]")
    top.legend(fontsize=7)
    bottom.set_ylabel("accepted step size eta")
    bottom.set_xlabel("iteration")
    bottom.set_ylim(0.0, 1.05)
    fig.suptitle("Convergence of the solvers on the paper's scene")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def run_paper(out: Path) -> dict[str, Any]:
    """Solve everything, write ``fig1_methods.png``, ``fig2_collision_weight.png``,
    ``fig3_convergence.png`` and ``paper.json``."""
    from rich.console import Console
    from rich.table import Table

    from planners.compile_cache import compile_cache_dir

    console = Console(width=160)
    out.mkdir(parents=True, exist_ok=True)
    game, x0 = paper_game()
    console.print("[bold]racing paper[/]: solving iLQR, feedback and open-loop iLQGame ...")
    methods = solve_methods(game, x0)
    fig2 = []
    base_cc = float(np.asarray(PAPER_WEIGHTS.c_collision))
    for ratio in FIG2_RATIOS:
        g2, _ = paper_game(opponent_collision=ratio * base_cc)
        res, first, run = time_jax_call(lambda: ilq.solve(g2, x0, mode="feedback"))
        rec = _record(g2, x0, f"feedback, c_c^2 = {ratio:g} c_c^1", res, first, run)
        rec["ratio"] = ratio
        fig2.append(rec)
    plot_methods(game, [("a) iLQR (opponent predicted at constant speed and offset)", methods["ilqr"]["xs"]),
                        ("b) feedback iLQGame", methods["feedback"]["xs"]),
                        ("c) open-loop iLQGame", methods["open_loop"]["xs"]),
                        ("d) open-loop iLQGame from a left-steering initial guess (a second equilibrium)", methods["open_loop_from_left_guess"]["xs"])],
                 out / "fig1_methods.png", "Figure 1: same costs, inputs initialised at zero")
    plot_methods(game, [(r["method"], r["xs"]) for r in fig2], out / "fig2_collision_weight.png",
                 "Figure 2: opponent collision weight c_c^2, feedback iLQGame")
    plot_convergence([methods[k] for k in ("ilqr", "feedback", "open_loop", "open_loop_from_feedback",
                                           "open_loop_from_left_guess", "feedback_from_left_guess")],
                     ilq.SolverOptions().tolerance, out / "fig3_convergence.png")
    checks = findings(methods, fig2)
    strip = lambda r: {k: v for k, v in r.items() if k != "xs"}  # noqa: E731
    report = {
        "scenario": {"x0": x0.tolist(), "dt": game.dt, "horizon": game.horizon,
                     "weights": {k: np.asarray(v).tolist() for k, v in vars(game.weights).items()}},
        "methods": {k: strip(v) for k, v in methods.items()},
        "figure2": [strip(r) for r in fig2],
        "findings": checks,
        # where set, compile_and_first_solve_s may be a load of a solver compiled by an earlier run
        "compile_cache": compile_cache_dir(),
    }
    (out / "paper.json").write_text(json.dumps(report, indent=2))
    table = Table(title="paper scenario")
    for col in ("method", "conv", "iters", "solve [ms]", "ego n min/max", "opp n min/max", "gap [m]", "min dist [m]", "Nash residual"):
        table.add_column(col)
    for r in list(methods.values()) + fig2:
        res = "-" if r["nash_residual"] is None else " ".join(f"{v:.1e}" for v in r["nash_residual"])
        table.add_row(r["method"], str(r["converged"]), str(r["iterations"]), f"{1e3 * r['solve_time_s']:.1f}",
                      f"{r['ego_n_min']:.2f}/{r['ego_n_max']:.2f}", f"{r['opponent_n_min']:.2f}/{r['opponent_n_max']:.2f}",
                      f"{r['final_gap_s']:.2f}", f"{r['min_distance']:.2f}", res)
    console.print(table)
    for row in checks:
        console.print(f"{'[green]yes[/]' if row['reproduced'] else '[red]no[/]'}  {row['claim']}: {row['evidence']}")
    figures = ", ".join(str(out / name) for name in ("fig1_methods.png", "fig2_collision_weight.png", "fig3_convergence.png"))
    console.print(f"wrote {figures}, {out / 'paper.json'}")
    return report
