"""The frames an acquisition works on, the prior it searches, and the correction it finds.

The window is a few seconds of frames dead-reckoned from one first state; a
:class:`Correction` changes that first state and re-propagates the window, exactly as
dead reckoning from the corrected state would.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cdtm_graph.constants import NS_PER_S
from cdtm_graph.dtm import Dtm
from cdtm_graph.errors import FlightLogError
from cdtm_graph.flightlog import CameraConfig, FlightLog, InitialState
from cdtm_graph.geometry import make_pose
from cdtm_graph.imu import SampleHold, dead_reckoning
from cdtm_graph.results import pose_covariance_in_world
from cdtm_graph.robust.acquisition.settings import AcquisitionSettings
from cdtm_graph.tracks import check_unique


@dataclass(frozen=True)
class AcquisitionFrame:
    """One frame of the window, as the smoother holds it.

    Attributes:
        t_ns: frame time.
        world_T_body: (4, 4) current (dead-reckoned) body pose.
        track_id: (m,) ids of the features seen. uv_px: (m, 2) their pixels.
    """

    t_ns: int
    world_T_body: np.ndarray
    track_id: np.ndarray
    uv_px: np.ndarray


@dataclass(frozen=True)
class SearchPrior:
    """Where the window's first state may be: the spread around its current estimate.

    The mean is the first frame's ``world_T_body``; the window was propagated from it
    with ``velocity_world_mps`` under world gravity ``(0, 0, -gravity_mps2)``.

    Attributes:
        position_covariance_world: (3, 3) covariance of the first position (m^2, world).
        heading_sigma_rad: 1-sigma heading error.
        tilt_sigma_rad: 1-sigma roll and pitch error.
        velocity_world_mps: (3,) the first frame's velocity.
        velocity_sigma_mps: 1-sigma of each velocity component.
        gravity_mps2: gravity magnitude.
    """

    position_covariance_world: np.ndarray
    heading_sigma_rad: float
    tilt_sigma_rad: float
    velocity_world_mps: np.ndarray
    velocity_sigma_mps: float
    gravity_mps2: float

    def __post_init__(self) -> None:
        P = np.asarray(self.position_covariance_world, dtype=float)
        if P.shape != (3, 3) or not np.all(np.isfinite(P)) or not np.allclose(P, P.T):
            raise ValueError(f"SearchPrior: position_covariance_world of shape {P.shape}, "
                             "expected a finite symmetric (3, 3) matrix")
        if np.linalg.eigvalsh(P)[0] <= 0.0:
            raise ValueError("SearchPrior: position_covariance_world is not positive "
                             "definite, expected a covariance with every variance > 0")
        object.__setattr__(self, "position_covariance_world", P)
        v = np.asarray(self.velocity_world_mps, dtype=float)
        if v.shape != (3,) or not np.all(np.isfinite(v)):
            raise ValueError(f"SearchPrior: velocity_world_mps = {v!r}, expected 3 finite "
                             "numbers")
        object.__setattr__(self, "velocity_world_mps", v)
        for name in ("heading_sigma_rad", "tilt_sigma_rad", "velocity_sigma_mps",
                     "gravity_mps2"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"SearchPrior: {name} = {value!r}, expected a finite "
                                 "number > 0")

    @classmethod
    def from_initial_state(cls, initial: InitialState, gravity_mps2: float) -> SearchPrior:
        """The initial-state prior of flight.yaml (isotropic sigmas)."""
        att = initial.sigma_attitude_rad
        return cls(np.eye(3) * initial.sigma_position_m ** 2, att, att,
                   np.asarray(initial.velocity_mps, dtype=float),
                   float(initial.sigma_velocity_mps), float(gravity_mps2))

    @classmethod
    def from_pose_covariance(cls, world_T_body: np.ndarray, pose_covariance: np.ndarray,
                             velocity_world_mps: np.ndarray, velocity_sigma_mps: float,
                             gravity_mps2: float) -> SearchPrior:
        """The spread of a smoother's current estimate (re-acquisition after a gap).

        Args:
            world_T_body: (4, 4) the estimate. pose_covariance: (6, 6) its marginal in
                GTSAM's order [rotation, translation], right perturbation (body frame).
            velocity_world_mps: (3,) its velocity. velocity_sigma_mps: 1-sigma of each
                component (e.g. the square root of the largest eigenvalue of its marginal).
            gravity_mps2: gravity magnitude.
        """
        orientation, position = pose_covariance_in_world(
            np.asarray(world_T_body, dtype=float)[None], np.asarray(pose_covariance)[None])
        heading = math.sqrt(orientation[0, 2, 2])
        tilt = math.sqrt(max(orientation[0, 0, 0], orientation[0, 1, 1]))
        return cls(position[0], heading, tilt, np.asarray(velocity_world_mps, dtype=float),
                   float(velocity_sigma_mps), float(gravity_mps2))

    @property
    def gravity_world(self) -> np.ndarray:
        return np.array([0.0, 0.0, -self.gravity_mps2])


@dataclass(frozen=True)
class Correction:
    """A change of the window's first state, and the window re-propagated from it.

    The window was dead-reckoned from a first state (position ``p0``, velocity ``v0``).
    The corrected first state has position ``p0 + translation``, velocity ``v0 +
    velocity`` and every attitude turned by ``rotation_world`` (left, world frame, about
    the first body position). The IMU's specific force turns with the attitude, the
    velocity and gravity do not, so frame k, ``dt`` after the first, moves to
    ``p0 + translation + (v0 + velocity) dt + g dt^2 / 2 + rotation s_k`` with
    ``s_k = p_k - p0 - v0 dt - g dt^2 / 2`` (exact for constant IMU biases): what dead
    reckoning from the corrected first state gives.

    Attributes:
        rotation_world: (3, 3). translation_world_m: (3,). velocity_world_mps: (3,).
    """

    rotation_world: np.ndarray
    translation_world_m: np.ndarray
    velocity_world_mps: np.ndarray

    @classmethod
    def identity(cls) -> Correction:
        return cls(np.eye(3), np.zeros(3), np.zeros(3))

    @property
    def heading_deg(self) -> float:
        """The turn about world z (deg, counter-clockwise seen from above)."""
        R = self.rotation_world
        return math.degrees(math.atan2(R[1, 0] - R[0, 1], R[0, 0] + R[1, 1]))

    def apply_to_state(self, world_T_body: np.ndarray, velocity_world_mps: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
        """The corrected first state: ``(world_T_body (4, 4), velocity (3,))``."""
        pose = make_pose(self.rotation_world @ world_T_body[:3, :3],
                         world_T_body[:3, 3] + self.translation_world_m)
        return pose, np.asarray(velocity_world_mps, dtype=float) + self.velocity_world_mps

    def apply(self, world_T_body: np.ndarray, t_ns: np.ndarray,
              velocity_world_mps: np.ndarray, gravity_mps2: float) -> np.ndarray:
        """The window re-propagated from the corrected first state.

        Args:
            world_T_body: (K, 4, 4) poses dead-reckoned from the first one.
            t_ns: (K,) their times. velocity_world_mps: (3,) the first frame's velocity.
            gravity_mps2: gravity magnitude (world -z).

        Returns:
            (K, 4, 4) corrected poses.
        """
        dt = (np.asarray(t_ns, dtype=np.int64) - int(t_ns[0])).astype(float) / NS_PER_S
        return propagate(world_T_body, dt, np.asarray(velocity_world_mps, dtype=float),
                         np.array([0.0, 0.0, -gravity_mps2]), self)


def drift(world_T_body: np.ndarray, dt: np.ndarray, v0: np.ndarray,
          g: np.ndarray) -> np.ndarray:
    """(K, 3) ``s_k``: each position less what the first state's velocity and gravity give
    (the specific force, integrated twice; it turns with the attitude)."""
    p = world_T_body[:, :3, 3]
    return p - p[0] - dt[:, None] * v0 - 0.5 * dt[:, None] ** 2 * g


def propagate(world_T_body: np.ndarray, dt: np.ndarray, v0: np.ndarray, g: np.ndarray,
              c: Correction) -> np.ndarray:
    """(K, 4, 4) the poses ``world_T_body`` (dead-reckoned from the first, with velocity
    ``v0`` and gravity ``g``, ``dt`` (K,) after it) under correction ``c``."""
    s = drift(world_T_body, dt, v0, g)
    out = world_T_body.copy()
    out[:, :3, :3] = c.rotation_world @ world_T_body[:, :3, :3]
    out[:, :3, 3] = (world_T_body[0, :3, 3] + c.translation_world_m
                     + dt[:, None] * (v0 + c.velocity_world_mps)
                     + 0.5 * dt[:, None] ** 2 * g + s @ c.rotation_world.T)
    return out


@dataclass(frozen=True)
class Window:
    """The frames' sightings by track (tracks with two or more sightings, time order).

    Attributes:
        world_T_body: (K, 4, 4). dt_s: (K,) time since the first frame.
        frame: (n,) frame of each sighting. q: (n, 3) its ray (z = 1, camera).
        starts: (T + 1,) sightings of track t are ``starts[t]:starts[t + 1]``.
        track_of: (n,) the track of each sighting.
    """

    world_T_body: np.ndarray
    t_ns: np.ndarray
    dt_s: np.ndarray
    frame: np.ndarray
    q: np.ndarray
    starts: np.ndarray
    track_of: np.ndarray

    @property
    def n_tracks(self) -> int:
        return self.starts.size - 1


def build_window(frames: Sequence[AcquisitionFrame], camera: CameraConfig) -> Window:
    """Check the frames and group their sightings by track.

    Raises:
        FlightLogError: fewer than two frames, times not increasing, a bad pose or
            shapes, a track seen twice in a frame.
    """
    if len(frames) < 2:
        raise FlightLogError(f"acquisition needs at least 2 frames, got {len(frames)}")
    t_ns = np.array([int(f.t_ns) for f in frames], dtype=np.int64)
    if np.any(np.diff(t_ns) <= 0):
        k = int(np.flatnonzero(np.diff(t_ns) <= 0)[0]) + 1
        raise FlightLogError(f"acquisition frame {k}: time {t_ns[k]} ns is not after the "
                             "previous frame")
    poses, ids, uvs, frame = [], [], [], []
    for k, f in enumerate(frames):
        pose = np.asarray(f.world_T_body, dtype=float)
        tid = np.asarray(f.track_id, dtype=np.int64)
        uv = np.asarray(f.uv_px, dtype=float)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise FlightLogError(f"acquisition frame {k}: world_T_body has shape {pose.shape}"
                                 " or non-finite entries, expected a finite (4, 4) pose")
        if tid.ndim != 1 or uv.shape != (tid.size, 2):
            raise FlightLogError(f"acquisition frame {k}: {tid.shape} track ids with pixels "
                                 f"of shape {uv.shape}; expected (m,) and (m, 2)")
        check_unique(k, tid)
        poses.append(pose)
        ids.append(tid)
        uvs.append(uv)
        frame.append(np.full(tid.size, k, dtype=np.int64))
    track_id, uv_px, frame_of = np.concatenate(ids), np.concatenate(uvs), np.concatenate(frame)
    q = camera.camera.pixels_to_rays(uv_px)
    ok = np.isfinite(q).all(axis=1)
    track_id, frame_of, q = track_id[ok], frame_of[ok], q[ok]
    order = np.lexsort((frame_of, track_id))
    track_id, frame_of, q = track_id[order], frame_of[order], q[order]
    counts = np.unique(track_id, return_counts=True)[1]
    keep = np.repeat(counts >= 2, counts)
    counts = counts[counts >= 2]
    starts = np.r_[0, np.cumsum(counts)].astype(np.int64)
    return Window(np.stack(poses), t_ns, (t_ns - t_ns[0]).astype(float) / NS_PER_S,
                  frame_of[keep], np.ascontiguousarray(q[keep]), starts,
                  np.repeat(np.arange(counts.size), counts))


def dead_reckoned_window(flight: FlightLog, n_frames: int,
                         hold: SampleHold = SampleHold.MIDPOINT
                         ) -> tuple[list[AcquisitionFrame], SearchPrior]:
    """The first frames of a log dead-reckoned from its initial state, and that state's
    prior: what :func:`~cdtm_graph.robust.acquisition.acquire` takes at the start of a flight.

    Args:
        flight: the log (tracks and IMU covering the frames).
        n_frames: how many frames (all if fewer).
        hold: the IMU sample hold (the smoother's default).
    """
    t_ns = flight.frames.t_ns[:n_frames]
    free = dead_reckoning(flight.config, flight.imu, t_ns, hold)
    tracks = flight.tracks
    frames = []
    for k, t in enumerate(t_ns):
        rows = (slice(*np.searchsorted(tracks.frame, [k, k + 1])) if tracks is not None
                else slice(0, 0))
        frames.append(AcquisitionFrame(
            int(t), free.world_T_body[k],
            tracks.track_id[rows] if tracks is not None else np.zeros(0, np.int64),
            tracks.uv_px[rows] if tracks is not None else np.zeros((0, 2))))
    return frames, SearchPrior.from_initial_state(flight.config.initial_state,
                                                  flight.config.gravity_mps2)


class Problem:
    """One acquisition's window, camera, DTM, prior and settings, and what follows from
    them (the ray noise, the propagation of a correction).

    Attributes:
        sigma_q: (2,) a sighting's ray error against the IMU's relative poses, in
            normalized image units (pixel noise and ``drift_sigma_rad``).
        ray_sigma_rad: the larger of the two.
        tau: the truncation of the robust costs (sigmas).
    """

    def __init__(self, window: Window, camera: CameraConfig, dtm: Dtm, prior: SearchPrior,
                 settings: AcquisitionSettings):
        self.window, self.camera, self.dtm, self.prior, self.settings = (
            window, camera, dtm, prior, settings)
        self.g = prior.gravity_world
        self.v0 = np.asarray(prior.velocity_world_mps, dtype=float)
        self.tau = settings.truncation_sigma
        self.elevation = np.ascontiguousarray(dtm.elevation)
        qx, qy = camera.camera.sigma_normalized(camera.pixel_sigma_px)
        self.sigma_q = (math.hypot(qx, settings.drift_sigma_rad),
                        math.hypot(qy, settings.drift_sigma_rad))
        self.ray_sigma_rad = max(self.sigma_q)

    def poses(self, c: Correction) -> np.ndarray:
        """(K, 4, 4) the window's body poses under a correction."""
        return propagate(self.window.world_T_body, self.window.dt_s, self.v0, self.g, c)

    def drift(self) -> np.ndarray:
        """(K, 3) the window's specific-force displacements (:func:`drift`)."""
        return drift(self.window.world_T_body, self.window.dt_s, self.v0, self.g)
