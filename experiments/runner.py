"""The resumable job loop of tournaments and sweeps.

A run is a fixed schedule of jobs, each a dict with a unique ``id``. Their records go to
``out/results.jsonl`` (one line each, appended as the jobs end), so an interrupted run keeps
what is done; run again with the same settings, it skips the jobs already recorded and runs
the rest on a backend (:func:`experiments.backends.run_jobs`: this process, local worker
processes or a Ray cluster). The records are read back in schedule order, so what is built
from them does not depend on the backend, the number of workers or interruptions.

A job's record may carry its race's :class:`experiments.replay.Replay` under ``"replay"``:
it is written to ``out/replays`` before the record's line (so a recorded race always has
its replay), and the line says ``"race": K`` (the job's index in the schedule) and
``"replay"``: the file's path relative to ``out``.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any, Callable, Iterable

from experiments.backends import run_jobs
from experiments.jsonl import append_jsonl, open_run_log
from experiments.replay import REPLAYS, replay_file, save_replay


class JobLog:
    """The records of a resumable run's jobs, by id, in ``out/log``.

    Opening it prepares ``out`` (:func:`experiments.jsonl.open_run_log`): ``fresh``
    discards earlier records and the files named in ``outputs``; otherwise records written
    under other ``settings`` (JSON, kept in ``out/settings_file``) are refused, naming the
    ``what`` they belong to.
    """

    def __init__(self, out: Path, jobs: Iterable[dict[str, Any]], *, log: str, settings_file: str,
                 settings: str, what: str, fresh: bool = False, outputs: tuple[str, ...] = ()) -> None:
        self.out = out
        self.path = out / log
        self.jobs = list(jobs)
        self._index = {job["id"]: k for k, job in enumerate(self.jobs)}
        if fresh:
            shutil.rmtree(out / REPLAYS, ignore_errors=True)
        self.done = open_run_log(out, log, settings_file, settings, fresh, what, outputs=outputs)

    @property
    def todo(self) -> list[dict[str, Any]]:
        """The scheduled jobs not recorded yet, in schedule order."""
        return [job for job in self.jobs if job["id"] not in self.done]

    def announce(self, console: Any) -> None:
        """Print how much of the run an earlier one did (nothing for a new run)."""
        if self.done:
            console.print(f"resuming: {len(self.done)} of {len(self.jobs)} races already in {self.path}")

    def add(self, record: dict[str, Any]) -> None:
        """Append a job's record (it carries the job's ``id``) and count it as done; its
        replay, if it carries one, is written first."""
        replay = record.pop("replay", None)
        if replay is not None:
            race = self._index[record["id"]]
            replay.race, replay.id = race, record["id"]
            save_replay(replay, self.out / replay_file(race))
            record = {**record, "race": race, "replay": replay_file(race)}
        append_jsonl(self.path, record)
        self.done[record["id"]] = record

    def _record(self, record: dict[str, Any], bar: Any, on_record: Callable[[dict[str, Any]], None] | None) -> None:
        self.add(record)
        bar.update(1)
        if on_record is not None:
            on_record(record)

    def records(self) -> list[dict[str, Any]]:
        """The recorded jobs' records in schedule order."""
        return [self.done[job["id"]] for job in self.jobs if job["id"] in self.done]

    def run(self, function: Callable[[dict[str, Any]], dict[str, Any]], backend: str = "local", workers: int = 1,
            address: str | None = None, progress: bool = True, desc: str = "jobs",
            here_first: Callable[[dict[str, Any]], dict[str, Any]] | None = None,
            on_record: Callable[[dict[str, Any]], None] | None = None) -> bool:
        """Run the jobs still to do, recording each as it ends, with a progress bar; returns
        whether Ctrl-C stopped the run (what was done is kept, the backend's workers are
        stopped).

        ``function(job)`` makes a job's record on the backend (it must be importable by name:
        :func:`experiments.backends.run_jobs`). ``here_first``: the first job to do runs in
        this process through this function instead (e.g. one that also draws the race).
        ``on_record(record)`` is called after each record is written.
        """
        from tqdm import tqdm

        todo = self.todo
        with tqdm(total=len(todo), desc=desc, disable=not progress) as bar:
            try:
                if here_first is not None and todo:
                    self._record(here_first(todo[0]), bar, on_record)
                    todo = todo[1:]
                records = run_jobs(function, todo, backend, workers, address)
                try:
                    for record in records:
                        self._record(record, bar, on_record)
                finally:
                    records.close()  # at an interruption: stops the workers or the Ray tasks
            except KeyboardInterrupt:
                return True
        return False
