"""Smoothing a flight log: batch Levenberg-Marquardt and incremental iSAM2.

``smooth(log, dtm, settings) -> SmootherResult`` does no file I/O. The batch solver
drives Levenberg-Marquardt from Python over ``graph.linearize(values)``: GTSAM's own
optimizers hand every ``CustomFactor`` call a fresh copy of all values, which makes
an iteration quadratic in the flight length (DESIGN.md, "Performance notes").

:class:`IncrementalSmoother` takes one frame at a time (its IMU samples and tracks)
and returns the current estimate and the newest frame's covariance, with iSAM2
underneath, or GTSAM's incremental fixed-lag smoother when a lag is given. Its pass
over a log is also the batch initializer when the log has no ``nav.csv``.
"""

from __future__ import annotations

import enum
import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from typing import Any, NamedTuple

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

from cdtm_graph.dtm import Dtm
from cdtm_graph.errors import FlightLogError
from cdtm_graph.flightlog import FlightConfig, FlightLog, ImuSamples
from cdtm_graph.gating import chi2_2dof_quantile, count_outliers, innovation_mahalanobis
from cdtm_graph.geometry import so3_log
from cdtm_graph.graph import (
    GraphSettings,
    cdtm_factors,
    feature_noise,
    imu_factor,
    insert_state,
    prior_factors,
)
from cdtm_graph.imu import ImuIntervals, ImuStream, initial_bias, navstate_predict
from cdtm_graph.optimizer import LinearSolver, explain_indeterminant, levenberg_marquardt
from cdtm_graph.preflight import check_constraints
from cdtm_graph.results import (
    GraphCounts,
    SmootherResult,
    SolverStats,
    StateCovariances,
    TrajectoryEstimate,
)
from cdtm_graph.tracks import (
    FramePairObservations,
    TrackTable,
    check_unique,
    frame_pair_observations,
)
from factors import CdtmPairFactor

log = logging.getLogger(__name__)

#: ``progress(done, total)``: called once per frame on long runs.
Progress = Callable[[int, int], None]


class SmootherMode(enum.Enum):
    BATCH = "batch"
    INCREMENTAL = "incremental"


@dataclass(frozen=True)
class SmootherSettings:
    """Settings of a smoothing run.

    Attributes:
        graph: how factors are built (plane mode, robust kernel, IMU hold).
        mode: BATCH (LM over the whole log) or INCREMENTAL (iSAM2, one update per frame).
        max_iterations: LM iterations (batch).
        relative_error_tol: LM stops when the error decreases less than this, relatively.
        lag_s: incremental only: a fixed-lag smoother of this lag (seconds); ``None``
            keeps the full history in iSAM2.
        final_iterations: incremental only: extra iSAM2 updates after the last frame
            so the final estimate reaches the optimum.
        marginals: compute per-frame marginal covariances.
        keep_exit_covariances: fixed lag: keep each frame's pose, velocity and bias
            covariances as it leaves the window (else NaN for frames older than the lag).
        innovation_gate: incremental only: drop each C-DTM feature whose innovation,
            against the prior covariance of its two poses, fails the chi-square(2) gate
            of this probability (e.g. 0.999); ``None`` gates nothing.
    """

    graph: GraphSettings = field(default_factory=GraphSettings)
    mode: SmootherMode = SmootherMode.BATCH
    max_iterations: int = 30
    relative_error_tol: float = 1e-6
    lag_s: float | None = None
    final_iterations: int = 5
    marginals: bool = True
    keep_exit_covariances: bool = True
    innovation_gate: float | None = None

    def as_dict(self) -> dict:
        d = asdict(self)
        d["mode"] = self.mode.value
        d["graph"] = {k: (v.value if isinstance(v, enum.Enum) else v)
                      for k, v in asdict(self.graph).items()}
        return d


# -- batch ---------------------------------------------------------------------------


def _estimate_from_values(values: gtsam.Values, t_ns: np.ndarray) -> TrajectoryEstimate:
    K = t_ns.shape[0]
    poses = np.stack([values.atPose3(X(k)).matrix() for k in range(K)])
    vel = np.stack([values.atVector(V(k)) for k in range(K)])
    biases = [values.atConstantBias(B(k)) for k in range(K)]
    return TrajectoryEstimate(
        t_ns=np.asarray(t_ns, dtype=np.int64), world_T_body=poses, velocity_mps=vel,
        gyro_bias=np.stack([b.gyroscope() for b in biases]),
        accel_bias=np.stack([b.accelerometer() for b in biases]))


