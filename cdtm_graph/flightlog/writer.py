"""Writing a flight log directory: flight.yaml and the CSV files, bit-exact round trips."""

from __future__ import annotations

import dataclasses
import os
import shutil
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from cdtm_graph.atomic import atomic_output_file
from cdtm_graph.camera import DistortionModel
from cdtm_graph.flightlog.config import _IMU_KEYS, _INITIAL_SIGMAS, _INITIAL_VECTORS
from cdtm_graph.flightlog.model import (
    FLIGHT_YAML,
    FORMAT,
    FRAMES_CSV,
    GROUNDTRUTH_CSV,
    IMU_CSV,
    LOG_FILES,
    NAV_CSV,
    TRACKS_CSV,
    FlightLog,
    States,
    Tracks,
    normalized_path,
)
from cdtm_graph.flightlog.problems import _fail_path
from cdtm_graph.flightlog.tables import _GEODETIC_STATE_COLUMNS, _STATE_COLUMNS
from cdtm_graph.geodesy import LocalFrame
from cdtm_graph.geometry import quat_wxyz_to_rotation, rotation_to_quat_wxyz


def _csv_text(header: str, int_columns: Sequence[np.ndarray], float_columns: np.ndarray) -> str:
    """Rows with integers as integers and floats as repr (shortest exact round trip)."""
    # .tolist() gives Python floats, whose repr is the shortest exact form
    # (numpy scalars would print as np.float64(...)).
    columns = [list(map(str, np.asarray(c, dtype=np.int64).tolist())) for c in int_columns]
    columns += [list(map(repr, float_columns[:, j].tolist()))
                for j in range(float_columns.shape[1])]
    body = "\n".join(map(",".join, zip(*columns, strict=True)))
    return f"{header}\n{body}\n" if body else f"{header}\n"


def _states_text(states: States, frame: LocalFrame | None = None) -> str:
    if frame is None:
        floats = np.hstack([states.position_m, states.quaternion_wxyz, states.velocity_mps])
        return _csv_text("#t_ns," + ",".join(_STATE_COLUMNS), [states.t_ns], floats)
    lat, lon, h, quat, vel = frame.states_to_geodetic(
        states.position_m, quat_wxyz_to_rotation(states.quaternion_wxyz), states.velocity_mps)
    floats = np.column_stack([lat, lon, h, quat, vel]).reshape(len(states), 10)
    return _csv_text("#t_ns," + ",".join(_GEODETIC_STATE_COLUMNS), [states.t_ns], floats)


def _tracks_text(tracks: Tracks) -> str:
    return _csv_text("#frame,track_id,u,v", [tracks.frame, tracks.track_id], tracks.uv_px)


def write_tracks(tracks: Tracks, path: str | os.PathLike) -> None:
    """Write tracks.csv alone (as :func:`write_flightlog` writes it), atomically.

    The file appears complete or not at all; an existing one is replaced.

    Args:
        tracks: the tracks (rows sorted by frame, as docs/flightlog.md "tracks.csv" requires).
        path: the file to write (normally ``<log>/tracks.csv``).
    """
    text = _tracks_text(tracks)  # rendered before the disk is touched
    with atomic_output_file(path) as tmp:
        with tmp.open("w", encoding="utf-8", newline="\n") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())


def _initial_state_document(log: FlightLog, geodetic: bool) -> dict[str, Any]:
    init = log.config.initial_state
    vectors = {name: getattr(init, name).tolist() for name, _ in _INITIAL_VECTORS}
    frame = log.config.local_frame
    if geodetic and frame is not None:
        lat, lon, h, quat, vel = frame.states_to_geodetic(
            init.position_m[None], quat_wxyz_to_rotation(init.quaternion_wxyz)[None],
            init.velocity_mps[None])
        del vectors["position_m"]
        vectors = {"latitude_deg": float(lat[0]), "longitude_deg": float(lon[0]),
                   "height_m": float(h[0]), **vectors,
                   "quaternion_wxyz": quat[0].tolist(), "velocity_mps": vel[0].tolist()}
    return {**vectors, **{name: float(getattr(init, name)) for name in _INITIAL_SIGMAS}}


