"""`racing convergence`: how often, and in how many iterations, the game solvers converge
from seeded random close-quarters starts, per circuit, number of cars and mode.

Each (track, cars) pair draws ``scenes`` starts with :func:`racing_env.scenarios.random_scenes`
and solves them as one batch per mode (:func:`experiments.bench.convergence_rows`), from
zero inputs, or for ``open_loop_from_feedback`` from the feedback solution.
Writes ``convergence.json`` (rewritten after every row, so an interrupted run keeps what it
measured) and ``convergence.png`` (per circuit, the fraction of scenes converged within k
iterations), and prints a table.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from experiments.bench import convergence_rows, solver_options_by_mode
from experiments.files import write_json_atomically
from experiments.formatting import or_dash
from planners import ilq
from racing_env.scenarios import check_scene_ranges

MODES = ("feedback", "open_loop", "open_loop_from_feedback")
_MODE_LABELS = {"feedback": "feedback", "open_loop": "open loop", "open_loop_from_feedback": "ol from fb"}


@dataclasses.dataclass(frozen=True)
class ConvergenceConfig:
    """What to sweep.

    Attributes:
        tracks: built-in track names or TUMFTM CSV paths.
        cars: numbers of cars per scene (each >= 1).
        scenes: random starts per (track, cars) pair (>= 1).
        seed: seed of the random starts.
        spread: the cars start up to this far apart along the track [m].
        speed: range of the start speeds [m/s] (capped at 95% of a car's v_max).
        modes: ``"feedback"``, ``"open_loop"``, ``"open_loop_from_feedback"`` (open loop
            initialised with the feedback solution of the same scene).
        max_iterations: the solver's iteration cap (>= 1).
        tolerance: the solver's convergence tolerance (>= 0; the largest state change of a
            full step, state units). The agents re-plan with 1e-3.
        step_control: ``"trust_region"`` (the solver's default), ``"residual"`` (backtracking
            on the open-loop Nash residual; open-loop modes only) or ``"none"``, a fixed step
            ``initial_step`` (the paper's plain update).
        initial_step: the step size ``eta`` tried first, in ``(0, 1]``.
        other_options: further :class:`planners.ilq.SolverOptions` fields as ``(name, value)``
            pairs, e.g. ``(("trust_radius", 10.0),)``; see :func:`parse_solver_option`.
        jerk_weight: every car's jerk weight ``r`` [s^6/m^2] (> 0); ``None`` for the
            ``CostWeights`` default (1.0), ``racing_env.costs.RACING_JERK_WEIGHT`` (0.01)
            for the tournaments' racing weights.
    """

    tracks: tuple[str, ...] = ("trefoil",)
    cars: tuple[int, ...] = (2,)
    scenes: int = 64
    seed: int = 0
    spread: float = 15.0
    speed: tuple[float, float] = (10.0, 19.0)
    modes: tuple[str, ...] = MODES[:2]
    max_iterations: int = 100
    tolerance: float = 1e-6
    step_control: str = "trust_region"
    initial_step: float = 1.0
    other_options: tuple[tuple[str, Any], ...] = ()
    jerk_weight: float | None = None

    def __post_init__(self) -> None:
        if not self.tracks or not self.cars or not self.modes:
            raise ValueError("need at least one track, one number of cars and one mode")
        if any(int(n) < 1 for n in self.cars):
            raise ValueError(f"every number of cars must be >= 1, got {list(self.cars)}")
        if int(self.scenes) < 1:
            raise ValueError(f"need scenes >= 1, got {self.scenes}")
        unknown = [m for m in self.modes if m not in MODES]
        if unknown:
            raise ValueError(f"unknown mode(s) {unknown}; choose from {list(MODES)}")
        check_scene_ranges(self.spread, self.speed)
        own = {"mode", *self.solver_options(include_other=False)}
        for name, _ in self.other_options:
            if name in own or name not in _SOLVER_FIELDS:
                raise ValueError(f"{name!r} is not one of the further solver options "
                                 f"{sorted(set(_SOLVER_FIELDS) - own)}")
        if self.step_control == "residual" and set(self.modes) != {"open_loop"}:
            raise ValueError("step_control 'residual' is for open-loop solves: use it with the "
                             f"modes ('open_loop',) only, not {self.modes}")
        # their own checks, before any work (the most cars: a feedback game refuses what one car takes)
        solver_options_by_mode(self.modes, max(int(n) for n in self.cars), **self.solver_options())
        if self.jerk_weight is not None and not (np.isfinite(self.jerk_weight) and self.jerk_weight > 0):
            raise ValueError(f"jerk_weight must be > 0, got {self.jerk_weight!r}")

    def solver_options(self, include_other: bool = True) -> dict[str, Any]:
        """The :class:`planners.ilq.SolverOptions` fields this sweep sets."""
        options = {"max_iterations": self.max_iterations, "tolerance": self.tolerance,
                   "step_control": self.step_control, "initial_step": self.initial_step}
        return {**options, **dict(self.other_options)} if include_other else options


# Each SolverOptions field's type, from its default value.
_SOLVER_FIELDS = {f.name: type(f.default) for f in dataclasses.fields(ilq.SolverOptions)}


def parse_solver_option(text: str) -> tuple[str, Any]:
    """``"name=value"`` -> ``(name, value)``, the value converted to the type of that
    :class:`planners.ilq.SolverOptions` field (``true``/``false`` for flags)."""
    name, sep, value = text.partition("=")
    name = name.strip().replace("-", "_")
    if not sep or name not in _SOLVER_FIELDS:
        raise ValueError(f"expected NAME=VALUE with NAME one of {sorted(_SOLVER_FIELDS)}, got {text!r}")
    kind = _SOLVER_FIELDS[name]
    if kind is bool:
        if value.lower() not in ("true", "false"):
            raise ValueError(f"{name} takes true or false, got {value!r}")
        return name, value.lower() == "true"
    try:
        return name, kind(value)
    except ValueError:
        raise ValueError(f"{name} takes a {kind.__name__}, got {value!r}") from None


def run_convergence(config: ConvergenceConfig, out: Path) -> dict[str, Any]:
    """Run the sweep, writing ``out/convergence.json`` after every row and
    ``out/convergence.png`` at the end (also after Ctrl-C, then with ``"interrupted": true``
    in the report, which is returned rather than raised)."""
    from rich.console import Console

    from racing_env import CostWeights
    from racing_env.track import get_track

    tracks = {name: get_track(name) for name in config.tracks}  # a bad name fails before any solve
    out.mkdir(parents=True, exist_ok=True)
    report: dict[str, Any] = {"config": dataclasses.asdict(config), "rows": []}
    console = Console(stderr=True)
    pairs = [(name, n) for name in tracks for n in dict.fromkeys(config.cars)]
    try:
        for done, (name, num_cars) in enumerate(pairs, start=1):
            console.print(f"[bold]{tracks[name].name}, {num_cars} cars[/] ({done}/{len(pairs)}): "
                          f"{config.scenes} scenes, compiling and solving ...")
            rows = convergence_rows(config.scenes, seed=config.seed, repeats=1, modes=config.modes,
                                    track=tracks[name], num_cars=num_cars, jerk_weight=config.jerk_weight,
                                    per_scene=True, spread=config.spread, speed=config.speed,
                                    **config.solver_options())
            for row in rows:
                report["rows"].append(row)
                write_json_atomically(report, out / "convergence.json")
                console.print(f"  {row['mode']}: {_summary(row)}")
    except KeyboardInterrupt:
        report["interrupted"] = True
        console.print("[bold red]interrupted[/]: convergence.json holds the rows measured so far")
    write_json_atomically(report, out / "convergence.json")
    if report["rows"]:
        r = f"{CostWeights().r_jx:g} (default)" if config.jerk_weight is None else f"{config.jerk_weight:g}"
        step = {"none": f"fixed step {config.initial_step:g}",
                "residual": f"residual line search, first step {config.initial_step:g}",
                }.get(config.step_control, f"trust region, first step {config.initial_step:g}")
        title = (f"Solves of {config.scenes} random close-quarters starts (seed {config.seed}, "
                 f"jerk weight {r}, tolerance {config.tolerance:g}, {step}"
                 + "".join(f", {k}={v}" for k, v in config.other_options) + ")")
        plot_convergence_profiles(report["rows"], config.max_iterations, out / "convergence.png", title)
    console.print(_table(report["rows"]))
    console.print(f"wrote {out / 'convergence.json'}" + (f", {out / 'convergence.png'}" if report["rows"] else ""))
    return report


def _summary(row: dict[str, Any]) -> str:
    converged = row["statuses"].get("converged", 0)
    text = f"{converged}/{row['scenes']} converged ({row['converged_fraction']:.1%})"
    if row["iterations_median"] is not None:
        text += f", median {row['iterations_median']:g} / p90 {row['iterations_p90']:.3g} iterations"
    if "residual_p90" in row:
        text += f", residual p90 {row['residual_p90']:.2g}"
    return text + f", {row['ms_batch'] / 1e3:.2f} s"


def _table(rows: list[dict[str, Any]]):
    from rich.table import Table

    short = {ilq.status_message(code): label for code, label in (
        (ilq.MAX_ITERATIONS, "capped"), (ilq.NON_FINITE, "non-finite"), (ilq.LINE_SEARCH_FAILED, "no step"))}
    table = Table(title="solves from random close-quarters starts",
                  caption="median, p90, max: iterations of the converged solves; residual p90: of every "
                          "solve, max_i |dJ^i/du^i| (open loop only); ol from fb: open loop started from "
                          "the feedback solution")
    for column in ("track", "cars", "mode", "converged", "median", "p90", "max", "residual p90", "others"):
        table.add_column(column, no_wrap=column in ("track", "others"))
    for row in rows:
        others = ", ".join(f"{v} {short.get(k, k)}" for k, v in row["statuses"].items() if k != "converged")
        table.add_row(row["track"], str(row["cars"]), _MODE_LABELS[row["mode"]],
                      f"{row['statuses'].get('converged', 0)}/{row['scenes']}",
                      *(or_dash(row.get(k), "{:.3g}")
                        for k in ("iterations_median", "iterations_p90", "iterations_max", "residual_p90")),
                      others)
    return table


def plot_convergence_profiles(rows: list[dict[str, Any]], max_iterations: int, path: Path, title: str = "") -> None:
    """One panel per track (four to a row): the fraction of scenes converged within k
    iterations, per mode (colour) and number of cars (line style); a curve ends at the
    converged fraction."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    tracks = list(dict.fromkeys(row["track"] for row in rows))
    cars = sorted({row["cars"] for row in rows})
    styles = dict(zip(cars, ("-", "--", ":", "-.") * len(cars)))
    colours = {"feedback": "tab:blue", "open_loop": "tab:orange", "open_loop_from_feedback": "tab:green"}
    columns = min(len(tracks), 4)
    grid_rows = -(-len(tracks) // columns)
    fig, axes = plt.subplots(grid_rows, columns, figsize=(4.2 * columns, 3.4 * grid_rows + 0.4),
                             sharey=True, squeeze=False)
    for ax in axes.flat[len(tracks):]:
        ax.set_visible(False)
    k = np.arange(0, max_iterations + 1)
    for ax, track in zip(axes.flat, tracks):
        for row in (r for r in rows if r["track"] == track):
            done = np.array([it for it, st in zip(row["iterations"], row["status"]) if st == "converged"])
            within = (done[None, :] <= k[:, None]).sum(axis=1) / row["scenes"]
            ax.step(k, within, where="post", color=colours[row["mode"]], ls=styles[row["cars"]],
                    label=f"{_MODE_LABELS[row['mode']]}, {row['cars']} cars")
        ax.set_title(track, fontsize=10)
        ax.set_xlabel("iterations")
        ax.set_xlim(0, max_iterations)
        ax.grid(alpha=0.3)
    for ax in axes[:, 0]:
        ax.set_ylabel("fraction of scenes converged")
    axes[0, 0].set_ylim(0.0, 1.02)
    axes[0, 0].legend(fontsize=7, loc="lower right")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)
