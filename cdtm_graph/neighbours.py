"""Sums over the points within a horizontal radius: the one search behind the spatial
views of the ground (:mod:`cdtm_graph.mismatch`'s neighbourhoods, :mod:`cdtm_graph.clutter`'s
neighbourhood means).

The reference points are binned in square cells as wide as the radius and sorted by cell
(column-major); a query then reads the three runs of cells (one per neighbouring column)
around its own. One compiled pass, not a tree built and walked from Python: a frame's few
hundred tracks or a flight's tens of thousands alike.
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
        radius_m: the radius (> 0).

    Returns:
        ``sums`` (Q, m) and ``counts`` (Q,) int64. A point with a NaN coordinate has no
        neighbours and is no one's.
    """
    query = np.ascontiguousarray(query_xy[:, :2], dtype=np.float64)
    ref = np.ascontiguousarray(ref_xy[:, :2], dtype=np.float64)
    values = np.ascontiguousarray(ref_values, dtype=np.float64).reshape(ref.shape[0], -1)
    sums = np.zeros((query.shape[0], values.shape[1]))
    counts = np.zeros(query.shape[0], np.int64)
    finite = np.isfinite(ref).all(axis=1)
    if not finite.any():
        return sums, counts
    ref, values = ref[finite], values[finite]
    origin = ref.min(axis=0)
    # cells one radius wide, rows offset by one so that a cell's neighbours never wrap
    n_rows = int(np.floor((ref[:, 1].max() - origin[1]) / radius_m)) + 3
    key = _cell_keys(ref, origin, radius_m, n_rows)
    order = np.argsort(key, kind="stable")
    _ball_sums_kernel(query, ref[order], values[order], key[order], origin, radius_m,
                      n_rows, sums, counts)
    return sums, counts


def near_any(query_xy: np.ndarray, ref_xy: np.ndarray, radius_m: float) -> np.ndarray:
    """(Q,) bool: whether any reference point lies within ``radius_m`` of each query."""
    return ball_sums(query_xy, ref_xy, np.zeros((ref_xy.shape[0], 0)), radius_m)[1] > 0


def _cell_keys(xy: np.ndarray, origin: np.ndarray, size: float, n_rows: int) -> np.ndarray:
    column = np.floor((xy[:, 0] - origin[0]) / size).astype(np.int64)
    row = np.floor((xy[:, 1] - origin[1]) / size).astype(np.int64) + 1
    return column * n_rows + row


@njit(cache=True)
def _ball_sums_kernel(query, ref, values, key, origin, radius, n_rows, sums, counts):
    radius2 = radius * radius
    m = values.shape[1]
    n_columns = key[-1] // n_rows + 1
    for q in range(query.shape[0]):
        qx, qy = query[q, 0], query[q, 1]
        if not (np.isfinite(qx) and np.isfinite(qy)):
            continue
        column = int(np.floor((qx - origin[0]) / radius))
        row = int(np.floor((qy - origin[1]) / radius)) + 1
        if row < 0 or row > n_rows - 1 or column < -1 or column > n_columns:
            continue  # farther than a cell from every reference point
        row = min(max(row, 1), n_rows - 2)
        for c in range(column - 1, column + 2):
            if c < 0 or c >= n_columns:
                continue
            lo = np.searchsorted(key, c * n_rows + row - 1)
            hi = np.searchsorted(key, c * n_rows + row + 1, side="right")
            for r in range(lo, hi):
                dx, dy = ref[r, 0] - qx, ref[r, 1] - qy
                if dx * dx + dy * dy <= radius2:
                    counts[q] += 1
                    for j in range(m):
                        sums[q, j] += values[r, j]
