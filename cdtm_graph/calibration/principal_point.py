"""flight.yaml's principal point, checked: one more step of the side solve with ``cx``,
``cy`` free.

A principal point ``d`` px off moves every normalized ray by ``d / f``, which a frame pair
reads as the camera moved by ``height * d / f`` in body axes (5 px at 1800 m: 17 m): not
a mount rotation (a rotation adds a perspective term), so the five parameters of the
calibration check (:mod:`cdtm_graph.calibration.check`) do not take it, and a run holding
it is trusted while wrong (1 px: ANEES 50-78; docs/verdict.md). What tells it are the
roll changes: the body-fixed offset would have to jump within a second, which the IMU
forbids.

The test is :mod:`~cdtm_graph.calibration.extra_parts`' score step with the shift's two
columns (:meth:`factors.CdtmPairFactor.principal_point_columns`, in pixels).
"""

from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np

from cdtm_graph.calibration.extra_parts import ExtraPart
from cdtm_graph.calibration.noise_bias import noise_gradient
from cdtm_graph.calibration.online import CALIBRATION_KEY
from cdtm_graph.camera import DistortionModel, PinholeCamera
from factors import CdtmPairFactor
from factors.calibrated_pair import RayJacobian

#: The shift's prior 1-sigma in the step (pixels): a regularizer where the flight does not
#: tell it (no roll change), far above any shift the test names.
PRIOR_SIGMA_PX = 50.0

#: The step tells the shift when it tells each of ``cx``, ``cy`` to this 1-sigma (px): a
#: flight of a few frames, or before its first roll change, tells it poorly (a 4-frame log
#: read cx -63 px at a sigma of 8.8 px, drop 25.8), while the issue's 90-frame flight tells
#: it to 0.45 px (cx, along track) and 0.18 px (cy).
CONCLUSIVE_PX = 1.0


def _noise_part(gradient: dict[int, np.ndarray]) -> np.ndarray:
    """The calibration's entries after the five (none without a C-DTM factor: zero)."""
    g = gradient.get(CALIBRATION_KEY)
    return np.zeros(2) if g is None else g[-2:]


def principal_point_part(camera: PinholeCamera) -> ExtraPart:
    """The principal point as a part of the calibration check: flight.yaml's focal lengths
    turn its columns (normalized coordinates) into pixels, its lens's undistortion
    Jacobian carries a pixel's shift to its ray (:meth:`~cdtm_graph.camera.PinholeCamera.
    undistortion_jacobian`; None without distortion). Its noise part is the calibration's
    entries after the five (:func:`~cdtm_graph.calibration.noise_bias.noise_gradient`
    with ``principal_point_px`` and the same Jacobian: :func:`noise_gradient_of`)."""
    to_px = np.array([1.0 / camera.fx, 1.0 / camera.fy])
    ray_jacobian = ray_jacobian_of(camera)

    def columns(f: CdtmPairFactor, Ta: np.ndarray, Tb: np.ndarray, c: np.ndarray,
                Ha: np.ndarray, Hb: np.ndarray) -> np.ndarray:
        return f.principal_point_columns(Ta, Tb, c, ray_jacobian=ray_jacobian) * to_px

    return ExtraPart("principal_point", ("cx", "cy"), "px", columns,
                     _noise_part, PRIOR_SIGMA_PX,
                     CONCLUSIVE_PX, "correct flight.yaml's principal point (cx, cy: "
                     "--calibration online does not estimate it)")


def ray_jacobian_of(camera: PinholeCamera) -> RayJacobian | None:
    """The lens's undistortion Jacobian as the columns take it; None without distortion
    (the identity, exactly)."""
    return None if camera.model is DistortionModel.NONE else camera.undistortion_jacobian


def noise_gradient_of(factors: Sequence[CdtmPairFactor], values: gtsam.Values,
                      camera: PinholeCamera) -> dict[int, np.ndarray]:
    """The noise's expected gradient with the principal point's part (the five's first),
    as :func:`principal_point_part` of ``camera`` reads it."""
    return noise_gradient(factors, values, (camera.fx, camera.fy), ray_jacobian_of(camera))
