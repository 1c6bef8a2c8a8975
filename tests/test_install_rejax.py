"""The install a JAX user types: ``pip install racing-games rejax`` into a fresh virtual
environment gives a set of packages on which rejax trains on ``GymnaxRace``.

rejax (0.1.3, the newest release) asks for ``gymnax>=0.0.9`` and unpacks gymnax 0.0.x's
five-value step; gymnax 1.x returns six values, and every gymnax 1.x release pins
``gymnasium<1.4``. This package's ``gymnasium>=1.4`` makes pip take gymnax 0.0.x rather than
downgrade Gymnasium to a gymnax 1.x; without it pip took gymnax 1.0.1 with Gymnasium 1.3.0, and
rejax's PPO, SAC and TD3 failed to compile (``too many values to unpack (expected 5)``).

The test builds this checkout's wheel, installs it and rejax from the package index as a
user would (with the repository's ``constraints.txt``, as ``make install`` installs), and
runs ``tests/rejax_train.py`` (rejax's PPO, 4,096 steps against the lane keeper) with the
fresh environment's Python, outside the checkout. It downloads JAX, flax and their
dependencies (a few hundred MB): slow, and skipped where the index cannot be reached.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
PIP_TIMEOUT_S = 1800  # the whole install: a few hundred MB downloaded
TRAIN_TIMEOUT_S = 900  # rejax's PPO, 4,096 steps: ~70 s with compiling on a loaded 2-core CPU


def _user_environment() -> dict[str, str]:
    """The environment a user's shell would give the fresh venv: without this test run's
    settings (the checkout on ``PYTHONPATH``, the quick-compile and XLA flags, the run's
    compile cache), which would import the checkout or set flags its jaxlib may not know."""
    dropped_prefixes = ("JAX_", "XLA_", "RACING_")
    return {key: value for key, value in os.environ.items()
            if key not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV") and not key.startswith(dropped_prefixes)}


def _source_tree(destination: Path) -> Path:
    """A copy of what the wheel is built from (the project's metadata and its three packages,
    without caches): pip builds a local project in place, and setuptools' ``build/`` in the
    checkout would keep files deleted since an earlier build."""
    destination.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(ROOT / name, destination / name)
    for package in ("racing_env", "planners", "experiments"):
        shutil.copytree(ROOT / package, destination / package, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    return destination


def _run(command: list[str], timeout: float, cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run(command, capture_output=True, text=True, timeout=timeout, cwd=cwd, env=env)


@pytest.mark.slow
def test_pip_install_racing_games_and_rejax_trains_ppo(tmp_path):
    env = _user_environment()
    probe = _run([sys.executable, "-m", "pip", "download", "--no-deps", "--quiet", "-d", str(tmp_path / "probe"),
                  "rejax"], 300, tmp_path, env)
    if probe.returncode != 0:
        pytest.skip(f"the package index cannot be reached (pip download rejax failed): {probe.stderr.strip()[-300:]}")

    source = _source_tree(tmp_path / "source")
    wheels = tmp_path / "wheels"
    built = _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "-w", str(wheels), str(source)],
                 600, tmp_path, env)
    assert built.returncode == 0, built.stderr[-3000:]
    (wheel,) = wheels.glob("racing_games-*.whl")

    venv = tmp_path / "venv"
    made = _run([sys.executable, "-m", "venv", str(venv)], 300, tmp_path, env)
    assert made.returncode == 0, made.stderr[-3000:]
    python = str(venv / ("Scripts" if os.name == "nt" else "bin") / "python")
    installed = _run([python, "-m", "pip", "install", "--quiet", "-c", str(ROOT / "constraints.txt"), str(wheel),
                      "rejax"], PIP_TIMEOUT_S, tmp_path, env)
    assert installed.returncode == 0, installed.stderr[-3000:]

    versions = _run([python, "-c", "import json, importlib.metadata as m, racing_env; print(json.dumps("
                     "{'racing_env': racing_env.__file__, **{p: m.version(p) for p in "
                     "('gymnasium', 'gymnax', 'rejax', 'jax')}}))"], 300, tmp_path, env)
    assert versions.returncode == 0, versions.stderr[-3000:]
    resolved = json.loads(versions.stdout.strip().splitlines()[-1])
    # the wheel's package, not the checkout's; Gymnasium not downgraded below this package's floor
    assert Path(resolved["racing_env"]).resolve().is_relative_to(venv.resolve()), resolved
    assert tuple(int(part) for part in resolved["gymnasium"].split(".")[:2]) >= (1, 4), resolved

    trained = _run([python, str(ROOT / "tests" / "rejax_train.py"), "off", "ppo"], TRAIN_TIMEOUT_S, tmp_path, env)
    assert trained.returncode == 0, f"{resolved}\n{trained.stderr[-3000:]}"
    (report,) = [json.loads(line) for line in trained.stdout.splitlines() if line.startswith("{")]
    # rejax evaluates before training, halfway and at the end: three mean returns, each over its races
    assert report["algo"] == "ppo" and report["steps"] == 4096 and report["finite"], (resolved, report)
    assert len(report["eval_returns"]) == 3 and np.all(np.isfinite(report["eval_returns"])), (resolved, report)
    assert all(length > 0 for length in report["eval_lengths"]), (resolved, report)
