"""The paper's closed-form error analysis (eqs. 9-32) and the degeneracy checks (section V.B).

Parameters are the paper's twelve, ``theta = (p1, phi1, theta1, psi1, p12, phi12,
theta12, psi12)``: the pose of camera 1 and the ego-motion, with

* ``p1``, ``R1``: camera-1 centre and camera-to-world rotation (``world_T_cam_a``),
* ``p12 = R2^T (p1 - p2)``, ``R12 = R2^T R1`` (camera-1 coordinates to camera-2),
* Euler angles as eqs. 29-31 extract them from a camera-to-world ``R``:
  ``theta = asin(-R13)``, ``phi = atan2(R23, R33)``, ``psi = atan2(R12, R11)``, so
  ``R^T = Rz(psi) Ry(theta) Rx(phi)``; the ego-motion angles are those of
  ``R12^T`` (camera 2's orientation in camera 1), i.e. ``R12 = Rz Ry Rx(alpha12)``.

``J_theta`` follows eqs. 15-18 literally (derivatives of the Euler
parametrization); the residual, its data Jacobians and the feature covariances
come from :mod:`factors.cdtm_math`, the same code the GTSAM factor uses.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cdtm_graph.codes import Code
from factors import cdtm_math
from factors.cdtm_factor import FeatureNoise

THETA_NAMES = ("p1_x", "p1_y", "p1_z", "phi1", "theta1", "psi1",
               "p12_x", "p12_y", "p12_z", "phi12", "theta12", "psi12")
C2_NAMES = ("p2_x", "p2_y", "p2_z", "phi2", "theta2", "psi2")

_EX, _EY, _EZ = np.eye(3)


def _rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def euler_from_rotation(R: np.ndarray) -> np.ndarray:
    """(phi, theta, psi) of a camera-to-world rotation, eqs. 29-31."""
    return np.array([np.arctan2(R[1, 2], R[2, 2]), np.arcsin(np.clip(-R[0, 2], -1, 1)),
                     np.arctan2(R[0, 1], R[0, 0])])


def rotation_from_euler(angles: np.ndarray) -> np.ndarray:
    """Camera-to-world ``R`` with ``R^T = Rz(psi) Ry(theta) Rx(phi)`` (inverse of eqs. 29-31)."""
    phi, theta, psi = angles
    return (_rz(psi) @ _ry(theta) @ _rx(phi)).T


def rotation_euler_derivatives(angles: np.ndarray) -> np.ndarray:
    """dR/d(phi, theta, psi) of :func:`rotation_from_euler`, (3, 3, 3) stacked by angle."""
    phi, theta, psi = angles
    Z, Y, Xr = _rz(psi), _ry(theta), _rx(phi)
    dM = [Z @ Y @ Xr @ cdtm_math.skew(_EX), Z @ Y @ cdtm_math.skew(_EY) @ Xr,
          Z @ cdtm_math.skew(_EZ) @ Y @ Xr]
    return np.stack([d.T for d in dM])


def euler_differential(R: np.ndarray, dR: np.ndarray) -> np.ndarray:
    """Differential of eqs. 29-31 at ``R`` along perturbations ``dR``, (k, 3, 3) -> (3, k)."""
    d_phi = (R[2, 2] * dR[:, 1, 2] - R[1, 2] * dR[:, 2, 2]) / (R[1, 2] ** 2 + R[2, 2] ** 2)
    d_theta = -dR[:, 0, 2] / np.sqrt(1 - R[0, 2] ** 2)
    d_psi = (R[0, 0] * dR[:, 0, 1] - R[0, 1] * dR[:, 0, 0]) / (R[0, 0] ** 2 + R[0, 1] ** 2)
    return np.stack([d_phi, d_theta, d_psi])


def theta_from_cameras(world_T_cam_a: np.ndarray, world_T_cam_b: np.ndarray) -> np.ndarray:
    """The twelve parameters of a camera pair, (12,)."""
    R1, p1 = world_T_cam_a[:3, :3], world_T_cam_a[:3, 3]
    R2, p2 = world_T_cam_b[:3, :3], world_T_cam_b[:3, 3]
    R12 = R2.T @ R1
    return np.concatenate([p1, euler_from_rotation(R1), R2.T @ (p1 - p2),
                           euler_from_rotation(R12.T)])


def cameras_from_theta(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(world_T_cam_a, world_T_cam_b)`` from the twelve parameters (eqs. 27-28)."""
    p1, R1 = theta[:3], rotation_from_euler(theta[3:6])
    p12, R12 = theta[6:9], rotation_from_euler(theta[9:12]).T
    R2 = R1 @ R12.T  # eq. 28
    p2 = p1 - R1 @ R12.T @ p12  # eq. 27
    Ta, Tb = np.eye(4), np.eye(4)
    Ta[:3, :3], Ta[:3, 3] = R1, p1
    Tb[:3, :3], Tb[:3, 3] = R2, p2
    return Ta, Tb


