"""`racing equilibria`: the equilibrium landscape of a scene, certified, as a table, JSON and PNG.

For each solver mode, :func:`planners.landscape.find_equilibria` solves the scene from
``starts`` seeded initial guesses as one batch, clusters what converged and certifies each
distinct solution (:func:`planners.certificates.certify`). ``solver="paper"`` runs the paper's
algorithm as printed (:data:`SOLVERS`) instead of the default solver. Orchestration and
output only: the math lives in :mod:`planners.landscape` and :mod:`planners.certificates`.
Guide: docs/solvers.md, "Equilibrium landscapes (planners.landscape)".
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from experiments.files import write_json_atomically

#: Solver configurations by name (:class:`planners.ilq.SolverOptions` fields). ``"paper"``
#: is the paper's Algorithm 1 as printed: exact Hessians, no curvature the linearised
#: dynamics drop, a fixed step of 0.1; its slower convergence needs more iterations.
SOLVERS: dict[str, dict[str, Any]] = {
    "default": {},
    "paper": {"convexify": "none", "step_control": "none", "initial_step": 0.1, "dynamics_curvature": False,
              "max_iterations": 1000},
}
SCENES = ("paper", "grid", "side_by_side")
MODES = ("open_loop", "feedback")
_MODE_LABELS = {"open_loop": "open loop", "feedback": "feedback"}


@dataclasses.dataclass(frozen=True)
class EquilibriaConfig:
    """What to explore.

    Attributes:
        scene: ``"paper"`` (the paper's overtaking scene, :func:`racing_env.scenarios.paper_game`)
            or a fixed start of ``cars`` cars on ``track``: ``"grid"``, ``"side_by_side"``.
        track, cars, jerk_weight: for ``grid`` and ``side_by_side`` (the track's name or a
            TUMFTM CSV path; ``jerk_weight`` r [s^6/m^2], None for ``CostWeights``' default).
        modes: solver modes, ``"open_loop"`` and/or ``"feedback"``.
        solver: a key of :data:`SOLVERS`.
        starts, seed: initial guesses per mode and the seed of the random ones.
        cluster_tolerance: solutions within this many state units of each other are one.
    """

    scene: str = "paper"
    track: str = "trefoil"
    cars: int = 2
    jerk_weight: float | None = None
    modes: tuple[str, ...] = MODES
    solver: str = "default"
    starts: int = 64
    seed: int = 0
    cluster_tolerance: float = 0.05

    def __post_init__(self) -> None:
        if self.scene not in SCENES:
            raise ValueError(f"unknown scene {self.scene!r}; choose from {list(SCENES)}")
        if self.solver not in SOLVERS:
            raise ValueError(f"unknown solver {self.solver!r}; choose from {list(SOLVERS)}")
        unknown = [m for m in self.modes if m not in MODES]
        if not self.modes or unknown:
            raise ValueError(f"modes must be some of {list(MODES)}, got {list(self.modes)}")
        if int(self.starts) < 1 or int(self.cars) < 1:
            raise ValueError(f"need starts >= 1 and cars >= 1, got {self.starts} and {self.cars}")
        if not self.cluster_tolerance >= 0:
            raise ValueError(f"cluster_tolerance must be >= 0, got {self.cluster_tolerance}")
        if self.jerk_weight is not None and not self.jerk_weight > 0:
            raise ValueError(f"jerk_weight must be > 0, got {self.jerk_weight}")


def scene_game(config: EquilibriaConfig):
    """``(RaceGame, x0 (N, 6))`` of the configured scene (horizon 50 x 0.1 s)."""
    from racing_env import CostWeights, RaceGame
    from racing_env.scenarios import paper_game, make_scenario
    from racing_env.track import get_track

    if config.scene == "paper":
        return paper_game()
    track = get_track(config.track)
    scenario = make_scenario(config.scene, track, config.cars, seed=config.seed)
    weights = CostWeights() if config.jerk_weight is None else CostWeights(r_jx=config.jerk_weight,
                                                                             r_jy=config.jerk_weight)
    return RaceGame.create(track, scenario.vehicles, weights, dt=0.1, horizon=50), scenario.x0


def solution_metrics(game, xs: np.ndarray) -> dict[str, Any]:
    """Of a trajectory ``(T+1, N, 6)``: every car's lateral extent [m] and arc length
    gained [m], the final order (car indices, leader first) and the closest approach of
    any two cars' centres [m]."""
    from racing_env.dynamics import N_LAT, S

    num = xs.shape[1]
    progress = np.asarray(game.track.wrap_ds(xs[-1, :, S] - xs[0, :, S]))
    distances = [np.min(np.hypot(np.asarray(game.track.wrap_ds(xs[:, j, S] - xs[:, i, S])), xs[:, j, N_LAT] - xs[:, i, N_LAT]))
                 for i in range(num) for j in range(i + 1, num)]
    return {"n_min": xs[:, :, N_LAT].min(axis=0).tolist(), "n_max": xs[:, :, N_LAT].max(axis=0).tolist(),
            "n_final": xs[-1, :, N_LAT].tolist(), "progress": progress.tolist(),
            "order": np.argsort(-(xs[0, :, S] + progress)).tolist(),
            "min_distance": float(min(distances)) if distances else None}


def landscape_record(game, landscape) -> dict[str, Any]:
    """A landscape as JSON: :meth:`planners.landscape.Landscape.as_dict` with every
    solution's :func:`solution_metrics`."""
    record = landscape.as_dict(trajectories=True)
    for entry, solution in zip(record["equilibria"], landscape.equilibria):
        entry["metrics"] = solution_metrics(game, solution.xs)
    return record


def plot_landscapes(game, records: dict[str, dict[str, Any]], path: Path, title: str, max_solutions: int = 6) -> None:
    """One row per mode, one s-n panel per distinct solution (most frequent first), titled
    with its share of the starts and its verdict; cars in their race colours."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from racing_env.dynamics import N_LAT, S
    from racing_env.render import car_colour

    columns = max(1, min(max_solutions, max(len(r["equilibria"]) for r in records.values())))
    fig, axes = plt.subplots(len(records), columns, figsize=(3.4 * columns, 2.3 * len(records)), squeeze=False)
    left, right = (float(np.asarray(w(np.asarray(0.0)))) for w in (game.track.width_left_at, game.track.width_right_at))
    for row, (mode, record) in zip(axes, records.items()):
        for ax in row:
            ax.set_axis_off()
        for ax, entry in zip(row, record["equilibria"][:columns]):
            ax.set_axis_on()
            xs = np.asarray(entry["xs"])
            for car in range(xs.shape[1]):
                colour = np.array(car_colour(car)) / 255
                ax.plot(xs[:, car, S], xs[:, car, N_LAT], color=colour, lw=1.6, label=f"car_{car}")
                ax.plot(xs[-1, car, S], xs[-1, car, N_LAT], "o", color=colour, ms=4)
            ax.axhspan(-right, left, color="0.94", zorder=0)  # the track at s = 0
            verdict = entry["certificate"]["verdict"]
            ax.set_title(f"{_MODE_LABELS[mode]}: {100 * entry['share']:.0f}% of starts\n{verdict}", fontsize=8,
                         color="black" if verdict == "local Nash equilibrium" else "firebrick")
            ax.tick_params(labelsize=7)
        row[0].set_ylabel("n [m]", fontsize=8)
    axes[0, 0].legend(fontsize=6, loc="lower left")
    for ax in axes[-1]:
        ax.set_xlabel("s [m]", fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def print_landscapes(records: dict[str, dict[str, Any]], solver: str) -> None:
    """A table of every distinct solution: mode, share, verdict and the numbers behind it."""
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"equilibria ({solver} solver)")
    for column in ("mode", "#", "share", "verdict", "lambda_min(H^i)", "best-response gain", "costs",
                   "n min/max per car [m]", "order", "min dist [m]"):
        table.add_column(column)
    for mode, record in records.items():
        for k, entry in enumerate(record["equilibria"]):
            c, m = entry["certificate"], entry["metrics"]
            fmt = lambda values, form: " ".join("-" if v is None else format(v, form) for v in values)  # noqa: E731
            table.add_row(_MODE_LABELS[mode], str(k), f"{100 * entry['share']:.1f}%", c["verdict"],
                          fmt(c["min_eigenvalue"], ".3g"), fmt(c["best_response_gain"], ".2g"),
                          fmt(entry["costs"], ".1f"),
                          " ".join(f"{a:.2f}/{b:.2f}" for a, b in zip(m["n_min"], m["n_max"])),
                          ">".join(map(str, m["order"])), "-" if m["min_distance"] is None else f"{m['min_distance']:.2f}")
        table.add_row(_MODE_LABELS[mode], "", f"{100 * (1 - record['converged_share']):.1f}%", "did not converge",
                      "", "", "", "", "", "")
    Console(width=170).print(table)


def explore(game, x0, modes, solver: str, starts: int, seed: int, cluster_tolerance: float,
            on_mode=None) -> dict[str, dict[str, Any]]:
    """``{mode: landscape_record}`` for every mode; ``on_mode(mode, record)`` after each."""
    from planners.landscape import find_equilibria

    records = {}
    for mode in modes:
        landscape = find_equilibria(game, x0, mode, starts=starts, seed=seed, cluster_tolerance=cluster_tolerance,
                                    **SOLVERS[solver])
        records[mode] = landscape_record(game, landscape)
        if on_mode is not None:
            on_mode(mode, records[mode])
    return records


def run_equilibria(config: EquilibriaConfig, out: Path) -> dict[str, Any]:
    """Explore every mode; write ``equilibria.json`` (after each mode) and ``equilibria.png``."""
    from rich.console import Console

    console = Console(stderr=True)
    out.mkdir(parents=True, exist_ok=True)
    game, x0 = scene_game(config)
    report: dict[str, Any] = {"config": dataclasses.asdict(config), "solver_options": SOLVERS[config.solver],
                              "x0": np.asarray(x0).tolist(), "landscapes": {}}

    def save(mode: str, record: dict[str, Any]) -> None:
        report["landscapes"][mode] = record
        write_json_atomically(report, out / "equilibria.json")
        found = ", ".join(f"{100 * e['share']:.0f}% {e['certificate']['verdict']}" for e in record["equilibria"])
        console.print(f"  {_MODE_LABELS[mode]}: {len(record['equilibria'])} distinct solution(s): {found}")

    console.print(f"[bold]racing equilibria[/]: {config.scene} scene, {config.starts} starts per mode, "
                  f"{config.solver} solver (each mode is one batch: compiling takes most of the first minute) ...")
    records = explore(game, x0, config.modes, config.solver, config.starts, config.seed, config.cluster_tolerance,
                      on_mode=save)
    print_landscapes(records, config.solver)
    plot_landscapes(game, records, out / "equilibria.png",
                    f"Distinct solutions of the {config.scene} scene from {config.starts} starts ({config.solver} solver)")
    console.print(f"wrote {out / 'equilibria.json'}, {out / 'equilibria.png'}")
    return report
