"""The files of one run directory (DESIGN.md "Outputs of a run"): writers and readers.

A run directory holds::

    trajectory.tum        t_s tx ty tz qx qy qz qw                      (evo, TUM format)
    trajectory_cov.txt    the same 8 columns + 6 + 6 covariance columns (OpenVINS ov_eval)
    states.csv            t_ns, position, quaternion wxyz, velocity, biases, 1-sigma
    covariances.npz       per-frame marginal covariances in GTSAM's tangent order
    report.json           counts, solver statistics, settings, flags + the caller's report
    trajectory_geodetic.csv  (logs with a geodetic origin) t_ns, WGS84 latitude, longitude,
                          ellipsoidal height, attitude and velocity in the local ENU,
                          1-sigma north/east/up
    trajectory.geojson    (logs with a geodetic origin) the track for GIS tools
    groundtruth.tum       (logs with ground truth) the true poses at the frames of
                          trajectory.tum it covers, same format and world frame:
                          ``evo_ape tum groundtruth.tum trajectory.tum`` reads both
    groundtruth_geodetic.csv  (ground truth and a geodetic origin) the same in
                          trajectory_geodetic.csv's first eleven columns
    <extra files>         e.g. PNG plots, written by caller-supplied functions

Conventions of the files:

- ``world`` is local ENU, ``body`` the IMU; every pose is ``world_T_body``.
- Times in the text files are seconds written from integer nanoseconds as
  ``<seconds>.<9 digits>`` (exact: a float64 cannot hold a 2024 epoch to 1 ns, a
  decimal string can); the readers parse them back to the same integer nanoseconds.
- Floats are written with Python's shortest round-trip ``repr``: every value reads back
  bit for bit, and a covariance of 1e-12 rad^2 is not printed as 0.000000000.
- ``trajectory_cov.txt`` carries *world-frame* 3x3 blocks (rotated from GTSAM's body-frame
  tangent with :func:`~cdtm_graph.results.pose_covariance_in_world`): the orientation
  block is the covariance of ``dtheta`` in ``R_true = Exp(dtheta) R_est`` (a small
  rotation about the world axes), the position block that of ``p_true - p_est``. Upper
  triangles in the order xx xy xz yy yz zz, orientation first, as ov_eval's loader reads
  them.
- ``covariances.npz`` keeps GTSAM's own order: pose [rotation, translation] with the
  perturbation on the right, ``world_T_body * Exp(xi)`` (body frame); bias [accel, gyro].

Everything is written inside :func:`~cdtm_graph.atomic.atomic_output_dir`: a failure
anywhere (including in an extra-file writer) leaves the target directory as it was, and
no file cdtm did not write there is ever replaced or deleted; the hidden manifest
``.cdtm-run.json`` lists the files the run wrote.
"""

from __future__ import annotations

import dataclasses
import enum
import json
import math
import os
import zipfile
from collections.abc import Callable, Iterator, Mapping, Sequence
from decimal import Decimal, InvalidOperation
from pathlib import Path, PurePath
from typing import Any

import numpy as np

from cdtm_graph.atomic import atomic_output_dir
from cdtm_graph.constants import NS_PER_S
from cdtm_graph.errors import CdtmError
from cdtm_graph.flightlog import States
from cdtm_graph.geodesy import LocalFrame
from cdtm_graph.geometry import quat_wxyz_to_rotation, rotation_to_quat_wxyz
from cdtm_graph.results import SmootherResult, pose_covariance_in_world
from cdtm_graph.verdict.evaluation import groundtruth_at_frames

TRAJECTORY_TUM = "trajectory.tum"
TRAJECTORY_COV = "trajectory_cov.txt"
STATES_CSV = "states.csv"
COVARIANCES_NPZ = "covariances.npz"
REPORT_JSON = "report.json"
TRAJECTORY_GEODETIC_CSV = "trajectory_geodetic.csv"
TRAJECTORY_GEOJSON = "trajectory.geojson"
GROUNDTRUTH_TUM = "groundtruth.tum"
GROUNDTRUTH_GEODETIC_CSV = "groundtruth_geodetic.csv"
#: The files ``write_run`` always writes, and those it adds for a log with a geodetic
#: origin; extra files may take none of these names.
RUN_FILES = (TRAJECTORY_TUM, TRAJECTORY_COV, STATES_CSV, COVARIANCES_NPZ, REPORT_JSON)
GEODETIC_RUN_FILES = (TRAJECTORY_GEODETIC_CSV, TRAJECTORY_GEOJSON)
#: The ground truth at the frames, for a log that has it (the second with a geodetic origin).
GROUNDTRUTH_RUN_FILES = (GROUNDTRUTH_TUM, GROUNDTRUTH_GEODETIC_CSV)
#: Every name ``write_run`` may write itself.
ALL_RUN_FILES = RUN_FILES + GEODETIC_RUN_FILES + GROUNDTRUTH_RUN_FILES