def jacobian_theta(
    theta: np.ndarray, q_a: np.ndarray, q_b: np.ndarray, G_E: np.ndarray, N: np.ndarray
) -> np.ndarray:
    """``J_theta = dF/dtheta`` of the stacked residuals, eqs. 14-18.

    Returns:
        (n, 3, 12) per-feature blocks (stack to the paper's (3n, 12)).
    """
    Ta, Tb = cameras_from_theta(theta)
    R1, p1 = Ta[:3, :3], Ta[:3, 3]
    _, g_b = cdtm_math.paper_residual(R1, p1, Tb[:3, :3], Tb[:3, 3], q_a, q_b, G_E, N)
    R12 = rotation_from_euler(theta[9:12]).T
    dR1 = rotation_euler_derivatives(theta[3:6])  # (3, 3, 3)
    dR12 = np.swapaxes(rotation_euler_derivatives(theta[9:12]), 1, 2)  # R12 = R(alpha12)^T
    NP = (cdtm_math.projector(q_b, q_b) @ cdtm_math.projector(g_b, g_b)
          / np.linalg.norm(g_b, axis=1)[:, None, None])  # eq. 14
    Nr = np.einsum("ni,ni->n", N, q_a @ R1.T)
    L = q_a[:, :, None] * N[:, None, :] / Nr[:, None, None]  # eq. 2
    LG = np.einsum("nij,nj->ni", L, G_E - p1)  # L (G_E - p1) = lambda q_a
    A = NP @ R12 @ L
    J = np.empty((q_a.shape[0], 3, 12))
    J[:, :, 0:3] = -A  # eq. 15
    J[:, :, 3:6] = -A @ np.einsum("kij,nj->nik", dR1, LG)  # eq. 16, one column per angle
    J[:, :, 6:9] = NP  # eq. 17
    J[:, :, 9:12] = NP @ np.einsum("kij,nj->nik", dR12, LG)  # eq. 18
    return J


def jacobian_c2(theta: np.ndarray) -> np.ndarray:
    """``J_C2``: d(p2, phi2, theta2, psi2)/d theta of eqs. 27-31, (6, 12)."""
    R1 = rotation_from_euler(theta[3:6])
    R12T = rotation_from_euler(theta[9:12])  # R12^T
    p12 = theta[6:9]
    R2 = R1 @ R12T
    dR1 = rotation_euler_derivatives(theta[3:6])
    dR12T = rotation_euler_derivatives(theta[9:12])
    J = np.zeros((6, 12))
    J[:3, 0:3] = np.eye(3)
    J[:3, 3:6] = -np.stack([d @ R12T @ p12 for d in dR1], axis=1)
    J[:3, 6:9] = -R2
    J[:3, 9:12] = -np.stack([R1 @ d @ p12 for d in dR12T], axis=1)
    J[3:, 3:6] = euler_differential(R2, np.stack([d @ R12T for d in dR1]))
    J[3:, 9:12] = euler_differential(R2, np.stack([R1 @ d for d in dR12T]))
    return J


