"""Numba kernel: C-DTM residuals and Jacobians of many features in one call.

The hot path of every linearization. It implements, feature by feature, the same
math as :mod:`factors.cdtm_math` (whose numpy functions are the readable reference
and are tested against it): ``e = B^T g/|g|`` with the Jacobians derived there,
chained to ``world_T_body`` through ``Ad(cam_T_body)``, whitened by the per-feature
square-root information, and reweighted per feature by an M-estimator.

Jacobians w.r.t. the camera pose, right perturbation ``[omega, v]`` (DESIGN.md):

* camera b: ``dg/d omega_b = [g]x``, ``dg/dv_b = -I``;
* camera a: ``dg/dv_a = R_b^T P(r, N) R_a``, ``dg/d omega_a = -lambda R_b^T P(r, N) R_a [q_a]x``,

with ``de/dg = B^T (I - g g^T/|g|^2) / |g|`` and ``P(r, N) = I - r N^T / N.r``.
"""

from __future__ import annotations

import numpy as np

from factors.jit import njit

# Robust kernels, numbered for the kernel; names and defaults in factors.robust.
KERNEL_NONE = 0
KERNEL_HUBER = 1
KERNEL_CAUCHY = 2
KERNEL_TUKEY = 3

# Features whose ray grazes the plane (|N.r| tiny) or points away carry no information.
_MIN_RAY_NORMAL_DOT = 1e-9


@njit(cache=True, inline="always")
def robust_weight(kernel: int, k: float, s: float) -> float:
    """M-estimator weight w(s) of a whitened residual norm ``s`` (GTSAM's definitions)."""
    if kernel == KERNEL_HUBER:
        return 1.0 if s <= k else k / s
    if kernel == KERNEL_CAUCHY:
        return 1.0 / (1.0 + (s / k) ** 2)
    if kernel == KERNEL_TUKEY:
        if s > k:
            return 0.0
        u = 1.0 - (s / k) ** 2
        return u * u
    return 1.0


@njit(cache=True, inline="always")
def robust_loss(kernel: int, k: float, s: float) -> float:
    """M-estimator loss rho(s) (GTSAM's definitions; rho = s^2/2 without a kernel)."""
    if kernel == KERNEL_HUBER:
        return 0.5 * s * s if s <= k else k * s - 0.5 * k * k
    if kernel == KERNEL_CAUCHY:
        return 0.5 * k * k * np.log1p((s / k) ** 2)
    if kernel == KERNEL_TUKEY:
        if s > k:
            return k * k / 6.0
        u = 1.0 - (s / k) ** 2
        return k * k / 6.0 * (1.0 - u * u * u)
    return 0.5 * s * s


@njit(cache=True, inline="always")
def _hit_in_b(i, R_a, p_a, R_b, p_b, q_a, G_E, N):
    """Feature i's ray ``r = R_a q_a``, ``N.r``, where it meets its plane ``P = p_a + lam
    r`` and ``g = R_b^T (P - p_b)``: ``(r0, r1, r2, Nr, lam, g0, g1, g2)``. ``lam`` is NaN
    for an inactive feature (the ray parallel to the plane or the hit behind camera a)."""
    r0 = R_a[0, 0] * q_a[i, 0] + R_a[0, 1] * q_a[i, 1] + R_a[0, 2] * q_a[i, 2]
    r1 = R_a[1, 0] * q_a[i, 0] + R_a[1, 1] * q_a[i, 1] + R_a[1, 2] * q_a[i, 2]
    r2 = R_a[2, 0] * q_a[i, 0] + R_a[2, 1] * q_a[i, 1] + R_a[2, 2] * q_a[i, 2]
    Nr = N[i, 0] * r0 + N[i, 1] * r1 + N[i, 2] * r2
    c = N[i, 0] * (G_E[i, 0] - p_a[0]) + N[i, 1] * (G_E[i, 1] - p_a[1]) \
        + N[i, 2] * (G_E[i, 2] - p_a[2])
    # (written so that NaN data, which fails every comparison, is inactive too)
    if not (abs(Nr) >= _MIN_RAY_NORMAL_DOT and c / Nr > 0.0):
        return r0, r1, r2, Nr, np.nan, 0.0, 0.0, 0.0
    lam = c / Nr
    d0 = p_a[0] + lam * r0 - p_b[0]
    d1 = p_a[1] + lam * r1 - p_b[1]
    d2 = p_a[2] + lam * r2 - p_b[2]
    # g = R_b^T d
    g0 = R_b[0, 0] * d0 + R_b[1, 0] * d1 + R_b[2, 0] * d2
    g1 = R_b[0, 1] * d0 + R_b[1, 1] * d1 + R_b[2, 1] * d2
    g2 = R_b[0, 2] * d0 + R_b[1, 2] * d1 + R_b[2, 2] * d2
    return r0, r1, r2, Nr, lam, g0, g1, g2


