"""Preparing a run: a flight log read, the DTM window planned from what is known before
smoothing (nav.csv, or the IMU dead-reckoned from the initial state), the DTM loaded.

The reader (:mod:`cdtm_graph.flightlog`) only reads; planning a geodetic DEM's window
needs the IMU model, which sits above the log format, so it lives here.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from cdtm_graph.dem import DEFAULT_MARGIN_M, import_dem, track_region_m
from cdtm_graph.dtm import Dtm, load_dtm
from cdtm_graph.errors import DtmError
from cdtm_graph.flightlog import FlightLog, read_flightlog
from cdtm_graph.imu import dead_reckoning


def load_flight_dtm(flight: FlightLog) -> Dtm:
    """The world-frame DTM of a flight log.

    Without a geodetic origin: the file named by ``dtm.path``, shifted by
    ``dtm.origin_enu_m``. With one: the DEM tiles read under the flight and resampled into
    the local ENU (:func:`cdtm_graph.dem.import_dem`), over the region
    :func:`dem_region_m` gives.

    Raises:
        DtmError: the DTM is unreadable, ungeoreferenced or does not cover the flight.
    """
    cfg = flight.config.dtm
    frame = flight.config.local_frame
    if frame is None:
        dtm = load_dtm(cfg.path, origin_enu_m=cfg.origin_enu_m, sigma_h_m=cfg.sigma_h_m)
        _check_flight_over_dtm(flight, dtm)
        return dtm
    assert cfg.vertical_datum is not None  # the parser requires it with an origin
    return import_dem(cfg.paths, frame, dem_region_m(flight), cfg.vertical_datum,
                      crs=cfg.crs, spacing_m=cfg.spacing_m, sigma_h_m=cfg.sigma_h_m)


def dem_region_m(flight: FlightLog) -> tuple[float, float, float, float]:
    """The world region whose DEM a geodetic flight reads: its prior track plus a margin.

    The prior track is what is known before smoothing: the initial position and nav.csv's
    positions when there is a nav.csv; else the IMU dead-reckoned from the initial state
    (the smoother's IMU model), whose drift the margin then also covers. The margin is
    ``dtm.margin_m`` (default :data:`cdtm_graph.dem.DEFAULT_MARGIN_M`), plus, for a
    dead-reckoned track,
    :data:`DEAD_RECKONING_MARGIN_FRACTION` of its length. Ground truth is never used, so
    a log smooths the same with or without it.
    """
    cfg = flight.config
    margin = cfg.dtm.margin_m if cfg.dtm.margin_m is not None else DEFAULT_MARGIN_M
    track = [cfg.initial_state.position_m[None, :2]]
    if flight.nav is not None:
        track.append(flight.nav.position_m[:, :2])
    elif len(flight.frames) > 1:
        xy = dead_reckoning(cfg, flight.imu, flight.frames.t_ns).position_m[:, :2]
        track.append(xy)
        margin += DEAD_RECKONING_MARGIN_FRACTION * float(
            np.sum(np.linalg.norm(np.diff(xy, axis=0), axis=1)))
    return track_region_m(np.concatenate(track), margin)


def _check_flight_over_dtm(flight: FlightLog, dtm: Dtm) -> None:
    """Refuse a metric DTM nowhere near the flight (a projected map read without its offset
    puts the flight hundreds of km away, and the run would silently be IMU-only)."""
    xmin, xmax, ymin, ymax = dtm.bounds

    def near(xy: np.ndarray) -> bool:
        return bool(np.any((xy[:, 0] >= xmin - DEFAULT_MARGIN_M)
                           & (xy[:, 0] <= xmax + DEFAULT_MARGIN_M)
                           & (xy[:, 1] >= ymin - DEFAULT_MARGIN_M)
                           & (xy[:, 1] <= ymax + DEFAULT_MARGIN_M)))

    start = flight.config.initial_state.position_m[None, :2]
    if near(start) or (flight.nav is not None and near(flight.nav.position_m[:, :2])):
        return
    if len(flight.frames) > 1:
        free = dead_reckoning(flight.config, flight.imu, flight.frames.t_ns)
        if near(free.position_m[:, :2]):
            return
    x, y = start[0]
    raise DtmError(f"{flight.config.dtm.path}: the DTM covers x {xmin:.0f}..{xmax:.0f}, "
                   f"y {ymin:.0f}..{ymax:.0f} m but the flight starts at ({x:.0f}, {y:.0f}) m "
                   "and never comes near it; expected the DTM under the flight (a projected "
                   "map needs dtm.origin_enu_m, or a top-level origin: to place it by its CRS)")


#: With only the IMU to place the flight, the DEM margin grows by this fraction of the
#: dead-reckoned path (a flat-model mechanization of a perfect IMU drifts 1.7 km over a
#: 48 km, 240 s flight: docs/geodesy.md).
DEAD_RECKONING_MARGIN_FRACTION = 0.1


def load_log_and_dtm(path: str | os.PathLike) -> tuple[FlightLog, Dtm]:
    """Read ``path`` (a ``cdtm-flightlog/1`` directory) and the DTM its flight.yaml names.

    For a geodetic log the returned config's ``dtm.sigma_h_m`` is the imported DTM's: the
    DEM's own (flight.yaml's, or the Fig. 6 model at the DEM's pixel size) combined with
    the resampling error (:func:`cdtm_graph.dem.import_dem`).

    Raises:
        FlightLogError: the log is malformed. DtmError: the DTM is.
    """
    flight = read_flightlog(path)
    dtm = load_flight_dtm(flight)
    if flight.config.origin is not None:
        # The imported DTM's sigma_h holds the resampling error too; the factors read
        # sigma_h from the config first, so the config carries the DTM's.
        dtm_cfg = dataclasses.replace(flight.config.dtm, sigma_h_m=dtm.sigma_h())
        flight = dataclasses.replace(
            flight, config=dataclasses.replace(flight.config, dtm=dtm_cfg))
    return flight, dtm