def theta_jacobian_wrt_body_tangents(
    world_T_body_a: np.ndarray, world_T_body_b: np.ndarray, body_T_cam: np.ndarray
) -> np.ndarray:
    """d theta / d(xi_a, xi_b) for right perturbations of ``world_T_body`` [omega, v], (12, 12).

    Maps GTSAM's joint marginal of ``(X(a), X(b))`` into theta:
    ``Sigma_theta = H Sigma_ab H^T``.
    """
    Ta, Tb = world_T_body_a @ body_T_cam, world_T_body_b @ body_T_cam
    R1, p1, R2, p2 = Ta[:3, :3], Ta[:3, 3], Tb[:3, :3], Tb[:3, 3]
    R12T = R1.T @ R2
    p12 = R2.T @ (p1 - p2)
    E = np.stack([cdtm_math.skew(e) for e in np.eye(3)])  # generators
    H_cam = np.zeros((12, 12))  # w.r.t. camera tangents (omega_a, v_a, omega_b, v_b)
    H_cam[0:3, 3:6] = R1
    H_cam[3:6, 0:3] = euler_differential(R1, R1 @ E)
    H_cam[6:9, 3:6] = R2.T @ R1
    H_cam[6:9, 6:9] = cdtm_math.skew(p12)
    H_cam[6:9, 9:12] = -np.eye(3)
    H_cam[9:12, 0:3] = euler_differential(R12T, -E @ R12T)
    H_cam[9:12, 6:9] = euler_differential(R12T, R12T @ E)
    Ad = cdtm_math.body_to_cam_adjoint(body_T_cam)
    return H_cam @ np.kron(np.eye(2), Ad)


@dataclass(frozen=True)
class DegeneracySettings:
    """Thresholds of the degeneracy verdict (section V.B).

    Attributes:
        min_features: the twelve parameters need at least six flow vectors (section III.A).
        min_fov_deg: angular spread of the feature rays below which the geometry
            degenerates (the paper reports failure below ~8 degrees).
        min_baseline_ratio: ``|p12|`` over the mean feature depth below which the
            DTM cannot fix the translation.
        flat_relief_sigma: terrain is flat when the RMS deviation of the hit points
            from their best-fit plane is below this many ``sigma_h`` (at least 0.5 m).
            Only near-planar patches are named flat: above that, the covariance
            itself reports the weak relief honestly (a 1-sigma threshold called every
            130 m-grid DTM and every 15-degree footprint flat).
        max_condition_number: of the scale-normalized information ``J^T W J``.
    """

    min_features: int = 6
    min_fov_deg: float = 8.0
    min_baseline_ratio: float = 0.005
    flat_relief_sigma: float = 0.25
    max_condition_number: float = 1e9


@dataclass(frozen=True)
class Degeneracy:
    """Degeneracy verdict: ``degenerate`` iff ``reasons`` is not empty."""

    reasons: tuple[str, ...]
    details: dict = field(default_factory=dict)

    @property
    def degenerate(self) -> bool:
        return bool(self.reasons)

    def message(self) -> str:
        return "; ".join(f"{r}: {self.details.get(r, '')}".rstrip(": ") for r in self.reasons)


