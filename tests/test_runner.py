"""The resumable job loop of tournaments and sweeps (experiments.runner.JobLog)."""

from __future__ import annotations

import json

import pytest

from experiments.runner import JobLog

JOBS = [{"id": f"job{k}", "value": k} for k in range(5)]


def square(job):
    return {"id": job["id"], "square": job["value"] ** 2}


def _open(out, fresh=False, settings="{}"):
    return JobLog(out, JOBS, log="results.jsonl", settings_file="settings.json", settings=settings,
                  what="test run", fresh=fresh, outputs=("drawing.txt",))


class Console:
    def __init__(self):
        self.lines = []

    def print(self, text):
        self.lines.append(text)


def test_jobs_run_once_and_a_rerun_skips_what_is_recorded(tmp_path):
    log = _open(tmp_path)
    assert log.todo == JOBS and log.run(square, progress=False) is False
    assert log.records() == [square(job) for job in JOBS]
    again = _open(tmp_path)
    console = Console()
    again.announce(console)
    assert again.todo == [] and console.lines == [f"resuming: 5 of 5 races already in {tmp_path / 'results.jsonl'}"]
    assert again.run(lambda job: pytest.fail("ran a recorded job"), progress=False) is False
    assert len((tmp_path / "results.jsonl").read_text().splitlines()) == 5


def test_ctrl_c_keeps_the_records_so_far_and_the_rerun_does_the_rest(tmp_path):
    calls = []

    def interrupted_at_the_third(job):
        calls.append(job["id"])
        if len(calls) == 3:
            raise KeyboardInterrupt
        return square(job)

    log = _open(tmp_path)
    assert log.run(interrupted_at_the_third, progress=False) is True
    assert [r["id"] for r in log.records()] == ["job0", "job1"]
    resumed = _open(tmp_path)
    assert [job["id"] for job in resumed.todo] == ["job2", "job3", "job4"]
    assert resumed.run(square, progress=False) is False
    assert resumed.records() == [square(job) for job in JOBS]


def test_the_first_job_can_run_here_and_records_come_back_in_schedule_order(tmp_path):
    here = []

    def drawn(job):
        here.append(job["id"])
        (tmp_path / "drawing.txt").write_text(job["id"])
        return square(job)

    log = _open(tmp_path)
    log.run(square, progress=False, here_first=drawn)
    assert here == ["job0"] and log.records() == [square(job) for job in JOBS]
    fresh = _open(tmp_path, fresh=True)  # discards the records and the outputs drawn from them
    assert fresh.todo == JOBS and not (tmp_path / "drawing.txt").exists()


def test_records_of_other_settings_are_refused(tmp_path):
    _open(tmp_path).run(square, progress=False)
    with pytest.raises(ValueError, match="different test run"):
        _open(tmp_path, settings=json.dumps({"other": 1}))
