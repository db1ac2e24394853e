"""Smoothing a flight log: batch Levenberg-Marquardt and incremental iSAM2 / fixed lag.

- :mod:`~cdtm_graph.smoother.settings`: ``SmootherSettings`` (one set of defaults).
- :mod:`~cdtm_graph.smoother.batch`: ``smooth(log, dtm, settings) -> SmootherResult``.
- :mod:`~cdtm_graph.smoother.incremental`: ``IncrementalSmoother``, one frame at a time,
  each frame's sightings through the defences' stages (:mod:`cdtm_graph.robust.stages`).
- :mod:`~cdtm_graph.smoother.window`: its solver side (a backend, the estimates, the C-DTM
  factors in the solver); :mod:`~cdtm_graph.smoother.backends`: iSAM2 and the fixed lag.
- :mod:`~cdtm_graph.smoother.assembly`: one result assembly for both.
- :mod:`~cdtm_graph.smoother.modes`: :class:`SmootherMode`, light (the command line's
  ``--mode``).

Names other than ``SmootherMode`` are loaded on first use, so that ``cdtm smooth --help``
does not pay for GTSAM.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from cdtm_graph.smoother.modes import SmootherMode

if TYPE_CHECKING:
    from cdtm_graph.smoother.batch import smooth
    from cdtm_graph.smoother.incremental import FrameUpdate, IncrementalSmoother
    from cdtm_graph.smoother.settings import Progress, SmootherSettings

_WHERE = {"smooth": "batch", "FrameUpdate": "incremental", "IncrementalSmoother": "incremental",
          "Progress": "settings", "SmootherSettings": "settings"}
__all__ = ["FrameUpdate", "IncrementalSmoother", "Progress", "SmootherMode",
           "SmootherSettings", "smooth"]


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        import importlib
        return getattr(importlib.import_module(f"cdtm_graph.smoother.{_WHERE[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
