"""Sums over the points within a horizontal radius: the one search behind the spatial
views of the ground (:mod:`cdtm_graph.robust.mismatch`'s neighbourhoods,
:mod:`cdtm_graph.robust.clutter`'s neighbourhood means).

The reference points are binned in square cells as wide as the radius and sorted by cell
(column-major); a query then reads the three runs of cells (one per neighbouring column)
around its own. One compiled pass, not a tree built and walked from Python: a frame's few
hundred tracks or a flight's tens of thousands alike.
"""

from __future__ import annotations

import numpy as np

from factors.jit import njit


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
    key, origin, n_rows, n_finite = _cell_keys(ref, float(radius_m))
    # (numpy's sort: one inside numba costs seconds to compile)
    order = np.argsort(key, kind="stable")
    return _ball_sums_kernel(query, ref, values, key, order, n_finite, origin,
                             float(radius_m), n_rows)


def near_any(query_xy: np.ndarray, ref_xy: np.ndarray, radius_m: float) -> np.ndarray:
    """(Q,) bool: whether any reference point lies within ``radius_m`` of each query."""
    return ball_sums(query_xy, ref_xy, np.zeros((ref_xy.shape[0], 0)), radius_m)[1] > 0


@njit(cache=True)
def _cell_keys(ref, size):
    """Each reference point's cell (column-major; the rows offset by one so that a cell's
    neighbours never wrap), past every cell for a point with a NaN coordinate; the grid's
    origin, its rows and how many points are finite."""
    n = ref.shape[0]
    finite = np.empty(n, np.bool_)
    origin = np.full(2, np.inf)
    top = -np.inf
    for i in range(n):
        finite[i] = np.isfinite(ref[i, 0]) and np.isfinite(ref[i, 1])
        if finite[i]:
            origin[0] = min(origin[0], ref[i, 0])
            origin[1] = min(origin[1], ref[i, 1])
            top = max(top, ref[i, 1])
    key = np.full(n, np.iinfo(np.int64).max)
    n_finite = 0
    n_rows = 3
    if np.isfinite(top):
        n_rows = int(np.floor((top - origin[1]) / size)) + 3
        for i in range(n):
            if finite[i]:
                column = int(np.floor((ref[i, 0] - origin[0]) / size))
                row = int(np.floor((ref[i, 1] - origin[1]) / size)) + 1
                key[i] = column * n_rows + row
                n_finite += 1
    return key, origin, n_rows, n_finite


@njit(cache=True)
def _ball_sums_kernel(query, ref, values, key, order, n_finite, origin, radius, n_rows):
    m = values.shape[1]
    sums = np.zeros((query.shape[0], m))
    counts = np.zeros(query.shape[0], np.int64)
    if n_finite == 0:
        return sums, counts
    # the finite points in cell order, contiguous
    sorted_key = np.empty(n_finite, np.int64)
    xy = np.empty((n_finite, 2))
    sorted_values = np.empty((n_finite, m))
    for s in range(n_finite):
        r = order[s]
        sorted_key[s], xy[s, 0], xy[s, 1] = key[r], ref[r, 0], ref[r, 1]
        for j in range(m):
            sorted_values[s, j] = values[r, j]
    radius2 = radius * radius
    n_columns = sorted_key[-1] // n_rows + 1
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
            lo = np.searchsorted(sorted_key, c * n_rows + row - 1)
            hi = np.searchsorted(sorted_key, c * n_rows + row + 1, side="right")
            for s in range(lo, hi):
                dx, dy = xy[s, 0] - qx, xy[s, 1] - qy
                if dx * dx + dy * dy <= radius2:
                    counts[q] += 1
                    for j in range(m):
                        sums[q, j] += sorted_values[s, j]
    return sums, counts
