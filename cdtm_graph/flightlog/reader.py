"""Reading a flight log directory (its DTM is loaded where a run is prepared:
:mod:`cdtm_graph.run.prepare`)."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from cdtm_graph.errors import why_not_a_directory, why_not_a_file
from cdtm_graph.flightlog.config import _parse_flight_yaml
from cdtm_graph.flightlog.model import (
    FLIGHT_YAML,
    FRAMES_CSV,
    GROUNDTRUTH_CSV,
    IMU_CSV,
    NAV_CSV,
    TRACKS_CSV,
    FlightConfig,
    FlightLog,
    Frames,
    States,
    normalized_path,
)
from cdtm_graph.flightlog.problems import _fail, _fail_path, _show
from cdtm_graph.flightlog.tables import (
    _GEODETIC_STATE_COLUMNS,
    _GROUNDTRUTH_SPEC,
    _NAV_SPEC,
    _check_nav_times,
    _CsvSpec,
    _is_geodetic_states,
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
        FlightLogError: anything in the log that does not follow docs/flightlog.md; the
            message names the file, the line and what was expected.
    """
    given = Path(path)
    root = normalized_path(given)

    def shown(name: str) -> str:
        return str(given / name)

    if not root.is_dir():
        _fail_path(str(given), why_not_a_directory(root),
                   f"a flight log directory holding {FLIGHT_YAML}")
    for name in (FLIGHT_YAML, IMU_CSV, FRAMES_CSV):
        if not (root / name).is_file():
            why = why_not_a_file(root / name)
            _fail_path(shown(name), "required file is missing" if why == "does not exist"
                       else f"required file {why}",
                       f"{FLIGHT_YAML}, {IMU_CSV} and {FRAMES_CSV} in every flight log")
    optional = (*((TRACKS_CSV,) if read_tracks else ()), NAV_CSV, GROUNDTRUTH_CSV)
    for name in optional:  # a folder in their place is not their absence
        if os.path.lexists(root / name) and not (root / name).is_file():
            _fail_path(shown(name), why_not_a_file(root / name),
                       f"the optional {name} as a file, or no such entry")

    config = _parse_flight_yaml(root / FLIGHT_YAML, shown(FLIGHT_YAML), root)
    imu = _read_imu(root / IMU_CSV, shown(IMU_CSV))
    frames, frames_first_line = _read_frames(root / FRAMES_CSV, shown(FRAMES_CSV))
    frames = _on_imu_clock(frames, config.camera.time_offset_ns, shown(FRAMES_CSV),
                           frames_first_line)

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
                      f"image {_show(image)} {why_not_a_file(root / image)}",
                      f"an image file relative to the log directory{alternative}")

    nav = None
    if (root / NAV_CSV).is_file():
        nav, nav_first_line = _read_world_states(root / NAV_CSV, shown(NAV_CSV), _NAV_SPEC,
                                                 config)
        _check_nav_times(nav, frames, shown(NAV_CSV), nav_first_line)

    groundtruth = None
    if (root / GROUNDTRUTH_CSV).is_file():
        groundtruth, gt_first_line = _read_world_states(root / GROUNDTRUTH_CSV,
                                                        shown(GROUNDTRUTH_CSV),
                                                        _GROUNDTRUTH_SPEC, config)
        if len(groundtruth) == 0:
            _fail(shown(GROUNDTRUTH_CSV), gt_first_line, "no rows", _GROUNDTRUTH_SPEC.expected_row)

    logger.debug("read %s: %d IMU samples, %d frames, %s track observations", root, len(imu),
                 len(frames), "no" if tracks is None else len(tracks))
    return FlightLog(root, config, imu, frames, tracks, nav, groundtruth)



def _on_imu_clock(frames: Frames, offset_ns: int, shown: str, first_line: int) -> Frames:
    """frames.csv's camera stamps moved onto the IMU clock: ``t_imu = t_cam + offset``
    (docs/flightlog.md, frames.csv); the one place the offset is applied."""
    if offset_ns == 0 or len(frames) == 0:
        return frames
    limit = np.iinfo(np.int64)
    outside = ((frames.t_ns > limit.max - offset_ns) if offset_ns > 0
               else (frames.t_ns < limit.min - offset_ns))
    if outside.any():
        k = int(np.flatnonzero(outside)[0])
        _fail(shown, first_line + k, f"t_ns {int(frames.t_ns[k])} plus camera.time_offset_s "
              "leaves the int64 range", "frame times within int64 on the IMU clock")
    return Frames(frames.t_ns + offset_ns, frames.image)


def _read_world_states(path: Path, shown: str, spec: _CsvSpec,
                       config: FlightConfig) -> tuple[States, int]:
    """nav.csv or groundtruth.csv in the world frame, converted from geodetic columns."""
    geodetic = _is_geodetic_states(path)
    if geodetic and config.local_frame is None:
        _fail(shown, 1, f"geodetic columns {','.join(_GEODETIC_STATE_COLUMNS[:3])} without "
              "a geodetic origin", f"a top-level origin: in {FLIGHT_YAML}, or world columns "
              "px,py,pz,qw,qx,qy,qz,vx,vy,vz")
    states, first_line = _read_states(path, shown, spec)
    if geodetic and len(states):
        frame = config.local_frame
        assert frame is not None
        p = states.position_m
        position, quat, velocity = frame.states_from_geodetic(
            p[:, 0], p[:, 1], p[:, 2], states.quaternion_wxyz, states.velocity_mps)
        states = States(states.t_ns, position, quat, velocity)
    return states, first_line
