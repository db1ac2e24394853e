"""Building the factor graph of a flight log: priors, IMU preintegration, C-DTM factors.

Each builder returns its own factors; the smoothers merge them. Keys (DESIGN.md):
``X(k)`` Pose3 ``world_T_body`` at frame k, ``V(k)`` world velocity, ``B(k)``
``imuBias.ConstantBias`` ([accel, gyro]).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

from cdtm_graph.camera import PinholeCamera
from cdtm_graph.dtm import Dtm
from cdtm_graph.errors import SolverError
from cdtm_graph.flightlog import FlightConfig, InitialState, Tracks
from cdtm_graph.imu import ImuNoise, SampleHold, integrate_interval, preintegration_params
from factors import CdtmPairFactor, FeatureNoise, PairFeatures, PlaneMode, RobustKernel


@dataclass(frozen=True)
class GraphSettings:
    """How the graph is built.

    Attributes:
        plane_mode: REINTERSECT (default) casts each feature's ray again at every
            linearization, so drifted initial guesses and hills are handled; FIXED
            keeps the planes of the initial guess (the paper).
        robust: per-feature M-estimator; ``robust_threshold`` in whitened units
            (``None``: the kernel's 95%-efficiency default).
        imu_hold: which interval an IMU sample stands for (see :mod:`cdtm_graph.imu`);
            MIDPOINT is second-order accurate for instantaneous samples.
        first_observation_noise: also count the pixel noise of the earlier observation
            ``q_a`` (off by default, as the paper's eq. 22). Along a track every
            observation is ``q_b`` of one pair and ``q_a`` of the next, so counting it in
            both, as independent noise, counts it twice: on simulated logs that made the
            position ANEES 1.25 instead of 1.9 (3 expected) and the pose ANEES 3.2
            instead of 5.3 (6 expected).
    """

    plane_mode: PlaneMode = PlaneMode.REINTERSECT
    robust: RobustKernel = RobustKernel.NONE
    robust_threshold: float | None = None
    imu_hold: SampleHold = SampleHold.MIDPOINT
    first_observation_noise: bool = False
    shared_dtm_error: bool = True


def dtm_ray_caster(dtm: Dtm):
    """The factor's ``RayCaster`` for a DTM (:meth:`Dtm.tangent_planes`)."""
    return dtm.tangent_planes


def feature_noise(config: FlightConfig, dtm: Dtm, settings: GraphSettings) -> FeatureNoise:
    """The data noise of the log's features (eqs. 21-26) in normalized image units."""
    cam = config.camera
    sigma_q = cam.camera.sigma_normalized(cam.pixel_sigma_px)
    sigma_h = config.dtm.sigma_h_m if config.dtm.sigma_h_m is not None else dtm.sigma_h()
    return FeatureNoise(sigma_q, sigma_h, sigma_q if settings.first_observation_noise else None)


def imu_noise(config: FlightConfig) -> ImuNoise:
    imu = config.imu
    return ImuNoise(imu.gyroscope_noise_density, imu.accelerometer_noise_density,
                    imu.gyroscope_random_walk, imu.accelerometer_random_walk)


def initial_bias(initial: InitialState) -> gtsam.imuBias.ConstantBias:
    return gtsam.imuBias.ConstantBias(np.asarray(initial.accel_bias, dtype=float),
                                      np.asarray(initial.gyro_bias, dtype=float))


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


class ImuArrays(Protocol):
    """IMU samples as arrays (``ImuSamples`` or any object with its three fields)."""

    @property
    def t_ns(self) -> np.ndarray: ...

    @property
    def gyro_radps(self) -> np.ndarray: ...

    @property
    def acc_mps2(self) -> np.ndarray: ...


class ImuIntervals:
    """Preintegrates the IMU over frame intervals of one flight."""

    def __init__(self, config: FlightConfig, imu: ImuArrays, hold: SampleHold):
        self.params = preintegration_params(imu_noise(config), config.gravity_mps2,
                                            config.imu.rate_hz)
        self.imu = imu
        self.hold = hold

    def preintegrate(self, t0_ns: int, t1_ns: int,
                     bias: gtsam.imuBias.ConstantBias) -> gtsam.PreintegratedCombinedMeasurements:
        """IMU over exactly [t0, t1], linearized at ``bias``.

        Raises:
            SolverError: the samples do not cover the interval.
        """
        pim = gtsam.PreintegratedCombinedMeasurements(self.params, bias)
        self.integrate(pim, t0_ns, t1_ns)
        return pim

    def integrate(self, pim: gtsam.PreintegratedCombinedMeasurements, t0_ns: int,
                  t1_ns: int) -> None:
        """Add the IMU over exactly [t0, t1] to ``pim``. Stopping and resuming on a hold
        boundary (:meth:`hold_boundary_before`) feeds GTSAM the same pieces as one call.

        Raises:
            SolverError: the samples do not cover the interval.
        """
        try:  # (it works on the samples near the interval only)
            integrate_interval(pim, self.imu.t_ns, self.imu.gyro_radps, self.imu.acc_mps2,
                               int(t0_ns), int(t1_ns), self.hold)
        except ValueError as exc:
            raise SolverError(f"imu.csv does not cover the frame interval "
                              f"[{t0_ns}, {t1_ns}] ns: {exc}") from None

    def hold_boundary_before(self, limit_ns: int) -> int | None:
        """The latest hold boundary at or before ``limit_ns`` up to which the samples held
        fix every hold piece (the newest sample's own hold needs the sample after it);
        ``None`` if there is none."""
        t = self.imu.t_ns
        n = t.shape[0]
        j = int(np.searchsorted(t, limit_ns, side="right")) - 1  # t[j] <= limit
        if n < 2 or j < 0:
            return None
        if self.hold is SampleHold.ZERO_ORDER:
            return int(t[j])
        # MIDPOINT: boundaries are the integer half-way points between neighbours
        if j + 1 <= n - 1 and t[j] + (t[j + 1] - t[j]) // 2 <= limit_ns:
            return int(t[j] + (t[j + 1] - t[j]) // 2)
        return int(t[j - 1] + (t[j] - t[j - 1]) // 2) if j >= 1 else None


class ImuStream:
    """The preintegration after the newest frame, advanced as IMU samples arrive.

    A live system receives ~100 IMU samples between two frames at 2 fps. Each hold
    piece can be integrated once the sample after it is known, which leaves the frame
    update one or two pieces. Integration only ever stops on hold boundaries, so the
    result is exactly :meth:`ImuIntervals.preintegrate` over the frame interval. If
    samples ran past the next frame time before that frame arrived (camera latency),
    :meth:`finish` redoes the interval from the samples, and from then on the stream
    holds back by that lead so it does not happen again.
    """

    def __init__(self, intervals: ImuIntervals):
        self.intervals = intervals
        self._pim: gtsam.PreintegratedCombinedMeasurements | None = None
        self._bias = gtsam.imuBias.ConstantBias()
        self._t0_ns = self._done_ns = 0
        self.holdback_ns = 0  # how far the IMU has been seen to run ahead of a frame

    def start(self, t0_ns: int, bias: gtsam.imuBias.ConstantBias) -> None:
        """Begin the interval after a frame at ``t0_ns``, linearized at ``bias``."""
        self._pim = gtsam.PreintegratedCombinedMeasurements(self.intervals.params, bias)
        self._bias = bias
        self._t0_ns = self._done_ns = int(t0_ns)

    def advance(self) -> None:
        """Integrate every piece the samples held so far fix (less the hold-back)."""
        t = self.intervals.imu.t_ns
        if self._pim is None or t.shape[0] < 2 or t[0] > self._done_ns:
            return  # nothing to do yet, or a gap that finish() will report
        horizon = self.intervals.hold_boundary_before(int(t[-1]) - self.holdback_ns)
        if horizon is not None and horizon > self._done_ns:
            self.intervals.integrate(self._pim, self._done_ns, horizon)
            self._done_ns = horizon

    def finish(self, t1_ns: int) -> gtsam.PreintegratedCombinedMeasurements:
        """The preintegration over [t0, t1], t1 the next frame's time. The stream is
        spent on success only: after an error (samples missing), feed them and retry.

        Raises:
            SolverError: the samples do not cover the interval.
        """
        if self._pim is None:
            raise ValueError("ImuStream.finish before start")
        t1_ns = int(t1_ns)
        if self._done_ns > t1_ns:  # integrated past the frame: redo the interval
            pim = self.intervals.preintegrate(self._t0_ns, t1_ns, self._bias)
            self.holdback_ns = max(self.holdback_ns, int(self.intervals.imu.t_ns[-1]) - t1_ns)
        else:
            pim = self._pim
            if t1_ns > self._done_ns:  # checks everything before it integrates
                self.intervals.integrate(pim, self._done_ns, t1_ns)
        self._pim = None
        return pim


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


@dataclass(frozen=True)
class FramePairObservations:
    """Consecutive observations of tracks between frames a < b (one batched factor).

    Attributes:
        frame_a, frame_b: frame indices.
        q_a, q_b: (n, 3) normalized rays (z = 1).
        track_id: (n,) track ids.
        track_pair_index: (n,) 1-based rank of this pair among its track's pairs.
    """

    frame_a: int
    frame_b: int
    q_a: np.ndarray
    q_b: np.ndarray
    track_id: np.ndarray
    track_pair_index: np.ndarray | None = None


def frame_pair_observations(tracks: Tracks, camera: PinholeCamera) -> list[FramePairObservations]:
    """Group the consecutive observation pairs of every track by frame pair, vectorized.

    Returns:
        One entry per distinct (frame_a, frame_b), sorted by (frame_b, frame_a).
    """
    rays = camera.pixels_to_rays(tracks.uv_px)
    rows_a, rows_b = tracks.pairs()
    fa, fb = tracks.frame[rows_a], tracks.frame[rows_b]
    # rank of each pair within its track, in time order (tracks.pairs() is time-sorted)
    tid = tracks.track_id[rows_a]
    by_track = np.lexsort((fa, tid))
    first = np.r_[True, tid[by_track][1:] != tid[by_track][:-1]]
    starts = np.maximum.accumulate(np.where(first, np.arange(tid.size), 0))
    rank = np.empty(tid.size, dtype=np.int64)
    rank[by_track] = np.arange(tid.size) - starts + 1
    order = np.lexsort((fa, fb))
    rows_a, rows_b, fa, fb, rank = rows_a[order], rows_b[order], fa[order], fb[order], rank[order]
    if fa.size == 0:
        return []
    change = np.flatnonzero((np.diff(fa) != 0) | (np.diff(fb) != 0)) + 1
    starts = np.r_[0, change]
    ends = np.r_[change, fa.size]
    return [FramePairObservations(int(fa[s]), int(fb[s]), rays[rows_a[s:e]], rays[rows_b[s:e]],
                                  tracks.track_id[rows_a[s:e]], rank[s:e])
            for s, e in zip(starts, ends)]


@dataclass
class CdtmBuild:
    """C-DTM factors of a set of frame pairs, with what was dropped."""

    factors: list[CdtmPairFactor] = field(default_factory=list)
    n_features: int = 0
    n_missed: int = 0
    features_per_frame: dict[int, int] = field(default_factory=dict)



def cdtm_factors(
    pairs: Sequence[FramePairObservations],
    world_T_body: dict[int, np.ndarray] | Sequence[np.ndarray],
    body_T_cam: np.ndarray,
    dtm: Dtm,
    noise: FeatureNoise,
    settings: GraphSettings,
) -> CdtmBuild:
    """One batched C-DTM factor per frame pair, planes cast from the current pose guesses.

    Args:
        pairs: observations grouped by frame pair.
        world_T_body: current guess of every frame's body pose (index -> (4, 4)).
        body_T_cam: (4, 4) camera mounting.
        dtm: the terrain. noise: data noise. settings: plane mode, robust kernel, and
            ``shared_dtm_error``: the j-th pair of a track (``track_pair_index``) has its
            DTM variance multiplied by ``j (j + 1) / 2``, so a track of any length m
            brings ``sum 2 / j (j + 1) = 2 - 2 / (m + 1)`` DTM samples of information (1
            for a single pair, under 2 however long) instead of m. The rule needs only
            the rank, known when the pair arrives, so batch and incremental weigh alike.

    Returns:
        The factors, and the count of features whose ray missed the DTM (dropped).
    """
    raycast = dtm_ray_caster(dtm)
    build = CdtmBuild()
    for pair in pairs:
        wTc_a = world_T_body[pair.frame_a] @ body_T_cam
        wTc_b = world_T_body[pair.frame_b] @ body_T_cam
        ray = pair.q_a @ wTc_a[:3, :3].T
        G_E, N, valid = raycast(wTc_a[:3, 3], ray)
        # A pixel the distortion model cannot undistort has a NaN ray: no ground point.
        valid &= np.isfinite((pair.q_a + pair.q_b).sum(axis=1))
        n_valid = int(valid.sum())
        build.n_missed += int(valid.size - n_valid)
        if n_valid == 0:
            continue
        q_a, q_b, rank = pair.q_a, pair.q_b, pair.track_pair_index
        if n_valid < valid.size:
            q_a, q_b, G_E, N = q_a[valid], q_b[valid], G_E[valid], N[valid]
            rank = None if rank is None else rank[valid]
        scale = None
        if settings.shared_dtm_error and rank is not None:
            j = rank.astype(float)
            scale = j * (j + 1) / 2
        features = PairFeatures.build(wTc_a, wTc_b, q_a, q_b, G_E, N, noise, scale)
        build.factors.append(CdtmPairFactor(
            X(pair.frame_a), X(pair.frame_b), features, body_T_cam, settings.plane_mode,
            raycast, settings.robust, settings.robust_threshold))
        build.n_features += n_valid
        build.features_per_frame[pair.frame_b] = (
            build.features_per_frame.get(pair.frame_b, 0) + n_valid)
    return build


def chi2_2dof_quantile(p: float) -> float:
    """The p-quantile of chi-square with 2 degrees of freedom: ``-2 ln(1 - p)``."""
    if not 0.0 < p < 1.0:
        raise ValueError(f"gate probability {p}: expected 0 < p < 1")
    return float(-2.0 * np.log1p(-p))


def innovation_mahalanobis(e: np.ndarray, H_a: np.ndarray, H_b: np.ndarray, P: np.ndarray,
                           R: np.ndarray | None = None) -> np.ndarray:
    """Squared Mahalanobis distance of each feature's innovation, (n,).

    ``d_i = e_i^T S_i^-1 e_i`` with ``S_i = R_i + H_i P H_i^T``: ``e`` (n, 2) are the
    whitened residuals, ``R`` (n, 2, 2) their measurement covariance in the same whitened
    coordinates (the identity if ``None``) and ``H_i = [H_a,i H_b,i]`` (n, 2, 12) maps the
    joint tangent of ``(X(a), X(b))``, whose prior covariance is ``P`` (12, 12), into the
    residual. Chi-square with 2 degrees of freedom for an inlier whose prior is honest.
    """
    H = np.concatenate([H_a, H_b], axis=2)
    S = H @ P @ np.swapaxes(H, 1, 2) + (np.eye(2) if R is None else R)
    return np.einsum("ni,ni->n", e, np.linalg.solve(S, e[..., None])[..., 0])


#: Inlier gate without a robust kernel: chi-square with 2 dof, 99.9%.
CHI2_2DOF_999 = chi2_2dof_quantile(0.999)


def count_outliers(factors: Sequence[CdtmPairFactor],
                   world_T_body: Sequence[np.ndarray] | np.ndarray,
                   n_frames: int) -> tuple[int, np.ndarray]:
    """Features whose whitened residual fails the chi-square(2) 99.9% gate at given poses.

    The same gate whatever the robust kernel (the kernel decides the weighting; a
    Huber threshold of 1.345 would call 40% of Gaussian inliers outliers).

    Returns:
        The total and the count per frame (by the pair's later frame), (K,).
    """
    per_frame = np.zeros(n_frames, dtype=int)
    for f in factors:
        a = int(gtsam.Symbol(f.key_a).index())
        b = int(gtsam.Symbol(f.key_b).index())
        r2 = np.sum(f.whitened_residuals(world_T_body[a], world_T_body[b]) ** 2, axis=1)
        per_frame[b] += int(np.count_nonzero(r2 > CHI2_2DOF_999))
    return int(per_frame.sum()), per_frame


_SYMBOL = re.compile(r"Symbol:\s*([a-zA-Z])(\d+)")


def explain_indeterminant(exc: RuntimeError) -> SolverError:
    """Turn GTSAM's 'indeterminant system near variable ...' into one clear line."""
    text = " ".join(str(exc).split())
    match = _SYMBOL.search(text)
    if not match:
        return SolverError(f"GTSAM could not solve the system: {text}")
    char, index = match.group(1).upper(), int(match.group(2))
    cause = {
        "X": "the pose is unobservable: no C-DTM features near this frame, flat terrain "
             "under it, or an IMU gap",
        "V": "the velocity is unobservable: check the IMU samples around this frame",
        "B": "the IMU bias is unobservable: check the IMU samples and the bias priors",
    }.get(char, "check the inputs around this variable")
    return SolverError(f"indeterminant system near {char}({index}): {cause}")


def navstate_predict(pim: gtsam.PreintegratedCombinedMeasurements, world_T_body: np.ndarray,
                     velocity: np.ndarray, bias: gtsam.imuBias.ConstantBias
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Propagate a body state over one preintegrated interval."""
    state = pim.predict(gtsam.NavState(gtsam.Pose3(world_T_body), np.asarray(velocity)), bias)
    return state.pose().matrix(), np.asarray(state.velocity())

