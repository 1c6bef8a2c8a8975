"""The built distribution holds every package of the source tree (subpackages included)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("racing_env", "planners", "experiments")


def test_the_wheel_holds_every_package(tmp_path):
    # Built from a copy: a build in the checkout leaves build/, whose files later builds reuse.
    source = tmp_path / "source"
    for package in PACKAGES:
        shutil.copytree(ROOT / package, source / package, ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, source / name)
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                    "-w", str(tmp_path / "dist"), str(source)], check=True, capture_output=True, timeout=300)
    wheel, = (tmp_path / "dist").glob("racing_games-*.whl")
    in_wheel = {name for name in zipfile.ZipFile(wheel).namelist() if name.endswith(".py")}
    in_tree = {path.relative_to(source).as_posix() for package in PACKAGES for path in (source / package).rglob("*.py")}
    assert in_tree - in_wheel == set(), "modules missing from the wheel"
    assert {"planners/agents/__init__.py", "experiments/rl/__init__.py"} <= in_wheel
