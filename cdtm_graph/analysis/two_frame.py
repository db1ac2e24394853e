"""The paper's one-shot problem: both poses of a frame pair from C-DTM factors alone.

Given the matched features of two frames, the DTM and an initial guess, GTSAM
estimates ``world_T_body`` of both frames (twelve unknowns, no prior: the DTM fixes
the gauge), then reports GTSAM's joint marginal, both closed-form covariances of
eq. 13 and the degeneracy verdict of section V.B.
"""

from __future__ import annotations

import enum
import logging
from dataclasses import dataclass, field

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from cdtm_graph.analysis.closed_form import (
    ClosedFormAnalysis,
    Degeneracy,
    DegeneracySettings,
    analyze_pair,
    geometric_degeneracy,
    theta_jacobian_wrt_body_tangents,
)
from cdtm_graph.errors import DegenerateGeometryError, FlightLogError, SolverError
from cdtm_graph.frontend.two_view import FitMethod, estimate_relative_pose, triangulate_depths
from cdtm_graph.geometry import make_pose
from cdtm_graph.graph import dtm_ray_caster
from cdtm_graph.optimizer import levenberg_marquardt
from factors import CdtmPairFactor, FeatureNoise, PairFeatures, PlaneMode, RayCaster, RobustKernel

log = logging.getLogger(__name__)


class TwoFrameInit(enum.Enum):
    """Where :func:`solve_two_frame` starts."""

    GIVEN = "given"        # both poses as guessed by the caller
    EPIPOLAR = "epipolar"  # pose a as guessed, pose b from the matches (epipolar_initial_pose_b)


@dataclass(frozen=True)
class TwoFrameSettings:
    """Settings of :func:`solve_two_frame`.

    Attributes:
        initialization: GIVEN starts from both guessed poses; EPIPOLAR replaces the
            guess of pose b with :func:`epipolar_initial_pose_b` (no prior on the
            ego-motion needed, only a rough pose a).
        plane_mode: REINTERSECT (default) follows the terrain from a far initial
            guess; FIXED is the paper's single linearization of the DTM.
        robust: per-feature M-estimator.
        max_iterations: Levenberg-Marquardt iterations.
        relative_error_tol: LM stops when the error decreases less than this, relatively
            (1e-10: a chi2 change far below the noise, ~1e-5 sigma on the estimate).
        degeneracy: thresholds of the degeneracy verdict.
        raise_on_degenerate: raise :class:`DegenerateGeometryError` (default) rather
            than return a flagged result.
    """

    initialization: TwoFrameInit = TwoFrameInit.GIVEN
    plane_mode: PlaneMode = PlaneMode.REINTERSECT
    robust: RobustKernel = RobustKernel.NONE
    max_iterations: int = 30
    relative_error_tol: float = 1e-10
    degeneracy: DegeneracySettings = field(default_factory=DegeneracySettings)
    raise_on_degenerate: bool = True


@dataclass(frozen=True)
class TwoFrameResult:
    """Estimate and uncertainty of a two-frame C-DTM solve.

    Attributes:
        world_T_body_a, world_T_body_b: (4, 4) estimated body poses.
        covariance_ab: (12, 12) GTSAM's joint marginal of ``(X(a), X(b))``, tangent order
            [omega_a, v_a, omega_b, v_b], right perturbations (body frame).
        sigma_theta_gtsam: (12, 12) that marginal mapped to the paper's theta.
        analysis: closed-form analysis at the estimate (both eq. 13 forms, Sigma_C2, verdict).
        iterations, initial_error, final_error: LM statistics (GTSAM error = chi2 / 2).
        converged: LM stopped on its tolerance (not on the iteration limit) at a finite error.
        n_features: features used; n_missed: features whose ray missed the DTM (dropped).
    """

    world_T_body_a: np.ndarray
    world_T_body_b: np.ndarray
    covariance_ab: np.ndarray
    sigma_theta_gtsam: np.ndarray
    analysis: ClosedFormAnalysis
    iterations: int
    initial_error: float
    final_error: float
    converged: bool
    n_features: int
    n_missed: int

    @property
    def degeneracy(self) -> Degeneracy:
        return self.analysis.degeneracy

    @property
    def degenerate(self) -> bool:
        return self.analysis.degeneracy.degenerate


