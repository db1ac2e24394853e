"""One smoothing run of a flight log, from the directory to the verdict.

- :mod:`~cdtm_graph.run.prepare`: the log read and its DTM loaded
  (:func:`load_log_and_dtm`; a geodetic DEM's window planned from the prior track).
- :mod:`~cdtm_graph.run.pipeline`: :func:`smooth_and_evaluate`: smooth, judge, evaluate
  against ground truth; no file I/O.

Names are loaded on first use, so that ``cdtm analyze`` (which only prepares) does not
pay for the smoothers.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from cdtm_graph.run.pipeline import RunOutput, smooth_and_evaluate
    from cdtm_graph.run.prepare import dem_region_m, load_flight_dtm, load_log_and_dtm

_WHERE = {"RunOutput": "pipeline", "smooth_and_evaluate": "pipeline",
          "dem_region_m": "prepare", "load_flight_dtm": "prepare", "load_log_and_dtm": "prepare"}
__all__ = ["RunOutput", "dem_region_m", "load_flight_dtm", "load_log_and_dtm",
           "smooth_and_evaluate"]


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        import importlib
        return getattr(importlib.import_module(f"cdtm_graph.run.{_WHERE[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
