"""The frame flags that need no solution, only what each frame was offered and kept: one
kernel for a run's verdict (every frame, after the run) and a live update (its newest
frame, :func:`~cdtm_graph.verdict.rules.newest_frame_flags`).

A frame's window is the frames within ``half`` of it, clipped to the frames given; the
shares, the off-map frames and the features per frame are taken over it as
:mod:`cdtm_graph.verdict.rules` states the rules (docs/verdict.md, "What a frame is
flagged for"). Compiled because a live update judges ~20 frames, where numpy's cost is
per call, not per frame (0.29 ms an update as numpy, ~0.1 ms in all now). Kept in a
module of its own: its prebuilt copy (:mod:`factors.jit`) stays valid while the rules
around it change.
"""

from __future__ import annotations

import numpy as np

from factors.jit import njit


@njit(cache=True)
def count_flags(features: np.ndarray, left_out: np.ndarray, offered: np.ndarray,
                min_fraction: np.ndarray, off_dtm_row: int, first: int, half: int,
                min_features: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each frame's flags from its window's counts.

    Args:
        features: (K,) C-DTM features ending at each frame.
        left_out: (M, K) features each rejection code left out (its reasons summed).
        offered: (K,) features offered (kept, or left out for a fault).
        min_fraction: (M,) each code's share of the window's offered that flags.
        off_dtm_row: the row of ``off_dtm`` (its frames have no fix), -1 if none.
        first: the index of the first frame in the run (frame 0 ends no pair).
        half: the frames on each side of a frame in its window.
        min_features: ``few_features`` below this mean over the window's fixed frames.

    Returns:
        ``(flagged (M, K), no_features (K,), few_features (K,), mean_features (K,))``:
        the codes' flags, the frames without a feature (and on the map), the frames whose
        window's frames with a fix hold fewer than ``min_features`` on average, and that
        mean.
    """
    m, k = left_out.shape
    later = np.empty(k, np.bool_)
    c_off = np.zeros(k + 1)
    c_left = np.zeros((m, k + 1))
    for j in range(k):
        later[j] = first + j >= 1
        c_off[j + 1] = c_off[j] + offered[j]
        for c in range(m):
            c_left[c, j + 1] = c_left[c, j] + left_out[c, j]
    flagged = np.zeros((m, k), np.bool_)
    for j in range(k):
        lo, hi = max(j - half, 0), min(j + half + 1, k)
        window_offered = c_off[hi] - c_off[lo]
        for c in range(m):
            total = c_left[c, hi] - c_left[c, lo]
            share = total / max(window_offered, 1.0) if window_offered > 0 else 0.0
            flagged[c, j] = later[j] and share >= min_fraction[c] and total > 0
        if off_dtm_row >= 0 and later[j] and features[j] == 0 and left_out[off_dtm_row, j] > 0:
            flagged[off_dtm_row, j] = True  # every ray of the frame missed the map
    no_features = np.zeros(k, np.bool_)
    judged = np.zeros(k, np.bool_)
    c_feat = np.zeros(k + 1)
    c_judged = np.zeros(k + 1)
    for j in range(k):
        off_map = off_dtm_row >= 0 and flagged[off_dtm_row, j]
        no_features[j] = later[j] and features[j] == 0 and not off_map
        judged[j] = later[j] and not (no_features[j] or off_map)
        c_feat[j + 1] = c_feat[j] + (features[j] if judged[j] else 0.0)
        c_judged[j + 1] = c_judged[j] + (1.0 if judged[j] else 0.0)
    few = np.zeros(k, np.bool_)
    mean_features = np.zeros(k)
    for j in range(k):
        lo, hi = max(j - half, 0), min(j + half + 1, k)
        mean_features[j] = (c_feat[hi] - c_feat[lo]) / max(c_judged[hi] - c_judged[lo], 1.0)
        few[j] = judged[j] and mean_features[j] < min_features
    return flagged, no_features, few, mean_features
