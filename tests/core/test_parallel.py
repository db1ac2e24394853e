"""Parallel task runner: order, errors, and the same numbers on any backend or worker count."""

from __future__ import annotations

import dataclasses
import math
import sys

import numpy as np
import pytest

from cdtm_graph import parallel
from cdtm_graph.errors import CdtmError
from cdtm_graph.parallel import ParallelBackend, ParallelSettings, map_tasks
from cdtm_graph.studies.sweeps import StudyParameter, StudySettings, run_study

#: A small study: two values, trials on two terrains, several tasks per worker.
SMALL = StudySettings(StudyParameter.BASELINE, values=(20.0, 60.0), trials=6,
                      trials_per_terrain=3)


@pytest.fixture(scope="module")
def small(seed: int) -> StudySettings:
    return dataclasses.replace(SMALL, seed=seed)


def _numbers(result) -> np.ndarray:
    rows = np.array([r.as_tuple() for r in result.rows], dtype=float)
    per_trial = np.concatenate([np.c_[o.pred_var, o.sq_err, o.nees] for o in result.outcomes])
    return np.concatenate([rows.ravel(), per_trial.ravel()])


@pytest.fixture(scope="module")
def serial_numbers(small) -> np.ndarray:
    return _numbers(run_study(small, ParallelSettings(workers=1)))


def test_results_come_back_in_task_order():
    tasks = list(range(40, 0, -1))
    assert map_tasks(math.factorial, tasks, ParallelSettings(workers=2)) == [
        math.factorial(n) for n in tasks]


def test_backend_follows_the_settings():
    assert ParallelSettings(workers=1).backend is ParallelBackend.SERIAL
    assert ParallelSettings(workers=3).backend is ParallelBackend.PROCESSES
    assert ParallelSettings(workers=1, scheduler_address="tcp://h:1").backend is \
        ParallelBackend.DASK
    assert ParallelSettings().n_local_workers() == parallel.available_cores()


@pytest.mark.parametrize("workers", [0, -1, 1.5, True])
def test_bad_worker_counts_are_user_errors(workers):
    with pytest.raises(CdtmError):
        ParallelSettings(workers=workers)


def test_a_task_error_reaches_the_caller():
    with pytest.raises(ValueError):
        map_tasks(math.sqrt, [4.0, -1.0, 9.0], ParallelSettings(workers=2))


@pytest.mark.slow
def test_two_workers_give_the_same_numbers_as_one(small, serial_numbers):
    numbers = _numbers(run_study(small, ParallelSettings(workers=2)))
    np.testing.assert_array_equal(numbers, serial_numbers)
    assert np.isfinite(serial_numbers).all()  # the comparison compared real numbers


@pytest.mark.slow
def test_dask_cluster_gives_the_same_numbers(small, serial_numbers):
    distributed = pytest.importorskip("dask.distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  host="127.0.0.1", dashboard_address=None) as cluster:
        result = run_study(small, ParallelSettings(scheduler_address=cluster.scheduler_address))
    np.testing.assert_array_equal(_numbers(result), serial_numbers)


def test_scheduler_without_dask_is_a_clear_user_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "dask.distributed", None)  # import fails
    with pytest.raises(CdtmError, match="dask"):
        map_tasks(abs, [1], ParallelSettings(scheduler_address="tcp://127.0.0.1:1"))


def test_unreachable_scheduler_is_a_clear_user_error(monkeypatch):
    pytest.importorskip("dask.distributed")
    monkeypatch.setattr(parallel, "DASK_CONNECT_TIMEOUT_S", 0.5)
    with pytest.raises(CdtmError, match="cannot reach"):
        map_tasks(abs, [1], ParallelSettings(scheduler_address="tcp://127.0.0.1:9"))