@dataclass(frozen=True)
class ClosedFormAnalysis:
    """Closed-form covariances of one frame pair (metres, radians; theta order THETA_NAMES).

    Attributes:
        theta: (12,) linearization point.
        sigma_theta_unweighted: (12, 12) eq. 13 as printed (unweighted least squares).
        sigma_theta_weighted: (12, 12) ``(J^T W J)^-1``, ``W = blockdiag(Sigma_f^+)`` (the
            pseudo-inverse on each residual's plane, orthogonal to ``q_b``): the
            covariance of the weighted estimator GTSAM solves.
        sigma_c2_unweighted, sigma_c2_weighted: (6, 6) camera-2 pose covariance (eqs. 27-32).
        information: (12, 12) ``J^T W J``.
        condition_number: of the scale-normalized information.
        weakest_directions: (12, k) unit directions (in theta, scale-normalized) of the
            smallest eigenvalues, weakest first.
        degeneracy: the verdict.
    """

    theta: np.ndarray
    sigma_theta_unweighted: np.ndarray
    sigma_theta_weighted: np.ndarray
    sigma_c2_unweighted: np.ndarray
    sigma_c2_weighted: np.ndarray
    information: np.ndarray
    condition_number: float
    weakest_directions: np.ndarray
    weakest_eigenvalues: np.ndarray
    degeneracy: Degeneracy
    n_features: int


