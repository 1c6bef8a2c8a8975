"""``racing tracks``: the tracks the commands take by name, with the figures a racer reads, and
a drawing of one with its racing line.

Orchestration only: the figures come from :func:`racing_env.track.track_summary` and
:func:`racing_env.limits.lap_time_limit`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from racing_env import limits
from racing_env.track import get_track, track_names, track_summary
from racing_env.vehicle import VehicleParams


def track_rows(names: list[str] | None = None, lap_limits: bool = False) -> list[dict[str, Any]]:
    """One :func:`track_summary` per track (default: every name :func:`track_names` gives),
    with ``raceline`` (whether one is shipped) and, with ``lap_limits``, the lap-time limits
    [s] of the default car on the racing line and on the centre line (closed tracks)."""
    rows = []
    for name in names or track_names():
        track = get_track(name)
        row: dict[str, Any] = {**track_summary(track), "name": name}  # the name it is asked by
        row["raceline"] = limits.has_raceline(track)
        if lap_limits and track.closed:
            row["limit_raceline_s"] = limits.lap_time_limit(track, line="raceline") if row["raceline"] else None
            row["limit_centerline_s"] = limits.lap_time_limit(track, line="centerline")
        rows.append(row)
    return rows


def print_tracks(rows: list[dict[str, Any]], as_json: bool = False) -> None:
    """The rows as a table on stdout (or as JSON)."""
    if as_json:
        print(json.dumps(rows, indent=1, default=str))
        return
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    table = Table(title="tracks (racing tournament --track NAME; racing tracks --plot NAME draws one)",
                  title_justify="left")
    columns = ["name", "length [m]", "mean width [m]", "min width [m]", "corners", "min radius [m]", "closed",
               "racing line"]
    with_limits = any("limit_centerline_s" in row for row in rows)
    if with_limits:
        columns += ["limit, racing line [s]", "limit, centre line [s]"]
    for column in columns:
        table.add_column(escape(column), justify="left" if column == "name" else "right")
    for row in rows:
        cells = [row["name"], f"{row['length']:.0f}", f"{row['mean_width']:.1f}", f"{row['min_width']:.1f}",
                 str(row["corners"]), f"{row['min_radius']:.1f}", "yes" if row["closed"] else "no",
                 "yes" if row["raceline"] else "-"]
        if with_limits:
            cells += [f"{row[key]:.2f}" if row.get(key) is not None else "-"
                      for key in ("limit_raceline_s", "limit_centerline_s")]
        table.add_row(*cells)
    Console(width=140).print(table)


def plot_track(name: str, path: Path, vehicle: VehicleParams = VehicleParams()) -> Path:
    """Draw track ``name``: its boundaries, the racing line coloured by the speed of its
    lap-time limit (or the centre line's, where no racing line is shipped) and the start line;
    written to ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    track = get_track(name)
    line = "raceline" if limits.has_raceline(track) else "centerline"
    profile = limits.speed_profile(limits.get_line(track, line), vehicle) if track.closed else None
    left, right = track.boundaries()
    fig, ax = plt.subplots(figsize=(8, 8))
    for edge in (left, right):
        closed_edge = np.vstack([edge, edge[:1]]) if track.closed else edge
        ax.plot(closed_edge[:, 0], closed_edge[:, 1], color="0.3", lw=0.8)
    title = f"{track.name}: {track.length:.0f} m"
    if profile is not None:
        x, y, _ = track.to_cartesian(track.s, profile.line.n)
        points = ax.scatter(x, y, c=profile.v, s=1.5, cmap="viridis")
        fig.colorbar(points, ax=ax, shrink=0.7, label=f"speed on the {line} at the lap-time limit [m/s]")
        title += f", lap-time limit {profile.lap_time:.2f} s on the {line} (default car)"
    x0, y0, heading = track.to_cartesian(0.0, 0.0)
    ax.plot([x0 - 8 * np.sin(heading), x0 + 8 * np.sin(heading)], [y0 + 8 * np.cos(heading), y0 - 8 * np.cos(heading)],
            color="red", lw=2, label="start/finish")
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(loc="best", fontsize=8)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return path
