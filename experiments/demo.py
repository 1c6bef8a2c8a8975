"""`racing demo`: two scripted cars race one lap of a built-in circuit."""

from __future__ import annotations

import json
from pathlib import Path

from rich.console import Console
from rich.table import Table

from experiments.race import run_race
from planners.scripted import ConstantSpeed, LaneKeeping
from racing_env.env import RacingParallelEnv
from racing_env.config import RaceConfig
from racing_env.render import plot_race, save_gif


def run_demo(out: Path, track: str = "trefoil", laps: int = 1, seed: int = 0, gif_every: int = 4,
             race_distance: float | None = None) -> dict:
    """Race a lane-keeping car (v_max) against a 20 m/s cruiser over ``laps``, or
    ``race_distance`` [m] when given; write GIF, plot and JSON."""
    console = Console()
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed (--seed) must be an integer >= 0, got {seed!r}")
    config = RaceConfig(track=track, num_agents=2, scenario="grid", laps=laps, race_distance=race_distance,
                        render_size=480)  # checks the race before out is made
    out.mkdir(parents=True, exist_ok=True)
    env = RacingParallelEnv(config)
    vehicles = [env.game.vehicles.car(i) for i in range(2)]
    policies = [
        LaneKeeping(env.track, 0, vehicles[0], target_n=1.0),
        ConstantSpeed(env.track, 1, vehicles[1], target_speed=20.0),
    ]
    names = ["lane-keeping", "constant-speed 20 m/s"]
    length = f"{laps} lap(s)" if race_distance is None else f"{race_distance:g} m"
    console.print(f"[bold]racing demo[/]: {names[0]} vs {names[1]} on {env.track!r}, {length}")
    record = run_race(env, policies, seed=seed, render_every=gif_every, progress=True, labels=names)
    table = Table(title=f"result ({record.steps} steps of {env.config.dt} s)")
    for column in ("pos", "car", "driver", "finish [s]", "penalty [s]", "mean speed [m/s]", "contact steps",
                   "at fault", "off track [s]"):
        table.add_column(column)
    for row, name in sorted(zip(record.summary, names), key=lambda r: r[0]["position"]):
        table.add_row(
            str(row["position"]), row["agent"], name,
            f"{row['finish_time']:.2f}" if row["finished"] else "DNF", f"{row['penalty']:g}",
            f"{row['mean_speed']:.2f}", str(row["collision_steps"]), str(row["faults"]), f"{row['time_off_track']:.1f}",
        )
    for incident in record.incidents:
        who = "nobody" if incident["at_fault"] is None else names[incident["at_fault"]]
        console.print(f"incident at {incident['time']:.1f} s: {incident['verdict']}, {who} answers "
                      f"(closing at {incident['closing_speed']:.1f} m/s)")
    console.print(table)
    gif = save_gif(record.frames, out / "race.gif", fps=10.0 / gif_every)
    plot = out / "trajectories.png"
    plot_race(env.track, record.xs, labels=[f"car_{i} ({n})" for i, n in enumerate(names)], title="racing demo", path=plot)
    result = {"track": env.track.name, "laps": laps, "race_distance": race_distance, "drivers": names,
              "summary": record.summary, "incidents": record.incidents, "steps": record.steps}
    (out / "result.json").write_text(json.dumps(result, indent=2))
    console.print(f"wrote {gif}, {plot} and {out / 'result.json'}")
    return result