def _raise_or_log(verdict: Degeneracy, settings: TwoFrameSettings) -> None:
    if verdict.degenerate:
        if settings.raise_on_degenerate:
            raise DegenerateGeometryError(f"degenerate geometry: {verdict.message()}",
                                          verdict.reasons)
        log.debug("degenerate geometry (flagged): %s", verdict.message())


#: Re-intersecting phase: stop once the error decreases by less than this, relatively.
#: The objective has kinks where rays cross DTM cell edges, so LM crawls there; the
#: fixed-plane phase then converges quadratically from a point this close.
_COARSE_RELATIVE_TOL = 1e-3
#: Fixed-plane rounds (planes re-cast at the estimate); one reaches 1e-11 m on noiseless data.
_FIXED_PLANE_ROUNDS = 1


def _optimize(pair: CdtmPairFactor, initial: gtsam.Values,
              settings: TwoFrameSettings) -> tuple[gtsam.Values, int, bool]:
    """Levenberg-Marquardt (GN steps while they reduce the error, damped ones when not: the
    paper's GN-then-LM). With re-intersecting planes, a coarse solve follows the terrain
    from the initial guess, then rounds with the planes fixed at the estimate finish on
    the smooth tangent-plane problem."""
    def solve(factor: CdtmPairFactor, start: gtsam.Values, tol: float):
        graph = gtsam.NonlinearFactorGraph()
        graph.add(factor.factor)
        return levenberg_marquardt(graph, start, settings.max_iterations, tol)

    if pair.plane_mode is PlaneMode.FIXED:
        estimate, stats = solve(pair, initial, settings.relative_error_tol)
        return estimate, stats.iterations, stats.converged
    estimate, stats = solve(pair, initial, _COARSE_RELATIVE_TOL)
    iterations = stats.iterations
    for _ in range(_FIXED_PLANE_ROUNDS):
        fixed = pair.refreshed(estimate.atPose3(X(0)).matrix(), estimate.atPose3(X(1)).matrix())
        fixed.plane_mode = PlaneMode.FIXED
        estimate, stats = solve(fixed, estimate, settings.relative_error_tol)
        iterations += stats.iterations
    return estimate, iterations, stats.converged


@dataclass(frozen=True)
class PairUncertainty:
    """Uncertainty of a frame pair linearized at given poses (no optimization).

    Attributes:
        covariance_ab: (12, 12) GTSAM's joint marginal of ``(X(a), X(b))`` of the
            C-DTM-only two-frame graph ([omega_a, v_a, omega_b, v_b], body frame).
        sigma_theta_gtsam: (12, 12) that marginal mapped to the paper's theta.
        analysis: the closed form (both eq. 13 forms, Sigma_C2, verdict).
    """

    covariance_ab: np.ndarray
    sigma_theta_gtsam: np.ndarray
    analysis: ClosedFormAnalysis


def pair_uncertainty(
    world_T_body_a: np.ndarray, world_T_body_b: np.ndarray, body_T_cam: np.ndarray,
    q_a: np.ndarray, q_b: np.ndarray, G_E: np.ndarray, N: np.ndarray, noise: FeatureNoise,
    settings: TwoFrameSettings | None = None,
) -> PairUncertainty:
    """GTSAM's marginals and the closed form of one frame pair at the given poses.

    Raises:
        DegenerateGeometryError: degenerate geometry, unless
            ``settings.raise_on_degenerate`` is False (then covariances may be inf).
    """
    settings = settings or TwoFrameSettings()
    wTc_a, wTc_b = world_T_body_a @ body_T_cam, world_T_body_b @ body_T_cam
    features = PairFeatures.build(wTc_a, wTc_b, q_a, q_b, G_E, N, noise)
    graph = gtsam.NonlinearFactorGraph()
    # With a robust kernel the marginal carries its weights at the estimate (outliers count
    # for little); the closed form below stays the paper's unweighted-by-kernel analysis.
    graph.add(CdtmPairFactor(X(0), X(1), features, body_T_cam, robust=settings.robust).factor)
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(world_T_body_a))
    values.insert(X(1), gtsam.Pose3(world_T_body_b))
    analysis = analyze_pair(wTc_a, wTc_b, q_a, q_b, G_E, N, noise, settings.degeneracy,
                            Sigma_f=features.Sigma_f)
    _raise_or_log(analysis.degeneracy, settings)
    try:
        cov = gtsam.Marginals(graph, values).jointMarginalCovariance([X(0), X(1)]).fullMatrix()
    except RuntimeError as exc:
        if settings.raise_on_degenerate:
            raise DegenerateGeometryError(
                f"degenerate geometry: GTSAM marginals failed ({str(exc).strip()})",
                ("ill_conditioned",)) from None
        cov = np.full((12, 12), np.inf)  # flagged above: no confident covariance
    H = theta_jacobian_wrt_body_tangents(world_T_body_a, world_T_body_b, body_T_cam)
    with np.errstate(invalid="ignore"):  # a flagged, singular result carries inf
        sigma_theta = H @ cov @ H.T
    return PairUncertainty(cov, sigma_theta, analysis)


