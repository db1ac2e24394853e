"""Smoothing a flight log: batch Levenberg-Marquardt and incremental iSAM2 / fixed lag.

- :mod:`~cdtm_graph.smoother.settings`: ``SmootherSettings`` (one set of defaults).
- :mod:`~cdtm_graph.smoother.batch`: ``smooth(log, dtm, settings) -> SmootherResult``.
- :mod:`~cdtm_graph.smoother.incremental`: ``IncrementalSmoother``, one frame at a time.
- :mod:`~cdtm_graph.smoother.backends`: the two incremental solvers behind it.
"""

from cdtm_graph.smoother.batch import smooth
from cdtm_graph.smoother.incremental import FrameUpdate, IncrementalSmoother
from cdtm_graph.smoother.settings import Progress, SmootherMode, SmootherSettings

__all__ = ["FrameUpdate", "IncrementalSmoother", "Progress", "SmootherMode",
           "SmootherSettings", "smooth"]
