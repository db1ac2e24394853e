"""The data model of a ``cdtm-flightlog/1`` log (docs/flightlog.md): plain numpy, no I/O.

The tolerances and dataclasses every reader and writer of the format shares (the file
names: :mod:`~cdtm_graph.flightlog.names`, re-exported here).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from cdtm_graph.camera import PinholeCamera
from cdtm_graph.errors import FlightLogError
from cdtm_graph.flightlog.names import (  # noqa: F401  (re-exported: the format's names)
    FLIGHT_YAML,
    FORMAT,
    FRAMES_CSV,
    GROUNDTRUTH_CSV,
    IMU_CSV,
    LOG_FILES,
    NAV_CSV,
    TRACKS_CSV,
)
from cdtm_graph.geodesy import GeodeticOrigin, LocalFrame, VerticalDatum, local_frame
from cdtm_graph.geometry import make_pose, quat_wxyz_to_rotation

DTM_SUFFIXES = (".npz", ".asc", ".tif")
#: DEM files a geodetic log (top-level ``origin:``) may name: any CRS, read through GDAL.
GEODETIC_DTM_SUFFIXES = (".tif", ".tiff", ".asc", ".hgt")

#: A quaternion whose norm is further than this from 1 is a data error, not rounding
#: (six printed digits, as in EuRoC's ground truth, stay well inside it).
QUATERNION_UNIT_TOL = 1e-3
#: Quaternions this close to unit norm are kept bit for bit, so that writing and
#: reading a log round-trips exactly (renormalizing would flip last bits).
QUATERNION_EXACT_TOL = 1e-12


def normalized_path(path: Path) -> Path:
    """Absolute path with '..' folded, symlinks left alone (so paths compare as written)."""
    return Path(os.path.normpath(os.path.abspath(path)))


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
        path: the DTM file (.npz, .asc or .tif; with a geodetic origin also .tiff, .hgt).
            The reader resolves a relative path against the log directory; a relative
            path given to the writer is written as is.
        sigma_h_m: 1-sigma height error of the DTM in metres; None: derive it from
            the grid spacing.
        origin_enu_m: subtracted from the DTM's own x, y, z to give world coordinates
            (logs without a geodetic origin only).
        more_paths: further tiles of a mosaic, after ``path`` (geodetic logs only; the
            first file listed wins where tiles overlap).
        vertical_datum: what the DEM's heights are measured from; required with a
            geodetic origin, None without.
        crs: the CRS of DEM files that carry none, e.g. ``"EPSG:4326"`` (geodetic logs).
        margin_m: how far around the prior track the DEM is read (m); None: the default
            of :mod:`cdtm_graph.dem`.
        spacing_m: spacing of the world grid the DEM is resampled into (m); None: the
            DEM's own finest pixel size in metres.
        horizontal_offset_sigma_m, vertical_offset_sigma_m: 1-sigma of an offset of the
            whole map under the flight (its registration and its vertical datum, a DEM
            product's absolute accuracy), apart from ``sigma_h_m``, the point-to-point
            error. The camera and the DTM cannot see such an offset: it passes one for
            one into every position, so it is added to the position covariances. None:
            not declared (taken as 0, and the verdict says so in a note).
    """

    #: flight.yaml's keys (under ``dtm:``) of the map's own offset, horizontal then vertical.
    OFFSET_SIGMA_KEYS: ClassVar[tuple[str, str]] = ("horizontal_offset_sigma_m",
                                                     "vertical_offset_sigma_m")

    path: Path
    sigma_h_m: float | None = None
    origin_enu_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    more_paths: tuple[Path, ...] = ()
    vertical_datum: VerticalDatum | None = None
    crs: str | None = None
    margin_m: float | None = None
    spacing_m: float | None = None
    horizontal_offset_sigma_m: float | None = None
    vertical_offset_sigma_m: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "path", Path(self.path))
        object.__setattr__(self, "more_paths", tuple(Path(p) for p in self.more_paths))
        object.__setattr__(self, "origin_enu_m", tuple(float(x) for x in self.origin_enu_m))
        if len(self.origin_enu_m) != 3:
            raise ValueError(f"origin_enu_m must have 3 values, got {self.origin_enu_m}")
        if self.sigma_h_m is not None:
            object.__setattr__(self, "sigma_h_m", float(self.sigma_h_m))
        if self.vertical_datum is not None:
            object.__setattr__(self, "vertical_datum", VerticalDatum(self.vertical_datum))
        for name in ("margin_m", "spacing_m", *self.OFFSET_SIGMA_KEYS):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, float(getattr(self, name)))

    @property
    def paths(self) -> tuple[Path, ...]:
        """Every DEM file, ``path`` first."""
        return (self.path, *self.more_paths)


