"""experiments.backends: worker processes are recycled after their share of jobs, and a process
holding too many memory maps lets go of its compiled programs."""

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


def test_a_process_over_its_map_budget_lets_go_of_its_compiled_programs():
    import jax
    import jax.numpy as jnp

    from experiments.backends import _released_after

    @jax.jit
    def double(x):
        return 2 * x

    double(jnp.ones(3))
    assert _released_after("result", budget=10**9) == "result" and double._cache_size() == 1
    assert _released_after("result", budget=0) == "result" and double._cache_size() == 0
