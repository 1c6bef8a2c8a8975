"""The `racing` command line: demo, bench (more subcommands join as they land)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def _cmd_demo(args: argparse.Namespace) -> int:
    from experiments.demo import run_demo

    run_demo(Path(args.out), track=args.track, laps=args.laps, seed=args.seed)
    return 0


def _cmd_paper(args: argparse.Namespace) -> int:
    from experiments.paper import run_paper

    run_paper(Path(args.out))
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from experiments.bench import run_bench

    only = [s for part in (args.only or []) for s in part.split(",") if s]
    report = run_bench(only or None, Path(args.json) if args.json else None)
    print(json.dumps(report, indent=2))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="racing",
        description="racing-games: race game-theoretic planners and RL agents on point-mass cars.",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="race two scripted cars and write a GIF, a plot and a result table")
    demo.add_argument("--out", default="runs/demo", help="output folder (default: runs/demo)")
    demo.add_argument("--track", default="trefoil", help="built-in track name or TUMFTM CSV path (default: trefoil)")
    demo.add_argument("--laps", type=int, default=1, help="race length in laps (default: 1)")
    demo.add_argument("--seed", type=int, default=0, help="start-grid seed (default: 0)")
    demo.set_defaults(func=_cmd_demo)

    paper = sub.add_parser("paper", help="reproduce the paper's Figures 1-2 and claims (PNG figures + paper.json)")
    paper.add_argument("--out", default="runs/paper", help="output folder (default: runs/paper)")
    paper.set_defaults(func=_cmd_paper)

    bench = sub.add_parser("bench", help="performance figures as JSON (stdout) and a table (stderr)")
    bench.add_argument("--only", action="append", help="section(s) to run, e.g. --only env (repeatable or comma-separated)")
    bench.add_argument("--json", help="also write the JSON report to this file")
    bench.set_defaults(func=_cmd_bench)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, KeyError, FileNotFoundError) as err:
        print(f"racing {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
