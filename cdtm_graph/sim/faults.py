"""What real flights do to the data, for tests and studies: faults injected into simulations.

Three kinds:

* **Terrain the map lacks** (:class:`TerrainMismatch`): a change to the *true* terrain
  only, made before features are cast on it, so the log's DTM (made from the unchanged
  truth) does not know it: a pit or quarry, buildings, a forest.
* **Terrain that gives the DTM nothing to hold** (:class:`FlatGround`): a lake under
  the track, in the truth and the DTM alike; the map is right, the geometry is weak.
* **Faults in a finished log** (functions on a :class:`~cdtm_graph.flightlog.FlightLog`
  or its DTM): wrong matches, IMU gaps, calibration errors, a DTM that ends under the
  flight. They return a new log or DTM and leave the input alone.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from cdtm_graph.constants import NS_PER_S
from cdtm_graph.dtm import Dtm
from cdtm_graph.flightlog import FlightLog, Frames, ImuSamples
from cdtm_graph.geometry import make_pose, so3_exp


class MismatchKind(enum.Enum):
    PIT = "pit"        # a round pit (quarry, collapsed ground) under the track
    BLOCKS = "blocks"  # flat-roofed blocks (buildings; a forest with small ones)
    HILL = "hill"      # a broad smooth hill under the track (a map from before an embankment)


@dataclass(frozen=True)
class TerrainMismatch:
    """Terrain that the true ground has and the DTM lacks.

    Attributes:
        kind: PIT, BLOCKS or HILL.
        depth_m: PIT: how far the pit floor lies below the ground (m); HILL: how high the
            hill rises above it.
        radius_m: PIT: radius of the floor (m); the wall slopes over ``wall_m`` outside it.
            HILL: the hill's Gaussian sigma (m): smooth, with no edge a test can see.
        wall_m: PIT: horizontal width of the wall (m).
        at_s: PIT, HILL: centred under the flight at this time (s).
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
    elif mismatch.kind is MismatchKind.HILL:
        r = np.hypot(x[None, :] - centre_xy_m[0], y[:, None] - centre_xy_m[1])
        elevation += mismatch.depth_m * np.exp(-0.5 * (r / mismatch.radius_m) ** 2)
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
        covered, enough = 0, mismatch.coverage * raised.size  # (a running count: a mean
        for i in range(n):                                     # per block is quadratic)
            if covered >= enough:
                break
            c0, c1 = np.searchsorted(x, [xs[i], xs[i] + sides[i, 0]])
            ys_sorted = y if truth.dy > 0 else y[::-1]
            r0, r1 = np.searchsorted(ys_sorted, [ys[i], ys[i] + sides[i, 1]])
            if truth.dy < 0:
                r0, r1 = rows - r1, rows - r0
            block = (slice(r0, r1), slice(c0, c1))
            covered += int(np.count_nonzero(~raised[block]))
            raised[block] = True
            heights[block] = tops[i]
        elevation += heights
    return Dtm(elevation, truth.x0, truth.y0, truth.dx, truth.dy, sigma_h_m=truth.sigma_h_m)


