"""Monte Carlo consistency of the smoothers with every default defence on: a test that
rejects a covariance 0.67x or 1.5x too large, shown inside the test by scaling it.

The unit is one run. A run's frames are correlated over tens of frames, so its NEES are
not independent draws; but each frame's NEES has mean 3 (chi-square(3)) when the
covariance is honest, whatever the correlation, and so has the run's mean, its ANEES.
Independent seeds give independent ANEES: their mean over the seeds is tested against 3
with Student's t (seeds - 1 dof, two-sided, ``CONFIDENCE``). A covariance scaled by ``s``
divides every NEES by ``s``. The t test on a handful of skewed ANEES is approximate; the
spread it uses is measured, not assumed (a run of 30 frames holds about 2 independent
frames' worth: per-run ANEES spread 0.55 of their mean).

The per-flight decision the product prints (:func:`cdtm_graph.verdict.evaluation.
covariance_verdict`, per-frame NEES against chi-square(3)) is a hint on one flight; this
is the test over many flights that docs/verdict.md points to. The runs are the shared
clean flights (``clean_flights``): batch seeds 1-20 (read by the calibration and verdict
tests too), iSAM2 and fixed lag seeds 1-8.

Measured 2026-11-27 (mean ANEES over the seeds; t at scales 0.67 / 1 / 1.5):
batch (20) 2.04, t +0.11 / -3.36 / -8.61; iSAM2 (8) 2.30, +0.70 / -1.70 / -5.34;
fixed lag (8) 2.19, +0.40 / -1.77 / -5.05. Every mode is pessimistic by ~1.35-1.47 in
NEES (1.16-1.21 in sigma): the batch's 20 seeds reject the covariance as it is, and no
mode's seeds can reject 0.67x, which would read ANEES 3.05-3.43. Those cases are strict
xfails (docs/verdict.md, "The Monte Carlo consistency test").
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import stdtrit

from cdtm_graph.studies.robustness import Mode
from cdtm_graph.verdict.evaluation import POSITION_DOF

#: Every test here smooths many flights: `-m "not slow"` leaves them out.
pytestmark = pytest.mark.slow

#: The shared clean flights: the batch's are read by the calibration and verdict tests.
SEEDS = {Mode.BATCH: range(1, 21), Mode.ISAM2: range(1, 9), Mode.FIXED_LAG: range(1, 9)}
FRAMES = 30
#: two-sided probability of the t test's acceptance region
CONFIDENCE = 0.99
#: the scales it must reject (build 7 of issue 21)
TOO_SMALL, TOO_LARGE = 0.67, 1.5

PESSIMISTIC = ("covariances pessimistic by ~1.35-1.47 in NEES in every mode (mean ANEES "
               "2.04 batch over 20 seeds, 2.30 iSAM2, 2.19 fixed lag over 8, against 3), "
               "measured 2026-11-27; mostly the pixel noise of each pair's first sighting, "
               "which telescopes along a track while the pair factors count it apart "
               "(docs/verdict.md, 'The pessimism split by noise source')")


def _t(anees_per_run: np.ndarray, scale: float) -> float:
    """Student's t of the runs' mean ANEES against chi-square(3)'s mean, for the
    covariance scaled by ``scale`` (every NEES divided by it)."""
    x = anees_per_run / scale
    return float((x.mean() - POSITION_DOF) / (x.std(ddof=1) / np.sqrt(x.size)))


def _rejected(anees_per_run: np.ndarray, scale: float) -> bool:
    bound = stdtrit(anees_per_run.size - 1, (1 + CONFIDENCE) / 2)  # Student t quantile
    return abs(_t(anees_per_run, scale)) > bound


@pytest.fixture(scope="module")
def anees(clean_flights) -> dict[Mode, np.ndarray]:
    """Each mode's per-run position ANEES over its seeds (runs shared, read only)."""
    return {mode: np.array([run.errors.anees_position
                            for run in clean_flights.runs_of(SEEDS[mode], FRAMES, mode)])
            for mode in Mode}


def _xfail(*modes: Mode, reason: str):
    return [pytest.param(m, marks=pytest.mark.xfail(strict=True, reason=reason))
            if m in modes else m for m in Mode]


@pytest.mark.parametrize("mode", _xfail(Mode.BATCH, reason=(
    "batch over 20 seeds: t = -3.36 beyond -2.86 (99%): " + PESSIMISTIC)),
    ids=lambda m: m.value)
def test_the_covariance_as_reported_is_accepted(anees, mode):
    """The covariances as the smoother reports them: the runs' mean ANEES is 3 within the
    t bound. The mutation is the scaling below: grown 1.5x, the same runs are rejected in
    every mode; shrunk to 0.67x they are not yet (strict xfail: the reported covariances
    are ~1.4x pessimistic, and the batch's 20 seeds reject them as they are)."""
    assert not _rejected(anees[mode], 1.0), (anees[mode].mean(), _t(anees[mode], 1.0))


@pytest.mark.parametrize("mode", list(Mode), ids=lambda m: m.value)
def test_a_covariance_too_large_by_1_5_is_rejected(anees, mode):
    """The same covariances scaled by 1.5 (mean ANEES 1.36-1.53 measured): rejected.
    Mutation: a test whose bound passes anything (the previous middle-frame chi-square sum
    passed scales 0.32-1.56, the fixed lag's covariances halved included)."""
    assert _rejected(anees[mode], TOO_LARGE), (anees[mode].mean() / TOO_LARGE,
                                                _t(anees[mode], TOO_LARGE))


@pytest.mark.parametrize("mode", _xfail(*Mode, reason=(
    "0.67x reads mean ANEES 3.05-3.43, t +0.11..+0.70: " + PESSIMISTIC)),
    ids=lambda m: m.value)
def test_a_covariance_too_small_by_0_67_is_rejected(anees, mode):
    """The same covariances scaled by 0.67 (optimistic by 1.5 in NEES): rejected. Fails
    today in every mode (strict xfail): the reported covariances are ~1.4x pessimistic,
    so 0.67x of them is about honest."""
    assert _rejected(anees[mode], TOO_SMALL), (anees[mode].mean() / TOO_SMALL,
                                                _t(anees[mode], TOO_SMALL))
