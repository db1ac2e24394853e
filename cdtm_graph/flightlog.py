"""Flight logs in the ``cdtm-flightlog/1`` format (FLIGHTLOG.md): read, validate, write.

A flight log is a directory: ``flight.yaml`` (camera, IMU, DTM, initial state),
``imu.csv``, ``frames.csv`` and optionally ``tracks.csv``, ``nav.csv``,
``groundtruth.csv``. The CSV files follow the EuRoC/ASL column order, so EuRoC
files can be copied in as they are.

Everything here is plain numpy: no GTSAM types. The DTM itself is not loaded here
(:mod:`cdtm_graph.dtm` does that); the reader only checks that its file exists.

Every problem in a log raises :class:`~cdtm_graph.errors.FlightLogError` with a
one-line message ``"<file>:<line>: <what is wrong>; expected <what>"``. When a file
has several problems, the one on the earliest line is reported.

Large CSV files (hours of 200 Hz IMU) are parsed by numpy's C reader; only when
that fails does a line-by-line scan run, to find and name the offending line.
"""

from __future__ import annotations

import logging
import math
import os
import shutil
import uuid
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
import yaml

from cdtm_graph.camera import PinholeCamera
from cdtm_graph.errors import FlightLogError
from cdtm_graph.geometry import make_pose, quat_wxyz_to_rotation, rotation_to_quat_wxyz

logger = logging.getLogger(__name__)

FORMAT = "cdtm-flightlog/1"

FLIGHT_YAML = "flight.yaml"
IMU_CSV = "imu.csv"
FRAMES_CSV = "frames.csv"
TRACKS_CSV = "tracks.csv"
NAV_CSV = "nav.csv"
GROUNDTRUTH_CSV = "groundtruth.csv"
#: Every file the writer owns; stale optional ones are removed when a log is rewritten.
LOG_FILES = (FLIGHT_YAML, IMU_CSV, FRAMES_CSV, TRACKS_CSV, NAV_CSV, GROUNDTRUTH_CSV)

DTM_SUFFIXES = (".npz", ".asc", ".tif")

#: A quaternion whose norm is further than this from 1 is a data error, not rounding
#: (six printed digits, as in EuRoC's ground truth, stay well inside it).
QUATERNION_UNIT_TOL = 1e-3
#: Quaternions this close to unit norm are kept bit for bit, so that writing and
#: reading a log round-trips exactly (renormalizing would flip last bits).
QUATERNION_EXACT_TOL = 1e-12

_INT64_MIN, _INT64_MAX = -(2**63), 2**63 - 1
_CHUNK_BYTES = 1 << 24


# --------------------------------------------------------------------------- dataclasses


class _ArrayEq:
    """Field-wise ``==`` for dataclasses holding numpy arrays (exact, dtype-agnostic)."""

    __hash__ = None  # type: ignore[assignment]  # mutable arrays inside: unhashable

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return all(_values_equal(getattr(self, f.name), getattr(other, f.name))
                   for f in fields(self))  # type: ignore[arg-type]


def _values_equal(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (isinstance(a, np.ndarray) and isinstance(b, np.ndarray)
                and a.shape == b.shape and bool(np.array_equal(a, b)))
    return bool(a == b)


def _as_int64(name: str, value: Any, shape: tuple[int | None, ...]) -> np.ndarray:
    arr = np.asarray(value)
    if arr.size == 0:
        arr = arr.astype(np.int64)
    if arr.dtype.kind not in "iu":
        raise ValueError(f"{name} must be an integer array, got dtype {arr.dtype}")
    return _check_shape(name, arr.astype(np.int64, copy=False), shape)


def _as_float(name: str, value: Any, shape: tuple[int | None, ...]) -> np.ndarray:
    return _check_shape(name, np.asarray(value, dtype=float), shape)


def _check_shape(name: str, arr: np.ndarray, shape: tuple[int | None, ...]) -> np.ndarray:
    if arr.ndim != len(shape) or any(
            s is not None and s != n for s, n in zip(shape, arr.shape, strict=True)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name} must have shape {want}, got {arr.shape}")
    return arr


def _same_length(owner: str, **arrays: np.ndarray) -> None:
    lengths = {name: a.shape[0] for name, a in arrays.items()}
    if len(set(lengths.values())) > 1:
        raise ValueError(f"{owner}: arrays differ in length: {lengths}")


@dataclass(frozen=True)
class DtmConfig:
    """Where the DTM is and how to read it (``dtm:`` in flight.yaml).

    Attributes:
        path: the DTM file (.npz, .asc or .tif). The reader resolves a relative path
            against the log directory; a relative path given to the writer is
            written as is.
        sigma_h_m: 1-sigma height error of the DTM in metres; None: derive it from
            the grid spacing.
        origin_enu_m: subtracted from the DTM's own x, y, z to give world coordinates.
    """

    path: Path
    sigma_h_m: float | None = None
    origin_enu_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "path", Path(self.path))
        object.__setattr__(self, "origin_enu_m", tuple(float(x) for x in self.origin_enu_m))
        if len(self.origin_enu_m) != 3:
            raise ValueError(f"origin_enu_m must have 3 values, got {self.origin_enu_m}")
        if self.sigma_h_m is not None:
            object.__setattr__(self, "sigma_h_m", float(self.sigma_h_m))


@dataclass(frozen=True, eq=False)
class CameraConfig(_ArrayEq):
    """The camera and its mounting (``camera:`` in flight.yaml).

    Attributes:
        camera: intrinsics and distortion.
        pixel_sigma_px: 1-sigma feature location error in pixels.
        body_T_cam: (4, 4) pose of the camera in the body (IMU) frame.
    """

    camera: PinholeCamera
    pixel_sigma_px: float
    body_T_cam: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "pixel_sigma_px", float(self.pixel_sigma_px))
        object.__setattr__(self, "body_T_cam", _as_float("body_T_cam", self.body_T_cam, (4, 4)))


