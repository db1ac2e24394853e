"""Two-view epipolar geometry on camera rays: verification of matches, relative pose.

Rays are camera-frame directions of matched features (any scale; ``z = 1`` normalized
points as :meth:`~cdtm_graph.camera.PinholeCamera.pixels_to_rays` gives them will do).
The relative pose of camera b in camera a is ``a_R_b`` (rotation) and ``a_t_b`` (the
direction of b's centre in a, unit length): a ground point ``X_a = a_R_b X_b + s a_t_b``.
The epipolar constraint is ``det(f_a, a_t_b, a_R_b f_b) = 0``.

Two robust fits, both RANSAC:

* :func:`fit_translation_given_rotation`: the rotation is known (an IMU's preintegrated
  gyro), only the translation direction is fitted. Each match says ``t . n_i = 0`` with
  ``n_i = (R f_b) x f_a``, so two matches give a hypothesis ``t = n_i x n_j``: a
  two-point minimal sample, many fewer draws than the five-point solver needs for the
  same confidence, and no planar-scene ambiguity.
* :func:`fit_essential`: nothing is known; OpenCV's five-point solver in RANSAC
  (``cv2.findEssentialMat``), then of the four poses the matrix holds the one keeping
  the most matches in front of both cameras.

Residuals are angles (radians); multiplied by the focal length they are pixels. With the
rotation given, the larger of the two rays' angular distances from the epipolar plane of
the fitted pose (:func:`epipolar_residual_rad`); with the five-point fit, sqrt(2) times
the Sampson distance from the fitted matrix (:func:`sampson_distance_rad`), which holds
when the rays are calibrated only roughly. Both are, to first order, the distance of a
match from its epipolar line in one image when the other image's point is exact: one
bound means the same in both fits.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from cdtm_graph.geometry import so3_exp

__all__ = [
    "EpipolarFit",
    "FitMethod",
    "epipolar_residual_rad",
    "estimate_relative_pose",
    "fit_essential",
    "fit_translation_given_rotation",
    "refine_relative_pose",
    "sampson_distance_rad",
    "triangulate_depths",
]

#: Fewest matches a fit is attempted with (the five-point solver needs 5; a handful more
#: keeps one wrong match from defining the model).
MIN_MATCHES = 8

#: A translation hypothesis whose two defining normals are closer to parallel than this
#: (sine of the angle) is ill-defined and skipped.
_MIN_HYPOTHESIS_SINE = 1e-9


class FitMethod(enum.Enum):
    """Which fit produced an :class:`EpipolarFit`."""

    ROTATION_PRIOR = "rotation_prior"  # translation direction only, rotation given
    ESSENTIAL = "essential"            # five-point essential matrix
    NONE = "none"                      # too few matches: nothing fitted, all kept


@dataclass(frozen=True)
class EpipolarFit:
    """Relative pose of camera b in camera a and which matches agree with it.

    Attributes:
        a_R_b: (3, 3) rotation of camera b in camera a.
        a_t_b: (3,) unit direction of b's centre in a (zeros when nothing was fitted).
        inliers: (N,) bool, the matches within the threshold (and in front of both
            cameras where their parallax can tell).
        residual_rad: (N,) epipolar residuals under the fitted pose (NaN: not fitted).
        method: the fit used.
    """

    a_R_b: np.ndarray
    a_t_b: np.ndarray
    inliers: np.ndarray
    residual_rad: np.ndarray
    method: FitMethod

    @property
    def inlier_fraction(self) -> float:
        n = self.inliers.size
        return float(self.inliers.sum()) / n if n else 0.0


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross`` of (..., 3) arrays (broadcast), the same products and differences
    (so the same bits) without its axis handling, which cost more than the arithmetic
    on the tracker's ~150 rays."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _norm(v: np.ndarray, keepdims: bool = False) -> np.ndarray:
    """``np.linalg.norm(v, axis=-1)`` of a real array, by the same sum (the same bits)."""
    return np.sqrt(np.sum(v * v, axis=-1, keepdims=keepdims))  # (np.add.reduce)


def _unit(v: np.ndarray) -> np.ndarray:
    norm = _norm(v, keepdims=True)
    return v / np.where(norm > 0, norm, 1.0)


class _Matches:
    """Matched rays under one rotation, with what every translation hypothesis shares
    (unit rays, their normals, parallax, the triangulation's dot products) computed once:
    the fits ask about several translations per frame pair. The arithmetic of
    :func:`epipolar_residual_rad`, :func:`triangulate_depths` and :func:`_inliers` (which
    call it) is unchanged, so are their bits."""

    def __init__(self, rays_a: np.ndarray, rays_b: np.ndarray, a_R_b: np.ndarray):
        self.fa = np.asarray(rays_a, dtype=float)
        self.fb = np.asarray(rays_b, dtype=float) @ np.asarray(a_R_b, dtype=float).T
        self.unit_a, self.unit_b = _unit(self.fa), _unit(self.fb)
        self.normal = _cross(self.unit_b, self.unit_a)  # t . n = 0 on the epipolar plane
        self.parallax = _norm(self.normal)  # (|f_a x f_b|: the same bits)
        self.aa = np.einsum("ij,ij->i", self.fa, self.fa)
        self.bb = np.einsum("ij,ij->i", self.fb, self.fb)
        self.ab = np.einsum("ij,ij->i", self.fa, self.fb)

    def residual_rad(self, a_t_b: np.ndarray) -> np.ndarray:
        """:func:`epipolar_residual_rad` under the translation ``a_t_b``."""
        t = _unit(np.asarray(a_t_b, dtype=float))
        det = np.abs(np.einsum("ij,ij->i", self.normal, np.broadcast_to(t, self.fa.shape)))
        sine = np.minimum(_norm(_cross(t, self.unit_a)), _norm(_cross(t, self.unit_b)))
        with np.errstate(divide="ignore", invalid="ignore"):
            return det / sine

    def depths(self, a_t_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:func:`triangulate_depths` with the baseline ``a_t_b``."""
        t = np.asarray(a_t_b, dtype=float)
        aa, bb, ab = self.aa, self.bb, self.ab
        ta, tb = self.fa @ t, self.fb @ t
        det = aa * bb - ab * ab
        with np.errstate(divide="ignore", invalid="ignore"):
            good = det > 1e-12 * aa * bb
            la = np.where(good, (bb * ta - ab * tb) / det, np.nan)
            lb = np.where(good, (ab * ta - aa * tb) / det, np.nan)
        return la, lb

    def inliers(self, t: np.ndarray, threshold_rad: float) -> tuple[np.ndarray, np.ndarray]:
        """Residuals and inliers under the translation ``t`` (:func:`_inliers`)."""
        residual = self.residual_rad(t)
        inliers = residual <= threshold_rad
        la, lb = self.depths(t)
        # Depth signs mean something only where the rays are apart by more than the noise.
        behind = (self.parallax > 3.0 * threshold_rad) & ~((la > 0) & (lb > 0))
        return residual, inliers & ~behind


def epipolar_residual_rad(rays_a: np.ndarray, rays_b: np.ndarray, a_R_b: np.ndarray,
                          a_t_b: np.ndarray) -> np.ndarray:
    """Angular distance of each match from its epipolar plane (radians).

    The larger of the angle between ``f_a`` and the plane through ``t`` and ``R f_b``, and
    that between ``R f_b`` and the plane through ``t`` and ``f_a``.

    Args:
        rays_a, rays_b: (N, 3) rays in cameras a and b.
        a_R_b: (3, 3). a_t_b: (3,) translation direction (any length > 0).

    Returns:
        (N,) residuals; ``|det(f_a, t, R f_b)|`` over the two sines, NaN for NaN rays.
    """
    return _Matches(rays_a, rays_b, a_R_b).residual_rad(a_t_b)


def triangulate_depths(rays_a: np.ndarray, rays_b: np.ndarray, a_R_b: np.ndarray,
                       a_t_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint triangulation: ``lambda_a f_a ~ lambda_b R f_b + t`` in least squares.

    Args:
        rays_a, rays_b: (N, 3) rays (their scale sets the depths' unit: with ``z = 1``
            rays the depths are z-depths).
        a_R_b: (3, 3). a_t_b: (3,) the baseline (its length is the unit of the depths).

    Returns:
        ``lambda_a``, ``lambda_b``: (N,) each; NaN where the rays are parallel.
    """
    # Normal equations of [fa, -fb] [la, lb]^T = t, one 2x2 system per match.
    return _Matches(rays_a, rays_b, a_R_b).depths(a_t_b)


def _inliers(rays_a: np.ndarray, rays_b: np.ndarray, a_R_b: np.ndarray, t: np.ndarray,
             threshold_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Residuals and inliers of one pose; matches with parallax behind a camera are out."""
    return _Matches(rays_a, rays_b, a_R_b).inliers(t, threshold_rad)


def fit_translation_given_rotation(rays_a: np.ndarray, rays_b: np.ndarray, a_R_b: np.ndarray,
                                   threshold_rad: float, rng: np.random.Generator,
                                   confidence: float = 0.999,
                                   max_hypotheses: int = 256) -> EpipolarFit:
    """RANSAC over translation directions with the rotation known (two-point samples).

    Hypotheses are drawn in batches and scored together (vectorized); sampling stops when
    the best inlier share so far makes a better model unlikely at ``confidence``. The
    winner is refined by least squares on its inliers (smallest singular vector of their
    ``n_i``) and its sign chosen so that most points lie in front of both cameras.

    When the rotation-compensated rays barely move (no translation to see), every
    hypothesis fits every match and all are kept.

    Args:
        rays_a, rays_b: (N, 3) matched rays.
        a_R_b: (3, 3) the known rotation.
        threshold_rad: inlier bound on :func:`epipolar_residual_rad`.
        rng: draws the samples.
        confidence: RANSAC stopping confidence.
        max_hypotheses: cap on the number of hypotheses.

    Returns:
        The fit (``method`` ROTATION_PRIOR, or NONE with fewer than MIN_MATCHES matches).
    """
    fa = _unit(np.asarray(rays_a, dtype=float))
    fb_in_a = _unit(np.asarray(rays_b, dtype=float) @ np.asarray(a_R_b, dtype=float).T)
    n_matches = fa.shape[0]
    if n_matches < MIN_MATCHES:
        return _nothing_fitted(n_matches, a_R_b)
    normals = _cross(fb_in_a, fa)  # (N, 3); t . n_i = 0 for an exact match
    best_t, best_count = None, -1
    drawn, needed, batch = 0, max_hypotheses, 32
    while drawn < min(needed, max_hypotheses):
        i = rng.integers(0, n_matches, batch)
        j = (i + rng.integers(1, n_matches, batch)) % n_matches
        t = _cross(normals[i], normals[j])
        size = _norm(t)
        scale = _norm(normals[i]) * _norm(normals[j])
        ok = size > _MIN_HYPOTHESIS_SINE * np.maximum(scale, 1e-300)
        drawn += batch
        if not ok.any():
            continue
        t = t[ok] / size[ok, None]
        # residual of every match under every hypothesis: |t . n| / sine(t, ray)
        det = np.abs(t @ normals.T)  # (H, N)
        sine = np.minimum(_norm(_cross(t[:, None, :], fa[None])),
                          _norm(_cross(t[:, None, :], fb_in_a[None])))
        counts = np.sum(det <= threshold_rad * sine, axis=1)
        h = int(np.argmax(counts))
        if counts[h] > best_count:
            best_count, best_t = int(counts[h]), t[h]
            share = best_count / n_matches
            if share >= 1.0:
                needed = drawn
            else:
                needed = math.ceil(math.log(1.0 - confidence)
                                   / math.log(max(1.0 - share * share, 1e-12)))
    if best_t is None:  # every hypothesis degenerate: no translation to see
        residual = np.zeros(n_matches)
        return EpipolarFit(np.asarray(a_R_b, float), np.zeros(3), np.ones(n_matches, bool),
                           residual, FitMethod.ROTATION_PRIOR)
    # Sign first (the hypotheses have none): most consensus points in front of camera a.
    t = best_t
    matches = _Matches(fa, fb_in_a, np.eye(3))
    consensus = matches.residual_rad(t) <= threshold_rad
    la, _ = triangulate_depths(fa[consensus], fb_in_a[consensus], np.eye(3), t)
    if np.sum(la < 0) > np.sum(la > 0):
        t = -t
    residual, inliers = matches.inliers(t, threshold_rad)
    for _ in range(2):  # least-squares refinement on the inliers, then re-score
        if inliers.sum() < 2:
            break
        _, _, vt = np.linalg.svd(normals[inliers], full_matrices=False)
        refined = vt[-1] if vt[-1] @ t >= 0 else -vt[-1]
        r_res, r_in = matches.inliers(refined, threshold_rad)
        if r_in.sum() < inliers.sum():
            break
        t, residual, inliers = refined, r_res, r_in
    return EpipolarFit(np.asarray(a_R_b, float), t, inliers, residual, FitMethod.ROTATION_PRIOR)


def fit_essential(rays_a: np.ndarray, rays_b: np.ndarray, threshold_rad: float,
                  confidence: float = 0.999, max_iterations: int = 1000) -> EpipolarFit:
    """Five-point RANSAC on the essential matrix (OpenCV's USAC), then the pose it holds.

    **Inliers are judged on the matrix OpenCV fitted**, by sqrt(2) times
    :func:`sampson_distance_rad` (to first order the distance from the epipolar line in
    one image, as :func:`epipolar_residual_rad`), not on the pose decomposed from it:
    USAC's final least-squares polish leaves the matrix slightly off the essential
    manifold when the rays are not exactly calibrated (a focal length known to a factor
    of two), and the nearest pose then moved the
    matches by up to 2 px (at 4400 px for a ~2200 px camera it kept 131 of 188 matches
    the matrix fits). Nor is a match dropped for triangulating behind a camera: over a
    narrow field of view with a baseline of ~1 % of the depth the translation direction
    is barely determined (a forward translation and a rotation explain the flow nearly as
    well as the true sideways one), and with it the side a match falls on.

    The pose is the minimal model's (:func:`_pose_in_front`): good for sorting matches.
    With a small baseline over deep terrain a rotation can mimic most of the
    translation's flow; :func:`estimate_relative_pose` resolves that for a pose.

    Args:
        rays_a, rays_b: (N, 3) matched rays with ``z > 0`` (others are outliers).
        threshold_rad: inlier bound on ``sqrt(2)`` times :func:`sampson_distance_rad`
            (RANSAC's too): a pixel bound over the focal length.
        confidence: RANSAC confidence.
        max_iterations: RANSAC iteration cap.

    Returns:
        The fit (``method`` ESSENTIAL, or NONE when there are too few matches or OpenCV
        finds no model); ``residual_rad`` holds sqrt(2) x the Sampson distances (NaN:
        behind the image plane).
    """
    fa = np.asarray(rays_a, dtype=float)
    fb = np.asarray(rays_b, dtype=float)
    n_matches = fa.shape[0]
    front = (fa[:, 2] > 0) & (fb[:, 2] > 0)
    if front.sum() < MIN_MATCHES:
        return _nothing_fitted(n_matches, np.eye(3))
    pa = np.ascontiguousarray(fa[front, :2] / fa[front, 2:])
    pb = np.ascontiguousarray(fb[front, :2] / fb[front, 2:])
    sampson_bound = threshold_rad / math.sqrt(2.0)  # (OpenCV's error is the Sampson distance)
    E, mask = cv2.findEssentialMat(pa, pb, np.eye(3), cv2.USAC_ACCURATE, confidence,
                                   sampson_bound, max_iterations)
    if E is None or E.shape[0] < 3 or mask is None:
        return _nothing_fitted(n_matches, np.eye(3))
    E = E[:3]
    residual = np.full(n_matches, np.nan)
    residual[front] = math.sqrt(2.0) * sampson_distance_rad(E, pa, pb)
    inliers = residual <= threshold_rad  # (NaN: False)
    a_R_b, a_t_b = _pose_in_front(E, fa[inliers], fb[inliers], threshold_rad)
    return EpipolarFit(a_R_b, a_t_b, inliers, residual, FitMethod.ESSENTIAL)


def sampson_distance_rad(E: np.ndarray, pa: np.ndarray, pb: np.ndarray) -> np.ndarray:
    """Sampson distance of matches from an essential matrix, on the normalized plane.

    The first-order distance of the match ``(pa, pb)`` (4-vector) from the variety
    ``pb^T E pa = 0``: ``|pb^T E pa| / ||(E pa)_xy, (E^T pb)_xy||``, OpenCV's own error for
    ``findEssentialMat``. On the ``z = 1`` plane, so an angle near the optical axis; times
    the focal length, pixels (split between the two images).

    Args:
        E: (3, 3), ``pb^T E pa = 0`` (``cv2.findEssentialMat(pa, pb, ...)``'s).
        pa, pb: (N, 2) normalized points.

    Returns:
        (N,) distances.
    """
    xa = np.column_stack([pa, np.ones(len(pa))])
    xb = np.column_stack([pb, np.ones(len(pb))])
    e_a = xa @ E.T  # E pa: lines in b
    e_b = xb @ E    # E^T pb: lines in a
    algebraic = np.abs(np.einsum("ij,ij->i", xb, e_a))
    norm = np.sqrt(e_a[:, 0] ** 2 + e_a[:, 1] ** 2 + e_b[:, 0] ** 2 + e_b[:, 1] ** 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        return algebraic / norm


def _pose_in_front(E: np.ndarray, fa: np.ndarray, fb: np.ndarray,
                   threshold_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """The pose of the four an essential matrix holds that keeps the most matches.

    ``E`` maps rays of a to epipolar lines in b (``f_b^T E f_a = 0``). Each of the four
    poses of ``cv2.decomposeEssentialMat`` (two rotations, two translation signs) is
    scored by :func:`_inliers` (within ``threshold_rad`` and, where the parallax can
    tell, in front of both cameras); ties (no parallax anywhere) go to the rotation
    that turns b's rays closest to a's. Not ``cv2.recoverPose``: it counts a point in
    front only nearer than 50 baselines, so over a scene farther than that (a city from
    2.8 km, 36 m between frames) no pose had a point in front and its pick was arbitrary,
    often the twisted pair, which put every match behind a camera.

    Returns:
        ``a_R_b`` and the unit ``a_t_b``.
    """
    b_R_a1, b_R_a2, b_t_a = cv2.decomposeEssentialMat(E)
    best, best_score = None, None
    for b_R_a in (b_R_a1, b_R_a2):
        a_R_b = b_R_a.T
        matches = _Matches(fa, fb, a_R_b)
        alignment = float(np.sum(matches.unit_a * matches.unit_b))
        for sign in (1.0, -1.0):
            a_t_b = _unit(-sign * (a_R_b @ b_t_a.ravel()))
            kept = int(matches.inliers(a_t_b, threshold_rad)[1].sum())
            if best_score is None or (kept, alignment) > best_score:
                best, best_score = (a_R_b, a_t_b), (kept, alignment)
    assert best is not None
    return best


def estimate_relative_pose(rays_a: np.ndarray, rays_b: np.ndarray, sigma_rad: float,
                           threshold_sigmas: float = 3.0) -> EpipolarFit:
    """The relative pose of two views, for initializing a solver: R12 and the direction of p12.

    :func:`fit_essential` gives a first pose; then the pose is refined by robust least
    squares (Cauchy, scale ``sigma_rad``) on all matches, started from the fitted
    translation direction and from the three axes (each with the rotation that best
    explains the flow with it), keeping the lowest cost. The extra starts get out of
    the rotation-for-translation basin the five-point fit can land in: on the paper's
    nominal pair (40 m baseline at 500 m, 0.5 px) it was off by 4-5 deg in 8 of 30
    draws; refined this way, by at most 0.3 deg in 30 of 30 (~0.2 s a call).

    Args:
        rays_a, rays_b: (N, 3) matched rays.
        sigma_rad: registration noise (an angle: pixels / focal length).
        threshold_sigmas: inlier bound in sigmas.

    Returns:
        The fit (``method`` NONE with too few matches).
    """
    threshold = threshold_sigmas * sigma_rad
    fit = fit_essential(rays_a, rays_b, threshold)
    if fit.method is not FitMethod.ESSENTIAL:
        return fit
    fa, fb = _unit(np.asarray(rays_a, float)), _unit(np.asarray(rays_b, float))
    best = None
    for start in (fit.a_t_b, *np.eye(3)):  # (the residual does not see the sign of t)
        # the rotation that best explains the flow with this direction, then both
        R, _, _ = refine_relative_pose(fa, fb, fit.a_R_b, start, sigma_rad, fix_translation=True)
        R, t, cost = refine_relative_pose(fa, fb, R, start, sigma_rad)
        if best is None or cost < best[2]:
            best = (R, t, cost)
    assert best is not None
    R, t, _ = best
    t = _in_front(fa, fb, R, t)
    residual, inliers = _inliers(fa, fb, R, t, threshold)
    return EpipolarFit(R, t, inliers, residual, FitMethod.ESSENTIAL)


def _in_front(fa: np.ndarray, fb: np.ndarray, a_R_b: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``t`` or ``-t``, whichever puts most triangulated points in front of camera a."""
    la, _ = triangulate_depths(fa, fb, a_R_b, t)
    return -t if np.sum(la < 0) > np.sum(la > 0) else t


def refine_relative_pose(rays_a: np.ndarray, rays_b: np.ndarray, a_R_b: np.ndarray,
                         a_t_b: np.ndarray, robust_scale_rad: float | None = None,
                         fix_translation: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares relative pose (five parameters; scipy's Levenberg-Marquardt).

    Minimizes the signed epipolar residuals (the angles of :func:`epipolar_residual_rad`)
    over a rotation increment ``a_R_b Exp(w)`` and a translation direction moved in its
    tangent plane. The residual does not see the sign of ``t``.

    Args:
        rays_a, rays_b: (N, 3) rays, N >= 5.
        a_R_b: (3, 3) starting rotation. a_t_b: (3,) starting direction.
        robust_scale_rad: None: plain least squares; else the Cauchy loss of this scale
            (each residual r becomes ``sign(r) sqrt(log(1 + (r/s)^2))``).
        fix_translation: refine the rotation only.

    Returns:
        The refined ``a_R_b``, unit ``a_t_b`` and the final cost (half the sum of squares).
    """
    fa = _unit(np.asarray(rays_a, dtype=float))
    fb = _unit(np.asarray(rays_b, dtype=float))
    t0 = _unit(np.asarray(a_t_b, dtype=float))
    R0 = np.asarray(a_R_b, dtype=float)
    # an orthonormal basis of the tangent plane of the sphere at t0
    e1 = _unit(np.cross(t0, [1.0, 0.0, 0.0] if abs(t0[0]) < 0.9 else [0.0, 1.0, 0.0]))
    e2 = np.cross(t0, e1)
    n_params = 3 if fix_translation else 5

    def poses(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(P, n_params) parameters -> (P, 3, 3) rotations, (P, 3) directions."""
        R = R0 @ so3_exp(x[:, :3])
        if fix_translation:
            return R, np.broadcast_to(t0, (x.shape[0], 3))
        return R, _unit(t0 + x[:, 3:4] * e1 + x[:, 4:5] * e2)

    def residuals(x: np.ndarray) -> np.ndarray:
        """(P, n_params) -> (P, N), all parameter vectors at once."""
        R, t = poses(x)
        fb_in_a = np.einsum("pij,nj->pni", R, fb)
        det = np.einsum("pni,pi->pn", np.cross(fb_in_a, fa[None]), t)
        sine = np.minimum(np.linalg.norm(np.cross(t[:, None, :], fa[None]), axis=2),
                          np.linalg.norm(np.cross(t[:, None, :], fb_in_a), axis=2))
        r = det / np.maximum(sine, 1e-12)
        if robust_scale_rad is None:
            return r
        return np.sign(r) * np.sqrt(np.log1p((r / robust_scale_rad) ** 2))

    step = 1e-7  # forward differences of one batched evaluation (angles ~1e-3 rad)

    def jacobian(x: np.ndarray) -> np.ndarray:
        r = residuals(np.vstack([x, x + step * np.eye(n_params)]))
        return ((r[1:] - r[0]) / step).T

    solution = least_squares(lambda x: residuals(x[None])[0], np.zeros(n_params),
                             jac=jacobian, method="lm")
    R, t = poses(solution.x[None])
    return R[0], t[0], float(solution.cost)


def _nothing_fitted(n_matches: int, a_R_b: np.ndarray) -> EpipolarFit:
    return EpipolarFit(np.asarray(a_R_b, float), np.zeros(3), np.ones(n_matches, bool),
                       np.full(n_matches, np.nan), FitMethod.NONE)