@dataclass(frozen=True)
class FlatGround:
    """Flat ground (a lake) under part of the flight, in the true terrain and the DTM.

    Attributes:
        at_s: the track reaches the flat ground at this time (s)...
        duration_s: ...and leaves it this much later: the ground under the track
            between those times, out to ``half_width_m`` on either side, is flat (the
            frames whose whole footprint lies on it see nothing else; a footprint
            reaching ~5 s ahead and behind, as the issue's flight's, sees flat ground only
            from ``at_s + 5`` to ``at_s + duration_s - 5``).
        half_width_m: how far the flat ground reaches either side of the track (m):
            wider than half the camera footprint across the track, or frames see its
            shore.
        shore_m: width of the edge over which the ground blends back into the terrain.
    """

    at_s: float = 30.0
    duration_s: float = 30.0
    half_width_m: float = 1500.0
    shore_m: float = 100.0

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def apply_flat_ground(terrain: Dtm, flat: FlatGround, track_xy_m: np.ndarray) -> Dtm:
    """The terrain with the ground along the track flattened to its mean height there (a
    new grid; ``terrain`` is unchanged): within ``half_width_m`` of the track and not past
    its ends, blended over ``shore_m``.

    Args:
        terrain: the terrain.
        flat: where and how wide.
        track_xy_m: (n >= 2, 2) the flight's positions over the flat stretch, densely
            sampled (every few tens of metres), in time order.
    """
    track = np.asarray(track_xy_m, dtype=float)
    rows, cols = terrain.shape
    x = terrain.x0 + np.arange(cols) * terrain.dx
    y = terrain.y0 + np.arange(rows) * terrain.dy
    xx, yy = np.meshgrid(x, y)
    points = np.column_stack([xx.ravel(), yy.ravel()])
    distance, nearest = cKDTree(track).query(points)
    # past either end of the track: how far along it, and how far across
    past = np.zeros(points.shape[0])
    for end, inward in ((0, track[1] - track[0]), (-1, track[-2] - track[-1])):
        course = -inward / np.linalg.norm(inward)  # pointing out of the stretch
        at_end = nearest == (end % track.shape[0])
        offset = points[at_end] - track[end]
        along = offset @ course
        past[at_end] = along
        distance[at_end] = np.where(along > 0, np.abs(offset @ [-course[1], course[0]]),
                                    distance[at_end])

    def smoothstep(u: np.ndarray) -> np.ndarray:
        u = np.clip(u, 0.0, 1.0)
        return u * u * (3.0 - 2.0 * u)

    weight = (smoothstep((flat.half_width_m + flat.shore_m - distance) / flat.shore_m)
              * smoothstep((flat.shore_m - past) / flat.shore_m)).reshape(rows, cols)
    inside = weight >= 1.0
    level = float(np.nanmean(terrain.elevation[inside])) if inside.any() else 0.0
    elevation = (1.0 - weight) * terrain.elevation + weight * level
    return Dtm(elevation, terrain.x0, terrain.y0, terrain.dx, terrain.dy,
               sigma_h_m=terrain.sigma_h_m)


def with_dtm_ending(log: FlightLog, dtm: Dtm, at_s: float) -> Dtm:
    """The log's DTM without data (NaN) past the point the flight reaches at ``at_s``
    (seconds after the first frame): the half-plane ahead of the true track there, across
    its course, as where a flight leaves the map it was given.

    Raises:
        ValueError: the log has no ground truth to find the track.
    """
    if log.groundtruth is None:
        raise ValueError("the log has no ground truth to place the DTM's end on")
    t0 = int(log.frames.t_ns[0])
    at = np.array([t0 + int(at_s * NS_PER_S), t0 + int((at_s + 1.0) * NS_PER_S)])
    p = log.groundtruth.interpolate(at).world_T_body[:, :2, 3]
    course = (p[1] - p[0]) / np.linalg.norm(p[1] - p[0])
    rows, cols = dtm.shape
    x = dtm.x0 + np.arange(cols) * dtm.dx
    y = dtm.y0 + np.arange(rows) * dtm.dy
    ahead = ((x[None, :] - p[0, 0]) * course[0] + (y[:, None] - p[0, 1]) * course[1]) > 0.0
    elevation = np.where(ahead, np.nan, dtm.elevation)
    return Dtm(elevation, dtm.x0, dtm.y0, dtm.dx, dtm.dy, sigma_h_m=dtm.sigma_h_m)


def with_map_offset(dtm: Dtm, offset_enu_m: tuple[float, float, float]) -> Dtm:
    """The log's DTM moved as a whole by ``offset_enu_m`` (east, north, up) against the
    true ground: a map registered off, or on another vertical datum."""
    east, north, up = (float(v) for v in offset_enu_m)
    return Dtm(dtm.elevation + up, dtm.x0 + east, dtm.y0 + north, dtm.dx, dtm.dy,
               sigma_h_m=dtm.sigma_h_m)


