"""The last sighting of every live track, for pairing observations as frames arrive.

The incremental smoother pairs each new observation of a track with the track's
previous one (the consecutive pairs of :func:`cdtm_graph.graph.frame_pair_observations`).
:class:`TrackTable` holds, per track id, the frame and ray of its last sighting and
how many pairs it has made, as arrays sorted by id; a frame's look-up, update and
grouping by earlier frame take one numba call and a small sort. :class:`TrackObservations`
holds every sighting that entered the graph, sorted by track then frame, for triangulating
a track again when it is seen.

numba where it pays per frame (the look-up, the merges and gathers: 5-30x their numpy
equivalents, ~15 us against ~0.4 ms a call); numpy for the few whole-array steps
(membership, grouping, appending) that cost a few microseconds more than a kernel and
no compilation on a fresh install (issue 22; docs/design.md, "The first run").
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from cdtm_graph.camera import PinholeCamera
from cdtm_graph.dtm import Dtm
from cdtm_graph.errors import FlightLogError
from cdtm_graph.flightlog import Tracks
from cdtm_graph.results import Rejection, Rejections
from cdtm_graph.robust.epipolar import EpipolarSettings, check_pair
from factors.jit import njit


@dataclass(frozen=True)
class FramePairObservations:
    """Consecutive observations of tracks between frames a < b (one batched factor).

    Attributes:
        frame_a, frame_b: frame indices.
        q_a, q_b: (n, 3) normalized rays (z = 1).
        track_id: (n,) track ids.
        track_pair_index: (n,) 1-based rank of this pair among its track's pairs.
    """

    frame_a: int
    frame_b: int
    q_a: np.ndarray
    q_b: np.ndarray
    track_id: np.ndarray
    track_pair_index: np.ndarray | None = None

    def subset(self, keep: np.ndarray) -> FramePairObservations:
        """The same pair with the features selected by ``keep`` (mask or indices)."""
        rank = None if self.track_pair_index is None else self.track_pair_index[keep]
        return FramePairObservations(self.frame_a, self.frame_b, self.q_a[keep],
                                     self.q_b[keep], self.track_id[keep], rank)


def frame_pair_observations(tracks: Tracks, camera: PinholeCamera) -> list[FramePairObservations]:
    """Group the consecutive observation pairs of every track by frame pair, vectorized.

    Returns:
        One entry per distinct (frame_a, frame_b), sorted by (frame_b, frame_a).
    """
    rays = camera.pixels_to_rays(tracks.uv_px)
    rows_a, rows_b = tracks.pairs()
    fa, fb = tracks.frame[rows_a], tracks.frame[rows_b]
    # rank of each pair within its track, in time order (tracks.pairs() is time-sorted)
    tid = tracks.track_id[rows_a]
    by_track = np.lexsort((fa, tid))
    first = np.r_[True, tid[by_track][1:] != tid[by_track][:-1]]
    starts = np.maximum.accumulate(np.where(first, np.arange(tid.size), 0))
    rank = np.empty(tid.size, dtype=np.int64)
    rank[by_track] = np.arange(tid.size) - starts + 1
    order = np.lexsort((fa, fb))
    rows_a, rows_b, fa, fb, rank = rows_a[order], rows_b[order], fa[order], fb[order], rank[order]
    if fa.size == 0:
        return []
    change = np.flatnonzero((np.diff(fa) != 0) | (np.diff(fb) != 0)) + 1
    starts = np.r_[0, change]
    ends = np.r_[change, fa.size]
    return [FramePairObservations(int(fa[s]), int(fb[s]), rays[rows_a[s:e]], rays[rows_b[s:e]],
                                  tracks.track_id[rows_a[s:e]], rank[s:e])
            for s, e in zip(starts, ends)]



class TrackTable:
    """Last sighting of each track: frame, ray (z = 1) and pairs made so far.

    Rows ``[:len(self)]`` of growable buffers, sorted by track id; new tracks are
    appended in place when their ids exceed every known one (trackers number tracks
    upwards), else merged in.
    """

    def __init__(self, capacity: int = 1024) -> None:
        self._ids = np.zeros(capacity, dtype=np.int64)
        self._frame = np.zeros(capacity, dtype=np.int64)
        self._q = np.zeros((capacity, 3))
        self._pairs = np.zeros(capacity, dtype=np.int64)
        self._fails = np.zeros(capacity, dtype=np.int64)  # pairs rejected in a row
        self._n = 0
        self._ever: set[int] = set()  # every id added (one forgotten may come back)

    @property
    def n_tracks(self) -> int:
        """Distinct track ids ever added."""
        return len(self._ever)

    def __len__(self) -> int:
        return self._n

    @property
    def ids(self) -> np.ndarray:
        return self._ids[:self._n]

    @property
    def frame(self) -> np.ndarray:
        return self._frame[:self._n]

    @property
    def q(self) -> np.ndarray:
        return self._q[:self._n]

    @property
    def pairs(self) -> np.ndarray:
        return self._pairs[:self._n]

    def add_frame(self, k: int, track_id: np.ndarray, q: np.ndarray,
                  oldest_frame: int = 0) -> tuple[list[FramePairObservations], int]:
        """Record frame k's sightings and return the pairs they close.

        Args:
            k: frame index (larger than any recorded). track_id: (m,) int64 ids.
            q: (m, 3) their rays.
            oldest_frame: pairs whose earlier frame is older are not returned (a
                fixed-lag window has let that frame go); they are counted.

        Returns:
            One :class:`FramePairObservations` per earlier frame (ascending), with each
            pair's 1-based rank among its track's pairs, and the number of pairs dropped
            as too old.

        Raises:
            FlightLogError: a track id appears twice in the frame.
        """
        track_id = np.ascontiguousarray(track_id, dtype=np.int64)
        q = np.ascontiguousarray(q, dtype=float)
        if track_id.ndim != 1 or q.shape != (track_id.size, 3):
            raise ValueError(f"frame {k}: {track_id.shape} track ids with rays of shape "
                             f"{q.shape}; expected (m,) and (m, 3)")
        check_unique(k, track_id)  # before anything changes
        new_rows, rows, frame_a, q_a, rank, n_too_old = _match(
            self.ids, self.frame, self.q, self.pairs, track_id, q, k, oldest_frame)
        if new_rows.size:
            self._insert(k, track_id[new_rows], q[new_rows])
        if not frame_a.size:
            return [], n_too_old
        # Group by earlier frame (numpy here: a sort inside numba costs seconds to compile).
        order = np.argsort(frame_a, kind="stable")
        rows, frame_a, q_a, rank = rows[order], frame_a[order], q_a[order], rank[order]
        bounds = np.concatenate(([0], np.flatnonzero(frame_a[1:] != frame_a[:-1]) + 1,
                                 [frame_a.size]))
        pairs = []
        for s, e in zip(bounds[:-1].tolist(), bounds[1:].tolist()):
            pairs.append(FramePairObservations(int(frame_a[s]), k, q_a[s:e], q[rows[s:e]],
                                               track_id[rows[s:e]], rank[s:e]))
        return pairs, n_too_old

    def reject(self, pair: FramePairObservations, rejected: np.ndarray,
               patience: int = 2) -> None:
        """Undo the newest sighting of tracks whose pair was rejected as a wrong match.

        The track keeps its earlier sighting, so its next sighting pairs across the bad
        one (a wrong match in frame b costs one pair, not two). A track whose pairs keep
        failing (``patience`` times in a row) restarts from its newest sighting instead:
        its earlier one was the wrong match.

        Args:
            pair: pairs :meth:`add_frame` returned. rejected: (n,) bool, which to undo.
        """
        if not rejected.any():
            return
        ids = np.ascontiguousarray(pair.track_id[rejected])
        _reject(self.ids, self.frame, self.q, self.pairs, self._fails[:self._n], ids,
                int(pair.frame_a), np.ascontiguousarray(pair.q_a[rejected]), patience)

    def accept(self, pair: FramePairObservations, accepted: np.ndarray) -> None:
        """Clear the failure count of tracks whose pair passed."""
        if accepted.any():
            self._fails[np.searchsorted(self.ids, pair.track_id[accepted])] = 0

    def forget_before(self, frame: int) -> None:
        """Drop tracks last seen before ``frame`` (they can only pair with older frames)."""
        self._n = _compact(self._ids, self._frame, self._q, self._pairs, self._fails, self._n,
                           frame)

    def _insert(self, k: int, new_ids: np.ndarray, q_new: np.ndarray) -> None:
        self._ever.update(new_ids.tolist())
        n = _append(self._ids, self._frame, self._q, self._pairs, self._fails, self._n, new_ids,
                    q_new, k)
        if n >= 0:
            self._n = n
            return
        # Out of room, or ids below known ones: merge into fresh buffers.
        order = np.argsort(new_ids, kind="stable")
        at = np.searchsorted(self.ids, new_ids[order])
        ids = np.insert(self.ids, at, new_ids[order])
        frame = np.insert(self.frame, at, k)
        q = np.insert(self.q, at, q_new[order], axis=0)
        pairs = np.insert(self.pairs, at, 0)
        fails = np.insert(self._fails[:self._n], at, 0)
        capacity = max(2 * ids.size, 1024)
        self._ids = np.resize(ids, capacity)
        self._frame = np.resize(frame, capacity)
        self._q = np.resize(q, (capacity, 3))
        self._pairs = np.resize(pairs, capacity)
        self._fails = np.resize(fails, capacity)
        self._n = ids.size


def pairs_without(pairs: list[FramePairObservations], track_ids: np.ndarray, k: int,
                  reason: Rejection, rejections: Rejections) -> list[FramePairObservations]:
    """Frame k's pairs without the sightings of ``track_ids`` (counted for ``reason``);
    pairs left empty are dropped."""
    if track_ids.size == 0:
        return pairs
    track_ids = np.ascontiguousarray(track_ids, np.int64)
    if not (track_ids[1:] > track_ids[:-1]).all():
        track_ids = np.unique(track_ids)
    kept = []
    for pair in pairs:
        off = _in_sorted(np.ascontiguousarray(pair.track_id, np.int64), track_ids)
        rejections.add(reason, k, int(off.sum()))
        if not off.all():
            kept.append(pair.subset(~off) if off.any() else pair)
    return kept


def _in_sorted(ids: np.ndarray, sorted_ids: np.ndarray) -> np.ndarray:
    """(n,) whether each id is one of ``sorted_ids`` (sorted, unique): ``np.isin`` by
    binary search, which a frame's few hundred ids against a long list want."""
    at = np.searchsorted(sorted_ids, ids)
    found = at < sorted_ids.shape[0]
    found[found] = sorted_ids[at[found]] == ids[found]
    return found