@njit(cache=True)
def cdtm_linearize(
    R_a, p_a, R_b, p_b, Ad, q_a, G_E, N, basis, sqrt_info, kernel, kernel_k,
    want_jacobians, e_out, Ha_out, Hb_out, e_loss_out,
):
    """Whitened, robustly reweighted residuals and body-pose Jacobians of n features.

    Args:
        R_a, p_a, R_b, p_b: camera-to-world rotation (3, 3) and centre (3,) of cameras a, b.
        Ad: (6, 6) ``Ad(cam_T_body)``: camera-tangent Jacobians times Ad give body ones.
        q_a: (n, 3) rays in camera a. G_E, N: (n, 3) tangent planes. basis: (n, 3, 2) ``B_b``.
        sqrt_info: (n, 2, 2) whitening; the identity gives the unwhitened residual.
        kernel, kernel_k: robust kernel id and per-feature thresholds (n,), in the units
            of the whitened residual.
        want_jacobians: fill ``Ha_out``/``Hb_out`` and return sqrt(w)-reweighted
            residuals (a linearization); otherwise return residuals whose half
            squared norm is the robust loss (an error evaluation).
        e_out: (n, 2) output. Ha_out, Hb_out: (n, 2, 6) outputs (body tangents).
        e_loss_out: (n, 2) or (0, 2): with Jacobians, also the error evaluation's
            residuals (so that an error and a linearization at the same poses are one
            call); (0, 2) for none.

    Returns:
        Number of features that were inactive (ray parallel to the plane or
        the ground point behind camera a); their rows are zero.
    """
    n = q_a.shape[0]
    n_inactive = 0
    Hc_a = np.empty((2, 6))
    Hc_b = np.empty((2, 6))
    for i in range(n):
        r0, r1, r2, Nr, lam, g0, g1, g2 = _hit_in_b(i, R_a, p_a, R_b, p_b, q_a, G_E, N)
        if np.isnan(lam):
            n_inactive += 1
            e_out[i, 0] = 0.0
            e_out[i, 1] = 0.0
            if want_jacobians and e_loss_out.shape[0]:
                e_loss_out[i, 0] = 0.0
                e_loss_out[i, 1] = 0.0
            if want_jacobians:  # (element by element: numba's slice stores cost compilation)
                for k in range(2):
                    for j in range(6):
                        Ha_out[i, k, j] = 0.0
                        Hb_out[i, k, j] = 0.0
            continue
        gn = np.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
        h0, h1, h2 = g0 / gn, g1 / gn, g2 / gn
        # unwhitened residual e = B^T h
        u0 = basis[i, 0, 0] * h0 + basis[i, 1, 0] * h1 + basis[i, 2, 0] * h2
        u1 = basis[i, 0, 1] * h0 + basis[i, 1, 1] * h1 + basis[i, 2, 1] * h2
        S00, S01, S10, S11 = sqrt_info[i, 0, 0], sqrt_info[i, 0, 1], sqrt_info[i, 1, 0], \
            sqrt_info[i, 1, 1]
        w0 = S00 * u0 + S01 * u1
        w1 = S10 * u0 + S11 * u1
        s = np.sqrt(w0 * w0 + w1 * w1)
        if not want_jacobians or e_loss_out.shape[0]:
            loss_out = e_out if not want_jacobians else e_loss_out
            if kernel == KERNEL_NONE or s == 0.0:
                loss_out[i, 0] = w0
                loss_out[i, 1] = w1
            else:
                scale = np.sqrt(2.0 * robust_loss(kernel, kernel_k[i], s)) / s
                loss_out[i, 0] = w0 * scale
                loss_out[i, 1] = w1 * scale
            if not want_jacobians:
                continue
        sw = np.sqrt(robust_weight(kernel, kernel_k[i], s)) if kernel != KERNEL_NONE else 1.0
        e_out[i, 0] = sw * w0
        e_out[i, 1] = sw * w1
        for k in range(2):
            # M_k = (B_k - (B_k.h) h) / |g|: row k of de/dg
            bh = basis[i, 0, k] * h0 + basis[i, 1, k] * h1 + basis[i, 2, k] * h2
            m0 = (basis[i, 0, k] - bh * h0) / gn
            m1 = (basis[i, 1, k] - bh * h1) / gn
            m2 = (basis[i, 2, k] - bh * h2) / gn
            # camera b: [M_k x g, -M_k]
            Hc_b[k, 0] = m1 * g2 - m2 * g1
            Hc_b[k, 1] = m2 * g0 - m0 * g2
            Hc_b[k, 2] = m0 * g1 - m1 * g0
            Hc_b[k, 3] = -m0
            Hc_b[k, 4] = -m1
            Hc_b[k, 5] = -m2
            # camera a: w = P(r,N)^T R_b M_k, u = R_a^T w -> [lam q_a x u, u]
            wm0 = R_b[0, 0] * m0 + R_b[0, 1] * m1 + R_b[0, 2] * m2
            wm1 = R_b[1, 0] * m0 + R_b[1, 1] * m1 + R_b[1, 2] * m2
            wm2 = R_b[2, 0] * m0 + R_b[2, 1] * m1 + R_b[2, 2] * m2
            rw = (r0 * wm0 + r1 * wm1 + r2 * wm2) / Nr
            wm0 -= N[i, 0] * rw
            wm1 -= N[i, 1] * rw
            wm2 -= N[i, 2] * rw
            a0 = R_a[0, 0] * wm0 + R_a[1, 0] * wm1 + R_a[2, 0] * wm2
            a1 = R_a[0, 1] * wm0 + R_a[1, 1] * wm1 + R_a[2, 1] * wm2
            a2 = R_a[0, 2] * wm0 + R_a[1, 2] * wm1 + R_a[2, 2] * wm2
            Hc_a[k, 0] = lam * (q_a[i, 1] * a2 - q_a[i, 2] * a1)
            Hc_a[k, 1] = lam * (q_a[i, 2] * a0 - q_a[i, 0] * a2)
            Hc_a[k, 2] = lam * (q_a[i, 0] * a1 - q_a[i, 1] * a0)
            Hc_a[k, 3] = a0
            Hc_a[k, 4] = a1
            Hc_a[k, 5] = a2
        # whiten, reweight and carry to the body tangent: H = sw * S @ Hc @ Ad
        for k in range(2):
            sk0 = sw * sqrt_info[i, k, 0]
            sk1 = sw * sqrt_info[i, k, 1]
            for j in range(6):
                acc_a = 0.0
                acc_b = 0.0
                for m in range(6):
                    ca = sk0 * Hc_a[0, m] + sk1 * Hc_a[1, m]
                    cb = sk0 * Hc_b[0, m] + sk1 * Hc_b[1, m]
                    acc_a += ca * Ad[m, j]
                    acc_b += cb * Ad[m, j]
                Ha_out[i, k, j] = acc_a
                Hb_out[i, k, j] = acc_b
    return n_inactive