def with_dtm_noise(dtm: Dtm, sigma_m: float, rng: np.random.Generator) -> Dtm:
    """The log's DTM with independent noise of ``sigma_m`` on every post: a map much worse
    than it states (a coarse or noisy product, heights from another survey). Between the
    posts the bilinear surface averages it: about 2/3 of ``sigma_m`` at a random point."""
    return Dtm(dtm.elevation + sigma_m * rng.standard_normal(dtm.elevation.shape),
               dtm.x0, dtm.y0, dtm.dx, dtm.dy, sigma_h_m=dtm.sigma_h_m)


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


def with_imu_bias(log: FlightLog, accel_mps2: tuple[float, float, float] = (0.0, 0.0, 0.0),
                  gyro_radps: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> FlightLog:
    """Every IMU sample offset by a constant bias that flight.yaml's prior does not know (an
    IMU out of its specification, a prior copied from another unit)."""
    imu = log.imu
    return dataclasses.replace(log, imu=ImuSamples(
        imu.t_ns, imu.gyro_radps + np.asarray(gyro_radps), imu.acc_mps2 + np.asarray(accel_mps2)))


def with_calibration_error(log: FlightLog, focal_scale: float = 1.0,
                           mount_rotation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0),
                           time_offset_s: float = 0.0,
                           principal_point_px: tuple[float, float] = (0.0, 0.0)) -> FlightLog:
    """flight.yaml and frames.csv as a user with a wrong calibration would write them.

    Args:
        focal_scale: fx and fy in flight.yaml are the true ones times this.
        principal_point_px: cx and cy in flight.yaml are the true ones plus this.
        mount_rotation_deg: ``body_T_cam`` in flight.yaml is the true mount turned by this
            rotation vector (camera frame, degrees).
        time_offset_s: the frame times are this late against the IMU (the camera's clock
            runs behind; the images were taken at the true times).
    """
    cfg = log.config
    cam = cfg.camera.camera
    camera = dataclasses.replace(cam, fx=cam.fx * focal_scale, fy=cam.fy * focal_scale,
                                 cx=cam.cx + principal_point_px[0],
                                 cy=cam.cy + principal_point_px[1])
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


def with_imu_bias_step(log: FlightLog, at_s: float,
                       accel_mps2: tuple[float, float, float] = (0.0, 0.0, 0.0),
                       gyro_radps: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> FlightLog:
    """Every IMU sample from ``t0 + at_s`` on offset by a bias step (a sensor's bias jumping
    once in flight: a temperature step, a shock), t0 the first frame's time."""
    imu = log.imu
    after = (imu.t_ns >= int(log.frames.t_ns[0]) + int(at_s * NS_PER_S))[:, None]
    return dataclasses.replace(log, imu=ImuSamples(
        imu.t_ns, imu.gyro_radps + after * np.asarray(gyro_radps),
        imu.acc_mps2 + after * np.asarray(accel_mps2)))


def with_imu_random_walks_stated(log: FlightLog, gyro_scale: float = 1.0,
                                 accel_scale: float = 1.0) -> FlightLog:
    """flight.yaml stating the IMU's bias random walks (``imu.gyroscope_random_walk``,
    ``imu.accelerometer_random_walk``) as ``scale`` times those of the IMU that made the
    samples: ``0.1`` states them 10x below the truth (a datasheet's in-run stability
    copied for the random walk, an IMU aged or warmer than its specification). The
    samples are untouched."""
    cfg = log.config
    imu = dataclasses.replace(
        cfg.imu, gyroscope_random_walk=cfg.imu.gyroscope_random_walk * gyro_scale,
        accelerometer_random_walk=cfg.imu.accelerometer_random_walk * accel_scale)
    return dataclasses.replace(log, config=dataclasses.replace(cfg, imu=imu))
