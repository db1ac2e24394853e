"""Pinhole camera with OpenCV radial-tangential ("radtan") or equidistant (fisheye) distortion.

Conventions (docs/flightlog.md): the camera frame ``cam`` is OpenCV's (x right, y down,
z along the optical axis); pixel (0, 0) is the *centre* of the top-left pixel, so the
image spans ``-0.5 <= u <= width - 0.5`` and ``-0.5 <= v <= height - 0.5``.
Normalized rays are ``q = (x, y, 1)``: the undistorted point on the plane z = 1.

The distortion model is OpenCV's with coefficients ``(k1, k2, p1, p2[, k3])``::

    r2 = x^2 + y^2,  radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3
    x_d = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
    y_d = y radial + p1 (r2 + 2 y^2) + 2 p2 x y
    u = fx x_d + cx,  v = fy y_d + cy

The equidistant model (Kannala-Brandt, OpenCV's ``cv2.fisheye``, Kalibr's ``equidistant``)
has coefficients ``(k1, k2, k3, k4)``::

    r = sqrt(x^2 + y^2),  theta = atan(r)
    theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)
    x_d = (theta_d / r) x,  y_d = (theta_d / r) y
    u = fx x_d + cx,  v = fy y_d + cy

Rays are written ``(x, y, 1)``, so only directions less than 90 degrees from the optical
axis have one: a fisheye pixel seeing further gets a NaN ray, as does any pixel where a
model does not invert.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from cdtm_graph.choices import DistortionModel

#: Reprojection error (pixels) at which OpenCV's iterative undistortion stops. Far below
#: any feature noise; the round trip pixels -> rays -> pixels is exact to this level.
UNDISTORT_EPS_PX = 1e-10
#: Iteration cap of the undistortion; radtan models of real lenses converge in < 20.
UNDISTORT_MAX_ITERATIONS = 200
#: A pixel whose undistorted ray reprojects further than this from it lies where the
#: distortion model is not invertible (folds over near the corners of strong lenses):
#: its ray is reported as NaN instead of a wrong direction.
UNDISTORT_CHECK_TOL_PX = 1e-6



#: How many coefficients each model takes.
DISTORTION_LENGTHS: dict[DistortionModel, tuple[int, ...]] = {
    DistortionModel.NONE: (0,),
    DistortionModel.RADTAN: (4, 5),
    DistortionModel.EQUIDISTANT: (4,),
}
_COEFFICIENT_NAMES = {DistortionModel.NONE: "none",
                      DistortionModel.RADTAN: "k1 k2 p1 p2 [k3]",
                      DistortionModel.EQUIDISTANT: "k1 k2 k3 k4"}


#: A downward camera on a level body (body x forward, y left, z up): cam x = body x,
#: cam y = -body y, cam z (optical axis) = -body z.
DOWNWARD_BODY_T_CAM = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics of a pinhole camera with optional radtan or equidistant distortion.

    Attributes:
        width: image width in pixels.
        height: image height in pixels.
        fx: focal length along u, pixels.
        fy: focal length along v, pixels.
        cx: principal point u, pixels (pixel-centre convention).
        cy: principal point v, pixels.
        distortion: the model's coefficients: radtan ``(k1, k2, p1, p2)`` or
            ``(k1, k2, p1, p2, k3)``, equidistant ``(k1, k2, k3, k4)``; ``()`` means no
            distortion.
        distortion_model: a :class:`DistortionModel` (or its name); None (the default):
            radtan when there are coefficients, else none.

    Raises:
        ValueError: non-positive or non-integer sizes, non-positive or non-finite
            focal lengths, non-finite principal point or coefficients, an unknown model,
            or a number of coefficients the model does not take.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = ()
    distortion_model: DistortionModel | str | None = None

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | np.integer) or value <= 0:
                raise ValueError(f"camera {name} must be a positive integer, got {value!r}")
            object.__setattr__(self, name, int(value))
        for name in ("fx", "fy", "cx", "cy"):
            value = _finite_float(getattr(self, name), name)
            if name in ("fx", "fy") and value <= 0.0:
                raise ValueError(f"camera {name} must be positive, got {value!r}")
            object.__setattr__(self, name, value)
        coeffs = tuple(_finite_float(c, "distortion coefficient") for c in self.distortion)
        model = self.distortion_model
        if model is None:
            model = DistortionModel.RADTAN if coeffs else DistortionModel.NONE
        try:
            model = DistortionModel(model)
        except ValueError:
            names = ", ".join(m.value for m in DistortionModel)
            raise ValueError(f"camera distortion model {model!r} is not one of {names}") from None
        if len(coeffs) not in DISTORTION_LENGTHS[model]:
            want = " or ".join(str(n) for n in DISTORTION_LENGTHS[model])
            raise ValueError(
                f"camera distortion {model.value} must have {want} coefficients "
                f"({_COEFFICIENT_NAMES[model]}), got {len(coeffs)}")
        object.__setattr__(self, "distortion", coeffs)
        object.__setattr__(self, "distortion_model", model)

    @property
    def model(self) -> DistortionModel:
        """The distortion model (``distortion_model`` after ``__post_init__``)."""
        return DistortionModel(self.distortion_model)

    @classmethod
    def from_fov(cls, width: int, height: int, fov_deg: float) -> PinholeCamera:
        """Undistorted camera with square pixels and a given horizontal field of view.

        The principal point is the image centre ``((width-1)/2, (height-1)/2)`` and the
        FOV spans the full image, outer pixel edges included:
        ``fx = (width / 2) / tan(fov / 2)``.

        Args:
            width: image width in pixels.
            height: image height in pixels.
            fov_deg: full horizontal field of view in degrees, in (0, 180).

        Returns:
            The camera.
        """
        if not 0.0 < float(fov_deg) < 180.0:
            raise ValueError(f"fov_deg must be in (0, 180), got {fov_deg!r}")
        f = 0.5 * width / math.tan(math.radians(fov_deg) / 2.0)
        return cls(width, height, f, f, (width - 1) / 2.0, (height - 1) / 2.0)

    @property
    def K(self) -> np.ndarray:
        """(3, 3) OpenCV camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        """(0,), (4,) or (5,) distortion coefficients as OpenCV takes them (``cv2`` for
        radtan, ``cv2.fisheye`` for equidistant)."""
        return np.array(self.distortion, dtype=float)

    @property
    def fov_deg(self) -> tuple[float, float]:
        """Full horizontal and vertical field of view in degrees, distortion included.

        The angle between the rays through the midpoints of the left and right
        (top and bottom) outer image edges; with an off-centre principal point the
        two halves differ and both are counted. NaN where an edge is not invertible.
        """
        mid_u, mid_v = self.cx, self.cy
        edges = np.array([
            [-0.5, mid_v], [self.width - 0.5, mid_v],   # left, right
            [mid_u, -0.5], [mid_u, self.height - 0.5],  # top, bottom
        ])
        rays = self.pixels_to_rays(edges)
        return (_angle_deg(rays[0], rays[1]), _angle_deg(rays[2], rays[3]))

    @property
    def diagonal_fov_deg(self) -> float:
        """Full field of view between the outer corners of the top-left and bottom-right pixels."""
        corners = np.array([[-0.5, -0.5], [self.width - 0.5, self.height - 0.5]])
        rays = self.pixels_to_rays(corners)
        return _angle_deg(rays[0], rays[1])

    def pixels_to_rays(self, uv: np.ndarray) -> np.ndarray:
        """Undistorted normalized rays of pixels.

        Uses OpenCV's iterative undistortion (``cv2.undistortPoints``, or
        ``cv2.fisheye.undistortPoints`` for the equidistant model) with a tight stopping
        rule (:data:`UNDISTORT_EPS_PX`), then checks by reprojection: pixels where the
        distortion model cannot be inverted, or whose direction is 90 degrees or more
        from the optical axis, get NaN rays.

        Args:
            uv: (N, 2) pixel coordinates (u, v).

        Returns:
            (N, 3) rays ``q = (x, y, 1)`` in the camera frame.
        """
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        rays = np.ones((uv.shape[0], 3))
        if uv.shape[0] == 0:
            return rays
        if self.model is DistortionModel.NONE:
            rays[:, 0] = (uv[:, 0] - self.cx) / self.fx
            rays[:, 1] = (uv[:, 1] - self.cy) / self.fy
            return rays
        if self.model is DistortionModel.EQUIDISTANT:
            rays[:, :2] = _undistort_fisheye_normalized(uv, self.K, self.dist_coeffs)
        else:
            rays[:, :2] = _undistort_normalized(uv, self.K, self.dist_coeffs)
        error_px = np.linalg.norm(self.rays_to_pixels(rays) - uv, axis=1)
        not_invertible = ~(error_px <= UNDISTORT_CHECK_TOL_PX)
        rays[not_invertible, :2] = np.nan
        return rays

    def rays_to_pixels(self, rays_cam: np.ndarray) -> np.ndarray:
        """Project camera-frame rays or points to distorted pixels.

        Args:
            rays_cam: (N, 3) directions or points in the camera frame (any scale).

        Returns:
            (N, 2) pixels (u, v); NaN rows where ``z <= 0`` (behind the camera).
        """
        p = np.asarray(rays_cam, dtype=float).reshape(-1, 3)
        z = p[:, 2]
        in_front = z > 0.0
        z_safe = np.where(in_front, z, 1.0)
        x = p[:, 0] / z_safe
        y = p[:, 1] / z_safe
        if self.model is DistortionModel.EQUIDISTANT:
            x, y = _equidistant(x, y, self.distortion)
        elif self.model is DistortionModel.RADTAN:
            k1, k2, p1, p2 = self.distortion[:4]
            k3 = self.distortion[4] if len(self.distortion) == 5 else 0.0
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            xy = x * y
            x, y = (x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x),
                    y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy)
        uv = np.stack([self.fx * x + self.cx, self.fy * y + self.cy], axis=1)
        uv[~in_front] = np.nan
        return uv

    def in_image(self, uv: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """Whether pixels lie on the image (outer pixel edges included; NaN is outside).

        Args:
            uv: (..., 2) pixel coordinates.
            margin_px: also accept pixels up to this far outside the outer edges.

        Returns:
            (...) booleans: ``-0.5 - m <= u <= width - 0.5 + m`` and likewise for v.
        """
        uv = np.asarray(uv, dtype=float)
        u, v = uv[..., 0], uv[..., 1]
        lo = -0.5 - margin_px
        return ((u >= lo) & (u <= self.width - 0.5 + margin_px)
                & (v >= lo) & (v <= self.height - 0.5 + margin_px))

    def undistortion_jacobian(self, rays: np.ndarray) -> np.ndarray:
        """(N, 2, 2) how each undistorted ray ``(x, y)`` moves with its pixel's distorted
        normalized coordinates ``((u - cx) / fx, (v - cy) / fy)``: the inverse of the
        distortion's Jacobian at the rays (N, 3, any positive z), by central differences
        of :meth:`rays_to_pixels` (the lens's one formula); the identity without
        distortion, and where the lens folds (a Jacobian that is not invertible or not
        finite: no pixel is measured there, :meth:`pixels_to_rays`).
        """
        q = np.asarray(rays, dtype=float).reshape(-1, 3)
        q = q / q[:, 2:3]
        n = q.shape[0]
        if self.model is DistortionModel.NONE:
            return np.broadcast_to(np.eye(2), (n, 2, 2)).copy()
        step = 1e-6
        J = np.empty((n, 2, 2))
        scale = np.array([self.fx, self.fy])
        for j in range(2):
            plus, minus = q.copy(), q.copy()
            plus[:, j] += step
            minus[:, j] -= step
            J[:, :, j] = (self.rays_to_pixels(plus) - self.rays_to_pixels(minus)) / (
                2.0 * step * scale)
        det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
        ok = np.isfinite(det) & (np.abs(det) > 1e-9)
        out = np.broadcast_to(np.eye(2), (n, 2, 2)).copy()
        a, b, c, d = J[ok, 0, 0], J[ok, 0, 1], J[ok, 1, 0], J[ok, 1, 1]
        out[ok] = np.stack([np.stack([d, -b], axis=1), np.stack([-c, a], axis=1)],
                           axis=1) / det[ok][:, None, None]
        return out

    def sigma_normalized(self, pixel_sigma_px: float) -> tuple[float, float]:
        """A pixel standard deviation in normalized image units: ``(sigma / fx, sigma / fy)``."""
        return (pixel_sigma_px / self.fx, pixel_sigma_px / self.fy)


def _finite_float(value: object, name: str) -> float:
    try:
        out = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"camera {name} must be a number, got {value!r}") from None
    if isinstance(value, bool) or not math.isfinite(out):
        raise ValueError(f"camera {name} must be a finite number, got {value!r}")
    return out


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = float(a @ b) / float(np.linalg.norm(a) * np.linalg.norm(b))
    return math.degrees(math.acos(min(1.0, max(-1.0, cos))))


