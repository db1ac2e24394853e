"""Writing a flight log directory: flight.yaml and the CSV files, bit-exact round trips."""

from __future__ import annotations

import os
import shutil
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from cdtm_graph.atomic import atomic_output_file
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
from cdtm_graph.flightlog.problems import _fail
from cdtm_graph.flightlog.tables import _STATE_COLUMNS
from cdtm_graph.geometry import rotation_to_quat_wxyz


def _csv_text(header: str, int_columns: Sequence[np.ndarray], float_columns: np.ndarray) -> str:
    """Rows with integers as integers and floats as repr (shortest exact round trip)."""
    # .tolist() gives Python floats, whose repr is the shortest exact form
    # (numpy scalars would print as np.float64(...)).
    columns = [list(map(str, np.asarray(c, dtype=np.int64).tolist())) for c in int_columns]
    columns += [list(map(repr, float_columns[:, j].tolist()))
                for j in range(float_columns.shape[1])]
    body = "\n".join(map(",".join, zip(*columns, strict=True)))
    return f"{header}\n{body}\n" if body else f"{header}\n"


def _states_text(states: States) -> str:
    floats = np.hstack([states.position_m, states.quaternion_wxyz, states.velocity_mps])
    return _csv_text("#t_ns," + ",".join(_STATE_COLUMNS), [states.t_ns], floats)


def _tracks_text(tracks: Tracks) -> str:
    return _csv_text("#frame,track_id,u,v", [tracks.frame, tracks.track_id], tracks.uv_px)


def write_tracks(tracks: Tracks, path: str | os.PathLike) -> None:
    """Write tracks.csv alone (as :func:`write_flightlog` writes it), atomically.

    The file appears complete or not at all; an existing one is replaced.

    Args:
        tracks: the tracks (rows sorted by frame, as FLIGHTLOG.md requires).
        path: the file to write (normally ``<log>/tracks.csv``).
    """
    text = _tracks_text(tracks)  # rendered before the disk is touched
    with atomic_output_file(path) as tmp:
        with tmp.open("w", encoding="utf-8", newline="\n") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())


def _yaml_document(log: FlightLog, target: Path) -> str:
    cfg = log.config
    cam = cfg.camera.camera
    body_T_cam = cfg.camera.body_T_cam
    dtm_path = Path(cfg.dtm.path)
    if dtm_path.is_absolute():
        try:
            dtm_text = dtm_path.relative_to(target).as_posix()
        except ValueError:
            dtm_text = str(dtm_path)
    else:
        dtm_text = dtm_path.as_posix()
    dtm: dict[str, Any] = {"path": dtm_text}
    if cfg.dtm.sigma_h_m is not None:
        dtm["sigma_h_m"] = float(cfg.dtm.sigma_h_m)
    dtm["origin_enu_m"] = [float(x) for x in cfg.dtm.origin_enu_m]
    camera: dict[str, Any] = {
        "resolution": [cam.width, cam.height],
        "intrinsics": [cam.fx, cam.fy, cam.cx, cam.cy],
    }
    if cam.distortion:
        camera["distortion_model"] = "radtan"
        camera["distortion_coeffs"] = list(cam.distortion)
    camera["pixel_sigma_px"] = float(cfg.camera.pixel_sigma_px)
    camera["body_T_cam"] = {
        "translation_m": body_T_cam[:3, 3].tolist(),
        "quaternion_wxyz": rotation_to_quat_wxyz(body_T_cam[:3, :3]).tolist(),
    }
    init = cfg.initial_state
    document: dict[str, Any] = {
        "format": FORMAT,
        "gravity_mps2": float(cfg.gravity_mps2),
        "dtm": dtm,
        "camera": camera,
        "imu": {key: float(getattr(cfg.imu, key)) for key in _IMU_KEYS},
        "initial_state": {
            **{name: getattr(init, name).tolist() for name, _ in _INITIAL_VECTORS},
            **{name: float(getattr(init, name)) for name in _INITIAL_SIGMAS},
        },
    }
    if cfg.extra:
        document["extra"] = cfg.extra
    # PyYAML writes floats with repr, so every number reads back bit for bit.
    return yaml.dump(document, Dumper=_FlightYamlDumper, sort_keys=False,
                     default_flow_style=False, allow_unicode=True)


class _FlightYamlDumper(yaml.SafeDumper):
    """Block mappings, lists on one line (``position_m: [0.0, 0.0, 1000.0]``): as FLIGHTLOG.md."""


def _represent_flow_list(dumper: yaml.SafeDumper, data: list) -> yaml.Node:
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=True)


_FlightYamlDumper.add_representer(list, _represent_flow_list)


def _render(log: FlightLog, target: Path) -> dict[str, str]:
    for image in log.frames.image:
        if any(c in image for c in ",\r\n"):
            raise ValueError(f"image path {image!r} holds a comma or a line break: "
                             f"frames.csv could not be read back")
    files = {
        FLIGHT_YAML: _yaml_document(log, target),
        IMU_CSV: _csv_text("#t_ns,gyro_x,gyro_y,gyro_z,acc_x,acc_y,acc_z", [log.imu.t_ns],
                           np.hstack([log.imu.gyro_radps, log.imu.acc_mps2])),
        FRAMES_CSV: "#t_ns,image\n" + "".join(
            f"{t},{image}\n" for t, image in zip(log.frames.t_ns.tolist(), log.frames.image,
                                                 strict=True)),
    }
    if log.tracks is not None:
        files[TRACKS_CSV] = _tracks_text(log.tracks)
    if log.nav is not None:
        files[NAV_CSV] = _states_text(log.nav)
    if log.groundtruth is not None:
        files[GROUNDTRUTH_CSV] = _states_text(log.groundtruth)
    return files


def write_flightlog(log: FlightLog, path: str | os.PathLike) -> None:
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

    Args:
        log: the flight log (``log.root`` is not used).
        path: the target directory; created with its parents if needed.

    Raises:
        FlightLogError: the target exists and is not a directory.
        ValueError: an image path holds a comma or a line break.
    """
    target = normalized_path(Path(path))
    if target.exists() and not target.is_dir():
        _fail(str(path), 1, "exists and is not a directory", "a directory for the flight log")
    files = _render(log, target)  # everything rendered before the disk is touched
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

