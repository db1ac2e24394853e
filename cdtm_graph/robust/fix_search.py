"""The incremental smoother's search for the fix: sightings held back, searches scheduled.

While the pose is too uncertain for the C-DTM linearization (a loose prior, a long stretch
without camera constraints), :class:`FixSearch` holds the frames' sightings back and, once
it holds a window of them, searches them for the fix (:func:`cdtm_graph.robust.acquisition.
acquire`); a failed search waits twice as long as the last before the next. The smoother
moves its estimate to a fix found and lets the held sightings in.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from cdtm_graph.dtm import Dtm
from cdtm_graph.flightlog import FlightConfig
from cdtm_graph.results import Rejection, Rejections
from cdtm_graph.robust.acquisition import (
    AcquisitionFrame,
    AcquisitionSettings,
    Correction,
    SearchPrior,
    acquire,
    needs_acquisition,
)

#: One held frame: (frame index, track ids (m,), pixels (m, 2)).
Held = tuple[int, np.ndarray, np.ndarray]


class FixSearch:
    """Held sightings and the searches over them.

    Args:
        settings: when to search and how. config: the log's flight.yaml (camera, initial
            state, gravity). dtm: the terrain. rejections: where sightings that waited
            longer than a window are counted (``no_fix``).
    """

    def __init__(self, settings: AcquisitionSettings, config: FlightConfig, dtm: Dtm,
                 rejections: Rejections):
        self.settings = settings
        self.config = config
        self.dtm = dtm
        self.rejections = rejections
        self.active = False  # sightings are held back
        self.held: list[Held] = []
        self.searches: list[dict] = []  # each search: frame, window, verdict, reason
        self._tried_at: int | None = None  # frame of the last search
        self._failed = 0  # searches failed since the last fix: each doubles the wait

    def needed_at_start(self) -> bool:
        """Whether the initial state's prior reaches farther than the smoothers pull in."""
        init = self.config.initial_state
        return needs_acquisition(np.eye(3) * init.sigma_position_m**2,
                                 init.sigma_attitude_rad, self.settings)

    def needed(self, world_T_body: np.ndarray, pose_cov: np.ndarray) -> bool:
        """Whether a frame's pose covariance (GTSAM's [rot, trans], body frame) reaches
        farther than the smoothers pull in (world position, heading)."""
        R = world_T_body[:3, :3]
        position = R @ pose_cov[3:6, 3:6] @ R.T
        heading = float(np.sqrt(max((R @ pose_cov[:3, :3] @ R.T)[2, 2], 0.0)))
        return needs_acquisition(position, heading, self.settings)

    def hold(self, k: int, seen: tuple[np.ndarray, np.ndarray] | None) -> None:
        """Hold frame k's sightings (ids, pixels) back until a fix is found."""
        self.active = True
        if seen is not None:
            self.held.append((k, *seen))

    def search(self, k: int, t_ns_of: Callable[[int], int],
               pose_of: Callable[[int], np.ndarray],
               prior_of: Callable[[int], SearchPrior]) -> Correction | None:
        """At frame k, search the held window if one is due: the frames older than the
        window lose their sightings first (``no_fix``). Returns the correction found (the
        held frames are the smoother's to let in, then :meth:`found`)."""
        window = self.settings.window_frames
        while len(self.held) > window:
            j, ids, _ = self.held.pop(0)
            self.rejections.add(Rejection.NO_FIX, j, len(ids))
        wait = self.settings.retry_every_frames * 2 ** max(self._failed - 1, 0)
        if len(self.held) < window or (self._tried_at is not None
                                       and k - self._tried_at < wait):
            return None
        self._tried_at = k
        frames = [AcquisitionFrame(t_ns_of(j), pose_of(j), ids, uv) for j, ids, uv in self.held]
        j0 = self.held[0][0]
        result = acquire(frames, self.config.camera, self.dtm, prior_of(j0), self.settings)
        self.searches.append({"frame": k, "window": [j0, k],
                              "verdict": result.verdict.value, "reason": result.reason})
        if result.correction is None:
            self._failed += 1
        return result.correction

    def forget_before(self, frame: int) -> None:
        """Drop the held frames before ``frame`` (the fixed lag let them go), counted as
        ``no_fix``."""
        while self.held and self.held[0][0] < frame:
            j, ids, _ = self.held.pop(0)
            self.rejections.add(Rejection.NO_FIX, j, len(ids))

    def found(self) -> list[Held]:
        """The fix was applied: stop holding; the frames that were held."""
        held, self.held = self.held, []
        self.active = False
        self._failed = 0
        return held

    def give_up(self) -> None:
        """The log ended before a fix was found: the held sightings count as ``no_fix``."""
        for j, ids, _ in self.held:
            self.rejections.add(Rejection.NO_FIX, j, len(ids))
        self.held = []
