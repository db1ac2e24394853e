"""Before smoothing: does the log give the camera and the DTM anything to constrain?

Without a C-DTM factor the smoother still runs and returns IMU dead reckoning, with
covariances that look like a result. That happens when there are no tracks (frames with
images nobody has tracked yet), when no track is seen in two frames, or when no observed
ray meets the DTM (a DTM in other coordinates, a missing ``dtm.origin_enu_m``). Each is
refused here with one line (:class:`~cdtm_graph.errors.NoConstraintError`), before any
solving; :func:`cdtm_graph.smoother.smooth` calls :func:`check_constraints` first.

Partial coverage (the DTM holds only part of the flight) is not refused: the frames off
the DTM are flagged from :func:`dtm_coverage`, which casts every observation's ray from
given poses (the priors here; a caller can pass the smoothed poses).

No file I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cdtm_graph.dtm import Dtm
from cdtm_graph.errors import FlightLogError, NoConstraintError
from cdtm_graph.flightlog import FRAMES_CSV, IMU_CSV, TRACKS_CSV, FlightLog, Tracks
from cdtm_graph.imu import dead_reckoning


@dataclass(frozen=True)
class DtmCoverage:
    """How much of each frame's observed ground the DTM holds, seen from given poses.

    Attributes:
        n_observations: (K,) observations (rows of tracks.csv) per frame.
        n_on_dtm: (K,) of them whose ray from the frame's camera meets the DTM surface.
    """

    n_observations: np.ndarray
    n_on_dtm: np.ndarray

    @property
    def fraction(self) -> np.ndarray:
        """(K,) share of each frame's observations on the DTM; NaN for frames without any."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.n_observations > 0,
                            self.n_on_dtm / np.maximum(self.n_observations, 1), np.nan)

    @property
    def frames_off_dtm(self) -> np.ndarray:
        """(F,) indices of frames with observations of which none meets the DTM."""
        return np.flatnonzero((self.n_observations > 0) & (self.n_on_dtm == 0))


def dtm_coverage(flight: FlightLog, dtm: Dtm, world_T_body: np.ndarray,
                 frames: np.ndarray | None = None) -> DtmCoverage:
    """Cast each observation's ray from its frame's camera into the DTM.

    Args:
        flight: the log (its tracks, camera and mounting).
        dtm: the terrain.
        world_T_body: (K, 4, 4) body poses at the frames (priors, or a smoothed estimate).
        frames: only these frame indices (the others count zero), or None for all.

    Returns:
        Per-frame counts; all zero without tracks.
    """
    k = len(flight.frames)
    n_obs = np.zeros(k, dtype=np.int64)
    n_hit = np.zeros(k, dtype=np.int64)
    tracks = flight.tracks
    if tracks is None or len(tracks) == 0:
        return DtmCoverage(n_obs, n_hit)
    rows = (np.arange(len(tracks)) if frames is None
            else np.flatnonzero(np.isin(tracks.frame, frames)))
    frame = tracks.frame[rows]
    cam = flight.config.camera
    q_cam = cam.camera.pixels_to_rays(tracks.uv_px[rows])  # (M, 3), NaN where not invertible
    world_T_cam = np.asarray(world_T_body)[frame] @ cam.body_T_cam  # (M, 4, 4)
    directions = np.einsum("mij,mj->mi", world_T_cam[:, :3, :3], q_cam)
    hits = dtm.raycast(world_T_cam[:, :3, 3], directions).hit
    np.add.at(n_obs, frame, 1)
    np.add.at(n_hit, frame, hits.astype(np.int64))
    return DtmCoverage(n_obs, n_hit)


def prior_poses(flight: FlightLog) -> tuple[np.ndarray, str]:
    """(K, 4, 4) body poses known before smoothing and where they come from: nav.csv if
    the log has one, else IMU dead reckoning from the initial state."""
    if flight.nav is not None:
        return flight.nav.world_T_body, "nav.csv"
    free = dead_reckoning(flight.config, flight.imu, flight.frames.t_ns)
    return free.world_T_body, "IMU dead reckoning from initial_state"


def check_imu_span(flight: FlightLog) -> None:
    """Refuse frames outside the IMU's samples: every frame interval is integrated from
    them, and a clock mismatch (a camera stamp on another epoch, a wrong
    ``camera.time_offset_s``) would otherwise surface as a solver error without the file.

    Raises:
        FlightLogError: the first frame outside, with both spans (one line).
    """
    t, imu_t = flight.frames.t_ns, flight.imu.t_ns
    if len(t) == 0 or len(imu_t) == 0:
        return
    outside = np.flatnonzero((t < imu_t[0]) | (t > imu_t[-1]))
    if outside.size:
        k = int(outside[0])
        raise FlightLogError(
            f"{flight.root / FRAMES_CSV}: frame {k} at {int(t[k])} ns (on the IMU clock) lies "
            f"outside {IMU_CSV}'s samples, {int(imu_t[0])} to {int(imu_t[-1])} ns; expected "
            "every frame within the IMU's span (one clock: camera.time_offset_s moves the "
            "frames onto the IMU's)")


