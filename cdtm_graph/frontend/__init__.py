"""The visual front-end: images to feature tracks (``cdtm track``).

- :mod:`~cdtm_graph.frontend.tracker`: :class:`FeatureTracker`, one image at a time
  (KLT with prediction, forward-backward check, epipolar RANSAC, bucketed replenishment).
- :mod:`~cdtm_graph.frontend.two_view`: two-view geometry on rays (verification, relative
  pose for the two-frame solve's initialization).
- :mod:`~cdtm_graph.frontend.track_log`: a whole log's images to tracks, with a report.

- :mod:`~cdtm_graph.frontend.settings`: :class:`TrackerSettings` (light: ``cdtm track
  --help``).

Part of the estimator core: nothing here imports the simulation harness. The settings are
loaded with the package, the tracker (OpenCV) on first use of one of its names.
"""

from __future__ import annotations

import sys
import types
from typing import TYPE_CHECKING, Any

from cdtm_graph.errors import ImageError
from cdtm_graph.frontend.settings import TrackerSettings

if TYPE_CHECKING:
    from cdtm_graph.frontend.track_log import (
        TrackingReport,
        TrackingResult,
        camera_rotation_from_imu,
        camera_rotations_from_imu,
        load_image,
        track_log,
    )
    from cdtm_graph.frontend.tracker import CameraModel, FeatureTracker, FrameTracks, MatchStatus

_WHERE = {"TrackingReport": "track_log", "TrackingResult": "track_log",
          "camera_rotation_from_imu": "track_log", "camera_rotations_from_imu": "track_log",
          "load_image": "track_log", "track_log": "track_log", "CameraModel": "tracker",
          "FeatureTracker": "tracker", "FrameTracks": "tracker", "MatchStatus": "tracker"}
__all__ = [
    "CameraModel", "FeatureTracker", "FrameTracks", "ImageError", "MatchStatus",
    "TrackerSettings", "TrackingReport", "TrackingResult", "camera_rotation_from_imu",
    "camera_rotations_from_imu",
    "load_image", "track_log",
]


class _Package(types.ModuleType):
    """The package's ``track_log`` is the function, as it was when the package loaded its
    modules eagerly: importing the submodule of the same name (which the import system
    binds on its package) leaves the name to the function."""

    def __setattr__(self, name: str, value: Any) -> None:
        if name == "track_log" and isinstance(value, types.ModuleType):
            return
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        import importlib
        return getattr(importlib.import_module(f"cdtm_graph.frontend.{_WHERE[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
