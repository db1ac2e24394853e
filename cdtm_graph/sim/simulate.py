"""Simulated flight logs: terrain, flight, IMU, ray-cast feature tracks (paper section VI.A).

The paper evaluates C-DTM inside a navigation filter on a simulated flight at 200 m/s
over a synthetic DTM made by cloning a basic cell of terrain until it covers the flight
region (Figs. 10-12), with an IMU error model, a 60 degree FOV and about 100-170
features per frame pair. :func:`simulate` builds the same kind of flight and returns it
as a ``cdtm-flightlog/1`` log (docs/flightlog.md) plus the DTM to ship with it:

* **Terrain** (the truth). By default a 3x3 km fractal cell with the paper's 300 m of
  relief (:func:`cdtm_graph.sim.terrain.fractal_terrain`), tiled over the region the flight
  and its camera footprint cover (:func:`cdtm_graph.sim.terrain.clone_basic_cell`; the cell
  is periodic, so plain tiling is seamless) and cropped to it. Or a DTM file given by
  the user, which is then both the truth and the log's DTM.
* **The log's DTM**. The truth resampled to ``dtm_spacing_m`` (30 m, as the paper) with
  ``sigma_h`` from the Fig. 6 model, or the truth itself (``exact_dtm``, ``noiseless``).
* **Flight**. A :class:`~cdtm_graph.sim.trajectory.FlightPlan` at constant altitude above
  the terrain's mean height: straight legs joined by alternating coordinated turns (the
  course zig-zags about east, so the flight region stays a band), with a small attitude
  wobble so the camera is never exactly level.
* **IMU**. :func:`~cdtm_graph.imu.simulate_imu` at 200 Hz with white noise and bias
  random walks at flight.yaml's densities; the initial biases are drawn from their
  priors. With a geodetic ``origin`` it senses the Earth's rotation and WGS84 normal
  gravity (:func:`~cdtm_graph.sim.imu.earth_imu`).
* **Tracks**. Ground features made by ray casting from the true camera into the true
  terrain and followed by projecting their ground points into later frames, each
  observation occlusion-checked (a ray from the camera toward the point must first hit
  the terrain at the point), inside the image after pixel noise. Tracks die when lost.
  New tracks are spawned only where they are also seen in the next frame (what a
  tracker's matched pairs give), so every consecutive frame pair has ``n_features``
  features exactly unless the terrain refuses (the shortfall is logged and counted).

All randomness comes from one seed, split into independent streams (terrain, initial
state, IMU, tracks, nav), so changing e.g. the feature count leaves the terrain and the
IMU samples as they were. The only I/O is reading a terrain file (``terrain``) and
writing the log (:func:`write_simulated_log`, :func:`write_simulation`).
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cdtm_graph.atomic import atomic_output_dir
from cdtm_graph.camera import DOWNWARD_BODY_T_CAM, DistortionModel, PinholeCamera
from cdtm_graph.constants import NS_PER_S
from cdtm_graph.dtm import Dtm, RayStatus, load_dtm, save_dtm_npz, sigma_h_from_grid_spacing
from cdtm_graph.errors import CdtmError, SimulationError  # noqa: F401  (re-exported)
from cdtm_graph.flightlog import (
    CameraConfig,
    DtmConfig,
    FlightConfig,
    FlightLog,
    Frames,
    ImuConfig,
    ImuSamples,
    InitialState,
    States,
    Tracks,
    write_flightlog_files,
)
from cdtm_graph.flightlog.config import RESOLUTION_RANGE_PX
from cdtm_graph.geodesy import GeodeticOrigin, VerticalDatum, local_frame, normal_gravity_mps2
from cdtm_graph.geometry import make_pose, rotation_to_quat_wxyz, so3_exp
from cdtm_graph.imu import ImuNoise, dead_reckoning
from cdtm_graph.sim.faults import (
    FlatGround,
    TerrainMismatch,
    apply_flat_ground,
    apply_terrain_mismatch,
)
from cdtm_graph.sim.geodetic import origin_of, write_geodetic_simulation_files
from cdtm_graph.sim.imu import ImuData, simulate_imu
from cdtm_graph.sim.map_detail import MapDetail, apply_map_detail
from cdtm_graph.sim.render import write_images
from cdtm_graph.sim.settings import (
    DEFAULT_SEED,
    NOMINAL_ALTITUDE_M,
    NOMINAL_DTM_SPACING_M,
    NOMINAL_FEATURES,
    NOMINAL_FPS,
    NOMINAL_FRAMES,
    NOMINAL_RELIEF_M,
    NOMINAL_RESOLUTION_PX,
    NOMINAL_SPEED_MPS,
    NavMode,
)
from cdtm_graph.sim.terrain import NOMINAL_CORRELATION_LENGTH_M, fractal_terrain
from cdtm_graph.sim.trajectory import STANDARD_GRAVITY_MPS2, FlightPlan, Trajectory, evaluate

logger = logging.getLogger(__name__)

__all__ = [
    "DTM_FILENAME",
    "NavMode",
    "SimulationError",
    "SimulationResult",
    "SimulationSettings",
    "TrackEnd",
    "TrackStats",
    "simulate",
    "simulate_flight",
    "write_simulated_log",
    "write_simulation",
    "write_simulation_files",
]

#: Name of the DTM file inside a simulated log directory.
DTM_FILENAME = "dtm.npz"

#: sigma_h (m) written for a DTM that *is* the surface the features lie on: only
#: round-off separates them, but flight.yaml requires sigma_h > 0.
EXACT_DTM_SIGMA_H_M = 0.1

#: A feature is visible from a camera if the ray toward it first meets the terrain
#: within this distance of it (m). The ground point lies on the surface to round-off and
#: the ray cast is exact (~1e-9 m), so anything farther is a real earlier crossing; 1 cm
#: is far above round-off and far below any terrain feature a DTM can hold.
OCCLUSION_TOLERANCE_M = 0.01

#: IMU samples run this long past the last frame (s), so the last frame interval is
#: covered with neighbours on both sides (the hold of a sample reaches its neighbours).
IMU_TAIL_S = 0.05

#: The simulated terrain (and the log's DTM) extends this far beyond the footprint of
#: the camera (m): a smoother re-casting rays from poses tens of metres off (prior sigma
#: 50 m, 1 degree at 1 km) must still hit the grid.
REGION_MARGIN_M = 400.0

#: The aircraft must clear the highest terrain under its footprint by this much (m).
MIN_CLEARANCE_M = 100.0

#: Most IMU samples of a simulation: 2e7 (28 h at 200 Hz) hold about 1 GB.
MAX_IMU_SAMPLES = 2e7

#: Largest true terrain grid (samples): 2000 x 2000 float64 is 32 MB.
MAX_TERRAIN_SAMPLES = 4_000_000

#: Finest spacing of the fractal truth (m): the spacing at which the terrain module's
#: Fig. 6 calibration (sigma_h of a 30 m DTM ~ 2.4 m) was made.
FINE_TERRAIN_SPACING_M = 5.0

#: Every image corner ray must point at least this far below the horizon (deg), or the
#: footprint runs off to the horizon (bank + FOV too large).
MIN_DEPRESSION_DEG = 10.0

#: Roll-in and roll-out time of every turn (s): a smooth bank, as FlightPlan's default.
_BANK_RAMP_S = 2.0

# Spawning new tracks: each round draws (tracks still needed) x this factor / (the share
# of candidates accepted so far) pixels, at least a floor and at most a cap. Candidates
# must hit the terrain and be seen in the next frame: with a small frame overlap few
# pass, and the first round's share sizes the next.
_SPAWN_OVERSAMPLING = 1.5
_SPAWN_MIN_CANDIDATES = 64
_SPAWN_MAX_CANDIDATES = 200_000
_SPAWN_ROUNDS = 8



class TrackEnd(enum.IntEnum):
    """Why a track ended (per track in :class:`SimulationResult`)."""

    LAST_FRAME = 0     # still seen in the last frame
    LEFT_IMAGE = 1     # its ground point projects outside the image (or behind the camera)
    OCCLUDED = 2       # the terrain hides it from the next camera
    NOISE_OUTSIDE = 3  # the noisy pixel fell outside the image
    NO_GROUND = 4      # the next camera's ray toward it leaves the terrain grid (no data)


@dataclass(frozen=True)
class SimulationSettings:
    """What to simulate. Defaults: the paper's section VI.A flight at 1000 m.

    Attributes:
        terrain: a DTM file (.npz, .asc, .tif; world = the file's coordinates) to fly
            over instead of the fractal terrain; it is then both the truth and the log's
            DTM (sigma_h ``EXACT_DTM_SIGMA_H_M``). The flight is centred on it.
        relief_m: max - min height of the fractal basic cell (m).
        terrain_cell_m: side of the fractal basic cell tiled over the flight region (m);
            the paper's nominal terrain is 3x3 km with 300 m of relief.
        correlation_length_m: roll-off length of the fractal cell (m).
        terrain_spacing_m: spacing of the true fractal terrain (m); None: 5 m, coarser
            only when the region would exceed ``MAX_TERRAIN_SAMPLES``.
        dtm_spacing_m: spacing of the log's DTM, the truth resampled (m); its sigma_h
            follows the Fig. 6 model.
        exact_dtm: the log's DTM is the truth itself (sigma_h ``EXACT_DTM_SIGMA_H_M``).
        altitude_m: flight altitude above the terrain's mean height (m).
        speed_mps: ground speed (m/s).
        frames: number of camera frames (>= 2).
        fps: frame rate (Hz).
        n_features: target number of features per consecutive frame pair.
        resolution_px: image (width, height) in pixels.
        fov_deg: horizontal field of view (deg) of the undistorted camera: it sets the
            focal length (:meth:`PinholeCamera.from_fov`), which a lens model then keeps.
        distortion_model: the lens (:class:`~cdtm_graph.camera.DistortionModel` or its
            name): features are projected through it, and flight.yaml states it.
        distortion_coeffs: its coefficients (radtan k1 k2 p1 p2 [k3], equidistant
            k1 k2 k3 k4; none: empty).
        pixel_sigma_px: 1-sigma pixel noise of every observation.
        camera_tilt_deg: the camera looks this far forward of the body's -z axis (deg),
            so the mounting ``body_T_cam`` is not a bare axis permutation.
        camera_offset_m: (3,) camera position in the body frame (m).
        leg_s: duration of the straight legs (s); the first one is half as long.
        turn_deg: heading change of each turn (deg); turns alternate left and right,
            starting left from a course of ``-turn_deg / 2``; 0 flies straight.
        turn_rate_dps: heading rate in the turns (deg/s); 1.5 deg/s at 200 m/s banks
            about 28 degrees.
        attitude_wobble_deg: amplitude of a slow roll/pitch wobble (deg).
        attitude_wobble_period_s: its period (s).
        imu_rate_hz: IMU sample rate (Hz).
        imu_noise: IMU noise densities (written to flight.yaml; simulated unless
            ``noiseless``).
        gravity_mps2: gravity magnitude.
        sigma_position_m, sigma_attitude_deg, sigma_velocity_mps, sigma_gyro_bias,
            sigma_accel_bias: the initial-state prior. The prior mean is the true first
            state moved by one draw of these sigmas; the bias prior means are zero and
            the true initial biases are drawn from them.
        noiseless: no IMU noise, zero biases, no pixel noise, exact DTM, prior mean =
            the true first state (flight.yaml still states the nominal noise).
        nav: :class:`NavMode` (or its string value): whether and how to write nav.csv.
        nav_sigma_position_m, nav_sigma_attitude_deg, nav_sigma_velocity_mps: white
            noise of ``NavMode.NOISY_TRUTH``.
        groundtruth_rate_hz: rate of groundtruth.csv (Hz); None: the IMU rate. Frame
            times are always included.
        region_margin_m: the terrain and the DTM extend this far beyond the camera
            footprint (m); a prior of hundreds of metres needs more than the default.
        initial_error_m: the prior mean's position error, exactly (world, m), instead of
            a draw of ``sigma_position_m``.
        initial_error_deg: the prior mean's attitude error, exactly (rotation vector in
            the body frame, deg), instead of a draw of ``sigma_attitude_deg``.
        terrain_mismatch: terrain the true ground has and the DTM lacks
            (:class:`~cdtm_graph.sim.faults.TerrainMismatch`).
        flat_ground: flat ground (a lake) under part of the track, in the truth and the
            DTM alike (:class:`~cdtm_graph.sim.faults.FlatGround`).
        map_detail: ground detail the DTM lacks, correlated over tens to hundreds of
            metres, everywhere (:class:`~cdtm_graph.sim.map_detail.MapDetail`): a map
            error other than the resampling remainder ``sigma_h`` is fitted to.
        origin: where the world is on the Earth (WGS84): the world is the ENU tangent
            plane there, fixed to the rotating Earth, and the IMU senses the Earth's
            rotation and WGS84 normal gravity along the local vertical
            (:func:`~cdtm_graph.sim.imu.earth_imu`); flight.yaml's ``gravity_mps2`` is
            then normal gravity at the origin. None: the flat world. Such a result is
            written as a geodetic log (:mod:`cdtm_graph.sim.geodetic`).
        seed: the one seed of every random draw (>= 0).
    """

    terrain: Path | None = None
    relief_m: float = NOMINAL_RELIEF_M
    terrain_cell_m: float = 3000.0
    correlation_length_m: float = NOMINAL_CORRELATION_LENGTH_M
    terrain_spacing_m: float | None = None
    dtm_spacing_m: float = NOMINAL_DTM_SPACING_M
    exact_dtm: bool = False
    altitude_m: float = NOMINAL_ALTITUDE_M
    speed_mps: float = NOMINAL_SPEED_MPS
    frames: int = NOMINAL_FRAMES
    fps: float = NOMINAL_FPS
    n_features: int = NOMINAL_FEATURES
    resolution_px: tuple[int, int] = NOMINAL_RESOLUTION_PX
    fov_deg: float = 60.0
    distortion_model: DistortionModel | str = DistortionModel.NONE
    distortion_coeffs: tuple[float, ...] = ()
    pixel_sigma_px: float = 0.5
    camera_tilt_deg: float = 2.0
    camera_offset_m: tuple[float, float, float] = (0.3, 0.0, -0.2)
    leg_s: float = 20.0
    turn_deg: float = 30.0
    turn_rate_dps: float = 1.5
    attitude_wobble_deg: float = 1.0
    attitude_wobble_period_s: float = 10.0
    imu_rate_hz: float = 200.0
    imu_noise: ImuNoise = ImuNoise()
    gravity_mps2: float = STANDARD_GRAVITY_MPS2
    sigma_position_m: float = 50.0
    sigma_attitude_deg: float = 1.0
    sigma_velocity_mps: float = 1.0
    sigma_gyro_bias: float = 1.0e-4
    sigma_accel_bias: float = 1.0e-2
    noiseless: bool = False
    nav: NavMode | str = NavMode.NONE
    nav_sigma_position_m: float = 10.0
    nav_sigma_attitude_deg: float = 0.5
    nav_sigma_velocity_mps: float = 0.5
    groundtruth_rate_hz: float | None = None
    region_margin_m: float = REGION_MARGIN_M
    initial_error_m: tuple[float, float, float] | None = None
    initial_error_deg: tuple[float, float, float] | None = None
    terrain_mismatch: TerrainMismatch | None = None
    flat_ground: FlatGround | None = None
    map_detail: MapDetail | None = None
    origin: GeodeticOrigin | None = None
    seed: int = DEFAULT_SEED

    def __post_init__(self) -> None:
        if self.terrain is not None:
            object.__setattr__(self, "terrain", Path(self.terrain))
        try:
            object.__setattr__(self, "nav", NavMode(self.nav))
        except ValueError:
            choices = ", ".join(m.value for m in NavMode)
            raise SimulationError(f"nav = {self.nav!r}, expected one of {choices}") from None
        positive = ("relief_m", "terrain_cell_m", "correlation_length_m", "dtm_spacing_m",
                    "altitude_m", "speed_mps", "fps", "fov_deg", "pixel_sigma_px", "leg_s",
                    "turn_rate_dps", "attitude_wobble_period_s", "imu_rate_hz",
                    "gravity_mps2", "sigma_position_m", "sigma_attitude_deg",
                    "sigma_velocity_mps", "sigma_gyro_bias", "sigma_accel_bias",
                    "nav_sigma_position_m", "nav_sigma_attitude_deg", "nav_sigma_velocity_mps")
        for name in positive:
            value = getattr(self, name)
            ok = _is_number(value) and math.isfinite(value) and (
                value >= 0 if name == "relief_m" else value > 0)
            if not ok:
                bound = ">= 0" if name == "relief_m" else "> 0"
                raise SimulationError(f"{name} = {value!r}, expected a finite number {bound}")
        if not (_is_number(self.region_margin_m) and self.region_margin_m >= 0):
            raise SimulationError(f"region_margin_m = {self.region_margin_m!r}, expected >= 0")
        for name in ("initial_error_m", "initial_error_deg"):
            value = getattr(self, name)
            if value is not None:
                if len(value) != 3 or not all(_is_number(v) and math.isfinite(v) for v in value):
                    raise SimulationError(f"{name} = {value!r}, expected 3 finite numbers")
                object.__setattr__(self, name, tuple(float(v) for v in value))
        for name in ("terrain_spacing_m", "groundtruth_rate_hz"):
            value = getattr(self, name)
            if value is not None and not (_is_number(value) and math.isfinite(value)
                                          and value > 0):
                raise SimulationError(f"{name} = {value!r}, expected None or a number > 0")
        for name in ("camera_tilt_deg", "turn_deg", "attitude_wobble_deg"):
            value = getattr(self, name)
            if not (_is_number(value) and math.isfinite(value)):
                raise SimulationError(f"{name} = {value!r}, expected a finite number")
        if not _is_int(self.frames) or self.frames < 2:
            raise SimulationError(f"frames = {self.frames!r}, expected an integer >= 2")
        if not _is_int(self.n_features) or self.n_features < 1:
            raise SimulationError(f"n_features = {self.n_features!r}, expected an integer >= 1")
        if not _is_int(self.seed) or self.seed < 0:
            raise SimulationError(f"seed = {self.seed!r}, expected an integer >= 0")
        lo_px, hi_px = RESOLUTION_RANGE_PX  # what the log's reader takes
        if (len(self.resolution_px) != 2
                or not all(_is_int(n) and lo_px <= n <= hi_px for n in self.resolution_px)):
            raise SimulationError(
                f"resolution_px = {self.resolution_px!r}, expected (width, height), each "
                f"from {lo_px} to {hi_px} px")
        if not self.fov_deg < 180.0:
            raise SimulationError(f"fov_deg = {self.fov_deg!r}, expected 0 < fov_deg < 180")
        if not self.fps <= self.imu_rate_hz:
            raise SimulationError(f"fps = {self.fps!r}, expected at most the IMU rate "
                                  f"{self.imu_rate_hz!r} Hz (at least one IMU sample a frame)")
        if not self.duration_s * self.imu_rate_hz <= MAX_IMU_SAMPLES:
            raise SimulationError(
                f"frames = {self.frames}, fps = {self.fps!r}, imu_rate_hz = "
                f"{self.imu_rate_hz!r}: {self.duration_s:.3g} s of IMU is more than "
                f"{MAX_IMU_SAMPLES:g} samples; expected a shorter flight")
        if len(self.camera_offset_m) != 3 or not all(
                _is_number(v) and math.isfinite(v) for v in self.camera_offset_m):
            raise SimulationError(
                f"camera_offset_m = {self.camera_offset_m!r}, expected 3 finite numbers")
        object.__setattr__(self, "resolution_px", tuple(int(n) for n in self.resolution_px))
        object.__setattr__(self, "camera_offset_m",
                           tuple(float(v) for v in self.camera_offset_m))
        try:
            lens = PinholeCamera(2, 2, 1.0, 1.0, 0.5, 0.5, tuple(self.distortion_coeffs),
                                 self.distortion_model)
        except (TypeError, ValueError) as exc:
            raise SimulationError(f"distortion_model = {self.distortion_model!r}, "
                                  f"distortion_coeffs = {self.distortion_coeffs!r}: {exc}"
                                  ) from None
        object.__setattr__(self, "distortion_model", lens.model)
        object.__setattr__(self, "distortion_coeffs", lens.distortion)

    @property
    def nav_mode(self) -> NavMode:
        """``nav`` as a :class:`NavMode` (``__post_init__`` converted it)."""
        return NavMode(self.nav)

    @property
    def camera(self) -> PinholeCamera:
        """The camera of ``resolution_px`` and ``fov_deg``, with the lens model."""
        plain = PinholeCamera.from_fov(*self.resolution_px, self.fov_deg)
        return dataclasses.replace(plain, distortion=self.distortion_coeffs,
                                   distortion_model=self.distortion_model)

    @property
    def body_T_cam(self) -> np.ndarray:
        """(4, 4) camera mounting: downward, tilted forward by ``camera_tilt_deg``."""
        # A rotation about body y by -tilt turns the optical axis (body -z) toward +x.
        tilt = so3_exp(np.array([0.0, -math.radians(self.camera_tilt_deg), 0.0]))
        return make_pose(tilt @ DOWNWARD_BODY_T_CAM[:3, :3], np.asarray(self.camera_offset_m))

    @property
    def duration_s(self) -> float:
        """Time of the last frame (s); the first frame is at t = 0."""
        return (self.frames - 1) / self.fps

    def to_dict(self) -> dict:
        """The settings as plain YAML-able values (recorded under ``extra`` in flight.yaml)."""
        out = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, Path):
                value = str(value)
            elif isinstance(value, enum.Enum):
                value = value.value
            elif isinstance(value, ImuNoise):
                value = dataclasses.asdict(value)
            elif isinstance(value, (TerrainMismatch, FlatGround, MapDetail)):
                value = value.to_dict()
            elif isinstance(value, GeodeticOrigin):
                value = dataclasses.asdict(value)
            elif isinstance(value, tuple):
                value = list(value)
            out[f.name] = value
        return out


@dataclass(frozen=True)
class TrackStats:
    """What happened to the features.

    Attributes:
        n_tracks: tracks made.
        n_observations: rows of tracks.csv.
        pairs_per_frame: (K-1,) features seen in both frame k and k+1.
        lost: number of tracks that ended for each :class:`TrackEnd` reason (name -> count).
        spawn_candidates: pixels tried for new tracks (``n_tracks`` of them became tracks).
    """

    n_tracks: int
    n_observations: int
    pairs_per_frame: np.ndarray
    lost: dict
    spawn_candidates: int

    def to_dict(self) -> dict:
        """Plain YAML-able summary."""
        pairs = self.pairs_per_frame
        return {
            "tracks": self.n_tracks,
            "observations": self.n_observations,
            "pairs_per_frame_min": int(pairs.min()),
            "pairs_per_frame_mean": float(pairs.mean()),
            "pairs_per_frame_max": int(pairs.max()),
            "track_ends": dict(self.lost),
            "spawn_candidates": self.spawn_candidates,
        }


@dataclass(frozen=True)
class SimulationResult:
    """A simulated flight: the log, its DTM and the truth behind them.

    Attributes:
        log: the flight log; ``root`` is a placeholder (``Path(".")``) and the DTM path
            is ``DTM_FILENAME``, relative to wherever the log is written.
        dtm: the log's DTM (with its ``sigma_h_m``).
        terrain: the true terrain the features were cast on.
        plan: the true flight plan.
        imu: the IMU samples with their true biases, (N,) samples.
        world_T_cam: (K, 4, 4) true camera poses at the frames.
        uv_true_px: (M, 2) noise-free pixel of each row of ``log.tracks``.
        ground_points_m: (T, 3) true ground point of each track, row = track_id.
        track_end: (T,) :class:`TrackEnd` value of each track.
        stats: counts.
    """

    log: FlightLog
    dtm: Dtm
    terrain: Dtm
    plan: FlightPlan
    imu: ImuData
    world_T_cam: np.ndarray
    uv_true_px: np.ndarray
    ground_points_m: np.ndarray
    track_end: np.ndarray
    stats: TrackStats


# --------------------------------------------------------------------------- public API


def simulate_flight(settings: SimulationSettings) -> tuple[FlightLog, Dtm]:
    """Simulate a flight log and its DTM (see :func:`simulate` for everything else).

    Args:
        settings: what to simulate.

    Returns:
        The log (``root`` a placeholder, DTM path ``DTM_FILENAME``) and the DTM to write
        beside it.
    """
    result = simulate(settings)
    return result.log, result.dtm


def write_simulated_log(settings: SimulationSettings, out_dir: str | Path, *,
                        force: bool = False) -> Path:
    """Simulate a flight and write it as a log directory holding its DTM (``dtm.npz``).

    The directory is checked before simulating and its files appear all or none, under
    the rules of :func:`cdtm_graph.atomic.atomic_output_dir`: a new or empty directory,
    or an earlier cdtm output (an earlier simulation: its log files are replaced and those
    this one does not write, say ``nav.csv``, removed; images or notes added since are
    kept). A non-empty directory cdtm did not write only with ``force``, and even then no
    file there is overwritten. The terrain file (``settings.terrain``) is never inside it.

    Args:
        settings: what to simulate.
        out_dir: the log directory to create or rewrite.
        force: also write into a non-empty directory cdtm did not write (beside its files).

    Returns:
        The log directory.

    Raises:
        SimulationError: bad settings.
        OutputError: ``out_dir`` may not be written (a file, someone else's folder, the
            terrain file's folder, not writable).
    """
    protected = [settings.terrain] if settings.terrain is not None else []
    with atomic_output_dir(out_dir, writer=WRITER, force=force, protected=protected) as staging:
        write_simulation_files(simulate(settings), staging, out_dir)
    logger.info("wrote simulated flight log %s", out_dir)
    return Path(out_dir)


def write_simulation(result: SimulationResult, out_dir: str | Path,
                     images: Sequence[np.ndarray] | None = None, *, force: bool = False,
                     protected: Sequence[str | Path] = ()) -> Path:
    """Write an already simulated flight (:func:`simulate`) as a log directory.

    Same contract as :func:`write_simulated_log`.

    Args:
        result: the simulation.
        out_dir: the log directory.
        images: one image per frame (e.g. :func:`cdtm_graph.sim.render.render_flight`),
            written as PNG under ``images/`` and listed in frames.csv.
        force, protected: as :func:`cdtm_graph.atomic.atomic_output_dir` (``protected``:
            inputs, such as the terrain file, that ``out_dir`` must not be, be inside or
            contain).
    """
    if images is not None and len(images) != len(result.log.frames):
        raise SimulationError(f"{len(images)} images for {len(result.log.frames)} frames, "
                              "expected one per frame")
    with atomic_output_dir(out_dir, writer=WRITER, force=force, protected=protected) as staging:
        write_simulation_files(result, staging, out_dir, images)
    logger.info("wrote simulated flight log %s", out_dir)
    return Path(out_dir)


#: The writer named in a simulated log's manifest (``.cdtm-run.json``).
WRITER = "simulate"


def write_simulation_files(result: SimulationResult, directory: Path,
                           final_dir: str | Path,
                           images: Sequence[np.ndarray] | None = None) -> None:
    """The log's files, its DTM and its images (``images/``), into ``directory`` (a
    staging directory that becomes ``final_dir``), plainly: for callers holding an
    ``atomic_output_dir`` open. A geodetic result (``SimulationSettings.origin``) is
    written as a geodetic log (:func:`~cdtm_graph.sim.geodetic.
    write_geodetic_simulation_files`: an EPSG:4326 EGM96 DEM tile, latitude and
    longitude; no images)."""
    log = result.log
    if log.config.origin is not None:
        if images is not None:
            raise SimulationError("images of a geodetic simulation: rendering a geodetic "
                                  "log is not supported yet; expected one of the two")
        write_geodetic_simulation_files(result, directory)
        return
    if images is not None:
        if len(images) != len(log.frames):
            raise SimulationError(f"{len(images)} images for {len(log.frames)} frames, "
                                  "expected one per frame")
        log = dataclasses.replace(log, frames=Frames(log.frames.t_ns,
                                                     write_images(images, directory)))
    save_dtm_npz(result.dtm, directory / DTM_FILENAME)
    write_flightlog_files(log, directory, final_dir)


def write_geodetic_simulation(result: SimulationResult, out_dir: str | Path,
                              origin: GeodeticOrigin | None = None,
                              dem_crs: str = "EPSG:4326", pixel_size: float | None = None,
                              vertical_datum: VerticalDatum = VerticalDatum.EGM96) -> Path:
    """Write a geodetic simulation as a GNSS user would have it: lat/lon and a DEM tile
    (into a new directory that appears complete; :func:`write_geodetic_simulation_files`
    for a caller that holds the staging directory).

    The simulator's world is the ENU tangent plane at the result's origin
    (``SimulationSettings.origin``); the log's DTM is written as a GeoTIFF in ``dem_crs``
    (``dem.tif``, heights in ``vertical_datum``), and the initial state, nav.csv and
    groundtruth.csv in latitude, longitude and ellipsoidal height. The IMU is the
    simulator's, which senses the Earth's rotation and normal gravity.

    Args:
        result: a :func:`~cdtm_graph.sim.simulate.simulate` result with an origin.
        out_dir: the log directory (appears complete or not at all).
        origin: the result's origin (checked), or None.
        dem_crs: CRS of the DEM tile.
        pixel_size: in CRS units; None: 1 arc-second for a geographic CRS, else the DTM's
            spacing.
        vertical_datum: heights of the tile above the ellipsoid or the EGM96 geoid.

    Returns:
        The log directory.

    Raises:
        SimulationError: the result was simulated without that origin (its IMU would not
            be the Earth's).
    """
    origin_of(result, origin)  # before the directory is made
    with atomic_output_dir(out_dir, writer=WRITER) as tmp:
        write_geodetic_simulation_files(result, tmp, origin, dem_crs, pixel_size,
                                        vertical_datum)
    return Path(out_dir)


def simulate(settings: SimulationSettings) -> SimulationResult:
    """Simulate a flight over terrain with an IMU and a downward camera (module docstring).

    Args:
        settings: what to simulate.

    Returns:
        The log, its DTM and the truth.

    Raises:
        SimulationError: the settings cannot give a valid log (camera sees the horizon,
            terrain file too small, aircraft below the terrain, ...).
        DtmError: the terrain file cannot be read.
    """
    streams = np.random.SeedSequence(settings.seed).spawn(5)
    terrain_seed = int(streams[0].generate_state(1)[0])
    rng_initial, rng_imu, rng_tracks, rng_nav = (np.random.default_rng(s) for s in streams[1:])
    camera = settings.camera
    body_T_cam = settings.body_T_cam
    frame_t_ns = np.round(np.arange(settings.frames) * (NS_PER_S / settings.fps)).astype(np.int64)
    frame_t_s = frame_t_ns.astype(float) / NS_PER_S

    world = _make_world(settings, frame_t_s, terrain_seed)
    plan, terrain, dtm = world.plan, world.terrain, world.dtm

    # True states at the frames and the camera poses.
    truth_frames = evaluate(plan, frame_t_s)
    world_T_body = np.tile(np.eye(4), (settings.frames, 1, 1))
    world_T_body[:, :3, :3] = truth_frames.rotation_world_body
    world_T_body[:, :3, 3] = truth_frames.position_m
    world_T_cam = world_T_body @ body_T_cam

    # Initial state: prior mean and true biases.
    initial, true_gyro_bias, true_accel_bias = _initial_state(settings, truth_frames,
                                                              rng_initial)

    # IMU.
    imu_dt_ns = int(round(NS_PER_S / settings.imu_rate_hz))
    imu_end_ns = int(frame_t_ns[-1]) + int(round(IMU_TAIL_S * NS_PER_S))
    imu_t_ns = np.arange(0, imu_end_ns + imu_dt_ns, imu_dt_ns, dtype=np.int64)  # >= the end
    earth = local_frame(settings.origin) if settings.origin is not None else None
    imu = simulate_imu(plan, imu_t_ns, settings.gravity_mps2,
                       None if settings.noiseless else settings.imu_noise, rng_imu,
                       tuple(true_gyro_bias), tuple(true_accel_bias), earth)

    # Feature tracks.
    pixel_sigma_px = 0.0 if settings.noiseless else settings.pixel_sigma_px
    tracks_sim = _simulate_tracks(terrain, camera, world_T_cam, settings.n_features, pixel_sigma_px,
                                  rng_tracks)
    if tracks_sim.stats.pairs_per_frame.min() == 0:
        k = int(np.argmin(tracks_sim.stats.pairs_per_frame))
        raise SimulationError(
            f"frames {k} and {k + 1} share no visible ground feature; expected frames closer "
            "together (higher fps, lower speed) or a wider footprint (higher altitude_m, fov_deg)")
    short = tracks_sim.stats.pairs_per_frame < settings.n_features
    if short.any():
        logger.warning("%d of %d frame pairs have fewer than %d features (min %d): the terrain "
                       "hides or lacks the rest", int(short.sum()), short.size, settings.n_features,
                       int(tracks_sim.stats.pairs_per_frame.min()))

    groundtruth = _groundtruth(plan, frame_t_ns, int(imu_t_ns[-1]),
                               settings.groundtruth_rate_hz or settings.imu_rate_hz)
    extra = {"simulation": {
        "generator": __name__,
        "settings": settings.to_dict(),
        "terrain": world.info,
        "true_initial_gyro_bias": [float(v) for v in true_gyro_bias],
        "true_initial_accel_bias": [float(v) for v in true_accel_bias],
        "tracks": tracks_sim.stats.to_dict(),
    }}
    imu_noise = settings.imu_noise
    origin = settings.origin
    config = FlightConfig(
        gravity_mps2=(settings.gravity_mps2 if origin is None else
                      float(normal_gravity_mps2(origin.latitude_deg, origin.height_m))),
        # the simulated map is registered exactly: no offset of the whole map
        dtm=DtmConfig(Path(DTM_FILENAME), dtm.sigma_h_m, (0.0, 0.0, 0.0),
                      horizontal_offset_sigma_m=0.0, vertical_offset_sigma_m=0.0),
        camera=CameraConfig(camera, settings.pixel_sigma_px, body_T_cam),
        imu=ImuConfig(settings.imu_rate_hz, imu_noise.gyroscope_noise_density,
                      imu_noise.accelerometer_noise_density, imu_noise.gyroscope_random_walk,
                      imu_noise.accelerometer_random_walk),
        initial_state=initial,
        extra=extra,
        origin=origin,
    )
    imu_samples = ImuSamples(imu.t_ns, imu.gyro_radps, imu.acc_mps2)
    frames = Frames(frame_t_ns, ("",) * settings.frames)
    tracks = Tracks(tracks_sim.frame, tracks_sim.track_id, tracks_sim.uv_px)
    if settings.nav_mode is NavMode.DEAD_RECKONING:
        nav = _dead_reckoning(config, imu_samples, frame_t_ns)
    elif settings.nav_mode is NavMode.NOISY_TRUTH:
        nav = _noisy_truth(settings, truth_frames, frame_t_ns, rng_nav)
    else:
        nav = None
    log = FlightLog(Path("."), config, imu_samples, frames, tracks, nav, groundtruth)
    logger.info("simulated %d frames, %d tracks, %d observations over a %dx%d DTM",
                settings.frames, tracks_sim.stats.n_tracks, tracks_sim.stats.n_observations,
                *dtm.shape)
    return SimulationResult(log=log, dtm=dtm, terrain=terrain, plan=plan, imu=imu,
                            world_T_cam=world_T_cam, uv_true_px=tracks_sim.uv_true_px,
                            ground_points_m=tracks_sim.ground_points_m,
                            track_end=tracks_sim.track_end, stats=tracks_sim.stats)


# --------------------------------------------------------------------------- flight


@dataclass(frozen=True)
class _World:
    """The true terrain, the log's DTM, the flight plan over them, and how they were made."""

    terrain: Dtm
    dtm: Dtm
    plan: FlightPlan
    info: dict


def _make_world(settings: SimulationSettings, frame_t_s: np.ndarray,
                terrain_seed: int) -> _World:
    """Terrain, DTM and plan: the flight and its camera footprint inside the terrain.

    The region the camera sees depends on the altitude, which depends on the terrain's
    mean height: known up front for the fractal (0) and read from a terrain file.
    """
    camera, body_T_cam = settings.camera, settings.body_T_cam
    file_terrain = None
    if settings.terrain is not None:
        file_terrain = load_dtm(settings.terrain)
        mean_height = float(np.nanmean(file_terrain.elevation))
        lowest = float(np.nanmin(file_terrain.elevation))
    else:
        mean_height = 0.0  # fractal_terrain has zero mean; tiling keeps it
        lowest = -settings.relief_m  # max - min = relief around a zero mean
    altitude = mean_height + settings.altitude_m
    plan = _flight_plan(settings, (0.0, 0.0), altitude)
    region = _footprint_region(plan, frame_t_s, body_T_cam, camera, lowest,
                               settings.region_margin_m)

    if file_terrain is None:
        terrain, info = _fractal_truth(settings, region, terrain_seed)
    else:
        terrain = file_terrain
        xmin, xmax, ymin, ymax = terrain.bounds
        need_x, need_y = region[1] - region[0], region[3] - region[2]
        if need_x > xmax - xmin or need_y > ymax - ymin:
            raise SimulationError(
                f"{settings.terrain}: covers {xmax - xmin:.0f} x {ymax - ymin:.0f} m, but the "
                f"flight and its camera footprint need {need_x:.0f} x {need_y:.0f} m; "
                "expected fewer frames, a lower speed or altitude, or a larger terrain")
        # Centre the flight region on the terrain.
        shift = (0.5 * (xmin + xmax - region[0] - region[1]),
                 0.5 * (ymin + ymax - region[2] - region[3]))
        region = (region[0] + shift[0], region[1] + shift[0],
                  region[2] + shift[1], region[3] + shift[1])
        plan = _flight_plan(settings, shift, altitude)
        info = {"kind": "file", "path": str(settings.terrain)}
    _check_clearance(terrain, region, altitude)
    if settings.flat_ground is not None:  # truth and DTM alike: made before the DTM
        flat = settings.flat_ground
        t_s = np.arange(flat.at_s, flat.at_s + flat.duration_s + 0.05, 0.1)
        track = evaluate(plan, t_s).position_m[:, :2]
        terrain = apply_flat_ground(terrain, flat, track)
        info["flat_ground"] = flat.to_dict()

    if settings.terrain is not None or settings.exact_dtm or settings.noiseless:
        dtm = Dtm(terrain.elevation, terrain.x0, terrain.y0, terrain.dx, terrain.dy,
                  sigma_h_m=EXACT_DTM_SIGMA_H_M)
    else:
        coarse = terrain.resample(settings.dtm_spacing_m)
        dtm = Dtm(coarse.elevation, coarse.x0, coarse.y0, coarse.dx, coarse.dy,
                  sigma_h_m=sigma_h_from_grid_spacing(settings.dtm_spacing_m))
    info["dtm_height_error_rms_m"] = _height_error_rms(dtm, terrain)
    if settings.terrain_mismatch is not None:  # the truth changes, the DTM does not
        at = evaluate(plan, np.array([settings.terrain_mismatch.at_s])).position_m[0]
        terrain = apply_terrain_mismatch(terrain, settings.terrain_mismatch, (at[0], at[1]))
        info["dtm_height_error_rms_with_mismatch_m"] = _height_error_rms(dtm, terrain)
    if settings.map_detail is not None:  # the truth changes, the DTM does not
        terrain = apply_map_detail(terrain, settings.map_detail)
        info["map_detail"] = settings.map_detail.to_dict()
        info["dtm_height_error_rms_with_detail_m"] = _height_error_rms(dtm, terrain)
    return _World(terrain, dtm, plan, info)


def _flight_plan(settings: SimulationSettings, start_xy: tuple[float, float],
                 altitude_m: float) -> FlightPlan:
    """Straight legs joined by alternating turns, long enough for every frame and the IMU."""
    needed_s = settings.duration_s + IMU_TAIL_S
    # The heading rate ramps up and down over _BANK_RAMP_S each, turning at half rate
    # meanwhile: a turn lasts angle / rate + one ramp.
    turn_s = abs(settings.turn_deg) / settings.turn_rate_dps + _BANK_RAMP_S
    legs: list[tuple[float, float]] = []
    if settings.turn_deg == 0.0:
        legs.append((settings.speed_mps * needed_s, 0.0))
    else:
        elapsed, sign = 0.0, 1.0
        while elapsed < needed_s:
            leg_s = settings.leg_s / 2 if not legs else settings.leg_s
            legs.append((settings.speed_mps * leg_s, sign * settings.turn_deg))
            elapsed += leg_s + turn_s
            sign = -sign
    return FlightPlan(
        start_xy_m=(float(start_xy[0]), float(start_xy[1])),
        altitude_m=altitude_m,
        speed_mps=settings.speed_mps,
        heading_deg=-settings.turn_deg / 2,
        legs=tuple(legs),
        turn_rate_dps=settings.turn_rate_dps,
        bank_ramp_s=_BANK_RAMP_S,
        gravity_mps2=settings.gravity_mps2,
        camera_wobble_deg=settings.attitude_wobble_deg,
        camera_wobble_period_s=settings.attitude_wobble_period_s,
    )


def _footprint_region(plan: FlightPlan, frame_t_s: np.ndarray, body_T_cam: np.ndarray,
                      camera: PinholeCamera, lowest_m: float, margin_m: float
                      ) -> tuple[float, float, float, float]:
    """(xmin, xmax, ymin, ymax) the frames can see, with ``margin_m`` around it.

    Image corner rays are cut with the plane of the lowest terrain: a ray from above
    meets any higher ground nearer to the camera's nadir, so this bounds the footprint.
    """
    traj = evaluate(plan, frame_t_s)
    world_T_body = np.tile(np.eye(4), (len(traj), 1, 1))
    world_T_body[:, :3, :3] = traj.rotation_world_body
    world_T_body[:, :3, 3] = traj.position_m
    world_T_cam = world_T_body @ body_T_cam
    w, h = camera.width, camera.height
    corners = camera.pixels_to_rays(np.array([[-0.5, -0.5], [w - 0.5, -0.5],
                                              [-0.5, h - 0.5], [w - 0.5, h - 0.5]]))
    rays = np.einsum("kij,cj->kci", world_T_cam[:, :3, :3], corners)  # (K, 4, 3)
    rays /= np.linalg.norm(rays, axis=2, keepdims=True)
    min_down = math.sin(math.radians(MIN_DEPRESSION_DEG))
    if np.any(rays[:, :, 2] > -min_down):
        k = int(np.flatnonzero(np.any(rays[:, :, 2] > -min_down, axis=1))[0])
        raise SimulationError(
            f"the camera sees (near) the horizon at frame {k}: an image corner is less than "
            f"{MIN_DEPRESSION_DEG:g} deg below it; expected a smaller fov_deg, turn rate or "
            "attitude wobble")
    origins = world_T_cam[:, :3, 3]
    t = (lowest_m - origins[:, None, 2]) / rays[:, :, 2]
    ground = origins[:, None, :2] + t[:, :, None] * rays[:, :, :2]
    xy = np.concatenate([ground.reshape(-1, 2), origins[:, :2]])
    lo, hi = xy.min(axis=0) - margin_m, xy.max(axis=0) + margin_m
    return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])