#: Columns of trajectory_geodetic.csv. Its first eleven are those of a geodetic nav.csv or
#: groundtruth.csv, so the file can be given back as either.
GEODETIC_COLUMNS = (
    "t_ns", "latitude_deg", "longitude_deg", "height_m",  # WGS84, ellipsoidal height
    "qw", "qx", "qy", "qz",  # body -> local ENU at the position
    "ve", "vn", "vu",  # m/s in the local ENU
    "sigma_north_m", "sigma_east_m", "sigma_up_m",  # 1-sigma position, local ENU
)
#: The writer named in the run directory's manifest (``.cdtm-run.json``).
RUN_WRITER = "smooth"

POSE_COVARIANCE_CONVENTION = ("Pose3 tangent [rot, trans], right perturbation (body frame): "
                              "world_T_body_true = world_T_body_est * Exp(xi)")
BIAS_COVARIANCE_CONVENTION = "imuBias.ConstantBias [accel (m/s^2), gyro (rad/s)]"
VELOCITY_COVARIANCE_CONVENTION = "world frame, (m/s)^2"

TUM_COLUMNS = ("t_s", "tx", "ty", "tz", "qx", "qy", "qz", "qw")
#: Upper-triangle order of a symmetric 3x3 block, as OpenVINS' ov_eval reads it.
UPPER_TRIANGLE = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_UPPER_NAMES = ("xx", "xy", "xz", "yy", "yz", "zz")
COV_COLUMNS = (TUM_COLUMNS + tuple(f"ori_{n}" for n in _UPPER_NAMES)
               + tuple(f"pos_{n}" for n in _UPPER_NAMES))

STATES_COLUMNS = (
    "t_ns", "px", "py", "pz", "qw", "qx", "qy", "qz", "vx", "vy", "vz",
    "bgx", "bgy", "bgz", "bax", "bay", "baz",
    # 1-sigma: position (m) and orientation (rad, small rotations about the world axes)
    # from the world-frame blocks; velocity (m/s, world); biases (rad/s, m/s^2).
    "sigma_px", "sigma_py", "sigma_pz", "sigma_rx", "sigma_ry", "sigma_rz",
    "sigma_vx", "sigma_vy", "sigma_vz",
    "sigma_bgx", "sigma_bgy", "sigma_bgz", "sigma_bax", "sigma_bay", "sigma_baz",
)

#: A quaternion read from a file further than this from unit norm is a data error (six
#: printed digits, as some tools write, stay well inside it).
QUATERNION_UNIT_TOL = 1e-3

#: Writes one extra file at the given path (inside the temporary run directory).
ExtraFileWriter = Callable[[Path], Any]


# --------------------------------------------------------------------------- formatting


def format_t_s(t_ns: int) -> str:
    """Seconds with exactly nine decimals from integer nanoseconds: ``-1`` -> ``-0.000000001``."""
    t = int(t_ns)
    sign = "-" if t < 0 else ""
    seconds, nanoseconds = divmod(abs(t), NS_PER_S)
    return f"{sign}{seconds}.{nanoseconds:09d}"


def parse_t_s(token: str) -> int:
    """Integer nanoseconds from a decimal seconds string (any float syntax), rounded to 1 ns.

    Raises:
        ValueError: the token is not a finite number.
    """
    try:
        value = Decimal(token)
    except InvalidOperation:
        raise ValueError(f"not a number: {token!r}") from None
    if not value.is_finite():
        raise ValueError(f"not finite: {token!r}")
    return int((value * NS_PER_S).to_integral_value())


def _rows_text(t_ns: np.ndarray, values: np.ndarray, sep: str = " ",
               t_format: Callable[[int], str] = format_t_s) -> str:
    """One line per row: the formatted time, then every value in shortest round-trip form."""
    lines = [sep.join([t_format(int(t)), *map(repr, row)])
             for t, row in zip(t_ns.tolist(), values.tolist(), strict=True)]
    return "\n".join(lines) + "\n" if lines else ""


