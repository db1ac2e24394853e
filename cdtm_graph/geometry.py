"""Rotation and pose helpers on plain numpy (no GTSAM), vectorized or compiled where it
matters; the triangulation of many tracks at once and the closed-form symmetric 3x3
algebra it shares.

Conventions (docs/flightlog.md): quaternions are Hamilton, stored w first, and rotate
body-frame vectors into the world frame; a pose ``a_T_b`` is a 4x4 matrix with
``x_a = R_ab x_b + t_ab``.
"""

from __future__ import annotations

import numpy as np

from factors.jit import njit


def quat_wxyz_to_rotation(quat_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrices from unit quaternions.

    Args:
        quat_wxyz: (..., 4) quaternions, w first; normalized here.

    Returns:
        (..., 3, 3) rotation matrices.
    """
    q = np.asarray(quat_wxyz, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def rotation_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (w first, w >= 0) from rotation matrices, (..., 3, 3) -> (..., 4)."""
    R = np.asarray(R, dtype=float)
    m = R.reshape(-1, 3, 3)
    out = np.empty((m.shape[0], 4))
    tr = np.trace(m, axis1=1, axis2=2)
    # Pick the numerically largest component per matrix (Shepperd's method).
    diag = np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1)
    k = np.argmax(diag, axis=1)
    for case in range(4):
        s = k == case
        if not np.any(s):
            continue
        a = m[s]
        if case == 0:
            r = np.sqrt(1.0 + tr[s]) * 2
            q = np.stack([0.25 * r, (a[:, 2, 1] - a[:, 1, 2]) / r,
                          (a[:, 0, 2] - a[:, 2, 0]) / r, (a[:, 1, 0] - a[:, 0, 1]) / r], 1)
        elif case == 1:
            r = np.sqrt(1.0 + a[:, 0, 0] - a[:, 1, 1] - a[:, 2, 2]) * 2
            q = np.stack([(a[:, 2, 1] - a[:, 1, 2]) / r, 0.25 * r,
                          (a[:, 0, 1] + a[:, 1, 0]) / r, (a[:, 0, 2] + a[:, 2, 0]) / r], 1)
        elif case == 2:
            r = np.sqrt(1.0 + a[:, 1, 1] - a[:, 0, 0] - a[:, 2, 2]) * 2
            q = np.stack([(a[:, 0, 2] - a[:, 2, 0]) / r, (a[:, 0, 1] + a[:, 1, 0]) / r,
                          0.25 * r, (a[:, 1, 2] + a[:, 2, 1]) / r], 1)
        else:
            r = np.sqrt(1.0 + a[:, 2, 2] - a[:, 0, 0] - a[:, 1, 1]) * 2
            q = np.stack([(a[:, 1, 0] - a[:, 0, 1]) / r, (a[:, 0, 2] + a[:, 2, 0]) / r,
                          (a[:, 1, 2] + a[:, 2, 1]) / r, 0.25 * r], 1)
        out[s] = q
    out *= np.where(out[:, :1] < 0, -1.0, 1.0)
    return out.reshape(R.shape[:-2] + (4,))


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices, (..., 3) -> (..., 3, 3), with ``skew(a) @ b == cross(a, b)``."""
    v = np.asarray(v, dtype=float)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def so3_exp(omega: np.ndarray) -> np.ndarray:
    """Rodrigues' formula, (..., 3) rotation vectors -> (..., 3, 3)."""
    w = np.asarray(omega, dtype=float)
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew(w)
    small = th < 1e-8
    th_safe = np.where(small, 1.0, th)
    a = np.where(small, 1.0, np.sin(th_safe) / th_safe)
    b = np.where(small, 0.5, (1 - np.cos(th_safe)) / th_safe**2)
    return np.eye(3) + a * K + b * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vectors of rotation matrices, (..., 3, 3) -> (..., 3) (angle < pi).

    The angle comes from ``atan2(|vee(R - R^T)|, tr R - 1)``, accurate near zero where
    ``arccos`` of the trace loses half the digits.
    """
    R = np.asarray(R, dtype=float)
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                  R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    s2 = np.linalg.norm(v, axis=-1)  # 2 sin(angle)
    th = np.arctan2(s2, np.trace(R, axis1=-2, axis2=-1) - 1)
    scale = np.where(s2 < 1e-12, 0.5, th / np.where(s2 < 1e-12, 1.0, s2))
    return v * scale[..., None]


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform from a rotation and a translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 rigid transform."""
    R, t = T[:3, :3], T[:3, 3]
    return make_pose(R.T, -R.T @ t)


