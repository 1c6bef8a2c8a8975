"""Keep compiled solvers on disk between runs (JAX's persistent compilation cache).

Compiling one iLQ solver takes several times longer than a converged solve
(docs/performance.md, "Compilation cache"). With the cache on, a process that needs a solver another process has
already compiled (same shapes, options and jaxlib) loads it from disk instead::

    import planners.compile_cache
    planners.compile_cache.enable_compile_cache()   # `racing demo|paper|tournament|train|convergence` do this

Where the cache lives, in order: the ``directory`` argument; the environment variable
``RACING_COMPILE_CACHE`` (a directory, or ``off`` to disable the cache); a directory the
user already gave JAX (``JAX_COMPILATION_CACHE_DIR``); ``$XDG_CACHE_HOME/racing-games/jax``
or ``~/.cache/racing-games/jax``. JAX keys the entries by the compiled program, the
backend and the JAX version, so a stale entry is never used; the directory may be deleted
at any time. Only programs whose compilation took at least ``min_compile_seconds`` are
stored (the solvers, not the many small helpers).
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

__all__ = ["ENV_VAR", "MAX_BYTES", "compile_cache_dir", "default_cache_dir", "enable_compile_cache"]

ENV_VAR = "RACING_COMPILE_CACHE"
_OFF = {"off", "0", "false", "no", "none", ""}
MAX_BYTES = 2 * 1024**3
"""The cache's size cap in bytes: least recently used entries are evicted beyond it."""


def compile_cache_dir() -> str | None:
    """The directory of JAX's persistent compilation cache in this process, or ``None``."""
    return jax.config.jax_compilation_cache_dir or None


def default_cache_dir() -> Path | None:
    """The directory :func:`enable_compile_cache` uses without an argument; ``None`` when
    ``RACING_COMPILE_CACHE`` turns the cache off."""
    setting = os.environ.get(ENV_VAR)
    if setting is not None:
        return None if setting.strip().lower() in _OFF else Path(setting).expanduser()
    configured = compile_cache_dir()
    if configured is not None:
        return Path(configured)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "racing-games" / "jax"


def enable_compile_cache(
    directory: str | os.PathLike | None = None, *, min_compile_seconds: float = 1.0
) -> Path | None:
    """Turn on JAX's persistent compilation cache for the rest of the process.

    Args:
        directory: where to keep compiled programs; default :func:`default_cache_dir`.
        min_compile_seconds: store only programs that took at least this long to compile.

    Returns:
        The cache directory, or ``None`` if ``RACING_COMPILE_CACHE=off`` disabled it.

    Raises:
        ValueError: the directory cannot be created or written, or ``min_compile_seconds < 0``.
    """
    if not min_compile_seconds >= 0:
        raise ValueError(f"min_compile_seconds must be >= 0, got {min_compile_seconds!r}")
    path = default_cache_dir() if directory is None else Path(directory).expanduser()
    if path is None:
        return None
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ValueError(
            f"cannot use {str(path)!r} as the compilation cache directory ({error}); set {ENV_VAR} "
            "to a writable folder, or to 'off'"
        ) from error
    if not os.access(path, os.W_OK | os.X_OK):
        raise ValueError(
            f"the compilation cache directory {str(path)!r} is not writable; set {ENV_VAR} to a "
            "writable folder, or to 'off'"
        )
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_seconds))
    jax.config.update("jax_compilation_cache_max_size", MAX_BYTES)
    return path
