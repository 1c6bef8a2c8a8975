"""Files written whole or not at all: a reader, or a run interrupted mid-write, finds the
old file or the new one, never half of one."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable


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