def rigid_motion_transfer(at_m: np.ndarray, about_m: np.ndarray) -> np.ndarray:
    """A small rigid motion of the world written about one point, as seen at another.

    The motion ``x -> x + omega x (x - about) + t`` is, about ``at``, ``[omega, t + omega x
    (at - about)]``. The returned matrix maps ``[omega, t]`` (world axes, about
    ``about_m``) to that; information on the motion about ``at`` becomes information
    about ``about`` as ``A^T I A``.

    Args:
        at_m, about_m: (..., 3) points (m), broadcast together.

    Returns:
        (..., 6, 6) ``[[I, 0], [-skew(at - about), I]]``, order [rotation, translation].
    """
    lever = np.asarray(at_m, dtype=float) - np.asarray(about_m, dtype=float)
    A = np.zeros(lever.shape[:-1] + (6, 6))
    A[..., :3, :3] = np.eye(3)
    A[..., 3:, 3:] = np.eye(3)
    A[..., 3:, :3] = -skew(lever)
    return A


def rigid_motion_to_tangent(world_T_body: np.ndarray, about_m: np.ndarray) -> np.ndarray:
    """(6, 6) map from a small rigid motion of the world ``[omega, t]`` (world axes, about
    ``about_m``; :func:`rigid_motion_transfer`) to the pose's GTSAM tangent [rot, trans]
    (right perturbation, body frame): ``R -> Exp(omega) R``, ``p -> p + omega x (p - about)
    + t``, i.e. ``[R^T omega, R^T (omega x (p - about) + t)]``."""
    T = np.asarray(world_T_body, dtype=float)
    # blockdiag(R^T, R^T) @ transfer as one broadcast product (np.kron costs more per factor)
    transfer = rigid_motion_transfer(T[:3, 3], about_m)
    return (T[:3, :3].T @ transfer.reshape(2, 3, 6)).reshape(6, 6)