@dataclass(frozen=True)
class CalibrationSigmas:
    """Prior 1-sigmas of the camera calibration a run may estimate online
    (``camera.calibration`` in flight.yaml; :mod:`cdtm_graph.calibration.online`).

    Attributes:
        time_offset_sigma_s: of the camera-IMU clock offset about ``time_offset_s``.
        mount_sigma_deg: of the mount's rotation about ``body_T_cam`` (each axis).
        focal_scale_sigma: of the focal lengths' common scale about 1 (0.01: 1%).
    """

    time_offset_sigma_s: float
    mount_sigma_deg: float
    focal_scale_sigma: float

    def __post_init__(self) -> None:
        for name in ("time_offset_sigma_s", "mount_sigma_deg", "focal_scale_sigma"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be positive and finite, got {value!r}")
            object.__setattr__(self, name, value)


@dataclass(frozen=True, eq=False)
class CameraConfig(_ArrayEq):
    """The camera and its mounting (``camera:`` in flight.yaml).

    Attributes:
        camera: intrinsics and distortion.
        pixel_sigma_px: 1-sigma feature location error in pixels.
        body_T_cam: (4, 4) pose of the camera in the body (IMU) frame.
        time_offset_s: the camera clock's offset, Kalibr's ``timeshift_cam_imu``:
            ``t_imu = t_cam + time_offset_s``. frames.csv holds camera stamps; the reader
            adds the offset (:attr:`time_offset_ns`), so :attr:`FlightLog.frames` is on the
            IMU clock, and the writer takes it off again. An online estimate of the
            offset starts from this value as its prior.
        calibration: prior sigmas of the calibration estimated online (the values above
            are the priors' means); None: the run's settings decide.
        principal_point_sigma_px: 1-sigma of ``cx`` and ``cy`` each (px): how well the
            camera's calibration knows its principal point. No run estimates it, so its
            effect on the poses is added to their covariances, as a considered parameter
            (:mod:`cdtm_graph.calibration.considered`); None: not declared, nothing added.
    """

    camera: PinholeCamera
    pixel_sigma_px: float
    body_T_cam: np.ndarray
    time_offset_s: float = 0.0
    calibration: CalibrationSigmas | None = None
    principal_point_sigma_px: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "pixel_sigma_px", float(self.pixel_sigma_px))
        object.__setattr__(self, "body_T_cam", _as_float("body_T_cam", self.body_T_cam, (4, 4)))
        object.__setattr__(self, "time_offset_s", float(self.time_offset_s))
        if not math.isfinite(self.time_offset_s):
            raise ValueError(f"time_offset_s must be finite, got {self.time_offset_s!r}")

    @property
    def time_offset_ns(self) -> int:
        """``time_offset_s`` in integer nanoseconds (rounded): ``t_imu_ns = t_cam_ns + this``."""
        return int(round(self.time_offset_s * 1e9))


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

    Always in the world frame: a flight.yaml that gives the state in latitude, longitude
    and height (and attitude and velocity in the local ENU there) is converted on reading.

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
        gravity_mps2: gravity magnitude; gravity points along -z of world (the flat
            model). With a geodetic origin flight.yaml may leave it out: WGS84 normal
            gravity at the origin.
        dtm: the DTM file and its settings.
        camera: camera intrinsics, pixel noise and mounting.
        imu: IMU noise model.
        initial_state: prior on the first body state.
        extra: the top-level ``extra:`` mapping, kept as read and otherwise ignored.
        origin: the geodetic point whose local ENU tangent plane is the world frame, or
            None: the world is a plane with no place on the Earth.
    """

    gravity_mps2: float
    dtm: DtmConfig
    camera: CameraConfig
    imu: ImuConfig
    initial_state: InitialState
    extra: dict = field(default_factory=dict)
    origin: GeodeticOrigin | None = None

    @property
    def local_frame(self) -> LocalFrame | None:
        """The world frame on the Earth (conversions, gravity), or None without an origin."""
        return None if self.origin is None else local_frame(self.origin)


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

    def covers(self, t_ns: np.ndarray) -> np.ndarray:
        """(Q,) bool: each of the times ``t_ns`` (Q,) lies in the sampled range (where
        :meth:`interpolate` answers); all False without samples."""
        t = np.asarray(t_ns, dtype=np.int64)
        if len(self) == 0:
            return np.zeros(t.shape, dtype=bool)
        return (t >= self.t_ns[0]) & (t <= self.t_ns[-1])

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
        outside = ~self.covers(query)
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
        frames: frames.csv, with times on the IMU clock: frames.csv's camera stamps plus
            ``config.camera.time_offset_s`` (:attr:`frame_t_cam_ns` gives the stamps).
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

    @property
    def frame_t_cam_ns(self) -> np.ndarray:
        """(K,) int64 frame times on the camera's clock, as frames.csv holds them:
        ``frames.t_ns - config.camera.time_offset_ns``."""
        return self.frames.t_ns - self.config.camera.time_offset_ns


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


