"""experiments.backends: worker processes are recycled after their share of jobs."""

from __future__ import annotations

import os

import pytest

from experiments.backends import run_jobs


def _job_and_worker(job: int) -> tuple[int, int]:
    return job, os.getpid()


def test_a_worker_runs_at_most_its_share_of_jobs_before_a_fresh_one_replaces_it():
    results = sorted(run_jobs(_job_and_worker, range(4), workers=2, jobs_per_worker=1))
    assert [job for job, _ in results] == [0, 1, 2, 3]
    assert len({pid for _, pid in results}) == 4 and os.getpid() not in {pid for _, pid in results}


@pytest.mark.parametrize("share", [0, 1.5])
def test_a_share_of_jobs_below_one_or_not_whole_is_refused(share):
    with pytest.raises(ValueError, match="jobs_per_worker must be an integer >= 1"):
        run_jobs(_job_and_worker, range(2), workers=2, jobs_per_worker=share)
