"""`racing bench`: performance figures as JSON and a table.

Sections: ``env`` (PettingZoo steps per second). Compile time is measured apart from run
time; each figure is the median over repeats so a noisy shared machine disturbs it less.
"""

from __future__ import annotations

import json
import platform
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np


def _median_rate(run: Callable[[], int], repeats: int) -> tuple[float, list[float]]:
    rates = []
    for _ in range(repeats):
        start = time.perf_counter()
        count = run()
        rates.append(count / (time.perf_counter() - start))
    return float(np.median(rates)), rates


def bench_env(steps: int = 3000, repeats: int = 3, cars: tuple[int, ...] = (2, 4)) -> list[dict[str, Any]]:
    """PettingZoo ``step`` calls per second (random actions, one core's worth of Python)."""
    from racing_env import parallel_env

    results = []
    for num in cars:
        env = parallel_env(track="trefoil", num_agents=num, max_steps=10**9, laps=1000)
        rng = np.random.default_rng(0)
        actions = rng.uniform(-1, 1, size=(steps, num, 2)).astype(np.float32)
        env.reset(seed=0)
        start = time.perf_counter()
        env.step({a: actions[0, i] for i, a in enumerate(env.agents)})
        compile_s = time.perf_counter() - start

        def run() -> int:
            env.reset(seed=0)
            for k in range(steps):
                env.step({a: actions[k, i] for i, a in enumerate(env.possible_agents)})
            return steps

        rate, rates = _median_rate(run, repeats)
        results.append(
            {
                "name": f"env_step_{num}_cars",
                "cars": num,
                "steps_per_s": rate,
                "us_per_step": 1e6 / rate,
                "compile_s": compile_s,
                "repeats": [round(r, 1) for r in rates],
                "target_steps_per_s": 5000 if num == 2 else None,
            }
        )
    return results


SECTIONS: dict[str, Callable[[], list[dict[str, Any]]]] = {"env": bench_env}


def run_bench(only: list[str] | None = None, out: Path | None = None) -> dict[str, Any]:
    from rich.console import Console
    from rich.table import Table

    import jax

    names = only or list(SECTIONS)
    unknown = [n for n in names if n not in SECTIONS]
    if unknown:
        raise ValueError(f"unknown bench section(s) {unknown}; choose from {sorted(SECTIONS)}")
    report: dict[str, Any] = {
        "machine": {"platform": platform.platform(), "python": platform.python_version(),
                    "jax": jax.__version__, "devices": [str(d) for d in jax.devices()]},
        "results": {},
    }
    console = Console(stderr=True)
    for name in names:
        console.print(f"[bold]bench {name}[/] ...")
        report["results"][name] = SECTIONS[name]()
    table = Table(title="racing bench")
    for column in ("section", "name", "figure", "compile [s]", "target"):
        table.add_column(column)
    for section, rows in report["results"].items():
        for row in rows:
            figure = next((f"{row[k]:.4g} {k}" for k in ("steps_per_s", "ms_per_iter", "ms_per_solve", "ms_p95") if k in row), "")
            target = next((str(row[k]) for k in row if k.startswith("target") and row[k] is not None), "")
            table.add_row(section, row["name"], figure, f"{row.get('compile_s', float('nan')):.2f}", target)
    console.print(table)
    text = json.dumps(report, indent=2)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text)
    return report
