"""What real flights do to the data, for tests and studies: faults injected into simulations.

Two kinds:

* **Terrain the map lacks** (:class:`TerrainMismatch`): a change to the *true* terrain
  only, made before features are cast on it, so the log's DTM (made from the unchanged
  truth) does not know it: a pit or quarry, buildings, a forest.
* **Faults in a finished log** (functions on a :class:`~cdtm_graph.flightlog.FlightLog`):
  wrong matches, IMU gaps, calibration errors. They return a new log and leave the input
  alone.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from dataclasses import dataclass

import numpy as np

from cdtm_graph.dtm import Dtm
from cdtm_graph.flightlog import FlightLog, Frames, ImuSamples
from cdtm_graph.geometry import make_pose, so3_exp

NS_PER_S = 1_000_000_000


class MismatchKind(enum.Enum):
    PIT = "pit"        # a round pit (quarry, collapsed ground) under the track
    BLOCKS = "blocks"  # flat-roofed blocks (buildings; a forest with small ones)


@dataclass(frozen=True)
class TerrainMismatch:
    """Terrain that the true ground has and the DTM lacks.

    Attributes:
        kind: PIT or BLOCKS.
        depth_m: PIT: how far the pit floor lies below the ground (m).
        radius_m: PIT: radius of the floor (m); the wall slopes over ``wall_m`` outside it.
        wall_m: PIT: horizontal width of the wall (m).
        at_s: PIT: the pit is centred under the flight at this time (s).
        coverage: BLOCKS: fraction of the ground the blocks cover.
        height_m: BLOCKS: (low, high) block heights, uniform (m).
        size_m: BLOCKS: (low, high) block side lengths, uniform (m).
        seed: BLOCKS: seed of the block layout.
    """

    kind: MismatchKind
    depth_m: float = 40.0
    radius_m: float = 900.0
    wall_m: float = 60.0
    at_s: float = 30.0
    coverage: float = 0.15
    height_m: tuple[float, float] = (15.0, 30.0)
    size_m: tuple[float, float] = (30.0, 80.0)
    seed: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "kind", MismatchKind(self.kind))

    def to_dict(self) -> dict:
        out = dataclasses.asdict(self)
        out["kind"] = self.kind.value
        return {k: list(v) if isinstance(v, tuple) else v for k, v in out.items()}


def apply_terrain_mismatch(truth: Dtm, mismatch: TerrainMismatch,
                           centre_xy_m: tuple[float, float]) -> Dtm:
    """The true terrain with the mismatch added (a new grid; ``truth`` is unchanged).

    Args:
        truth: the true terrain.
        mismatch: what to add.
        centre_xy_m: the flight's position at ``mismatch.at_s`` (PIT).
    """
    rows, cols = truth.shape
    x = truth.x0 + np.arange(cols) * truth.dx
    y = truth.y0 + np.arange(rows) * truth.dy
    elevation = truth.elevation.copy()
    if mismatch.kind is MismatchKind.PIT:
        r = np.hypot(x[None, :] - centre_xy_m[0], y[:, None] - centre_xy_m[1])
        s = np.clip((mismatch.radius_m + mismatch.wall_m - r) / mismatch.wall_m, 0.0, 1.0)
        elevation -= mismatch.depth_m * s * s * (3.0 - 2.0 * s)  # smoothstep wall
    else:
        rng = np.random.default_rng(mismatch.seed)
        raised = np.zeros(truth.shape, dtype=bool)
        heights = np.zeros(truth.shape)
        area = (x[-1] - x[0]) * abs(y[-1] - y[0])
        mean_side = 0.5 * sum(mismatch.size_m)
        n = int(math.ceil(2.0 * mismatch.coverage * area / mean_side**2)) + 1
        xs = rng.uniform(x.min(), x.max(), n)
        ys = rng.uniform(y.min(), y.max(), n)
        sides = rng.uniform(*mismatch.size_m, (n, 2))
        tops = rng.uniform(*mismatch.height_m, n)
        for i in range(n):
            if raised.mean() >= mismatch.coverage:
                break
            c0, c1 = np.searchsorted(x, [xs[i], xs[i] + sides[i, 0]])
            ys_sorted = y if truth.dy > 0 else y[::-1]
            r0, r1 = np.searchsorted(ys_sorted, [ys[i], ys[i] + sides[i, 1]])
            if truth.dy < 0:
                r0, r1 = rows - r1, rows - r0
            block = (slice(r0, r1), slice(c0, c1))
            raised[block] = True
            heights[block] = tops[i]
        elevation += heights
    return Dtm(elevation, truth.x0, truth.y0, truth.dx, truth.dy, sigma_h_m=truth.sigma_h_m)


def with_wrong_matches(log: FlightLog, fraction: float, rng: np.random.Generator
                       ) -> tuple[FlightLog, np.ndarray]:
    """A fraction of the observations moved to a uniformly random pixel of the image: the
    classic tracker failure (a match to something else entirely).

    Returns:
        The log, and which rows of tracks.csv were replaced, (M,) bool.
    """
    tracks = log.tracks
    if tracks is None:
        raise ValueError("the log has no tracks")
    camera = log.config.camera.camera
    bad = rng.random(len(tracks)) < fraction
    uv = tracks.uv_px.copy()
    uv[bad] = rng.uniform([-0.5, -0.5], [camera.width - 0.5, camera.height - 0.5],
                          (int(bad.sum()), 2))
    return dataclasses.replace(log, tracks=dataclasses.replace(tracks, uv_px=uv)), bad


def with_imu_gap(log: FlightLog, start_s: float, duration_s: float) -> FlightLog:
    """The IMU samples in ``[t0 + start_s, t0 + start_s + duration_s)`` removed (a data
    gap, e.g. a dropped connection), t0 the first frame's time."""
    t0 = int(log.frames.t_ns[0])
    lo, hi = t0 + int(start_s * NS_PER_S), t0 + int((start_s + duration_s) * NS_PER_S)
    keep = (log.imu.t_ns < lo) | (log.imu.t_ns >= hi)
    imu = ImuSamples(log.imu.t_ns[keep], log.imu.gyro_radps[keep], log.imu.acc_mps2[keep])
    return dataclasses.replace(log, imu=imu)


def with_calibration_error(log: FlightLog, focal_scale: float = 1.0,
                           mount_rotation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0),
                           time_offset_s: float = 0.0) -> FlightLog:
    """flight.yaml and frames.csv as a user with a wrong calibration would write them.

    Args:
        focal_scale: fx and fy in flight.yaml are the true ones times this.
        mount_rotation_deg: ``body_T_cam`` in flight.yaml is the true mount turned by this
            rotation vector (camera frame, degrees).
        time_offset_s: the frame times are this late against the IMU (the camera's clock
            runs behind; the images were taken at the true times).
    """
    cfg = log.config
    cam = cfg.camera.camera
    camera = dataclasses.replace(cam, fx=cam.fx * focal_scale, fy=cam.fy * focal_scale)
    turn = make_pose(so3_exp(np.radians(np.asarray(mount_rotation_deg, dtype=float))),
                     np.zeros(3))
    camera_cfg = dataclasses.replace(cfg.camera, camera=camera,
                                     body_T_cam=cfg.camera.body_T_cam @ turn)
    config = dataclasses.replace(cfg, camera=camera_cfg)
    shift = int(round(time_offset_s * NS_PER_S))
    frames = Frames(log.frames.t_ns + shift, log.frames.image)
    nav = log.nav
    if nav is not None and shift:
        nav = dataclasses.replace(nav, t_ns=nav.t_ns + shift)
    return dataclasses.replace(log, config=config, frames=frames, nav=nav)