@njit(cache=True, inline="always")
def _ray_move(i, R_a, p_a, R_b, p_b, q_a, q_b, G_E, N, dqa0, dqa1, dqx, dqy):
    """Feature i's unwhitened residual ``e = B(q_b)^T h`` and its derivative when camera
    a's ray moves by ``[dqa0, dqa1, 0]`` and camera b's by ``[dqx, dqy, 0]``, the poses and
    the tangent plane held: ``(active, e0, e1, de0, de1)``; ``active`` False for an
    inactive feature (:func:`_hit_in_b`).

    With ``P = p_a + lam r`` on the plane, ``dP = lam P(r, N) dr``; ``dh = (I - h h^T) dg /
    |g|``; ``B = B(q_b)`` is :func:`factors.cdtm_math.orthonormal_complement`'s basis.
    (Moving a hit along its tangent plane changes the plane only at second order, so
    holding the planes is exact to first order where they are re-cast.)"""
    r0, r1, r2, Nr, lam, g0, g1, g2 = _hit_in_b(i, R_a, p_a, R_b, p_b, q_a, G_E, N)
    if np.isnan(lam):
        return False, 0.0, 0.0, 0.0, 0.0
    gn = np.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
    h0, h1, h2 = g0 / gn, g1 / gn, g2 / gn
    # camera a's ray: dr = R_a dq_a, dP = lam (dr - r (N.dr) / N.r), dg = R_b^T dP
    dr0 = R_a[0, 0] * dqa0 + R_a[0, 1] * dqa1
    dr1 = R_a[1, 0] * dqa0 + R_a[1, 1] * dqa1
    dr2 = R_a[2, 0] * dqa0 + R_a[2, 1] * dqa1
    Ndr = (N[i, 0] * dr0 + N[i, 1] * dr1 + N[i, 2] * dr2) / Nr
    dP0, dP1, dP2 = lam * (dr0 - r0 * Ndr), lam * (dr1 - r1 * Ndr), lam * (dr2 - r2 * Ndr)
    dg0 = R_b[0, 0] * dP0 + R_b[1, 0] * dP1 + R_b[2, 0] * dP2
    dg1 = R_b[0, 1] * dP0 + R_b[1, 1] * dP1 + R_b[2, 1] * dP2
    dg2 = R_b[0, 2] * dP0 + R_b[1, 2] * dP1 + R_b[2, 2] * dP2
    hdg = h0 * dg0 + h1 * dg1 + h2 * dg2
    dh0, dh1, dh2 = (dg0 - h0 * hdg) / gn, (dg1 - h1 * hdg) / gn, (dg2 - h2 * hdg) / gn
    # camera b's ray and its basis: b1 = (qz, 0, -qx) / |(qx, qz)|, b2 = q^ x b1
    qx, qy, qz = q_b[i, 0], q_b[i, 1], q_b[i, 2]
    rho = np.sqrt(qx * qx + qz * qz)
    b10, b12 = qz / rho, -qx / rho
    db10 = -qz * qx * dqx / rho**3
    db12 = -dqx / rho + qx * qx * dqx / rho**3
    qn = np.sqrt(qx * qx + qy * qy + qz * qz)
    u0, u1, u2 = qx / qn, qy / qn, qz / qn
    udq = (u0 * dqx + u1 * dqy) / qn
    du0, du1, du2 = dqx / qn - u0 * udq, dqy / qn - u1 * udq, -u2 * udq
    b20, b21, b22 = u1 * b12, u2 * b10 - u0 * b12, -u1 * b10
    db20 = du1 * b12 + u1 * db12
    db21 = du2 * b10 + u2 * db10 - du0 * b12 - u0 * db12
    db22 = -du1 * b10 - u1 * db10
    e0 = b10 * h0 + b12 * h2
    e1 = b20 * h0 + b21 * h1 + b22 * h2
    de0 = db10 * h0 + db12 * h2 + b10 * dh0 + b12 * dh2
    de1 = db20 * h0 + db21 * h1 + db22 * h2 + b20 * dh0 + b21 * dh1 + b22 * dh2
    return True, e0, e1, de0, de1


