"""Online camera calibration: the camera-IMU time offset, the mount rotation and a focal
scale as one estimated variable.

The variable ``C(0)`` is the 5-vector of corrections to flight.yaml's calibration,
``[dt_s, dtheta_mount (3, rad, camera axes), focal_scale - 1]`` (the model:
:mod:`factors.calibration`), with a zero-mean Gaussian prior whose sigmas come from
``camera.calibration`` in flight.yaml (or the run's settings). Every C-DTM pair factor
then holds it as a third variable, so the per-frame marginals include its uncertainty.

A parameter the flight cannot tell (e.g. a time offset on a straight, steady stretch,
where it only moves the track along itself) keeps a posterior sigma near its prior's:
:attr:`CalibrationEstimate.observable` says so per parameter.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np

from cdtm_graph.flightlog import CalibrationSigmas, FlightConfig, ImuSamples
from factors.calibration import (
    CALIBRATION_DIM,
    FOCAL_SCALE,
    MOUNT,
    TIME_OFFSET,
    corrected_mount,
    corrected_rays,
    shift,
)

#: The calibration variable's key.
CALIBRATION_KEY = gtsam.symbol("c", 0)

#: A parameter whose posterior sigma is above this share of its prior sigma was barely
#: told by the flight: ``calibration_unobservable``.
UNOBSERVABLE_SIGMA_RATIO = 0.5

#: Parameter names, in the variable's order of parts.
PARAMETERS = ("time_offset", "mount", "focal_scale")


def prior_sigmas(sigmas: CalibrationSigmas) -> np.ndarray:
    """(5,) prior 1-sigmas of ``C(0)`` (s, rad x3, 1)."""
    out = np.empty(CALIBRATION_DIM)
    out[TIME_OFFSET] = sigmas.time_offset_sigma_s
    out[MOUNT] = np.radians(sigmas.mount_sigma_deg)
    out[FOCAL_SCALE] = sigmas.focal_scale_sigma
    return out


def prior_factor(sigmas: CalibrationSigmas) -> gtsam.PriorFactorVector:
    """The zero-mean prior on ``C(0)`` (flight.yaml's calibration is its mean)."""
    return gtsam.PriorFactorVector(CALIBRATION_KEY, np.zeros(CALIBRATION_DIM),
                                   gtsam.noiseModel.Diagonal.Sigmas(prior_sigmas(sigmas)))


def body_twists(t_ns: np.ndarray, imu: ImuSamples, gyro_bias: np.ndarray,
                world_T_body: np.ndarray, velocity_mps: np.ndarray) -> np.ndarray:
    """(K, 6) body twists ``[omega, v]`` (body axes) at the frames: what a time offset
    moves each pose along.

    The angular rate is the IMU's, interpolated at the frame and less the gyro bias; the
    velocity the estimate's (a metre per second off moves a 20 ms offset's pose by 2 cm:
    the twist is held as data).

    Args:
        t_ns: (K,) frame times. imu: the samples. gyro_bias: (3,) or (K, 3).
        world_T_body: (K, 4, 4). velocity_mps: (K, 3) world frame.
    """
    t = np.asarray(t_ns, dtype=np.int64)
    rel = (t - imu.t_ns[0]).astype(float)
    at = (imu.t_ns - imu.t_ns[0]).astype(float)
    omega = np.stack([np.interp(rel, at, imu.gyro_radps[:, i]) for i in range(3)], axis=1)
    omega = omega - np.asarray(gyro_bias, dtype=float)
    v_body = np.einsum("kji,kj->ki", world_T_body[:, :3, :3], velocity_mps)
    return np.concatenate([omega, v_body], axis=1)


@dataclass(frozen=True)
class CalibrationEstimate:
    """The calibration estimated online (report.json ``calibration``).

    Attributes:
        time_offset_s: the camera-IMU offset, Kalibr's ``timeshift_cam_imu``
            (``t_imu = t_cam + offset``): flight.yaml's ``time_offset_s`` plus the
            correction.
        time_offset_correction_s: the correction.
        mount_correction_deg: (3,) rotation vector turning flight.yaml's mount to the
            estimate (``body_T_cam Exp(dtheta)``, camera axes), degrees.
        focal_scale: the estimated focal lengths over flight.yaml's (fx, fy alike).
        fx_px, fy_px: the estimated focal lengths.
        sigmas: posterior 1-sigmas in the same units: ``[time_offset_s, mount x, y, z
            (deg), focal_scale]``.
        prior_sigmas: the prior's, same order.
        covariance: (5, 5) posterior covariance of ``C(0)`` (s, rad, 1).
        observable: per parameter (``time_offset``, ``mount``, ``focal_scale``): did the
            flight tell it (posterior sigma below ``UNOBSERVABLE_SIGMA_RATIO`` of the
            prior's; the mount by its worst axis)?
    """

    time_offset_s: float
    time_offset_correction_s: float
    mount_correction_deg: np.ndarray
    focal_scale: float
    fx_px: float
    fy_px: float
    sigmas: np.ndarray
    prior_sigmas: np.ndarray
    covariance: np.ndarray
    observable: dict[str, bool]

    @property
    def unobservable(self) -> list[str]:
        """The parameters the flight did not tell."""
        return [name for name, told in self.observable.items() if not told]


def _report_units(c: np.ndarray) -> np.ndarray:
    """(5,) from the variable's units (s, rad, 1) to the report's (s, deg, 1)."""
    out = np.array(c, dtype=float)
    out[MOUNT] = np.degrees(out[MOUNT])
    return out


def estimate(value: np.ndarray, covariance: np.ndarray, sigmas: CalibrationSigmas,
             config: FlightConfig) -> CalibrationEstimate:
    """The estimate of ``C(0)`` (5,) with its marginal covariance (5, 5), in the units of
    flight.yaml."""
    value = np.asarray(value, dtype=float)
    covariance = np.asarray(covariance, dtype=float)
    posterior = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    prior = prior_sigmas(sigmas)
    ratio = posterior / prior
    told = ratio < UNOBSERVABLE_SIGMA_RATIO
    observable = {"time_offset": bool(told[TIME_OFFSET]), "mount": bool(told[MOUNT].all()),
                  "focal_scale": bool(told[FOCAL_SCALE])}
    cam = config.camera
    scale = 1.0 + float(value[FOCAL_SCALE])
    return CalibrationEstimate(
        cam.time_offset_s + float(value[TIME_OFFSET]), float(value[TIME_OFFSET]),
        np.degrees(value[MOUNT]), scale, cam.camera.fx * scale, cam.camera.fy * scale,
        _report_units(posterior), _report_units(prior), covariance, observable)


def calibrated_cameras(world_T_body: Callable[[int], np.ndarray], body_T_cam: np.ndarray,
                       ray_cam: np.ndarray, twists: np.ndarray, value: np.ndarray
                       ) -> tuple[Callable[[int], np.ndarray], np.ndarray, np.ndarray]:
    """The cameras as the calibration ``value`` (5,) sees them: each frame's body at its
    exposure, the mount turned, the rays (M, 3) under the focal scale.

    Args:
        world_T_body: frame -> (4, 4) body pose at its stamp. twists: (K, 6) body twists.
    """
    dt = float(value[TIME_OFFSET])

    def exposed(k: int) -> np.ndarray:
        return world_T_body(k) @ shift(twists[k], dt)

    return (exposed, corrected_mount(body_T_cam, value[MOUNT]),
            corrected_rays(ray_cam, float(value[FOCAL_SCALE])))
