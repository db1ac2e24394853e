"""From what sensor files hold to a ``cdtm-flightlog/1`` log: the DTM, the prior, the files.

An importer (EuRoC folder, ROS bag) reads a :class:`SensorRecording`: IMU samples, camera
stamps on the camera's clock, the calibration, optionally ground truth. What the sensors do
not know comes from :class:`ImportSettings`: the DTM (and a geodetic origin, and the map's
own offset sigmas), the pixel noise, the initial state where no ground truth covers the
first frame, and whether the IMU noise densities are the stated ones or what the samples
show (:class:`ImuNoiseSource`; the samples' scatter is measured at every import, by
:func:`cdtm_graph.verdict.imu_faults.sample_noise`, and a stated density below it is said then,
not only after smoothing).
:func:`assemble_flightlog` makes the :class:`~cdtm_graph.flightlog.FlightLog`;
:func:`write_imported_log` writes it (and copies the DTM when asked) into a directory the
caller publishes (:func:`cdtm_graph.atomic.atomic_output_dir`), then reads it back: what
was written is what the smoother will read.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from cdtm_graph.constants import STANDARD_GRAVITY_MPS2
from cdtm_graph.errors import FlightLogError, SensorDataError, why_not_a_file
from cdtm_graph.flightlog.config import RANGES
from cdtm_graph.flightlog.model import (
    CameraConfig,
    DtmConfig,
    FlightConfig,
    FlightLog,
    Frames,
    ImuConfig,
    ImuSamples,
    InitialState,
    States,
    normalized_path,
)
from cdtm_graph.flightlog.reader import read_flightlog
from cdtm_graph.flightlog.tables import (
    _GROUNDTRUTH_SPEC,
    _is_geodetic_states,
    _read_states,
)
from cdtm_graph.flightlog.writer import write_flightlog_files
from cdtm_graph.geodesy import GeodeticOrigin, VerticalDatum, local_frame, normal_gravity_mps2
from cdtm_graph.geometry import quat_wxyz_to_rotation
from cdtm_graph.importers.calibration import CameraCalibration
from cdtm_graph.importers.options import ImuNoiseSource
from cdtm_graph.run.prepare import load_flight_dtm
from cdtm_graph.verdict.imu_faults import MeasuredImuNoise, sample_noise

logger = logging.getLogger(__name__)

#: Gravity of a log without a geodetic origin unless told otherwise (m/s^2).
#: Where image files go inside an imported log.
IMAGE_DIR = "images"
#: Sidecar files copied with a DTM (an .asc's CRS is in the .prj beside it).
DTM_SIDECARS = (".prj",)


@dataclass(frozen=True, eq=False)
class SensorRecording:
    """What a sensor recording holds, before a DTM and a prior make it a flight log.

    Attributes:
        source: the recording as the user named it (messages, ``extra.import``).
        imu: the IMU samples, body (IMU) frame, on the IMU clock.
        frame_t_cam_ns: (K,) int64 frame stamps on the camera's clock, strictly increasing.
        camera: the camera calibration (intrinsics, lens, mounting, clock offset).
        imu_config: the IMU's rate and noise densities.
        groundtruth: true body states on the IMU clock, or None.
        groundtruth_bias: (N, 6) gyro (rad/s) then accelerometer (m/s^2) biases at the
            ground truth's times (EuRoC's estimate has them), or None.
        provenance: what the importer records under ``extra: import:`` in flight.yaml.
    """

    source: str
    imu: ImuSamples
    frame_t_cam_ns: np.ndarray
    camera: CameraCalibration
    imu_config: ImuConfig
    groundtruth: States | None = None
    groundtruth_bias: np.ndarray | None = None
    provenance: dict = field(default_factory=dict)


@dataclass(frozen=True)
class DtmSource:
    """The DTM of an imported log (flight.yaml ``dtm:``; docs/flightlog.md, DTM files).

    Attributes:
        paths: the DTM file, or with an origin DEM tiles (mosaicked, first wins).
        sigma_h_m: the map's 1-sigma height error; None: the grid-spacing model.
        origin: a geodetic origin: the world is the ENU tangent plane there and the DEMs
            may be in any CRS; None: the DTM is a metric grid in the world frame.
        vertical_datum: what the DEM heights are above (required with an origin).
        crs: the CRS of DEM files that carry none.
        copy: copy the files into the log (else flight.yaml names them where they are).
        offset_sigma_m: (horizontal, vertical) 1-sigma of the whole map's offset (flight.yaml
            ``dtm.horizontal_offset_sigma_m``, ``dtm.vertical_offset_sigma_m``: a DEM
            product's absolute accuracy); None: not declared (the verdict's note).
    """

    paths: tuple[Path, ...]
    sigma_h_m: float | None = None
    origin: GeodeticOrigin | None = None
    vertical_datum: VerticalDatum | None = None
    crs: str | None = None
    copy: bool = False
    offset_sigma_m: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "paths", tuple(normalized_path(Path(p)) for p in self.paths))
        if not self.paths:
            raise SensorDataError("no DTM given; expected --dtm FILE (the terrain under the "
                                  "flight)")
        if len(self.paths) > 1 and self.origin is None:
            raise SensorDataError(f"{len(self.paths)} DTM files without a geodetic origin; "
                                  "expected one metric DTM, or --origin to mosaic DEM tiles")
        if (self.origin is None) != (self.vertical_datum is None):
            raise SensorDataError("a geodetic origin and a DEM vertical datum go together; "
                                  "expected both --origin and --vertical-datum, or neither")
        for path in self.paths:
            if not path.is_file():
                raise SensorDataError(f"{path}: DTM file {why_not_a_file(path)}; expected an "
                                      "existing DTM or DEM file")
        if self.offset_sigma_m is not None:
            sigmas = tuple(float(v) for v in self.offset_sigma_m)
            if len(sigmas) != 2:
                raise SensorDataError(f"DTM offset sigmas {self.offset_sigma_m!r}: expected "
                                      "two numbers, horizontal then vertical (m)")
            for key, value in zip(DtmConfig.OFFSET_SIGMA_KEYS, sigmas):
                limit = RANGES[f"dtm.{key}"]
                if not limit.lo <= value <= limit.hi:
                    raise SensorDataError(f"DTM {key} {value!r}: expected {limit}")
            object.__setattr__(self, "offset_sigma_m", sigmas)


@dataclass(frozen=True, eq=False)
class InitialPrior:
    """The initial state where no ground truth gives it, and the prior's sigmas.

    Every given field wins over ground truth; the sigmas are always these.

    Attributes:
        position_m: (3,) body position in world, or None.
        geodetic: (latitude_deg, longitude_deg, height_m) instead of ``position_m`` (needs
            an origin; then ``quaternion_wxyz`` and ``velocity_mps`` are in the local ENU
            at that position, as flight.yaml's geodetic initial state).
        quaternion_wxyz: (4,) body -> world, or None.
        velocity_mps: (3,) in world, or None.
        gyro_bias, accel_bias: (3,) turn-on biases, or None (ground truth's, else zero).
        sigma_*: the prior's 1-sigma values (flight.yaml ``initial_state.sigma_*``).
    """

    position_m: np.ndarray | None = None
    geodetic: tuple[float, float, float] | None = None
    quaternion_wxyz: np.ndarray | None = None
    velocity_mps: np.ndarray | None = None
    gyro_bias: np.ndarray | None = None
    accel_bias: np.ndarray | None = None
    sigma_position_m: float = 50.0
    sigma_attitude_deg: float = 1.0
    sigma_velocity_mps: float = 1.0
    sigma_gyro_bias: float = 1.0e-4
    sigma_accel_bias: float = 1.0e-2

    def __post_init__(self) -> None:
        for name, n in (("position_m", 3), ("quaternion_wxyz", 4), ("velocity_mps", 3),
                        ("gyro_bias", 3), ("accel_bias", 3)):
            value = getattr(self, name)
            if value is not None:
                arr = np.asarray(value, dtype=float)
                if arr.shape != (n,) or not np.all(np.isfinite(arr)):
                    raise SensorDataError(f"initial {name} {value!r}: expected {n} finite "
                                          "numbers")
                object.__setattr__(self, name, arr)
        if self.quaternion_wxyz is not None:
            norm = float(np.linalg.norm(self.quaternion_wxyz))
            if not abs(norm - 1.0) <= 1e-3:
                raise SensorDataError(f"initial quaternion has norm {norm:.6g}; expected a "
                                      "unit quaternion w x y z")
            object.__setattr__(self, "quaternion_wxyz", self.quaternion_wxyz / norm)
        if self.position_m is not None and self.geodetic is not None:
            raise SensorDataError("both an initial position and an initial latitude/longitude/"
                                  "height; expected one of the two")
        for name in ("sigma_position_m", "sigma_attitude_deg", "sigma_velocity_mps",
                     "sigma_gyro_bias", "sigma_accel_bias"):
            limit = RANGES[f"initial_state.{name}"]
            value = float(getattr(self, name))
            if not limit.lo <= value <= limit.hi:
                raise SensorDataError(f"initial {name} {value!r}: expected {limit}")
            object.__setattr__(self, name, value)


@dataclass(frozen=True)
class ImportSettings:
    """What a flight log needs beyond the sensor files.

    Attributes:
        dtm: the terrain.
        pixel_sigma_px: 1-sigma of a tracked feature's position (flight.yaml
            ``camera.pixel_sigma_px``).
        gravity_mps2: gravity; None: 9.80665 m/s^2, or WGS84 normal gravity at the origin.
        initial: the initial state where ground truth does not give it, and its sigmas.
        imu_noise: the calibration's noise densities, or the samples' own where larger.
        principal_point_sigma_px: how well the calibration knows ``cx``, ``cy`` (flight.yaml
            ``camera.principal_point_sigma_px``); None: undeclared.
    """

    dtm: DtmSource
    pixel_sigma_px: float = 0.5
    gravity_mps2: float | None = None
    initial: InitialPrior = field(default_factory=InitialPrior)
    imu_noise: ImuNoiseSource = ImuNoiseSource.STATED
    principal_point_sigma_px: float | None = None


def image_size_px(image: Path) -> tuple[int, int]:
    """(width, height) of an image file.

    Raises:
        SensorDataError: it cannot be read as an image.
    """
    pixels = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
    if pixels is None:
        raise SensorDataError(f"{image}: cannot be read as an image; expected a PNG or "
                              "another format OpenCV reads")
    height, width = pixels.shape[:2]
    return width, height


def check_image_size(image: Path, cam: CameraCalibration) -> None:
    """An image has the calibration's resolution (else a wrong camera or camchain).

    Raises:
        SensorDataError: naming the image and both sizes.
    """
    width, height = image_size_px(image)
    c = cam.camera
    if (width, height) != (c.width, c.height):
        raise SensorDataError(f"{image}: {width}x{height} px but the calibration says "
                              f"{c.width}x{c.height}; expected images of the calibrated "
                              "camera")


def read_groundtruth(path: str | os.PathLike, origin: GeodeticOrigin | None
                     ) -> tuple[States, np.ndarray | None]:
    """A ground-truth CSV: groundtruth.csv's columns, EuRoC's state_groundtruth_estimate0
    (whose columns 12-17 are the gyro and accelerometer biases), or geodetic columns.

    Returns:
        The states in the world frame, and (N, 6) biases when the file has 17 columns.

    Raises:
        FlightLogError: the file is malformed (file, line, expected); geodetic columns
            without an origin.
    """
    path = Path(path)
    shown = str(path)
    geodetic = _is_geodetic_states(path)
    if geodetic and origin is None:
        raise FlightLogError(f"{shown}:1: latitude/longitude columns without a geodetic "
                             "origin; expected --origin LAT LON H, or world columns")
    states, first_line = _read_states(path, shown, _GROUNDTRUTH_SPEC)
    if len(states) == 0:
        raise FlightLogError(f"{shown}:{first_line}: no rows; expected "
                             f"{_GROUNDTRUTH_SPEC.expected_row}")
    if geodetic:
        assert origin is not None
        p = states.position_m
        position, quat, velocity = local_frame(origin).states_from_geodetic(
            p[:, 0], p[:, 1], p[:, 2], states.quaternion_wxyz, states.velocity_mps)
        states = States(states.t_ns, position, quat, velocity)
    return states, None if geodetic else _euroc_biases(path, first_line, len(states))


#: EuRoC's state_groundtruth_estimate0 columns: t, p(3), q(4), v(3), b_w(3), b_a(3).
_EUROC_GROUNDTRUTH_COLUMNS = 17


def _euroc_biases(path: Path, first_line: int, n_rows: int) -> np.ndarray | None:
    """Columns 12-17 of a EuRoC ground truth (gyro, accelerometer biases), or None."""
    with path.open(encoding="utf-8-sig") as f:
        lines = f.read().splitlines()[first_line - 1:]
    if not lines or len(lines[0].split(",")) != _EUROC_GROUNDTRUTH_COLUMNS:
        return None
    out = np.empty((n_rows, 6))
    for i, text in enumerate(lines[:n_rows]):
        fields = text.split(",")
        try:
            if len(fields) != _EUROC_GROUNDTRUTH_COLUMNS:
                raise ValueError
            out[i] = [float(v) for v in fields[11:]]
        except ValueError:
            raise FlightLogError(
                f"{path}:{first_line + i}: {len(fields)} values with a malformed bias column; "
                f"expected {_EUROC_GROUNDTRUTH_COLUMNS} numbers like the first row (EuRoC "
                "state_groundtruth_estimate0: t, p, q, v, gyro bias, accelerometer bias)"
            ) from None
    if not np.all(np.isfinite(out)):
        return None
    return out


def assemble_flightlog(recording: SensorRecording, images: tuple[str, ...],
                       settings: ImportSettings) -> FlightLog:
    """The flight log of a recording (``root`` a placeholder: ``Path(".")``).

    The frames are moved onto the IMU clock by the camera's ``time_offset_s``, which
    flight.yaml keeps (frames.csv holds the camera stamps); frames outside the IMU's time
    span are left out (counted in ``extra.import.frames_outside_imu``). The initial state
    at the first
    frame is the ground truth there (biases too when it has them), field by field
    overridden by ``settings.initial``; what neither gives is an error.

    Args:
        recording: the sensor data.
        images: one path per frame, relative to the log directory.
        settings: DTM, pixel noise, gravity, prior.

    Raises:
        SensorDataError: the initial state is not known; fewer than 2 frames lie inside
            the IMU's time span.
        DtmError: the DTM cannot be read, or is nowhere near the flight (it is read here
            as the smoother will read it).
    """
    cam = recording.camera
    for name, key, value in (
            ("pixel sigma", "camera.pixel_sigma_px", settings.pixel_sigma_px),
            ("principal point sigma", "camera.principal_point_sigma_px",
             settings.principal_point_sigma_px)):
        if value is not None and not RANGES[key].lo <= value <= RANGES[key].hi:
            raise SensorDataError(f"{name} {value!r} px: expected {RANGES[key]}")
    camera_config = CameraConfig(cam.camera, settings.pixel_sigma_px, cam.body_T_cam,
                                 cam.time_offset_s,
                                 principal_point_sigma_px=settings.principal_point_sigma_px)
    frames = _frames_inside_imu(recording, Frames(
        recording.frame_t_cam_ns + camera_config.time_offset_ns, images))
    dtm = settings.dtm
    origin = dtm.origin
    if settings.gravity_mps2 is not None:
        gravity = float(settings.gravity_mps2)
    elif origin is not None:
        gravity = float(normal_gravity_mps2(origin.latitude_deg, origin.height_m))
    else:
        gravity = STANDARD_GRAVITY_MPS2
    limit = RANGES["gravity_mps2"]
    if not limit.lo <= gravity <= limit.hi:
        raise SensorDataError(f"gravity {gravity!r} m/s^2: expected {limit}")
    names = [Path(p.name) for p in dtm.paths] if dtm.copy else list(dtm.paths)
    offsets = dtm.offset_sigma_m or (None, None)
    dtm_config = DtmConfig(names[0], dtm.sigma_h_m, (0.0, 0.0, 0.0), tuple(names[1:]),
                           dtm.vertical_datum, dtm.crs, horizontal_offset_sigma_m=offsets[0],
                           vertical_offset_sigma_m=offsets[1])
    initial = _initial_state(recording, int(frames.t_ns[0]), settings.initial, origin)
    imu_config, noise = imu_noise_config(recording, settings.imu_noise)
    extra = {"import": {"source": recording.source, **recording.provenance,
                        "frames_outside_imu": len(images) - len(frames),
                        "imu_noise_source": settings.imu_noise.value,
                        "imu_noise_measured": noise.to_dict() if noise is not None else None}}
    config = FlightConfig(gravity, dtm_config, camera_config, imu_config, initial,
                          extra, origin)
    log = FlightLog(Path("."), config, recording.imu, frames, None, None,
                    recording.groundtruth)
    _check_dtm(log, dtm)
    return log


def imu_noise_config(recording: SensorRecording, source: ImuNoiseSource
                     ) -> tuple[ImuConfig, MeasuredImuNoise | None]:
    """The IMU configuration an imported log gets, and the samples' measured noise.

    The samples' white noise is measured (:func:`cdtm_graph.verdict.imu_faults.sample_noise`, as
    the verdict measures it after smoothing). With the stated densities, one found above
    them by more than the verdict's ``max_imu_noise_ratio`` is said now (a warning naming
    the measured values): smoothing would end ``degraded: imu_noise``. With
    :attr:`ImuNoiseSource.MEASURED` each density becomes its noisiest axis's measured
    value where that is larger than the stated one.

    Returns:
        The configuration, and the measurement (None: under 10 samples).
    """
    from cdtm_graph.verdict import VerdictSettings  # the threshold smoothing will apply

    stated = recording.imu_config
    imu = recording.imu
    noise = sample_noise(imu.t_ns, imu.gyro_radps, imu.acc_mps2,
                         stated.gyroscope_noise_density, stated.accelerometer_noise_density)
    if noise is None:
        return stated, None
    gyro, accel = float(np.max(noise.gyro_density)), float(np.max(noise.accel_density))
    if source is ImuNoiseSource.MEASURED:
        config = dataclasses.replace(
            stated, gyroscope_noise_density=max(gyro, stated.gyroscope_noise_density),
            accelerometer_noise_density=max(accel, stated.accelerometer_noise_density))
        for key in ("gyroscope_noise_density", "accelerometer_noise_density"):
            limit = RANGES[f"imu.{key}"]
            if not getattr(config, key) <= limit.hi:
                raise SensorDataError(f"{recording.source}: the IMU samples scatter as a "
                                      f"{key} of {getattr(config, key):.3g}; expected "
                                      f"{limit} (a stuck clock, or values in other units)")
        return config, noise
    gyro_ratio, accel_ratio = noise.ratios
    if max(gyro_ratio, accel_ratio) > VerdictSettings().max_imu_noise_ratio:
        logger.warning(
            "%s: the IMU samples scatter %.1fx (gyro) and %.1fx (accelerometer) the stated "
            "noise densities: measured %.3g rad/s/sqrt(Hz) and %.3g m/s^2/sqrt(Hz) (median "
            "axis; noisiest %.3g and %.3g) against %.3g and %.3g stated (vibration counts); "
            "smoothing will say degraded: imu_noise; --imu-noise measured takes the "
            "measured values", recording.source, gyro_ratio, accel_ratio,
            float(np.median(noise.gyro_density)), float(np.median(noise.accel_density)),
            gyro, accel, stated.gyroscope_noise_density, stated.accelerometer_noise_density)
    return stated, noise


def _check_dtm(log: FlightLog, dtm: DtmSource) -> None:
    """Read the DTM the way the smoother will read the imported log (the whole file, or
    the DEM window under the prior track, resampled), before anything is written: a
    damaged or oversized map, or one nowhere near the flight, fails the import instead of
    being published in a log that can never be smoothed.

    Raises:
        DtmError: naming the user's file.
    """
    cfg = dataclasses.replace(log.config.dtm, path=dtm.paths[0], more_paths=dtm.paths[1:])
    load_flight_dtm(dataclasses.replace(log, config=dataclasses.replace(log.config, dtm=cfg)))


def _frames_inside_imu(recording: SensorRecording, frames: Frames) -> Frames:
    """The frames inside the IMU's time span: the smoother needs samples around every frame,
    and a recording's camera often starts before its IMU (or ends after it)."""
    t_imu = recording.imu.t_ns
    inside = (frames.t_ns >= t_imu[0]) & (frames.t_ns <= t_imu[-1])
    if inside.sum() < 2:
        raise SensorDataError(
            f"{recording.source}: {int(inside.sum())} frame(s) inside the IMU's time span "
            f"[{int(t_imu[0])}, {int(t_imu[-1])}] ns (frames {int(frames.t_ns[0])}.."
            f"{int(frames.t_ns[-1])} ns on the IMU clock); expected at least 2, with camera "
            "and IMU stamps on one clock up to timeshift_cam_imu")
    if inside.all():
        return frames
    logger.warning("%s: %d of %d frames lie outside the IMU's time span and are left out",
                   recording.source, int((~inside).sum()), len(frames))
    keep = np.flatnonzero(inside)
    return Frames(frames.t_ns[keep], tuple(frames.image[k] for k in keep))