def _upper(cov: np.ndarray) -> np.ndarray:
    """(K, 3, 3) -> (K, 6) upper triangles in ``UPPER_TRIANGLE`` order."""
    rows, cols = zip(*UPPER_TRIANGLE, strict=True)
    return cov[:, list(rows), list(cols)]


def _sigma(cov: np.ndarray) -> np.ndarray:
    """(K, n, n) -> (K, n) square roots of the diagonals (NaN where a variance is negative)."""
    var = np.diagonal(cov, axis1=1, axis2=2)
    with np.errstate(invalid="ignore"):
        return np.sqrt(np.where(var >= 0, var, np.nan))


# --------------------------------------------------------------------------- JSON


def to_json_safe(obj: Any) -> Any:
    """A structure ``json.dumps(..., allow_nan=False)`` accepts.

    Dataclasses become dicts, numpy arrays and tuples lists, numpy scalars Python ones,
    mapping keys strings, enums their values, paths strings; NaN and +-inf become None
    (JSON has no token for them, and a bare ``NaN`` breaks strict parsers).
    """
    if obj is None or isinstance(obj, bool | str):
        return obj
    if isinstance(obj, enum.Enum):
        return to_json_safe(obj.value)
    if isinstance(obj, int | np.integer):
        return int(obj)
    if isinstance(obj, float | np.floating):
        value = float(obj)
        return value if math.isfinite(value) else None
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, np.ndarray):
        return to_json_safe(obj.tolist())
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_json_safe(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, Mapping):
        return {str(to_json_safe(k)): to_json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple | set | frozenset):
        return [to_json_safe(v) for v in obj]
    if isinstance(obj, PurePath):
        return str(obj)
    raise TypeError(f"cannot write a {type(obj).__name__} to JSON: {obj!r}")


def run_report(result: SmootherResult, report: Mapping[str, Any]) -> dict[str, Any]:
    """The content of report.json: the result's counts, statistics, settings and flags,
    the file conventions, and the caller's ``report`` (timings, evaluation, degeneracy...).

    Raises:
        ValueError: ``report`` reuses a key this function fills in.
    """
    generated: dict[str, Any] = {
        "counts": result.counts,
        "solver": result.stats,
        "settings": result.settings,
        "stages": result.stages,
        "flags": result.flags,
        "terrain": result.terrain,
        "calibration": result.calibration,
        "map_offset": result.map_offset,
        "conventions": {
            "world": "local ENU, metres",
            "pose": "world_T_body (body = IMU)",
            "covariances.npz/pose": POSE_COVARIANCE_CONVENTION,
            "covariances.npz/bias": BIAS_COVARIANCE_CONVENTION,
            "covariances.npz/velocity": VELOCITY_COVARIANCE_CONVENTION,
            "trajectory_cov.txt": ("world frame: orientation rad^2 of dtheta in "
                                   "R_true = Exp(dtheta) R_est, position m^2"),
            "time": "t_s written from integer ns with 9 decimals",
        },
    }
    clash = sorted(set(generated) & set(report))
    if clash:
        raise ValueError(f"report keys {clash} are filled in by write_run; use other names")
    return to_json_safe({**generated, **report})


# --------------------------------------------------------------------------- writers


def _check_result(result: SmootherResult) -> int:
    est, cov = result.estimate, result.covariances
    k = len(est)
    expected = {
        "estimate.world_T_body": (est.world_T_body, (k, 4, 4)),
        "estimate.velocity_mps": (est.velocity_mps, (k, 3)),
        "estimate.gyro_bias": (est.gyro_bias, (k, 3)),
        "estimate.accel_bias": (est.accel_bias, (k, 3)),
        "covariances.pose": (cov.pose, (k, 6, 6)),
        "covariances.velocity": (cov.velocity, (k, 3, 3)),
        "covariances.bias": (cov.bias, (k, 6, 6)),
    }
    for name, (array, shape) in expected.items():
        if np.shape(array) != shape:
            raise ValueError(f"{name} has shape {np.shape(array)}, expected {shape}")
    return k


def _tum_values(world_T_body: np.ndarray) -> np.ndarray:
    """(K, 7) ``tx ty tz qx qy qz qw``."""
    q_wxyz = rotation_to_quat_wxyz(world_T_body[:, :3, :3])
    return np.column_stack([world_T_body[:, :3, 3], q_wxyz[:, 1:], q_wxyz[:, :1]])