@njit(cache=True)
def focal_scale_kernel(R_a, p_a, R_b, p_b, q_a, q_b, G_E, N, sqrt_info, one_plus_s, kernel,
                       kernel_k, out):
    """``d e / d s`` of the whitened, reweighted residuals of n features w.r.t. the focal
    scale ``s`` (:mod:`factors.calibration`), the poses and the tangent planes held.

    The rays are the corrected ones at ``s``, ``q = [q0_xy / (1 + s), 1]``, so
    ``dq/ds = -[q_xy, 0] / (1 + s)`` moves both rays (:func:`_ray_move`); the whitening is
    ``S0 (1 + s)`` (``sqrt_info``), so ``dS/ds = S / (1 + s)``; the row is reweighted by
    the feature's sqrt weight, as :func:`cdtm_linearize` weighs its Jacobians.

    Args:
        R_a, p_a, R_b, p_b, G_E, N, kernel, kernel_k: as :func:`cdtm_linearize`.
        q_a, q_b: (n, 3) the corrected rays (z = 1). sqrt_info: (n, 2, 2) at ``s``.
        one_plus_s: ``1 + s``. out: (n, 2) output; zero rows for inactive features.
    """
    k = -1.0 / one_plus_s
    for i in range(q_a.shape[0]):
        out[i, 0] = 0.0
        out[i, 1] = 0.0
        active, e0, e1, de0, de1 = _ray_move(i, R_a, p_a, R_b, p_b, q_a, q_b, G_E, N,
                                             k * q_a[i, 0], k * q_a[i, 1],
                                             k * q_b[i, 0], k * q_b[i, 1])
        if not active:
            continue
        S00, S01, S10, S11 = sqrt_info[i, 0, 0], sqrt_info[i, 0, 1], sqrt_info[i, 1, 0], \
            sqrt_info[i, 1, 1]
        w0 = S00 * e0 + S01 * e1
        w1 = S10 * e0 + S11 * e1
        s = np.sqrt(w0 * w0 + w1 * w1)
        sw = np.sqrt(robust_weight(kernel, kernel_k[i], s)) if kernel != KERNEL_NONE else 1.0
        # d(S e) = S de + (dS/ds) e, dS/ds = S / (1 + s)
        out[i, 0] = sw * (S00 * de0 + S01 * de1 + w0 / one_plus_s)
        out[i, 1] = sw * (S10 * de0 + S11 * de1 + w1 / one_plus_s)