def _fractal_truth(settings: SimulationSettings, region: tuple[float, float, float, float],
                   seed: int) -> tuple[Dtm, dict]:
    """A fractal basic cell tiled over the region and cropped to it (paper Figs. 11-12)."""
    xmin, xmax, ymin, ymax = region
    width, height = xmax - xmin, ymax - ymin
    spacing = settings.terrain_spacing_m
    if spacing is None:
        spacing = FINE_TERRAIN_SPACING_M
        if (width / spacing + 1) * (height / spacing + 1) > MAX_TERRAIN_SAMPLES:
            spacing = math.sqrt(width * height / MAX_TERRAIN_SAMPLES) * 1.01
        # A whole number of grid steps per cell: the cell spans terrain_cell_m exactly.
        spacing = settings.terrain_cell_m / max(1, math.floor(settings.terrain_cell_m / spacing))
        if not settings.exact_dtm and not settings.noiseless and spacing > settings.dtm_spacing_m:
            raise SimulationError(
                f"the flight region {width:.0f} x {height:.0f} m needs a true-terrain spacing of "
                f"{spacing:.1f} m, coarser than the DTM's {settings.dtm_spacing_m:g} m; "
                "expected fewer frames or a lower speed")
    cols = int(math.ceil(width / spacing)) + 1
    rows = int(math.ceil(height / spacing)) + 1
    if rows * cols > MAX_TERRAIN_SAMPLES:
        raise SimulationError(
            f"terrain_spacing_m = {spacing:g} gives a {rows} x {cols} terrain over the "
            f"{width:.0f} x {height:.0f} m flight region, expected at most "
            f"{MAX_TERRAIN_SAMPLES} samples")
    if spacing * 2 > settings.terrain_cell_m:
        raise SimulationError(f"terrain spacing {spacing:g} m, expected at most half of "
                              f"terrain_cell_m = {settings.terrain_cell_m:g}")
    truth = _tiled_fractal(settings.terrain_cell_m, spacing, settings.relief_m,
                           settings.correlation_length_m, seed, xmin, ymin, rows, cols)
    info = {"kind": "fractal_cloned_cell", "cell_m": settings.terrain_cell_m,
            "spacing_m": spacing, "relief_m": settings.relief_m,
            "correlation_length_m": settings.correlation_length_m, "seed": seed,
            "shape": [rows, cols]}
    return truth, info