def write_trajectory_tum(path: str | os.PathLike, t_ns: np.ndarray,
                         world_T_body: np.ndarray, what: str = "world_T_body") -> None:
    """Write a TUM trajectory ``t_s tx ty tz qx qy qz qw`` (one '#' header line).

    Args:
        path: file to write (not atomic by itself; ``write_run`` makes it so).
        t_ns: (K,) int64 times.
        world_T_body: (K, 4, 4) body poses in world.
        what: what the poses are, for the header line.
    """
    header = "# " + " ".join(TUM_COLUMNS) + f"  ({what}; world = local ENU, m)\n"
    text = _rows_text(np.asarray(t_ns, dtype=np.int64), _tum_values(world_T_body))
    Path(path).write_text(header + text)


def write_trajectory_cov(path: str | os.PathLike, t_ns: np.ndarray, world_T_body: np.ndarray,
                         pose_cov: np.ndarray) -> None:
    """Write the 20-column trajectory-with-covariance file (OpenVINS ov_eval format).

    Args:
        path: file to write.
        t_ns: (K,) int64 times.
        world_T_body: (K, 4, 4) body poses in world.
        pose_cov: (K, 6, 6) GTSAM tangent order [rot, trans], body frame; rotated to the
            world frame here.
    """
    orientation_cov, position_cov = pose_covariance_in_world(world_T_body, pose_cov)
    values = np.column_stack([_tum_values(world_T_body), _upper(orientation_cov),
                              _upper(position_cov)])
    header = ("# " + " ".join(COV_COLUMNS) + "  (world frame: orientation rad^2 of dtheta in "
              "R_true = Exp(dtheta) R_est, position m^2; upper triangles)\n")
    Path(path).write_text(header + _rows_text(np.asarray(t_ns, dtype=np.int64), values))


def write_states_csv(path: str | os.PathLike, result: SmootherResult) -> None:
    """Write ``states.csv``: one row per frame, columns ``STATES_COLUMNS``, one header line."""
    est, cov = result.estimate, result.covariances
    orientation_cov, position_cov = pose_covariance_in_world(est.world_T_body, cov.pose)
    values = np.column_stack([
        est.position_m, rotation_to_quat_wxyz(est.world_T_body[:, :3, :3]), est.velocity_mps,
        est.gyro_bias, est.accel_bias,
        _sigma(position_cov), _sigma(orientation_cov), _sigma(cov.velocity),
        # GTSAM's bias order is [accel, gyro]; the columns are gyro first.
        _sigma(cov.bias[:, 3:, 3:]), _sigma(cov.bias[:, :3, :3]),
    ])
    text = _rows_text(np.asarray(est.t_ns, dtype=np.int64), values, sep=",", t_format=str)
    Path(path).write_text(",".join(STATES_COLUMNS) + "\n" + text)


def write_covariances_npz(path: str | os.PathLike, result: SmootherResult) -> None:
    """Write ``covariances.npz``: t_ns, pose, velocity, bias and their conventions as strings."""
    cov = result.covariances
    with open(path, "wb") as f:
        np.savez(f, t_ns=np.asarray(result.estimate.t_ns, dtype=np.int64),
                 pose=np.asarray(cov.pose, dtype=float),
                 velocity=np.asarray(cov.velocity, dtype=float),
                 bias=np.asarray(cov.bias, dtype=float),
                 convention=np.array(POSE_COVARIANCE_CONVENTION),
                 velocity_convention=np.array(VELOCITY_COVARIANCE_CONVENTION),
                 bias_convention=np.array(BIAS_COVARIANCE_CONVENTION))


def _geodetic_states(result: SmootherResult, frame: LocalFrame) -> np.ndarray:
    """(K, 13): the columns of ``GEODETIC_COLUMNS`` after t_ns."""
    est = result.estimate
    lat, lon, h, quat, vel = frame.states_to_geodetic(
        est.position_m, est.world_T_body[:, :3, :3], est.velocity_mps)
    _, position_cov = pose_covariance_in_world(est.world_T_body, result.covariances.pose)
    sigma_enu = _sigma(frame.covariance_to_enu(est.position_m, position_cov))
    return np.column_stack([lat, lon, h, quat, vel, sigma_enu[:, 1], sigma_enu[:, 0],
                            sigma_enu[:, 2]])


def write_trajectory_geodetic_csv(path: str | os.PathLike, result: SmootherResult,
                                  frame: LocalFrame) -> None:
    """Write ``trajectory_geodetic.csv``: one row per frame, columns ``GEODETIC_COLUMNS``.

    Latitude and longitude in degrees (WGS84), height above the WGS84 ellipsoid (m);
    attitude (body -> ENU) and velocity in the local ENU at the row's own position; the
    position's 1-sigma along the local north, east and up (m). Floats in shortest
    round-trip form.
    """
    values = _geodetic_states(result, frame)
    t_ns = np.asarray(result.estimate.t_ns, dtype=np.int64)
    text = _rows_text(t_ns, values, sep=",", t_format=str)
    Path(path).write_text(",".join(GEODETIC_COLUMNS) + "\n" + text)


