"""`racing study run`: one declared study of several sweeps, raced as one resumable run.

A study is a TOML file: a name, a question, and parts, each a sweep in the format of
``racing sweep`` (:mod:`experiments.sweep`: a ``lineup``, the race's settings, ``grids``,
``seed`` and a ``parameters`` table) with a name of its own. A ``[shared]`` table holds the
settings every part starts from (a part's own keys, and its own parameters, win)::

    name = "outlook"
    question = "Open loop or feedback, on every circuit, under the racing rules?"

    [shared]
    laps = 1
    [shared.parameters]
    car = ["av21", "paper"]

    [[part]]
    name = "duel-fb-ol"
    lineup = ["ilqgame-fb", "ilqgame-ol"]
    grids = 1
    [part.parameters]
    track = ["Monza", "Spa"]
    car = ["av21", "paper"]

    [[part]]
    name = "fields"
    lineup = ["ilqgame-fb*2", "ilqgame-ol*2", "raceline*2"]
    grids = 2
    [part.parameters]
    track = ["Monza"]

Each part then races every combination of its parameters (here the duels: 2 circuits x 2
cars, once per starting slot; the fields: one per grid and car).

Every race of every part is one job (:func:`schedule`: a part's own schedule, its ids
prefixed by the part's name); the study runs them as one resumable run
(:class:`experiments.runner.JobLog`: ``results.jsonl`` appended as races end, a rerun
skips the races recorded, one progress bar with the time left over the whole study) on
this process, local worker processes or a Ray cluster. Each record is the part's sweep
record (:func:`experiments.sweep.run_job`) with its ``part``. The parts' summaries
(:func:`experiments.sweep.summarize`) go to ``summary.json``, in schedule order, so they
do not depend on the backend, the number of workers or interruptions.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import re
import sys
import time
from pathlib import Path
from typing import Any

from experiments.backends import check_backend
from experiments.files import one_writer, replace_atomically
from experiments.jsonl import settings_json
from experiments.runner import JobLog
from experiments.sweep import ADDED_LATER, SweepConfig, flatten_parameters, run_job, summarize, sweep_from_table

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

RESULTS = "results.jsonl"
CONFIG = "study.json"
SUMMARY = "summary.json"
RUN_LOG = "run.json"  # each invocation of the run: commit, machine, start, seconds, races run
STUDY_KEYS = ("name", "question", "shared", "part")
PART_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")  # a part's name: a folder-safe word, no "/"


@dataclasses.dataclass(frozen=True)
class StudyConfig:
    """A study: its ``name``, its ``question`` and its ``parts``, ``(name, sweep)`` pairs in
    the file's order, with distinct names."""

    name: str
    question: str
    parts: tuple[tuple[str, SweepConfig], ...]

    def __post_init__(self) -> None:
        self.check_title(self.name, self.question)
        if not self.parts:
            raise ValueError("a study needs at least one [[part]]")
        names = [name for name, _ in self.parts]
        for name in names:
            if not isinstance(name, str) or not PART_NAME.fullmatch(name):
                raise ValueError(f"a part's name is a word of letters, digits, '_', '-' or '.', got {name!r}")
        repeated = sorted({name for name in names if names.count(name) > 1})
        if repeated:
            raise ValueError(f"part names must be distinct; repeated: {repeated}")

    @staticmethod
    def check_title(name: Any, question: Any) -> None:
        """Refuse a study's name that is not a word (it names the default output folder) and
        a missing or empty question."""
        if not isinstance(name, str) or not PART_NAME.fullmatch(name):
            raise ValueError(f"a study's name is a word of letters, digits, '_', '-' or '.', got {name!r}")
        if not isinstance(question, str) or not question.strip():
            raise ValueError("a study needs its question, a non-empty string")

    def part(self, name: str) -> SweepConfig:
        """The sweep of the part named ``name``."""
        return dict(self.parts)[name]

    def schedule(self) -> list[dict[str, Any]]:
        """Every race of the study in a fixed order (:func:`schedule`)."""
        return schedule(self)


def schedule(study: StudyConfig) -> list[dict[str, Any]]:
    """Every race of every part, part after part in the file's order, each part's in its
    sweep's order (:func:`experiments.sweep.schedule`): the sweep's job with ``part`` and the
    id ``"<part>/<the sweep's id>"``."""
    return [{**job, "id": f"{name}/{job['id']}", "part": name}
            for name, sweep in study.parts for job in sweep.schedule()]


def load_study(path: str | Path) -> StudyConfig:
    """Read a study TOML file (module docstring).

    Raises:
        ValueError: not TOML, an unknown key, a part that is not a sweep (the sweep's own
            message, naming the part), a missing name or question.
    """
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"no study file {str(path)!r}") from None
    except tomllib.TOMLDecodeError as err:
        raise ValueError(f"{path} is not valid TOML: {err}") from None
    unknown = sorted(set(data) - set(STUDY_KEYS))
    if unknown:
        raise ValueError(f"{path}: unknown keys {unknown}; a study file has {list(STUDY_KEYS)} "
                         "(each [[part]] a sweep with a name)")
    StudyConfig.check_title(data.get("name"), data.get("question"))
    tables = data.get("part", [])
    if not isinstance(tables, list) or not all(isinstance(table, dict) for table in tables):
        raise ValueError(f"{path}: parts are [[part]] tables, got {tables!r}")
    shared = data.get("shared", {})
    if not isinstance(shared, dict) or not isinstance(shared.get("parameters", {}), dict) or "name" in shared:
        raise ValueError(f"{path}: [shared] is a table of sweep settings (no name), its parameters a table")
    parts = []
    for index, table in enumerate(tables):
        name = table.get("name")
        where = f"{path}, part {name!r}" if isinstance(name, str) else f"{path}, part {index + 1}"
        if name is None:
            raise ValueError(f"{where}: a part needs a name")
        own = {k: v for k, v in table.items() if k != "name"}
        merged = {**shared, **own}
        if not isinstance(own.get("parameters", {}), dict):
            raise ValueError(f"{where}: parameters must be a table ([part.parameters]), got {own['parameters']!r}")
        parameters = {**flatten_parameters(path, shared.get("parameters", {})),
                      **flatten_parameters(where, own.get("parameters", {}))}
        if parameters:
            merged["parameters"] = parameters
        parts.append((name, sweep_from_table(merged, where)))
    return StudyConfig(name=data.get("name"), question=data.get("question"), parts=tuple(parts))