@functools.lru_cache(maxsize=2)
def _tiled_fractal(cell_m: float, spacing_m: float, relief_m: float,
                   correlation_length_m: float, seed: int, xmin: float, ymin: float,
                   rows: int, cols: int) -> Dtm:
    """The fractal cell tiled over ``rows`` x ``cols`` samples from ``(xmin, ymin)``.

    Kept for the next flight: the scenarios of a study (and the test suite's flights)
    share one terrain seed and region, and the cell's FFT and the grid's surface were a
    tenth of the suite's time. A ``Dtm`` is immutable (its heights are read-only), so
    sharing it changes nothing downstream.
    """
    cell = fractal_terrain(size_m=cell_m, spacing_m=spacing_m, relief_m=relief_m,
                           correlation_length_m=correlation_length_m, seed=seed,
                           origin_xy=(xmin, ymin))
    cell_rows, cell_cols = cell.shape
    # fractal_terrain is periodic over its sample count, so plain tiling is seamless
    # (clone_basic_cell's mirror=False, without making a Dtm of the uncropped tiling).
    tiled = np.tile(cell.elevation, (math.ceil(rows / cell_rows), math.ceil(cols / cell_cols)))
    return Dtm(tiled[:rows, :cols], xmin, ymin, spacing_m, spacing_m)


