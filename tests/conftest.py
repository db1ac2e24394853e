"""Fixtures every test folder shares: the seed, the helpers of ``tests/support`` and the
simulated flights several files smooth (each made once per session).

Test files never import each other, this file or ``tests/support``: what they share comes
through the fixtures below (tests/README.md lists them).
"""

from __future__ import annotations

import importlib
import os
from typing import TYPE_CHECKING

import numpy as np
import pytest

if TYPE_CHECKING:
    from tests.support import flights as _flights


def _support(name: str):
    """``tests.support.<name>``, imported when a fixture first needs it: the helpers pull
    in the estimator, GTSAM and SciPy (2 s), which a run of light tests never pays (the
    scheduling check's own pytest run: tests/project/test_scheduling.py)."""
    return importlib.import_module(f"tests.support.{name}")

#: One seed for every random generator in the tests.
TEST_SEED = 20261121


@pytest.fixture(scope="session")
def seed() -> int:
    """The tests' one seed (:data:`TEST_SEED`); a second independent draw is ``seed + 1``."""
    return TEST_SEED


@pytest.fixture
def rng(seed: int) -> np.random.Generator:
    return np.random.default_rng(seed)


# --------------------------------------------------------------------------- helpers


@pytest.fixture(scope="session")
def manifold():
    """:mod:`tests.support.manifold`: central differences on the manifold, random rotations
    and mountings, a wavy terrain with an exact ray caster, a random C-DTM frame pair."""
    return _support("manifold")


@pytest.fixture(scope="session")
def sensor_files():
    """:mod:`tests.support.sensor_files`: EuRoC, Kalibr and ROS bag writers of a log."""
    return _support("sensor_files")


@pytest.fixture(scope="session")
def ulog_files():
    """:mod:`tests.support.ulog_files`: PX4 ULog files written from a simulated log."""
    return _support("ulog_files")


@pytest.fixture(scope="session")
def flightlog_files():
    """:mod:`tests.support.flightlogs`: the small log's builder and the line editing of
    the malformed-input tests (``expect_error`` asserts the one-line message)."""
    return _support("flightlogs")


@pytest.fixture(scope="session")
def live():
    """:mod:`tests.support.live`: a log fed to the live API frame by frame, each update's
    position NEES against the log's truth."""
    return _support("live")


@pytest.fixture(scope="session")
def synthetic():
    """:mod:`tests.support.synthetic`: a made-up smoother result, a smooth world DTM."""
    return _support("synthetic")


@pytest.fixture
def small_log(tmp_path, rng: np.random.Generator):
    """A small valid log (4 frames, 6 tracks, random values), written to tmp_path/log with
    its DTM (:func:`tests.support.flightlogs.make_log`)."""
    from cdtm_graph.flightlog import write_flightlog

    flightlogs = _support("flightlogs")
    the_log = flightlogs.make_log(tmp_path / "log", rng)
    write_flightlog(the_log, the_log.root)
    flightlogs.write_dtm(the_log.root / "dtm.npz")
    return the_log


# --------------------------------------------------------------------------- flights


@pytest.fixture(scope="session")
def nominal_log():
    """60 frames at 1 fps, ~1000 m above 300 m-relief fractal terrain, 30 m DTM. Seed 1:
    the literal is the point, the smoother tests quote this flight's measured figures
    (its ANEES 2.63 inside the band for independent frames, which other seeds may leave)."""
    from cdtm_graph.sim.simulate import SimulationSettings, simulate_flight

    return simulate_flight(SimulationSettings(frames=60, altitude_m=1000.0, relief_m=300.0, seed=1))


@pytest.fixture(scope="session")
def gross_outliers() -> _flights.GrossOutliers:
    """:func:`tests.support.flights.gross_outliers`: the innovation gate test's flight with
    2% of its observations moved 15-25 px (``clean``, ``corrupted``, ``bad``, ``dtm``)."""
    return _support("flights").gross_outliers()