def rays_in_world(world_T_cam: np.ndarray, camera: np.ndarray, ray_cam: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Observations' camera centres and rays in the world.

    Args:
        world_T_cam: (F, 4, 4) the cameras. camera: (M,) each observation's camera (an
            index into ``world_T_cam``). ray_cam: (M, 3) its ray in its camera.

    Returns:
        ``centre`` (M, 3) and ``ray`` (M, 3) (``R ray_cam``, not normalized).
    """
    centre = np.empty((camera.shape[0], 3))
    ray = np.empty((camera.shape[0], 3))
    # compiled: a flight's observations gathered as (M, 3, 3) rotations cost ~10x more
    _rays_in_world_kernel(np.ascontiguousarray(world_T_cam, dtype=np.float64),
                          np.ascontiguousarray(camera, dtype=np.int64),
                          np.ascontiguousarray(ray_cam, dtype=np.float64), centre, ray)
    return centre, ray


@njit(cache=True)
def _rays_in_world_kernel(world_T_cam, camera, ray_cam, centre, ray):
    for m in range(camera.shape[0]):
        T = world_T_cam[camera[m]]
        for r in range(3):
            centre[m, r] = T[r, 3]
            ray[m, r] = T[r, 0] * ray_cam[m, 0] + T[r, 1] * ray_cam[m, 1] + T[r, 2] * ray_cam[m, 2]


def largest_eigenvalue_sym3(A: np.ndarray) -> float:
    """The largest eigenvalue of a symmetric 3x3 (a covariance's largest variance)."""
    # (contiguous: a view of a larger covariance would compile the kernel a second time)
    return float(sym3_eigenvalue_range(np.ascontiguousarray(A, dtype=np.float64))[1])


@njit(cache=True)
def sym3_eigenvalue_range(A: np.ndarray) -> tuple[float, float]:
    """The smallest and largest eigenvalues of a symmetric 3x3, in closed form (the
    trigonometric solution of the characteristic cubic; LAPACK per matrix costs more than
    what asks for them)."""
    off = A[0, 1] ** 2 + A[0, 2] ** 2 + A[1, 2] ** 2
    q = (A[0, 0] + A[1, 1] + A[2, 2]) / 3.0
    p2 = (A[0, 0] - q) ** 2 + (A[1, 1] - q) ** 2 + (A[2, 2] - q) ** 2 + 2.0 * off
    if p2 <= 0.0:  # a multiple of the identity
        return q, q
    p = np.sqrt(p2 / 6.0)
    b00, b11, b22 = (A[0, 0] - q) / p, (A[1, 1] - q) / p, (A[2, 2] - q) / p
    b01, b02, b12 = A[0, 1] / p, A[0, 2] / p, A[1, 2] / p
    half_det = 0.5 * (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02)
                      + b02 * (b01 * b12 - b11 * b02))
    phi = np.arccos(min(max(half_det, -1.0), 1.0)) / 3.0
    return q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0), q + 2.0 * p * np.cos(phi)