def _marginals(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
               K: int, qr_only: bool = False) -> StateCovariances:
    """Per-frame marginals from a Bayes tree of the graph linearized at ``values``.

    Cholesky first (as ``gtsam.Marginals``); where it declares the system indeterminant,
    which happens on these wide-range systems (information from ~1e-4 for the pose prior
    to ~1e10 for the bias random walk), QR, which does not square the condition number.
    """
    linear = graph.linearize(values)
    for qr in (True,) if qr_only else (False, True):
        try:
            tree = (linear.eliminateMultifrontal(function=gtsam.EliminateQR) if qr
                    else linear.eliminateMultifrontal())

            def cov(key: int, tree=tree, qr=qr) -> np.ndarray:
                marginal = (tree.marginalFactor(key, gtsam.EliminateQR) if qr
                            else tree.marginalFactor(key))
                # information() includes the conditional's noise model (QR leaves sigmas)
                return np.linalg.inv(marginal.information())

            pose = np.stack([cov(X(k)) for k in range(K)])
            vel = np.stack([cov(V(k)) for k in range(K)])
            bias = np.stack([cov(B(k)) for k in range(K)])
            return StateCovariances(pose, vel, bias)
        except RuntimeError as exc:
            error = exc
    raise explain_indeterminant(error) from None


@dataclass
class _LogGraph:
    """Everything the batch solver builds from a log."""

    base: gtsam.NonlinearFactorGraph  # priors and IMU factors
    values: gtsam.Values
    counts: GraphCounts
    cdtm: list  # CdtmPairFactor

    @property
    def graph(self) -> gtsam.NonlinearFactorGraph:
        graph = gtsam.NonlinearFactorGraph()
        graph.push_back(self.base)
        for f in self.cdtm:
            graph.add(f.factor)
        return graph

    def refresh_noise(self, values: gtsam.Values) -> None:
        """Re-linearize every C-DTM factor's planes and noise at ``values``."""
        poses = {k: values.atPose3(X(k)).matrix() for k in range(self.counts.n_frames)}
        self.cdtm = [f.refreshed(poses[int(gtsam.Symbol(f.key_a).index())],
                                 poses[int(gtsam.Symbol(f.key_b).index())]) for f in self.cdtm]


def _observation_counts(flight: FlightLog,
                        pairs: list[FramePairObservations]) -> tuple[int, int, int]:
    tracks = flight.tracks
    if tracks is None:
        return 0, 0, 0
    return (int(np.unique(tracks.track_id).size), len(tracks),
            int(sum(p.q_a.shape[0] for p in pairs)))


def _initial_values(flight: FlightLog, dtm: Dtm, settings: SmootherSettings,
                    intervals: ImuIntervals, progress: Progress | None) -> tuple[gtsam.Values, str]:
    """Initial guess: nav.csv if present, else the incremental pass (dead reckoning
    corrected frame by frame)."""
    K = len(flight.frames)
    values = gtsam.Values()
    bias = initial_bias(flight.config.initial_state)
    if flight.nav is not None:
        poses = flight.nav.world_T_body
        for k in range(K):
            insert_state(values, k, poses[k], flight.nav.velocity_mps[k], bias)
        return values, "nav.csv"
    incremental = IncrementalSmoother(flight.config, dtm, settings.graph)
    incremental.run(flight, progress)
    return incremental.values(), "incremental pass"


def build_log_graph(flight: FlightLog, dtm: Dtm, settings: SmootherSettings,
                    initial: gtsam.Values, intervals: ImuIntervals) -> _LogGraph:
    """Priors, IMU factors and C-DTM factors of the whole log, planes cast from ``initial``."""
    K = len(flight.frames)
    t = flight.frames.t_ns
    graph = prior_factors(flight.config.initial_state)
    bias0 = initial_bias(flight.config.initial_state)
    for k in range(K - 1):
        graph.add(imu_factor(k, intervals.preintegrate(int(t[k]), int(t[k + 1]), bias0)))
    pairs = (frame_pair_observations(flight.tracks, flight.config.camera.camera)
             if flight.tracks is not None else [])
    poses = [initial.atPose3(X(k)).matrix() for k in range(K)]
    build = cdtm_factors(pairs, poses, flight.config.camera.body_T_cam, dtm,
                         feature_noise(flight.config, dtm, settings.graph), settings.graph)
    n_tracks, n_obs, n_pairs = _observation_counts(flight, pairs)
    per_frame = np.zeros(K, dtype=int)
    for k, n in build.features_per_frame.items():
        per_frame[k] = n
    counts = GraphCounts(K, n_tracks, n_obs, n_pairs, build.n_features, build.n_missed,
                         len(build.factors), K - 1, per_frame,
                         outliers_per_frame=np.zeros(K, dtype=int),
                         gated_per_frame=np.zeros(K, dtype=int))
    return _LogGraph(graph, initial, counts, build.factors)


def _frame_flags(counts: GraphCounts) -> dict:
    flags: dict[int, list[str]] = {}
    for k in range(1, counts.n_frames):
        if counts.features_per_frame[k] == 0:
            flags.setdefault(k, []).append("no_features")
    return flags