def _settings(study: StudyConfig) -> str:
    """The study's settings as the JSON a resumed run compares (each part's as its sweep's)."""
    parts = {name: json.loads(settings_json(sweep, sweep.added_later(ADDED_LATER))) for name, sweep in study.parts}
    return json.dumps({"name": study.name, "question": study.question, "parts": parts}, sort_keys=True)


def run_study_job(study: StudyConfig, job: dict[str, Any]) -> dict[str, Any]:
    """Race one job of the study: its part's sweep record (:func:`experiments.sweep.run_job`)."""
    return run_job(study.part(job["part"]), job)


def summarize_study(study: StudyConfig, records: list[dict[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    """Per part, its sweep's summary (:func:`experiments.sweep.summarize`) of its records (each
    under its id in the sweep: the study's without ``"<part>/"``)."""
    return {name: summarize(sweep, [{**r, "id": r["id"].split("/", 1)[1]} for r in records if r["part"] == name])
            for name, sweep in study.parts}


def source_commit() -> str | None:
    """The commit of the code that runs (``git describe --always --dirty`` of the package's
    checkout; None outside a git checkout)."""
    import subprocess

    root = Path(__file__).resolve().parents[1]
    try:
        done = subprocess.run(["git", "describe", "--always", "--dirty", "--abbrev=7"], cwd=root,
                              capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return (done.stdout.strip() or None) if done.returncode == 0 else None


class _Invocation:
    """This invocation's entry in ``out/run.json`` (what a page says the study ran on): its
    start, commit and machine, and the seconds and races so far, rewritten after every race
    so that a run killed without clean-up still leaves the time of the races it recorded."""

    def __init__(self, out: Path, backend: str, workers: int) -> None:
        import datetime
        import os

        from experiments.bench import cpu_model

        self.path, self.started = out / RUN_LOG, time.time()
        self.log = json.loads(self.path.read_text()) if self.path.exists() else {"invocations": []}
        self.entry = {
            "started": datetime.datetime.fromtimestamp(self.started, datetime.timezone.utc).isoformat(timespec="seconds"),
            "seconds": 0.0, "races": 0, "commit": source_commit(), "cpu": cpu_model(),
            "cpu_count": os.cpu_count(), "backend": backend, "workers": workers}
        self.log["invocations"].append(self.entry)
        self._write()

    def update(self, races: int) -> None:
        """Record ``races`` done so far by this invocation and the seconds since it started."""
        self.entry.update(seconds=round(time.time() - self.started, 1), races=races)
        self._write()

    def _write(self) -> None:
        replace_atomically(lambda partial: partial.write_text(json.dumps(self.log, indent=1)), self.path)


def run_study(study: StudyConfig, out: Path, backend: str = "local", workers: int = 1, address: str | None = None,
              fresh: bool = False, progress: bool = True) -> dict[str, Any]:
    """Run (or resume) a study into ``out``; returns ``{"races": done, "scheduled": total,
    "interrupted": bool, "parts": summaries}`` and writes ``results.jsonl`` (one record per
    race), ``study.json`` (its settings), ``summary.json``, ``run.json`` (each invocation's
    commit, machine, start, seconds and races) and every race's replay in ``replays/``.

    Raises:
        ValueError: a bad backend, an agent spec or race the parts cannot make, or ``out``
            holding another study's races (unless ``fresh``).
    """
    from rich.console import Console

    from planners.agents import check_specs
    from racing_env.env import RacingParallelEnv

    check_backend(backend, workers)
    for _, sweep in study.parts:  # every spec and race made once before the first race
        check_specs(sweep.specs)
        for point in sweep.points():
            RacingParallelEnv(sweep.race_config(point, rotation=0))
    console = Console(stderr=True, width=160)
    with one_writer(out, "study"):
        log = JobLog(out, schedule(study), log=RESULTS, settings_file=CONFIG, settings=_settings(study),
                     what="study", fresh=fresh, outputs=(SUMMARY,))
        log.announce(console)
        invocation, done_before = _Invocation(out, backend, workers), len(log.done)
        interrupted = log.run(functools.partial(run_study_job, study), backend, workers, address, progress=progress,
                              desc=study.name, on_record=lambda _: invocation.update(len(log.done) - done_before))
        invocation.update(len(log.done) - done_before)
        records = log.records()
        parts = summarize_study(study, records)
        summary = {"study": study.name, "races": len(records), "scheduled": len(log.jobs), "parts": parts}
        replace_atomically(lambda partial: partial.write_text(json.dumps(summary, indent=1)), out / SUMMARY)
    if interrupted:
        console.print(f"interrupted: {len(log.done)} of {len(log.jobs)} races in {out / RESULTS}; run the same "
                      "command to resume")
    else:
        console.print(f"{len(records)} races of {len(log.jobs)} in {out / RESULTS}; summaries in {out / SUMMARY}")
    return {"races": len(records), "scheduled": len(log.jobs), "interrupted": interrupted, "parts": parts}
