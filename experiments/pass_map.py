"""Where passes happen: every pass of a run's recorded races placed on the lap and classed by
the car class's limit lap at that spot.

A pass is :func:`experiments.tournament.pass_events` on the race distance of two cars both
still racing. Its spot is the passer's arc length on the lap (``s mod`` track length) at the
step of the pass, and its zone comes from the quasi-steady-state speed profile of the run's
car class along the circuit's racing line (:func:`racing_env.limits.speed_profile`; the centre
line where the track ships none):

* ``braking``: the profile decelerates there harder than :data:`BRAKING_AX`;
* ``corner``: else, its lateral acceleration is over :data:`CORNER_SHARE` of the class's
  lateral limit at the profile's speed there (the gg radius ``rho(V)``);
* ``straight``: everything else.

``python -m experiments.pass_map RUN_FOLDER [...]`` prints, per run folder, the passes per
agent and zone and writes the figure of the circuit with its passes
(``RUN_FOLDER/pass-map.png``, or ``--figures DIR/<circuit>-pass-map.png``).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

#: Longitudinal acceleration of the limit lap [m/s^2] below which a spot is a braking zone.
BRAKING_AX = -1.0
#: Share of the class's lateral limit ``rho(V)`` above which ``|ay|`` makes a spot a corner.
CORNER_SHARE = 0.5
#: The zones, in the order of the classification's tests.
ZONES = ("braking", "corner", "straight")


def classify_zones(ax: np.ndarray, ay: np.ndarray, lateral_limit: np.ndarray) -> np.ndarray:
    """The zone index (into :data:`ZONES`) of each point of a limit lap.

    Args:
        ax: ``(M,)`` longitudinal acceleration of the limit lap [m/s^2].
        ay: ``(M,)`` lateral acceleration of the limit lap [m/s^2] (either sign).
        lateral_limit: ``(M,)`` or scalar, the car's lateral limit at each point [m/s^2].

    Returns:
        ``(M,)`` int: 0 braking (``ax < BRAKING_AX``), else 1 corner
        (``|ay| > CORNER_SHARE * lateral_limit``), else 2 straight.
    """
    ax, ay = np.asarray(ax, dtype=float), np.asarray(ay, dtype=float)
    limit = np.broadcast_to(np.asarray(lateral_limit, dtype=float), ay.shape)
    return np.where(ax < BRAKING_AX, 0, np.where(np.abs(ay) > CORNER_SHARE * limit, 1, 2))


def zone_at(s: np.ndarray, zones: np.ndarray, ds: float, length: float) -> np.ndarray:
    """The zones of arc lengths ``s`` on a closed track.

    Args:
        s: ``(K,)`` arc lengths [m], any lap (wrapped into ``[0, length)``).
        zones: ``(M,)`` zone indices at the grid points ``k * ds`` (:func:`classify_zones`).
        ds: grid spacing [m].
        length: lap length [m].

    Returns:
        ``(K,)`` int, the zone of the nearest grid point (the last wraps to the first).
    """
    lap = np.mod(np.asarray(s, dtype=float), length)
    k = np.rint(lap / ds).astype(int) % len(zones)
    return np.asarray(zones)[k]


def track_zones(track, vehicle) -> tuple[np.ndarray, Any]:
    """The zones ``(M,)`` of ``track``'s grid points for one car ``vehicle``
    (:class:`racing_env.VehicleParams`) and the speed profile they come from."""
    from racing_env import limits

    line = limits.get_line(track, "raceline" if limits.has_raceline(track) else "centerline")
    profile = limits.speed_profile(line, vehicle)
    lateral = np.asarray(vehicle.rho(np.asarray(profile.v, dtype=np.float32)), dtype=float)
    return classify_zones(profile.ax, profile.ay, lateral), profile


def run_car_class(out: Path, records: Sequence[dict[str, Any]] = ()) -> str:
    """The car class of run folder ``out``: the first car's ``car_class`` in its records,
    else ``tournament.json``'s ``car``, else ``"paper"`` (the default car)."""
    for record in records:
        cars = record.get("cars") or []
        if cars and cars[0].get("car_class"):
            return str(cars[0]["car_class"])
    config = Path(out) / "tournament.json"
    if config.exists():
        car = json.loads(config.read_text()).get("car")
        if car:
            return str(car)
    return "paper"


def run_passes(out: Path) -> tuple[list[dict[str, Any]], Any, str]:
    """Every pass of the recorded races of run folder ``out``.

    Returns:
        ``(passes, track, car_class)``: ``passes`` one dict per pass with ``race``, ``step``,
        ``s`` (race distance of the passer [m]), ``lap_s`` (its arc length on the lap [m]),
        ``x``, ``y`` (the passer's position [m]), ``zone`` (a name of :data:`ZONES`),
        ``passer``/``passed`` (car indices) and ``passer_agent``/``passed_agent`` (their
        agent specs as the records give them); the races' track; the car class.

    Raises:
        FileNotFoundError: when ``out`` holds no recorded race.
    """
    from experiments.replay import load_replay, recorded_races
    from experiments.tournament import pass_events
    from racing_env.car_classes import get_car
    from racing_env.render import RACING
    from racing_env.track import Track, get_track

    races = recorded_races(Path(out))
    if not races:
        raise FileNotFoundError(f"{out}: no recorded races (replays with their results.jsonl lines)")
    car_class = run_car_class(out, [race["record"] for race in races])
    track, zones = None, None
    passes = []
    for race in races:
        replay = load_replay(race["path"])
        if track is None:
            track = replay.track if isinstance(replay.track, Track) else get_track(replay.track)
            zones, _ = track_zones(track, get_car(car_class))
        cars = race["record"].get("cars") or []
        agents = [car["agent"] for car in cars] if len(cars) == replay.xs.shape[1] else list(replay.labels)
        for step, passer, passed in pass_events(replay.xs[:, :, 0], replay.status == RACING):
            s = float(replay.xs[step, passer, 0])
            lap_s = float(np.mod(s, track.length))
            x, y, _ = track.to_cartesian(lap_s, float(replay.xs[step, passer, 2]))
            passes.append({
                "race": race["race"], "step": int(step), "s": s, "lap_s": lap_s, "x": float(x), "y": float(y),
                "zone": ZONES[int(zone_at(np.array([lap_s]), zones, track.ds, track.length)[0])],
                "passer": int(passer), "passed": int(passed),
                "passer_agent": agents[passer], "passed_agent": agents[passed],
            })
    return passes, track, car_class