def smooth(flight: FlightLog, dtm: Dtm, settings: SmootherSettings | None = None,
           progress: Progress | None = None) -> SmootherResult:
    """Smooth a flight log (batch LM, or the incremental smoother's pass).

    Args:
        flight: the log (``read_flightlog``). dtm: its terrain (``load_dtm``).
        settings: solver settings. progress: per-frame callback on long runs.

    Returns:
        Smoothed states, per-frame covariances, statistics and counts.

    Raises:
        SolverError: indeterminant system (names the variable and the likely cause).
        FlightLogError: the log has fewer than two frames.
        NoConstraintError: no camera or DTM constraint at all (``preflight``).
        ValueError: ``innovation_gate`` with the batch smoother.
    """
    settings = settings or SmootherSettings()
    if settings.innovation_gate is not None and settings.mode is not SmootherMode.INCREMENTAL:
        raise ValueError("the innovation gate needs the incremental smoother (a prior "
                         "covariance for each frame as it arrives)")
    if len(flight.frames) < 2:
        raise FlightLogError(f"{flight.root / 'frames.csv'}: {len(flight.frames)} frame(s); "
                             "expected at least 2")
    check_constraints(flight, dtm)  # no camera/DTM constraint at all: refuse, not IMU-only
    if settings.mode is SmootherMode.INCREMENTAL:
        dt_s = float(np.max(np.diff(flight.frames.t_ns))) * 1e-9
        smoother = IncrementalSmoother(flight.config, dtm, settings.graph, lag_s=settings.lag_s,
                                       frame_interval_s=dt_s,
                                       keep_exit_covariances=settings.keep_exit_covariances,
                                       innovation_gate=settings.innovation_gate)
        return smoother.run(flight, progress, final_iterations=settings.final_iterations,
                            settings_dict=settings.as_dict())
    intervals = ImuIntervals(flight.config, flight.imu, settings.graph.imu_hold)
    initial, source = _initial_values(flight, dtm, settings, intervals, progress)
    built = build_log_graph(flight, dtm, settings, initial, intervals)
    solver = LinearSolver()
    values, first = levenberg_marquardt(built.graph, initial, settings.max_iterations,
                                        settings.relative_error_tol, solver=solver)
    # The C-DTM noise (eqs. 19-26) was linearized at the initial guess; evaluate it at the
    # estimate and finish there, so the solution does not depend on the initial guess.
    built.refresh_noise(values)
    graph = built.graph
    values, stats = levenberg_marquardt(graph, values, settings.max_iterations,
                                        settings.relative_error_tol, solver=solver)
    stats = replace(stats, iterations=first.iterations + stats.iterations,
                    initial_error=first.initial_error, time_s=first.time_s + stats.time_s)
    K = len(flight.frames)
    start = time.perf_counter()
    covariances = (_marginals(graph, values, K) if settings.marginals else
                   StateCovariances(np.full((K, 6, 6), np.nan), np.full((K, 3, 3), np.nan),
                                    np.full((K, 6, 6), np.nan)))
    stats = SolverStats(stats.mode, stats.iterations, stats.initial_error, stats.final_error,
                        stats.converged, stats.time_s, time.perf_counter() - start)
    settings_dict = settings.as_dict()
    settings_dict["initial_values"] = source
    estimate = _estimate_from_values(values, flight.frames.t_ns)
    n_out, out_per_frame = count_outliers(built.cdtm, estimate.world_T_body, K)
    counts = replace(built.counts, n_outliers=n_out, outliers_per_frame=out_per_frame)
    return SmootherResult(estimate, covariances, stats, counts, settings_dict,
                          _frame_flags(counts))


# -- incremental ---------------------------------------------------------------------


@dataclass(frozen=True)
class FrameUpdate:
    """What the incremental smoother knows right after a frame.

    Attributes:
        frame: index of the newest frame. t_ns: its time.
        world_T_body: (4, 4) its current estimate. velocity_mps: (3,).
        pose_covariance: (6, 6) its marginal, GTSAM tangent order [rot, trans], body frame.
        n_features: C-DTM features that arrived with it. update_time_s: the update's cost.
        imu_time_s: time spent preintegrating this frame's interval as its IMU samples
            arrived (``add_imu``), before this update.
    """

    frame: int
    t_ns: int
    world_T_body: np.ndarray
    velocity_mps: np.ndarray
    pose_covariance: np.ndarray
    n_features: int
    update_time_s: float
    imu_time_s: float = 0.0


def isam2_params() -> gtsam.ISAM2Params:
    """iSAM2: per-type relinearization thresholds, relinearize every 10th update, QR."""
    params = gtsam.ISAM2Params()
    thresholds = gtsam.ISAM2ThresholdMap()
    # Finer than DESIGN.md's first guess (0.01 rad, 1 m, 0.1 m/s, 1e-3): with metre-level
    # pose sigmas, a 1 m threshold left the final estimate ~0.3 sigma from the batch
    # optimum; these cost ~0.3 ms per frame more.
    thresholds.insert(("x", np.r_[[0.002] * 3, [0.1] * 3]))
    thresholds.insert(("v", np.full(3, 0.02)))
    thresholds.insert(("b", np.full(6, 1e-4)))
    params.setRelinearizeThreshold(thresholds)
    params.relinearizeSkip = 10
    # Cholesky declares the IMU + prior system indeterminant at frame 1 (information
    # spans ~1e-4..1e9 across pose, velocity and bias); QR is stable there.
    params.setFactorization("QR")
    params.cacheLinearizedFactors = True
    params.enablePartialRelinearizationCheck = True
    return params


class _ImuBuffer(NamedTuple):
    """IMU samples already checked (the fields of ``ImuSamples``)."""

    t_ns: np.ndarray
    gyro_radps: np.ndarray
    acc_mps2: np.ndarray


