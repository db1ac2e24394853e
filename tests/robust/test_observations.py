"""The full history's tiered record of observations answers as the one-run record does."""

from __future__ import annotations

import numpy as np
import pytest

from cdtm_graph.robust.observations import TieredObservations
from cdtm_graph.tracks import TrackObservations


@pytest.mark.parametrize("fold_rows", [1, 7, 40, 10**6])
def test_tiered_record_answers_as_one_run(rng, fold_rows):
    """Against :class:`TrackObservations` (itself checked against a plain record in
    tests/core/test_tracks.py), folding every row, every few frames or never: random
    frames with repeated (track, frame) pairs across both runs (the first ray kept), ids
    out of order, tracks asked for with observations not recorded, the window moving on.
    Catches: ``of`` gathering one run only (the small run's rows lost), the runs merged
    the wrong way round (a later ray kept), ``since`` or ``forget_before`` reading one
    run, ``len`` counting a pair twice."""
    tiered, one_run = TieredObservations(fold_rows), TrackObservations()
    for k in range(40):
        n = int(rng.integers(0, 30))
        track_id = rng.choice(60, n, replace=True) * 3 - 20
        frame = np.maximum(k - rng.integers(0, 4, n), 0)
        q = rng.normal(size=(n, 3))
        tiered.add(track_id, frame, q)
        one_run.add(track_id, frame, q)
        if k % 9 == 8:
            tiered.forget_before(k - 12)
            one_run.forget_before(k - 12)
        asked = rng.choice(70, 15) * 3 - 20
        extra_id = rng.choice(70, 8) * 3 - 20
        extra = (extra_id, np.maximum(k - rng.integers(0, 4, 8), 0), rng.normal(size=(8, 3)))
        for args in ((asked,), (asked[:0], extra), (asked, extra)):
            for got, want in zip(tiered.of(*args), one_run.of(*args)):
                assert np.array_equal(got, want)
        assert np.array_equal(tiered.since(k - 5), one_run.since(k - 5))
    assert len(tiered) == len(one_run)


def test_first_recorded_is_the_earliest_frame_of_any_track_asked(rng):
    """The frame a take-out scan starts from (``TrackJudge.first_recorded``): the earliest
    frame any of the tracks entered the solver at, past every frame for tracks never
    recorded (none of the factors holds them). Catches: the latest frame taken (a scan
    starting after factors that hold the tracks: features left in the solver), the
    tracks' first frames not gathered from both runs of a tiered record."""
    from cdtm_graph.results import Rejections
    from cdtm_graph.robust.mismatch import MismatchSettings
    from cdtm_graph.robust.track_judge import TrackJudge

    judge = TrackJudge(MismatchSettings(), None, None, None, np.eye(4), Rejections(),
                       TieredObservations(fold_rows=50))
    for k in range(1, 12):  # track t closes pairs at frames t // 10 + 1 ... t // 10 + 3
        ids = np.array([t for t in range(200) if t // 10 + 1 <= k <= t // 10 + 3])
        judge.observations.add(np.r_[ids, ids], np.r_[np.full(ids.size, k - 1),
                                                       np.full(ids.size, k)],
                               rng.normal(size=(2 * ids.size, 3)))
    # recorded frames: track 31 3-6, track 47 4-7, track 95 9-11
    assert judge.first_recorded(np.array([95, 47, 31])) == 3
    assert judge.first_recorded(np.array([95, 47])) == 4
    assert judge.first_recorded(np.array([95])) == 9
    assert judge.first_recorded(np.array([5000])) == np.iinfo(np.int64).max
