"""The incremental smoother's frame flags: its own, and what each update says of its newest
frame.

A run's verdict (:func:`~cdtm_graph.verdict.rules.assess`) flags a frame from its whole
window, after the run. A live user reads each update as it comes, and an update whose
covariance is small while its features leave the map is confidently wrong unless it says
so then. So every update reports the flags known of its newest frame
(``FrameUpdate.flags``):

- the verdict's tests that need no solution, over the part of the frame's window that
  has arrived (:func:`~cdtm_graph.verdict.rules.newest_frame_flags`: the same kernel, the
  default :class:`~cdtm_graph.verdict.rules.VerdictSettings`' thresholds; the window's
  frames from the latest frames' spacing);
- the smoother's own (``no_fix``, ``search_beyond_lag``);
- ``imu_gap`` where the frame's interval was preintegrated across a gap (a sample held:
  :class:`~cdtm_graph.imu.GapNoise`, gaps beyond three nominal sample periods; finer than
  the verdict's test from the sample times, more than 0.1 s or 3 median intervals);
- ``clutter`` where its features carry, on average, more expected clutter height than
  the flag under the track tests' latest fit (:func:`~cdtm_graph.robust.clutter.
  frame_offset_m` of the factors that end at it; the run's result takes every factor
  that involves the frame, at the run's last fit).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from cdtm_graph.codes import Code
from cdtm_graph.imu import Preintegration
from cdtm_graph.results import Rejections
from cdtm_graph.robust.clutter import ClutterSettings, frame_offset_m
from cdtm_graph.robust.track_judge import TrackJudge
from cdtm_graph.verdict.fix_geometry import window_half_width
from cdtm_graph.verdict.rules import VerdictSettings, newest_frame_flags

#: A window's width live: from the median spacing of this many latest frames (a window is
#: seconds: where the frame rate changes, the frames it holds change with it; the verdict
#: takes the whole run's median), taken again every ``SPACING_EVERY`` frames.
SPACING_FRAMES, SPACING_EVERY = 64, 8


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
               track_ids: Sequence[np.ndarray] = ()) -> tuple[str, ...]:
        """The newest frame's flags (frame ``len(t_ns) - 1``) as known at its update.

        Args:
            t_ns: every frame's stamp so far. rejections: the run's so far.
            pim: its interval's preintegration (an IMU gap held across; None: frame 0).
            judge: the track tests (their clutter fit now; None: none).
            track_ids: the tracks of the features of the frame's own C-DTM factors.
        """
        k = len(t_ns) - 1
        if k % SPACING_EVERY == 0 or k < SPACING_EVERY:
            self._half = window_half_width(np.asarray(t_ns[-SPACING_FRAMES:], np.int64),
                                           self.verdict.window_s)
        first = max(0, k - 2 * self._half)  # (its window's frames with their own windows)
        flags = newest_frame_flags(
            np.array([self.features.get(j, 0) for j in range(first, k + 1)], float),
            rejections.in_frames(first, k + 1), first, self._half, self.verdict)
        flags += [f for f in self.own.get(k, ()) if f not in flags]
        if pim is not None and pim.spans_gap:
            flags.append(Code.IMU_GAP)
        # (its factors so far: those that end at it, as they entered)
        if judge is not None and self.clutter is not None \
                and frame_offset_m(judge.clutter, track_ids) > self.clutter.flag_offset_m:
            flags.append(Code.CLUTTER)
        return tuple(flags)