def _equidistant(x: np.ndarray, y: np.ndarray, coeffs: tuple[float, ...]
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Normalized (N,) x, y -> distorted x_d, y_d of the equidistant model (module docstring)."""
    k1, k2, k3, k4 = coeffs
    r = np.hypot(x, y)
    theta = np.arctan(r)
    t2 = theta * theta
    theta_d = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    # theta_d / r -> 1 as r -> 0 (theta ~ r): the optical axis maps to the principal point.
    safe_r = np.where(r > 0.0, r, 1.0)
    scale = np.where(r > 0.0, theta_d / safe_r, 1.0)
    return x * scale, y * scale


def _undistort_fisheye_normalized(uv: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(N, 2) distorted pixels -> (N, 2) undistorted normalized coordinates via cv2.fisheye."""
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
                UNDISTORT_MAX_ITERATIONS, UNDISTORT_EPS_PX)
    out = cv2.fisheye.undistortPoints(uv.reshape(-1, 1, 2), K, dist.reshape(4, 1),
                                      criteria=criteria)
    return np.asarray(out, dtype=float).reshape(-1, 2)


def _undistort_normalized(uv: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(N, 2) distorted pixels -> (N, 2) undistorted normalized coordinates via OpenCV."""
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
                UNDISTORT_MAX_ITERATIONS, UNDISTORT_EPS_PX)
    src = uv.reshape(-1, 1, 2)
    # OpenCV 4 has the stopping rule only in undistortPointsIter; OpenCV 5 folded it
    # into undistortPoints (its default rule stops after 5 iterations: ~0.3 px off).
    iterative = getattr(cv2, "undistortPointsIter", None)
    if iterative is not None:
        out = iterative(src, K, dist, None, None, criteria)
    else:
        out = cv2.undistortPoints(src, K, dist, R=None, P=None, criteria=criteria)
    return np.asarray(out, dtype=float).reshape(-1, 2)