#: Epipolar initialization: RANSAC inlier bound in registration sigmas.
EPIPOLAR_THRESHOLD_SIGMAS = 3.0
#: ... and the median parallax (angle between the matched rays, rotation undone) must
#: exceed this many registration sigmas, or the translation direction is noise.
EPIPOLAR_MIN_PARALLAX_SIGMAS = 10.0


def epipolar_initial_pose_b(q_a: np.ndarray, q_b: np.ndarray, raycast: RayCaster,
                            world_T_body_a: np.ndarray, body_T_cam: np.ndarray,
                            noise: FeatureNoise) -> np.ndarray:
    """An initial pose b from the matches alone, given a rough pose a (the paper's conclusion).

    The essential matrix (five-point RANSAC, refined:
    :func:`~cdtm_graph.frontend.two_view.estimate_relative_pose`) gives the ego-motion's
    rotation ``R12`` and the direction of ``p12``; its length comes
    from the DTM: each inlier's ray from camera a is cast into the DTM, and the ratio of
    that depth to the depth triangulated with a unit baseline is the scale (median over
    the inliers). The C-DTM solve then fixes the absolute pose and refines everything.

    Args:
        q_a, q_b: (n, 3) matched normalized rays (z = 1) in frames a and b.
        raycast: the DTM ray caster.
        world_T_body_a: (4, 4) rough pose a.
        body_T_cam: (4, 4) camera mounting.
        noise: the registration noise (sets the RANSAC bound).

    Returns:
        (4, 4) ``world_T_body_b``.

    Raises:
        DegenerateGeometryError: too few matches, too little parallax for a translation
            direction, or no inlier ray meets the DTM in front of both cameras.
    """
    sigma = max(noise.sigma_q_xy)
    fit = estimate_relative_pose(q_a, q_b, sigma, EPIPOLAR_THRESHOLD_SIGMAS)
    if fit.method is not FitMethod.ESSENTIAL or fit.inliers.sum() < 6:
        raise DegenerateGeometryError(
            f"degenerate geometry: {int(np.sum(fit.inliers))} of {q_a.shape[0]} matches fit "
            "an essential matrix; expected enough matches for the epipolar initialization",
            ("few_features",))
    inl = fit.inliers
    rays_a = q_a[inl] / np.linalg.norm(q_a[inl], axis=1, keepdims=True)
    rays_b = q_b[inl] @ fit.a_R_b.T
    rays_b /= np.linalg.norm(rays_b, axis=1, keepdims=True)
    parallax = float(np.median(np.linalg.norm(np.cross(rays_a, rays_b), axis=1)))
    if parallax < EPIPOLAR_MIN_PARALLAX_SIGMAS * sigma:
        raise DegenerateGeometryError(
            f"degenerate geometry: median parallax {parallax:.2e} rad, expected more than "
            f"{EPIPOLAR_MIN_PARALLAX_SIGMAS:g} registration sigmas for the direction of p12",
            ("short_baseline",))
    depth_unit, _ = triangulate_depths(q_a[inl], q_b[inl], fit.a_R_b, fit.a_t_b)
    wTc_a = world_T_body_a @ body_T_cam
    ray = q_a[inl] @ wTc_a[:3, :3].T
    G_E, _, valid = raycast(np.broadcast_to(wTc_a[:3, 3], ray.shape), ray)
    # z-depth along q_a (z = 1): G = p_a + depth * R_a q_a
    depth_dtm = np.einsum("ij,ij->i", G_E - wTc_a[:3, 3], ray) / np.einsum("ij,ij->i", ray, ray)
    ok = valid & (depth_unit > 0) & (depth_dtm > 0)
    if not ok.any():
        raise DegenerateGeometryError(
            "degenerate geometry: no matched ray from the guess of pose a meets the DTM in "
            "front of both cameras; expected a guess of pose a over the DTM", ("ill_conditioned",))
    scale = float(np.median(depth_dtm[ok] / depth_unit[ok]))
    a_T_b = make_pose(fit.a_R_b, scale * fit.a_t_b)
    return wTc_a @ a_T_b @ np.linalg.inv(body_T_cam)


