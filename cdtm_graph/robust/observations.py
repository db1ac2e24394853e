"""The track judge's record of observations over a full history, at a cost per frame that
does not grow with the flight.

:class:`~cdtm_graph.tracks.TrackObservations` keeps one array sorted by (track, frame):
recording a frame merges its rows into it, a copy of every row held. A fixed lag forgets
the old rows, so that array stays a window's; full-history iSAM2 never forgets, and at
frame 1000 the copy was ~4% of an update. :class:`TieredObservations` answers the same
questions with the same answers from two sorted runs: the newest rows in a small run that a
frame's rows merge into, folded into the large run once the small one holds
``FOLD_ROWS`` rows.
"""

from __future__ import annotations

import numpy as np

from cdtm_graph.tracks import TrackObservations, _forget, _gather, _merge, _sorted_once


class TieredObservations(TrackObservations):
    """:class:`~cdtm_graph.tracks.TrackObservations` in two sorted runs (the same rows,
    order and first rays; see the module's docstring).

    Args:
        fold_rows: rows of the small run that fold it into the large one.
    """

    #: The small run's rows at a fold (a frame records ~2x its features: ~25 frames).
    FOLD_ROWS = 8192

    def __init__(self, fold_rows: int = FOLD_ROWS) -> None:
        super().__init__()
        self.fold_rows = int(fold_rows)
        self._new_id = np.zeros(0, np.int64)
        self._new_frame = np.zeros(0, np.int64)
        self._new_q = np.zeros((0, 3))

    def add(self, track_id: np.ndarray, frame: np.ndarray, q: np.ndarray) -> None:
        # the small run is newer than the large one: a pair both hold keeps the large one's
        # ray at a fold, as it would have kept the first
        new_id, new_frame, new_q = _sorted_once(track_id, frame, q)
        self._new_id, self._new_frame, self._new_q = _merge(
            self._new_id, self._new_frame, self._new_q, new_id, new_frame, new_q)
        if self._new_id.size >= self.fold_rows:
            self._fold()

    def of(self, track_ids: np.ndarray, extra: tuple[np.ndarray, np.ndarray, np.ndarray]
           | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self._new_id.size == 0:
            return super().of(track_ids, extra)
        query = np.unique(np.asarray(track_ids, np.int64))
        if extra is None:
            extra = (query[:0], query[:0], self._q[:0])
        extra_rows = _sorted_once(*extra)
        # the rows of every track asked for (the extra rows' too) from both runs, merged
        # as a fold would: then the same gathering as from one run
        tracks = np.union1d(query, extra_rows[0])
        none = (tracks[:0], tracks[:0], self._q[:0])
        old_id, old_frame, old_q = _gather(self._id, self._frame, self._q, tracks, *none)
        new_id, new_frame, new_q = _gather(self._new_id, self._new_frame, self._new_q,
                                           tracks, *none)
        ids, frame, q = _merge(old_id, old_frame, old_q, new_id, new_frame, new_q)
        return _gather(ids, frame, q, query, *extra_rows)

    def since(self, frame: int) -> np.ndarray:
        return np.unique(np.concatenate((self._id[self._frame >= frame],
                                         self._new_id[self._new_frame >= frame])))

    def forget_before(self, frame: int) -> None:
        super().forget_before(frame)
        n = _forget(self._new_id, self._new_frame, self._new_q, frame)
        self._new_id, self._new_frame, self._new_q = (
            self._new_id[:n], self._new_frame[:n], self._new_q[:n])

    def __len__(self) -> int:
        self._fold()
        return super().__len__()

    def _fold(self) -> None:
        self._id, self._frame, self._q = _merge(self._id, self._frame, self._q,
                                                self._new_id, self._new_frame, self._new_q)
        self._new_id, self._new_frame, self._new_q = (
            self._new_id[:0], self._new_frame[:0], self._new_q[:0])
