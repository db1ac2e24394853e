"""The camera calibration a C-DTM pair factor may estimate: time offset, mount, focal scale.

One 5-vector ``c = [dt_s, dtheta_mount (3), focal_scale - 1]`` of corrections to the
nominal calibration (flight.yaml), zero at the nominal:

* ``dt_s``: the true exposure of a frame is ``dt_s`` after its (IMU-clock) stamp, so the
  camera sees the body at ``world_T_body(t_k + dt) ~ world_T_body_k Exp(dt xi_k)`` with
  ``xi_k = [omega_body, v_body]`` the body twist at the frame (first order in ``dt``: the
  frame's motion held over the offset, tens of milliseconds). In Kalibr's convention
  (``t_imu = t_cam + timeshift_cam_imu``) the calibrated offset is the nominal plus ``dt``.
* ``dtheta_mount``: rotation vector (rad, camera axes) turning the mount:
  ``body_T_cam_true = body_T_cam Exp([dtheta, 0])``.
* ``focal_scale - 1``: ``fx_true = (1 + s) fx`` (and fy): the measured normalized
  coordinates are ``(1 + s)`` times the true ones, which are ``q_xy / (1 + s)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

#: Dimension of the calibration variable and the index of each part.
CALIBRATION_DIM = 5
TIME_OFFSET = 0
MOUNT = slice(1, 4)
FOCAL_SCALE = 4


@dataclass(frozen=True)
class CalibrationLink:
    """How one pair factor sees the camera calibration.

    Attributes:
        key: the calibration variable's key (a 5-vector), or None: held at ``value``.
        twist_a, twist_b: (6,) body twists ``[omega (rad/s), v (m/s)]``, body axes, at the
            pair's frames (what a time offset moves each pose along).
        value: (5,) the calibration used when ``key`` is None (e.g. the estimate, for
            the checks after a solve).
    """

    key: int | None
    twist_a: np.ndarray
    twist_b: np.ndarray
    value: np.ndarray = field(default_factory=lambda: np.zeros(CALIBRATION_DIM))

    def fixed_at(self, value: np.ndarray) -> CalibrationLink:
        """The same link held at ``value`` (no key)."""
        return CalibrationLink(None, self.twist_a, self.twist_b,
                               np.asarray(value, dtype=float).copy())


def corrected_rays(q: np.ndarray, focal_scale_minus_1: float) -> np.ndarray:
    """Normalized rays (n, 3), z = 1, under the focal scale: ``[q_xy / (1 + s), 1]``."""
    out = np.array(q, dtype=float)
    out[:, :2] /= 1.0 + focal_scale_minus_1
    return out


def corrected_mount(body_T_cam: np.ndarray, dtheta: np.ndarray) -> np.ndarray:
    """``body_T_cam Exp([dtheta, 0])``, (4, 4)."""
    turn = np.eye(4)
    turn[:3, :3] = gtsam.Rot3.Expmap(np.asarray(dtheta, dtype=float)).matrix()
    return body_T_cam @ turn


def shift(twist: np.ndarray, dt_s: float) -> np.ndarray:
    """``Exp(dt xi)``, (4, 4): the body's motion over ``dt_s`` at the twist ``xi`` (6,)."""
    return gtsam.Pose3.Expmap(dt_s * np.asarray(twist, dtype=float)).matrix()


def shift_adjoint(twist: np.ndarray, dt_s: float) -> np.ndarray:
    """``Ad(Exp(-dt xi))``, (6, 6): carries a Jacobian w.r.t. the right perturbation of
    the shifted pose ``X Exp(dt xi)`` to one w.r.t. ``X``'s."""
    return gtsam.Pose3.Expmap(-dt_s * np.asarray(twist, dtype=float)).AdjointMap()


def mount_jacobian(dtheta: np.ndarray) -> np.ndarray:
    """The right Jacobian of SO(3) at ``dtheta``, (3, 3): ``Exp(dtheta + d) ~
    Exp(dtheta) Exp(J d)``."""
    return np.asarray(gtsam.Rot3.ExpmapDerivative(np.asarray(dtheta, dtype=float)))