def _yaml_document(log: FlightLog, target: Path, geodetic: bool = False) -> str:
    cfg = log.config
    cam = cfg.camera.camera
    body_T_cam = cfg.camera.body_T_cam

    def path_text(path: Path) -> str:
        if path.is_absolute():
            try:
                return path.relative_to(target).as_posix()
            except ValueError:
                return str(path)
        return path.as_posix()

    paths = [path_text(Path(p)) for p in cfg.dtm.paths]
    dtm: dict[str, Any] = {"path": paths if len(paths) > 1 else paths[0]}
    if cfg.dtm.sigma_h_m is not None:
        dtm["sigma_h_m"] = float(cfg.dtm.sigma_h_m)
    for key in cfg.dtm.OFFSET_SIGMA_KEYS:
        if getattr(cfg.dtm, key) is not None:
            dtm[key] = float(getattr(cfg.dtm, key))
    if cfg.origin is None:
        dtm["origin_enu_m"] = [float(x) for x in cfg.dtm.origin_enu_m]
    else:
        if cfg.dtm.vertical_datum is not None:
            dtm["vertical_datum"] = cfg.dtm.vertical_datum.value
        if cfg.dtm.crs is not None:
            dtm["crs"] = cfg.dtm.crs
        for key in ("margin_m", "spacing_m"):
            if getattr(cfg.dtm, key) is not None:
                dtm[key] = float(getattr(cfg.dtm, key))
    camera: dict[str, Any] = {
        "resolution": [cam.width, cam.height],
        "intrinsics": [cam.fx, cam.fy, cam.cx, cam.cy],
    }
    if cam.distortion_model is not DistortionModel.NONE:
        camera["distortion_model"] = cam.model.value
        camera["distortion_coeffs"] = list(cam.distortion)
    camera["pixel_sigma_px"] = float(cfg.camera.pixel_sigma_px)
    if cfg.camera.time_offset_s != 0.0:
        camera["time_offset_s"] = float(cfg.camera.time_offset_s)
    if cfg.camera.calibration is not None:
        camera["calibration"] = dataclasses.asdict(cfg.camera.calibration)
    if cfg.camera.principal_point_sigma_px is not None:
        camera["principal_point_sigma_px"] = float(cfg.camera.principal_point_sigma_px)
    camera["body_T_cam"] = {
        "translation_m": body_T_cam[:3, 3].tolist(),
        "quaternion_wxyz": rotation_to_quat_wxyz(body_T_cam[:3, :3]).tolist(),
    }
    document: dict[str, Any] = {"format": FORMAT}
    if cfg.origin is not None:
        document["origin"] = {"latitude_deg": cfg.origin.latitude_deg,
                              "longitude_deg": cfg.origin.longitude_deg,
                              "height_m": cfg.origin.height_m}
    document.update({
        "gravity_mps2": float(cfg.gravity_mps2),
        "dtm": dtm,
        "camera": camera,
        "imu": {key: float(getattr(cfg.imu, key)) for key in _IMU_KEYS},
        "initial_state": _initial_state_document(log, geodetic),
    })
    if cfg.extra:
        document["extra"] = cfg.extra
    # PyYAML writes floats with repr, so every number reads back bit for bit.
    return yaml.dump(document, Dumper=_FlightYamlDumper, sort_keys=False,
                     default_flow_style=False, allow_unicode=True)


class _FlightYamlDumper(yaml.SafeDumper):
    """Block mappings, lists on one line (``position_m: [0.0, 0.0, 1000.0]``): docs/flightlog.md."""


def _represent_flow_list(dumper: yaml.SafeDumper, data: list) -> yaml.Node:
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=True)


_FlightYamlDumper.add_representer(list, _represent_flow_list)