@njit(cache=True)
def principal_point_kernel(R_a, p_a, R_b, p_b, q_a, q_b, G_E, N, sqrt_info, one_plus_s,
                           kernel, kernel_k, J_a, J_b, out):
    """``d e / d c`` of the whitened, reweighted residuals of n features w.r.t. a shift
    ``c`` of the principal point in (distorted) normalized coordinates (``[dcx / fx,
    dcy / fy]``), the poses, the focal scale and the tangent planes held.

    A pixel's distorted normalized coordinates move by ``-c``; its undistorted ray by
    ``-J c`` (``J``: the undistortion's Jacobian there, the identity without distortion),
    under the focal scale ``/ (1 + s)`` (:func:`_ray_move`, each ray by its own ``J``); the
    whitening does not depend on ``c``.

    Args:
        as :func:`focal_scale_kernel`. J_a, J_b: (n, 2, 2) ``J`` at each feature's two
        sightings. out: (n, 2, 2) output, ``out[i, :, j] = d e_i / d c_j``; zero for
        inactive features.
    """
    k = -1.0 / one_plus_s
    for i in range(q_a.shape[0]):
        for j in range(2):
            out[i, 0, j] = 0.0
            out[i, 1, j] = 0.0
        for j in range(2):
            active, e0, e1, de0, de1 = _ray_move(i, R_a, p_a, R_b, p_b, q_a, q_b, G_E, N,
                                                 k * J_a[i, 0, j], k * J_a[i, 1, j],
                                                 k * J_b[i, 0, j], k * J_b[i, 1, j])
            if not active:
                break
            S00, S01, S10, S11 = sqrt_info[i, 0, 0], sqrt_info[i, 0, 1], \
                sqrt_info[i, 1, 0], sqrt_info[i, 1, 1]
            w0 = S00 * e0 + S01 * e1
            w1 = S10 * e0 + S11 * e1
            s = np.sqrt(w0 * w0 + w1 * w1)
            sw = np.sqrt(robust_weight(kernel, kernel_k[i], s)) if kernel != KERNEL_NONE \
                else 1.0
            out[i, 0, j] = sw * (S00 * de0 + S01 * de1)
            out[i, 1, j] = sw * (S10 * de0 + S11 * de1)


#: Rows of a compressed pair factor: 12 pose columns plus the residual column.
COMPRESSED_ROWS = 13


#: Below this fraction of its squared norm left as a Cholesky pivot, a column has lost
#: too many digits to the normal equations (~1e-16 / fraction relative error in that
#: direction's information): Householder redoes the triangle.
_MIN_PIVOT_FRACTION = 1e-6