_PRIOR_FLAGS = (("position_m", "--initial-position X Y Z"),
                ("quaternion_wxyz", "--initial-quaternion W X Y Z"),
                ("velocity_mps", "--initial-velocity VX VY VZ"))


def check_prior(settings: ImportSettings, has_groundtruth: bool, source: str) -> None:
    """Without ground truth the prior must give the whole initial state (an early check,
    before a long read; :func:`assemble_flightlog` checks again at the first frame).

    Raises:
        SensorDataError: naming the missing flags.
    """
    if has_groundtruth:
        return
    prior = settings.initial
    given = {"position_m": prior.position_m is not None or prior.geodetic is not None,
             "quaternion_wxyz": prior.quaternion_wxyz is not None,
             "velocity_mps": prior.velocity_mps is not None}
    missing = [flag for name, flag in _PRIOR_FLAGS if not given[name]]
    if missing:
        raise SensorDataError(f"{source}: no ground truth gives the initial state at the "
                              f"first frame; expected {', '.join(missing)}")


def _initial_state(recording: SensorRecording, t0_ns: int, prior: InitialPrior,
                   origin: GeodeticOrigin | None) -> InitialState:
    truth = recording.groundtruth
    at_truth = truth is not None and truth.t_ns[0] <= t0_ns <= truth.t_ns[-1]
    values: dict[str, np.ndarray] = {"gyro_bias": np.zeros(3), "accel_bias": np.zeros(3)}
    if at_truth:
        assert truth is not None
        state = truth.interpolate(t0_ns)
        values.update(position_m=state.position_m[0], quaternion_wxyz=state.quaternion_wxyz[0],
                      velocity_mps=state.velocity_mps[0])
        if recording.groundtruth_bias is not None:
            k = int(np.argmin(np.abs(truth.t_ns - t0_ns)))  # biases drift slowly: nearest row
            values.update(gyro_bias=recording.groundtruth_bias[k, :3],
                          accel_bias=recording.groundtruth_bias[k, 3:])
    for name in ("position_m", "quaternion_wxyz", "velocity_mps", "gyro_bias", "accel_bias"):
        given = getattr(prior, name)
        if given is not None:
            values[name] = given
    if prior.geodetic is not None:
        if origin is None:
            raise SensorDataError("an initial latitude/longitude/height without a geodetic "
                                  "origin; expected --origin LAT LON H too, or "
                                  "--initial-position in the world frame")
        quat, vel = prior.quaternion_wxyz, prior.velocity_mps
        if quat is None or vel is None:
            raise SensorDataError("a geodetic initial position needs --initial-quaternion and "
                                  "--initial-velocity in the local ENU there")
        lat, lon, h = prior.geodetic
        position, q, v = local_frame(origin).states_from_geodetic(lat, lon, h, quat, vel)
        values.update(position_m=position[0], quaternion_wxyz=q[0], velocity_mps=v[0])
    missing = [flag for name, flag in _PRIOR_FLAGS if name not in values]
    if missing:
        where = ("no ground truth" if truth is None else
                 f"the ground truth spans {int(truth.t_ns[0])}..{int(truth.t_ns[-1])} ns")
        raise SensorDataError(
            f"{recording.source}: the initial state at the first frame (t_ns {t0_ns} on the "
            f"IMU clock) is unknown ({where}); expected {', '.join(missing)}")
    for name, key in (("position_m", "initial_state.position_m"),
                      ("velocity_mps", "initial_state.velocity_mps"),
                      ("gyro_bias", "initial_state.gyro_bias"),
                      ("accel_bias", "initial_state.accel_bias")):
        limit = RANGES[key]
        if not np.all((values[name] >= limit.lo) & (values[name] <= limit.hi)):
            raise SensorDataError(f"initial {name} {values[name].tolist()}: expected each "
                                  f"{limit}")
    return InitialState(
        values["position_m"], values["quaternion_wxyz"], values["velocity_mps"],
        values["gyro_bias"], values["accel_bias"], prior.sigma_position_m,
        prior.sigma_attitude_deg, prior.sigma_velocity_mps, prior.sigma_gyro_bias,
        prior.sigma_accel_bias)