def _render(log: FlightLog, target: Path, geodetic: bool = False) -> dict[str, str]:
    for image in log.frames.image:
        if any(c in image for c in ",\r\n"):
            raise ValueError(f"image path {image!r} holds a comma or a line break: "
                             f"frames.csv could not be read back")
    files = {
        FLIGHT_YAML: _yaml_document(log, target, geodetic),
        IMU_CSV: _csv_text("#t_ns,gyro_x,gyro_y,gyro_z,acc_x,acc_y,acc_z", [log.imu.t_ns],
                           np.hstack([log.imu.gyro_radps, log.imu.acc_mps2])),
        # frames.csv holds the camera's stamps (docs/flightlog.md, frames.csv)
        FRAMES_CSV: "#t_ns,image\n" + "".join(
            f"{t},{image}\n" for t, image in zip(log.frame_t_cam_ns.tolist(),
                                                 log.frames.image, strict=True)),
    }
    if log.tracks is not None:
        files[TRACKS_CSV] = _tracks_text(log.tracks)
    frame = log.config.local_frame if geodetic else None
    if log.nav is not None:
        files[NAV_CSV] = _states_text(log.nav, frame)
    if log.groundtruth is not None:
        files[GROUNDTRUTH_CSV] = _states_text(log.groundtruth, frame)
    return files


def write_flightlog_files(log: FlightLog, directory: str | os.PathLike,
                          final_dir: str | os.PathLike | None = None,
                          geodetic: bool = False) -> list[str]:
    """Write the log's files into an existing ``directory``, plainly (not atomic).

    For a caller that writes into a staging directory it publishes itself
    (:func:`cdtm_graph.atomic.atomic_output_dir`); otherwise use :func:`write_flightlog`.

    Args:
        log: the flight log. directory: where to write now.
        final_dir: where the files will live (an absolute DTM path inside it is written
            relative to it); default ``directory``.
        geodetic: write states in geodetic form (:func:`write_flightlog`).

    Returns:
        The names written.
    """
    directory = Path(directory)
    if geodetic and log.config.origin is None:
        raise ValueError("geodetic=True needs a log with a geodetic origin")
    files = _render(log, normalized_path(Path(final_dir if final_dir is not None else directory)),
                    geodetic)
    for name, text in files.items():
        with (directory / name).open("w", encoding="utf-8", newline="\n") as f:
            f.write(text)
    return list(files)


def write_flightlog(log: FlightLog, path: str | os.PathLike, geodetic: bool = False) -> None:
    """Write a flight log directory (flight.yaml and the CSV files; not the DTM or images).

    Every file is first written into a temporary directory next to the target. A
    new (or empty) target directory then appears in one rename, complete. Into an
    existing directory (say one already holding the DTM) each file is moved by an
    atomic rename, and log files the new log lacks (a stale tracks.csv) are removed;
    other files are left alone. Nothing is ever half written.

    Floats are written with ``repr`` and times as integers, so reading the log back
    gives the same numbers bit for bit. ``body_T_cam`` is stored as a quaternion,
    so its rotation matrix round-trips to ~1e-16 (exactly for the identity and for
    half turns about x, y or z). The DTM path is written relative to the log directory when the DTM
    lies inside it, else absolute; a relative path is written as given. The writer
    does not validate: :func:`read_flightlog` does.

    With ``geodetic`` (and a geodetic origin in the log) the initial state, nav.csv and
    groundtruth.csv are written as a GNSS/INS gives them: latitude, longitude, ellipsoidal
    height, attitude and velocity in the local ENU; they then read back to ~1e-9 m, not
    bit for bit.

    Args:
        log: the flight log (``log.root`` is not used).
        path: the target directory; created with its parents if needed.
        geodetic: write states in geodetic form (needs ``log.config.origin``).

    Raises:
        FlightLogError: the target exists and is not a directory.
        ValueError: an image path holds a comma or a line break.
    """
    target = normalized_path(Path(path))
    if target.exists() and not target.is_dir():
        _fail_path(str(path), "exists and is not a directory", "a directory for the flight log")
    if geodetic and log.config.origin is None:
        raise ValueError("geodetic=True needs a log with a geodetic origin")
    files = _render(log, target, geodetic)  # everything rendered before the disk is touched
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = target.parent / f".{target.name}.{uuid.uuid4().hex[:12]}.tmp"
    staging.mkdir()
    try:
        for name, text in files.items():
            with (staging / name).open("w", encoding="utf-8", newline="\n") as f:
                f.write(text)
                f.flush()
                os.fsync(f.fileno())
        try:
            os.rename(staging, target)  # atomic; fails if target holds anything
            return
        except OSError:
            if not target.is_dir():
                raise
        for name in files:
            os.replace(staging / name, target / name)
        for name in LOG_FILES:
            if name not in files:
                (target / name).unlink(missing_ok=True)
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)

