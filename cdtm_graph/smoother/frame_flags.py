"""The incremental smoother's frame flags: its own, and what each update says of its newest
frame.

A run's verdict (:func:`~cdtm_graph.verdict.rules.assess`) flags a frame from its whole
window, after the run. A live user reads each update as it comes, and an update whose
covariance is small while its features leave the map is confidently wrong unless it says
so then. So every update reports the flags known of its newest frame
(``FrameUpdate.flags``): the verdict's tests that need no solution, over the part of the
frame's window that has arrived (:func:`~cdtm_graph.verdict.rules.newest_frame_flags`:
the same rules, the same thresholds), the smoother's own (``no_fix``), an IMU gap the
preintegration held a sample across, and clutter its features may carry (the track
tests' clutter fit, :func:`~cdtm_graph.robust.clutter.considered_offsets`, as the run's
result flags it).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from cdtm_graph.codes import Code
from cdtm_graph.imu import Preintegration
from cdtm_graph.results import Rejections
from cdtm_graph.robust.clutter import ClutterSettings, considered_offsets
from cdtm_graph.robust.track_judge import TrackJudge
from cdtm_graph.verdict.fix_geometry import window_half_width
from cdtm_graph.verdict.rules import VerdictSettings, newest_frame_flags
from factors import CdtmPairFactor

#: A window's width live: from the spacing of this many latest frames, taken again every
#: this many frames (the verdict takes the whole run's median spacing).
SPACING_FRAMES = 64


class FrameFlags:
    """The flags the incremental smoother sets itself (``no_fix``, ``search_beyond_lag``:
    the run's result keeps them) and those each update reports (:meth:`newest`).

    Args:
        verdict: the rules whose frame tests the updates apply.
        clutter: the clutter view's settings (its flag), None without a clutter view.
    """

    def __init__(self, verdict: VerdictSettings | None = None,
                 clutter: ClutterSettings | None = None):
        self.own: dict[int, list[str]] = {}
        self.features: dict[int, int] = {}  # frame -> C-DTM features that entered with it
        self._half = 1  # a window's frames each side (window_half_width)
        self.verdict = verdict or VerdictSettings()
        self.clutter = clutter

    def add(self, k: int, flags: Sequence[str]) -> None:
        if flags:
            self.own.setdefault(k, []).extend(flags)

    def clear(self, k: int, flag: str) -> None:
        """Frame k no longer holds ``flag`` (its held sightings are in)."""
        self.own[k].remove(flag)
        if not self.own[k]:
            del self.own[k]

    def frames_with(self, flag: str) -> np.ndarray:
        return np.array(sorted(k for k, flags in self.own.items() if flag in flags),
                        dtype=np.int64)

    def newest(self, t_ns: Sequence[int], rejections: Rejections,
               pim: Preintegration | None, judge: TrackJudge | None,
               factors: Sequence[CdtmPairFactor] = (),
               track_ids: Sequence[np.ndarray] = ()) -> tuple[str, ...]:
        """The newest frame's flags (frame ``len(t_ns) - 1``) as known at its update.

        Args:
            t_ns: every frame's stamp so far. rejections: the run's so far.
            pim: its interval's preintegration (an IMU gap held across; None: frame 0).
            judge: the track tests (their clutter fit now; None: none).
            factors, track_ids: the frame's own C-DTM factors and their features' tracks.
        """
        k = len(t_ns) - 1
        if k < SPACING_FRAMES or k % SPACING_FRAMES == 0:  # (from the latest frames)
            self._half = window_half_width(np.asarray(t_ns[-SPACING_FRAMES:], np.int64),
                                           self.verdict.window_s)
        first = max(0, k - 2 * self._half)  # (its window's frames with their own windows)
        flags = newest_frame_flags(
            np.array([self.features.get(j, 0) for j in range(first, k + 1)], float),
            rejections.in_frames(first, k + 1), first, self._half, self.verdict)
        flags += [f for f in self.own.get(k, ()) if f not in flags]
        if pim is not None and pim.spans_gap:
            flags.append(Code.IMU_GAP)
        if judge is not None and self.clutter is not None and factors:
            offset_m = considered_offsets(judge.clutter, [f.key_a for f in factors],
                                          [f.key_b for f in factors], track_ids, k + 1)[k]
            if offset_m > self.clutter.flag_offset_m:
                flags.append(Code.CLUTTER)
        return tuple(flags)