def write_trajectory_geojson(path: str | os.PathLike, result: SmootherResult,
                             frame: LocalFrame) -> None:
    """Write ``trajectory.geojson`` (RFC 7946: WGS84, [longitude, latitude, height]).

    One LineString of the whole track, then one Point per frame with its time and
    1-sigma north/east/up as properties. Heights are ellipsoidal (m).
    """
    values = _geodetic_states(result, frame)
    t_ns = np.asarray(result.estimate.t_ns, dtype=np.int64)
    lat, lon, h = values[:, 0], values[:, 1], values[:, 2]
    coords = [[round(float(x), 9), round(float(y), 9), round(float(z), 3)]
              for x, y, z in zip(lon, lat, h)]
    features: list[dict[str, Any]] = [{
        "type": "Feature",
        "geometry": {"type": "LineString", "coordinates": coords},
        "properties": {"name": "trajectory", "t_ns_first": int(t_ns[0]) if len(t_ns) else None,
                       "t_ns_last": int(t_ns[-1]) if len(t_ns) else None,
                       "frames": int(len(t_ns)), "height": "WGS84 ellipsoidal, m"},
    }]
    for k, coord in enumerate(coords):
        features.append({
            "type": "Feature",
            "geometry": {"type": "Point", "coordinates": coord},
            "properties": {"frame": k, "t_ns": int(t_ns[k]),
                           "sigma_north_m": values[k, 10], "sigma_east_m": values[k, 11],
                           "sigma_up_m": values[k, 12]},
        })
    document = {"type": "FeatureCollection", "features": features}
    Path(path).write_text(json.dumps(to_json_safe(document), allow_nan=False) + "\n")


def write_groundtruth_geodetic_csv(path: str | os.PathLike, truth: States,
                                   frame: LocalFrame) -> None:
    """Write ``groundtruth_geodetic.csv``: the true states in the first eleven columns of
    ``GEODETIC_COLUMNS`` (those of a geodetic groundtruth.csv), floats in shortest
    round-trip form."""
    lat, lon, h, quat, vel = frame.states_to_geodetic(
        truth.position_m, truth.world_T_body[:, :3, :3], truth.velocity_mps)
    values = np.column_stack([lat, lon, h, quat, vel])
    text = _rows_text(truth.t_ns, values, sep=",", t_format=str)
    Path(path).write_text(",".join(GEODETIC_COLUMNS[:11]) + "\n" + text)


def groundtruth_run_files(result: SmootherResult, groundtruth: States | None,
                          frame: LocalFrame | None) -> tuple[str, ...]:
    """The ground-truth files ``write_run`` writes for this result (none without ground
    truth or when no frame lies inside its time range)."""
    if groundtruth is None:
        return ()
    inside, _ = groundtruth_at_frames(result.estimate.t_ns, groundtruth)
    if not inside.any():
        return ()
    return GROUNDTRUTH_RUN_FILES if frame is not None else (GROUNDTRUTH_TUM,)


def _check_extra_name(name: str) -> None:
    pure = PurePath(name)
    if (not name or pure.name != name or name in (".", "..") or "\\" in name
            or name in ALL_RUN_FILES):
        raise ValueError(f"extra file name {name!r} must be a plain file name other than "
                         f"{', '.join(ALL_RUN_FILES)}")