def _check_clearance(terrain: Dtm, region: tuple[float, float, float, float],
                     altitude_m: float) -> None:
    xmin, xmax, ymin, ymax = region
    rows, cols = terrain.shape
    xs = terrain.x0 + np.arange(cols) * terrain.dx
    ys = terrain.y0 + np.arange(rows) * terrain.dy
    inside = np.ix_((ys >= ymin) & (ys <= ymax), (xs >= xmin) & (xs <= xmax))
    block = terrain.elevation[inside]
    if block.size == 0 or np.isnan(block).all():
        raise SimulationError("the terrain has no data under the flight, expected heights there")
    top = float(np.nanmax(block))
    if altitude_m - top < MIN_CLEARANCE_M:
        raise SimulationError(
            f"the aircraft at {altitude_m:.0f} m clears the highest terrain under it "
            f"({top:.0f} m) by less than {MIN_CLEARANCE_M:g} m; expected a larger altitude_m")


def _height_error_rms(dtm: Dtm, truth: Dtm) -> float:
    """RMS of the log's DTM minus the true terrain at the true samples (m)."""
    rows, cols = truth.shape
    xs = truth.x0 + np.arange(cols) * truth.dx
    ys = truth.y0 + np.arange(rows) * truth.dy
    diff = dtm.height(xs[None, :], ys[:, None]) - truth.elevation
    valid = np.isfinite(diff)
    return float(np.sqrt(np.mean(diff[valid] ** 2))) if valid.any() else float("nan")


