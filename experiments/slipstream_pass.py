"""A pass out of the slipstream: a planner behind a car of its class on Monza's main straight.

The scene: two AV-21s (``--car av21``: drag and the slipstream, docs/model.md) leave the
Parabolica onto Monza's main straight side by side in lane, the follower :data:`GAPS` metres
(centre to centre, along the track) behind, both at the class's limit-lap speed there. The
car ahead is the racing-line driver: flat out on its line, as fast as the follower alone.
The straight ends at :data:`STRAIGHT_END`, before the braking zone of the first chicane; a pass
made by then is one made on the straight, which with equal cars only the tow of the wake can
make. The scene goes on through the chicane to :data:`FINISH`: who comes out of it in front.

Each follower (:data:`FOLLOWERS`) races it three ways (:data:`WAKES`):

* ``game``: the wake in the physics and in the follower's game, so its plans see the tow
  ahead and the loss of it when pulling out;
* ``physics``: the wake in the physics only; the follower plans with drag alone;
* ``none``: no wake anywhere (``RaceConfig(slipstream=False)``).

``python -m experiments.slipstream_pass run --out DIR`` races every follower, wake and gap
(resuming: a race already in ``DIR/results.jsonl`` is not run again), prints the table and
draws ``DIR/slipstream-pass.png`` (the feedback iLQGame follower's races at the first gap:
its gap to the car ahead, its lateral offset and the share of its drag the wake takes away,
along the straight). ``report DIR`` prints the table and draws the figure from the records.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

#: The track and class of the scene.
TRACK, CAR = "Monza", "av21"
#: Arc length [m] at which the car ahead starts (past the line: the lap's end), just out of the Parabolica.
LEADER_START = -260.0
#: The straight's end [m]: before the first chicane's braking zone (the AV-21's limit lap brakes from 778 m).
STRAIGHT_END = 700.0
#: The scene's finish line [m]: out of the first chicane.
FINISH = 1150.0
#: Gaps [m] along the track, centre to centre, from the follower to the car ahead at the start.
GAPS = (12.0, 20.0, 30.0)
#: The planners that follow.
FOLLOWERS = ("ilqr", "ilqgame-ol", "ilqgame-fb")
#: The car ahead.
LEADER = "raceline"
#: Where the wake acts: in the physics and the follower's game, the physics only, nowhere.
WAKES = ("game", "physics", "none")
#: Steps the scene may take (its 1,410 m take about 20 s).
MAX_STEPS = 400


def check_wake(wake: str) -> None:
    """Refuse a wake that is not one of :data:`WAKES`, naming them."""
    if wake not in WAKES:
        raise ValueError(f"wake must be one of {WAKES}, got {wake!r}")


def scene_start(gap: float, speed: float) -> np.ndarray:
    """The joint start state ``(2, 6)``: the follower (row 0) ``gap`` [m] behind the car ahead
    (row 1) at :data:`LEADER_START`, both on the centre line at ``speed`` [m/s], no acceleration."""
    x0 = np.zeros((2, 6))
    x0[:, 0] = (LEADER_START - gap, LEADER_START)
    x0[:, 1] = speed
    return x0


def start_speed() -> float:
    """The AV-21's limit-lap speed [m/s] at :data:`LEADER_START` on Monza's racing line."""
    from racing_env import limits
    from racing_env.car_classes import get_car
    from racing_env.track import get_track

    track = get_track(TRACK)
    line = limits.get_line(track, "raceline")
    profile = limits.speed_profile(line, get_car(CAR))
    return float(np.interp(LEADER_START % track.length, np.asarray(track.s), profile.v, period=track.length))


def race_scene(follower: str, wake: str, gap: float, speed: float) -> dict[str, Any]:
    """Race the scene once. The record: per step until the first car finishes, the follower's
    ``margin`` [m] to the car ahead (its arc length minus the other's: > 0 ahead), both cars'
    lateral offsets ``n`` [m] and the share of the follower's drag the wake takes away
    (``tow``); the follower's place at the finish (``place``, 1: out of the chicane in front)
    and each car's contact steps, time off the track [s], at-fault incidents and finish time."""
    from experiments.race import run_race
    from experiments.race_spec import RaceSpec
    from planners.agents import make_agent
    from racing_env.dynamics import slipstream_reduction
    from racing_env.env import RacingParallelEnv

    check_wake(wake)
    spec = RaceSpec(track=TRACK, car=CAR, race_distance=FINISH, max_steps=MAX_STEPS)
    env = RacingParallelEnv(spec.to_race_config(2, slipstream=wake != "none"))
    plans_with = env.game if wake != "physics" else dataclasses.replace(env.game, slipstream=None)
    agents = [make_agent(follower), make_agent(LEADER)]
    agents[0].reset(0, 0, plans_with)
    agents[1].reset(0, 1, env)
    record = run_race(env, agents, seed=0, reset_options={"x0": scene_start(gap, speed)}, catch_errors=True)
    xs = record.xs
    finished = np.flatnonzero(xs[:, :, 0].max(axis=1) >= FINISH)
    xs = xs[: int(finished[0]) + 1] if finished.size else xs  # a finished car stands still after
    aero = env.game.aero()  # the physics' wake (none with wake="none")
    tow = np.array([float(slipstream_reduction(x, aero)[0]) for x in xs])
    cars = [{key: car.get(key) for key in ("position", "collision_steps", "time_off_track", "faults", "finish_time")}
            for car in record.summary]
    return {"follower": follower, "leader": LEADER, "wake": wake, "gap": gap, "speed": speed,
            "steps": record.steps, "dt": record.dt, "margin": (xs[:, 0, 0] - xs[:, 1, 0]).tolist(),
            "s": xs[:, 0, 0].tolist(), "n": xs[:, :, 2].tolist(), "tow": tow.tolist(),
            "place": cars[0]["position"], "cars": cars, "faults": record.faults}


def first_ahead(s: np.ndarray, margin: np.ndarray) -> float | None:
    """The follower's arc length [m] at the first step it is ahead (``margin > 0``); None: never."""
    ahead = np.flatnonzero(np.asarray(margin) > 0.0)
    return None if ahead.size == 0 else float(np.asarray(s)[ahead[0]])


def best_margin(s: np.ndarray, margin: np.ndarray, before: float) -> float:
    """The follower's largest margin [m] over the steps before it reaches arc length ``before`` [m]."""
    s, margin = np.asarray(s), np.asarray(margin)
    return float(margin[s < before].max()) if np.any(s < before) else float(margin[0])


def summary_rows(records: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per record: who, which wake, the start gap [m]; where the follower first got
    ahead [m], its best margin on the straight (before :data:`STRAIGHT_END`) [m], its place out
    of the chicane; its largest lateral distance from the car ahead [m] and its mean tow while
    behind; the contact steps."""
    rows = []
    for r in records:
        s, margin, n, tow = (np.asarray(r[k]) for k in ("s", "margin", "n", "tow"))
        behind = margin < 0.0
        rows.append({"follower": r["follower"], "wake": r["wake"], "gap": r["gap"],
                     "ahead_s": first_ahead(s, margin), "straight_margin": best_margin(s, margin, STRAIGHT_END),
                     "place": r["place"], "largest_offset": float(np.max(np.abs(n[:, 0] - n[:, 1]))),
                     "mean_tow": float(tow[behind].mean()) if behind.any() else 0.0,
                     "contact_steps": sum(int(c["collision_steps"] or 0) for c in r["cars"])})
    return rows


def table(records: Sequence[dict[str, Any]]) -> str:
    """The summary as a Markdown table, followers in :data:`FOLLOWERS` order."""
    lines = [f"| follower | wake | start gap [m] | first ahead at [m] | best margin before {STRAIGHT_END:.0f} m [m] "
             "| place out of the chicane | largest offset [m] | mean tow behind | contact steps |",
             "|---|---|---|---|---|---|---|---|---|"]
    order = {name: i for i, name in enumerate(FOLLOWERS)}
    rows = sorted(summary_rows(records), key=lambda r: (order.get(r["follower"], 99), r["gap"], WAKES.index(r["wake"])))
    for r in rows:
        ahead = "-" if r["ahead_s"] is None else f"{r['ahead_s']:.0f}"
        lines.append(f"| {r['follower']} | {r['wake']} | {r['gap']:.0f} | {ahead} | {r['straight_margin']:+.1f} "
                     f"| {r['place']} | {r['largest_offset']:.1f} | {r['mean_tow']:.2f} | {r['contact_steps']} |")
    return "\n".join(lines)


def plot(records: Sequence[dict[str, Any]], path: Path, follower: str = "ilqgame-fb") -> Path | None:
    """The ``follower``'s races at the smallest gap, one line per wake: its margin to the car
    ahead, both cars' lateral offsets and its tow, against its arc length. None when no such
    race is recorded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    chosen = [r for r in records if r["follower"] == follower]
    if not chosen:
        return None
    gap = min(r["gap"] for r in chosen)
    chosen = sorted((r for r in chosen if r["gap"] == gap), key=lambda r: WAKES.index(r["wake"]))
    fig, axes = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    colours = {"game": "tab:red", "physics": "tab:orange", "none": "tab:grey"}
    for r in chosen:
        s, n = np.asarray(r["s"]), np.asarray(r["n"])
        colour = colours[r["wake"]]
        axes[0].plot(s, r["margin"], color=colour, label=f"wake: {r['wake']}")
        axes[1].plot(s, n[:, 0], color=colour, label=f"{follower} (wake: {r['wake']})")
        axes[1].plot(s, n[:, 1], color=colour, linestyle=":", alpha=0.7)
        axes[2].plot(s, r["tow"], color=colour)
    axes[0].axhline(0.0, color="black", linewidth=0.8)
    axes[0].set_ylabel("margin to the car ahead [m]")
    axes[0].legend(loc="upper left")
    axes[1].set_ylabel("lateral offset n [m]\n(dotted: the car ahead)")
    axes[1].legend(loc="lower left", fontsize=8)
    axes[2].set_ylabel("share of drag taken\nby the wake")
    for ax in axes:
        ax.axvline(STRAIGHT_END, color="black", linestyle="--", linewidth=0.8)
    axes[2].set_xlabel("follower's arc length on Monza [m] (dashed: the straight's end)")
    fig.suptitle(f"{follower} {gap:.0f} m behind the racing-line driver, two AV-21s on Monza's main straight")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def load(out: Path) -> list[dict[str, Any]]:
    """The records of ``out/results.jsonl`` (none for a new folder)."""
    path = out / "results.jsonl"
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def run(out: Path, followers: Sequence[str] = FOLLOWERS, gaps: Sequence[float] = GAPS,
        wakes: Sequence[str] = WAKES, progress: bool = True) -> list[dict[str, Any]]:
    """Race every follower, wake and gap not yet in ``out/results.jsonl`` (each record appended as
    it finishes, so an interrupted run resumes); returns every record."""
    from tqdm import tqdm

    for wake in wakes:
        check_wake(wake)
    out.mkdir(parents=True, exist_ok=True)
    records = load(out)
    done = {(r["follower"], r["wake"], r["gap"]) for r in records}
    todo = [(f, w, float(g)) for f in followers for g in gaps for w in wakes if (f, w, float(g)) not in done]
    speed = start_speed()
    with open(out / "results.jsonl", "a") as sink:
        for follower, wake, gap in tqdm(todo, desc="slipstream scenes", disable=not progress):
            record = race_scene(follower, wake, gap, speed)
            sink.write(json.dumps(record) + "\n")
            sink.flush()
            records.append(record)
    return records


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.slipstream_pass", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    run_parser = sub.add_parser("run", help="race the scenes (resumes) and report")
    run_parser.add_argument("--out", type=Path, default=Path("runs/slipstream-pass"))
    run_parser.add_argument("--followers", nargs="+", default=list(FOLLOWERS))
    run_parser.add_argument("--gaps", nargs="+", type=float, default=list(GAPS))
    report_parser = sub.add_parser("report", help="the table and the figure from a run's records")
    report_parser.add_argument("out", type=Path)
    for p in (run_parser, report_parser):
        p.add_argument("--figure", type=Path, default=None, help="where to draw the figure (default: OUT/slipstream-pass.png)")
    args = parser.parse_args(argv)
    import racing_env

    racing_env.configure_for_racing()
    records = run(args.out, args.followers, args.gaps) if args.command == "run" else load(args.out)
    if not records:
        raise SystemExit(f"no records in {args.out / 'results.jsonl'}")
    print(table(records))
    figure = plot(records, args.figure or args.out / "slipstream-pass.png")
    if figure is not None:
        print(f"figure: {figure}")


if __name__ == "__main__":
    main()
