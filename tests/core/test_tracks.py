"""Pairing of track sightings: the whole-log grouping, and TrackTable frame by frame."""

from __future__ import annotations

import numpy as np
import pytest

from cdtm_graph.camera import PinholeCamera
from cdtm_graph.errors import FlightLogError
from cdtm_graph.flightlog import Tracks
from cdtm_graph.results import Rejection, Rejections
from cdtm_graph.tracks import (
    FramePairObservations,
    TrackObservations,
    TrackTable,
    frame_pair_observations,
    pairs_without,
)

CAMERA = PinholeCamera(width=640, height=480, fx=400.0, fy=400.0, cx=320.0, cy=240.0)


def random_tracks(rng, n_frames=30, n_tracks=120) -> Tracks:
    """Tracks with gaps, unsorted ids within frames, and ids that arrive out of order."""
    rows = []
    for tid in rng.permutation(np.arange(n_tracks) * 7 - 50):
        first = rng.integers(0, n_frames - 1)
        frames = first + np.cumsum(rng.integers(1, 4, rng.integers(1, 8))) - 1
        rows += [(f, tid) for f in frames if f < n_frames]
    rows = np.array(sorted(rows, key=lambda r: (r[0], rng.random())))
    uv = rng.uniform([0, 0], [640, 480], (len(rows), 2))
    return Tracks(rows[:, 0], rows[:, 1], uv)


def feed(table, tracks, oldest_of=lambda k: 0):
    got, too_old = {}, 0
    bounds = np.searchsorted(tracks.frame, np.arange(tracks.frame.max() + 2))
    for k in range(tracks.frame.max() + 1):
        s, e = bounds[k], bounds[k + 1]
        q = CAMERA.pixels_to_rays(tracks.uv_px[s:e])
        pairs, dropped = table.add_frame(k, tracks.track_id[s:e], q, oldest_of(k))
        too_old += dropped
        got.update({(p.frame_a, p.frame_b): p for p in pairs})
    return got, too_old


def _by_track(pair):
    order = np.argsort(pair.track_id)
    return (pair.track_id[order], pair.q_a[order], pair.q_b[order],
            pair.track_pair_index[order])


def test_frame_by_frame_pairs_equal_the_whole_log_pairs(rng):
    tracks = random_tracks(rng)
    got, too_old = feed(TrackTable(), tracks)
    want = {(p.frame_a, p.frame_b): p for p in frame_pair_observations(tracks, CAMERA)}
    assert too_old == 0
    assert got.keys() == want.keys()
    for key, pair in want.items():
        for a, b in zip(_by_track(got[key]), _by_track(pair)):
            np.testing.assert_array_equal(a, b)


def test_pairs_reaching_before_the_window_are_dropped_and_counted(rng):
    tracks = random_tracks(rng)
    lag = 2  # gaps reach 3 frames
    table = TrackTable()
    got, too_old = feed(table, tracks, lambda k: max(k - lag, 0))
    want = frame_pair_observations(tracks, CAMERA)
    kept = [p for p in want if p.frame_a >= max(p.frame_b - lag, 0)]
    assert set(got) == {(p.frame_a, p.frame_b) for p in kept}
    assert too_old == sum(p.q_a.shape[0] for p in want) - sum(p.q_a.shape[0] for p in kept)
    assert too_old > 0
    assert table.n_tracks == np.unique(tracks.track_id).size
    table.forget_before(tracks.frame.max())
    assert np.all(table.frame >= tracks.frame.max()) and len(table) > 0


def test_a_repeated_track_is_refused_before_the_table_changes(rng):
    table = TrackTable()
    q = CAMERA.pixels_to_rays(rng.uniform(0, 400, (3, 2)))
    table.add_frame(0, np.array([5, 9, 2]), q)
    before = (table.ids.copy(), table.frame.copy(), table.q.copy(), table.pairs.copy())
    with pytest.raises(FlightLogError, match="frame 1: track 9 is seen twice"):
        table.add_frame(1, np.array([9, 4, 9]), q)
    for a, b in zip(before, (table.ids, table.frame, table.q, table.pairs)):
        np.testing.assert_array_equal(a, b)


def test_pairs_are_grouped_by_frame_pair_with_their_rank_in_the_track():
    # track 7 seen in frames 2, 3 and 7; track 9 in 3 and 7; track 4 only once
    tracks = Tracks(frame=np.array([2, 3, 3, 4, 7, 7]), track_id=np.array([7, 7, 9, 4, 7, 9]),
                    uv_px=np.arange(12, dtype=float).reshape(6, 2) * 10)
    camera = PinholeCamera.from_fov(400, 400, 60)
    pairs = frame_pair_observations(tracks, camera)
    got = {(p.frame_a, p.frame_b): (p.track_id.tolist(), p.track_pair_index.tolist())
           for p in pairs}
    assert got == {(2, 3): ([7], [1]), (3, 7): ([7, 9], [2, 1])}
    pair_23 = pairs[0]
    np.testing.assert_allclose(pair_23.q_a, camera.pixels_to_rays(tracks.uv_px[[0]]))
    np.testing.assert_allclose(pair_23.q_b, camera.pixels_to_rays(tracks.uv_px[[1]]))


