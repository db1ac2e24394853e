"""The calibrated side of the C-DTM pair factor: the camera calibration as its third
variable.

With a :class:`~factors.calibration.CalibrationLink` that has a key, a
:class:`~factors.cdtm_factor.CdtmPairFactor` also depends on the calibration (time offset,
mount rotation, focal scale; a 5-vector): its residuals are evaluated with the bodies
shifted over the time offset, the mount corrected and the rays rescaled, and its
Jacobians chained to the calibration. This mixin holds that evaluation; the factor itself
(:mod:`factors.cdtm_factor`) holds the features, the planes and the plain evaluation.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import gtsam
import numpy as np

import factors.cdtm_math as cdtm_math
from factors.calibration import (
    CALIBRATION_DIM,
    FOCAL_SCALE,
    MOUNT,
    TIME_OFFSET,
    CalibrationLink,
    corrected_mount,
    corrected_rays,
    mount_jacobian,
    shift,
    shift_adjoint,
)
from factors.kernel import (
    KERNEL_NONE,
    cdtm_linearize,
    focal_scale_kernel,
    principal_point_kernel,
)

if TYPE_CHECKING:
    from factors.cdtm_factor import PairFeatures, RobustKernel

#: Rays (m, 3) -> the lens's undistortion Jacobian at them (m, 2, 2): how each undistorted
#: ray moves with its pixel's distorted normalized coordinates.
RayJacobian = Callable[[np.ndarray], np.ndarray]

#: ``cdtm_linearize``'s ``e_loss_out`` when only one kind of residual is wanted.
NO_LOSS = np.empty((0, 2))


#: Rows of a compressed pair factor that also holds the calibration: 12 pose columns,
#: 5 calibration columns and the residual column.
CALIBRATED_ROWS = 12 + CALIBRATION_DIM + 1


def pose_matrix(values: gtsam.Values, key: int) -> np.ndarray:
    return values.atPose3(key).matrix()



class CalibratedPair:
    """The calibration-dependent evaluation of :class:`~factors.cdtm_factor.CdtmPairFactor`
    (a mixin: it reads the factor's features, mount, planes and caches)."""

    features: PairFeatures
    body_T_cam: np.ndarray
    calibration: CalibrationLink | None
    robust: RobustKernel
    n_inactive: int
    key_a: int
    key_b: int
    _kernel_k: np.ndarray
    _compressed: bool
    _shifts: dict
    _rays: dict

    if TYPE_CHECKING:  # the factor's own
        def planes(self, world_T_cam_a: np.ndarray, focal_scale_minus_1: float = 0.0
                   ) -> tuple[np.ndarray, np.ndarray]: ...

    def _calibrated_kernel(self, world_T_body_a: np.ndarray, world_T_body_b: np.ndarray,
                           calibration: np.ndarray, kernel: int, want_jacobians: bool,
                           e: np.ndarray, Ha: np.ndarray, Hb: np.ndarray) -> np.ndarray:
        """The kernel at a calibration (5,); Jacobians w.r.t. the right perturbations of
        the bodies at exposure, ``X Exp(dt xi)``. Returns ``Ad(cam_T_body)`` of the
        corrected mount."""
        s = float(calibration[FOCAL_SCALE])
        shift_a, shift_b, body_T_cam, Ad, q_a, basis_b, sqrt_info = self._calibrated_setup(
            calibration)
        wTc_a = world_T_body_a @ shift_a @ body_T_cam
        wTc_b = world_T_body_b @ shift_b @ body_T_cam
        G_E, N = self.planes(wTc_a, s)
        self.n_inactive = cdtm_linearize(
            wTc_a[:3, :3], wTc_a[:3, 3], wTc_b[:3, :3], wTc_b[:3, 3], Ad, q_a, G_E, N,
            basis_b, sqrt_info, kernel, self._kernel_k, want_jacobians, e, Ha, Hb, NO_LOSS)
        return Ad

    #: Time offsets and focal scales whose derived quantities a factor keeps (a solve's
    #: current ones and its last rejected candidates).
    _SETUPS_KEPT = 4

    def _calibrated_setup(self, calibration: np.ndarray) -> tuple[np.ndarray, ...]:
        """What the kernel needs at a calibration (5,) besides the poses: the two body
        shifts over the time offset, the corrected mount and its adjoint (shared by every
        factor: :func:`_mount_at`), the corrected rays' ``q_a`` and ``q_b``'s basis, the
        whitening. Kept for the last few values: a solve asks for the same ones at every
        factor evaluation."""
        link = self.calibration
        assert link is not None
        dt, s = float(calibration[TIME_OFFSET]), float(calibration[FOCAL_SCALE])
        shifts = self._shifts.get(dt)
        if shifts is None:
            shifts = _kept(self._shifts, dt, (shift(link.twist_a, dt), shift(link.twist_b, dt)),
                           self._SETUPS_KEPT)
        rays = self._rays.get(s)
        if rays is None:
            f = self.features
            # The whitening was made for the nominal focal length: the pixel noise is
            # (1 + s) times smaller in the corrected normalized coordinates. Without this
            # the cost itself would fall as the focal length grows (every residual
            # shrinks), pulling the scale (and with it the height) off: +0.46% and 8 m on
            # a clean flight.
            rays = _kept(self._rays, s, (corrected_rays(f.q_a, s),
                                         cdtm_math.orthonormal_complement(
                                             corrected_rays(f.q_b, s)),
                                         f.sqrt_info * (1.0 + s)), self._SETUPS_KEPT)
        body_T_cam, Ad = _mount_at(self.body_T_cam.tobytes(),
                                   np.asarray(calibration[MOUNT], dtype=float).tobytes())
        return (*shifts, body_T_cam, Ad, *rays)

    def evaluate_calibrated(
        self, world_T_body_a: np.ndarray, world_T_body_b: np.ndarray,
        calibration: np.ndarray, want_jacobians: bool = True,
        robust: bool = True,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Whitened, reweighted residuals (n, 2) and Jacobians w.r.t. X(a), X(b) (n, 2, 6)
        and the calibration (n, 2, 5), at the calibration ``calibration`` (5,).

        The time offset and the mount are chained from the pose Jacobians, the focal scale
        is :func:`~factors.kernel.focal_scale_kernel`'s (all exact). Fresh arrays.
        ``robust=False``: no reweighting.
        """
        link = self.calibration
        if link is None:
            raise ValueError("a factor without a calibration link has no calibration")
        c = np.asarray(calibration, dtype=float)
        n = self.features.n
        kernel = self.robust.kernel_id if robust else KERNEL_NONE
        e, Ha, Hb = np.empty((n, 2)), np.empty((n, 2, 6)), np.empty((n, 2, 6))
        Ad = self._calibrated_kernel(world_T_body_a, world_T_body_b, c, kernel,
                                     want_jacobians, e, Ha, Hb)
        if not want_jacobians:
            return e, Ha, Hb, np.zeros((n, 2, CALIBRATION_DIM))
        # (as (2n, 6) rows: one matrix product each, not n small ones)
        J = self.chained(Ha.reshape(-1, 6), Hb.reshape(-1, 6), self._focal_scale_column(
            world_T_body_a, world_T_body_b, c, kernel).reshape(-1), c, Ad)
        return e, J[:, :6].reshape(n, 2, 6), J[:, 6:12].reshape(n, 2, 6), J[:, 12:].reshape(
            n, 2, CALIBRATION_DIM)

    def chained(self, rows_a: np.ndarray, rows_b: np.ndarray, focal: np.ndarray,
                calibration: np.ndarray, Ad: np.ndarray) -> np.ndarray:
        """Rows of Jacobians w.r.t. the shifted bodies, ``rows_a``, ``rows_b`` (m, 6), and
        the focal scale ``focal`` (m,), chained to ``[X(a), X(b), calibration]``: (m, 17).

        Linear in the rows, so a sum of rows chains as the rows do (the noise's expected
        gradient sums before it chains: :meth:`~factors.CdtmPairFactor.
        noise_cost_gradient`). ``Ad``: ``Ad(cam_T_body)`` of the corrected mount
        (:meth:`_calibrated_kernel`'s)."""
        link = self.calibration
        assert link is not None
        dt = float(calibration[TIME_OFFSET])
        out = np.empty((rows_a.shape[0], 12 + CALIBRATION_DIM))
        out[:, :6] = rows_a @ shift_adjoint(link.twist_a, dt)
        out[:, 6:12] = rows_b @ shift_adjoint(link.twist_b, dt)
        Hc = out[:, 12:]
        Hc[:, TIME_OFFSET] = rows_a @ link.twist_a + rows_b @ link.twist_b
        Ad_inv = np.linalg.inv(Ad)  # back to camera tangents: the mount turns both cameras
        Hc[:, MOUNT] = (((rows_a @ Ad_inv)[:, :3] + (rows_b @ Ad_inv)[:, :3])
                        @ mount_jacobian(calibration[MOUNT]))
        Hc[:, FOCAL_SCALE] = focal
        return out

    def _focal_scale_column(self, world_T_body_a: np.ndarray, world_T_body_b: np.ndarray,
                            c: np.ndarray, kernel: int) -> np.ndarray:
        """d e / d(focal scale), (n, 2), reweighted as its row (:func:`focal_scale_kernel`,
        at the planes the residual was just evaluated on)."""
        s = float(c[FOCAL_SCALE])
        shift_a, shift_b, body_T_cam, _, q_a, _, sqrt_info = self._calibrated_setup(c)
        wTc_a = world_T_body_a @ shift_a @ body_T_cam
        wTc_b = world_T_body_b @ shift_b @ body_T_cam
        G_E, N = self.planes(wTc_a, s)
        column = np.empty((self.features.n, 2))
        focal_scale_kernel(wTc_a[:3, :3], wTc_a[:3, 3], wTc_b[:3, :3], wTc_b[:3, 3], q_a,
                           corrected_rays(self.features.q_b, s), G_E, N, sqrt_info, 1.0 + s,
                           kernel, self._kernel_k, column)
        return column

    def principal_point_columns(self, world_T_body_a: np.ndarray, world_T_body_b: np.ndarray,
                                calibration: np.ndarray, robust: bool = True,
                                ray_jacobian: RayJacobian | None = None) -> np.ndarray:
        """d e / d c, (n, 2, 2): the whitened (and, ``robust``, reweighted) residuals'
        derivative w.r.t. a shift ``c`` of the principal point in normalized coordinates
        (``[dcx / fx, dcy / fy]``), at the calibration ``calibration`` (5,)
        (:func:`~factors.kernel.principal_point_kernel`: the rays move, the poses and the
        planes are held). ``ray_jacobian``: rays (m, 3) -> the lens's undistortion
        Jacobian at them (m, 2, 2); None: no distortion (the identity). Not a part of the
        calibration variable: the calibration check tests it apart
        (:mod:`cdtm_graph.calibration.principal_point`)."""
        c = np.asarray(calibration, dtype=float)
        s = float(c[FOCAL_SCALE])
        shift_a, shift_b, body_T_cam, _, q_a, _, sqrt_info = self._calibrated_setup(c)
        wTc_a = world_T_body_a @ shift_a @ body_T_cam
        wTc_b = world_T_body_b @ shift_b @ body_T_cam
        G_E, N = self.planes(wTc_a, s)
        n = self.features.n
        if ray_jacobian is None:
            J_a = J_b = np.broadcast_to(np.eye(2), (n, 2, 2))
        else:
            J_a, J_b = ray_jacobian(self.features.q_a), ray_jacobian(self.features.q_b)
        out = np.empty((n, 2, 2))
        principal_point_kernel(wTc_a[:3, :3], wTc_a[:3, 3], wTc_b[:3, :3], wTc_b[:3, 3], q_a,
                               corrected_rays(self.features.q_b, s), G_E, N, sqrt_info,
                               1.0 + s, self.robust.kernel_id if robust else KERNEL_NONE,
                               self._kernel_k, np.ascontiguousarray(J_a),
                               np.ascontiguousarray(J_b), out)
        return out

    def _calibrated_error(self, values: gtsam.Values, key: int, jacobians) -> np.ndarray:
        """The factor's error with the calibration as its third variable."""
        e, Ha, Hb, Hc = self.evaluate_calibrated(
            pose_matrix(values, self.key_a), pose_matrix(values, self.key_b),
            values.atVector(key), jacobians is not None)
        if not self._compressed:
            if jacobians is not None:
                jacobians[0] = Ha.reshape(-1, 6)
                jacobians[1] = Hb.reshape(-1, 6)
                jacobians[2] = Hc.reshape(-1, CALIBRATION_DIM)
            return e.reshape(-1)
        if jacobians is None:
            out = np.zeros(CALIBRATED_ROWS)
            out[-1] = np.sqrt(np.einsum("ij,ij->", e, e))
            return out
        # the square-root information form of [Ha Hb Hc | e] (as triangularize, in numpy:
        # one call per pair and linearization)
        stacked = np.concatenate([Ha.reshape(-1, 6), Hb.reshape(-1, 6),
                                  Hc.reshape(-1, CALIBRATION_DIM), e.reshape(-1, 1)], axis=1)
        R: np.ndarray = np.linalg.qr(stacked, mode="r")  # type: ignore[assignment]
        jacobians[0] = np.ascontiguousarray(R[:, :6])
        jacobians[1] = np.ascontiguousarray(R[:, 6:12])
        jacobians[2] = np.ascontiguousarray(R[:, 12:12 + CALIBRATION_DIM])
        return np.ascontiguousarray(R[:, -1])



def _kept(cache: dict, key: Any, value: tuple[np.ndarray, ...], size: int
          ) -> tuple[np.ndarray, ...]:
    """``cache[key] = value``, the oldest entry out beyond ``size``; returns ``value``."""
    if len(cache) >= size:
        cache.pop(next(iter(cache)))
    cache[key] = value
    return value


@functools.lru_cache(maxsize=8)
def _mount_at(body_T_cam: bytes, mount: bytes) -> tuple[np.ndarray, np.ndarray]:
    """The mount corrected by a calibration's mount part, and its ``Ad(cam_T_body)``
    (both as bytes of float arrays: (4, 4) and (3,)); read-only, shared by the factors."""
    corrected = corrected_mount(np.frombuffer(body_T_cam).reshape(4, 4),
                                np.frombuffer(mount))
    Ad = cdtm_math.body_to_cam_adjoint(corrected)
    corrected.flags.writeable = False
    Ad.flags.writeable = False
    return corrected, Ad


