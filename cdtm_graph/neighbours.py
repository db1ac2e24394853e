"""Sums over the points within a horizontal radius: the one search behind the spatial
views of the ground (:mod:`cdtm_graph.mismatch`'s neighbourhoods, :mod:`cdtm_graph.clutter`'s
neighbourhood means).

The reference points are sorted along the axis they spread over most; each query then
looks at the strip within the radius along that axis only. A frame's few hundred tracks
or a flight's few thousand, laid along a track on the ground, meet a strip of tens: the
search is one compiled pass, not a tree built and walked from Python.
"""

from __future__ import annotations

import numpy as np
from numba import njit


def ball_sums(query_xy: np.ndarray, ref_xy: np.ndarray, ref_values: np.ndarray,
              radius_m: float) -> tuple[np.ndarray, np.ndarray]:
    """For each query point, the sums of ``ref_values`` over the reference points within
    ``radius_m`` of it (horizontal distance, inclusive) and how many those are.

    Args:
        query_xy: (Q, 2+) the query points (columns beyond the first two are ignored).
        ref_xy: (R, 2+) the reference points. ref_values: (R, m) their values.
        radius_m: the radius.

    Returns:
        ``sums`` (Q, m) and ``counts`` (Q,) int64. A point with a NaN coordinate has no
        neighbours and is no one's.
    """
    query = np.ascontiguousarray(query_xy[:, :2], dtype=np.float64)
    ref = np.ascontiguousarray(ref_xy[:, :2], dtype=np.float64)
    values = np.ascontiguousarray(ref_values, dtype=np.float64).reshape(ref.shape[0], -1)
    finite = np.isfinite(ref).all(axis=1)
    ref, values = ref[finite], values[finite]
    spread = np.ptp(ref, axis=0) if ref.shape[0] else np.zeros(2)
    axis = int(spread[1] > spread[0])  # sort along the longer extent
    order = np.argsort(ref[:, axis], kind="stable")
    ref, values = ref[order], values[order]
    # the strip a hair wider than the radius (rounding of q +- r): the distance decides
    reach = radius_m * (1.0 + 1e-9) + 1e-9
    lo = np.searchsorted(ref[:, axis], query[:, axis] - reach, "left")
    hi = np.searchsorted(ref[:, axis], query[:, axis] + reach, "right")
    sums = np.zeros((query.shape[0], values.shape[1]))
    counts = np.zeros(query.shape[0], np.int64)
    _ball_sums_kernel(query, ref, values, lo, hi, radius_m * radius_m, sums, counts)
    return sums, counts


def near_any(query_xy: np.ndarray, ref_xy: np.ndarray, radius_m: float) -> np.ndarray:
    """(Q,) bool: whether any reference point lies within ``radius_m`` of each query."""
    return ball_sums(query_xy, ref_xy, np.zeros((ref_xy.shape[0], 0)), radius_m)[1] > 0


@njit(cache=True)
def _ball_sums_kernel(query, ref, values, lo, hi, radius2, sums, counts):
    m = values.shape[1]
    acc = np.zeros(m)
    for q in range(query.shape[0]):
        qx, qy = query[q, 0], query[q, 1]
        acc[:] = 0.0
        n = 0
        for r in range(lo[q], hi[q]):
            dx, dy = ref[r, 0] - qx, ref[r, 1] - qy
            if dx * dx + dy * dy <= radius2:
                n += 1
                for c in range(m):
                    acc[c] += values[r, c]
        counts[q] = n
        for c in range(m):
            sums[q, c] = acc[c]