def _normalized_spectrum(info: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    d = np.sqrt(np.clip(np.diag(info), 1e-300, None))
    normalized = info / np.outer(d, d)
    w, V = np.linalg.eigh(normalized)
    cond = float(w[-1] / w[0]) if w[0] > 0 else float("inf")
    return cond, w, V


def geometric_degeneracy(
    world_T_cam_a: np.ndarray, world_T_cam_b: np.ndarray, q_a: np.ndarray, G_E: np.ndarray,
    sigma_h_m: float, settings: DegeneracySettings,
) -> Degeneracy:
    """Named degeneracies from the geometry alone: features, FOV, baseline, flat terrain."""
    reasons: list[str] = []
    details: dict = {}
    n = q_a.shape[0]
    if n < settings.min_features:
        reasons.append(Code.FEW_FEATURES)
        details[Code.FEW_FEATURES] = f"{n} features, need >= {settings.min_features}"
    if n >= 2:
        rays = q_a / np.linalg.norm(q_a, axis=1, keepdims=True)
        centre = rays.mean(axis=0)
        centre /= np.linalg.norm(centre)
        spread_deg = 2 * np.degrees(np.arccos(np.clip(rays @ centre, -1, 1)).max())
        details["feature_spread_deg"] = spread_deg
        if spread_deg < settings.min_fov_deg:
            reasons.append(Code.NARROW_FOV)
            details[Code.NARROW_FOV] = (f"features span {spread_deg:.2f} deg, need >= "
                                     f"{settings.min_fov_deg:g} deg")
    depth = np.linalg.norm(G_E - world_T_cam_a[:3, 3], axis=1).mean() if n else np.inf
    baseline = np.linalg.norm(world_T_cam_a[:3, 3] - world_T_cam_b[:3, 3])
    details["baseline_m"] = baseline
    if baseline < settings.min_baseline_ratio * depth:
        reasons.append("short_baseline")
        details["short_baseline"] = (f"baseline {baseline:.2f} m at mean depth {depth:.0f} m, "
                                     f"need >= {settings.min_baseline_ratio:g} of the depth")
    if n >= 3:
        centred = G_E - G_E.mean(axis=0)
        relief = np.linalg.svd(centred, compute_uv=False)[-1] / np.sqrt(n)
        details["relief_rms_m"] = relief
        if relief < max(settings.flat_relief_sigma * sigma_h_m, 0.5):
            reasons.append(Code.FLAT_TERRAIN)
            details[Code.FLAT_TERRAIN] = (f"hit points within {relief:.2f} m RMS of a plane "
                                       f"(DTM sigma {sigma_h_m:.2f} m)")
    return Degeneracy(tuple(reasons), details)


def analyze_pair(
    world_T_cam_a: np.ndarray,
    world_T_cam_b: np.ndarray,
    q_a: np.ndarray,
    q_b: np.ndarray,
    G_E: np.ndarray,
    N: np.ndarray,
    noise: FeatureNoise,
    settings: DegeneracySettings | None = None,
    Sigma_f: np.ndarray | None = None,
) -> ClosedFormAnalysis:
    """Closed-form covariance of the C-DTM estimate of one frame pair, eqs. 9-32.

    Args:
        world_T_cam_a, world_T_cam_b: (4, 4) camera poses of the linearization point.
        q_a, q_b: (n, 3) normalized rays (z = 1). G_E, N: (n, 3) DTM tangent planes.
        noise: data noise (eqs. 21-26).
        settings: degeneracy thresholds.
        Sigma_f: (n, 3, 3) feature covariances at this point if already computed
            (:func:`factors.cdtm_math.feature_covariance`).

    Returns:
        Both forms of Sigma_theta, Sigma_C2, conditioning and the degeneracy verdict.
    """
    settings = settings or DegeneracySettings()
    theta = theta_from_cameras(world_T_cam_a, world_T_cam_b)
    n = q_a.shape[0]
    verdict = geometric_degeneracy(world_T_cam_a, world_T_cam_b, q_a, G_E, noise.sigma_h_m,
                                   settings)
    J = jacobian_theta(theta, q_a, q_b, G_E, N)  # (n, 3, 12)
    if Sigma_f is None:
        Sigma_f = cdtm_math.feature_covariance(
            world_T_cam_a[:3, :3], world_T_cam_a[:3, 3], world_T_cam_b[:3, :3],
            world_T_cam_b[:3, 3], q_a, q_b, G_E, N, noise.sigma_q_xy, noise.sigma_h_m,
            noise.sigma_qa_xy)
    # f = P(q_b, q_b) g/|g| lies in q_b's orthogonal complement by construction, so its
    # covariance is inverted there: W = B (B^T Sigma_f B)^-1 B^T. (A plain pseudo-inverse
    # of Sigma_f would also invert the tiny q_b component that eq. 19 picks up when the
    # residual is not zero, i.e. with real data, and invent information.)
    B = cdtm_math.orthonormal_complement(q_b)
    Bt = np.swapaxes(B, 1, 2)
    W = B @ np.linalg.inv(Bt @ Sigma_f @ B) @ Bt
    J_flat = J.reshape(-1, 12)
    info = J_flat.T @ (W @ J).reshape(-1, 12)
    JtJ = J_flat.T @ J_flat
    JtSJ = J_flat.T @ (Sigma_f @ J).reshape(-1, 12)
    cond, w, V = _normalized_spectrum(info)
    reasons = list(verdict.reasons)
    details = dict(verdict.details)
    details["condition_number"] = cond
    if not cond < settings.max_condition_number and "ill_conditioned" not in reasons:
        reasons.append("ill_conditioned")
        details["ill_conditioned"] = (f"condition number {cond:.3g} of J^T W J exceeds "
                                      f"{settings.max_condition_number:.3g}")
    with np.errstate(all="ignore"):
        try:
            sigma_w = np.linalg.inv(info)
            JtJ_inv = np.linalg.inv(JtJ)
        except np.linalg.LinAlgError:
            sigma_w = np.full((12, 12), np.inf)
            JtJ_inv = np.full((12, 12), np.inf)
        sigma_u = JtJ_inv @ JtSJ @ JtJ_inv  # eq. 13
        J_c2 = jacobian_c2(theta)
        sigma_c2_u = J_c2 @ sigma_u @ J_c2.T
        sigma_c2_w = J_c2 @ sigma_w @ J_c2.T
    return ClosedFormAnalysis(
        theta=theta,
        sigma_theta_unweighted=sigma_u,
        sigma_theta_weighted=sigma_w,
        sigma_c2_unweighted=sigma_c2_u,
        sigma_c2_weighted=sigma_c2_w,
        information=info,
        condition_number=cond,
        weakest_directions=V[:, :3],
        weakest_eigenvalues=w[:3],
        degeneracy=Degeneracy(tuple(reasons), details),
        n_features=n,
    )
