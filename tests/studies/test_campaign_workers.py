"""The campaign's local worker processes (opnav.studies.campaign_workers): addressed, keeping, failing."""

import os

import pytest

from opnav.studies.campaign_workers import LocalWorkers, keep, kept


def _all(pool):
    """Every result of the tasks running on ``pool``, by worker."""
    out = {}
    while pool.busy:
        out.update(pool.wait())
    return out


def test_each_task_runs_on_the_worker_it_is_sent_to_which_keeps_values_between_tasks():
    pool = LocalWorkers(2)
    try:
        assert pool.free() == [0, 1]
        for worker in (0, 1):
            pool.send(worker, os.getpid)
        assert pool.free() == []
        pids = _all(pool)
        assert pids[0] != pids[1] and os.getpid() not in pids.values()
        pool.send(0, keep, "sim", [1.5, 2.5])
        _all(pool)
        pool.send(1, kept, "sim")  # the other worker does not have it
        pool.send(0, os.getpid)
        answers = _all(pool)
        assert answers == {1: None, 0: pids[0]}
        pool.send(0, kept, "sim")
        assert _all(pool) == {0: [1.5, 2.5]}
        pool.send(0, kept, "sim")  # forgotten once taken
        assert _all(pool) == {0: None}
    finally:
        pool.close()


def test_a_tasks_exception_is_raised_in_the_campaign_and_the_worker_goes_on():
    pool = LocalWorkers(1)
    try:
        pool.send(0, int, "not a number")
        with pytest.raises(ValueError, match="not a number"):
            pool.wait()
        pool.send(0, int, "12")
        assert pool.wait() == [(0, 12)]
    finally:
        pool.close(cancel=True)