@pytest.fixture(scope="session")
def nominal_runs(nominal_log) -> _flights.FlightRuns:
    """``nominal_log`` smoothed and judged with default settings, once per mode per session
    (``nominal_runs.run(Mode.BATCH)``): the smoother and incremental tests read the same
    runs."""
    return _support("flights").FlightRuns(nominal_log)


@pytest.fixture(scope="session")
def clean_flights() -> _flights.CleanFlights:
    """The clean flights of the robustness study's base flight, smoothed once per session
    and shared (:class:`tests.support.flights.CleanFlights`): ``clean_flights.run(seed,
    frames, mode)``. The calibration, verdict and consistency tests read the same runs."""
    return _support("flights").CleanFlights()


# --------------------------------------------------------------------------- scheduling


#: Session fixtures whose runs several files read (their files share an xdist worker).
SHARED_FIXTURES = ("clean_flights", "nominal_runs")


#: Test files that never call a numba kernel (a py-spy profile of the whole suite,
#: 2026-11-28). They go out right after the clean flights (:func:`_start_order`).
KERNEL_FREE = ("tests.frontend.test_frontend_real", "tests.plots.test_plots",
               "tests.project.test_layout", "tests.project.test_kernels",
               "tests.sim.test_trajectory", "tests.flightlog.test_flightlog",
               "tests.project.test_scheduling", "tests.cli.test_startup",
               "tests.core.test_atomic", "tests.core.test_geodesy", "tests.core.test_optimizer")
#: The longest file of its own (the robustness scenarios, 80-90 s of one worker).
LONGEST_FILE = "tests.robust.test_robustness"


def pytest_configure(config):
    """Under xdist, one BLAS thread in each worker (``OPENBLAS_NUM_THREADS``, unless set):
    the workers fill the cores already, and OpenBLAS's own threads spin while they wait
    for a core. Set here, in the controller, before it starts the workers (and their
    subprocesses inherit it). Measured 2026-11-28, the suite in turn with and without
    (2 cores): 234 and 221 s wall, 419 and 397 s CPU, against 247 and 243 s, 451 and
    439 s."""
    if getattr(config.option, "numprocesses", None) and not hasattr(config, "workerinput"):
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


@pytest.hookimpl(tryfirst=True)  # before xdist's, which reads the groups into node ids
def pytest_collection_modifyitems(config, items):
    """Keep work shared under pytest-xdist (``-n auto --dist loadgroup`` in pyproject.toml):
    each test file runs whole on one worker, so its module fixtures are made once, and the
    files that read one of :data:`SHARED_FIXTURES` run on one worker together, so its
    flights are smoothed once. Without xdist the groups are only labels. The groups go
    out in :func:`_start_order`."""
    group = {}
    for fixture in SHARED_FIXTURES:
        group.update({item.module.__name__: fixture for item in items
                      if fixture in item.fixturenames and item.module.__name__ not in group})
    for item in items:
        if item.get_closest_marker("xdist_group") is None:
            name = item.module.__name__
            item.add_marker(pytest.mark.xdist_group(group.get(name, name)))
    items.sort(key=lambda item: _start_order(item.module.__name__,
                                             group.get(item.module.__name__)))


def _start_order(module: str, group: str | None) -> int:
    """Where a file's group stands in the queue (``--no-loadscope-reorder``: xdist hands
    out the groups in collection order, two to each worker first; it used to order them by
    their count of tests).

    The clean flights first: the longest group, and where numba compiles (a platform
    without prebuilt kernels: :mod:`factors.jit`) its first test compiles the kernels
    every smoothing test needs. Then the files that call no kernel, about 30 s of the
    other worker's time: there, the other worker started compiling the same kernels at the
    same moment before (a cold run's compilation CPU that both workers spent on the same
    kernels: ~15 s -> 9.8 s, 2026-11-28). Then the longest file, so that it does not end
    the run on one worker. A file missing from the lists only runs later; nothing else
    depends on the order.
    """
    if group == "clean_flights":
        return 0
    if module in KERNEL_FREE:
        return 1
    return 2 if module == LONGEST_FILE else 3
