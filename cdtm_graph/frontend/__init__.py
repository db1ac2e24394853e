"""The visual front-end: images to feature tracks (``cdtm track``).

- :mod:`~cdtm_graph.frontend.tracker`: :class:`FeatureTracker`, one image at a time
  (KLT with prediction, forward-backward check, epipolar RANSAC, bucketed replenishment).
- :mod:`~cdtm_graph.frontend.two_view`: two-view geometry on rays (verification, relative
  pose for the two-frame solve's initialization).
- :mod:`~cdtm_graph.frontend.track_log`: a whole log's images to tracks, with a report.

Part of the estimator core: nothing here imports the simulation harness.
"""

from cdtm_graph.errors import ImageError
from cdtm_graph.frontend.track_log import (
    TrackingReport,
    TrackingResult,
    camera_rotation_from_imu,
    camera_rotations_from_imu,
    load_image,
    track_log,
)
from cdtm_graph.frontend.tracker import (
    CameraModel,
    FeatureTracker,
    FrameTracks,
    MatchStatus,
    TrackerSettings,
)

__all__ = [
    "CameraModel", "FeatureTracker", "FrameTracks", "ImageError", "MatchStatus",
    "TrackerSettings", "TrackingReport", "TrackingResult", "camera_rotation_from_imu",
    "camera_rotations_from_imu",
    "load_image", "track_log",
]
