"""Reading a flight log together with its DTM (the two inputs of every run)."""

from __future__ import annotations

import os

from cdtm_graph.dtm import Dtm, load_dtm
from cdtm_graph.flightlog import FlightLog, read_flightlog


def load_log_and_dtm(path: str | os.PathLike) -> tuple[FlightLog, Dtm]:
    """Read ``path`` (a ``cdtm-flightlog/1`` directory) and the DTM its flight.yaml names.

    Raises:
        FlightLogError: the log is malformed. DtmError: the DTM is.
    """
    flight = read_flightlog(path)
    cfg = flight.config.dtm
    dtm = load_dtm(cfg.path, origin_enu_m=cfg.origin_enu_m, sigma_h_m=cfg.sigma_h_m)
    return flight, dtm
