"""Append-only JSON Lines files: the records a long run writes as it goes (races,
episodes, evaluations), so that an interrupted run keeps them and can resume."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from experiments.files import replace_atomically


def read_jsonl(path: Path) -> list[dict[str, Any]]:
    """The records of ``path`` (none if it does not exist); a line cut by an interruption
    is skipped."""
    if not path.exists():
        return []
    records = []
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line:
            continue
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return records


def drop_cut_line(path: Path) -> None:
    """Remove an unfinished last line (one without its newline), which an interrupted
    write leaves behind, so that the next appended record starts on a line of its own."""
    if not path.exists():
        return
    data = path.read_bytes()
    if data and not data.endswith(b"\n"):
        # not in place: a kill while rewriting would truncate the records before the cut line
        replace_atomically(lambda partial: partial.write_bytes(data[: data.rfind(b"\n") + 1]), path)


def append_jsonl(path: Path, record: dict[str, Any]) -> None:
    """Append one record as a line and flush it."""
    with open(path, "a") as sink:
        sink.write(json.dumps(record) + "\n")


def settings_json(config: Any, added_later: tuple[str, ...] = ()) -> str:
    """A dataclass configuration as the JSON :func:`open_run_log` compares. The fields named
    in ``added_later`` are left out while at their defaults, so that a run written before
    they existed still resumes under the same settings."""
    settings = dataclasses.asdict(config)
    defaults = {field.name: field.default for field in dataclasses.fields(config)}
    for name in added_later:
        if settings[name] == defaults[name]:
            del settings[name]
    return json.dumps(settings, sort_keys=True)


def open_run_log(out: Path, log: str, settings_file: str, settings_json: str, fresh: bool,
                 what: str, outputs: tuple[str, ...] = ()) -> dict[str, dict[str, Any]]:
    """Prepare ``out`` for a resumable run that appends its records (each with an ``id``)
    to ``out/log``, and return the records already there by id.

    ``fresh`` discards them, and the files in ``out`` named in ``outputs`` (drawn from
    earlier records, e.g. a GIF, which would otherwise outlive them). Otherwise a log
    written under other settings (``settings_file`` holds those of the last run) is
    refused: its records would mix two ``what``s. A line cut by an interruption is
    dropped, so the next record starts on a line of its own. The settings file is replaced,
    never rewritten in place, so a kill leaves the old or the new one whole.
    """
    out.mkdir(parents=True, exist_ok=True)
    settings = out / settings_file
    if fresh:
        for name in (log, *outputs):
            (out / name).unlink(missing_ok=True)
    elif settings.exists() and settings.read_text() != settings_json and (out / log).exists():
        raise ValueError(f"{out} holds results of a different {what}; use another --out folder or --fresh "
                         "to start over")
    replace_atomically(lambda partial: partial.write_text(settings_json), settings)
    drop_cut_line(out / log)
    return {record["id"]: record for record in read_jsonl(out / log)}
