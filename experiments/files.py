"""Safe writes to a run's output folder.

- Files written whole or not at all (:func:`replace_atomically`): a reader, or a run
  interrupted mid-write, finds the old file or the new one, never half of one; a Ctrl-C
  during the write is held until the file is in place (:func:`interrupts_held`), so the
  run stops as interrupted, not with the error of a writer cut in half.
- One writer per folder (:func:`one_writer`): the resumable runs (tournaments, sweeps,
  trainings, exploitability studies) append to the files in their ``--out`` folder and
  resume from what those hold, so two runs writing one folder at once would interleave
  their records (the same race twice, one run's checkpoint resumed by the other). The second
  run is refused at once instead.
"""

from __future__ import annotations

import contextlib
import json
import signal
import threading
from pathlib import Path
from typing import Any, Callable, Iterator

LOCK = ".lock"
"""The file in an output folder that a run writing there holds locked."""


@contextlib.contextmanager
def interrupts_held() -> Iterator[None]:
    """Hold Ctrl-C (SIGINT) while the block runs, then act on it: the handler that was in
    place runs once the block has ended (Python's raises ``KeyboardInterrupt`` there).

    A ``KeyboardInterrupt`` raised inside a writer (``zipfile``, ``numpy.savez``) can leave
    it half closed, and the error its cleanup then raises replaces the interrupt. Outside
    the main thread (where signal handlers cannot be set), or where SIGINT's handler was not
    set from Python (it could not be put back), the block runs as it is."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) is None:
        yield
        return
    caught: list[Any] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(frame))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if caught and callable(previous):
        previous(signal.SIGINT, caught[0])
    elif caught and previous == signal.SIG_DFL:
        raise KeyboardInterrupt


def replace_atomically(write: Callable[[Path], Any], path: Path) -> None:
    """``write(partial)`` to ``path`` + ``.partial`` in the same folder, then rename it onto
    ``path``, so a reader (or an interrupted run) never finds a half-written file: the old
    one stays. A Ctrl-C meanwhile takes effect once the file is in place
    (:func:`interrupts_held`)."""
    partial = path.with_name(path.name + ".partial")
    with interrupts_held():
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
