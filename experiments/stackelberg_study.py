"""Cinar & Laine's leader-follower claims (arXiv 2402.09548) raced in the arena.

The study: a round robin of duels between the strategies of their pairings, mapped onto the
arena's agents (constant-velocity prediction = ``ilqr``, Nash = ``ilqgame-fb`` and
``ilqgame-ol``, ``ilqgame-leader``, ``ilqgame-follower``), on four circuits, from seeded
close-quarters starts anywhere before the finish (the ``anywhere`` scenario: the two cars
within 15 m of each other at 5-19 m/s each, as their random starts), each start raced with
the two agents in both slots, under the contact rules (docs/rules.md). Each circuit is one
``racing tournament`` folder, so the study resumes where it stopped and grows with ``--grids``.

    python -m experiments.stackelberg_study run --out runs/stackelberg --grids 8 --workers 2
    python -m experiments.stackelberg_study report --out runs/stackelberg

``report`` prints the tables of docs/experiments/stackelberg.md: each agent's means with 95%
intervals, the head-to-head win rates, and every claim as a paired comparison
(:mod:`experiments.claims`).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Sequence

import numpy as np

from experiments.claims import CarRace, agent_mean, car_races, compare, head_to_head
from experiments.jsonl import read_jsonl

AGENTS = ("ilqr", "ilqgame-ol", "ilqgame-fb", "ilqgame-leader", "ilqgame-follower")
"""The strategies: constant-velocity prediction, the two Nash equilibria, leader, follower."""
CIRCUITS = (("trefoil", "trefoil", None), ("Monza", "Monza", 1300.0), ("Spa", "Spa", 1300.0),
            ("Norisring", "Norisring", 1300.0))
"""(folder, track, race distance [m]; None: one lap) of each circuit raced."""
SCENARIO = "anywhere"
"""The starts (:data:`racing_env.scenarios.SCENARIOS`): from a rolling grid two equal cars
hardly ever pass, so the race is decided by the slot; close-quarters scenes are contested."""
LEADER, FOLLOWER, NASH = "ilqgame-leader", "ilqgame-follower", "ilqgame-fb"


@dataclasses.dataclass(frozen=True)
class Claim:
    """A claim of the paper as a paired comparison: ``a`` is higher than ``b`` on ``measure``."""

    text: str
    a: str
    b: str
    measure: str


CLAIMS = (
    Claim("leading wins more than Nash play", LEADER, NASH, "win"),
    Claim("leading wins more than following", LEADER, FOLLOWER, "win"),
    Claim("leading blocks more than Nash play", LEADER, NASH, "blocks"),
    Claim("leading blocks more than open-loop Nash play", LEADER, "ilqgame-ol", "blocks"),
    Claim("leading costs safety: more at-fault incidents than Nash play", LEADER, NASH, "at-fault incidents"),
    Claim("leading costs safety: more contact than Nash play", LEADER, NASH, "contact"),
    Claim("following is safer: fewer at-fault incidents than Nash play", NASH, FOLLOWER, "at-fault incidents"),
    Claim("following is safer: less contact than Nash play", NASH, FOLLOWER, "contact"),
    Claim("following is safer: less contact than leading", LEADER, FOLLOWER, "contact"),
    Claim("following is safer: less time off track than Nash play", NASH, FOLLOWER, "time off track [s]"),
)
"""The claims, each written so that "reproduced" means the paper's direction."""


def run(out: Path, grids: int, workers: int = 1, circuits: Sequence[tuple] = CIRCUITS,
        agents: Sequence[str] = AGENTS, scenario: str = SCENARIO) -> None:
    """Race (or resume) the round robin on every circuit into ``out/<folder>``."""
    from experiments.tournament import TournamentConfig, run_tournament

    for folder, track, distance in circuits:
        config = TournamentConfig(agents=tuple(agents), grids=grids, track=track, scenario=scenario,
                                  **({} if distance is None else {"race_distance": distance}))
        run_tournament(config, out / folder, gif=False, workers=workers, report=False)


def load(out: Path, circuits: Sequence[tuple] = CIRCUITS) -> list[CarRace]:
    """Every car's race of the study's folders that exist."""
    rows: list[CarRace] = []
    for folder, track, _ in circuits:
        results = out / folder / "results.jsonl"
        if results.exists():
            rows += car_races(read_jsonl(results), track)
    return rows


def _interval(value: float, low: float, high: float, fmt: str) -> str:
    return f"{fmt.format(value)} [{fmt.format(low)}, {fmt.format(high)}]"


def report(rows: Sequence[CarRace], agents: Sequence[str] = AGENTS) -> str:
    """The page's tables (markdown) from the study's races."""
    measures = (("win", "{:.2f}"), ("blocks", "{:.2f}"), ("at-fault incidents", "{:.2f}"), ("contact", "{:.2f}"),
                ("time off track [s]", "{:.2f}"), ("passes made", "{:.2f}"))
    lines = ["| agent | races | " + " | ".join(f"{m} per race" for m, _ in measures) + " |",
             "|---|---|" + "---|" * len(measures)]
    for agent in agents:
        means = [agent_mean(rows, agent, m) for m, _ in measures]
        lines.append(f"| `{agent}` | {means[0].n} | "
                     + " | ".join(_interval(x.value, x.low, x.high, fmt) for x, (_, fmt) in zip(means, measures)) + " |")
    table = head_to_head(rows, agents)
    lines += ["", "| win rate of the row against the column | " + " | ".join(f"`{a}`" for a in agents) + " |",
              "|---|" + "---|" * len(agents)]
    for i, a in enumerate(agents):
        cells = ["-" if np.isnan(x) else f"{x:.2f}" for x in table[i]]
        lines.append(f"| `{a}` | " + " | ".join(cells) + " |")
    lines += ["", "| claim | a - b, paired | 95% interval | pairs | verdict |", "|---|---|---|---|---|"]
    for claim in CLAIMS:
        c = compare(rows, claim.a, claim.b, claim.measure)
        lines.append(f"| {claim.text} (`{claim.a}` - `{claim.b}`, {claim.measure}) | {c.difference:+.3f} | "
                     f"[{c.low:+.3f}, {c.high:+.3f}] | {c.pairs} | {c.verdict} |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.stackelberg_study", description=__doc__.split("\n")[0])
    parser.add_argument("what", choices=("run", "report"))
    parser.add_argument("--out", type=Path, default=Path("runs/stackelberg"))
    parser.add_argument("--grids", type=int, default=8, help="seeded starts per pairing and circuit (default 8)")
    parser.add_argument("--workers", type=int, default=1, help="local worker processes (default 1)")
    args = parser.parse_args(argv)
    if args.grids < 1 or args.workers < 1:
        parser.error("--grids and --workers must be at least 1")
    if args.what == "run":
        run(args.out, args.grids, args.workers)
    print(report(load(args.out)))


if __name__ == "__main__":
    main()