def write_run(out_dir: str | os.PathLike, result: SmootherResult, report: Mapping[str, Any],
              extra_files: Sequence[tuple[str, ExtraFileWriter]] = (), *, force: bool = False,
              protected: Sequence[str | os.PathLike] = (),
              frame: LocalFrame | None = None, groundtruth: States | None = None) -> None:
    """Write a whole run directory, atomically, never over a file cdtm did not write.

    The files are written into a staging directory and published into ``out_dir`` only
    when every file, extras included, has been written; on any exception ``out_dir``
    keeps its old content (or stays absent) and the exception propagates. The rules of
    :func:`~cdtm_graph.atomic.atomic_output_dir` apply (writer ``"smooth"``): an earlier
    run there is replaced file by file, files cdtm did not write are kept.

    Args:
        out_dir: the run directory: new, empty, or an earlier cdtm output directory.
        result: what the smoother produced.
        report: extra report.json content (timings, degeneracy flags, evaluation...);
            must not use the keys ``run_report`` fills in.
        extra_files: ``(file name, writer)`` pairs; each writer is called with the
            file's path inside the staging directory, e.g.
            ``("trajectory.png", lambda p: plot_trajectory_over_dtm(p, dtm, ...))``.
        force: also write into a non-empty directory cdtm did not write (beside its files).
        protected: inputs ``out_dir`` must not be, be inside or contain (the flight log).
        frame: the log's geodetic frame (``FlightConfig.local_frame``); when given, also
            ``trajectory_geodetic.csv`` and ``trajectory.geojson``, and the origin in
            report.json.
        groundtruth: the log's ground truth (world frame), or None; when given, also
            ``groundtruth.tum`` at the frames it covers (as ``trajectory_errors`` takes
            the errors there) and, with ``frame``, ``groundtruth_geodetic.csv``.

    Raises:
        ValueError: inconsistent shapes, a bad or duplicate extra file name, or report
            keys that clash with generated ones (all checked before anything is written).
        OutputError: ``out_dir`` may not be written (see ``atomic_output_dir``).
    """
    check_run(result, report, extra_files)
    names = [*RUN_FILES, *(GEODETIC_RUN_FILES if frame is not None else ()),
             *groundtruth_run_files(result, groundtruth, frame),
             *(name for name, _ in extra_files)]
    with atomic_output_dir(out_dir, writer=RUN_WRITER, force=force, protected=protected,
                           names=names) as tmp:
        write_run_files(tmp, result, report, extra_files, frame, groundtruth)


def check_run(result: SmootherResult, report: Mapping[str, Any],
              extra_files: Sequence[tuple[str, ExtraFileWriter]] = ()) -> None:
    """Raise ValueError if :func:`write_run_files` would refuse these inputs."""
    _check_result(result)
    names = [name for name, _ in extra_files]
    for name in names:
        _check_extra_name(name)
    if len(set(names)) != len(names):
        raise ValueError(f"duplicate extra file names in {names}")
    json.dumps(run_report(result, report), allow_nan=False)


def write_run_files(directory: str | os.PathLike, result: SmootherResult,
                    report: Mapping[str, Any],
                    extra_files: Sequence[tuple[str, ExtraFileWriter]] = (),
                    frame: LocalFrame | None = None,
                    groundtruth: States | None = None) -> None:
    """Write the files of a run into ``directory`` (not atomic by itself).

    For a caller holding an :func:`~cdtm_graph.atomic.atomic_output_dir` open (the CLI
    opens it before smoothing, so an unwritable ``--out`` fails first); otherwise use
    :func:`write_run`. Same arguments and ``ValueError`` checks as :func:`write_run`.
    """
    check_run(result, report, extra_files)
    directory = Path(directory)
    k = _check_result(result)
    content = run_report(result, report)
    if frame is not None:
        o = frame.origin
        content["conventions"]["world"] = (
            f"local ENU tangent plane at WGS84 latitude {o.latitude_deg} deg, longitude "
            f"{o.longitude_deg} deg, ellipsoidal height {o.height_m} m; metres")
        content["conventions"][TRAJECTORY_GEODETIC_CSV] = (
            "WGS84 latitude/longitude (deg), ellipsoidal height (m); attitude body -> local "
            "ENU and velocity in the local ENU at each position; 1-sigma north/east/up (m)")
    report_text = json.dumps(content, indent=2, allow_nan=False) + "\n"
    est = result.estimate
    t_ns = np.asarray(est.t_ns, dtype=np.int64).reshape(k)
    write_trajectory_tum(directory / TRAJECTORY_TUM, t_ns, est.world_T_body)
    write_trajectory_cov(directory / TRAJECTORY_COV, t_ns, est.world_T_body,
                         result.covariances.pose)
    write_states_csv(directory / STATES_CSV, result)
    write_covariances_npz(directory / COVARIANCES_NPZ, result)
    (directory / REPORT_JSON).write_text(report_text)
    if frame is not None:
        write_trajectory_geodetic_csv(directory / TRAJECTORY_GEODETIC_CSV, result, frame)
        write_trajectory_geojson(directory / TRAJECTORY_GEOJSON, result, frame)
    if groundtruth is not None and groundtruth_run_files(result, groundtruth, frame):
        _, truth = groundtruth_at_frames(t_ns, groundtruth)
        write_trajectory_tum(directory / GROUNDTRUTH_TUM, truth.t_ns, truth.world_T_body,
                             "ground truth world_T_body at the frames of trajectory.tum")
        if frame is not None:
            write_groundtruth_geodetic_csv(directory / GROUNDTRUTH_GEODETIC_CSV, truth, frame)
    for name, writer in extra_files:
        writer(directory / name)