def frames_seen(frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct frames of a set of observations and each one's index among them: what
    ``np.unique(frame, return_inverse=True)`` gives, by counting (frame indices are small
    non-negative integers; a flight's observations are too many to sort twice a solve)."""
    frame = np.ascontiguousarray(frame, dtype=np.int64)
    if frame.size == 0:
        return frame, np.zeros(0, np.int64)
    return _frames_seen(frame)


def _frames_seen(frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    first = int(frame.min())
    present = np.zeros(int(frame.max()) - first + 1, np.bool_)
    present[frame - first] = True
    index = np.cumsum(present) - 1  # each frame's rank among those present
    return np.flatnonzero(present) + first, index[frame - first]


def track_groups(track_id: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The distinct tracks of a set of observations, each observation's index among them
    and their counts: what ``np.unique(track_id, return_inverse=True, return_counts=True)``
    gives, in one pass where the observations come sorted by track (they mostly do)."""
    track_id = np.ascontiguousarray(track_id, dtype=np.int64)
    if not (track_id[1:] < track_id[:-1]).any():  # sorted: the groups are runs
        new = np.empty(track_id.size, np.bool_)
        new[:1] = True
        np.not_equal(track_id[1:], track_id[:-1], out=new[1:])
        starts = np.flatnonzero(new)
        return (track_id[starts], np.cumsum(new) - 1,
                np.diff(np.append(starts, track_id.size)))
    ids, index, counts = np.unique(track_id, return_inverse=True, return_counts=True)
    return ids, index.reshape(-1), counts


def first_sightings(track_id: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """Indices of the first of each (track, frame) among these observations, ordered by
    track then frame (as ``np.unique(np.c_[track_id, frame], axis=0, return_index=True)``
    gives them, at a fraction of its cost: no structured sort)."""
    order = np.lexsort((frame, track_id))  # stable: the first of equals stays first
    tid, fr = track_id[order], frame[order]
    new = np.ones(order.size, dtype=bool)
    new[1:] = (tid[1:] != tid[:-1]) | (fr[1:] != fr[:-1])
    return order[new]


def checked_sightings(k: int, track_id: np.ndarray | None, uv_px: np.ndarray | None
                      ) -> tuple[np.ndarray, np.ndarray] | None:
    """Frame k's sightings as ``(ids int64 (m,), pixels (m, 2))``, or None without any.

    Raises:
        FlightLogError: shapes that do not match, or a track id seen twice.
    """
    if track_id is None or not len(track_id):
        return None
    ids = np.asarray(track_id, dtype=np.int64)
    uv = np.asarray(uv_px, dtype=float)
    if ids.ndim != 1 or uv.shape != (ids.size, 2):
        raise FlightLogError(f"frame {k}: {ids.shape} track ids with pixels of "
                             f"shape {uv.shape}; expected (m,) and (m, 2)")
    check_unique(k, ids)
    return ids, uv


def check_unique(k: int, track_id: np.ndarray) -> None:
    """Raise ``FlightLogError`` if a track id appears twice in frame k."""
    ids = np.sort(np.asarray(track_id))
    repeated = ids[1:][ids[1:] == ids[:-1]]
    if repeated.size:
        raise FlightLogError(f"frame {k}: track {int(repeated[0])} is seen twice")


class TrackObservations:
    """Every observation that entered the graph, once each, sorted by track then frame:
    what the incremental smoother triangulates a track from when it is seen again.

    Gathering a frame's tracks is then a binary search and a slice per track (one
    compiled call), not a membership test over the whole window and a sort.
    """

    def __init__(self) -> None:
        self._id = np.zeros(0, np.int64)
        self._frame = np.zeros(0, np.int64)
        self._q = np.zeros((0, 3))

    def add(self, track_id: np.ndarray, frame: np.ndarray, q: np.ndarray) -> None:
        """Record observations ((n,) ids, (n,) frames, (n, 3) rays); a (track, frame)
        already held keeps its first ray."""
        new_id, new_frame, new_q = _sorted_once(track_id, frame, q)
        self._id, self._frame, self._q = _merge(self._id, self._frame, self._q,
                                                new_id, new_frame, new_q)

    def of(self, track_ids: np.ndarray, extra: tuple[np.ndarray, np.ndarray, np.ndarray]
           | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The observations of these tracks, once each and sorted by track then frame:
        (ids, frames, rays). ``extra`` observations (ids, frames, rays) not recorded
        join them (a recorded (track, frame) keeps its ray); their tracks are asked for
        too."""
        query = np.unique(np.asarray(track_ids, np.int64))
        if extra is None:
            extra = (query[:0], query[:0], self._q[:0])
        return _gather(self._id, self._frame, self._q, query, *_sorted_once(*extra))

    def since(self, frame: int) -> np.ndarray:
        """Ids of the tracks observed at or after ``frame`` (sorted)."""
        return np.unique(self._id[self._frame >= frame])

    def forget_before(self, frame: int) -> None:
        n = _forget(self._id, self._frame, self._q, frame)
        self._id, self._frame, self._q = self._id[:n], self._frame[:n], self._q[:n]

    def __len__(self) -> int:
        return int(self._id.size)


def _sorted_once(track_id: np.ndarray, frame: np.ndarray, q: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Observations sorted by track then frame, the first of each (track, frame) only."""
    first = first_sightings(np.asarray(track_id), np.asarray(frame))
    return (np.ascontiguousarray(track_id[first], np.int64),
            np.ascontiguousarray(frame[first], np.int64),
            np.ascontiguousarray(np.asarray(q, float).reshape(-1, 3)[first]))


@njit(cache=True)
def _before(id_a, frame_a, id_b, frame_b):
    """(id_a, frame_a) < (id_b, frame_b)."""
    return id_a < id_b or (id_a == id_b and frame_a < frame_b)


@njit(cache=True)
def _merge(ids, frame, q, new_ids, new_frame, new_q):
    """Two runs sorted by (track, frame) merged; a pair in both keeps the first run's
    row."""
    n, m = ids.shape[0], new_ids.shape[0]
    out_id = np.empty(n + m, np.int64)
    out_frame = np.empty(n + m, np.int64)
    out_q = np.empty((n + m, 3))
    i = j = o = 0
    while i < n or j < m:
        if j >= m or (i < n and not _before(new_ids[j], new_frame[j], ids[i], frame[i])):
            if j < m and i < n and new_ids[j] == ids[i] and new_frame[j] == frame[i]:
                j += 1  # held already
            _put(out_id, out_frame, out_q, o, ids[i], frame[i], q, i)
            i += 1
        else:
            _put(out_id, out_frame, out_q, o, new_ids[j], new_frame[j], new_q, j)
            j += 1
        o += 1
    return out_id[:o], out_frame[:o], out_q[:o]


@njit(cache=True)
def _gather(ids, frame, q, query, extra_id, extra_frame, extra_q):
    """The rows of the ``query`` tracks (sorted, unique) and of the ``extra`` rows' tracks,
    each track's merged with its extra rows (sorted by (track, frame), unique; a held pair
    keeps its row)."""
    n_extra = extra_id.shape[0]
    # the tracks asked for: the union of the query and the extra rows' tracks
    tracks = np.empty(query.shape[0] + n_extra, np.int64)
    n_tracks = a = e = 0
    while a < query.shape[0] or e < n_extra:
        if e >= n_extra or (a < query.shape[0] and query[a] <= extra_id[e]):
            track = query[a]
            a += 1
        else:
            track = extra_id[e]
            e += 1
        if n_tracks == 0 or tracks[n_tracks - 1] != track:
            tracks[n_tracks] = track
            n_tracks += 1
    tracks = tracks[:n_tracks]
    lo = np.searchsorted(ids, tracks)
    hi = np.searchsorted(ids, tracks, side="right")
    n_out = n_extra
    for t in range(n_tracks):
        n_out += hi[t] - lo[t]
    out_id = np.empty(n_out, np.int64)
    out_frame = np.empty(n_out, np.int64)
    out_q = np.empty((n_out, 3))
    o = e = 0
    for t in range(n_tracks):
        track = tracks[t]
        i = lo[t]
        while i < hi[t] or (e < n_extra and extra_id[e] == track):
            if e < n_extra and extra_id[e] == track and (i >= hi[t] or extra_frame[e] < frame[i]):
                _put(out_id, out_frame, out_q, o, track, extra_frame[e], extra_q, e)
                e += 1
            else:
                if e < n_extra and extra_id[e] == track and extra_frame[e] == frame[i]:
                    e += 1  # recorded: its own row
                _put(out_id, out_frame, out_q, o, track, frame[i], q, i)
                i += 1
            o += 1
    return out_id[:o], out_frame[:o], out_q[:o]


@njit(cache=True)
def _forget(ids, frame, q, oldest_frame):
    """Keep the rows of ``oldest_frame`` or later, in order, in place: the new length."""
    j = 0
    for i in range(ids.shape[0]):
        if frame[i] >= oldest_frame:
            _put(ids, frame, q, j, ids[i], frame[i], q, i)
            j += 1
    return j


@njit(cache=True, inline="always")
def _put(out_id, out_frame, out_q, o, track, frame, q, i):
    """Row o of the output: the track, the frame and row i of ``q`` (element by element:
    numba's row slices cost more than the copy)."""
    out_id[o], out_frame[o] = track, frame
    _copy_row(out_q, o, q, i)


@njit(cache=True, inline="always")
def _copy_row(out, o, a, i):
    """Row o of ``out`` = row i of ``a`` (three columns), element by element: numba's row
    slices cost more than the copy, and their stores cost ~1 s of compilation each."""
    out[o, 0], out[o, 1], out[o, 2] = a[i, 0], a[i, 1], a[i, 2]


@njit(cache=True)
def _match(ids, frame, q_seen, pairs, track_id, q, k, oldest_frame):
    """Look up, pair and update a frame's tracks in the sorted table (in place).

    Returns the rows of the frame's new tracks; for the pairs kept, in the frame's order:
    the rows of the frame's arrays, the earlier frame, its ray and the pair's rank; then
    the count of pairs too old. Track ids must be unique within the frame.
    """
    m = track_id.shape[0]
    new_rows = np.empty(m, dtype=np.int64)
    rows = np.empty(m, dtype=np.int64)
    frame_a = np.empty(m, dtype=np.int64)
    q_a = np.empty((m, 3))
    rank = np.empty(m, dtype=np.int64)
    n_new = 0
    n_kept = 0
    n_too_old = 0
    for i in range(m):
        at = np.searchsorted(ids, track_id[i])
        if at >= ids.shape[0] or ids[at] != track_id[i]:
            new_rows[n_new] = i
            n_new += 1
            continue
        a = frame[at]
        pairs[at] += 1
        if a >= oldest_frame:
            rows[n_kept] = i
            frame_a[n_kept] = a
            _copy_row(q_a, n_kept, q_seen, at)
            rank[n_kept] = pairs[at]
            n_kept += 1
        else:
            n_too_old += 1
        frame[at] = k
        _copy_row(q_seen, at, q, i)
    return (new_rows[:n_new], rows[:n_kept], frame_a[:n_kept], q_a[:n_kept], rank[:n_kept],
            n_too_old)


@njit(cache=True)
def _reject(ids, frame, q_seen, pairs, fails, track_id, frame_a, q_a, patience):
    """Restore the earlier sighting of each rejected track (or, after ``patience``
    rejections in a row, keep the newest and start over)."""
    for i in range(track_id.shape[0]):
        at = np.searchsorted(ids, track_id[i])
        pairs[at] -= 1
        fails[at] += 1
        if fails[at] >= patience:
            fails[at] = 0
            continue
        frame[at] = frame_a
        _copy_row(q_seen, at, q_a, i)


def _append(ids: np.ndarray, frame: np.ndarray, q_seen: np.ndarray, pairs: np.ndarray,
            fails: np.ndarray, n: int, new_ids: np.ndarray, q_new: np.ndarray, k: int
            ) -> int:
    """Append tracks whose ids are increasing and above every known id, in place, if the
    buffers have room: the new length, else -1. (numpy: a few slice stores.)"""
    m = new_ids.shape[0]
    if n + m > ids.shape[0]:
        return -1
    if m and ((n > 0 and new_ids[0] <= ids[n - 1]) or (new_ids[1:] <= new_ids[:-1]).any()):
        return -1
    ids[n:n + m] = new_ids
    frame[n:n + m] = k
    q_seen[n:n + m] = q_new
    pairs[n:n + m] = 0
    fails[n:n + m] = 0
    return n + m


@njit(cache=True)
def _compact(ids, frame, q_seen, pairs, fails, n, oldest_frame):
    """Keep the rows last seen at or after ``oldest_frame``, in order: the new length."""
    j = 0
    for i in range(n):
        if frame[i] >= oldest_frame:
            ids[j] = ids[i]
            frame[j] = frame[i]
            _copy_row(q_seen, j, q_seen, i)
            pairs[j] = pairs[i]
            fails[j] = fails[i]
            j += 1
    return j


class SightingPairs:
    """Pairs each frame's sightings with their tracks' last good ones, wrong matches out.

    A :class:`TrackTable` pairs each sighting with its track's previous one; each pair's
    features are then checked against the epipolar geometry of the current relative pose
    (:func:`cdtm_graph.robust.epipolar.check_pair`). A rejected feature's newest sighting is
    undone (:meth:`TrackTable.reject`), so the track pairs across the wrong match. The
    batch smoother pairs a whole log this way, frame by frame, as the incremental
    smoother does live.

    Args:
        camera: undistorts pixels to rays. body_T_cam: (4, 4) the mounting.
        dtm: for the camera's height above the ground (the parallax test).
        pixel_sigma_px: one observation's pixel noise.
        settings: the check (``None``: pairing without it).
        rejections: where wrong matches and pairs too old are counted.
    """

    def __init__(self, camera: PinholeCamera, body_T_cam: np.ndarray, dtm: Dtm,
                 pixel_sigma_px: float, settings: EpipolarSettings | None,
                 rejections: Rejections):
        self.table = TrackTable()
        self._camera = camera
        self._body_T_cam = body_T_cam
        self._dtm = dtm
        self._sigma_q = float(np.mean(camera.sigma_normalized(pixel_sigma_px)))
        self.settings = settings  # the epipolar check's (None: no check)
        self._rejections = rejections
        self.n_observations = 0
        self.n_pairs = 0

    def add_frame(self, k: int, track_id: np.ndarray, uv_px: np.ndarray,
                  world_T_body: Callable[[int], np.ndarray], oldest_frame: int = 0
                  ) -> list[FramePairObservations]:
        """Frame k's sightings: the pairs they close that pass the check.

        Args:
            k: the frame. track_id: (m,) ids. uv_px: (m, 2) pixels.
            world_T_body: frame -> current (4, 4) pose guess (frame k's and the earlier
                frames' of its pairs).
            oldest_frame: pairs with an earlier frame before this are dropped (counted).
        """
        q = self._camera.pixels_to_rays(uv_px)
        self.n_observations += len(track_id)
        pairs, n_too_old = self.table.add_frame(k, track_id, q, oldest_frame)
        self._rejections.add(Rejection.TOO_OLD, k, n_too_old)
        self.n_pairs += sum(p.q_a.shape[0] for p in pairs) + n_too_old
        if self.settings is None:
            return pairs
        wTc_b = world_T_body(k) @ self._body_T_cam
        kept = []
        for pair in pairs:
            wTc_a = world_T_body(pair.frame_a) @ self._body_T_cam
            check = check_pair(pair.q_a, pair.q_b, wTc_b[:3, :3].T @ wTc_a[:3, :3],
                               wTc_b[:3, :3].T @ (wTc_a[:3, 3] - wTc_b[:3, 3]), self._sigma_q,
                               self._range_m(wTc_a[:3, 3]), self.settings)
            self.table.reject(pair, ~check.inlier)
            self.table.accept(pair, check.inlier)
            self._rejections.add(Rejection.WRONG_MATCH, k, int((~check.inlier).sum()))
            if check.inlier.all():
                kept.append(pair)
            elif check.inlier.any():
                kept.append(pair.subset(check.inlier))
        return kept

    def _range_m(self, camera_m: np.ndarray) -> float:
        """Height of the camera above the ground under it (the DTM's mean if outside)."""
        ground = float(self._dtm.height(camera_m[0], camera_m[1]))
        if not np.isfinite(ground):
            ground = float(np.nanmean(self._dtm.elevation))
        return max(float(camera_m[2]) - ground, 1.0)