def check_constraints(flight: FlightLog, dtm: Dtm) -> DtmCoverage:
    """Refuse a log that would give the smoother no camera or DTM constraint at all.

    The DTM test casts the observations of the first observed frame from its prior pose
    (cheap: the usual case ends there); only if none meets the DTM are all frames cast
    from their prior poses (nav.csv, else IMU dead reckoning).

    Returns:
        The coverage the test computed (the first observed frame only, or every frame).

    Raises:
        NoConstraintError: no tracks.csv, no observation in it, no track seen in two
            frames, or no observed ray meets the DTM; the message says which and where.
        FlightLogError: a frame outside the IMU's samples (no interval to it could be
            integrated; :func:`check_imu_span`).
    """
    check_imu_span(flight)
    root = flight.root
    tracks = flight.tracks
    if tracks is None:
        images = sum(1 for image in flight.frames.image if image)
        raise NoConstraintError(
            f"{root}: no {TRACKS_CSV}: {images} frame(s) of {FRAMES_CSV} name images but "
            f"nothing has tracked features in them; expected a {TRACKS_CSV} (run `cdtm "
            f"track {root}` first): without tracks the result would be IMU-only")
    if len(tracks) == 0:
        raise NoConstraintError(
            f"{root / TRACKS_CSV}: no observations (no data rows); expected features "
            "tracked over at least two frames: without them the result would be IMU-only")
    rows_a, _ = tracks.pairs()
    if rows_a.size == 0:
        raise NoConstraintError(
            f"{root / TRACKS_CSV}: no track is seen in two frames ({len(tracks)} "
            "observations, each track once); expected tracks over consecutive frames: "
            "without them the result would be IMU-only")
    first = int(tracks.frame[rows_a].min())
    if flight.nav is not None or first == 0:  # a prior pose of that frame without the IMU
        start = (flight.nav.world_T_body if flight.nav is not None else
                 np.broadcast_to(flight.config.initial_state.world_T_body,
                                 (len(flight.frames), 4, 4)))
        quick = dtm_coverage(flight, dtm, start, frames=np.array([first]))
        if quick.n_on_dtm.sum() > 0:
            return quick
    poses, source = prior_poses(flight)
    coverage = dtm_coverage(flight, dtm, poses)
    if coverage.n_on_dtm.sum() > 0:
        return coverage
    raise NoConstraintError(_off_dtm_message(flight, tracks, dtm, poses, source, coverage))


def _off_dtm_message(flight: FlightLog, tracks: Tracks, dtm: Dtm, poses: np.ndarray,
                     source: str, coverage: DtmCoverage) -> str:
    xmin, xmax, ymin, ymax = dtm.bounds
    zmin, zmax = float(np.nanmin(dtm.elevation)), float(np.nanmax(dtm.elevation))
    p = poses[:, :3, 3]
    x0, y0, z0 = (float(v) for v in p[0])
    inside = (xmin <= p[:, 0]) & (p[:, 0] <= xmax) & (ymin <= p[:, 1]) & (p[:, 1] <= ymax)
    span = (f"the DTM spans x {xmin:.6g}..{xmax:.6g} m, y {ymin:.6g}..{ymax:.6g} m, "
            f"heights {zmin:.6g}..{zmax:.6g} m (world, after dtm.origin_enu_m)")
    where = (f"the flight goes from x {x0:.6g}, y {y0:.6g}, z {z0:.6g} m to "
             f"x {p[-1, 0]:.6g}, y {p[-1, 1]:.6g} m")
    camera = flight.config.camera.camera
    undistortable = np.isfinite(camera.pixels_to_rays(tracks.uv_px)).all(axis=1)
    if not undistortable.any():
        hint = ("no observed pixel can be undistorted: are camera.intrinsics and "
                "camera.distortion_coeffs right?")
    elif not inside.any():
        hint = ("the DTM is elsewhere: are dtm.origin_enu_m and the DTM's coordinates "
                "right (a projected DTM needs the world origin subtracted)?")
    elif np.all(p[inside, 2] < zmin):
        hint = "the aircraft is below the terrain: are the heights in the same unit and datum?"
    else:
        hint = ("the rays miss the terrain: does camera.body_T_cam point the camera down, "
                "and is the initial attitude right?")
    n = int(coverage.n_observations.sum())
    return (f"{flight.root}: no observed ray meets the DTM ({n} observations cast from "
            f"poses of {source}): {span}; {where}; {hint} Without the DTM the result would "
            "be IMU-only")