# --------------------------------------------------------------------------- readers


def _data_lines(path: Path) -> Iterator[tuple[int, list[str]]]:
    """(1-based line number, whitespace-split tokens) of every non-blank, non-'#' line."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise CdtmError(f"{path}: cannot read: {exc}") from None
    for line_no, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if stripped and not stripped.startswith("#"):
            yield line_no, stripped.split()


def _read_pose_table(path: str | os.PathLike, n_columns: int
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Parse a space-separated table whose first 8 columns are TUM.

    Returns:
        t_ns (K,) int64, world_T_body (K, 4, 4), the remaining columns (K, n_columns - 8).
    """
    path = Path(path)
    expected = " ".join(COV_COLUMNS[:n_columns])
    times: list[int] = []
    rows: list[list[float]] = []
    line_numbers: list[int] = []
    for line_no, tokens in _data_lines(path):
        where = f"{path}:{line_no}"
        if len(tokens) != n_columns:
            raise CdtmError(f"{where}: {len(tokens)} columns; expected {n_columns}: {expected}")
        try:
            t = parse_t_s(tokens[0])
            values = [float(tok) for tok in tokens[1:]]
        except ValueError as exc:
            raise CdtmError(f"{where}: {exc}; expected numbers: {expected}") from None
        # Pose columns must be finite; a covariance may be "nan" (not available), not inf.
        if not all(math.isfinite(v) for v in values[:7]) or any(
                math.isinf(v) for v in values[7:]):
            raise CdtmError(f"{where}: non-finite value; expected finite numbers (nan allowed "
                            f"only for a covariance that is not available): {expected}")
        if times and t <= times[-1]:
            raise CdtmError(f"{where}: time {tokens[0]} s does not increase; expected "
                            f"strictly increasing times")
        times.append(t)
        rows.append(values)
        line_numbers.append(line_no)
    if not rows:
        raise CdtmError(f"{path}:1: no data lines; expected rows of {expected}")
    table = np.array(rows, dtype=float)
    q_xyzw = table[:, 3:7]
    norm = np.linalg.norm(q_xyzw, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > QUATERNION_UNIT_TOL)
    if bad.size:
        i = int(bad[0])
        raise CdtmError(f"{path}:{line_numbers[i]}: quaternion norm {norm[i]:.6g}; expected a "
                        f"unit quaternion qx qy qz qw")
    T = np.tile(np.eye(4), (table.shape[0], 1, 1))
    T[:, :3, :3] = quat_wxyz_to_rotation(np.column_stack([q_xyzw[:, 3], q_xyzw[:, :3]]))
    T[:, :3, 3] = table[:, :3]
    return np.array(times, dtype=np.int64), T, table[:, 7:]


