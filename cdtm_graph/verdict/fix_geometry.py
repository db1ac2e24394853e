"""What each frame's window of C-DTM information says about the fix: the paper's section
V.B weak geometries (few features, flat terrain, a narrow footprint), from the
eigen-structure of the information the features give a rigid move of the poses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cdtm_graph.constants import NS_PER_S
from cdtm_graph.geometry import rigid_motion_transfer


def window_half_width(t_ns: np.ndarray, window_s: float) -> int:
    """Frames on each side of a frame in its window: ``window_s / 2`` over the median
    frame interval, at least 1."""
    if t_ns.size < 2:
        return 1
    dt_s = float(np.median(np.diff(t_ns))) / NS_PER_S
    return max(1, int(round(0.5 * window_s / dt_s))) if dt_s > 0 else 1


def window_sum(values: np.ndarray, half: int) -> np.ndarray:
    """(K, ...) -> (K, ...) sums over frames ``k - half .. k + half`` (clipped to the run)."""
    values = np.asarray(values, dtype=float)
    k = values.shape[0]
    cumulative = np.concatenate([np.zeros((1,) + values.shape[1:]), np.cumsum(values, axis=0)])
    lo = np.clip(np.arange(k) - half, 0, k)
    hi = np.clip(np.arange(k) + half + 1, 0, k)
    return cumulative[hi] - cumulative[lo]


def window_information(information: np.ndarray, position_m: np.ndarray, half: int
                       ) -> np.ndarray:
    """(K, 6, 6) C-DTM fix information of each frame's window, about that frame.

    Each frame's information (``SmootherResult.cdtm_information``: [rotation,
    translation], world axes, about its own position) is moved to the window's frame
    (:func:`~cdtm_graph.geometry.rigid_motion_transfer`) and summed.
    """
    k = information.shape[0]
    out = np.zeros_like(information)
    for offset in range(-half, half + 1):
        frames = np.arange(k)
        other = frames + offset
        inside = (other >= 0) & (other < k)
        A = rigid_motion_transfer(position_m[other[inside]], position_m[frames[inside]])
        out[inside] += np.swapaxes(A, 1, 2) @ information[other[inside]] @ A
    return out


def unit_height_information(information: np.ndarray) -> np.ndarray:
    """(K, 6, 6) each frame's information scaled to unit height information (zero where
    it has none), so that every frame of a window counts alike: a window half over a
    lake then reads as half flat, not as flat as the lake's many features make the sum."""
    height = information[:, 5, 5]
    scale = np.where(height > 0, 1.0 / np.where(height > 0, height, 1.0), 0.0)
    return information * scale[:, None, None]


@dataclass(frozen=True)
class FixGeometry:
    """What each frame's window of C-DTM information says about the fix (world axes).

    Attributes:
        horizontal: (K,) information of the weakest horizontal direction, attitude held
            (1/m^2).
        vertical: (K,) information of height, attitude held (1/m^2).
        attitude_free_fraction: (K,) share of ``horizontal`` left once the attitude is
            free (Schur complement), NaN where ``horizontal`` is zero.
    """

    horizontal: np.ndarray
    vertical: np.ndarray
    attitude_free_fraction: np.ndarray

    @property
    def flatness(self) -> np.ndarray:
        """(K,) horizontal over vertical information: about the squared RMS slope."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.vertical > 0, self.horizontal / self.vertical, np.nan)


def fix_geometry(window_info: np.ndarray) -> FixGeometry:
    """The eigen-structure of (K, 6, 6) window information [rotation, translation]."""
    translation = window_info[:, 3:, 3:]
    horizontal = np.linalg.eigvalsh(translation[:, :2, :2])[:, 0]
    vertical = translation[:, 2, 2]
    rotation = window_info[:, :3, :3]
    cross = window_info[:, 3:, :3]
    k = window_info.shape[0]
    free = np.full(k, np.nan)
    # the rotation block is singular only without any feature in the window
    ok = np.linalg.matrix_rank(rotation, hermitian=True) == 3
    if ok.any():
        schur = translation[ok] - cross[ok] @ np.linalg.solve(
            rotation[ok], np.swapaxes(cross[ok], 1, 2))
        weakest = np.linalg.eigvalsh(schur[:, :2, :2])[:, 0]
        with np.errstate(invalid="ignore", divide="ignore"):
            free[ok] = np.where(horizontal[ok] > 0, weakest / horizontal[ok], np.nan)
    return FixGeometry(np.clip(horizontal, 0.0, None), vertical, free)
