"""The suite's scheduling: under pytest-xdist a test file runs whole on one worker (its
module fixtures made once; ``tests/conftest.py``, ``pytest_collection_modifyitems``)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
#: A file of quick unit tests, many of them.
SAMPLE = "tests/core/test_atomic.py"


@pytest.mark.slow  # a pytest run of its own, on two workers
def test_a_files_tests_run_on_one_worker():
    """Catches the grouping silently lost (pytest 9.2 with pytest-xdist 3.8: the group no
    longer reaches the scheduler, pytest-xdist#1386; or the conftest hook running after
    xdist's): every test then runs alone and the shared flights and module fixtures are
    made on both workers. Seen 2026-11-27: the wheel installed twice, the 20 clean
    calibration flights smoothed twice."""
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-n", "2", "--dist", "loadgroup", "-v",
         "-p", "no:cacheprovider", "-m", "not slow", SAMPLE],
        cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-2000:]
    workers = re.findall(r"^\[(gw\d+)\] .*PASSED .*$", done.stdout, re.M)
    assert len(workers) >= 4, done.stdout[-2000:]
    assert len(set(workers)) == 1, done.stdout[-2000:]


def test_a_worker_runs_one_blas_thread(request):
    """Under xdist, each worker (and the processes it starts) runs OpenBLAS on one thread
    (``tests/conftest.py``, ``pytest_configure``; 7-9% of the suite's CPU went to BLAS
    threads spinning while the workers held the cores). Catches the setting lost
    (mutation tried: the hook's body removed: the variable unset in the workers)."""
    if not hasattr(request.config, "workerinput"):
        pytest.skip("not under pytest-xdist: the one process keeps OpenBLAS's threads")
    assert os.environ.get("OPENBLAS_NUM_THREADS") is not None