def read_tum(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory (``t_s tx ty tz qx qy qz qw``; '#' lines and blank lines skipped).

    Args:
        path: the file.

    Returns:
        t_ns (K,) int64 (the decimal seconds parsed exactly, rounded to 1 ns) and
        world_T_body (K, 4, 4).

    Raises:
        CdtmError: unreadable file, wrong column count, non-numbers, non-increasing
            times or non-unit quaternions; the message names the file and line.
    """
    t_ns, T, _ = _read_pose_table(path, len(TUM_COLUMNS))
    return t_ns, T


def read_trajectory_cov(path: str | os.PathLike
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Read the 20-column trajectory-with-covariance file ``write_trajectory_cov`` writes.

    Returns:
        t_ns (K,) int64, world_T_body (K, 4, 4), orientation_cov (K, 3, 3) rad^2 and
        position_cov (K, 3, 3) m^2, both world frame and symmetric.

    Raises:
        CdtmError: as :func:`read_tum`, for 20 columns.
    """
    t_ns, T, upper = _read_pose_table(path, len(COV_COLUMNS))
    covs = []
    for block in (upper[:, :6], upper[:, 6:]):
        cov = np.empty((upper.shape[0], 3, 3))
        for col, (i, j) in enumerate(UPPER_TRIANGLE):
            cov[:, i, j] = cov[:, j, i] = block[:, col]
        covs.append(cov)
    return t_ns, T, covs[0], covs[1]


# --------------------------------------------------------------------------- a whole run

#: What a run directory must hold to be read back by :func:`read_run`.
RUN_EXPECTED = (f"a run directory of cdtm smooth ({REPORT_JSON}, {TRAJECTORY_TUM}, "
                f"{COVARIANCES_NPZ}, and {GROUNDTRUTH_TUM} for a log with ground truth)")


@dataclasses.dataclass(frozen=True)
class RunFiles:
    """A run directory read back: what ``cdtm evaluate`` compares.

    Attributes:
        directory: where it was read.
        report: report.json's content.
        t_ns: (K,) frame times. world_T_body: (K, 4, 4) the estimate.
        pose_covariance: (K, 6, 6) GTSAM tangent order [rot, trans], body frame.
        groundtruth_t_ns: (M,) the ground truth's times (frames of ``t_ns``), or None
            without ground truth. groundtruth_world_T_body: (M, 4, 4), or None.
    """

    directory: Path
    report: dict[str, Any]
    t_ns: np.ndarray
    world_T_body: np.ndarray
    pose_covariance: np.ndarray
    groundtruth_t_ns: np.ndarray | None
    groundtruth_world_T_body: np.ndarray | None


def read_run(directory: str | os.PathLike, require_groundtruth: bool = False) -> RunFiles:
    """Read a run directory back (report.json, trajectory.tum, covariances.npz, and
    groundtruth.tum when there).

    Raises:
        CdtmError: not a directory, not a run directory, no ground truth (when required),
            or a file that does not read; the message names the directory or file.
    """
    path = Path(directory)
    if not path.is_dir():
        what = "does not exist" if not path.exists() else "is not a directory"
        raise CdtmError(f"{path}: {what}; expected {RUN_EXPECTED}")
    missing = [n for n in (REPORT_JSON, TRAJECTORY_TUM, COVARIANCES_NPZ)
               if not (path / n).is_file()]
    if missing:
        inside = sorted(p.name for p in path.iterdir() if (p / REPORT_JSON).is_file())
        hint = (f" (it holds run directories: {', '.join(inside[:3])}"
                f"{', ...' if len(inside) > 3 else ''}; name them)" if inside else "")
        raise CdtmError(f"{path}: not a run directory (no {missing[0]}){hint}; expected "
                        f"{RUN_EXPECTED}")
    has_truth = (path / GROUNDTRUTH_TUM).is_file()
    try:
        report = json.loads((path / REPORT_JSON).read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise CdtmError(f"{path / REPORT_JSON}: cannot read: {exc}; expected the JSON "
                        "report cdtm smooth writes") from None
    if not isinstance(report, dict):
        raise CdtmError(f"{path / REPORT_JSON}: not a JSON object; expected the report "
                        "cdtm smooth writes")
    if require_groundtruth and not has_truth:
        evaluation = report.get("evaluation")
        compensated = evaluation.get("compensated") if isinstance(evaluation, dict) else None
        evaluated = (compensated.get("n_frames_evaluated") if isinstance(compensated, dict)
                     else None)
        why = ("its log's groundtruth.csv covered none of its frames: another clock?"
               if evaluated == 0 else "its log has no groundtruth.csv, or it was smoothed "
               "before cdtm wrote one")
        raise CdtmError(f"{path}: no ground truth (no {GROUNDTRUTH_TUM}: {why}); expected "
                        "runs of logs with ground truth over their frames")
    t_ns, world_T_body = read_tum(path / TRAJECTORY_TUM)
    try:
        with np.load(path / COVARIANCES_NPZ, allow_pickle=False) as npz:
            pose_cov, cov_t_ns = np.asarray(npz["pose"], float), np.asarray(npz["t_ns"])
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise CdtmError(f"{path / COVARIANCES_NPZ}: cannot read: {exc}; expected the "
                        "covariances cdtm smooth writes") from None
    if pose_cov.shape != (len(t_ns), 6, 6) or not np.array_equal(cov_t_ns, t_ns):
        raise CdtmError(f"{path / COVARIANCES_NPZ}: {pose_cov.shape[0]} frames that are not "
                        f"the {len(t_ns)} of {TRAJECTORY_TUM}; expected the files of one run")
    gt_t = gt_T = None
    if has_truth:
        gt_t, gt_T = read_tum(path / GROUNDTRUTH_TUM)
        if not np.isin(gt_t, t_ns).all():
            raise CdtmError(f"{path / GROUNDTRUTH_TUM}: times that are no frame of "
                            f"{TRAJECTORY_TUM}; expected the files of one run")
    return RunFiles(path, report, t_ns, world_T_body, pose_cov, gt_t, gt_T)
