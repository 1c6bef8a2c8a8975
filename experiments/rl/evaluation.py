"""How a policy in training is judged: raced against its opponents under tournament rules
(:func:`evaluate`, one record per evaluation, :func:`summarize_evaluation`), the line
printed for it, and the learning curve drawn from the episodes and evaluations
(:func:`plot_learning_curve`). Used by both learners, through :mod:`experiments.rl.common`."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from experiments.formatting import or_dash
from experiments.standings import won_race

if TYPE_CHECKING:
    from experiments.rl.config import TrainConfig


def evaluate(config: TrainConfig, model_path: Path, timesteps: int) -> dict[str, Any]:
    """Race the saved policy against the opponents under tournament rules: every starting
    slot on ``eval_grids`` seeded grids. Returns one evaluation record."""
    from experiments.tournament import race_lineup

    learner = f"rl:{config.algo}:{model_path}"
    by_lineup = {}
    with _global_rngs_kept():  # SB3Agent.reset seeds the global RNGs, which training draws from
        for label, opponents in config.evaluation_lineups():
            races = by_lineup.setdefault(label, [])
            for grid in range(config.eval_grids):
                seed = 1_000_000 + config.seed * 10_000 + grid  # seeds of their own: the training's are seed + copy
                for slot in range(config.cars):
                    lineup = list(opponents)
                    lineup.insert(slot, learner)
                    record, _ = race_lineup(config.race_config(training=False, learner=slot), lineup, seed,
                                            cars=config.car_classes_with_learner(slot))
                    races.append((slot, record))
    record = summarize_evaluation([race for races in by_lineup.values() for race in races], timesteps)
    if config.pool:
        keys = ("races", "wins", "win_rate", "wins_by_start_place", "finished", "mean_margin_s", "contact_steps",
                "time_off_track_s")
        record["by_opponent"] = {label: {k: v for k, v in summarize_evaluation(races, timesteps).items() if k in keys}
                                 for label, races in by_lineup.items()}
    return record


@contextlib.contextmanager
def _global_rngs_kept():
    """Restore Python's, NumPy's and (where installed) torch's global random states on exit."""
    import random

    try:
        import torch
    except ImportError:  # the JAX learner needs no torch
        torch = None
    states = random.getstate(), np.random.get_state(), None if torch is None else torch.get_rng_state()
    try:
        yield
    finally:
        random.setstate(states[0])
        np.random.set_state(states[1])
        if torch is not None:
            torch.set_rng_state(states[2])


def summarize_evaluation(races: list[tuple[int, dict[str, Any]]], timesteps: int) -> dict[str, Any]:
    """The learner's results over ``(slot, race record)`` pairs: wins (a lone car wins the
    races it finishes), places, its mean finish time over the races it finished, its mean
    margin over the races every car finished (the others' mean finish time minus its own),
    distance and incidents (contact steps, and the contact incidents the steward found it caused:
    ``faults``)."""
    places, margins, times, distances, contact, off_track, finished, errors = [], [], [], [], 0, 0.0, 0, []
    faults = 0
    ratios = []
    for slot, record in races:
        me = record["cars"][slot]
        others = [c for k, c in enumerate(record["cars"]) if k != slot]
        places.append(me["place"])
        distances.append(me["distance"])
        contact += me["collision_steps"]
        faults += me.get("faults", 0)  # records from before the steward: none
        off_track += me["time_off_track"]
        if me["finish_time"] is not None:
            finished += 1
            times.append(me["finish_time"])
            if me.get("limit_ratio") is not None:
                ratios.append(me["limit_ratio"])
        if me["error"]:
            errors.append(me["error"])
        if others and me["finish_time"] is not None and all(c["finish_time"] is not None for c in others):
            margins.append(float(np.mean([c["finish_time"] for c in others])) - me["finish_time"])
    won = [won_race(record["cars"][slot], len(record["cars"])) for slot, record in races]
    wins = sum(won)
    starts = [record["cars"][slot]["start_place"] for slot, record in races]
    cars = len(races[0][1]["cars"])
    races_from = [sum(s == k for s in starts) for k in range(1, cars + 1)]
    wins_from = [sum(s == k and w for s, w in zip(starts, won)) for k in range(1, cars + 1)]
    return {"timesteps": int(timesteps), "races": len(races), "wins": wins, "win_rate": wins / len(races),
            "races_by_start_place": races_from, "wins_by_start_place": wins_from,
            "mean_place": float(np.mean(places)), "finished": finished,
            "mean_finish_time_s": float(np.mean(times)) if times else None,
            # its finish time over the race's lap-time limit (racing_env.limits.race_limit), where one applies
            "mean_limit_ratio": float(np.mean(ratios)) if ratios else None,
            "mean_margin_s": float(np.mean(margins)) if margins else None,
            "mean_distance": float(np.mean(distances)), "contact_steps": contact, "faults": faults,
            "time_off_track_s": off_track, "errors": errors}