def solve_two_frame(
    q_a: np.ndarray,
    q_b: np.ndarray,
    raycast: RayCaster,
    world_T_body_a: np.ndarray,
    world_T_body_b: np.ndarray | None,
    body_T_cam: np.ndarray,
    noise: FeatureNoise,
    settings: TwoFrameSettings | None = None,
) -> TwoFrameResult:
    """Estimate both poses of a frame pair from C-DTM factors only.

    Args:
        q_a, q_b: (n, 3) normalized rays (z = 1) of the matched features in frames a, b.
        raycast: the DTM ray caster (see :data:`factors.RayCaster`).
        world_T_body_a, world_T_body_b: (4, 4) initial guess (with
            ``TwoFrameInit.EPIPOLAR``, b's is not used and may be None).
        body_T_cam: (4, 4) camera mounting.
        noise: data noise (pixels in normalized units, DTM height).
        settings: solver and degeneracy settings.

    Returns:
        The estimate with GTSAM's marginals and the closed-form analysis.

    Raises:
        DegenerateGeometryError: the geometry cannot fix the poses (unless
            ``settings.raise_on_degenerate`` is False, then the result is flagged).
    """
    settings = settings or TwoFrameSettings()
    if settings.initialization is TwoFrameInit.EPIPOLAR:
        world_T_body_b = epipolar_initial_pose_b(q_a, q_b, raycast, world_T_body_a, body_T_cam,
                                                 noise)
    elif world_T_body_b is None:
        raise ValueError("solve_two_frame: world_T_body_b is needed unless the "
                         "initialization is TwoFrameInit.EPIPOLAR")
    wTc_a = world_T_body_a @ body_T_cam
    wTc_b = world_T_body_b @ body_T_cam
    ray = q_a @ wTc_a[:3, :3].T
    G_E, N, valid = raycast(np.broadcast_to(wTc_a[:3, 3], ray.shape), ray)
    n_missed = int((~valid).sum())
    q_a, q_b, G_E, N = q_a[valid], q_b[valid], G_E[valid], N[valid]
    _raise_or_log(geometric_degeneracy(wTc_a, wTc_b, q_a, G_E, noise.sigma_h_m,
                                       settings.degeneracy), settings)

    features = PairFeatures.build(wTc_a, wTc_b, q_a, q_b, G_E, N, noise)
    pair = CdtmPairFactor(X(0), X(1), features, body_T_cam, settings.plane_mode, raycast,
                          settings.robust)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(pair.factor)
    initial = gtsam.Values()
    initial.insert(X(0), gtsam.Pose3(world_T_body_a))
    initial.insert(X(1), gtsam.Pose3(world_T_body_b))
    initial_error = graph.error(initial)
    try:
        estimate, iterations, lm_converged = _optimize(pair, initial, settings)
    except SolverError as exc:  # indeterminant system: the data cannot fix a direction
        verdict = Degeneracy(("ill_conditioned",), {"ill_conditioned": str(exc)})
        raise DegenerateGeometryError(f"degenerate geometry: {verdict.message()}",
                                      verdict.reasons) from None
    final_error = graph.error(estimate)
    Ta = estimate.atPose3(X(0)).matrix()
    Tb = estimate.atPose3(X(1)).matrix()

    # Linearize the uncertainty at the estimate: planes and noise from the final poses.
    G_E, N = pair.planes(Ta @ body_T_cam)
    unc = pair_uncertainty(Ta, Tb, body_T_cam, q_a, q_b, G_E, N, noise, settings)
    converged = bool(np.isfinite(final_error) and lm_converged)
    return TwoFrameResult(
        world_T_body_a=Ta,
        world_T_body_b=Tb,
        covariance_ab=unc.covariance_ab,
        sigma_theta_gtsam=unc.sigma_theta_gtsam,
        analysis=unc.analysis,
        iterations=iterations,
        initial_error=initial_error,
        final_error=final_error,
        converged=converged,
        n_features=int(q_a.shape[0]),
        n_missed=n_missed,
    )