# --------------------------------------------------------------------------- states


def _groundtruth(plan: FlightPlan, frame_t_ns: np.ndarray, end_ns: int,
                 rate_hz: float) -> States:
    """True body states at ``rate_hz`` from 0 to ``end_ns`` and at every frame time."""
    step_ns = int(round(NS_PER_S / rate_hz))
    t_ns = np.union1d(np.arange(0, end_ns + 1, step_ns, dtype=np.int64), frame_t_ns)
    truth = evaluate(plan, t_ns.astype(float) / NS_PER_S)
    return States(t_ns, truth.position_m, truth.quaternion_wxyz, truth.velocity_mps)


def _initial_state(settings: SimulationSettings, truth_frames: Trajectory, rng: np.random.Generator
                   ) -> tuple[InitialState, np.ndarray, np.ndarray]:
    """The initial-state prior (mean = truth + one draw of the prior) and the true biases."""
    position = truth_frames.position_m[0]
    R = truth_frames.rotation_world_body[0]
    velocity = truth_frames.velocity_mps[0]
    zero = np.zeros(3)
    if settings.noiseless:
        true_gyro_bias, true_accel_bias = zero, zero
    else:
        draws = rng.standard_normal((5, 3))  # one fixed block: order never changes the stream
        position_error = (settings.sigma_position_m * draws[0] if settings.initial_error_m
                          is None else np.asarray(settings.initial_error_m))
        attitude_error = (math.radians(settings.sigma_attitude_deg) * draws[1]
                          if settings.initial_error_deg is None
                          else np.radians(settings.initial_error_deg))
        position = position + position_error
        # Right perturbation (body frame), as GTSAM's Pose3 prior measures it.
        R = R @ so3_exp(attitude_error)
        velocity = velocity + settings.sigma_velocity_mps * draws[2]
        true_gyro_bias = settings.sigma_gyro_bias * draws[3]
        true_accel_bias = settings.sigma_accel_bias * draws[4]
    initial = InitialState(
        position_m=position,
        quaternion_wxyz=rotation_to_quat_wxyz(R),
        velocity_mps=velocity,
        gyro_bias=zero,
        accel_bias=zero,
        sigma_position_m=settings.sigma_position_m,
        sigma_attitude_deg=settings.sigma_attitude_deg,
        sigma_velocity_mps=settings.sigma_velocity_mps,
        sigma_gyro_bias=settings.sigma_gyro_bias,
        sigma_accel_bias=settings.sigma_accel_bias,
    )
    if settings.noiseless:
        # The prior is the truth exactly: keep the trajectory's own quaternion (its sign
        # may differ from rotation_to_quat_wxyz's w >= 0 form, the rotation is the same).
        initial = dataclasses.replace(initial, quaternion_wxyz=truth_frames.quaternion_wxyz[0])
    return initial, np.asarray(true_gyro_bias), np.asarray(true_accel_bias)