def evaluation_line(record: dict[str, Any]) -> str:
    if len(record["races_by_start_place"]) == 1:  # a time trial: no one to win against
        lap = or_dash(record["mean_finish_time_s"], "{:.2f} s")
        ratio = "" if record.get("mean_limit_ratio") is None else f" ({record['mean_limit_ratio']:.3f}x the limit)"
        return (f"[bold]evaluation at {record['timesteps']:,} steps[/]: finished {record['finished']}/"
                f"{record['races']}, mean finish time {lap}{ratio}, mean distance {record['mean_distance']:.0f} m, "
                f"off track {record['time_off_track_s']:.1f} s")
    margin = or_dash(record["mean_margin_s"], "{:+.2f} s")
    by_start = ", ".join(f"{w}/{n}" for w, n in zip(record["wins_by_start_place"], record["races_by_start_place"]))
    line = (f"[bold]evaluation at {record['timesteps']:,} steps[/]: won {record['wins']}/{record['races']} "
            f"(starting 1st, 2nd, ...: {by_start}), "
            f"finished {record['finished']}/{record['races']}, mean margin {margin}, "
            f"mean distance {record['mean_distance']:.0f} m, contact steps {record['contact_steps']}, "
            f"at fault {record.get('faults', 0)}, off track {record['time_off_track_s']:.1f} s")
    for label, part in record.get("by_opponent", {}).items():
        margin = or_dash(part["mean_margin_s"], "{:+.2f} s")
        line += f"\n  vs {label}: won {part['wins']}/{part['races']}, mean margin {margin}"
    return line


def plot_learning_curve(episodes: list[dict[str, Any]], evaluations: list[dict[str, Any]], path: Path,
                        title: str = "", time_trial: bool = False) -> None:
    """Three panels against timesteps: training episode returns (with a moving mean); the
    share of training episodes finished and the evaluations' win and finish rates; the
    evaluations' mean finish-time margin over the opponents [s] (races all cars finished),
    or with ``time_trial`` the evaluations' mean finish time [s] with the training
    episodes' finish times."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, (top, middle, bottom) = plt.subplots(3, 1, figsize=(8, 8.5), sharex=True)
    if episodes:
        steps = np.array([e["timesteps"] for e in episodes])
        returns = np.array([e["return"] for e in episodes])
        done = np.array([e["finished"] for e in episodes], dtype=float)
        window = max(1, min(100, len(episodes) // 10))
        kernel = np.ones(window) / window
        top.plot(steps, returns, ".", ms=2, alpha=0.3, color="tab:blue", label="episode return")
        top.plot(steps[window - 1:], np.convolve(returns, kernel, "valid"), color="tab:blue",
                 label=f"mean of {window}")
        middle.plot(steps[window - 1:], np.convolve(done, kernel, "valid"), color="tab:gray",
                    label=f"training episodes finished (mean of {window})")
        top.legend(loc="lower right", fontsize=8)
    top.set_ylabel("return")
    if time_trial and episodes:
        laps = [(e["timesteps"], e["finish_time"]) for e in episodes if e["finish_time"] is not None]
        if laps:
            bottom.plot(*zip(*laps), ".", ms=2, alpha=0.3, color="tab:blue", label="training episode")
    if evaluations:
        steps = [e["timesteps"] for e in evaluations]
        if not time_trial:  # alone, a finished race is a won one
            middle.plot(steps, [e["win_rate"] for e in evaluations], "o-", color="tab:red", label="evaluation: won")
        middle.plot(steps, [e["finished"] / e["races"] for e in evaluations], "s--", color="tab:green",
                    label="evaluation: finished")
        key = "mean_finish_time_s" if time_trial else "mean_margin_s"
        timed = [(e["timesteps"], e.get(key)) for e in evaluations if e.get(key) is not None]
        if timed:
            bottom.plot(*zip(*timed), "o-", color="tab:purple",
                        label=f"evaluation: mean {'finish time' if time_trial else 'margin'}")
        labels = dict.fromkeys(label for e in evaluations for label in e.get("by_opponent", {}))
        for label in labels:  # a pool: the margin against each of its drivers
            part = [(e["timesteps"], e["by_opponent"][label]["mean_margin_s"]) for e in evaluations
                    if e.get("by_opponent", {}).get(label, {}).get("mean_margin_s") is not None]
            if part:
                bottom.plot(*zip(*part), ".--", label=f"vs {label}")
    if time_trial:
        bottom.set_ylabel("finish time [s]")
        times = [y for line in bottom.lines for y in line.get_ydata()]
        if times:  # the first laps can take minutes: show the range of the fast ones
            best = min(times)
            bottom.set_ylim(best - 0.5, min(max(times), 1.2 * best) + 0.5)
    else:
        bottom.axhline(0.0, color="black", lw=0.8)
        bottom.set_ylabel("finish margin [s]\n(> 0: ahead)")
    bottom.set_xlabel("timesteps")
    middle.set_ylim(-0.05, 1.05)
    middle.set_ylabel("fraction")
    if middle.lines:
        middle.legend(loc="best", fontsize=8)
    if len(bottom.lines) > (0 if time_trial else 1):  # more than the zero line
        bottom.legend(loc="upper right" if time_trial else "lower right", fontsize=8)
    top.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