@dataclass(frozen=True)
class ImuConfig:
    """IMU rate and continuous-time noise densities (Kalibr names, SI units).

    Attributes:
        rate_hz: nominal sample rate.
        gyroscope_noise_density: rad/s/sqrt(Hz).
        accelerometer_noise_density: m/s^2/sqrt(Hz).
        gyroscope_random_walk: rad/s^2/sqrt(Hz).
        accelerometer_random_walk: m/s^3/sqrt(Hz).
    """

    rate_hz: float
    gyroscope_noise_density: float
    accelerometer_noise_density: float
    gyroscope_random_walk: float
    accelerometer_random_walk: float


@dataclass(frozen=True, eq=False)
class InitialState(_ArrayEq):
    """Prior on the body state at the first frame (``initial_state:`` in flight.yaml).

    Attributes:
        position_m: (3,) body position in world.
        quaternion_wxyz: (4,) unit quaternion rotating body vectors into world.
        velocity_mps: (3,) body velocity in world.
        gyro_bias: (3,) rad/s.
        accel_bias: (3,) m/s^2.
        sigma_position_m: 1-sigma of each position component.
        sigma_attitude_deg: 1-sigma of each attitude angle, degrees.
        sigma_velocity_mps: 1-sigma of each velocity component.
        sigma_gyro_bias: 1-sigma of each gyro bias component, rad/s.
        sigma_accel_bias: 1-sigma of each accelerometer bias component, m/s^2.
    """

    position_m: np.ndarray
    quaternion_wxyz: np.ndarray
    velocity_mps: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray
    sigma_position_m: float
    sigma_attitude_deg: float
    sigma_velocity_mps: float
    sigma_gyro_bias: float
    sigma_accel_bias: float

    def __post_init__(self) -> None:
        for name, n in (("position_m", 3), ("quaternion_wxyz", 4), ("velocity_mps", 3),
                        ("gyro_bias", 3), ("accel_bias", 3)):
            object.__setattr__(self, name, _as_float(name, getattr(self, name), (n,)))
        for name in ("sigma_position_m", "sigma_attitude_deg", "sigma_velocity_mps",
                     "sigma_gyro_bias", "sigma_accel_bias"):
            object.__setattr__(self, name, float(getattr(self, name)))

    @property
    def world_T_body(self) -> np.ndarray:
        """(4, 4) initial body pose in world."""
        return make_pose(quat_wxyz_to_rotation(self.quaternion_wxyz), self.position_m)

    @property
    def sigma_attitude_rad(self) -> float:
        """1-sigma of each attitude angle in radians."""
        return math.radians(self.sigma_attitude_deg)


@dataclass(frozen=True)
class FlightConfig:
    """Everything in flight.yaml.

    Attributes:
        gravity_mps2: gravity magnitude; gravity points along -z of world.
        dtm: the DTM file and its settings.
        camera: camera intrinsics, pixel noise and mounting.
        imu: IMU noise model.
        initial_state: prior on the first body state.
        extra: the top-level ``extra:`` mapping, kept as read and otherwise ignored.
    """

    gravity_mps2: float
    dtm: DtmConfig
    camera: CameraConfig
    imu: ImuConfig
    initial_state: InitialState
    extra: dict = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class ImuSamples(_ArrayEq):
    """IMU samples in the body frame.

    Attributes:
        t_ns: (N,) int64 sample times, strictly increasing.
        gyro_radps: (N, 3) angular rate, rad/s.
        acc_mps2: (N, 3) specific force, m/s^2.
    """

    t_ns: np.ndarray
    gyro_radps: np.ndarray
    acc_mps2: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "t_ns", _as_int64("t_ns", self.t_ns, (None,)))
        object.__setattr__(self, "gyro_radps", _as_float("gyro_radps", self.gyro_radps, (None, 3)))
        object.__setattr__(self, "acc_mps2", _as_float("acc_mps2", self.acc_mps2, (None, 3)))
        _same_length("ImuSamples", t_ns=self.t_ns, gyro_radps=self.gyro_radps,
                     acc_mps2=self.acc_mps2)

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])


@dataclass(frozen=True, eq=False)
class Frames(_ArrayEq):
    """Camera frame times and image files.

    Attributes:
        t_ns: (K,) int64 frame times, strictly increasing.
        image: K image paths relative to the log directory; ``""`` for no image.
    """

    t_ns: np.ndarray
    image: tuple[str, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "t_ns", _as_int64("t_ns", self.t_ns, (None,)))
        object.__setattr__(self, "image", tuple(str(s) for s in self.image))
        if len(self.image) != self.t_ns.shape[0]:
            raise ValueError(f"Frames: {self.t_ns.shape[0]} times but {len(self.image)} images")

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])


@dataclass(frozen=True, eq=False)
class Tracks(_ArrayEq):
    """Feature tracks: one row per observation of a ground feature in a frame.

    Attributes:
        frame: (M,) int64 0-based frame index (row of frames.csv), non-decreasing.
        track_id: (M,) int64 feature identity; at most one row per (frame, track_id).
        uv_px: (M, 2) observed pixel (u, v), OpenCV pixel-centre convention.
    """

    frame: np.ndarray
    track_id: np.ndarray
    uv_px: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "frame", _as_int64("frame", self.frame, (None,)))
        object.__setattr__(self, "track_id", _as_int64("track_id", self.track_id, (None,)))
        object.__setattr__(self, "uv_px", _as_float("uv_px", self.uv_px, (None, 2)))
        _same_length("Tracks", frame=self.frame, track_id=self.track_id, uv_px=self.uv_px)

    def __len__(self) -> int:
        return int(self.frame.shape[0])

    def pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """Consecutive observations of each track, as row indices into these arrays.

        For a track seen in frames 2, 3 and 7 the pairs are (2, 3) and (3, 7): one
        C-DTM factor each. A track seen once gives no pair.

        Returns:
            ``(rows_a, rows_b)``: (P,) int64 each; ``frame[rows_a] < frame[rows_b]``,
            same ``track_id``, sorted by (frame_a, frame_b, track_id).
        """
        by_track = np.lexsort((self.frame, self.track_id))
        same = self.track_id[by_track[1:]] == self.track_id[by_track[:-1]]
        rows_a = by_track[:-1][same]
        rows_b = by_track[1:][same]
        order = np.lexsort((self.track_id[rows_a], self.frame[rows_b], self.frame[rows_a]))
        return rows_a[order].astype(np.int64), rows_b[order].astype(np.int64)