def _dead_reckoning(config: FlightConfig, imu: ImuSamples, frame_t_ns: np.ndarray) -> States:
    """IMU-only propagation of the prior mean to every frame, as nav.csv rows."""
    free = dead_reckoning(config, imu, frame_t_ns)
    return States(frame_t_ns, free.position_m, rotation_to_quat_wxyz(free.world_T_body[:, :3, :3]),
                  free.velocity_mps)


def _noisy_truth(settings: SimulationSettings, truth_frames: Trajectory, frame_t_ns: np.ndarray,
                 rng: np.random.Generator) -> States:
    """The true state at every frame plus independent white noise."""
    k_frames = frame_t_ns.shape[0]
    draws = rng.standard_normal((3, k_frames, 3))
    position = truth_frames.position_m + settings.nav_sigma_position_m * draws[0]
    R = truth_frames.rotation_world_body @ so3_exp(
        math.radians(settings.nav_sigma_attitude_deg) * draws[1])
    velocity = truth_frames.velocity_mps + settings.nav_sigma_velocity_mps * draws[2]
    return States(frame_t_ns, position, rotation_to_quat_wxyz(R), velocity)


# --------------------------------------------------------------------------- tracks


@dataclass(frozen=True)
class _Observed:
    """Features projected into one camera: noisy pixels and why each is (not) seen."""

    uv_true_px: np.ndarray  # (N, 2)
    uv_px: np.ndarray       # (N, 2) with pixel noise
    end: np.ndarray         # (N,) TrackEnd, LAST_FRAME (= 0) meaning "seen"

    @property
    def seen(self) -> np.ndarray:
        return self.end == TrackEnd.LAST_FRAME


