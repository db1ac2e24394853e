"""How right a feature tracker is on a rendered flight: its matches against the renderer's truth.

For each frame pair (k-1, k) the ground seen at a feature's pixel in frame k-1 is found by
casting its ray into the true terrain from the true camera; its true pixel in frame k
is that point projected (:func:`~cdtm_graph.sim.render.true_correspondences`). A match is
wrong when the tracker's pixel is more than :data:`WRONG_MATCH_PX` from it, or when frame
k cannot see that ground at all (occluded, outside).

Two errors are measured: the *pair* error (frame k against the truth from the tracker's
own pixel in frame k-1: what one C-DTM factor sees) and the *drift* (each sighting against
the truth from the track's first sighting: what accumulates along a track).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cdtm_graph.dtm import Dtm
from cdtm_graph.frontend.tracker import FrameTracks, MatchStatus
from cdtm_graph.sim.render import true_correspondences

__all__ = ["WRONG_MATCH_PX", "MatchErrors", "match_errors"]

#: A match further than this from the truth (pixels) counts as wrong: several times the
#: tracker's noise (~0.2 px) and the backend's 0.5 px sigma, well below a feature's size.
WRONG_MATCH_PX = 2.0


@dataclass(frozen=True)
class MatchErrors:
    """Tracker matches against the truth, over a flight.

    Attributes:
        klt_px: (n,) pair errors of every Lucas-Kanade result (before any check; inf:
            ground not seen in the truth).
        verified_input_px: (m,) those that passed the forward-backward check (the input
            of the epipolar verification).
        accepted_px: (a,) those the tracker kept.
        drift_px: (d,) every kept sighting against the truth from its track's first one.
    """

    klt_px: np.ndarray
    verified_input_px: np.ndarray
    accepted_px: np.ndarray
    drift_px: np.ndarray

    @staticmethod
    def _wrong(errors: np.ndarray) -> float:
        return float(np.mean(~(errors <= WRONG_MATCH_PX))) if errors.size else 0.0

    def to_dict(self) -> dict:
        """The figures of the note: quantiles of kept matches, wrong-match fractions."""
        finite = self.accepted_px[np.isfinite(self.accepted_px)]
        drift = self.drift_px[np.isfinite(self.drift_px)]
        return {
            "matches_kept": int(self.accepted_px.size),
            "pair_error_median_px": float(np.median(finite)) if finite.size else float("nan"),
            "pair_error_p95_px": float(np.percentile(finite, 95)) if finite.size else float("nan"),
            "drift_median_px": float(np.median(drift)) if drift.size else float("nan"),
            "drift_p95_px": float(np.percentile(drift, 95)) if drift.size else float("nan"),
            "wrong_fraction_klt": self._wrong(self.klt_px),
            "wrong_fraction_before_verification": self._wrong(self.verified_input_px),
            "wrong_fraction_after_verification": self._wrong(self.accepted_px),
            "wrong_match_px": WRONG_MATCH_PX,
        }


def match_errors(terrain: Dtm, camera, world_T_cam: np.ndarray,
                 frames: list[FrameTracks]) -> MatchErrors:
    """Compare a tracker's output on rendered images with the truth.

    Args:
        terrain: the true terrain the images show.
        camera: the camera model.
        world_T_cam: (K, 4, 4) true camera poses of the images.
        frames: the tracker's output for images 0..K-1 in order.

    Returns:
        The errors.
    """
    klt, verified, accepted, drift = [], [], [], []
    n_ids = 1 + max((int(o.track_id.max()) for o in frames if o.track_id.size), default=-1)
    first_frame = np.full(n_ids, -1, np.int64)  # per track id: frame and pixel first seen
    first_uv = np.full((n_ids, 2), np.nan)
    for out in frames:
        k = out.frame
        if k > 0 and out.prev_track_id.size:
            truth, seen = true_correspondences(terrain, camera, world_T_cam[k - 1],
                                               world_T_cam[k], out.prev_uv_px)
            error = np.where(seen, np.linalg.norm(out.matched_uv_px - truth, axis=1), np.inf)
            has_klt = np.isin(out.status, [MatchStatus.TRACKED, MatchStatus.FORWARD_BACKWARD,
                                           MatchStatus.EPIPOLAR])
            klt.append(error[has_klt])
            verified.append(error[np.isin(out.status, [MatchStatus.TRACKED,
                                                       MatchStatus.EPIPOLAR])])
            accepted.append(error[out.status == MatchStatus.TRACKED])
        old_ids = out.track_id[~out.is_new]
        old_uv = out.uv_px[~out.is_new]
        for k0 in np.unique(first_frame[old_ids]):  # one cast per frame of first sighting
            rows = first_frame[old_ids] == k0
            truth, seen = true_correspondences(terrain, camera, world_T_cam[k0], world_T_cam[k],
                                               first_uv[old_ids[rows]])
            drift.append(np.where(seen, np.linalg.norm(old_uv[rows] - truth, axis=1), np.inf))
        new_ids = out.track_id[out.is_new]
        first_frame[new_ids] = k
        first_uv[new_ids] = out.uv_px[out.is_new]

    def cat(parts: list[np.ndarray]) -> np.ndarray:
        return np.concatenate(parts) if parts else np.zeros(0)

    return MatchErrors(cat(klt), cat(verified), cat(accepted), cat(drift))
