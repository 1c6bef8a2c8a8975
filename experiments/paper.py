"""`racing paper`: the paper's Figures 1-2 and its open-loop-from-feedback claim, reproduced.

Scenario (the paper's Section "Exemplary Results", :func:`racing_env.scenarios.paper_game`):
ego car_0 (v_max 20 m/s) ahead at 20 m/s on the centre line, opponent car_1 (v_max 25 m/s)
approaching at 23 m/s, 2 m to the left, on a straight; horizon 50 steps of 0.1 s; inputs
initialised at zero. Methods: iLQR (opponent predicted at constant speed and offset),
open-loop and feedback iLQGame, all with the same cost weights, and the two game modes once
more with the paper's algorithm as printed (exact Hessians, a fixed step of 0.1); beyond the
paper, the scene as a leader-follower game both ways (feedback Stackelberg iLQGame, each car
leading in turn, certified by :func:`planners.stackelberg.certify_stackelberg`). Every game
solution is certified (:mod:`planners.certificates`: local Nash equilibrium, saddle or not
stationary), and the scene's landscape (:mod:`planners.landscape`: 64 starts per mode and
solver, clustered and certified) says which equilibria the scene has. Orchestration only:
the math lives in ``planners``, the scene in ``racing_env.scenarios``. Results:
docs/experiments/paper.md.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from experiments.equilibria import SOLVERS, explore, plot_landscapes, solution_metrics
from experiments.timing import time_jax_call
from planners import ilq, ilqr
from planners.certificates import LOCAL_NASH, SADDLE, certify
from planners.nash import nash_residual
from planners.stackelberg import certify_stackelberg
from racing_env.dynamics import N_LAT, S
from racing_env.game import RaceGame
from racing_env.scenarios import PAPER_WEIGHTS, paper_game  # noqa: F401  (the scene; re-exported here)

#: Initial guesses per mode and solver of the landscapes (:func:`experiments.equilibria.explore`).
LANDSCAPE_STARTS = 64

#: Opponent collision weights c_c^2 of Figure 2, as multiples of the ego's c_c^1.
FIG2_RATIOS = (1.0, 2.0, 5.0)

#: The leader-follower solutions of the scene: record key -> (leading car, label).
STACKELBERG_LEADERS = {"stackelberg_ego_leads": (0, "feedback Stackelberg iLQGame, the ego (car_0) leading"),
                       "stackelberg_opponent_leads": (1, "feedback Stackelberg iLQGame, the opponent (car_1) leading")}


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
    """Lateral extremes, final gap and closest approach of a 2-car trajectory ``(T+1, 2, 6)``
    (:func:`experiments.equilibria.solution_metrics` named for the ego and the opponent)."""
    metrics = solution_metrics(game, xs)
    return {
        "ego_n_min": metrics["n_min"][0],
        "ego_n_max": metrics["n_max"][0],
        "opponent_n_min": metrics["n_min"][1],
        "opponent_n_max": metrics["n_max"][1],
        "final_gap_s": float(xs[-1, 0, S] - xs[-1, 1, S]),  # > 0: ego still ahead
        "min_distance": metrics["min_distance"],
    }


def _record(game, x0, method: str, res, first_s: float, run_s: float, mode: str | None = None) -> dict[str, Any]:
    """One method's row of ``paper.json`` from its solver result (``ilq.SolverResult``, or an
    ``ilqr.ILQRResult``, whose single-player ``plan`` holds the iteration histories).

    ``convergence`` and ``step_sizes`` are the solver's convergence measure (the full-step
    state change [max abs state entry]) and accepted step size of every iteration. A game
    solution (``mode`` given) carries its first-order Nash residual and its certificate
    (:func:`planners.certificates.certify`); iLQR's opponent is a prediction, so it has neither.
    """
    nash = mode is not None
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
        "certificate": certify(game, x0, res, mode).as_dict() if nash else None,
        "convergence": np.asarray(plan.history)[:iterations].tolist(),
        "step_sizes": np.asarray(plan.step_history)[:iterations].tolist(),
        "xs": xs,
    }


def solve_methods(game: RaceGame, x0: np.ndarray) -> dict[str, dict[str, Any]]:
    """iLQR, feedback and open-loop iLQGame from zero inputs, and open loop from feedback."""
    out = {}
    res, first, run = time_jax_call(lambda: ilqr.solve_ilqr(game, x0, ego=0))
    # iLQR's residual is not a Nash quantity (the opponent is a prediction): not computed
    out["ilqr"] = _record(game, x0, "iLQR", res, first, run)
    fb, first, run = time_jax_call(lambda: ilq.solve(game, x0, mode="feedback"))
    out["feedback"] = _record(game, x0, "feedback iLQGame", fb, first, run, "feedback")
    ol, first, run = time_jax_call(lambda: ilq.solve(game, x0, mode="open_loop"))
    out["open_loop"] = _record(game, x0, "open-loop iLQGame", ol, first, run, "open_loop")
    olfb, first, run = time_jax_call(lambda: ilq.solve(game, x0, init=fb, mode="open_loop"))
    out["open_loop_from_feedback"] = _record(game, x0, "open-loop iLQGame from the feedback solution", olfb, first,
                                             run, "open_loop")
    out["open_loop_from_feedback"]["max_state_change_vs_feedback"] = float(np.max(np.abs(np.asarray(olfb.xs) - np.asarray(fb.xs))))
    guess = left_guess(game.horizon)
    for mode, label in (("open_loop", "open-loop"), ("feedback", "feedback")):
        res, first, run = time_jax_call(lambda: ilq.solve(game, x0, init=guess, mode=mode))
        out[f"{mode}_from_left_guess"] = _record(
            game, x0, f"{label} iLQGame from a left-steering initial guess", res, first, run, mode
        )
    for mode, label in (("open_loop", "open-loop"), ("feedback", "feedback")):
        res, first, run = time_jax_call(lambda: ilq.solve(game, x0, mode=mode, **SOLVERS["paper"]))
        out[f"{mode}_printed"] = _record(
            game, x0, f"{label} iLQGame, the paper's algorithm as printed (exact Hessians, fixed step 0.1)",
            res, first, run, mode)
    return out


def solve_stackelberg(game: RaceGame, x0: np.ndarray) -> dict[str, dict[str, Any]]:
    """The scene as a leader-follower game, each car leading in turn (:data:`STACKELBERG_LEADERS`):
    ``ilq.solve(mode="stackelberg")`` from zero inputs with the solver's defaults, each
    solution certified with :func:`planners.stackelberg.certify_stackelberg` (full checks:
    the follower's best response too). A record as :func:`_record`'s, its ``certificate``
    the Stackelberg certificate's fields and ``leader`` the leading car."""
    out = {}
    for key, (leader, label) in STACKELBERG_LEADERS.items():
        options = ilq.SolverOptions(mode="stackelberg", leader=leader)
        res, first, run = time_jax_call(lambda: ilq.solve(game, x0, options=options))
        iterations = int(res.iterations)
        certificate = certify_stackelberg(game, x0, res, options=options)
        out[key] = {
            "method": label,
            "leader": leader,
            "converged": bool(res.converged),
            "iterations": iterations,
            "solve_time_s": run,
            "compile_and_first_solve_s": first,
            **trajectory_metrics(game, np.asarray(res.xs)),
            "costs": np.asarray(res.costs).tolist(),
            "certificate": {k: (v.tolist() if isinstance(v, np.ndarray) else list(v) if isinstance(v, tuple) else v)
                            for k, v in dataclasses.asdict(certificate).items()},
            "convergence": np.asarray(res.history)[:iterations].tolist(),
            "step_sizes": np.asarray(res.step_history)[:iterations].tolist(),
            "xs": np.asarray(res.xs),
        }
    return out


def plot_stackelberg(game: RaceGame, methods: dict[str, dict[str, Any]], stackelberg: dict[str, dict[str, Any]],
                     path: Path) -> None:
    """Figure 6: the feedback Nash solution beside the two leader-follower solutions
    (:func:`solve_stackelberg`), one s-n panel each, each titled with its certificate's verdict."""
    panels = [(f"a) {methods['feedback']['method']} ({methods['feedback']['certificate']['verdict']})",
               methods["feedback"]["xs"])]
    for letter, record in zip("bc", stackelberg.values()):
        panels.append((f"{letter}) {record['method']} ({record['certificate']['verdict']})", record["xs"]))
    plot_methods(game, panels, path, "Figure 6: leader and follower, feedback Stackelberg iLQGame")


def findings(methods: dict[str, dict], fig2: list[dict], landscapes: dict[str, dict[str, dict]] | None = None
             ) -> list[dict[str, Any]]:
    """The paper's qualitative claims, each checked against the numbers; with
    ``landscapes``, also the claims about the scene's equilibria
    (:func:`landscape_findings`). For a "(revisited)" row, "reproduced" is the truth of
    the statement."""
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
    if landscapes is not None:
        rows += landscape_findings(methods, landscapes)
    return [{"claim": c, "reproduced": bool(ok), "evidence": e} for c, ok, e in rows]


def _verdict_share(record: dict[str, Any], verdict: str) -> float:
    return sum(e["share"] for e in record["equilibria"] if e["certificate"]["verdict"] == verdict)


def _ego_ahead(entry: dict[str, Any]) -> bool:
    """The ego (car 0) ends ahead after moving left, towards the opponent's side: the
    paper's open-loop "blocking" (Figure 1c)."""
    return entry["metrics"]["order"][0] == 0 and entry["metrics"]["n_max"][0] > 0.5


def _describe(entry: dict[str, Any]) -> str:
    c, m = entry["certificate"], entry["metrics"]
    text = (f"{100 * entry['share']:.0f}% of starts: {c['verdict']} (ego n max {m['n_max'][0]:.2f} m, "
            f"opponent ends at n = {m['n_final'][1]:.2f} m")
    gains = [(i, g) for i, g in enumerate(c["best_response_gain"]) if g is not None and c["verdict"] == SADDLE and g > 1e-6]
    lows = [(i, lo) for i, lo in enumerate(c["min_eigenvalue"]) if lo is not None and lo < 0]
    if lows:
        text += "; lambda_min " + ", ".join(f"{('ego', 'opponent')[i]} {lo:.3g}" for i, lo in lows)
    if gains:
        text += "; a best response gains " + ", ".join(f"{('ego', 'opponent')[i]} {g:.3g}" for i, g in gains)
    return text + ")"


def landscape_findings(methods: dict[str, dict], landscapes: dict[str, dict[str, dict]]) -> list[tuple[str, bool, str]]:
    """Claims about the scene's equilibria, from the certified solutions and the landscapes
    (``{solver: {mode: landscape record}}``, :func:`experiments.equilibria.explore`)."""
    printed, default = landscapes["paper"], landscapes["default"]
    olp = methods["open_loop_printed"]
    rows = [(
        "(revisited) the paper's algorithm as printed blocks in open loop from zero inputs",
        olp["final_gap_s"] > 0 and olp["ego_n_max"] > 0.5,
        f"ego n max {olp['ego_n_max']:.2f} m, final gap {olp['final_gap_s']:.2f} m: {olp['certificate']['verdict']}",
    )]
    saddle = {mode: _verdict_share(printed[mode], SADDLE) for mode in printed}
    rows.append((
        "(revisited) the printed algorithm converges to saddles, reported as converged",
        max(saddle.values()) > 0,
        "; ".join(f"{mode}: {100 * saddle[mode]:.0f}% of {printed[mode]['starts']} starts" for mode in saddle)
        + "; default solver: " + ", ".join(f"{mode} {100 * _verdict_share(default[mode], SADDLE):.0f}%" for mode in default),
    ))
    ahead = [e for e in printed["open_loop"]["equilibria"] if _ego_ahead(e)]
    rows.append((
        "(revisited) open-loop blocking (the ego ends ahead after moving left) is a local Nash equilibrium",
        any(e["certificate"]["verdict"] == LOCAL_NASH for e in ahead),
        "; ".join(_describe(e) for e in ahead) or "no converged open-loop solution has the ego ahead",
    ))
    fb_ahead = [e for e in default["feedback"]["equilibria"] if _ego_ahead(e) and e["certificate"]["verdict"] == LOCAL_NASH]
    rows.append((
        "(revisited) blocking is specific to open loop",
        not fb_ahead,
        "feedback has it too: " + "; ".join(_describe(e) for e in fb_ahead) if fb_ahead
        else "no certified feedback equilibrium has the ego ahead",
    ))
    for mode in ("open_loop", "feedback"):
        nash = [e for e in default[mode]["equilibria"] if e["certificate"]["verdict"] == LOCAL_NASH]
        rows.append((
            f"(revisited) distinct certified {mode.replace('_', '-')} equilibria of the scene",
            True,
            f"{len(nash)}: " + "; ".join(
                f"{100 * e['share']:.0f}% of starts, {'ego' if e['metrics']['order'][0] == 0 else 'opponent'} ahead, "
                f"ego n {e['metrics']['n_min'][0]:.2f}/{e['metrics']['n_max'][0]:.2f} m" for e in nash),
        ))
    return rows


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
    """Solve everything, write ``fig1_methods.png`` to ``fig6_stackelberg.png`` and ``paper.json``."""
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
        rec = _record(g2, x0, f"feedback, c_c^2 = {ratio:g} c_c^1", res, first, run, "feedback")
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
    console.print("solving the scene as a leader-follower game, each car leading ...")
    stackelberg = solve_stackelberg(game, x0)
    plot_stackelberg(game, methods, stackelberg, out / "fig6_stackelberg.png")
    console.print(f"exploring the scene's landscape: {LANDSCAPE_STARTS} starts per mode and solver ...")
    landscapes = {solver: explore(game, x0, ("open_loop", "feedback"), solver, LANDSCAPE_STARTS, 0, 0.05)
                  for solver in ("default", "paper")}
    for solver, name in (("default", "fig4_landscape_default.png"), ("paper", "fig5_landscape_printed.png")):
        label = "the default solver" if solver == "default" else "the paper's algorithm as printed"
        plot_landscapes(game, landscapes[solver], out / name,
                        f"Distinct solutions of the paper's scene from {LANDSCAPE_STARTS} starts, {label}")
    checks = findings(methods, fig2, landscapes)
    strip = lambda r: {k: v for k, v in r.items() if k != "xs"}  # noqa: E731
    report = {
        "scenario": {"x0": x0.tolist(), "dt": game.dt, "horizon": game.horizon,
                     "weights": {k: np.asarray(v).tolist() for k, v in vars(game.weights).items()}},
        "methods": {k: strip(v) for k, v in methods.items()},
        "figure2": [strip(r) for r in fig2],
        "stackelberg": {k: strip(v) for k, v in stackelberg.items()},
        "findings": checks,
        "landscapes": {solver: {mode: {k: v for k, v in record.items() if k != "labels"}
                                for mode, record in by_mode.items()} for solver, by_mode in landscapes.items()},
        # where set, compile_and_first_solve_s may be a load of a solver compiled by an earlier run
        "compile_cache": compile_cache_dir(),
    }
    (out / "paper.json").write_text(json.dumps(report, indent=2))
    table = Table(title="paper scenario")
    for col in ("method", "conv", "iters", "solve [ms]", "ego n min/max", "opp n min/max", "gap [m]", "min dist [m]",
                "Nash residual", "certificate"):
        table.add_column(col)
    for r in list(methods.values()) + fig2:
        res = "-" if r["nash_residual"] is None else " ".join(f"{v:.1e}" for v in r["nash_residual"])
        table.add_row(r["method"], str(r["converged"]), str(r["iterations"]), f"{1e3 * r['solve_time_s']:.1f}",
                      f"{r['ego_n_min']:.2f}/{r['ego_n_max']:.2f}", f"{r['opponent_n_min']:.2f}/{r['opponent_n_max']:.2f}",
                      f"{r['final_gap_s']:.2f}", f"{r['min_distance']:.2f}", res,
                      "-" if r["certificate"] is None else r["certificate"]["verdict"])
    console.print(table)
    for r in stackelberg.values():
        console.print(f"{r['method']}: converged={r['converged']} in {r['iterations']} iterations, ego n "
                      f"{r['ego_n_min']:.2f}/{r['ego_n_max']:.2f} m, opponent n {r['opponent_n_min']:.2f}/"
                      f"{r['opponent_n_max']:.2f} m, final gap {r['final_gap_s']:.2f} m: {r['certificate']['verdict']}")
    for row in checks:
        console.print(f"{'[green]yes[/]' if row['reproduced'] else '[red]no[/]'}  {row['claim']}: {row['evidence']}")
    figures = ", ".join(str(out / name) for name in ("fig1_methods.png", "fig2_collision_weight.png", "fig3_convergence.png",
                                                     "fig4_landscape_default.png", "fig5_landscape_printed.png",
                                                     "fig6_stackelberg.png"))
    console.print(f"wrote {figures}, {out / 'paper.json'}")
    return report