def triangulate(track_index: np.ndarray, n_tracks: int, centre_m: np.ndarray,
                ray_world: np.ndarray, sigma_rad: float | np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares points of many tracks at once, their covariances and fit.

    Each observation constrains its track's point to its ray; the point minimizes the
    sum of squared angular errors (perpendicular distance over range, ranges from a
    first unweighted pass).

    Args:
        track_index: (M,) which track (0..T-1) each observation belongs to.
        n_tracks: T.
        centre_m: (M, 3) the observing camera's centre. ray_world: (M, 3) its ray.
        sigma_rad: 1-sigma angular error of one observation, scalar or (M,).

    Returns:
        points (T, 3), covariances (T, 3, 3) and the fit's chi-square (T,) (squared angular
        misses in sigmas, ``2 n - 3`` degrees of freedom for n rays); NaN where the rays do
        not fix a point.
    """
    m = np.asarray(track_index).shape[0]
    points = np.empty((n_tracks, 3))
    cov = np.empty((n_tracks, 3, 3))
    chi2_fit = np.empty(n_tracks)
    # (one compiled pass: the grouped sums and 3x3 solves were most of a frame's judgement)
    _triangulate_kernel(np.ascontiguousarray(track_index, np.int64),
                        np.ascontiguousarray(centre_m, float),
                        np.ascontiguousarray(ray_world, float),
                        np.ascontiguousarray(np.broadcast_to(sigma_rad, (m,)), float),
                        points, cov, chi2_fit)
    return points, cov, chi2_fit


@njit(cache=True, inline="always")
def _well_conditioned(A: np.ndarray) -> bool:
    """Whether a symmetric positive semi-definite 3x3's smallest eigenvalue exceeds 1e-12
    of its largest (in closed form: LAPACK per track cost more than the rest of the
    triangulation)."""
    smallest, largest = sym3_eigenvalue_range(A)
    return smallest > 1e-12 * max(largest, 1e-300)


@njit(cache=True, inline="always")
def _inverse_sym3(A: np.ndarray, out: np.ndarray) -> None:
    """The inverse of a regular symmetric 3x3 (its adjugate over its determinant)."""
    c00 = A[1, 1] * A[2, 2] - A[1, 2] * A[1, 2]
    c01 = A[0, 2] * A[1, 2] - A[0, 1] * A[2, 2]
    c02 = A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]
    c11 = A[0, 0] * A[2, 2] - A[0, 2] * A[0, 2]
    c12 = A[0, 1] * A[0, 2] - A[0, 0] * A[1, 2]
    c22 = A[0, 0] * A[1, 1] - A[0, 1] * A[0, 1]
    det = A[0, 0] * c00 + A[0, 1] * c01 + A[0, 2] * c02
    out[0, 0], out[0, 1], out[0, 2] = c00 / det, c01 / det, c02 / det
    out[1, 0], out[1, 1], out[1, 2] = c01 / det, c11 / det, c12 / det
    out[2, 0], out[2, 1], out[2, 2] = c02 / det, c12 / det, c22 / det


@njit(cache=True)
def _triangulate_kernel(track_index: np.ndarray, centre: np.ndarray, ray: np.ndarray,
                        sigma: np.ndarray, points: np.ndarray, cov: np.ndarray,
                        chi2_fit: np.ndarray) -> None:
    """:func:`triangulate` into ``points``, ``cov``, ``chi2_fit`` (T rows each)."""
    m, n_tracks = track_index.shape[0], points.shape[0]
    d = np.empty((m, 3))
    for i in range(m):
        norm = np.sqrt(ray[i, 0] ** 2 + ray[i, 1] ** 2 + ray[i, 2] ** 2)
        for r in range(3):
            d[i, r] = ray[i, r] / norm
    weight = np.ones(m)
    A = np.empty((n_tracks, 3, 3))
    b = np.empty((n_tracks, 3))
    # (element by element throughout: numba's slice stores cost ~1 s of compilation each)
    for _ in range(2):
        for t in range(n_tracks):
            for r in range(3):
                b[t, r] = 0.0
                for c in range(3):
                    A[t, r, c] = 0.0
        for i in range(m):
            t, w = track_index[i], weight[i]
            dc = d[i, 0] * centre[i, 0] + d[i, 1] * centre[i, 1] + d[i, 2] * centre[i, 2]
            for r in range(3):
                b[t, r] += w * (centre[i, r] - d[i, r] * dc)  # w P c, P = I - d d^T
                for c in range(3):
                    A[t, r, c] += w * ((1.0 if r == c else 0.0) - d[i, r] * d[i, c])
        for t in range(n_tracks):
            if _well_conditioned(A[t]):
                _inverse_sym3(A[t], cov[t])  # with weights 1/(sigma r)^2: the covariance
                for r in range(3):
                    points[t, r] = (cov[t, r, 0] * b[t, 0] + cov[t, r, 1] * b[t, 1]
                                    + cov[t, r, 2] * b[t, 2])
            else:
                for r in range(3):
                    points[t, r] = np.nan
                    for c in range(3):
                        cov[t, r, c] = np.nan
        for i in range(m):
            t = track_index[i]
            range_m = np.sqrt((points[t, 0] - centre[i, 0]) ** 2
                              + (points[t, 1] - centre[i, 1]) ** 2
                              + (points[t, 2] - centre[i, 2]) ** 2)
            if not np.isfinite(range_m):
                range_m = 1.0
            weight[i] = 1.0 / max(sigma[i] * range_m, 1e-12) ** 2
    for t in range(n_tracks):
        chi2_fit[t] = 0.0
    for i in range(m):
        t = track_index[i]
        x0, x1, x2 = (points[t, 0] - centre[i, 0], points[t, 1] - centre[i, 1],
                      points[t, 2] - centre[i, 2])
        along = d[i, 0] * x0 + d[i, 1] * x1 + d[i, 2] * x2
        chi2_fit[t] += weight[i] * ((x0 - along * d[i, 0]) ** 2 + (x1 - along * d[i, 1]) ** 2
                                    + (x2 - along * d[i, 2]) ** 2)
    for t in range(n_tracks):
        if not np.isfinite(points[t, 0]):
            chi2_fit[t] = np.nan
