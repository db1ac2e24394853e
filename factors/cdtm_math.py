"""The C-DTM constraint as plain numpy math: residual, Jacobians and noise.

One formula, one place: the GTSAM factors (:mod:`factors.cdtm_factor`), the
closed-form analysis (``cdtm_graph.analysis.closed_form``) and the tests all call these.

Notation follows the paper (Kupervasser, Lerner, Rivlin, Rotstein) and DESIGN.md.
For one feature observed at frames a < b, with camera poses
``world_T_cam_a = (R_a, p_a)`` and ``world_T_cam_b = (R_b, p_b)``:

* ``r = R_a q_a`` is the world ray of the feature from camera a,
* the DTM tangent plane at ``G_E`` with upward normal ``N`` is met at
  ``G = p_a + lambda r``, ``lambda = N.(G_E - p_a) / N.r``,
* ``g_b = R_b^T (G - p_b)`` is that ground point seen from camera b,
* the paper's residual (eq. 7) is ``f = P(q_b, q_b) g_b / |g_b|`` (rank 2),
* the factor's residual is ``e = B_b^T g_b / |g_b| = B_b^T f`` with ``B_b`` an
  orthonormal basis of ``q_b``'s orthogonal complement (``|e| = |f|``, ~ the angle
  between predicted and measured rays, radians).

Camera Jacobians here are w.r.t. GTSAM's Pose3 tangent ``[omega, v]`` of the
*camera* pose, perturbed on the right; :func:`body_to_cam_adjoint` carries them to
``world_T_body``.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "projector",
    "skew",
    "orthonormal_complement",
    "tangent_plane_intersection",
    "paper_residual",
    "paper_data_jacobians",
    "feature_covariance",
    "residual_covariance",
    "sqrt_information",
    "body_to_cam_adjoint",
]


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices, (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def projector(u: np.ndarray, s: np.ndarray) -> np.ndarray:
    """The paper's operator ``P(u, s) = I - u s^T / (s^T u)`` (eq. 1).

    Args:
        u: (..., 3).
        s: (..., 3).

    Returns:
        (..., 3, 3). It projects along ``u`` onto the plane orthogonal to ``s``.
    """
    u = np.asarray(u, dtype=float)
    s = np.asarray(s, dtype=float)
    denom = np.einsum("...i,...i->...", s, u)[..., None, None]
    return np.eye(3) - u[..., :, None] * s[..., None, :] / denom


def orthonormal_complement(q: np.ndarray) -> np.ndarray:
    """Orthonormal basis ``B`` (columns) of the plane orthogonal to each ``q``.

    Smooth in ``q`` for rays with z > 0 (built from the camera's y axis), so a
    measurement's basis is well defined.

    Args:
        q: (n, 3) rays, z > 0.

    Returns:
        (n, 3, 2) with ``B^T B = I`` and ``B^T q = 0``.
    """
    q = np.asarray(q, dtype=float)
    qh = q / np.sqrt(np.einsum("ni,ni->n", q, q))[:, None]
    # b1 = e_y x q / |.| = (q_z, 0, -q_x) / |.|, b2 = q x b1 (np.cross is slow on small arrays)
    B = np.zeros(q.shape + (2,))
    s = 1.0 / np.hypot(qh[:, 0], qh[:, 2])
    B[:, 0, 0] = qh[:, 2] * s
    B[:, 2, 0] = -qh[:, 0] * s
    B[:, 0, 1] = qh[:, 1] * B[:, 2, 0]
    B[:, 1, 1] = qh[:, 2] * B[:, 0, 0] - qh[:, 0] * B[:, 2, 0]
    B[:, 2, 1] = -qh[:, 1] * B[:, 0, 0]
    return B


def tangent_plane_intersection(
    p_a: np.ndarray, ray_world: np.ndarray, G_E: np.ndarray, N: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Where each ray meets the DTM tangent plane (paper eqs. 2-3, 24).

    Args:
        p_a: (3,) or (n, 3) ray origin (camera a centre, world).
        ray_world: (n, 3) ray directions ``R_a q_a``.
        G_E: (n, 3) DTM points defining the planes.
        N: (n, 3) plane normals ``(-dh/dx, -dh/dy, 1)``.

    Returns:
        ``lam`` (n,), ``G`` (n, 3) with ``G = p_a + lam * ray_world``.
    """
    lam = np.einsum("ni,ni->n", N, G_E - p_a) / np.einsum("ni,ni->n", N, ray_world)
    return lam, p_a + lam[:, None] * ray_world


def paper_residual(
    R_a: np.ndarray, p_a: np.ndarray, R_b: np.ndarray, p_b: np.ndarray,
    q_a: np.ndarray, q_b: np.ndarray, G_E: np.ndarray, N: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The paper's 3-vector residual ``f`` (eq. 7) and ``g_b = ^{C2}G``.

    Args:
        R_a, p_a, R_b, p_b: camera-to-world rotations (3, 3) and centres (3,).
        q_a, q_b: (n, 3) normalized image rays (z = 1).
        G_E, N: (n, 3) DTM tangent planes.

    Returns:
        ``f`` (n, 3) and ``g_b`` (n, 3).
    """
    _, G = tangent_plane_intersection(p_a, q_a @ R_a.T, G_E, N)
    g_b = (G - p_b) @ R_b
    f = np.einsum("nij,nj->ni", projector(q_b, q_b), g_b) / np.linalg.norm(g_b, axis=1)[:, None]
    return f, g_b


def _normalized_projector_np(q_b: np.ndarray, g_b: np.ndarray) -> np.ndarray:
    """``N_P(q_2, ^{C2}G) = P(q2, q2) P(G, G) / |G|`` (eq. 14), (n, 3, 3)."""
    return (projector(q_b, q_b) @ projector(g_b, g_b)) / np.linalg.norm(g_b, axis=1)[:, None, None]


def paper_data_jacobians(
    R_a: np.ndarray, p_a: np.ndarray, R_b: np.ndarray, p_b: np.ndarray,
    q_a: np.ndarray, q_b: np.ndarray, G_E: np.ndarray, N: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Jacobians of ``f`` w.r.t. the data (eqs. 19, 20; and ``q_a``, beyond the paper).

    Returns:
        ``J_qb`` (n, 3, 3) = df/dq_b (eq. 19), ``J_G`` (n, 3, 3) = df/dG_E (eq. 20),
        ``J_qa`` (n, 3, 3) = df/dq_a (the paper treats q_a as exact; a tracker does not).
    """
    ray = q_a @ R_a.T
    lam, _ = tangent_plane_intersection(p_a, ray, G_E, N)
    _, g_b = paper_residual(R_a, p_a, R_b, p_b, q_a, q_b, G_E, N)
    g_norm = np.linalg.norm(g_b, axis=1)
    qq = np.einsum("ni,ni->n", q_b, q_b)
    qg = np.einsum("ni,ni->n", q_b, g_b)
    # eq. 19
    J_qb = -(
        (qg[:, None, None] * np.eye(3) + q_b[:, :, None] * g_b[:, None, :])
        @ projector(q_b, q_b)
    ) / (qq * g_norm)[:, None, None]
    NP = _normalized_projector_np(q_b, g_b)
    # R12 L with R12 = R_b^T R_a and L = q_a N^T / (N^T R_a q_a): eq. 20
    Nr = np.einsum("ni,ni->n", N, ray)
    R12_L = (R_b.T @ ray.T).T[:, :, None] * N[:, None, :] / Nr[:, None, None]
    J_G = NP @ R12_L
    # dG/dq_a = lam P(r, N) R_a
    J_qa = NP @ (R_b.T @ (lam[:, None, None] * projector(ray, N)) @ R_a)
    return J_qb, J_G, J_qa


def feature_covariance(
    R_a: np.ndarray, p_a: np.ndarray, R_b: np.ndarray, p_b: np.ndarray,
    q_a: np.ndarray, q_b: np.ndarray, G_E: np.ndarray, N: np.ndarray,
    sigma_q_xy: tuple[float, float], sigma_h_m: float,
    sigma_qa_xy: tuple[float, float] | None = None,
) -> np.ndarray:
    """Covariance of ``f`` per feature, ``J_q Sigma_q J_q^T + J_G Sigma_G J_G^T`` (eqs. 19-26).

    Args:
        sigma_q_xy: 1-sigma of ``q_b`` in normalized units (sigma_px/fx, sigma_px/fy), eq. 22.
        sigma_h_m: 1-sigma DTM height error, scalar or (n,); eqs. 25-26 move ``G_E`` along
            the ray.
        sigma_qa_xy: 1-sigma of ``q_a``; ``None`` keeps the paper's model (``q_a`` exact).

    Returns:
        ``Sigma_f`` (n, 3, 3), rank 2 at a noiseless solution.
    """
    J_qb, J_G, J_qa = paper_data_jacobians(R_a, p_a, R_b, p_b, q_a, q_b, G_E, N)
    Sigma_q = np.diag([sigma_q_xy[0] ** 2, sigma_q_xy[1] ** 2, 0.0])
    ray = q_a @ R_a.T
    dG_dh = ray / np.einsum("ni,ni->n", N, ray)[:, None]  # eq. 25
    sigma_h2 = np.broadcast_to(np.asarray(sigma_h_m, dtype=float) ** 2, dG_dh.shape[:1])
    Sigma_G = sigma_h2[:, None, None] * dG_dh[:, :, None] * dG_dh[:, None, :]  # eq. 26
    Sigma_f = J_qb @ Sigma_q @ np.swapaxes(J_qb, 1, 2) + J_G @ Sigma_G @ np.swapaxes(J_G, 1, 2)
    if sigma_qa_xy is not None:
        Sigma_qa = np.diag([sigma_qa_xy[0] ** 2, sigma_qa_xy[1] ** 2, 0.0])
        Sigma_f = Sigma_f + J_qa @ Sigma_qa @ np.swapaxes(J_qa, 1, 2)
    return Sigma_f


def residual_covariance(Sigma_f: np.ndarray, basis_b: np.ndarray) -> np.ndarray:
    """The 2x2 covariance of ``e = B^T f``: ``B^T Sigma_f B``, (n, 2, 2)."""
    return np.swapaxes(basis_b, 1, 2) @ Sigma_f @ basis_b


def sqrt_information(Sigma_e: np.ndarray) -> np.ndarray:
    """Upper-triangular ``S`` with ``S^T S = Sigma_e^-1`` (GTSAM's whitening), (n, 2, 2).

    Closed form for 2x2 blocks: with ``I = Sigma_e^-1``, ``S = [[a, b], [0, c]]``,
    ``a = sqrt(I00)``, ``b = I01 / a``, ``c = sqrt(I11 - b^2)``.
    """
    s00, s01, s11 = Sigma_e[:, 0, 0], Sigma_e[:, 0, 1], Sigma_e[:, 1, 1]
    det = s00 * s11 - s01 * s01
    i00, i01, i11 = s11 / det, -s01 / det, s00 / det
    S = np.zeros_like(Sigma_e)
    S[:, 0, 0] = np.sqrt(i00)
    S[:, 0, 1] = i01 / S[:, 0, 0]
    S[:, 1, 1] = np.sqrt(i11 - S[:, 0, 1] ** 2)
    return S


def body_to_cam_adjoint(body_T_cam: np.ndarray) -> np.ndarray:
    """``Ad(cam_T_body)`` in GTSAM's [omega, v] order, (6, 6).

    A right perturbation ``xi`` of ``world_T_body`` moves ``world_T_cam`` by
    ``Ad(cam_T_body) xi``, so ``H_body = H_cam @ Ad(cam_T_body)``.
    """
    R_bc = body_T_cam[:3, :3]
    t_bc = body_T_cam[:3, 3]
    R = R_bc.T
    t = -R_bc.T @ t_bc
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = R
    Ad[3:, 3:] = R
    Ad[3:, :3] = skew(t) @ R
    return Ad