def test_a_returning_track_id_counts_once():
    """A track id forgotten by the fixed lag and seen again counts once among the tracks."""
    table = TrackTable()
    q = np.c_[np.zeros((2, 2)), np.ones(2)]
    table.add_frame(0, np.array([3, 4]), q)
    table.forget_before(1)
    table.add_frame(1, np.array([4, 5]), q)
    assert table.n_tracks == 3


def test_pairs_without_leaves_out_and_counts_the_sightings_of_given_tracks(rng):

    def pair(a, ids):
        q = np.c_[rng.normal(size=(len(ids), 2)), np.ones(len(ids))]
        return FramePairObservations(a, 5, q, q + 0.01, np.array(ids))

    pairs = [pair(3, [1, 2, 3]), pair(4, [2, 7]), pair(2, [8])]
    rejections = Rejections()
    kept = pairs_without(pairs, np.array([2, 7]), 5, Rejection.MAP_MISMATCH, rejections)
    assert [p.frame_a for p in kept] == [3, 2]  # frame 4's pair held only those tracks
    np.testing.assert_array_equal(kept[0].track_id, [1, 3])
    np.testing.assert_array_equal(kept[0].q_a, pairs[0].q_a[[0, 2]])
    assert kept[1] is pairs[2]
    assert rejections.total(Rejection.MAP_MISMATCH) == 3
    assert pairs_without(pairs, np.zeros(0, np.int64), 5, Rejection.MAP_MISMATCH,
                         rejections) is pairs
    # the ids to leave out in any order, repeated
    again = pairs_without(pairs, np.array([7, 2, 7]), 5, Rejection.MAP_MISMATCH, Rejections())
    assert [p.track_id.tolist() for p in again] == [[1, 3], [8]]


class RecordedObservations:
    """Reference: every observation appended as it comes; the first of each (track,
    frame) counts, the rest in track then frame order (a sort of the whole record)."""

    def __init__(self):
        self.rows = []  # (track, frame, ray)

    def add(self, track_id, frame, q):
        self.rows += list(zip(track_id.tolist(), frame.tolist(), q))

    def of(self, track_ids, extra=None):
        asked = set(track_ids.tolist()) | set(() if extra is None else extra[0].tolist())
        rows = [r for r in self.rows if r[0] in asked]
        if extra is not None:
            rows += list(zip(extra[0].tolist(), extra[1].tolist(), extra[2]))
        first = {}
        for r in rows:
            first.setdefault((r[0], r[1]), r)
        keys = sorted(first)
        return (np.array([t for t, _ in keys], np.int64), np.array([f for _, f in keys], np.int64),
                np.array([first[key][2] for key in keys]).reshape(-1, 3))

    def forget_before(self, frame):
        self.rows = [r for r in self.rows if r[1] >= frame]


def test_recorded_observations_are_gathered_by_track_first_ray_kept(rng):
    """The store against a plain record: random frames of observations with repeats
    (a (track, frame) recorded twice keeps its first ray), ids out of order, tracks
    asked for with observations not recorded, and the window moving on."""
    store, reference = TrackObservations(), RecordedObservations()
    for k in range(40):
        n = int(rng.integers(0, 30))
        track_id = rng.choice(60, n, replace=True) * 3 - 20
        frame = np.maximum(k - rng.integers(0, 3, n), 0)
        q = rng.normal(size=(n, 3))
        store.add(track_id, frame, q)
        reference.add(track_id, frame, q)
        if k % 7 == 6:
            store.forget_before(k - 10)
            reference.forget_before(k - 10)
        asked = rng.choice(70, 15) * 3 - 20
        extra_id = rng.choice(70, 8) * 3 - 20
        extra = (extra_id, np.maximum(k - rng.integers(0, 4, 8), 0), rng.normal(size=(8, 3)))
        for args in ((asked,), (asked[:0], extra), (asked, extra)):
            got, want = store.of(*args), reference.of(*args)
            for g, w in zip(got, want):
                assert np.array_equal(g, w)
        since = store.since(k - 5)
        assert np.array_equal(since, np.unique([r[0] for r in reference.rows if r[1] >= k - 5]))
    assert len(store) == len({(r[0], r[1]) for r in reference.rows})