def pass_table(passes: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per agent (in order of first appearance): passes ``made`` and ``suffered`` per zone
    (dicts zone name -> count) and their totals."""
    agents: dict[str, dict[str, Any]] = {}

    def row(agent: str) -> dict[str, Any]:
        return agents.setdefault(agent, {"agent": agent, "made": dict.fromkeys(ZONES, 0),
                                         "suffered": dict.fromkeys(ZONES, 0)})

    for p in passes:
        row(p["passer_agent"])["made"][p["zone"]] += 1
        row(p["passed_agent"])["suffered"][p["zone"]] += 1
    for r in agents.values():
        r["made_total"], r["suffered_total"] = sum(r["made"].values()), sum(r["suffered"].values())
    return list(agents.values())


def format_table(rows: Sequence[dict[str, Any]]) -> str:
    """``rows`` (:func:`pass_table`) as a Markdown table: made and suffered per zone."""
    from experiments.formatting import markdown_table

    head = ["agent", *(f"made: {z}" for z in ZONES), "made", *(f"suffered: {z}" for z in ZONES), "suffered"]
    cells = ([r["agent"], *(str(r["made"][z]) for z in ZONES), str(r["made_total"]),
              *(str(r["suffered"][z]) for z in ZONES), str(r["suffered_total"])] for r in rows)
    return "\n".join(markdown_table(head, cells))


def plot_pass_map(track, passes: Sequence[dict[str, Any]], path: Path, zones: np.ndarray | None = None,
                  title: str | None = None) -> Path:
    """Draw ``track``'s outline, its braking zones (``zones``, :func:`track_zones`, shaded
    on the centre line) and the passes as points coloured by the passer's agent, marked by
    zone; written to ``path`` (PNG). Returns ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 8))
    for edge in track.boundaries():
        edge = np.vstack([edge, edge[:1]]) if track.closed else edge
        ax.plot(edge[:, 0], edge[:, 1], color="0.55", lw=0.7)
    if zones is not None:
        braking = np.asarray(zones) == 0
        ax.scatter(np.asarray(track.x)[braking], np.asarray(track.y)[braking], s=10, color="#f6c89f",
                   label=f"braking zone (limit lap ax < {BRAKING_AX:g} m/s^2)", zorder=1)
    x0, y0, heading = track.to_cartesian(0.0, 0.0)
    ax.plot([x0 - 10 * np.sin(heading), x0 + 10 * np.sin(heading)],
            [y0 + 10 * np.cos(heading), y0 - 10 * np.cos(heading)], color="black", lw=2, label="start/finish")
    agents = list(dict.fromkeys(p["passer_agent"] for p in passes))
    colours = plt.get_cmap("tab10")
    markers = {"braking": "v", "corner": "o", "straight": "s"}
    for a, agent in enumerate(agents):
        label = agent  # one legend entry per agent, on its first zone drawn
        for zone, marker in markers.items():
            mine = [p for p in passes if p["passer_agent"] == agent and p["zone"] == zone]
            if mine:
                ax.scatter([p["x"] for p in mine], [p["y"] for p in mine], color=colours(a % 10), marker=marker,
                           s=36, edgecolor="black", linewidth=0.4, zorder=3, label=label)
                label = None
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title or f"{track.name}: {len(passes)} passes (marker: v braking, o corner, s straight)", fontsize=10)
    ax.legend(loc="best", fontsize=7, title="passer", title_fontsize=8)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m experiments.pass_map RUN_FOLDER [...] [--figures DIR]``: the pass table of
    each run folder and its figure."""
    parser = argparse.ArgumentParser(prog="python -m experiments.pass_map", description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run folders (racing tournament --out)")
    parser.add_argument("--figures", type=Path, default=None,
                        help="write each figure as DIR/<circuit>-pass-map.png (default: RUN_FOLDER/pass-map.png)")
    parser.add_argument("--json", action="store_true", help="print every pass as a JSON line instead of the table")
    args = parser.parse_args(argv)
    from racing_env.car_classes import get_car

    for out in args.runs:
        passes, track, car_class = run_passes(out)
        zones, _ = track_zones(track, get_car(car_class))
        if args.json:
            for p in passes:
                print(json.dumps({"run": str(out), **p}))
        else:
            shares = {z: float(np.mean(zones == i)) for i, z in enumerate(ZONES)}
            print(f"## {out} ({track.name}, car {car_class}): {len(passes)} passes; lap share "
                  + ", ".join(f"{z} {100 * v:.0f}%" for z, v in shares.items()))
            print(format_table(pass_table(passes)))
        name = f"{track.name}-pass-map.png" if args.figures else "pass-map.png"
        figure = plot_pass_map(track, passes, (args.figures or out) / name, zones,
                               title=f"{track.name}, {car_class}: {len(passes)} passes in {out.name}")
        print(f"figure: {figure}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
