"""The on-disk compilation cache: a second process loads what the first compiled."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from planners import compile_cache
from planners.compile_cache import ENV_VAR, default_cache_dir, enable_compile_cache

ROOT = Path(__file__).resolve().parents[1]

# A fresh process: enable the cache (directory from the environment), solve a small LQ
# game (every program is stored: threshold 0 s), and report JAX's cache events.
_CHILD = """
import json, jax, numpy as np
from planners.compile_cache import enable_compile_cache
events = []
jax.monitoring.register_event_listener(lambda name, **kw: events.append(name))
path = enable_compile_cache(min_compile_seconds=0.0)
jax.config.update("jax_enable_x64", True)
from planners import lq_game
T, N, n, m = 6, 2, 3, 1
rng = np.random.default_rng(0)
L = rng.normal(size=(T + 1, N, n, n))
K, k = lq_game.solve_feedback_own(
    np.eye(n) + 0.1 * rng.normal(size=(T, n, n)), rng.normal(size=(T, N, n, m)),
    L @ np.swapaxes(L, -1, -2), rng.normal(size=(T + 1, N, n)),
    np.broadcast_to(np.eye(m), (T, N, m, m)), rng.normal(size=(T, N, m)))
print(json.dumps({"path": None if path is None else str(path),
                  "hits": events.count("/jax/compilation_cache/cache_hits"),
                  "misses": events.count("/jax/compilation_cache/cache_misses"),
                  "finite": bool(np.all(np.isfinite(K)) and np.all(np.isfinite(k)))}))
"""


def _run_child(env_value: str) -> dict:
    env = {**os.environ, ENV_VAR: env_value, "PYTHONPATH": str(ROOT)}
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    done = subprocess.run([sys.executable, "-c", _CHILD], env=env, capture_output=True, text=True,
                          timeout=300, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_second_process_loads_the_compiled_solver(tmp_path):
    """The first process compiles and stores; the second finds every program it needs."""
    cache = tmp_path / "cache"
    first = _run_child(str(cache))
    assert first["path"] == str(cache) and first["finite"]
    assert first["hits"] == 0 and first["misses"] > 0
    assert any(p.name.startswith("jit_solve_feedback_own") for p in cache.iterdir())
    second = _run_child(str(cache))
    assert second["finite"]
    assert second["misses"] == 0 and second["hits"] == first["misses"]


def test_the_environment_can_turn_the_cache_off(tmp_path):
    """``RACING_COMPILE_CACHE=off``: nothing is enabled, nothing is written."""
    report = _run_child("off")
    assert report["path"] is None and report["hits"] == 0


def test_default_directory_order(monkeypatch, tmp_path):
    """RACING_COMPILE_CACHE first, then a directory JAX already has, then the XDG cache."""
    monkeypatch.setattr(compile_cache, "compile_cache_dir", lambda: str(tmp_path / "jax"))
    monkeypatch.setenv(ENV_VAR, str(tmp_path / "mine"))
    assert default_cache_dir() == tmp_path / "mine"
    monkeypatch.setenv(ENV_VAR, "OFF")
    assert default_cache_dir() is None
    monkeypatch.delenv(ENV_VAR)
    assert default_cache_dir() == tmp_path / "jax"
    monkeypatch.setattr(compile_cache, "compile_cache_dir", lambda: None)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert default_cache_dir() == tmp_path / "xdg" / "racing-games" / "jax"


def test_unusable_directory_is_a_clear_error(tmp_path):
    """A path that is a file, or a negative threshold, is refused before JAX is touched."""
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    with pytest.raises(ValueError, match="compilation cache directory"):
        enable_compile_cache(blocker / "cache")
    with pytest.raises(ValueError, match="min_compile_seconds"):
        enable_compile_cache(tmp_path, min_compile_seconds=-1.0)


@pytest.mark.parametrize(
    "argv, enabled",
    [(["demo", "--scripted"], True), (["paper"], True), (["tournament"], True),
     (["demo", "--scripted", "--no-compile-cache"], False), (["bench", "--only", "env"], False)],
)
def test_cli_commands_that_compile_solvers_use_the_cache(monkeypatch, argv, enabled):
    """demo, paper and tournament turn the cache on before they run; --no-compile-cache and
    bench (whose compile times must be real compilations) do not."""
    from experiments import cli

    calls, ran = [], []
    monkeypatch.setattr(compile_cache, "enable_compile_cache", lambda *a, **k: calls.append(a))
    for command in ("demo", "paper", "tournament", "bench"):  # record the command instead of running it
        monkeypatch.setattr(cli, f"_cmd_{command}", lambda args: ran.append(args.command) or 0)
    assert cli.main(argv) == 0
    assert ran == [argv[0]] and len(calls) == int(enabled)