def _observe(terrain: Dtm, camera: PinholeCamera, world_T_cam: np.ndarray,
             ground_m: np.ndarray, pixel_sigma_px: float, rng: np.random.Generator) -> _Observed:
    """Project ground points into a camera, occlusion-check them and add pixel noise.

    Args:
        terrain: the true terrain.
        camera: intrinsics.
        world_T_cam: (4, 4) the camera pose.
        ground_m: (N, 3) ground points in world.
        pixel_sigma_px: pixel noise (0: none).
        rng: noise source; draws (N, 2) normals whatever the outcome, so the stream does
            not depend on which points are seen.

    Returns:
        The observations.
    """
    n = ground_m.shape[0]
    R, p = world_T_cam[:3, :3], world_T_cam[:3, 3]
    to_ground = ground_m - p
    uv_true = camera.rays_to_pixels(to_ground @ R)  # NaN behind the camera
    uv = uv_true + pixel_sigma_px * rng.standard_normal((n, 2))
    end = np.full(n, TrackEnd.LAST_FRAME, dtype=np.int64)
    end[~camera.in_image(uv_true)] = TrackEnd.LEFT_IMAGE
    check = np.flatnonzero(end == TrackEnd.LAST_FRAME)
    if check.size:
        hits = terrain.raycast(p, to_ground[check])
        distance = np.linalg.norm(to_ground[check], axis=1)
        # The ray is origin + t * (G - p): the hit is at G when t = 1.
        early = np.abs(1.0 - hits.t) * distance > OCCLUSION_TOLERANCE_M
        no_ground = hits.status == RayStatus.NODATA  # unknown, so not seen
        end[check[no_ground]] = TrackEnd.NO_GROUND
        end[check[~no_ground & (~hits.hit | early)]] = TrackEnd.OCCLUDED
    end[(end == TrackEnd.LAST_FRAME) & ~camera.in_image(uv)] = TrackEnd.NOISE_OUTSIDE
    return _Observed(uv_true, uv, end)