@dataclass(frozen=True)
class LogPairAnalysis:
    """``cdtm analyze``: the uncertainty of frames a, b of a flight log at given poses."""

    frame_a: int
    frame_b: int
    poses_from: str
    n_features: int
    n_missed: int
    uncertainty: PairUncertainty


def analyze_log_pair(flight, dtm, frame_a: int, frame_b: int, poses_from: str = "groundtruth",
                     ) -> LogPairAnalysis:
    """Linearize the C-DTM problem of two frames of a log at known poses (no solve).

    The features are the tracks seen in both frames; ``G_E`` and ``N`` come from ray
    casting from pose a. The noise is the paper's (``q_a`` exact, eqs. 21-26).

    Args:
        flight: the log. dtm: its terrain.
        frame_a, frame_b: frame indices (rows of frames.csv), a != b.
        poses_from: "groundtruth" (interpolated to the frame times) or "nav".

    Raises:
        FlightLogError: bad frame indices, or the pose source is missing.
    """
    K = len(flight.frames)
    for name, k in (("A", frame_a), ("B", frame_b)):
        if not 0 <= k < K:
            raise FlightLogError(f"{flight.root / 'frames.csv'}: frame {name}={k} does not "
                                 f"exist; expected 0 <= frame < {K}")
    if frame_a == frame_b:
        raise FlightLogError(f"frames A and B are both {frame_a}; expected two different frames")
    states = {"groundtruth": flight.groundtruth, "nav": flight.nav}.get(poses_from)
    if states is None:
        raise FlightLogError(f"{flight.root}: no {poses_from}.csv to take the poses from; "
                             "expected --at groundtruth or --at nav with that file present")
    t_ns = flight.frames.t_ns[[frame_a, frame_b]]
    for name, k, t in (("A", frame_a, t_ns[0]), ("B", frame_b, t_ns[1])):
        if not states.t_ns[0] <= t <= states.t_ns[-1]:
            raise FlightLogError(
                f"{flight.root / (poses_from + '.csv')}: covers {states.t_ns[0] * 1e-9:.3f}-"
                f"{states.t_ns[-1] * 1e-9:.3f} s; frame {name}={k} at {t * 1e-9:.3f} s is "
                "outside it; expected frames within its time range")
    poses = states.interpolate(t_ns).world_T_body
    tracks = flight.tracks
    if tracks is None:
        raise FlightLogError(f"{flight.root / 'tracks.csv'}: missing; expected feature tracks")
    in_a = tracks.frame == frame_a
    in_b = tracks.frame == frame_b
    common, ia, ib = np.intersect1d(tracks.track_id[in_a], tracks.track_id[in_b],
                                    return_indices=True)
    if common.size == 0:
        raise FlightLogError(f"{flight.root / 'tracks.csv'}: frames A={frame_a} and "
                             f"B={frame_b} share no tracked feature; expected two frames that "
                             "see common features")
    camera = flight.config.camera.camera
    q_a = camera.pixels_to_rays(tracks.uv_px[in_a][ia])
    q_b = camera.pixels_to_rays(tracks.uv_px[in_b][ib])
    body_T_cam = flight.config.camera.body_T_cam
    wTc_a = poses[0] @ body_T_cam
    ray = q_a @ wTc_a[:3, :3].T
    G_E, N, valid = dtm_ray_caster(dtm)(np.broadcast_to(wTc_a[:3, 3], ray.shape), ray)
    cam_cfg = flight.config.camera
    sigma_h = flight.config.dtm.sigma_h_m
    sigma_h = dtm.sigma_h() if sigma_h is None else sigma_h
    noise = FeatureNoise(camera.sigma_normalized(cam_cfg.pixel_sigma_px), sigma_h)
    if not valid.any():
        raise FlightLogError(f"frames A={frame_a} and B={frame_b}: none of their "
                             f"{common.size} common features' rays from A hits the DTM; "
                             "expected a pair over the map")
    unc = pair_uncertainty(poses[0], poses[1], body_T_cam, q_a[valid], q_b[valid], G_E[valid],
                           N[valid], noise, TwoFrameSettings(raise_on_degenerate=False))
    return LogPairAnalysis(frame_a, frame_b, poses_from, int(valid.sum()),
                           int((~valid).sum()), unc)
