"""Reading a flight log directory (and the DTM its flight.yaml names)."""

from __future__ import annotations

import logging
import os
from pathlib import Path

from cdtm_graph.dtm import Dtm, load_dtm
from cdtm_graph.flightlog.config import _parse_flight_yaml
from cdtm_graph.flightlog.model import (
    FLIGHT_YAML,
    FRAMES_CSV,
    GROUNDTRUTH_CSV,
    IMU_CSV,
    NAV_CSV,
    TRACKS_CSV,
    FlightLog,
    normalized_path,
)
from cdtm_graph.flightlog.problems import _fail, _show
from cdtm_graph.flightlog.tables import (
    _GROUNDTRUTH_SPEC,
    _NAV_SPEC,
    _check_nav_times,
    _read_frames,
    _read_imu,
    _read_states,
    _read_tracks,
)

logger = logging.getLogger(__name__)


def read_flightlog(path: str | os.PathLike, read_tracks: bool = True) -> FlightLog:
    """Read and validate a ``cdtm-flightlog/1`` directory.

    Image files named in frames.csv are checked for existence only when there is no
    tracks.csv (then the images are the only source of features).

    Args:
        path: the log directory.
        read_tracks: False: leave tracks.csv unread (``tracks`` is None) and check the
            images instead, for a tracker about to replace it.

    Returns:
        The flight log; ``root`` and ``config.dtm.path`` are absolute.

    Raises:
        FlightLogError: anything in the log that does not follow FLIGHTLOG.md; the
            message names the file, the line and what was expected.
    """
    given = Path(path)
    root = normalized_path(given)

    def shown(name: str) -> str:
        return str(given / name)

    if not root.is_dir():
        _fail(str(given), 1, "not a directory", f"a flight log directory holding {FLIGHT_YAML}")
    for name in (FLIGHT_YAML, IMU_CSV, FRAMES_CSV):
        if not (root / name).is_file():
            _fail(shown(name), 1, "required file is missing",
                  f"{FLIGHT_YAML}, {IMU_CSV} and {FRAMES_CSV} in every flight log")

    config = _parse_flight_yaml(root / FLIGHT_YAML, shown(FLIGHT_YAML), root)
    imu = _read_imu(root / IMU_CSV, shown(IMU_CSV))
    frames, frames_first_line = _read_frames(root / FRAMES_CSV, shown(FRAMES_CSV))

    tracks = None
    if read_tracks and (root / TRACKS_CSV).is_file():
        tracks = _read_tracks(root / TRACKS_CSV, shown(TRACKS_CSV), len(frames),
                              config.camera.camera)
    else:
        # (without read_tracks the images are about to become the tracks: no alternative)
        alternative = f", or a {TRACKS_CSV}" if read_tracks else " to track"
        for k, image in enumerate(frames.image):
            if not image:
                _fail(shown(FRAMES_CSV), frames_first_line + k,
                      f"frame {k} has no image" + (f" and there is no {TRACKS_CSV}"
                                                   if read_tracks else ""),
                      f"an image path for every frame{alternative}")
            if not (root / image).is_file():
                _fail(shown(FRAMES_CSV), frames_first_line + k,
                      f"image {_show(image)} does not exist",
                      f"an image file relative to the log directory{alternative}")

    nav = None
    if (root / NAV_CSV).is_file():
        nav, nav_first_line = _read_states(root / NAV_CSV, shown(NAV_CSV), _NAV_SPEC)
        _check_nav_times(nav, frames, shown(NAV_CSV), nav_first_line)

    groundtruth = None
    if (root / GROUNDTRUTH_CSV).is_file():
        groundtruth, gt_first_line = _read_states(root / GROUNDTRUTH_CSV,
                                                  shown(GROUNDTRUTH_CSV), _GROUNDTRUTH_SPEC)
        if len(groundtruth) == 0:
            _fail(shown(GROUNDTRUTH_CSV), gt_first_line, "no rows", _GROUNDTRUTH_SPEC.expected_row)

    logger.debug("read %s: %d IMU samples, %d frames, %s track observations", root, len(imu),
                 len(frames), "no" if tracks is None else len(tracks))
    return FlightLog(root, config, imu, frames, tracks, nav, groundtruth)




def load_log_and_dtm(path: str | os.PathLike) -> tuple[FlightLog, Dtm]:
    """Read ``path`` (a ``cdtm-flightlog/1`` directory) and the DTM its flight.yaml names.

    Raises:
        FlightLogError: the log is malformed. DtmError: the DTM is.
    """
    flight = read_flightlog(path)
    cfg = flight.config.dtm
    dtm = load_dtm(cfg.path, origin_enu_m=cfg.origin_enu_m, sigma_h_m=cfg.sigma_h_m)
    return flight, dtm