@dataclass(frozen=True)
class _TrackSimulation:
    frame: np.ndarray            # (M,)
    track_id: np.ndarray         # (M,)
    uv_px: np.ndarray            # (M, 2)
    uv_true_px: np.ndarray       # (M, 2)
    ground_points_m: np.ndarray  # (T, 3)
    track_end: np.ndarray        # (T,)
    stats: TrackStats


@dataclass(frozen=True)
class _Spawned:
    """New tracks of frame k: ground points and their observations in frames k and k+1."""

    ground_m: np.ndarray       # (n, 3)
    uv_px: np.ndarray          # (n, 2) frame k, noisy
    uv_true_px: np.ndarray     # (n, 2)
    next_uv_px: np.ndarray     # (n, 2) frame k+1, noisy
    next_uv_true_px: np.ndarray
    candidates: int


def _spawn(terrain: Dtm, camera: PinholeCamera, world_T_cam_k: np.ndarray,
           world_T_cam_next: np.ndarray, need: int, pixel_sigma_px: float,
           rng: np.random.Generator) -> _Spawned:
    """Up to ``need`` new ground features seen (in the image after noise) in frames k and k+1.

    Random pixels of frame k are cast into the terrain from the true camera (the first
    hit is visible by construction) and kept when frame k+1 sees the hit too.
    """
    w, h = camera.width, camera.height
    R, p = world_T_cam_k[:3, :3], world_T_cam_k[:3, 3]
    parts: list[tuple[np.ndarray, ...]] = []
    candidates = accepted = 0
    for _ in range(_SPAWN_ROUNDS):
        if need <= 0:
            break
        # Before any draw assume half pass (the overlap of consecutive frames is large).
        share = max(accepted / candidates, 0.01) if candidates else 0.5
        n_try = int(min(max(_SPAWN_MIN_CANDIDATES, _SPAWN_OVERSAMPLING * need / share),
                        _SPAWN_MAX_CANDIDATES))
        candidates += n_try
        uv_true = np.column_stack([rng.uniform(-0.5, w - 0.5, n_try),
                                   rng.uniform(-0.5, h - 0.5, n_try)])
        uv = uv_true + pixel_sigma_px * rng.standard_normal((n_try, 2))
        hits = terrain.raycast(p, camera.pixels_to_rays(uv_true) @ R.T)
        cast = np.flatnonzero(hits.hit & camera.in_image(uv))
        nxt = _observe(terrain, camera, world_T_cam_next, hits.point[cast], pixel_sigma_px, rng)
        keep = np.flatnonzero(nxt.seen)[:need]
        rows = cast[keep]
        parts.append((hits.point[rows], uv[rows], uv_true[rows], nxt.uv_px[keep],
                      nxt.uv_true_px[keep]))
        need -= rows.size
        accepted += int(np.count_nonzero(nxt.seen))
    if not parts:
        empty2 = np.zeros((0, 2))
        return _Spawned(np.zeros((0, 3)), empty2, empty2, empty2, empty2, 0)
    ground, uv, uv_true, next_uv, next_uv_true = (np.concatenate(column)
                                                  for column in zip(*parts, strict=True))
    return _Spawned(ground, uv, uv_true, next_uv, next_uv_true, candidates)


def _simulate_tracks(terrain: Dtm, camera: PinholeCamera, world_T_cam: np.ndarray,
                     features: int, pixel_sigma_px: float, rng: np.random.Generator
                     ) -> _TrackSimulation:
    """Feature tracks over K frames, vectorized per frame.

    Every observation in frame k+1 is decided at frame k: the live tracks are projected
    into frame k+1 (those seen survive, the others end), then new tracks are spawned at
    frame k (:func:`_spawn`) until ``features`` tracks join the two frames. Track ids are
    0, 1, ... in order of birth, so the rows of a frame come sorted by id.

    Args:
        terrain: the true terrain.
        camera: intrinsics.
        world_T_cam: (K, 4, 4) true camera poses.
        features: target features per frame pair.
        pixel_sigma_px: pixel noise (0: none).
        rng: randomness.

    Returns:
        Rows sorted by frame then track id, and per-track truth.
    """
    k_frames = world_T_cam.shape[0]
    ground = np.zeros((0, 3))                   # (T, 3) every track so far
    track_end = np.zeros(0, dtype=np.int64)     # (T,)
    live_id = np.zeros(0, dtype=np.int64)       # tracks seen in the current frame
    live_uv = np.zeros((0, 2))                  # ... their observation in it
    live_uv_true = np.zeros((0, 2))
    rows_frame, rows_id, rows_uv, rows_uv_true = [], [], [], []
    pairs = np.zeros(k_frames - 1, dtype=np.int64)
    candidates = 0
    for k in range(k_frames - 1):
        nxt = _observe(terrain, camera, world_T_cam[k + 1], ground[live_id], pixel_sigma_px, rng)
        track_end[live_id[~nxt.seen]] = nxt.end[~nxt.seen]
        need = features - int(nxt.seen.sum())
        new = _spawn(terrain, camera, world_T_cam[k], world_T_cam[k + 1], need, pixel_sigma_px, rng)
        candidates += new.candidates
        n_new = new.ground_m.shape[0]
        new_id = np.arange(ground.shape[0], ground.shape[0] + n_new, dtype=np.int64)
        ground = np.concatenate([ground, new.ground_m])
        track_end = np.concatenate([track_end, np.full(n_new, TrackEnd.LAST_FRAME)])
        pairs[k] = int(nxt.seen.sum()) + n_new
        rows_frame.append(np.full(live_id.size + n_new, k, dtype=np.int64))
        rows_id.append(np.concatenate([live_id, new_id]))
        rows_uv.append(np.concatenate([live_uv, new.uv_px]))
        rows_uv_true.append(np.concatenate([live_uv_true, new.uv_true_px]))
        live_id = np.concatenate([live_id[nxt.seen], new_id])
        live_uv = np.concatenate([nxt.uv_px[nxt.seen], new.next_uv_px])
        live_uv_true = np.concatenate([nxt.uv_true_px[nxt.seen], new.next_uv_true_px])
    rows_frame.append(np.full(live_id.size, k_frames - 1, dtype=np.int64))
    rows_id.append(live_id)
    rows_uv.append(live_uv)
    rows_uv_true.append(live_uv_true)

    frame = np.concatenate(rows_frame)
    lost = {reason.name.lower(): int(np.sum(track_end == reason)) for reason in TrackEnd}
    stats = TrackStats(n_tracks=int(ground.shape[0]), n_observations=int(frame.size),
                       pairs_per_frame=pairs, lost=lost, spawn_candidates=candidates)
    return _TrackSimulation(frame=frame, track_id=np.concatenate(rows_id),
                            uv_px=np.concatenate(rows_uv),
                            uv_true_px=np.concatenate(rows_uv_true), ground_points_m=ground,
                            track_end=track_end, stats=stats)


# --------------------------------------------------------------------------- helpers


def _is_number(value: object) -> bool:
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(value,
                                                                                       bool)


def _is_int(value: object) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool)