def write_imported_log(log: FlightLog, settings: ImportSettings, directory: str | os.PathLike,
                       final_dir: str | os.PathLike, geodetic: bool = False) -> FlightLog:
    """Write an assembled log's files (and copy its DTM when asked) into ``directory``.

    The images must already be there (the importer writes them as it reads). The log is
    read back from ``directory`` and compared with ``log``, so a value the reader would
    refuse, or one that does not survive the round trip, fails here, before publishing.

    Args:
        log: from :func:`assemble_flightlog`.
        settings: as given to it (the DTM files to copy).
        directory: where to write now (a staging directory).
        final_dir: where the log will live (messages, relative DTM paths).
        geodetic: the initial state and ground truth in latitude, longitude and height
            (a log with a geodetic origin; they then read back to rounding, not bit for
            bit: :data:`GEODETIC_ROUND_TRIP_TOL_M`).

    Returns:
        The log as read back (root ``directory``).

    Raises:
        FlightLogError: the written log does not read back as assembled.
    """
    directory = Path(directory)
    if settings.dtm.copy:
        for source in settings.dtm.paths:
            shutil.copyfile(source, directory / source.name)
            for suffix in DTM_SIDECARS:
                sidecar = source.with_suffix(suffix)
                if sidecar.is_file() and sidecar != source:
                    shutil.copyfile(sidecar, directory / sidecar.name)
    write_flightlog_files(log, directory, final_dir, geodetic=geodetic)
    try:
        back = read_flightlog(directory, read_tracks=False)
    except FlightLogError as exc:  # a value of the inputs (a camchain's), as written
        raise FlightLogError(str(exc).replace(str(directory), str(final_dir))
                             + " (in the log the import would write from its inputs: "
                             "nothing was written)") from None
    expected = dataclasses.replace(log, root=back.root, config=dataclasses.replace(
        log.config, dtm=back.config.dtm))
    _check_round_trip(expected, back, Path(final_dir), geodetic)
    return back


