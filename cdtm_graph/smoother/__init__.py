"""Smoothing a flight log: batch Levenberg-Marquardt and incremental iSAM2 / fixed lag.

- :mod:`~cdtm_graph.smoother.settings`: ``SmootherSettings`` (one set of defaults).
- :mod:`~cdtm_graph.smoother.batch`: ``smooth(log, dtm, settings) -> SmootherResult``.
- :mod:`~cdtm_graph.smoother.incremental`: ``IncrementalSmoother``, one frame at a time,
  each frame's sightings through the defences' stages (:mod:`cdtm_graph.robust.stages`).
- :mod:`~cdtm_graph.smoother.window`: its solver side (a backend, the estimates, the C-DTM
  factors in the solver); :mod:`~cdtm_graph.smoother.backends`: iSAM2 and the fixed lag.
- :mod:`~cdtm_graph.smoother.assembly`: one result assembly for both.
"""

from cdtm_graph.smoother.batch import smooth
from cdtm_graph.smoother.incremental import FrameUpdate, IncrementalSmoother
from cdtm_graph.smoother.settings import Progress, SmootherMode, SmootherSettings

__all__ = ["FrameUpdate", "IncrementalSmoother", "Progress", "SmootherMode",
           "SmootherSettings", "smooth"]
