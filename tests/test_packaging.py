"""The built distribution holds every package of the source tree (subpackages included), the
shipped circuits and the example sweeps; a wheel installed outside the source tree loads every circuit by name,
and installed alone into a fresh virtual environment imports and races."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("racing_env", "planners", "experiments")
PROJECT_FILES = ("pyproject.toml", "README.md", "LICENSE")  # what the build reads besides the packages


def _source_copy(to: Path) -> Path:
    """The packages and the project files copied to ``to`` (a build in the checkout leaves
    build/, whose files later builds reuse)."""
    for package in PACKAGES:
        shutil.copytree(ROOT / package, to / package, ignore=shutil.ignore_patterns("__pycache__"))
    for name in PROJECT_FILES:
        shutil.copy(ROOT / name, to / name)
    return to


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    tmp_path = tmp_path_factory.mktemp("wheel")
    source = _source_copy(tmp_path / "source")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                    "-w", str(tmp_path / "dist"), str(source)], check=True, capture_output=True, timeout=300)
    built, = (tmp_path / "dist").glob("racing_games-*.whl")
    return built


def test_the_wheel_holds_every_package(wheel):
    in_wheel = {name for name in zipfile.ZipFile(wheel).namelist() if name.endswith(".py")}
    in_tree = {path.relative_to(ROOT).as_posix() for package in PACKAGES for path in (ROOT / package).rglob("*.py")}
    assert in_tree - in_wheel == set(), "modules missing from the wheel"
    assert {"planners/agents/__init__.py", "experiments/rl/__init__.py"} <= in_wheel
    assert any(name.endswith(".dist-info/licenses/LICENSE") or name.endswith(".dist-info/LICENSE")
               for name in zipfile.ZipFile(wheel).namelist()), "the wheel carries no LICENSE"


def test_the_wheel_holds_the_circuits_unmodified_with_their_license(wheel):
    data = ROOT / "racing_env" / "data" / "tracks"
    with zipfile.ZipFile(wheel) as archive:
        names = set(archive.namelist())
        shipped = sorted(path.relative_to(ROOT).as_posix() for path in data.rglob("*") if path.is_file())
        assert len(shipped) == 25 + 25 + 2  # circuits, racing lines, LICENSE and README.md
        assert set(shipped) <= names
        for name in shipped:
            assert archive.read(name) == (ROOT / name).read_bytes()


def test_the_wheel_holds_the_example_sweeps(wheel):
    """`racing sweep aggression` works from an installed package: the TOML files are in it."""
    sweeps = sorted((ROOT / "experiments" / "sweeps").glob("*.toml"))
    assert len(sweeps) >= 7
    with zipfile.ZipFile(wheel) as archive:
        for path in sweeps:
            assert archive.read(path.relative_to(ROOT).as_posix()) == path.read_bytes()


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


def _run(command: list[str], cwd: Path, env: dict[str, str], timeout: float) -> str:
    result = subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert result.returncode == 0, f"{' '.join(command)} failed:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    return result.stdout


@pytest.mark.slow
def test_the_wheel_installs_and_races_in_a_fresh_environment(tmp_path):
    """Build the sdist and the wheel (setuptools' PEP 517 hooks, as ``python -m build
    --no-isolation`` calls them), install the wheel with its dependencies from the package
    index into a new virtual environment outside the repository, and there import the three
    packages and race: ``racing demo --scripted`` and a short tournament of a planner."""
    source = _source_copy(tmp_path / "source")
    dist = tmp_path / "dist"
    dist.mkdir()
    # the folder is read before the first hook: setuptools' hooks rewrite sys.argv
    build = ("import sys; from setuptools import build_meta as backend; out = sys.argv[1]; "
             "print(backend.build_sdist(out)); print(backend.build_wheel(out))")
    _run([sys.executable, "-c", build, str(dist)], source, dict(os.environ), timeout=300)
    wheel, = dist.glob("racing_games-*.whl")
    sdist, = dist.glob("racing_games-*.tar.gz")
    with tarfile.open(sdist) as archive:
        in_sdist = {name.split("/", 1)[1] for name in archive.getnames() if "/" in name}
    in_tree = {path.relative_to(source).as_posix() for package in PACKAGES for path in (source / package).rglob("*.py")}
    assert in_tree | {"LICENSE", "pyproject.toml", "README.md"} <= in_sdist, "files missing from the sdist"

    venv = tmp_path / "venv"  # outside the repository: the test's own temporary folder
    _run([sys.executable, "-m", "venv", str(venv)], tmp_path, dict(os.environ), timeout=120)
    python = venv / "bin" / "python"
    env = {key: value for key, value in os.environ.items() if key not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env.update(PATH=f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}", MPLBACKEND="Agg",
               RACING_COMPILE_CACHE="off")
    _run([str(python), "-m", "pip", "install", "--quiet", str(wheel)], tmp_path, env, timeout=1200)

    work = tmp_path / "work"
    work.mkdir()
    where = json.loads(_run([str(python), "-c", "import json, racing_env, planners, experiments; "
                             "print(json.dumps([m.__file__ for m in (racing_env, planners, experiments)]))"],
                            work, env, timeout=300))
    site = _run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], work, env,
                timeout=60).strip()
    assert all(Path(path).is_relative_to(site) for path in where), f"imported from {where}, not from {site}"

    racing = str(venv / "bin" / "racing")
    _run([racing, "demo", "--scripted", "--race-distance", "100", "--out", "demo"], work, env, timeout=600)
    result = json.loads((work / "demo" / "result.json").read_text())
    assert result["steps"] > 0 and len(result["summary"]) == 2
    assert (work / "demo" / "race.gif").stat().st_size > 0
    _run([racing, "tournament", "--agents", "ilqgame-fb", "lane-keeping", "--grids", "1", "--race-distance", "60",
          "--track", "straight", "--out", "tour"], work, env, timeout=900)
    board = json.loads((work / "tour" / "leaderboard.json").read_text())
    assert sorted(row["agent"] for row in board["rows"]) == ["ilqgame-fb", "lane-keeping"]
    assert sum(row["races"] for row in board["rows"]) == 4  # two races (both starting orders), two cars each
    assert (work / "tour" / "report.html").exists()