@njit(cache=True)
def triangularize(e, Ha, Hb, work, Ja_out, Jb_out, z_out):
    """The 13 x 13 triangle ``[Ja Jb | z]`` of the stacked ``[Ha Hb | e]`` (2n, 13).

    ``[Ja Jb | z]^T [Ja Jb | z] = [Ha Hb | e]^T [Ha Hb | e]``, so
    ``|Ja da + Jb db + z|^2 = |Ha da + Hb db + e|^2`` for every step: the square-root
    information form of the pair, and a factor of 2n rows becomes one of 13 (GTSAM's
    elimination never sees the tall block). Cholesky of the 13 x 13 Gram matrix is
    ~3x cheaper than Householder QR; when a pose column's pivot keeps less than
    ``_MIN_PIVOT_FRACTION`` of its norm (rank-deficient or ill-conditioned pairs, e.g.
    flat ground) the triangle comes from Householder QR instead.

    Args:
        e: (n, 2) residuals. Ha, Hb: (n, 2, 6) Jacobians; 2n >= 13.
        work: (13, >= max(13, 2n)) scratch.
        Ja_out, Jb_out: (13, 6) outputs. z_out: (13,) output; its last entry is the
            residual left outside the Jacobians' range, so ``|z| = |e|`` (to rounding).
    """
    if not _gram_triangle(e, Ha, Hb, Ja_out, Jb_out, z_out):
        _householder_triangle(e, Ha, Hb, work, Ja_out, Jb_out, z_out)


@njit(cache=True, inline="always")
def _gram_triangle(e, Ha, Hb, Ja_out, Jb_out, z_out):
    """Upper Cholesky factor of the Gram matrix; False if a pose column lost its pivot."""
    c = COMPRESSED_ROWS
    G = np.zeros((c, c))
    row = np.empty(c)
    for i in range(e.shape[0]):
        for k in range(2):
            for j in range(6):
                row[j] = Ha[i, k, j]
                row[6 + j] = Hb[i, k, j]
            row[12] = e[i, k]
            for p in range(c):
                rp = row[p]
                for q in range(p, c):
                    G[p, q] += rp * row[q]
    for j in range(c):
        norm2 = G[j, j]
        d = norm2
        for m in range(j):
            d -= G[m, j] * G[m, j]
        if j < c - 1 and not d > _MIN_PIVOT_FRACTION * norm2:
            return False
        # The residual column's pivot only sets the constant |e|^2 - |z|^2.
        r = np.sqrt(d) if d > 0.0 else 0.0
        G[j, j] = r
        for q in range(j + 1, c):
            s = G[j, q]
            for m in range(j):
                s -= G[m, j] * G[m, q]
            G[j, q] = s / r if r > 0.0 else 0.0
    # the triangle out (here and in _householder_triangle, not one helper with a
    # `transposed` flag: numba compiled such a helper once per constant flag)
    for r in range(c):
        for j in range(6):
            Ja_out[r, j] = G[r, j] if j >= r else 0.0
            Jb_out[r, j] = G[r, 6 + j] if 6 + j >= r else 0.0
        z_out[r] = G[r, 12]
    return True


@njit(cache=True, inline="always")
def _householder_triangle(e, Ha, Hb, work, Ja_out, Jb_out, z_out):
    """Householder QR of the stacked rows (their columns held as rows of ``work``)."""
    n = e.shape[0]
    m = 2 * n
    c = COMPRESSED_ROWS
    for i in range(n):
        for k in range(2):
            row = 2 * i + k
            for j in range(6):
                work[j, row] = Ha[i, k, j]
                work[6 + j, row] = Hb[i, k, j]
            work[12, row] = e[i, k]
    for j in range(c):
        x = work[j]
        norm2 = 0.0
        for i in range(j, m):
            norm2 += x[i] * x[i]
        norm = np.sqrt(norm2)
        if norm == 0.0:
            continue  # a zero column below the diagonal: nothing to reflect
        alpha = -norm if x[j] >= 0.0 else norm
        v0 = x[j] - alpha
        vtv = v0 * v0 + norm2 - x[j] * x[j]
        if vtv > 0.0:
            beta = 2.0 / vtv
            for k in range(j + 1, c):
                y = work[k]
                s = v0 * y[j]
                for i in range(j + 1, m):
                    s += x[i] * y[i]
                s *= beta
                y[j] -= s * v0
                for i in range(j + 1, m):
                    y[i] -= s * x[i]
        x[j] = alpha
    for r in range(c):  # the triangle out, transposed back
        for j in range(6):
            Ja_out[r, j] = work[j, r] if j >= r else 0.0
            Jb_out[r, j] = work[6 + j, r] if 6 + j >= r else 0.0
        z_out[r] = work[12, r]