@dataclass(frozen=True, eq=False)
class States(_ArrayEq):
    """Body states in world at given times (nav.csv, groundtruth.csv).

    Attributes:
        t_ns: (K,) int64 times, strictly increasing.
        position_m: (K, 3) body position in world.
        quaternion_wxyz: (K, 4) unit quaternions rotating body vectors into world.
        velocity_mps: (K, 3) body velocity in world.
    """

    t_ns: np.ndarray
    position_m: np.ndarray
    quaternion_wxyz: np.ndarray
    velocity_mps: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "t_ns", _as_int64("t_ns", self.t_ns, (None,)))
        object.__setattr__(self, "position_m", _as_float("position_m", self.position_m, (None, 3)))
        object.__setattr__(self, "quaternion_wxyz",
                           _as_float("quaternion_wxyz", self.quaternion_wxyz, (None, 4)))
        object.__setattr__(self, "velocity_mps",
                           _as_float("velocity_mps", self.velocity_mps, (None, 3)))
        _same_length("States", t_ns=self.t_ns, position_m=self.position_m,
                     quaternion_wxyz=self.quaternion_wxyz, velocity_mps=self.velocity_mps)

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    @property
    def world_T_body(self) -> np.ndarray:
        """(K, 4, 4) body poses in world."""
        T = np.tile(np.eye(4), (len(self), 1, 1))
        T[:, :3, :3] = quat_wxyz_to_rotation(self.quaternion_wxyz)
        T[:, :3, 3] = self.position_m
        return T

    def interpolate(self, t_ns: np.ndarray | int) -> States:
        """States at other times: linear in position and velocity, slerp in orientation.

        Times equal to a sample give that sample exactly.

        Args:
            t_ns: (Q,) int64 query times (or one int), each within
                ``[t_ns[0], t_ns[-1]]``.

        Returns:
            The states at the query times, (Q,) rows.

        Raises:
            FlightLogError: a query time lies outside the sampled range (no
                extrapolation), or there are no samples.
        """
        query = np.atleast_1d(np.asarray(t_ns))
        if query.dtype.kind not in "iu":
            raise ValueError(f"t_ns must be integer nanoseconds, got dtype {query.dtype}")
        query = query.astype(np.int64)
        if len(self) == 0:
            raise FlightLogError("States.interpolate: no samples; expected at least one state")
        outside = (query < self.t_ns[0]) | (query > self.t_ns[-1])
        if np.any(outside):
            bad = int(query[np.flatnonzero(outside)[0]])
            raise FlightLogError(
                f"States.interpolate: t_ns={bad} is outside the states' time range; expected "
                f"{int(self.t_ns[0])} <= t_ns <= {int(self.t_ns[-1])}")
        if len(self) == 1:
            idx = np.zeros(query.shape, dtype=np.int64)
            return States(query, self.position_m[idx], self.quaternion_wxyz[idx],
                          self.velocity_mps[idx])
        i0 = np.clip(np.searchsorted(self.t_ns, query, side="right") - 1, 0, len(self) - 2)
        i1 = i0 + 1
        # Integer differences first: int64 nanoseconds lose precision as float64 epochs.
        s = ((query - self.t_ns[i0]).astype(float)
             / (self.t_ns[i1] - self.t_ns[i0]).astype(float))[:, None]
        # (1-s) a + s b (not a + s (b-a)) returns the samples bit-exactly at s = 0 and 1.
        position = (1.0 - s) * self.position_m[i0] + s * self.position_m[i1]
        velocity = (1.0 - s) * self.velocity_mps[i0] + s * self.velocity_mps[i1]
        quat = _slerp(self.quaternion_wxyz[i0], self.quaternion_wxyz[i1], s[:, 0])
        return States(query, position, quat, velocity)


@dataclass(frozen=True)
class FlightLog:
    """A whole flight log, as read from or to be written to its directory.

    Attributes:
        root: the log directory (absolute).
        config: flight.yaml.
        imu: imu.csv.
        frames: frames.csv.
        tracks: tracks.csv, or None when absent.
        nav: nav.csv (one state per frame), or None.
        groundtruth: groundtruth.csv (any rate), or None.
    """

    root: Path
    config: FlightConfig
    imu: ImuSamples
    frames: Frames
    tracks: Tracks | None = None
    nav: States | None = None
    groundtruth: States | None = None