class IncrementalSmoother:
    """Feed one frame at a time; get the current estimate and the newest covariance.

    Example::

        smoother = IncrementalSmoother(flight.config, dtm, imu=flight.imu)
        for k in range(len(flight.frames)):
            update = smoother.add_frame(t_ns[k], track_ids_k, uv_px_k)

    Args:
        config: the log's flight.yaml (camera, IMU noise, initial state).
        dtm: the terrain.
        settings: graph settings.
        lag_s: use GTSAM's ``IncrementalFixedLagSmoother`` with this lag; ``None`` keeps
            the full history in iSAM2.
        imu: IMU samples known up front (a log); otherwise feed them with ``add_imu``.
        frame_interval_s: expected time between frames; with a lag, it lets the smoother
            relinearize less often than every update (still four times per window).
        keep_exit_covariances: with a lag, keep the covariances each frame has when it
            leaves the window (about 1.5 ms per frame; offline runs want them, a live
            system needs only the newest covariance).
        innovation_gate: chi-square(2) gate probability (e.g. 0.999) on each feature's
            innovation against the prior covariance of its two poses (the state after
            the frame's IMU factor, one more update per frame); ``None``: no gate.
    """

    def __init__(self, config: FlightConfig, dtm: Dtm, settings: GraphSettings | None = None,
                 lag_s: float | None = None, imu: ImuSamples | None = None,
                 frame_interval_s: float | None = None, keep_exit_covariances: bool = False,
                 innovation_gate: float | None = None):
        self.config = config
        # A feature's innovation against the prior must pass this chi-square(2) bound.
        self._gate = None if innovation_gate is None else chi2_2dof_quantile(innovation_gate)
        self.dtm = dtm
        self.settings = settings or GraphSettings()
        self.lag_s = lag_s
        self.keep_exit_covariances = keep_exit_covariances
        self._imu: ImuSamples | _ImuBuffer = imu or ImuSamples(
            np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))
        self._intervals = ImuIntervals(config, self._imu, self.settings.imu_hold)
        self._stream = ImuStream(self._intervals)  # the interval after the newest frame
        self._imu_time_s = 0.0  # spent preintegrating samples since the newest frame
        self.imu_times_s: list[float] = []  # ... per frame interval
        self._noise = feature_noise(config, dtm, self.settings)
        self._camera = config.camera.camera
        self._body_T_cam = config.camera.body_T_cam
        self._isam: gtsam.ISAM2 | None = None  # full history
        self._fls: gtsam.IncrementalFixedLagSmoother | None = None  # or a fixed lag
        self._relinearize_skip = 10
        # A gate updates twice per frame (IMU, then the features that pass): relinearize
        # every other update as often, in frames.
        updates_per_frame = 1 if innovation_gate is None else 2
        if lag_s is None:
            params = isam2_params()
            params.relinearizeSkip *= updates_per_frame
            self._relinearize_skip = params.relinearizeSkip
            self._isam = gtsam.ISAM2(params)
        else:
            # The fixed-lag smoother marginalizes states at their linearization point and
            # its update cannot force relinearization: every state must be relinearized
            # well before it leaves the window, so relinearize at least four times per
            # window (every update when the frame interval is not known).
            params = isam2_params()
            params.relinearizeSkip = 1
            if frame_interval_s is not None and frame_interval_s > 0:
                params.relinearizeSkip = int(np.clip(lag_s / frame_interval_s // 4, 1, 10))
            params.relinearizeSkip *= updates_per_frame
            self._relinearize_skip = params.relinearizeSkip
            self._fls = gtsam.IncrementalFixedLagSmoother(lag_s, params)
        self.final_error = float("nan")
        self.converged = False
        self._solver: Any = self._isam if self._fls is None else self._fls
        self._settled = 0  # fixed lag: frames before this one have left the window
        self._left_cov: dict[int, tuple] = {}  # ... and their covariances then (X, V, B)
        self._cdtm: list = []  # every C-DTM factor (outlier count, noise refresh)
        self._cdtm_indices: list[int] = []  # ... their iSAM2 factor slots
        self._n_new_cdtm = 0
        self._t_ns: list[int] = []
        self._poses: dict[int, np.ndarray] = {}  # latest estimate of every frame
        self._velocities: dict[int, np.ndarray] = {}
        self._biases: dict[int, gtsam.imuBias.ConstantBias] = {}
        self._tracks = TrackTable()  # last sighting of every live track
        self._factors_by_frame: dict[int, int] = {}
        self.n_features = 0
        self.n_missed = 0
        self.n_too_old = 0
        self.n_gated = 0
        self._innovation_nis: list[np.ndarray] = []  # squared Mahalanobis distances tested
        self._converging = True  # the newest update moved its frame far from the prediction
        self._gated_by_frame: dict[int, int] = {}
        self.n_cdtm_factors = 0
        self.update_times_s: list[float] = []
        self._pair_count = 0
        self._observations = 0

    # -- input ------------------------------------------------------------------------

    def add_imu(self, imu: ImuSamples) -> None:
        """Append IMU samples (times after the ones already held) as they arrive.

        They are preintegrated at once, as far as they fix the hold pieces, so a frame
        update is left with the last piece or two of its interval. The time this takes
        is kept per frame interval (``imu_times_s``).
        """
        start = time.perf_counter()
        self._append_imu(imu)
        self._stream.advance()
        self._imu_time_s += time.perf_counter() - start

    def _append_imu(self, imu: ImuSamples) -> None:
        old = self._imu
        if old.t_ns.size and imu.t_ns.size and imu.t_ns[0] <= old.t_ns[-1]:
            raise FlightLogError("IMU samples must arrive in increasing time order")
        # Samples before the newest frame's are never needed again (two kept for the
        # holds), so a live feed does not grow without bound.
        keep = 0
        if self._t_ns:
            keep = max(int(np.searchsorted(old.t_ns, self._t_ns[-1], side="right")) - 2, 0)
        # (validated on the way in: a plain tuple of the joined arrays will do)
        self._imu = _ImuBuffer(np.concatenate((old.t_ns[keep:], imu.t_ns)),
                               np.concatenate((old.gyro_radps[keep:], imu.gyro_radps)),
                               np.concatenate((old.acc_mps2[keep:], imu.acc_mps2)))
        self._intervals.imu = self._imu

    def add_frame(self, t_ns: int, track_id: np.ndarray | None = None,
                  uv_px: np.ndarray | None = None, imu: ImuSamples | None = None) -> FrameUpdate:
        """Add the next frame: its time, its tracked features, and new IMU samples.

        Args:
            t_ns: frame time (after the previous frame's).
            track_id: (m,) ids of the features seen in this frame.
            uv_px: (m, 2) their pixels.
            imu: IMU samples since the last call (optional if given at construction).

        Returns:
            The newest frame's estimate and covariance.
        """
        start = time.perf_counter()
        k = len(self._t_ns)
        if k and t_ns <= self._t_ns[-1]:
            raise FlightLogError(f"frame {k}: time {t_ns} ns is not after the previous frame")
        seen: tuple[np.ndarray, np.ndarray] | None = None  # (track ids, pixels)
        if track_id is not None and len(track_id):  # checked before anything changes
            ids = np.asarray(track_id, dtype=np.int64)
            uv = np.asarray(uv_px, dtype=float)
            if ids.ndim != 1 or uv.shape != (ids.size, 2):
                raise FlightLogError(f"frame {k}: {ids.shape} track ids with pixels of "
                                     f"shape {uv.shape}; expected (m,) and (m, 2)")
            check_unique(k, ids)
            seen = ids, uv
        if imu is not None and len(imu):
            # Samples that come with the frame may run past it: held, not yet integrated.
            self._append_imu(imu)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        if k == 0:
            init = self.config.initial_state
            graph.push_back(prior_factors(init, 0))
            pose, bias = init.world_T_body, initial_bias(init)
            vel = np.asarray(init.velocity_mps, float)
        else:
            bias = self._biases[k - 1]  # the stream's linearization point too
            pim = self._stream.finish(int(t_ns))
            graph.add(imu_factor(k - 1, pim))
            pose, vel = navstate_predict(pim, self._poses[k - 1], self._velocities[k - 1], bias)
        insert_state(values, k, pose, vel, bias)
        self._t_ns.append(int(t_ns))
        self._poses[k], self._velocities[k], self._biases[k] = pose, vel, bias
        if self._fls is not None and k:
            self._settle(k)
        n_new = 0
        self._n_new_cdtm = 0
        new_factors: list[CdtmPairFactor] = []
        if seen is not None:
            new_factors = self._add_cdtm(k, *seen)
        if self._gate is not None and new_factors:
            # The prior the innovations are gated against: everything up to this frame's
            # IMU factor. The features that pass go in with a second update. While the
            # solution is still converging from its initial prior (the last update moved
            # its frame far), the linearized test would misjudge good features: all pass.
            self._update(graph, values, k, relinearize=self._converging)
            if self._converging:
                self._settle_prior(k)
            new_factors = self._gated(k, new_factors)
            graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        n_new = self._commit_cdtm(k, new_factors, graph)
        self._update(graph, values, k)
        if self._fls is None and self._n_new_cdtm:
            self._refresh_newest_noise(k, pose)
        # Still converging from a loose prior: the frame's update moved it far.
        self._converging = self._moved_far(k, pose)
        cov = self._marginal(k)
        self._stream.start(int(t_ns), self._biases[k])
        elapsed = time.perf_counter() - start
        self.update_times_s.append(elapsed)
        self.imu_times_s.append(self._imu_time_s)
        self._imu_time_s = 0.0
        return FrameUpdate(k, int(t_ns), self._poses[k], self._velocities[k], cov, n_new,
                           elapsed, self.imu_times_s[-1])

    def _add_cdtm(self, k: int, track_id: np.ndarray, uv_px: np.ndarray) -> list[CdtmPairFactor]:
        """The C-DTM factors frame k's sightings close (counted, not yet in the graph)."""
        q = self._camera.pixels_to_rays(uv_px)
        self._observations += len(track_id)
        # A fixed lag has let go of frames before the window: their pairs are dropped
        # (counted), and tracks last seen there can never pair again.
        oldest = self._settled if self.lag_s is not None else 0
        pairs, n_too_old = self._tracks.add_frame(k, track_id, q, oldest)
        self.n_too_old += n_too_old
        self._pair_count += sum(p.q_a.shape[0] for p in pairs) + n_too_old
        if self.lag_s is not None and len(self._tracks) > 4 * len(track_id):
            self._tracks.forget_before(self._settled)
        for pair in pairs:  # fetch only the poses these planes need
            a = pair.frame_a
            self._poses[a] = self._solver.calculateEstimatePose3(X(a)).matrix()
        build = cdtm_factors(pairs, self._poses, self._body_T_cam, self.dtm, self._noise,
                             self.settings)
        self.n_missed += build.n_missed
        return build.factors

    def _settle_prior(self, k: int) -> None:
        """A few relinearizing Gauss-Newton steps before the gate uses the prior: one
        iSAM2 update is one step, and while the solution converges from its initial prior
        the linearized test would misjudge good features."""
        try:
            for _ in range(self.GATE_SETTLE_UPDATES):
                if self._fls is not None:  # its update cannot force relinearization
                    for _ in range(self._relinearize_skip):
                        self._fls.update()
                else:
                    self._isam2().update(gtsam.NonlinearFactorGraph(), gtsam.Values(), [],
                                         None, None, None, True)
        except RuntimeError as exc:
            raise explain_indeterminant(exc) from None
        self._fetch(k)

    def _gated(self, k: int, factors: list[CdtmPairFactor]) -> list[CdtmPairFactor]:
        """The factors with only the features whose innovation passes the chi-square gate
        against the current (prior) joint covariance of their two poses."""
        isam = self._isam2()
        self._fetch(k)
        # The factors leave the first observation's pixel noise out (each observation is
        # the second of one pair and the first of the next); a fresh innovation has it.
        noise = replace(self._noise, sigma_qa_xy=self._noise.sigma_q_xy)
        # Where the new pose is still uncertain by more than a DTM cell (the first frame
        # under its initial prior), the tangent-plane linearization cannot judge a feature.
        spacing_m = max(abs(self.dtm.dx), abs(self.dtm.dy))
        kept, n_gated = [], 0
        for f in factors:
            a = int(gtsam.Symbol(f.key_a).index())
            self._poses[a] = self._solver.calculateEstimatePose3(f.key_a).matrix()
            try:
                P = isam.jointMarginalCovariance([f.key_a, f.key_b]).fullMatrix()
            except RuntimeError as exc:
                raise explain_indeterminant(exc) from None
            if np.sqrt(np.linalg.eigvalsh(P[9:, 9:]).max()) > spacing_m:
                kept.append(f)  # the DTM plane at the guess means nothing a cell away
                continue
            e, H_a, H_b = f.innovations(self._poses[a], self._poses[k])
            R = f.whitened_noise(self._poses[a], self._poses[k], noise)
            d = innovation_mahalanobis(e, H_a, H_b, P, R)
            self._innovation_nis.append(d)
            passed = d <= self._gate
            n_gated += int(f.features.n - passed.sum())
            if passed.all():
                kept.append(f)
            elif passed.any():
                kept.append(f.with_features(passed))
        self.n_gated += n_gated
        self._gated_by_frame[k] = n_gated
        return kept

    @property
    def innovation_nis(self) -> np.ndarray:
        """Squared Mahalanobis distance of every innovation the gate tested, (n,):
        chi-square(2) (median 1.39, mean 2) when the noise model and the prior are honest."""
        return (np.concatenate(self._innovation_nis) if self._innovation_nis
                else np.zeros(0))

    def _commit_cdtm(self, k: int, factors: list[CdtmPairFactor],
                     graph: gtsam.NonlinearFactorGraph) -> int:
        n_features = sum(f.features.n for f in factors)
        for f in factors:
            graph.add(f.factor)
        self._cdtm.extend(factors)
        self._n_new_cdtm = len(factors)
        self.n_features += n_features
        self.n_cdtm_factors += len(factors)
        self._factors_by_frame[k] = n_features
        return n_features

    def _update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, k: int,
                relinearize: bool = False) -> None:
        """One solver update with frame k's new factors and states; ``relinearize``
        (full history) relinearizes every state that moved past its threshold now."""
        try:
            if self._fls is not None:
                stamps = gtsam.FixedLagSmootherKeyTimestampMap()
                t_s = self._t_ns[k] * 1e-9
                for key in (X(k), V(k), B(k)):
                    stamps.insert((key, t_s))
                self._fls.update(graph, values, stamps)
            else:
                result = self._isam2().update(graph, values, [], None, None, None, relinearize)
                if self._n_new_cdtm:  # the frame's C-DTM factors are the graph's last ones
                    self._cdtm_indices.extend(
                        list(result.getNewFactorsIndices())[-self._n_new_cdtm:])
            # Only the newest state: a full calculateEstimate grows with the flight.
            self._fetch(k)
        except RuntimeError as exc:
            raise explain_indeterminant(exc) from None

    def _settle(self, k: int) -> None:
        """Fixed lag: fetch, for the last time, the frames that frame k's update may
        marginalize (older than the lag, with one frame interval of margin so float
        timestamps cannot race the smoother); they keep that estimate."""
        fls, lag_s = self._fls, self.lag_s
        if fls is None or lag_s is None:
            return
        margin_ns = self._t_ns[k] - self._t_ns[k - 1]
        horizon = self._t_ns[k] - lag_s * 1e9 + margin_ns
        while self._settled < k and self._t_ns[self._settled] < horizon:
            self._fetch(self._settled)
            if self.keep_exit_covariances:  # ~1 ms: marginals deep in the Bayes tree
                j = self._settled
                self._left_cov[j] = tuple(np.asarray(fls.marginalCovariance(key))
                                          for key in (X(j), V(j), B(j)))
            self._settled += 1

    def _isam2(self) -> gtsam.ISAM2:
        """The iSAM2 underneath (the fixed-lag smoother's own, by reference)."""
        if self._fls is not None:
            return self._fls.getISAM2()
        assert self._isam is not None  # one of the two exists from __init__ on
        return self._isam

    def _fetch(self, k: int) -> None:
        """Current estimate of frame k's states."""
        self._poses[k] = self._solver.calculateEstimatePose3(X(k)).matrix()
        self._velocities[k] = np.asarray(self._solver.calculateEstimateVector(V(k)))
        self._biases[k] = self._solver.calculateEstimateConstantBias(B(k))

    def _refresh(self, estimate: gtsam.Values) -> None:
        for key in estimate.keys():
            sym = gtsam.Symbol(key)
            i, c = int(sym.index()), chr(sym.chr())
            if c == "x":
                self._poses[i] = estimate.atPose3(key).matrix()
            elif c == "v":
                self._velocities[i] = np.asarray(estimate.atVector(key))
            elif c == "b":
                self._biases[i] = estimate.atConstantBias(key)

    def _marginal(self, k: int) -> np.ndarray:
        try:
            return np.asarray(self._solver.marginalCovariance(X(k)))
        except RuntimeError as exc:
            raise explain_indeterminant(exc) from None

    # -- results ----------------------------------------------------------------------

    def finalize(self, iterations: int = 5, relative_tol: float = 1e-6) -> bool:
        """Relinearize everything and iterate with no new data, so the estimate reaches the
        optimum (``relinearizeSkip`` otherwise leaves it one step from a stale point).

        Returns:
            Whether it settled: the error stopped decreasing (relatively, by
            ``relative_tol``) within ``CONVERGED_SPREAD`` of the lowest error seen. Near
            the optimum, relinearizing only the states past their thresholds makes the
            error wander by ~1e-5 relative: it stops at the first step that does not gain.
        """
        previous = best = self._current_error()
        done = False
        for _ in range(iterations):
            if self._fls is not None:
                # its update cannot force relinearization: run as many as it skips
                for _ in range(self._relinearize_skip):
                    self._fls.update()
            else:
                self._isam2().update(gtsam.NonlinearFactorGraph(), gtsam.Values(), [], None,
                                     None, None, True)
            error = self._current_error()
            best = min(best, error)
            done = error >= previous * (1.0 - relative_tol)  # no gain left (or a loss)
            previous = error
            if done:
                break
        self._refresh(self._solver.calculateEstimate())
        if self._t_ns:  # more frames may follow: the next interval at the new bias estimate
            self._stream.start(self._t_ns[-1], self._biases[len(self._t_ns) - 1])
            self._stream.advance()
        self.final_error = previous
        self.converged = done and previous <= best * (1.0 + self.CONVERGED_SPREAD)
        return self.converged

    #: Gate, while converging: relinearizing steps before the prior is used.
    GATE_SETTLE_UPDATES = 2

    #: finalize(): a settled error within this relative spread of the lowest one is converged.
    CONVERGED_SPREAD = 1e-4

    #: The newest C-DTM factors are rebuilt once when the update moved their frame this
    #: far from the prediction their noise was linearized at (metres, radians).
    NOISE_REFRESH_POSITION_M = 2.0
    NOISE_REFRESH_ROTATION_RAD = np.radians(0.2)

    def _moved_far(self, k: int, predicted: np.ndarray) -> bool:
        """Whether frame k's estimate is past the refresh thresholds from ``predicted``."""
        moved = np.linalg.inv(predicted) @ self._poses[k]
        return bool(np.linalg.norm(moved[:3, 3]) >= self.NOISE_REFRESH_POSITION_M
                    or np.linalg.norm(so3_log(moved[:3, :3])) >= self.NOISE_REFRESH_ROTATION_RAD)

    def _refresh_newest_noise(self, k: int, predicted: np.ndarray) -> None:
        """Full history: when frame k's update moved it far from its IMU prediction (early
        frames under a loose prior), swap its new C-DTM factors for ones whose planes and
        noise (eqs. 19-26) are linearized at the updated estimate, as the batch smoother
        does at its solution. Only the newest factors change: a local re-elimination."""
        if not self._moved_far(k, predicted):
            return
        n = self._n_new_cdtm
        old, slots = self._cdtm[-n:], self._cdtm_indices[-n:]
        isam = self._isam2()
        refreshed = [f.refreshed(isam.calculateEstimatePose3(f.key_a).matrix(),
                                 self._poses[k]) for f in old]
        graph = gtsam.NonlinearFactorGraph()
        for f in refreshed:
            graph.add(f.factor)
        try:
            result = isam.update(graph, gtsam.Values(), slots)
        except RuntimeError as exc:
            raise explain_indeterminant(exc) from None
        self._cdtm[-n:] = refreshed
        self._cdtm_indices[-n:] = list(result.getNewFactorsIndices())
        self._fetch(k)

    def _current_error(self) -> float:
        factors = (self._fls.getFactors() if self._fls is not None
                   else self._isam2().getFactorsUnsafe())
        return float(factors.error(self._solver.calculateEstimate()))

    def values(self) -> gtsam.Values:
        """Latest estimate of every frame so far (frames out of a lag window keep the
        estimate they had when they left it)."""
        values = gtsam.Values()
        for k in range(len(self._t_ns)):
            insert_state(values, k, self._poses[k], self._velocities[k], self._biases[k])
        return values

    def estimate(self) -> TrajectoryEstimate:
        return _estimate_from_values(self.values(), np.asarray(self._t_ns, dtype=np.int64))

    def covariances(self) -> StateCovariances:
        """Marginals of every frame (full-history iSAM2), or of the frames still in the
        window (fixed lag; older frames keep the covariances they left the window with
        if ``keep_exit_covariances``, else NaN)."""
        K = len(self._t_ns)
        pose = np.full((K, 6, 6), np.nan)
        vel = np.full((K, 3, 3), np.nan)
        bias = np.full((K, 6, 6), np.nan)
        source = self._solver
        current = self._solver.calculateEstimate()
        try:
            for k in range(K):
                if not current.exists(X(k)):
                    if k in self._left_cov:  # as it left the window
                        pose[k], vel[k], bias[k] = self._left_cov[k]
                    continue
                pose[k] = source.marginalCovariance(X(k))
                vel[k] = source.marginalCovariance(V(k))
                bias[k] = source.marginalCovariance(B(k))
        except RuntimeError as exc:
            raise explain_indeterminant(exc) from None
        return StateCovariances(pose, vel, bias)

    def run(self, flight: FlightLog, progress: Progress | None = None, final_iterations: int = 3,
            settings_dict: dict | None = None) -> SmootherResult:
        """Feed a whole log frame by frame; return the result like :func:`smooth`.

        Unless the smoother was given the IMU up front, the log's samples are fed as they
        would arrive live: those before each frame through :meth:`add_imu`, then the
        frame with the sample that closes its interval.
        """
        start = time.perf_counter()
        K = len(flight.frames)
        t_frames = flight.frames.t_ns
        tracks = flight.tracks
        if tracks is not None:
            bounds = np.searchsorted(tracks.frame, np.arange(K + 1))
        imu = flight.imu
        live_imu = self._imu.t_ns.size == 0
        first_after = np.searchsorted(imu.t_ns, t_frames, side="left")  # first >= frame time
        sent = 0

        def samples(a: int, b: int) -> ImuSamples:
            return ImuSamples(imu.t_ns[a:b], imu.gyro_radps[a:b], imu.acc_mps2[a:b])

        for k in range(K):
            frame_imu = None
            if live_imu:
                before = int(first_after[k])
                if before > sent:
                    self.add_imu(samples(sent, before))
                    sent = before
                upto = max(min(before + 1, len(imu)), sent)
                frame_imu, sent = samples(sent, upto), upto
            ids = uv = None
            if tracks is not None:
                rows = slice(bounds[k], bounds[k + 1])
                ids, uv = tracks.track_id[rows], tracks.uv_px[rows]
            self.add_frame(int(t_frames[k]), ids, uv, frame_imu)
            if progress is not None:
                progress(k + 1, K)
        self.finalize(final_iterations)
        elapsed = time.perf_counter() - start
        t0 = time.perf_counter()
        covariances = self.covariances()
        per_frame = np.array([self._factors_by_frame.get(k, 0) for k in range(K)])
        estimate = self.estimate()
        n_out, out_per_frame = count_outliers(self._cdtm, estimate.world_T_body, K)
        gated = np.array([self._gated_by_frame.get(k, 0) for k in range(K)])
        counts = GraphCounts(K, self._tracks.n_tracks, self._observations, self._pair_count,
                             self.n_features, self.n_missed, self.n_cdtm_factors, K - 1, per_frame,
                             n_out, out_per_frame, self.n_gated, gated)
        nis = self.innovation_nis
        stats = SolverStats("incremental" if self.lag_s is None else "fixed_lag", K, float("nan"),
                            self.final_error, self.converged, elapsed, time.perf_counter() - t0,
                            tuple(self.update_times_s), tuple(self.imu_times_s),
                            float(np.median(nis)) if nis.size else float("nan"),
                            float(np.mean(nis)) if nis.size else float("nan"))
        settings = dict(settings_dict or {})
        settings["n_too_old_for_lag"] = self.n_too_old
        return SmootherResult(estimate, covariances, stats, counts, settings,
                              _frame_flags(counts))
