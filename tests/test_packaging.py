"""The built distribution holds every package of the source tree (subpackages included) and
the shipped circuits, and a wheel installed outside the source tree loads every circuit by name."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("racing_env", "planners", "experiments")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    # Built from a copy: a build in the checkout leaves build/, whose files later builds reuse.
    tmp_path = tmp_path_factory.mktemp("wheel")
    source = tmp_path / "source"
    for package in PACKAGES:
        shutil.copytree(ROOT / package, source / package, ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, source / name)
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                    "-w", str(tmp_path / "dist"), str(source)], check=True, capture_output=True, timeout=300)
    built, = (tmp_path / "dist").glob("racing_games-*.whl")
    return built


def test_the_wheel_holds_every_package(wheel):
    in_wheel = {name for name in zipfile.ZipFile(wheel).namelist() if name.endswith(".py")}
    in_tree = {path.relative_to(ROOT).as_posix() for package in PACKAGES for path in (ROOT / package).rglob("*.py")}
    assert in_tree - in_wheel == set(), "modules missing from the wheel"
    assert {"planners/agents/__init__.py", "experiments/rl/__init__.py"} <= in_wheel


def test_the_wheel_holds_the_circuits_unmodified_with_their_license(wheel):
    data = ROOT / "racing_env" / "data" / "tracks"
    with zipfile.ZipFile(wheel) as archive:
        names = set(archive.namelist())
        shipped = sorted(path.relative_to(ROOT).as_posix() for path in data.rglob("*") if path.is_file())
        assert len(shipped) == 25 + 25 + 2  # circuits, racing lines, LICENSE and README.md
        assert set(shipped) <= names
        for name in shipped:
            assert archive.read(name) == (ROOT / name).read_bytes()


def test_an_installed_wheel_loads_every_circuit_by_name(wheel, tmp_path):
    """Installed (without dependencies: they are this interpreter's) into a folder of its own
    and imported from there, in a process whose working directory is not the source tree."""
    site = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-compile", "-q", "--target", str(site),
                    str(wheel)], check=True, capture_output=True, timeout=300)
    code = (
        "import json, sys; sys.path.insert(0, sys.argv[1]); import racing_env\n"
        "from racing_env import limits, track\n"
        "names = track.circuit_names()\n"
        "lengths = {n: track.get_track(n.lower()).length for n in names}\n"
        "print(json.dumps({'file': racing_env.__file__, 'lengths': lengths,\n"
        "                  'monza': limits.lap_time_limit('Monza')}))\n"
    )
    # -I: no PYTHONPATH, no user site, and neither the script's folder nor the cwd on sys.path
    done = subprocess.run([sys.executable, "-I", "-c", code, str(site)], cwd=tmp_path, check=True,
                          capture_output=True, text=True, timeout=300)
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert Path(result["file"]).is_relative_to(site), result["file"]
    assert len(result["lengths"]) == 25 and all(length > 2000 for length in result["lengths"].values())
    assert result["monza"] > 0
