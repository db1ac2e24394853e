"""Building the factor graph of a flight log: priors, IMU preintegration, C-DTM factors.

Each builder returns its own factors; the smoothers merge them. Keys (DESIGN.md):
``X(k)`` Pose3 ``world_T_body`` at frame k, ``V(k)`` world velocity, ``B(k)``
``imuBias.ConstantBias`` ([accel, gyro]).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

from cdtm_graph.dtm import Dtm, grazing_hits
from cdtm_graph.flightlog import CalibrationSigmas, FlightConfig, InitialState
from cdtm_graph.geometry import rigid_motion_to_tangent
from cdtm_graph.imu import GapNoise, SampleHold, initial_bias
from cdtm_graph.results import Rejection, Rejections
from cdtm_graph.robust.clutter import ClutterSettings
from cdtm_graph.robust.epipolar import EpipolarSettings
from cdtm_graph.robust.imu_walk import RandomWalkSettings
from cdtm_graph.robust.map_error import BroadErrorSettings, MapErrorSettings
from cdtm_graph.robust.mismatch import MismatchSettings
from cdtm_graph.tracks import FramePairObservations, first_sightings
from factors import CdtmPairFactor, FeatureNoise, PairFeatures, PlaneMode, RobustKernel
from factors.calibration import CalibrationLink

#: The calibration's prior when flight.yaml gives none: 30 ms of camera-IMU offset, 1 deg
#: of mount rotation per axis, 2% of focal length (a 20 ms offset, a 0.5 deg mount, a 1%
#: focal error sit well within them). Used by the side solve that checks flight.yaml's
#: calibration, and by the online estimate when asked (docs/design.md, "Calibration
#: online": why it is not estimated by default).
DEFAULT_CALIBRATION_SIGMAS = CalibrationSigmas(time_offset_sigma_s=0.03, mount_sigma_deg=1.0,
                                               focal_scale_sigma=0.02)


@dataclass(frozen=True)
class GraphSettings:
    """How the graph is built.

    Attributes:
        plane_mode: REINTERSECT (default) casts each feature's ray again at every
            linearization, so drifted initial guesses and hills are handled; FIXED
            keeps the planes of the initial guess (the paper).
        robust: per-feature M-estimator (default Cauchy, a redescending kernel reached
            from a robust start: the gated incremental pass); ``robust_threshold`` in
            units of one residual's spread (``None``: the kernel's default, ~98% efficient).
            ``NONE`` is plain least squares, for studies.
        imu_hold: which interval an IMU sample stands for (see :mod:`cdtm_graph.imu`);
            MIDPOINT is second-order accurate for instantaneous samples.
        earth_physics: for a log with a geodetic origin, the IMU model of the rotating,
            curved Earth (WGS84 normal gravity along the local vertical, the Earth rate and
            Coriolis; :mod:`cdtm_graph.imu`). False: the flat model (``gravity_mps2``
            along -z, no Earth rate), for comparisons. No effect without an origin.
        imu_gap_noise: the maneuver model whose noise the IMU pieces across a gap get
            (:class:`~cdtm_graph.imu.GapNoise`); None: the sensor's noise only (the
            covariance then claims to know the motion the gap hides).
        first_observation_noise: also count the pixel noise of the earlier observation
            ``q_a`` (off by default, as the paper's eq. 22). Along a track every
            observation is ``q_b`` of one pair and ``q_a`` of the next, so counting it in
            both, as independent noise, counts it twice: on simulated logs that made the
            position ANEES 1.25 instead of 1.9 (3 expected) and the pose ANEES 3.2
            instead of 5.3 (6 expected).
        shared_dtm_error: a track's pairs share its ground point's DTM error
            (:func:`cdtm_factors`).
        epipolar: sightings are paired only where they agree with the epipolar geometry
            of the current relative pose (:mod:`cdtm_graph.robust.epipolar`): wrong matches are
            left out and counted, and their tracks pair across them. ``None``: no check.
        grazing_turn_cells: features whose ray grazes a ridge are dropped and counted
            (:func:`cdtm_graph.dtm.grazing_hits`, the ray turned by this many DTM cells
            at its range). ``None``: no check.
        mismatch: tracks whose triangulated ground point lies off the DTM (terrain the
            map lacks) lose their features (:mod:`cdtm_graph.robust.mismatch`). ``None``: no
            test.
        clutter: with ``mismatch``, the tracks' heights are also seen as a population of
            ground and clutter (forest, towns: :mod:`cdtm_graph.robust.clutter`); the likely
            clutter goes, and what may remain is a considered bias of the frames'
            vertical covariance. ``None``: no such view.
        calibration: prior sigmas of the camera calibration (camera-IMU time offset,
            mount rotation, focal scale: :mod:`cdtm_graph.calibration.online`) when flight.yaml
            gives none (its ``camera.calibration`` wins). With ``calibration_online`` (or
            flight.yaml's block) the batch estimates it; otherwise every mode holds
            flight.yaml's and checks it in a batch side solve
            (:mod:`cdtm_graph.calibration.check`: ``calibration_suspect``).
            ``None``: held as flight.yaml writes it, unchecked (unless flight.yaml asks).
        calibration_online: the batch estimates the calibration (off by default: on
            short flights the focal scale trades with the height, docs/design.md).
        map_error: after the run, the DTM's height error is estimated from the tracks at
            its estimate; when it exceeds the stated sigma_h beyond chance, the run is
            made again with it (:mod:`cdtm_graph.robust.map_error`). ``None``: sigma_h
            as stated, always.
        imu_random_walk: after the run, the calibration check's first solve tests
            flight.yaml's IMU bias random walks against the bias steps; when the steps
            exceed them beyond chance through most of the flight (and no bias lies beyond
            its prior), the walks are grown and the run made again with them
            (:mod:`cdtm_graph.robust.imu_walk`). ``None``: the walks as stated, always.
        broad_map_error: with ``map_error``, the map's smooth error across each frame's
            footprint (a hill the DTM lacks) is looked for in the tracks at the final
            estimate (:func:`cdtm_graph.robust.map_error.broad_map_error`), for the verdict
            to name (``broad_map_error``). ``None``: not looked for.
    """

    plane_mode: PlaneMode = PlaneMode.REINTERSECT
    robust: RobustKernel = RobustKernel.CAUCHY
    robust_threshold: float | None = None
    imu_hold: SampleHold = SampleHold.MIDPOINT
    earth_physics: bool = True
    imu_gap_noise: GapNoise | None = field(default_factory=GapNoise)
    first_observation_noise: bool = False
    shared_dtm_error: bool = True
    epipolar: EpipolarSettings | None = field(default_factory=EpipolarSettings)
    grazing_turn_cells: float | None = 1.0
    mismatch: MismatchSettings | None = field(default_factory=MismatchSettings)
    clutter: ClutterSettings | None = field(default_factory=ClutterSettings)
    calibration: CalibrationSigmas | None = field(
        default_factory=lambda: DEFAULT_CALIBRATION_SIGMAS)
    calibration_online: bool = False
    map_error: MapErrorSettings | None = field(default_factory=MapErrorSettings)
    imu_random_walk: RandomWalkSettings | None = field(default_factory=RandomWalkSettings)
    broad_map_error: BroadErrorSettings | None = field(default_factory=BroadErrorSettings)


def dtm_ray_caster(dtm: Dtm):
    """The factor's ``RayCaster`` for a DTM (:meth:`Dtm.tangent_planes`)."""
    return dtm.tangent_planes


def feature_noise(config: FlightConfig, dtm: Dtm, settings: GraphSettings) -> FeatureNoise:
    """The data noise of the log's features (eqs. 21-26) in normalized image units."""
    cam = config.camera
    sigma_q = cam.camera.sigma_normalized(cam.pixel_sigma_px)
    sigma_h = config.dtm.sigma_h_m if config.dtm.sigma_h_m is not None else dtm.sigma_h()
    return FeatureNoise(sigma_q, sigma_h, sigma_q if settings.first_observation_noise else None)


def prior_factors(initial: InitialState, key: int = 0) -> gtsam.NonlinearFactorGraph:
    """Priors on ``X(key)``, ``V(key)``, ``B(key)`` from ``initial_state``."""
    graph = gtsam.NonlinearFactorGraph()
    att = initial.sigma_attitude_rad
    pose_sigmas = np.r_[[att] * 3, [initial.sigma_position_m] * 3]
    graph.add(gtsam.PriorFactorPose3(X(key), gtsam.Pose3(initial.world_T_body),
                                     gtsam.noiseModel.Diagonal.Sigmas(pose_sigmas)))
    velocity_noise = gtsam.noiseModel.Isotropic.Sigma(3, initial.sigma_velocity_mps)
    graph.add(gtsam.PriorFactorVector(V(key), np.asarray(initial.velocity_mps, dtype=float),
                                      velocity_noise))
    bias_sigmas = np.r_[[initial.sigma_accel_bias] * 3, [initial.sigma_gyro_bias] * 3]
    graph.add(gtsam.PriorFactorConstantBias(B(key), initial_bias(initial),
                                            gtsam.noiseModel.Diagonal.Sigmas(bias_sigmas)))
    return graph


def insert_state(values: gtsam.Values, k: int, world_T_body: np.ndarray,
                 velocity_mps: np.ndarray, bias: gtsam.imuBias.ConstantBias) -> None:
    """Insert frame k's ``X(k)``, ``V(k)``, ``B(k)``.

    Keyword arguments select the wrapper's overload by name: positionally, pybind tries
    ~40 overloads of ``Values.insert`` before the bias one (~40 us a call).
    """
    values.insert(j=X(k), pose3=gtsam.Pose3(world_T_body))
    values.insert(j=V(k), vector=np.asarray(velocity_mps, dtype=float))
    values.insert(j=B(k), constant_bias=bias)


def imu_factor(k: int, pim: gtsam.PreintegratedCombinedMeasurements) -> gtsam.CombinedImuFactor:
    """The IMU factor between frames k and k+1."""
    return gtsam.CombinedImuFactor(X(k), V(k), X(k + 1), V(k + 1), B(k), B(k + 1), pim)


@dataclass
class CdtmBuild:
    """C-DTM factors of a set of frame pairs, with what was left out."""

    factors: list[CdtmPairFactor] = field(default_factory=list)
    track_ids: list[np.ndarray] = field(default_factory=list)  # each factor's features'
    n_features: int = 0
    features_per_frame: dict[int, int] = field(default_factory=dict)
    rejections: Rejections = field(default_factory=Rejections)


def cdtm_factors(
    pairs: Sequence[FramePairObservations],
    world_T_body: Mapping[int, np.ndarray] | Sequence[np.ndarray],
    body_T_cam: np.ndarray,
    dtm: Dtm,
    noise: FeatureNoise,
    settings: GraphSettings,
    rejections: Rejections | None = None,
    calibration: tuple[int, np.ndarray] | None = None,
) -> CdtmBuild:
    """One batched C-DTM factor per frame pair, planes cast from the current pose guesses.

    Before a feature enters, it must hit the DTM and not graze a ridge; what fails is
    counted by reason. (Wrong matches are left out earlier, when sightings are paired:
    :class:`cdtm_graph.tracks.SightingPairs`.)

    Args:
        pairs: observations grouped by frame pair.
        world_T_body: current guess of every frame's body pose (index -> (4, 4)).
        body_T_cam: (4, 4) camera mounting.
        dtm: the terrain. noise: data noise. settings: plane mode, robust kernel, checks,
            and ``shared_dtm_error``: the j-th pair of a track (``track_pair_index``) has
            its DTM variance multiplied by ``j (j + 1) / 2``, so a track of any length m
            brings ``sum 2 / j (j + 1) = 2 - 2 / (m + 1)`` DTM samples of information (1
            for a single pair, under 2 however long) instead of m. The rule needs only
            the rank, known when the pair arrives, so batch and incremental weigh alike.
        rejections: where to count what is left out (a new record if None).
        calibration: the calibration variable's key and every frame's body twist (K, 6)
            (:func:`cdtm_graph.calibration.online.body_twists`): each factor then holds the
            calibration as its third variable. None: the nominal calibration.

    Returns:
        The factors and the counts.
    """
    raycast = dtm_ray_caster(dtm)
    build = CdtmBuild(rejections=rejections if rejections is not None else Rejections())
    for pair in pairs:
        wTc_a = world_T_body[pair.frame_a] @ body_T_cam
        wTc_b = world_T_body[pair.frame_b] @ body_T_cam
        k = pair.frame_b
        ray = pair.q_a @ wTc_a[:3, :3].T
        G_E, N, valid = raycast(wTc_a[:3, 3], ray)
        # A pixel the distortion model cannot undistort has a NaN ray: no ground point.
        valid &= np.isfinite((pair.q_a + pair.q_b).sum(axis=1))
        build.rejections.add(Rejection.MISSED_DTM, k, int(valid.size - valid.sum()))
        if settings.grazing_turn_cells is not None and valid.any():
            range_m_each = np.linalg.norm(G_E[valid] - wTc_a[:3, 3], axis=1)
            turn = settings.grazing_turn_cells * dtm.grid_spacing_m / range_m_each
            grazing = grazing_hits(dtm, wTc_a[:3, 3], ray[valid], G_E[valid], N[valid], turn)
            build.rejections.add(Rejection.GRAZING, k, int(grazing.sum()))
            valid[np.flatnonzero(valid)[grazing]] = False
        n_valid = int(valid.sum())
        if n_valid == 0:
            continue
        q_a, q_b, rank, ids = pair.q_a, pair.q_b, pair.track_pair_index, pair.track_id
        if n_valid < valid.size:
            q_a, q_b, G_E, N, ids = q_a[valid], q_b[valid], G_E[valid], N[valid], ids[valid]
            rank = None if rank is None else rank[valid]
        scale = None
        if settings.shared_dtm_error and rank is not None:
            j = rank.astype(float)
            scale = j * (j + 1) / 2
        features = PairFeatures.build(wTc_a, wTc_b, q_a, q_b, G_E, N, noise, scale)
        link = None if calibration is None else CalibrationLink(
            calibration[0], calibration[1][pair.frame_a], calibration[1][k])
        build.factors.append(CdtmPairFactor(
            X(pair.frame_a), X(k), features, body_T_cam, settings.plane_mode,
            raycast, settings.robust, settings.robust_threshold, link).built_at(wTc_a))
        build.track_ids.append(ids)
        build.n_features += n_valid
        build.features_per_frame[k] = build.features_per_frame.get(k, 0) + n_valid
    return build


def track_observations(factors: Sequence[CdtmPairFactor], track_ids: Sequence[np.ndarray]
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The observations the factors hold, once each: (track id (M,), frame (M,), ray
    (M, 3) in its camera)."""
    ids, frames, rays = [], [], []
    for f, tid in zip(factors, track_ids):
        a = int(gtsam.Symbol(f.key_a).index())
        b = int(gtsam.Symbol(f.key_b).index())
        ids += [tid, tid]
        frames += [np.full(tid.size, a), np.full(tid.size, b)]
        rays += [f.features.q_a, f.features.q_b]
    if not ids:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3))
    track_id, frame, ray = np.concatenate(ids), np.concatenate(frames), np.concatenate(rays)
    first = first_sightings(track_id, frame)
    return track_id[first], frame[first], ray[first]


def without_tracks(factors: Sequence[CdtmPairFactor], track_ids: Sequence[np.ndarray],
                   drop: np.ndarray, reason: Rejection, rejections: Rejections
                   ) -> tuple[list[int], list[CdtmPairFactor | None], list[np.ndarray]]:
    """The factors holding features of the ``drop`` tracks, rebuilt without them.

    Returns:
        The indices of the changed factors, their replacements (``None`` where no
        feature is left) and the replacements' track ids; the dropped features are
        counted for ``reason`` by the pair's later frame.
    """
    changed: list[int] = []
    replacements: list[CdtmPairFactor | None] = []
    kept_ids: list[np.ndarray] = []
    if not track_ids or drop.size == 0:
        return changed, replacements, kept_ids
    # one test over every feature (a flight's factors one by one cost more than the rest)
    sizes = np.array([tid.size for tid in track_ids])
    hit_all = np.isin(np.concatenate(track_ids), drop)
    n_hit = np.bincount(np.repeat(np.arange(sizes.size), sizes), weights=hit_all,
                        minlength=sizes.size)
    ends = np.cumsum(sizes)
    for i in np.flatnonzero(n_hit).tolist():
        f, tid = factors[i], track_ids[i]
        hit = hit_all[ends[i] - sizes[i]:ends[i]]
        rejections.add(reason, int(gtsam.Symbol(f.key_b).index()), int(n_hit[i]))
        changed.append(i)
        replacements.append(f.with_features(~hit) if not hit.all() else None)
        kept_ids.append(tid[~hit])
    return changed, replacements, kept_ids


def cdtm_information(factors: Sequence[CdtmPairFactor], world_T_body: Callable[[int], np.ndarray],
                     n_frames: int) -> np.ndarray:
    """(K, 6, 6) what the C-DTM features ending at each frame say about where the aircraft
    is (``SmootherResult.cdtm_information``), at the given poses.

    Each factor ``(a, b)`` adds, to frame b, the information its whitened, robustly
    weighted rows give a rigid motion of both poses: ``M^T M``, ``M = H_a A_a + H_b A_b``
    with ``A`` from :func:`~cdtm_graph.geometry.rigid_motion_to_tangent` about the body
    position of frame b. Order [rotation, translation], world axes, about that frame's
    body position (:func:`~cdtm_graph.geometry.rigid_motion_transfer` moves it). This is
    the fix the camera and the DTM give, with the relative motion (which the IMU knows
    too) held: over flat ground its horizontal translation and yaw get nothing. The
    per-pose blocks ``H_b^T H_b`` cannot show that: they hold the other pose, so they carry
    the ego-motion the optical flow gives over any terrain (a 25-frame flight over flat
    ground had horizontal eigenvalues 1.3-2.7 against 1.6-2.9 over 300 m of relief).
    """
    info = np.zeros((n_frames, 6, 6))
    for f in factors:
        a = int(gtsam.Symbol(f.key_a).index())
        b = int(gtsam.Symbol(f.key_b).index())
        pose_a, pose_b = world_T_body(a), world_T_body(b)
        _, H_a, H_b = f.evaluate(pose_a, pose_b)
        centre = pose_b[:3, 3]
        M = (H_a.reshape(-1, 6) @ rigid_motion_to_tangent(pose_a, centre)
             + H_b.reshape(-1, 6) @ rigid_motion_to_tangent(pose_b, centre))
        info[b] += M.T @ M
    return info
