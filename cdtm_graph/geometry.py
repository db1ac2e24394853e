"""Rotation and pose helpers on plain numpy (no GTSAM), vectorized or compiled where it
matters.

Conventions (docs/flightlog.md): quaternions are Hamilton, stored w first, and rotate
body-frame vectors into the world frame; a pose ``a_T_b`` is a 4x4 matrix with
``x_a = R_ab x_b + t_ab``.
"""

from __future__ import annotations

import numpy as np
from numba import njit


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
    return float(sym3_eigenvalue_range(np.asarray(A, dtype=np.float64))[1])


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
