"""The data a real flight produces, with default settings, in every mode (issue 9).

Small versions of the robustness study's scenarios (:mod:`cdtm_graph.studies.
robustness`, the issue's 90-frame flight): wrong matches, terrain
the DTM lacks, a far initial fix, and one the terrain cannot resolve. Each run is judged
against the same flight without the fault, in the same mode. ``scripts/
robustness_matrix.py`` prints the full 90-frame table.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest

from cdtm_graph.results import Rejection
from cdtm_graph.run import RunOutput, smooth_and_evaluate
from cdtm_graph.smoother import SmootherSettings
from cdtm_graph.studies.robustness import BASE, SCENARIOS, Mode

#: Every test here smooths long flights or many: `-m "not slow"` leaves them out.
pytestmark = pytest.mark.slow

FRAMES = BASE.frames  # the flight
#: The issue's acceptance bounds.
MAX_ANEES = 6.0
WRONG_MATCH_RMSE_RATIO = 1.5
TERRAIN_RMSE_RATIO = 2.0
ACQUIRED_RMSE_RATIO = 1.5
#: NEES of one frame's position (3 dof) beyond which a covariance is not honest: the
#: chi-square(3) 99.9% point.
CHI2_3DOF_999 = 16.27

#: A flight whose fix is never found: the searches are its cost (about a second each: 3
#: searches by 20 s, 4 by 30 s, 5 by 90 s, each of them ``ambiguous`` in every mode and
#: every frame's NEES at most 1.0, measured 2026-11-27), and 20 s of waiting shows all it
#: shows (30 -> 20 s: 16.4 -> 10.1 s of the suite's CPU).
UNRESOLVED_FRAMES = 20


@functools.cache
def flight(scenario: str, frames: int = FRAMES):
    return SCENARIOS[scenario].flight(dataclasses.replace(BASE, frames=frames))


@functools.cache
def outcome(scenario: str, mode: Mode, frames: int = FRAMES) -> RunOutput:
    """The scenario smoothed in the mode with default settings (once per session)."""
    return smooth_and_evaluate(*flight(scenario, frames), mode.settings(SmootherSettings()))


def rmse_3d(out: RunOutput) -> float:
    assert out.errors is not None
    return float(out.errors.rmse_position_3d_m)


def anees(out: RunOutput) -> float:
    assert out.errors is not None and out.errors.anees_position is not None
    return float(out.errors.anees_position)


@pytest.mark.parametrize("mode", list(Mode), ids=lambda m: m.value)
def test_a_clean_flight_keeps_an_honest_covariance(mode):
    """Issue 9: clean flights ANEES between 1.2 and 4.5 with every defence on."""
    out = outcome("clean", mode)
    assert 1.2 <= anees(out) <= 4.5
    # the defences leave a clean flight nearly whole
    counts = out.result.counts
    assert counts.n_rejected() - counts.n_rejected(Rejection.MISSED_DTM) \
        < 0.02 * counts.n_cdtm_features


@pytest.mark.parametrize("mode", list(Mode), ids=lambda m: m.value)
@pytest.mark.parametrize("scenario", ["wrong15", "wrong30"])
def test_wrong_matches_are_left_out_before_they_pull(scenario, mode):
    """15% and 30% of the observations at a random pixel: RMSE within 1.5x the clean
    flight's, ANEES <= 6, and the wrong matches counted frame by frame."""
    out, clean = outcome(scenario, mode), outcome("clean", mode)
    assert rmse_3d(out) <= WRONG_MATCH_RMSE_RATIO * rmse_3d(clean)
    assert anees(out) <= MAX_ANEES
    wrong = out.result.counts.rejected_per_frame[Rejection.WRONG_MATCH.value]
    share = float(scenario.removeprefix("wrong")) / 100.0
    n_obs = out.result.counts.n_observations
    # each wrong observation spoils up to two pairs; most of them are caught
    assert wrong.sum() > 0.8 * share * n_obs
    assert np.count_nonzero(wrong[1:]) >= 0.9 * (FRAMES - 1)


@pytest.mark.parametrize("mode", list(Mode), ids=lambda m: m.value)
@pytest.mark.parametrize("scenario", ["pit", "blocks", "forest"])
def test_terrain_the_dtm_lacks_does_not_pull_the_estimate_along(scenario, mode):
    """A 40 m pit under the track, 15-30 m blocks on 15% of the ground, a 20% forest of
    15-25 m trees: RMSE within 2x the clean flight's and ANEES <= 6; the features on them
    are counted as map mismatches."""
    out, clean = outcome(scenario, mode), outcome("clean", mode)
    assert rmse_3d(out) <= TERRAIN_RMSE_RATIO * rmse_3d(clean)
    assert anees(out) <= MAX_ANEES
    assert out.result.counts.n_rejected(Rejection.MAP_MISMATCH) > 0


@pytest.mark.parametrize("mode", list(Mode), ids=lambda m: m.value)
def test_a_far_initial_fix_is_acquired(mode):
    """1000 m and 3 deg off with a matching sigma: the smoother searches first, its first
    frames' features held, then smooths as from a clean prior."""
    out, clean = outcome("far1000", mode), outcome("clean", mode)
    searches = out.result.settings["acquisitions"]
    assert searches and searches[-1]["verdict"] == "acquired"
    assert rmse_3d(out) <= ACQUIRED_RMSE_RATIO * rmse_3d(clean)
    assert anees(out) <= MAX_ANEES
    assert not any("no_fix" in flags for flags in out.result.flags.values())


@pytest.mark.parametrize("mode", list(Mode), ids=lambda m: m.value)
def test_a_fix_the_terrain_cannot_resolve_is_never_claimed(mode):
    """The same 1000 m error over terrain that repeats every 3 km: copies of the true fix
    lie within the prior. The search says so, the features wait (flagged, counted), and
    no frame has a small covariance on a far estimate (20 s of it, three searches: issue
    20, 9.5 -> 3.5 s a mode). Mutation: the search's rivals ignored (``rivals = []``:
    ``acquired`` on a copy) fails the first assertion."""
    out = outcome("far1000_periodic", mode, UNRESOLVED_FRAMES)
    searches = out.result.settings["acquisitions"]
    assert searches and all(s["verdict"] != "acquired" for s in searches)
    result = out.result
    assert all("no_fix" in result.flags.get(k, []) for k in range(UNRESOLVED_FRAMES))
    assert result.counts.n_rejected(Rejection.NO_FIX) > 0
    assert out.errors is not None
    nees = out.errors.position_nees
    assert nees is not None
    assert np.all(nees[np.isfinite(nees)] < CHI2_3DOF_999)