#: States written in latitude, longitude and height read back within this (m, and m/s
#: and rad for velocities and attitudes): PROJ's round trip is ~1e-9 m.
GEODETIC_ROUND_TRIP_TOL_M = 1e-6


def _same_states(a: States | None, b: States | None, geodetic: bool) -> bool:
    if a is None or b is None or not geodetic:
        return a == b
    tol = GEODETIC_ROUND_TRIP_TOL_M
    rotation = np.einsum("nji,njk->nik", quat_wxyz_to_rotation(a.quaternion_wxyz),
                         quat_wxyz_to_rotation(b.quaternion_wxyz))
    return (np.array_equal(a.t_ns, b.t_ns)
            and np.allclose(a.position_m, b.position_m, rtol=0.0, atol=tol)
            and np.allclose(a.velocity_mps, b.velocity_mps, rtol=0.0, atol=tol)
            and np.allclose(rotation, np.eye(3), rtol=0.0, atol=tol))


def _check_round_trip(expected: FlightLog, back: FlightLog, shown: Path,
                      geodetic: bool = False) -> None:
    """The written log reads back as assembled (``body_T_cam`` to float rounding, states
    written in latitude and longitude to :data:`GEODETIC_ROUND_TRIP_TOL_M`)."""
    same = (back.imu == expected.imu and back.frames == expected.frames
            and _same_states(back.groundtruth, expected.groundtruth, geodetic)
            and back.config.camera.camera == expected.config.camera.camera
            and back.config.camera.time_offset_s == expected.config.camera.time_offset_s
            and np.allclose(back.config.camera.body_T_cam, expected.config.camera.body_T_cam,
                            rtol=0.0, atol=1e-12)
            and back.config.imu == expected.config.imu)
    if not same:  # a writer/reader disagreement: a bug, but never a silently different log
        raise FlightLogError(f"{shown}: the written log does not read back as imported; "
                             "expected an exact round trip (please report this)")