@njit(cache=True, inline="always")
def _np_apply(q, qq, g, gn, x, out):
    """out = N_P(q, g) x = P(q, q) P(g, g) x / |g| (eq. 14)."""
    gx = (g[0] * x[0] + g[1] * x[1] + g[2] * x[2]) / (gn * gn)
    y0, y1, y2 = x[0] - g[0] * gx, x[1] - g[1] * gx, x[2] - g[2] * gx
    qy = (q[0] * y0 + q[1] * y1 + q[2] * y2) / qq
    out[0] = (y0 - q[0] * qy) / gn
    out[1] = (y1 - q[1] * qy) / gn
    out[2] = (y2 - q[2] * qy) / gn


@njit(cache=True)
def feature_covariance_kernel(R_a, p_a, R_b, p_b, q_a, q_b, G_E, N, sx, sy, sigma_h,
                              sax, say, Sigma_out, Sigma_full_out):
    # sigma_h: (n,) DTM height 1-sigma per feature
    """Sigma_f of eqs. 19-26 per feature, as a sum of rank-one terms (n, 3, 3).

    ``Sigma_full_out`` gets the covariance of a single residual's data as measured: with
    ``q_a``'s pixel noise (``sx, sy``) whatever ``sax, say`` say (a residual tested on its
    own carries both observations' noise; the factors leave ``q_a``'s out because each
    observation is ``q_b`` of one pair and ``q_a`` of the next).

    The same formula as :func:`factors.cdtm_math.feature_covariance` (the tested
    reference): ``J_q Sigma_q J_q^T`` has one term per noisy image axis, and the DTM
    term is ``sigma_h^2 u u^T`` with ``u = J_G dG_E/dh = N_P R_b^T r / N.r`` (eqs. 20, 25).
    ``sax = say = 0`` leaves ``q_a`` exact (the paper).
    """
    n = q_a.shape[0]
    r = np.empty(3)
    g = np.empty(3)
    x = np.empty(3)
    w = np.empty(3)
    cols = np.empty((7, 3))
    for i in range(n):
        for a in range(3):
            r[a] = R_a[a, 0] * q_a[i, 0] + R_a[a, 1] * q_a[i, 1] + R_a[a, 2] * q_a[i, 2]
        Nr = N[i, 0] * r[0] + N[i, 1] * r[1] + N[i, 2] * r[2]
        lam = (N[i, 0] * (G_E[i, 0] - p_a[0]) + N[i, 1] * (G_E[i, 1] - p_a[1])
               + N[i, 2] * (G_E[i, 2] - p_a[2])) / Nr
        d0 = p_a[0] + lam * r[0] - p_b[0]
        d1 = p_a[1] + lam * r[1] - p_b[1]
        d2 = p_a[2] + lam * r[2] - p_b[2]
        for a in range(3):
            g[a] = R_b[0, a] * d0 + R_b[1, a] * d1 + R_b[2, a] * d2
        gn = np.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2])
        q = q_b[i]
        qq = q[0] * q[0] + q[1] * q[1] + q[2] * q[2]
        qg = q[0] * g[0] + q[1] * g[1] + q[2] * g[2]
        # eq. 19 columns x, y: -[(q.g) I + q g^T] P(q,q) e_c / (|q|^2 |g|)
        for c in range(2):
            pc0 = -q[0] * q[c] / qq
            pc1 = -q[1] * q[c] / qq
            pc2 = -q[2] * q[c] / qq
            if c == 0:
                pc0 += 1.0
            else:
                pc1 += 1.0
            gp = g[0] * pc0 + g[1] * pc1 + g[2] * pc2
            scale = (sx if c == 0 else sy) / (qq * gn)
            cols[c, 0] = -(qg * pc0 + q[0] * gp) * scale
            cols[c, 1] = -(qg * pc1 + q[1] * gp) * scale
            cols[c, 2] = -(qg * pc2 + q[2] * gp) * scale
        # DTM height: sigma_h N_P R_b^T r / N.r
        for a in range(3):
            x[a] = (R_b[0, a] * r[0] + R_b[1, a] * r[1] + R_b[2, a] * r[2]) * sigma_h[i] / Nr
        _np_apply(q, qq, g, gn, x, w)
        cols[2, 0], cols[2, 1], cols[2, 2] = w[0], w[1], w[2]
        # q_a columns: lam N_P R_b^T P(r, N) R_a e_c, as configured (sax, say); when the
        # factor leaves q_a exact, the full covariance gets them at the pixel noise.
        configured = sax != 0.0 or say != 0.0
        m = m_configured = 3
        for c in range(4):
            s = (sax, say, sx, sy)[c]
            if s == 0.0 or (c >= 2 and configured):
                continue
            v0, v1, v2 = R_a[0, c % 2], R_a[1, c % 2], R_a[2, c % 2]
            nv = (N[i, 0] * v0 + N[i, 1] * v1 + N[i, 2] * v2) / Nr
            v0 -= r[0] * nv
            v1 -= r[1] * nv
            v2 -= r[2] * nv
            for a in range(3):
                x[a] = (R_b[0, a] * v0 + R_b[1, a] * v1 + R_b[2, a] * v2) * lam * s
            _np_apply(q, qq, g, gn, x, w)
            cols[m, 0], cols[m, 1], cols[m, 2] = w[0], w[1], w[2]
            m += 1
            if c < 2:
                m_configured = m
        for a in range(3):
            for b in range(3):
                acc = 0.0
                for k in range(m_configured):
                    acc += cols[k, a] * cols[k, b]
                Sigma_out[i, a, b] = acc
                for k in range(m_configured, m):
                    acc += cols[k, a] * cols[k, b]
                Sigma_full_out[i, a, b] = acc