def _slerp(q0: np.ndarray, q1: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation of (N, 4) unit quaternions at fractions (N,)."""
    dot = np.sum(q0 * q1, axis=1)
    # q and -q are one rotation: interpolate along the shorter arc.
    q1_short = np.where(dot[:, None] < 0.0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_theta = np.sin(theta)
    nearly_equal = sin_theta < 1e-9  # weights -> (1-s, s); avoids 0/0
    safe_sin = np.where(nearly_equal, 1.0, sin_theta)
    w0 = np.where(nearly_equal, 1.0 - s, np.sin((1.0 - s) * theta) / safe_sin)
    w1 = np.where(nearly_equal, s, np.sin(s * theta) / safe_sin)
    q = w0[:, None] * q0 + w1[:, None] * q1_short
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    # At the samples themselves return them bit for bit (and with their own sign).
    q = np.where((s == 0.0)[:, None], q0, q)
    return np.where((s == 1.0)[:, None], q1, q)


# --------------------------------------------------------------------------- errors


def _fail(file: str, line: int, what: str, expected: str) -> NoReturn:
    raise FlightLogError(_one_line(f"{file}:{line}: {what}; expected {expected}"))


def _one_line(text: str) -> str:
    return " ".join(text.split("\n"))


def _show(token: str, limit: int = 40) -> str:
    """A token as it appears in a message: quoted, one line, truncated."""
    text = repr(token)
    return text if len(text) <= limit else text[: limit - 4] + "...'"


def _first(mask: np.ndarray) -> int | None:
    hits = np.flatnonzero(mask)
    return int(hits[0]) if hits.size else None


class _Problems:
    """Collects the first failing row of each check; reports the earliest in the file."""

    def __init__(self, file: str, first_line: int):
        self.file = file
        self.first_line = first_line
        self.found: list[tuple[int, int, str, str]] = []

    def add(self, row: int | None, what: str, expected: str) -> None:
        if row is not None:
            self.found.append((row, len(self.found), what, expected))

    def check(self, mask: np.ndarray, describe, expected: str) -> None:
        """Add the first row where ``mask`` is True, described by ``describe(row)``."""
        row = _first(mask)
        if row is not None:
            self.add(row, describe(row), expected)

    def raise_first(self) -> None:
        if self.found:
            row, _, what, expected = min(self.found)
            _fail(self.file, self.first_line + row, what, expected)


# --------------------------------------------------------------------------- CSV reading


@dataclass(frozen=True)
class _CsvSpec:
    """Columns of one CSV file: integer columns first, then float columns."""

    name: str
    int_columns: tuple[str, ...]
    float_columns: tuple[str, ...]
    extra_columns_ignored: bool = False

    @property
    def columns(self) -> tuple[str, ...]:
        return self.int_columns + self.float_columns

    @property
    def expected_row(self) -> str:
        more = " (further columns ignored)" if self.extra_columns_ignored else ""
        return f"{len(self.columns)} comma-separated values {','.join(self.columns)}{more}"


_STATE_COLUMNS = ("px", "py", "pz", "qw", "qx", "qy", "qz", "vx", "vy", "vz")
_IMU_SPEC = _CsvSpec(IMU_CSV, ("t_ns",),
                     ("gyro_x", "gyro_y", "gyro_z", "acc_x", "acc_y", "acc_z"))
_TRACKS_SPEC = _CsvSpec(TRACKS_CSV, ("frame", "track_id"), ("u", "v"))
_NAV_SPEC = _CsvSpec(NAV_CSV, ("t_ns",), _STATE_COLUMNS)
_GROUNDTRUTH_SPEC = _CsvSpec(GROUNDTRUTH_CSV, ("t_ns",), _STATE_COLUMNS,
                             extra_columns_ignored=True)
_FRAMES_COLUMNS = ("t_ns", "image")
_FRAMES_EXPECTED = "2 comma-separated values t_ns,image; image may be empty"


@dataclass(frozen=True)
class _Table:
    """Parsed numeric CSV: row i was line ``first_line + i`` of the file."""

    ints: np.ndarray    # (N, n_int) int64
    floats: np.ndarray  # (N, n_float) float64
    first_line: int


def _is_header(first_line: str) -> bool:
    """A first line is a header when it does not parse as numbers.

    Only the first field decides: a header's first field is a name (EuRoC's
    ``#timestamp [ns]``), while a data row with one bad value further right is a
    malformed row to report, not a line to skip silently.
    """
    first_field = first_line.split(",", 1)[0].strip()
    try:
        float(first_field)
    except ValueError:
        return True
    return False


@dataclass(frozen=True)
class _LineCount:
    has_header: bool
    data_lines: int      # lines after the header, as a text editor counts them
    plain_newlines: bool  # only '\n' or '\r\n' line ends: numpy's row i is line i


def _count_lines(path: Path, shown: str) -> _LineCount:
    with path.open("rb") as f:
        first = f.readline()
        try:
            first_text = first.decode("utf-8-sig")
        except UnicodeDecodeError:
            _fail(shown, 1, "the first line is not UTF-8 text", "a UTF-8 CSV file")
        has_header = _is_header(first_text.rstrip("\r\n"))
        newlines = first.count(b"\n")
        carriage_returns = first.count(b"\r")
        crlf = first.count(b"\r\n")
        ends_with_newline = first.endswith(b"\n")
        size = len(first)
        previous_last = first[-1:]
        while chunk := f.read(_CHUNK_BYTES):
            newlines += chunk.count(b"\n")
            if b"\r" in chunk or previous_last == b"\r":  # rare: skip two scans otherwise
                carriage_returns += chunk.count(b"\r")
                crlf += chunk.count(b"\r\n") + (previous_last == b"\r" and chunk[:1] == b"\n")
            ends_with_newline = chunk.endswith(b"\n")
            previous_last = chunk[-1:]
            size += len(chunk)
    total = newlines + (1 if size and not ends_with_newline else 0)
    return _LineCount(has_header, total - int(has_header), carriage_returns == crlf)


def _read_numeric_csv(path: Path, shown: str, spec: _CsvSpec) -> _Table:
    """Parse a numeric CSV: numpy's C reader when the file is clean, else a line scan."""
    count = _count_lines(path, shown)
    first_line = 2 if count.has_header else 1
    n_int, n_float = len(spec.int_columns), len(spec.float_columns)
    if count.data_lines == 0:
        return _Table(np.zeros((0, n_int), np.int64), np.zeros((0, n_float)), first_line)
    dtype = np.dtype([("i", np.int64, (n_int,)), ("f", np.float64, (n_float,))])
    usecols = range(n_int + n_float) if spec.extra_columns_ignored else None
    rows = None
    if count.plain_newlines:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                rows = np.loadtxt(path, delimiter=",", dtype=dtype, comments=None,
                                  skiprows=int(count.has_header), usecols=usecols,
                                  encoding="utf-8-sig", ndmin=1)
        except (ValueError, UnicodeDecodeError):
            rows = None
    # numpy skips blank lines, which would shift every later line number: only a
    # row count equal to the line count proves row i is line first_line + i.
    if rows is None or rows.shape[0] != count.data_lines:
        return _scan_numeric_csv(path, shown, spec, count.has_header)
    return _Table(np.ascontiguousarray(rows["i"]), np.ascontiguousarray(rows["f"]), first_line)


def _split_lines(path: Path, shown: str, has_header: bool) -> Iterable[tuple[int, str]]:
    """(line number, text) of each data line, decoding line by line to name bad bytes."""
    data = path.read_bytes()
    if data.startswith(b"\xef\xbb\xbf"):
        data = data[3:]
    lines = data.splitlines()  # \n, \r\n and \r, as numpy and text editors split
    for index in range(int(has_header), len(lines)):
        try:
            text = lines[index].decode("utf-8")
        except UnicodeDecodeError:
            _fail(shown, index + 1, "the line is not UTF-8 text", "a UTF-8 CSV file")
        yield index + 1, text


def _parse_int(token: str) -> int | None:
    text = token.strip()
    if "_" in text:  # Python's int() accepts 1_000; the format does not
        return None
    try:
        value = int(text, 10)
    except ValueError:
        return None
    return value if _INT64_MIN <= value <= _INT64_MAX else None


def _parse_float(token: str) -> float | None:
    text = token.strip()
    if "_" in text:
        return None
    try:
        return float(text)
    except ValueError:
        return None


def _split_row(shown: str, line_no: int, text: str, n_columns: int, columns: Sequence[str],
               expected: str, extra_ignored: bool) -> list[str]:
    if not text.strip():
        _fail(shown, line_no, "empty line", expected)
    tokens = text.split(",")
    if len(tokens) < n_columns:
        _fail(shown, line_no,
              f"short row: {len(tokens)} value{'s' if len(tokens) != 1 else ''}, "
              f"no {columns[len(tokens)]}", expected)
    if len(tokens) > n_columns and not extra_ignored:
        _fail(shown, line_no, f"{len(tokens)} values, {len(tokens) - n_columns} too many",
              expected)
    return tokens


def _scan_numeric_csv(path: Path, shown: str, spec: _CsvSpec, has_header: bool) -> _Table:
    """The slow, exact path: parse line by line; the first bad line raises."""
    columns = spec.columns
    n_int = len(spec.int_columns)
    ints: list[list[int]] = []
    floats: list[list[float]] = []
    first_line = 2 if has_header else 1
    for line_no, text in _split_lines(path, shown, has_header):
        tokens = _split_row(shown, line_no, text, len(columns), columns, spec.expected_row,
                            spec.extra_columns_ignored)
        row_ints = []
        for j in range(n_int):
            value = _parse_int(tokens[j])
            if value is None:
                _fail(shown, line_no, f"{columns[j]} is {_show(tokens[j].strip())}",
                      f"an integer ({spec.expected_row})")
            row_ints.append(value)
        row_floats = []
        for j in range(n_int, len(columns)):
            number = _parse_float(tokens[j])
            if number is None:
                _fail(shown, line_no, f"{columns[j]} is {_show(tokens[j].strip())}, not a number",
                      f"a number ({spec.expected_row})")
            row_floats.append(number)
        ints.append(row_ints)
        floats.append(row_floats)
    return _Table(np.array(ints, dtype=np.int64).reshape(-1, n_int),
                  np.array(floats, dtype=float).reshape(-1, len(columns) - n_int), first_line)


def _check_finite(problems: _Problems, table: _Table, spec: _CsvSpec) -> None:
    bad = ~np.isfinite(table.floats)
    row = _first(bad.any(axis=1))
    if row is not None:
        col = int(np.flatnonzero(bad[row])[0])
        problems.add(row, f"{spec.float_columns[col]} is {float(table.floats[row, col])!r}",
                     "a finite number (no NaN or inf)")


def _check_increasing(problems: _Problems, t_ns: np.ndarray, name: str = "t_ns") -> None:
    step = np.diff(t_ns)
    row = _first(step <= 0)
    if row is not None:
        problems.add(row + 1, f"{name} {int(t_ns[row + 1])} is not after the previous row's "
                     f"{int(t_ns[row])}", f"strictly increasing {name}")


def _checked_quaternions(problems: _Problems, quat: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(quat, axis=1)
    off = np.abs(norm - 1.0)
    problems.check(~(off <= QUATERNION_UNIT_TOL),
                   lambda r: f"quaternion qw,qx,qy,qz has norm {norm[r]:.6g}",
                   f"a unit quaternion (|norm - 1| <= {QUATERNION_UNIT_TOL:g})")
    fix = off > QUATERNION_EXACT_TOL
    if np.any(fix):
        quat = quat.copy()
        quat[fix] /= norm[fix, None]
    return quat


def _read_states(path: Path, shown: str, spec: _CsvSpec) -> tuple[States, int]:
    table = _read_numeric_csv(path, shown, spec)
    problems = _Problems(shown, table.first_line)
    _check_finite(problems, table, spec)
    t_ns = table.ints[:, 0]
    _check_increasing(problems, t_ns)
    finite = np.isfinite(table.floats).all(axis=1)
    quat = table.floats[:, 3:7]
    quat = np.where(finite[:, None], quat, 1.0)  # NaN rows are already reported
    quat = _checked_quaternions(problems, quat)
    problems.raise_first()
    states = States(t_ns.copy(), table.floats[:, 0:3].copy(), quat, table.floats[:, 7:10].copy())
    return states, table.first_line


def _read_imu(path: Path, shown: str) -> ImuSamples:
    table = _read_numeric_csv(path, shown, _IMU_SPEC)
    if table.ints.shape[0] == 0:
        _fail(shown, table.first_line, "no IMU samples", _IMU_SPEC.expected_row)
    problems = _Problems(shown, table.first_line)
    _check_finite(problems, table, _IMU_SPEC)
    _check_increasing(problems, table.ints[:, 0])
    problems.raise_first()
    return ImuSamples(table.ints[:, 0].copy(), table.floats[:, 0:3].copy(),
                      table.floats[:, 3:6].copy())


def _read_frames(path: Path, shown: str) -> tuple[Frames, int]:
    """frames.csv: small (one row per frame), so a plain line loop is fast enough."""
    with path.open("rb") as f:
        first = f.readline()
    try:
        first_text = first.decode("utf-8-sig")
    except UnicodeDecodeError:
        _fail(shown, 1, "the first line is not UTF-8 text", "a UTF-8 CSV file")
    has_header = bool(first) and _is_header(first_text.rstrip("\r\n"))
    first_line = 2 if has_header else 1
    times: list[int] = []
    images: list[str] = []
    for line_no, text in _split_lines(path, shown, has_header):
        tokens = _split_row(shown, line_no, text, 2, _FRAMES_COLUMNS, _FRAMES_EXPECTED, False)
        value = _parse_int(tokens[0])
        if value is None:
            _fail(shown, line_no, f"t_ns is {_show(tokens[0].strip())}",
                  f"integer nanoseconds in {_FRAMES_EXPECTED}")
        times.append(value)
        images.append(tokens[1].strip())
    if not times:
        _fail(shown, first_line, "no frames", _FRAMES_EXPECTED)
    t_ns = np.array(times, dtype=np.int64)
    problems = _Problems(shown, first_line)
    _check_increasing(problems, t_ns)
    problems.raise_first()
    return Frames(t_ns, tuple(images)), first_line


def _read_tracks(path: Path, shown: str, n_frames: int, camera: PinholeCamera) -> Tracks:
    spec = _TRACKS_SPEC
    table = _read_numeric_csv(path, shown, spec)
    frame, track_id = table.ints[:, 0], table.ints[:, 1]
    uv = table.floats
    problems = _Problems(shown, table.first_line)
    _check_finite(problems, table, spec)
    problems.check((frame < 0) | (frame >= n_frames),
                   lambda r: f"frame {int(frame[r])} does not exist "
                             f"({FRAMES_CSV} has {n_frames} frames)",
                   f"a 0-based row index of {FRAMES_CSV}: 0 <= frame <= {n_frames - 1}")
    problems.check(np.concatenate([[False], np.diff(frame) < 0]),
                   lambda r: f"frame {int(frame[r])} comes after frame {int(frame[r - 1])}",
                   "rows sorted by frame")
    # A track seen twice in one frame: report the later row of each duplicate pair.
    order = np.lexsort((np.arange(len(frame)), frame, track_id))
    dup = (track_id[order[1:]] == track_id[order[:-1]]) & (frame[order[1:]] == frame[order[:-1]])
    later = order[1:][dup]
    if later.size:
        row = int(later.min())
        problems.add(row, f"track {int(track_id[row])} is seen twice in frame {int(frame[row])}",
                     "each track at most once per frame")
    finite = np.isfinite(uv).all(axis=1)
    problems.check(finite & ~camera.in_image(uv),
                   lambda r: f"pixel (u, v) = ({float(uv[r, 0])!r}, {float(uv[r, 1])!r}) is "
                             f"outside the {camera.width}x{camera.height} image",
                   f"-0.5 <= u <= {camera.width - 0.5} and -0.5 <= v <= {camera.height - 0.5}")
    problems.raise_first()
    return Tracks(frame.copy(), track_id.copy(), uv.copy())


def _check_nav_times(nav: States, frames: Frames, shown: str, first_line: int) -> None:
    k_nav, k_frames = len(nav), len(frames)
    expected = f"one row per frame, with the times of {FRAMES_CSV} ({k_frames} rows)"
    n = min(k_nav, k_frames)
    row = _first(nav.t_ns[:n] != frames.t_ns[:n])
    if row is not None:
        _fail(shown, first_line + row,
              f"t_ns {int(nav.t_ns[row])} is not the time of frame {row} "
              f"({int(frames.t_ns[row])})", expected)
    if k_nav < k_frames:
        _fail(shown, first_line + k_nav, f"{k_nav} rows for {k_frames} frames: "
              f"no row for frame {k_nav} (t_ns {int(frames.t_ns[k_nav])})", expected)
    if k_nav > k_frames:
        _fail(shown, first_line + k_frames, f"{k_nav} rows for {k_frames} frames: "
              f"this row is beyond the last frame", expected)


# --------------------------------------------------------------------------- flight.yaml


class _Yaml:
    """flight.yaml walked node by node, so every message can name the offending line."""

    def __init__(self, shown: str, loader: yaml.SafeLoader):
        self.shown = shown
        self.loader = loader

    @staticmethod
    def line(node: yaml.Node) -> int:
        return node.start_mark.line + 1

    def fail(self, node_or_line: yaml.Node | int, what: str, expected: str) -> NoReturn:
        line = node_or_line if isinstance(node_or_line, int) else self.line(node_or_line)
        _fail(self.shown, line, what, expected)

    def pairs(self, node: yaml.Node, name: str,
              line: int) -> dict[str, tuple[yaml.Node, yaml.Node]]:
        """Key -> (key node, value node) of a mapping; duplicate keys are an error."""
        if not isinstance(node, yaml.MappingNode):
            label = name or "the document"
            self.fail(line, f"{label} is not a mapping", f"a mapping of {label}'s keys")
        out: dict[str, tuple[yaml.Node, yaml.Node]] = {}
        for key_node, value_node in node.value:
            key = self.loader.construct_object(key_node) if isinstance(
                key_node, yaml.ScalarNode) else None
            if not isinstance(key, str):
                self.fail(key_node, f"key {key!r} in {name} is not a name", "string keys")
            if key in out:
                self.fail(key_node, f"duplicate key '{_dotted(name, key)}'",
                          f"each key once (first on line {self.line(out[key][0])})")
            out[key] = (key_node, value_node)
        return out

    def keys(self, pairs: dict[str, tuple[yaml.Node, yaml.Node]], name: str, line: int,
             required: Sequence[str], optional: Sequence[str] = ()) -> dict[str, yaml.Node]:
        """Value nodes by key, after rejecting unknown keys and reporting missing ones."""
        allowed = tuple(required) + tuple(optional)
        for key, (key_node, _) in pairs.items():
            if key not in allowed:
                self.fail(key_node, f"unknown key '{_dotted(name, key)}'",
                          f"one of {', '.join(allowed)}"
                          + ("; free-form keys belong under extra:" if not name else ""))
        for key in required:
            if key not in pairs:
                self.fail(line, f"missing key '{_dotted(name, key)}'",
                          f"every required key of {name or 'the top level'}: "
                          f"{', '.join(required)}")
        return {key: value for key, (_, value) in pairs.items()}

    def value(self, node: yaml.Node) -> Any:
        return self.loader.construct_object(node, deep=True)

    def scalar(self, node: yaml.Node, name: str, expected: str) -> Any:
        if not isinstance(node, yaml.ScalarNode):
            kind = "a list" if isinstance(node, yaml.SequenceNode) else "a mapping"
            self.fail(node, f"{name} is {kind}", expected)
        return self.value(node)

    def number(self, node: yaml.Node, name: str, *, positive: bool = False) -> float:
        value = self.scalar(node, name, "a finite number")
        number: float | None = None
        if isinstance(value, int | float) and not isinstance(value, bool):
            number = float(value)
        elif isinstance(value, str):
            # PyYAML (YAML 1.1) reads 1e-4 as a string; it is a number to anyone else.
            number = _parse_float(value)
        if number is None or not math.isfinite(number):
            self.fail(node, f"{name} is {_show(str(value))}", "a finite number")
        if positive and not number > 0.0:
            self.fail(node, f"{name} is {number!r}", "a positive number")
        return number

    def integer(self, node: yaml.Node, name: str) -> int:
        value = self.scalar(node, name, "a positive integer")
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
            self.fail(node, f"{name} is {_show(str(value))}", "a positive integer")
        return value

    def text(self, node: yaml.Node, name: str) -> str:
        value = self.scalar(node, name, "a non-empty string")
        if not isinstance(value, str) or not value.strip():
            self.fail(node, f"{name} is {_show(str(value))}", "a non-empty string")
        return value

    def vector(self, node: yaml.Node, name: str, lengths: Sequence[int]) -> np.ndarray:
        want = " or ".join(str(n) for n in lengths)
        expected = f"a list of {want} finite numbers"
        if not isinstance(node, yaml.SequenceNode):
            self.fail(node, f"{name} is {_show(str(self.scalar(node, name, expected)))}",
                      expected)
        if len(node.value) not in lengths:
            self.fail(node, f"{name} has {len(node.value)} values", expected)
        return np.array([self.number(item, f"{name}[{i}]") for i, item in enumerate(node.value)])

    def quaternion(self, node: yaml.Node, name: str) -> np.ndarray:
        quat = self.vector(node, name, (4,))
        norm = float(np.linalg.norm(quat))
        if not abs(norm - 1.0) <= QUATERNION_UNIT_TOL:
            self.fail(node, f"{name} has norm {norm:.6g}",
                      f"a unit quaternion w,x,y,z (|norm - 1| <= {QUATERNION_UNIT_TOL:g})")
        return quat / norm if abs(norm - 1.0) > QUATERNION_EXACT_TOL else quat


def _dotted(parent: str, key: str) -> str:
    return f"{parent}.{key}" if parent else key


def _parse_flight_yaml(path: Path, shown: str, root: Path) -> FlightConfig:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        _fail(shown, 1 + path.read_bytes()[: exc.start].count(b"\n"), "not UTF-8 text",
              "a UTF-8 YAML file")
    loader = yaml.SafeLoader(text)
    try:
        return _parse_flight_document(loader, shown, root)
    except yaml.YAMLError as exc:
        # Syntax errors, and constructor errors such as an unknown !tag.
        mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
        problem = getattr(exc, "problem", None) or str(exc)
        _fail(shown, mark.line + 1 if mark else 1, f"YAML error: {problem}", "valid YAML")
    finally:
        loader.dispose()


def _parse_flight_document(loader: yaml.SafeLoader, shown: str, root: Path) -> FlightConfig:
    document = loader.get_single_node()
    y = _Yaml(shown, loader)
    if document is None:
        _fail(shown, 1, "empty file", f"a mapping starting with format: {FORMAT}")
    top_pairs = y.pairs(document, "", 1)
    if "format" not in top_pairs:
        _fail(shown, 1, "missing key 'format'", f"format: {FORMAT}")
    format_node = top_pairs["format"][1]
    if y.value(format_node) != FORMAT:
        y.fail(format_node, f"format is {_show(str(y.value(format_node)))}", f"{FORMAT!r}")
    top = y.keys(top_pairs, "", 1,
                 ("format", "gravity_mps2", "dtm", "camera", "imu", "initial_state"),
                 ("extra",))
    line_of = {key: y.line(key_node) for key, (key_node, _) in top_pairs.items()}

    gravity = y.number(top["gravity_mps2"], "gravity_mps2", positive=True)
    dtm = _parse_dtm(y, top["dtm"], line_of["dtm"], root)
    camera = _parse_camera(y, top["camera"], line_of["camera"])
    imu = _parse_imu(y, top["imu"], line_of["imu"])
    initial = _parse_initial_state(y, top["initial_state"], line_of["initial_state"])
    extra: dict = {}
    if "extra" in top:
        value = y.value(top["extra"])
        if value is not None and not isinstance(value, dict):
            y.fail(top["extra"], "extra is not a mapping", "extra: a mapping (or nothing)")
        extra = value or {}
    return FlightConfig(gravity, dtm, camera, imu, initial, extra)


def _parse_dtm(y: _Yaml, node: yaml.Node, line: int, root: Path) -> DtmConfig:
    m = y.keys(y.pairs(node, "dtm", line), "dtm", line, ("path",), ("sigma_h_m", "origin_enu_m"))
    text = y.text(m["path"], "dtm.path")
    given = Path(text)
    resolved = _normalized(given if given.is_absolute() else root / given)
    if resolved.suffix.lower() not in DTM_SUFFIXES:
        y.fail(m["path"], f"dtm.path {_show(text)} has suffix {_show(resolved.suffix)}",
               f"a {', '.join(DTM_SUFFIXES[:-1])} or {DTM_SUFFIXES[-1]} file")
    if not resolved.is_file():
        y.fail(m["path"], f"dtm.path {_show(text)} does not exist ({resolved})",
               "an existing DTM file, relative to the log directory or absolute")
    sigma_h = None
    if "sigma_h_m" in m and y.value(m["sigma_h_m"]) is not None:
        sigma_h = y.number(m["sigma_h_m"], "dtm.sigma_h_m", positive=True)
    origin = (0.0, 0.0, 0.0)
    if "origin_enu_m" in m:
        origin = tuple(y.vector(m["origin_enu_m"], "dtm.origin_enu_m", (3,)).tolist())
    return DtmConfig(resolved, sigma_h, origin)  # type: ignore[arg-type]


def _parse_camera(y: _Yaml, node: yaml.Node, line: int) -> CameraConfig:
    pairs = y.pairs(node, "camera", line)
    m = y.keys(pairs, "camera", line,
               ("resolution", "intrinsics", "pixel_sigma_px", "body_T_cam"),
               ("distortion_model", "distortion_coeffs"))
    res_node = m["resolution"]
    if not isinstance(res_node, yaml.SequenceNode) or len(res_node.value) != 2:
        y.fail(res_node, "camera.resolution is not two values", "[width, height] in pixels")
    width = y.integer(res_node.value[0], "camera.resolution width")
    height = y.integer(res_node.value[1], "camera.resolution height")
    fx, fy, cx, cy = y.vector(m["intrinsics"], "camera.intrinsics", (4,)).tolist()

    model_node = m.get("distortion_model")
    model = None if model_node is None else y.value(model_node)
    distortion: tuple[float, ...] = ()
    if model == "radtan":
        if "distortion_coeffs" not in m:
            y.fail(model_node, "distortion_model radtan without distortion_coeffs",
                   "camera.distortion_coeffs: [k1, k2, p1, p2] or [k1, k2, p1, p2, k3]")
        distortion = tuple(y.vector(m["distortion_coeffs"], "camera.distortion_coeffs",
                                    (4, 5)).tolist())
    elif model is None or model == "none":
        if "distortion_coeffs" in m:
            y.fail(m["distortion_coeffs"], "distortion_coeffs given without a distortion model",
                   "camera.distortion_model: radtan, or no distortion_coeffs")
    else:
        y.fail(model_node, f"distortion_model {_show(str(model))} is not supported",
               "radtan (OpenCV k1 k2 p1 p2 [k3]) or none")
    try:
        camera = PinholeCamera(width, height, fx, fy, cx, cy, distortion)
    except ValueError as exc:
        y.fail(m["intrinsics"], f"invalid camera: {exc}",
               "positive focal lengths fx, fy and a finite principal point cx, cy")
    sigma = y.number(m["pixel_sigma_px"], "camera.pixel_sigma_px", positive=True)

    mount_line = y.line(pairs["body_T_cam"][0])
    mount = y.keys(y.pairs(m["body_T_cam"], "camera.body_T_cam", mount_line),
                   "camera.body_T_cam", mount_line, ("translation_m", "quaternion_wxyz"))
    translation = y.vector(mount["translation_m"], "camera.body_T_cam.translation_m", (3,))
    quat = y.quaternion(mount["quaternion_wxyz"], "camera.body_T_cam.quaternion_wxyz")
    return CameraConfig(camera, sigma, make_pose(quat_wxyz_to_rotation(quat), translation))


_IMU_KEYS = ("rate_hz", "gyroscope_noise_density", "accelerometer_noise_density",
             "gyroscope_random_walk", "accelerometer_random_walk")


def _parse_imu(y: _Yaml, node: yaml.Node, line: int) -> ImuConfig:
    m = y.keys(y.pairs(node, "imu", line), "imu", line, _IMU_KEYS)
    # Zero noise would make the IMU factors' information infinite: positive required.
    return ImuConfig(*(y.number(m[key], f"imu.{key}", positive=True) for key in _IMU_KEYS))


_INITIAL_VECTORS = (("position_m", 3), ("quaternion_wxyz", 4), ("velocity_mps", 3),
                    ("gyro_bias", 3), ("accel_bias", 3))
_INITIAL_SIGMAS = ("sigma_position_m", "sigma_attitude_deg", "sigma_velocity_mps",
                   "sigma_gyro_bias", "sigma_accel_bias")


def _parse_initial_state(y: _Yaml, node: yaml.Node, line: int) -> InitialState:
    keys = tuple(name for name, _ in _INITIAL_VECTORS) + _INITIAL_SIGMAS
    m = y.keys(y.pairs(node, "initial_state", line), "initial_state", line, keys)
    values: dict[str, Any] = {}
    for name, n in _INITIAL_VECTORS:
        dotted = f"initial_state.{name}"
        values[name] = (y.quaternion(m[name], dotted) if name == "quaternion_wxyz"
                        else y.vector(m[name], dotted, (n,)))
    for name in _INITIAL_SIGMAS:
        values[name] = y.number(m[name], f"initial_state.{name}", positive=True)
    return InitialState(**values)


# --------------------------------------------------------------------------- read


def _normalized(path: Path) -> Path:
    """Absolute path with '..' folded, symlinks left alone (so paths compare as written)."""
    return Path(os.path.normpath(os.path.abspath(path)))


def read_flightlog(path: str | os.PathLike) -> FlightLog:
    """Read and validate a ``cdtm-flightlog/1`` directory.

    Image files named in frames.csv are checked for existence only when there is no
    tracks.csv (then the images are the only source of features).

    Args:
        path: the log directory.

    Returns:
        The flight log; ``root`` and ``config.dtm.path`` are absolute.

    Raises:
        FlightLogError: anything in the log that does not follow FLIGHTLOG.md; the
            message names the file, the line and what was expected.
    """
    given = Path(path)
    root = _normalized(given)

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
    if (root / TRACKS_CSV).is_file():
        tracks = _read_tracks(root / TRACKS_CSV, shown(TRACKS_CSV), len(frames),
                              config.camera.camera)
    else:
        for k, image in enumerate(frames.image):
            if not image:
                _fail(shown(FRAMES_CSV), frames_first_line + k,
                      f"frame {k} has no image and there is no {TRACKS_CSV}",
                      f"an image path for every frame, or a {TRACKS_CSV}")
            if not (root / image).is_file():
                _fail(shown(FRAMES_CSV), frames_first_line + k,
                      f"image {_show(image)} does not exist",
                      f"an image file relative to the log directory (or a {TRACKS_CSV})")

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


# --------------------------------------------------------------------------- write


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
        files[TRACKS_CSV] = _csv_text("#frame,track_id,u,v", [log.tracks.frame,
                                                             log.tracks.track_id],
                                      log.tracks.uv_px)
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
    target = _normalized(Path(path))
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


__all__ = [
    "FORMAT", "CameraConfig", "DtmConfig", "FlightConfig", "FlightLog", "Frames", "ImuConfig",
    "ImuSamples", "InitialState", "States", "Tracks", "read_flightlog", "write_flightlog",
]
