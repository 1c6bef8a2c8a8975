"""Safe writes to a run's output folder.

- Files written whole or not at all (:func:`replace_atomically`): a reader, or a run
  interrupted mid-write, finds the old file or the new one, never half of one.
- One writer per folder (:func:`one_writer`): the resumable runs (tournaments, sweeps,
  trainings, exploitability studies) append to the files in their ``--out`` folder and
  resume from what those hold, so two runs writing one folder at once would interleave
  their records (the same race twice, one run's checkpoint resumed by the other). The second
  run is refused at once instead.
"""

from __future__ import annotations

import contextlib
import json
from pathlib import Path
from typing import Any, Callable, Iterator

LOCK = ".lock"
"""The file in an output folder that a run writing there holds locked."""


def replace_atomically(write: Callable[[Path], Any], path: Path) -> None:
    """``write(partial)`` to ``path`` + ``.partial`` in the same folder, then rename it onto
    ``path``, so a reader (or an interrupted run) never finds a half-written file: the old
    one stays."""
    partial = path.with_name(path.name + ".partial")
    write(partial)
    partial.replace(path)


def write_json_atomically(report: Any, path: Path) -> None:
    """Write ``report`` (anything ``json.dumps`` takes) as indented JSON to ``path`` with
    :func:`replace_atomically`."""
    replace_atomically(lambda partial: partial.write_text(json.dumps(report, indent=2)), path)


class FolderInUse(OSError):
    """Another process is writing to the output folder."""


@contextlib.contextmanager
def one_writer(out: Path, what: str) -> Iterator[None]:
    """Hold ``out`` (created if missing) for this run while the block runs; raise
    :class:`FolderInUse`, naming ``what`` the folder holds, when another process holds it.

    The lock is an exclusive, non-blocking ``flock`` on ``out/.lock``: the operating system
    drops it when the holder ends, however it ends (Ctrl-C, a kill, a crash), so no stale
    lock outlives a run, and the file left behind means nothing by itself. It is advisory:
    it stops other runs of this project, not other programs. Where ``fcntl`` does not exist
    (Windows) runs are not locked."""
    try:
        import fcntl
    except ImportError:
        yield
        return
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / LOCK, "a") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise FolderInUse(f"another process is writing a {what} to {out} (it holds {out / LOCK}); wait for "
                              "it to end, or use another --out folder") from None
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