@njit(cache=True)
def residual_noise_kernel(q_b, Sigma_f, basis_out, Sigma_e_out, sqrt_info_out):
    """Per feature: the basis ``B`` of q_b's complement, ``Sigma_e = B^T Sigma_f B`` and
    its upper-triangular whitening ``S`` (``S^T S = Sigma_e^-1``).

    numba twin of :func:`factors.cdtm_math.orthonormal_complement`,
    :func:`~factors.cdtm_math.residual_covariance` and
    :func:`~factors.cdtm_math.sqrt_information` (tested equal).
    """
    for i in range(q_b.shape[0]):
        qn = np.sqrt(q_b[i, 0] ** 2 + q_b[i, 1] ** 2 + q_b[i, 2] ** 2)
        x, y, z = q_b[i, 0] / qn, q_b[i, 1] / qn, q_b[i, 2] / qn
        s = 1.0 / np.sqrt(x * x + z * z)
        b00, b10, b20 = z * s, 0.0, -x * s  # e_y x q / |.|
        b01, b11, b21 = y * b20, z * b00 - x * b20, -y * b00  # q x b1
        basis_out[i, 0, 0], basis_out[i, 1, 0], basis_out[i, 2, 0] = b00, b10, b20
        basis_out[i, 0, 1], basis_out[i, 1, 1], basis_out[i, 2, 1] = b01, b11, b21
        F = Sigma_f[i]
        f0 = F[0, 0] * b00 + F[0, 1] * b10 + F[0, 2] * b20  # Sigma_f b1
        f1 = F[1, 0] * b00 + F[1, 1] * b10 + F[1, 2] * b20
        f2 = F[2, 0] * b00 + F[2, 1] * b10 + F[2, 2] * b20
        g0 = F[0, 0] * b01 + F[0, 1] * b11 + F[0, 2] * b21  # Sigma_f b2
        g1 = F[1, 0] * b01 + F[1, 1] * b11 + F[1, 2] * b21
        g2 = F[2, 0] * b01 + F[2, 1] * b11 + F[2, 2] * b21
        s00 = b00 * f0 + b10 * f1 + b20 * f2
        s01 = b00 * g0 + b10 * g1 + b20 * g2
        s10 = b01 * f0 + b11 * f1 + b21 * f2
        s11 = b01 * g0 + b11 * g1 + b21 * g2
        Sigma_e_out[i, 0, 0], Sigma_e_out[i, 0, 1] = s00, s01
        Sigma_e_out[i, 1, 0], Sigma_e_out[i, 1, 1] = s10, s11
        det = s00 * s11 - s01 * s01
        a = np.sqrt(s11 / det)
        b = -s01 / det / a
        sqrt_info_out[i, 0, 0], sqrt_info_out[i, 0, 1] = a, b
        sqrt_info_out[i, 1, 0], sqrt_info_out[i, 1, 1] = 0.0, np.sqrt(s00 / det - b * b)
