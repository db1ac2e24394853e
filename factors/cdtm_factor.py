"""GTSAM factors for the C-DTM constraint (paper eq. 7) between two ``world_T_body`` poses.

Two forms with the same linearization:

* :func:`make_feature_factors`: one ``CustomFactor`` per feature with a 2x2
  Gaussian noise model (optionally wrapped in ``noiseModel.Robust``): the paper's
  picture, and the reference the fast form is tested against.
* :class:`CdtmPairFactor`: one ``CustomFactor`` per frame pair holding every
  feature of the pair; whitening and per-feature M-estimator reweighting happen
  inside a numba kernel, so a linearization costs one Python callback per pair
  rather than per feature. Wrapping it in ``noiseModel.Robust`` would treat all its
  rows as one residual, hence the internal reweighting; its error-only evaluation
  returns rows whose half squared norm is the robust loss, as GTSAM's Robust does.
  A pair of more than six features hands GTSAM a 13-row square root of its 2n rows
  (:func:`factors.kernel.triangularize`): the same linear system, and eliminating it
  no longer costs in proportion to the feature count.

Both use the tangent plane in one of two ways (:class:`PlaneMode`): FIXED keeps
``G_E, N`` from construction (the paper); REINTERSECT casts the ray again from the
current camera a at every evaluation and linearizes on the tangent plane at the
new hit (which is the exact derivative of the re-intersected residual).
"""

from __future__ import annotations

import dataclasses
import functools
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np

import factors.cdtm_math as cdtm_math
from factors.calibrated_pair import (
    CALIBRATED_ROWS,
    NO_LOSS,
    CalibratedPair,
    RayJacobian,
    pose_matrix,
)
from factors.calibration import (
    CALIBRATION_DIM,
    FOCAL_SCALE,
    MOUNT,
    TIME_OFFSET,
    CalibrationLink,
    corrected_mount,
    corrected_rays,
    shift,
)
from factors.kernel import (
    COMPRESSED_ROWS,
    KERNEL_NONE,
    cdtm_linearize,
    feature_covariance_kernel,
    residual_noise_kernel,
    triangularize,
)
from factors.modes import PlaneMode, RobustKernel

#: ``raycast(origin (3,) or (n,3), directions (n,3)) -> (points, normals, valid)``, fresh
#: (n,3), (n,3), (n,) arrays; normals ``(-dh/dx, -dh/dy, 1)``. The factor stays free of
#: any DTM class.
RayCaster = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class FeatureNoise:
    """Data noise of the C-DTM features (eqs. 21-26).

    Attributes:
        sigma_q_xy: 1-sigma of ``q_b`` in normalized image units (sigma_px/fx, sigma_px/fy).
        sigma_h_m: 1-sigma DTM height error, metres.
        sigma_qa_xy: 1-sigma of ``q_a``; ``None`` treats ``q_a`` as exact (the paper's model).
    """

    sigma_q_xy: tuple[float, float]
    sigma_h_m: float
    sigma_qa_xy: tuple[float, float] | None = None


@dataclass
class PairFeatures:
    """All features of one frame pair (a, b), with their planes and noise.

    Attributes:
        q_a, q_b: (n, 3) normalized rays (z = 1) in cameras a and b.
        G_E, N: (n, 3) DTM tangent planes (point, upward normal ``(-dh/dx, -dh/dy, 1)``).
        Sigma_e: (n, 2, 2) covariance of the 2-vector residual.
        Sigma_f: (n, 3, 3) covariance of the paper's 3-vector residual (eqs. 19-26).
        basis_b: (n, 3, 2) orthonormal complement of ``q_b``.
        sqrt_info: (n, 2, 2) upper-triangular whitening, ``S^T S = Sigma_e^-1``.
        sqrt_info_full: (n, 2, 2) the whitening of one residual as measured, with the
            first observation's pixel noise too: ``|S_full e|^2`` is chi-square(2) for an
            inlier tested on its own (the gate, the outlier count); None: ``sqrt_info``.
        robust_scale: (n,) how much larger one residual's spread is than the factor's
            whitening says (``sqrt(trace(S Sigma_full S^T) / 2)``, >= 1): the robust
            kernel judges ``|S e| / robust_scale``, so it does not count the first
            observation's noise against an inlier. None: 1.
    """

    q_a: np.ndarray
    q_b: np.ndarray
    G_E: np.ndarray
    N: np.ndarray
    Sigma_e: np.ndarray
    Sigma_f: np.ndarray
    basis_b: np.ndarray
    sqrt_info: np.ndarray
    noise: FeatureNoise | None = None
    dtm_variance_scale: np.ndarray | None = None
    sqrt_info_full: np.ndarray | None = None
    robust_scale: np.ndarray | None = None

    @property
    def n(self) -> int:
        return self.q_a.shape[0]

    @classmethod
    def build(
        cls,
        world_T_cam_a: np.ndarray,
        world_T_cam_b: np.ndarray,
        q_a: np.ndarray,
        q_b: np.ndarray,
        G_E: np.ndarray,
        N: np.ndarray,
        noise: FeatureNoise,
        dtm_variance_scale: np.ndarray | None = None,
    ) -> PairFeatures:
        """Features with their noise linearized at the given camera poses (4x4 each).

        Args:
            dtm_variance_scale: (n,) multiplies each feature's DTM height variance
                (e.g. by the number of pairs sharing its ground point); ``None``: 1.
        """
        q_a = np.ascontiguousarray(q_a, dtype=float)
        q_b = np.ascontiguousarray(q_b, dtype=float)
        G_E = np.ascontiguousarray(G_E, dtype=float)
        N = np.ascontiguousarray(N, dtype=float)
        n = q_a.shape[0]
        if dtm_variance_scale is None:
            sigma_h = np.full(n, float(noise.sigma_h_m))
        else:
            dtm_variance_scale = np.asarray(dtm_variance_scale, dtype=float)
            sigma_h = float(noise.sigma_h_m) * np.sqrt(dtm_variance_scale)
        Sigma_f = np.empty((n, 3, 3))
        Sigma_full = np.empty((n, 3, 3))
        sax, say = noise.sigma_qa_xy if noise.sigma_qa_xy is not None else (0.0, 0.0)
        # numba twins of cdtm_math's feature_covariance, orthonormal_complement,
        # residual_covariance and sqrt_information (tested equal): ~10x faster
        feature_covariance_kernel(
            np.ascontiguousarray(world_T_cam_a[:3, :3]), world_T_cam_a[:3, 3].copy(),
            np.ascontiguousarray(world_T_cam_b[:3, :3]), world_T_cam_b[:3, 3].copy(),
            q_a, q_b, G_E, N, float(noise.sigma_q_xy[0]), float(noise.sigma_q_xy[1]),
            sigma_h, float(sax), float(say), Sigma_f, Sigma_full)
        basis = np.empty((n, 3, 2))
        Sigma_e = np.empty((n, 2, 2))
        sqrt_info = np.empty((n, 2, 2))
        residual_noise_kernel(q_b, Sigma_f, basis, Sigma_e, sqrt_info)
        Sigma_e_full = np.empty((n, 2, 2))
        sqrt_info_full = np.empty((n, 2, 2))
        residual_noise_kernel(q_b, Sigma_full, np.empty((n, 3, 2)), Sigma_e_full, sqrt_info_full)
        # trace(S Sigma_e_full S^T) / 2 with S = [[a, b], [0, d]] (the kernel's triangle),
        # written out: two stacked 2x2 products cost more than the rest of the build
        a, b, d = sqrt_info[:, 0, 0], sqrt_info[:, 0, 1], sqrt_info[:, 1, 1]
        E00, E01, E11 = Sigma_e_full[:, 0, 0], Sigma_e_full[:, 0, 1], Sigma_e_full[:, 1, 1]
        half_trace = 0.5 * (a * a * E00 + 2.0 * a * b * E01 + (b * b + d * d) * E11)
        robust_scale = np.sqrt(np.maximum(half_trace, 1.0))
        return cls(q_a, q_b, G_E, N, Sigma_e, Sigma_f, basis, sqrt_info, noise,
                   dtm_variance_scale, sqrt_info_full, robust_scale)

    def whitened_full_covariance(self) -> np.ndarray:
        """(n, 2, 2) covariance of one residual as measured (``sqrt_info_full``), in the
        coordinates ``sqrt_info`` whitens to (the identity without ``sqrt_info_full``)."""
        if self.sqrt_info_full is None:
            return np.broadcast_to(np.eye(2), (self.n, 2, 2)).copy()
        # T = S F^-1, T T^T, with S, F the kernel's upper triangles [[a, b], [0, d]]
        # (written out: numpy's stacked 2x2 inverse and products cost most of a gate)
        S, F = self.sqrt_info, self.sqrt_info_full
        t00 = S[:, 0, 0] / F[:, 0, 0]
        t01 = (S[:, 0, 1] - t00 * F[:, 0, 1]) / F[:, 1, 1]
        t11 = S[:, 1, 1] / F[:, 1, 1]
        out = np.empty((self.n, 2, 2))
        out[:, 0, 0] = t00 * t00 + t01 * t01
        out[:, 0, 1] = out[:, 1, 0] = t01 * t11
        out[:, 1, 1] = t11 * t11
        return out

    def subset(self, index: np.ndarray) -> PairFeatures:
        """The features selected by ``index`` (mask or indices)."""
        def pick(a: np.ndarray) -> np.ndarray:
            return np.ascontiguousarray(a[index])

        def maybe(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else pick(a)

        return PairFeatures(pick(self.q_a), pick(self.q_b), pick(self.G_E), pick(self.N),
                            pick(self.Sigma_e), pick(self.Sigma_f), pick(self.basis_b),
                            pick(self.sqrt_info), self.noise, maybe(self.dtm_variance_scale),
                            maybe(self.sqrt_info_full), maybe(self.robust_scale))


_SCRATCH = [np.empty((COMPRESSED_ROWS, 512))]


def _scratch(rows: int) -> np.ndarray:
    """Work space of ``triangularize`` (13 x at least ``rows``), shared by all pair
    factors: a callback uses it and is done before the next one runs (they hold the GIL
    throughout)."""
    if _SCRATCH[0].shape[1] < rows:
        _SCRATCH[0] = np.empty((COMPRESSED_ROWS, 2 * rows))
    return _SCRATCH[0]


@functools.lru_cache(maxsize=8)
def _adjoint_of(body_T_cam_bytes: bytes) -> np.ndarray:
    Ad = cdtm_math.body_to_cam_adjoint(np.frombuffer(body_T_cam_bytes).reshape(4, 4))
    Ad = np.ascontiguousarray(Ad)
    Ad.flags.writeable = False
    return Ad


def _adjoint(body_T_cam: np.ndarray) -> np.ndarray:
    """``Ad(cam_T_body)``, computed once per mounting (a log has one)."""
    return _adjoint_of(np.ascontiguousarray(body_T_cam, dtype=float).tobytes())


class CdtmPairFactor(CalibratedPair):
    """Every C-DTM feature of a frame pair in one vectorized GTSAM factor.

    Args:
        key_a, key_b: ``X(a)``, ``X(b)`` keys of ``world_T_body`` poses, a observed first.
        features: the pair's features and noise.
        body_T_cam: (4, 4) camera mounting.
        plane_mode: FIXED or REINTERSECT.
        raycast: DTM ray caster, required for REINTERSECT. Where it misses, the
            construction plane is kept.
        robust: per-feature M-estimator; ``robust_threshold`` defaults to the kernel's.
        calibration: the camera calibration the residuals are evaluated with
            (:mod:`factors.calibration`); with a key, the factor's third variable (a
            5-vector) and Jacobians w.r.t. it. None: the nominal calibration, as before.

    Attributes:
        factor: the ``gtsam.CustomFactor`` to add to a graph, unit noise (whitening
            happens inside). Its dimension is 2n for up to six features (nine with a
            calibration key), otherwise 13 (18): a linearization returns the QR triangle
            of the whitened ``[Ha Hb (Hc) | e]`` (same Hessian, gradient and error), and an
            error evaluation returns 13 (18) rows of which only the norm means anything
            (the last entry; the rest are zero).
    """

    def __init__(
        self,
        key_a: int,
        key_b: int,
        features: PairFeatures,
        body_T_cam: np.ndarray,
        plane_mode: PlaneMode = PlaneMode.FIXED,
        raycast: RayCaster | None = None,
        robust: RobustKernel = RobustKernel.NONE,
        robust_threshold: float | None = None,
        calibration: CalibrationLink | None = None,
    ):
        if plane_mode is PlaneMode.REINTERSECT and raycast is None:
            raise ValueError("PlaneMode.REINTERSECT needs a raycast function")
        self.key_a, self.key_b = key_a, key_b
        self.calibration = calibration
        self.features = features
        self.body_T_cam = np.asarray(body_T_cam, dtype=float)
        self.plane_mode = plane_mode
        self.raycast = raycast
        self.robust = robust
        self.robust_threshold = (robust.default_threshold if robust_threshold is None
                                 else float(robust_threshold))
        self._Ad = _adjoint(self.body_T_cam)
        n = features.n
        scale = features.robust_scale if features.robust_scale is not None else np.ones(n)
        self._kernel_k = np.ascontiguousarray(self.robust_threshold * scale)
        self._e = np.empty((n, 2))
        self._e_loss = np.empty((n, 2))  # the error evaluation's residuals (robust loss)
        self._Ha = np.empty((n, 2, 6))
        self._Hb = np.empty((n, 2, 6))
        self.n_inactive = 0
        self._planes_cache: tuple[bytes, np.ndarray, np.ndarray] | None = None
        self._evaluated_at: bytes | None = None  # the poses _e, _Ha, _Hb were made at
        # _calibrated_setup's, by time offset and by focal scale
        self._shifts: dict[float, tuple[np.ndarray, ...]] = {}
        self._rays: dict[float, tuple[np.ndarray, ...]] = {}
        # Tall pairs reach GTSAM as a 13-row triangle: QR elimination of the raw 2n rows
        # was most of a fixed-lag update, and the batch's memory.
        keys = [key_a, key_b]
        compressed_rows = COMPRESSED_ROWS
        if calibration is not None and calibration.key is not None:
            keys.append(calibration.key)
            compressed_rows = CALIBRATED_ROWS
        self._compressed = 2 * n > compressed_rows
        rows = 2 * n
        if self._compressed:
            rows = compressed_rows
            self._Ja = np.empty((COMPRESSED_ROWS, 6))
            self._Jb = np.empty((COMPRESSED_ROWS, 6))
            self._z = np.empty(COMPRESSED_ROWS)
        self._keys, self._rows = keys, rows
        self._factor: weakref.ref[gtsam.CustomFactor] | None = None

    @property
    def factor(self) -> gtsam.CustomFactor:
        """The ``gtsam.CustomFactor`` to add to a graph (unit noise; class docstring).

        Held weakly, made again when no one holds it: the factor's C++ callback holds
        this object, so a strong reference back would close a cycle through GTSAM that
        Python's collector cannot see (every pair factor of every run stayed in memory:
        +240 MB a 1000-frame batch run). A graph that holds it keeps this object alive.
        """
        made = self._factor() if self._factor is not None else None
        if made is None:
            made = gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(self._rows), self._keys,
                                      self._error)
            self._factor = weakref.ref(made)
        return made

    def planes(self, world_T_cam_a: np.ndarray,
               focal_scale_minus_1: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """The tangent planes ``(G_E, N)`` used at this camera-a pose (and focal scale,
        :mod:`factors.calibration`)."""
        f = self.features
        if self.plane_mode is PlaneMode.FIXED:
            return f.G_E, f.N
        # An optimizer evaluates the error at a candidate and then linearizes at the
        # same values: cast once per distinct camera-a pose.
        key = _planes_key(world_T_cam_a, focal_scale_minus_1)
        if self._planes_cache is not None and self._planes_cache[0] == key:
            return self._planes_cache[1], self._planes_cache[2]
        q_a = f.q_a if focal_scale_minus_1 == 0.0 else corrected_rays(f.q_a, focal_scale_minus_1)
        ray = q_a @ world_T_cam_a[:3, :3].T
        assert self.raycast is not None  # checked at construction for REINTERSECT
        points, normals, valid = self.raycast(world_T_cam_a[:3, 3], ray)
        if not valid.all():
            points[~valid] = f.G_E[~valid]
            normals[~valid] = f.N[~valid]
        self._planes_cache = (key, points, normals)
        return points, normals

    def built_at(self, world_T_cam_a: np.ndarray) -> CdtmPairFactor:
        """Take the features' planes as this factor's cast at ``world_T_cam_a``, the
        camera-a pose they were cast at when the features were built (with this factor's
        ray caster), so an evaluation there (an innovation test's) does not cast them
        again. Returns the factor."""
        if self.plane_mode is PlaneMode.REINTERSECT:
            self._planes_cache = (_planes_key(world_T_cam_a, 0.0), self.features.G_E,
                                  self.features.N)
        return self

    def evaluate(
        self, world_T_body_a: np.ndarray, world_T_body_b: np.ndarray, want_jacobians: bool = True
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Whitened, reweighted residuals (n, 2) and Jacobians (n, 2, 6) w.r.t. X(a), X(b).

        The arrays are the factor's own buffers: copy them to keep them. With a
        calibration link, at its ``value`` (the variable's value: :meth:`evaluate_calibrated`).
        Without one the Jacobians are made whether or not ``want_jacobians`` asks (and kept
        for the next call at the same poses).
        """
        if self.calibration is not None:
            e, Ha, Hb, _ = self.evaluate_calibrated(world_T_body_a, world_T_body_b,
                                                    self.calibration.value, want_jacobians)
            return e, Ha, Hb
        # An optimizer evaluates the error at a candidate and, taking the step, linearizes
        # there: the Jacobians are made at the first call (about twice a bare error's
        # cost) and the second is a lookup. (Rejected candidates pay for them unused.)
        key = world_T_body_a.tobytes() + world_T_body_b.tobytes()
        if self._evaluated_at == key:
            return self._e if want_jacobians else self._e_loss, self._Ha, self._Hb
        wTc_a = world_T_body_a @ self.body_T_cam
        wTc_b = world_T_body_b @ self.body_T_cam
        G_E, N = self.planes(wTc_a)
        f = self.features
        self.n_inactive = cdtm_linearize(
            wTc_a[:3, :3], wTc_a[:3, 3], wTc_b[:3, :3], wTc_b[:3, 3], self._Ad,
            f.q_a, G_E, N, f.basis_b, f.sqrt_info, self.robust.kernel_id,
            self._kernel_k, True, self._e, self._Ha, self._Hb, self._e_loss)
        self._evaluated_at = key
        return self._e if want_jacobians else self._e_loss, self._Ha, self._Hb

    def noise_cost_gradient(self, world_T_body_a: np.ndarray, world_T_body_b: np.ndarray,
                            calibration: np.ndarray | None = None,
                            principal_point: bool = False,
                            ray_jacobian: RayJacobian | None = None) -> np.ndarray:
        """Gradient of the cost the data noise alone is expected to leave, ``E[|r|^2]``
        with ``r`` whitened and reweighted as the factor does, w.r.t. ``X(a)``, ``X(b)``
        (right perturbations) and, with a calibration link, the calibration (5,):
        (12,) or (17,); ``principal_point`` (a calibration link only): also w.r.t. a shift
        of the principal point in normalized coordinates (:meth:`principal_point_columns`,
        with ``ray_jacobian``), (19,).

        Why: the factor holds its whitening fixed and ``q_a`` exact, but the residual's
        noise (``q_a``'s pixel noise above all: it moves the ground point by its range
        from camera a) grows and shrinks with the poses and the focal scale. Least
        squares then leans toward the poses where the noise looks small: at the truth the
        expected gradient of ``|r|^2 / 2`` holds half this vector (an errors-in-variables
        bias; on the issue's flight it pulled the focal scale 2.5 sigma low).
        :func:`cdtm_graph.calibration.noise_bias.debiased` subtracts it (a corrected score).

        The noise is the factor's own residual moved by one sigma of each source, both
        ways (``q_a`` and ``q_b`` pixels, the DTM height without its sharing discount):
        half the difference is the residual's part linear in that noise, to third order,
        so the expectation follows the residual exactly as the factor computes it
        (eqs. 19-26 describe the paper's 3-vector, which differs from the factor's
        2-vector at first order off the solution). Planes held where camera a casts them
        now; robust weights as the kernel gives them here (:meth:`noise_moved`). The
        gradient is exact: the moved data's Jacobians, one evaluation of the 10 moved
        copies of the data (``sum w odd . (J+ - J-)``).
        """
        moved, weight, c = self.noise_moved(world_T_body_a, world_T_body_b, calibration)
        n = self.features.n
        calibrated = moved.calibration is not None
        extra = 2 if principal_point and calibrated else 0
        if n == 0:
            return np.zeros((12 + CALIBRATION_DIM if calibrated else 12) + extra)
        if calibrated:
            # the Jacobians w.r.t. the shifted bodies and the focal scale, summed as the
            # gradient weighs them, then chained once (the chain is linear: ``chained``)
            m = moved.features.n
            e, Ha, Hb = np.empty((m, 2)), np.empty((m, 2, 6)), np.empty((m, 2, 6))
            Ad = moved._calibrated_kernel(world_T_body_a, world_T_body_b, c, KERNEL_NONE,
                                          True, e, Ha, Hb)
            focal = moved._focal_scale_column(world_T_body_a, world_T_body_b, c, KERNEL_NONE)
            J = np.concatenate((Ha, Hb, focal[:, :, None]) + ((moved.principal_point_columns(
                world_T_body_a, world_T_body_b, c, robust=False, ray_jacobian=ray_jacobian),)
                if extra else ()), axis=2)
        else:
            e, Ha, Hb = moved.innovations(world_T_body_a, world_T_body_b)
            J = np.concatenate((Ha, Hb), axis=2)
        sides_e = e.reshape(-1, 2, n, 2)
        sides_J = J.reshape(-1, 2, n, 2, J.shape[2])
        # d(w |odd|^2) = 2 w odd . d(odd), d(odd) = (J+ - J-) / 2
        g = np.einsum("n,mni,mnij->j", weight, 0.5 * (sides_e[:, 0] - sides_e[:, 1]),
                      sides_J[:, 0] - sides_J[:, 1])
        if not calibrated:
            return g
        chained = moved.chained(g[None, :6], g[None, 6:12], g[12], c, Ad)[0]
        return np.concatenate([chained, g[13:]]) if extra else chained

    def noise_moved(self, world_T_body_a: np.ndarray, world_T_body_b: np.ndarray,
                    calibration: np.ndarray | None = None
                    ) -> tuple[CdtmPairFactor, np.ndarray, np.ndarray]:
        """The data moved by +- one sigma of each noise source (rows [source, sign,
        feature]: ``q_a`` x and y, ``q_b`` x and y, the DTM height), as a factor on the
        planes camera a casts now (held, no kernel; the calibration held at
        ``calibration`` when given), with the features' IRLS weights (n,) here and the
        calibration (5,) used. Its residuals' half differences are the noise's linear
        part (:meth:`noise_cost_gradient`)."""
        f = self.features
        if f.noise is None:
            raise ValueError("features built without their noise settings have no noise cost")
        link = self.calibration
        calibrated = link is not None and calibration is not None
        c = np.zeros(CALIBRATION_DIM) if not calibrated else np.asarray(calibration, float)
        if calibrated:
            e_r = self.evaluate_calibrated(world_T_body_a, world_T_body_b, c, False)[0]
            e_p = self.evaluate_calibrated(world_T_body_a, world_T_body_b, c, False,
                                           robust=False)[0]
        else:
            e_p = self.whitened_residuals(world_T_body_a, world_T_body_b)
            e_r = self.evaluate(world_T_body_a, world_T_body_b, False)[0].copy()
        plain = np.einsum("ni,ni->n", e_p, e_p)
        # the kernel's IRLS weight (its loss over the plain one: exact for a quadratic)
        weight = np.divide(np.einsum("ni,ni->n", e_r, e_r), plain, out=np.ones(f.n),
                           where=plain > 0)
        body_T_cam = corrected_mount(self.body_T_cam, c[MOUNT])
        wTc_a = world_T_body_a
        if link is not None and calibrated:
            wTc_a = wTc_a @ shift(link.twist_a, float(c[TIME_OFFSET]))
        G_E, N = self.planes(wTc_a @ body_T_cam, float(c[FOCAL_SCALE]))
        (sx, sy), sh = f.noise.sigma_q_xy, float(f.noise.sigma_h_m)
        moves = ((0, 0, sx), (0, 1, sy), (1, 0, sx), (1, 1, sy), (2, 2, sh))
        copies = 2 * len(moves)
        stacked = [np.tile(a, (copies, 1)) for a in (f.q_a, f.q_b, G_E)]
        for m, (which, axis, sigma) in enumerate(moves):
            for half, sign in enumerate((1.0, -1.0)):
                rows = slice((2 * m + half) * f.n, (2 * m + half + 1) * f.n)
                stacked[which][rows, axis] += sign * sigma
        q_a, q_b, G = stacked
        moved = PairFeatures(
            q_a, q_b, G, np.tile(N, (copies, 1)), np.tile(f.Sigma_e, (copies, 1, 1)),
            np.tile(f.Sigma_f, (copies, 1, 1)), cdtm_math.orthonormal_complement(q_b),
            np.tile(f.sqrt_info, (copies, 1, 1)), f.noise)
        return CdtmPairFactor(self.key_a, self.key_b, moved, self.body_T_cam, PlaneMode.FIXED,
                              calibration=link.fixed_at(c) if calibrated and link else None
                              ), weight, c

    def refreshed(self, world_T_body_a: np.ndarray, world_T_body_b: np.ndarray, noise:
                  FeatureNoise | None = None, raycast: RayCaster | None = None) -> CdtmPairFactor:
        """The same factor with planes and noise (eqs. 19-26) linearized at these poses (the
        estimate's, as the closed form: batch and incremental then solve the same problem);
        given, on another reading of the map: ``noise`` (a grown sigma_h), ``raycast`` (its
        planes, e.g. regional slopes; where a ray misses, the plane it had)."""
        f = self.features
        if (noise := noise or f.noise) is None:
            raise ValueError("features built without their noise settings cannot be refreshed")
        source = self if raycast is None else CdtmPairFactor(  # (cast: PlaneMode.FIXED too)
            self.key_a, self.key_b, f, self.body_T_cam, PlaneMode.REINTERSECT, raycast)
        wTc_a = world_T_body_a @ self.body_T_cam
        G_E, N = source.planes(wTc_a)
        features = PairFeatures.build(wTc_a, world_T_body_b @ self.body_T_cam, f.q_a, f.q_b,
                                      G_E, N, noise, f.dtm_variance_scale)
        return source._planes_to(CdtmPairFactor(
            self.key_a, self.key_b, features, self.body_T_cam, self.plane_mode, source.raycast,
            self.robust, self.robust_threshold, self.calibration))

    def _planes_to(self, other: CdtmPairFactor, keep: np.ndarray | None = None
                   ) -> CdtmPairFactor:
        """``other`` (this factor's features, or ``keep`` of them) with the planes this one
        cast last: the next evaluation at the same pose need not cast them again."""
        if self._planes_cache is not None:
            key, points, normals = self._planes_cache
            other._planes_cache = ((key, points, normals) if keep is None
                                   else (key, points[keep], normals[keep]))
        return other

    def with_calibration(self, calibration: CalibrationLink | None) -> CdtmPairFactor:
        """The same factor with another calibration link (e.g. held at an estimate)."""
        return self._planes_to(CdtmPairFactor(
            self.key_a, self.key_b, self.features, self.body_T_cam, self.plane_mode,
            self.raycast, self.robust, self.robust_threshold, calibration))

    def whitened_residuals(self, world_T_body_a: np.ndarray,
                           world_T_body_b: np.ndarray) -> np.ndarray:
        """Whitened residuals before any robust reweighting, (n, 2) (a fresh array).

        ``|r|^2`` is chi-square with 2 degrees of freedom for an inlier.
        """
        return self._unweighted(world_T_body_a, world_T_body_b, False)[0]

    def innovations(self, world_T_body_a: np.ndarray,
                    world_T_body_b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Whitened residuals (n, 2) and Jacobians (n, 2, 6) w.r.t. X(a), X(b) with no
        robust reweighting, as fresh arrays (an innovation and its measurement matrix)."""
        return self._unweighted(world_T_body_a, world_T_body_b, True)

    def _unweighted(self, world_T_body_a: np.ndarray, world_T_body_b: np.ndarray,
                    want_jacobians: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self.calibration is not None:
            e, Ha, Hb, _ = self.evaluate_calibrated(world_T_body_a, world_T_body_b,
                                                    self.calibration.value, want_jacobians,
                                                    robust=False)
            return e, Ha, Hb
        wTc_a = world_T_body_a @ self.body_T_cam
        wTc_b = world_T_body_b @ self.body_T_cam
        G_E, N = self.planes(wTc_a)
        f = self.features
        e = np.empty((f.n, 2))
        # (without Jacobians the kernel leaves the factor's own buffers untouched)
        Ha = np.empty((f.n, 2, 6)) if want_jacobians else self._Ha
        Hb = np.empty((f.n, 2, 6)) if want_jacobians else self._Hb
        cdtm_linearize(wTc_a[:3, :3], wTc_a[:3, 3], wTc_b[:3, :3], wTc_b[:3, 3], self._Ad,
                       f.q_a, G_E, N, f.basis_b, f.sqrt_info, KERNEL_NONE, self._kernel_k,
                       want_jacobians, e, Ha, Hb, NO_LOSS)
        return e, Ha, Hb

    def normalized_residuals(self, world_T_body_a: np.ndarray,
                             world_T_body_b: np.ndarray) -> np.ndarray:
        """Squared Mahalanobis distance of each residual as measured (both observations'
        pixel noise and the DTM's), (n,): chi-square(2) for an inlier at the true poses."""
        f = self.features
        e = self.whitened_residuals(world_T_body_a, world_T_body_b)
        if f.sqrt_info_full is None:
            return np.einsum("ni,ni->n", e, e)
        # back to the unwhitened residual, then the full whitening: both are the kernel's
        # upper triangles [[a, b], [0, d]] (written out; numpy's stacked 2x2 solve is slow)
        S, F = f.sqrt_info, f.sqrt_info_full
        u1 = e[:, 1] / S[:, 1, 1]
        u0 = (e[:, 0] - S[:, 0, 1] * u1) / S[:, 0, 0]
        z0 = F[:, 0, 0] * u0 + F[:, 0, 1] * u1
        z1 = F[:, 1, 1] * u1
        return z0 * z0 + z1 * z1

    def whitened_noise(self, world_T_body_a: np.ndarray, world_T_body_b: np.ndarray,
                       noise: FeatureNoise) -> np.ndarray:
        """Covariance (n, 2, 2) of the residuals under ``noise`` (eqs. 19-26 at these
        poses), in the coordinates this factor whitens to: the identity when ``noise`` is
        the factor's own, more when it adds terms (the first observation's pixel noise)."""
        f = self.features
        wTc_a = world_T_body_a @ self.body_T_cam
        wTc_b = world_T_body_b @ self.body_T_cam
        G_E, N = self.planes(wTc_a)
        Sigma_e = PairFeatures.build(wTc_a, wTc_b, f.q_a, f.q_b, G_E, N, noise,
                                     f.dtm_variance_scale).Sigma_e
        W = f.sqrt_info
        return W @ Sigma_e @ np.swapaxes(W, 1, 2)

    def with_robust_scale(self, robust_scale: np.ndarray | None) -> CdtmPairFactor:
        """The same factor whose kernel judges each residual against ``robust_scale``
        (n,) times the factor's whitening (e.g. the innovation's spread while the poses
        are uncertain)."""
        scale = None if robust_scale is None else np.asarray(robust_scale, dtype=float)
        features = dataclasses.replace(self.features, robust_scale=scale)
        return self._planes_to(CdtmPairFactor(
            self.key_a, self.key_b, features, self.body_T_cam, self.plane_mode, self.raycast,
            self.robust, self.robust_threshold, self.calibration))

    def with_features(self, keep: np.ndarray) -> CdtmPairFactor:
        """The same factor over the features selected by ``keep`` (mask or indices)."""
        return self._planes_to(CdtmPairFactor(
            self.key_a, self.key_b, self.features.subset(keep), self.body_T_cam,
            self.plane_mode, self.raycast, self.robust, self.robust_threshold,
            self.calibration), keep)

    def _error(self, this: gtsam.CustomFactor, values: gtsam.Values, jacobians) -> np.ndarray:
        link = self.calibration
        if link is not None and link.key is not None:
            return self._calibrated_error(values, link.key, jacobians)
        e, Ha, Hb = self.evaluate(pose_matrix(values, self.key_a),
                                  pose_matrix(values, self.key_b), jacobians is not None)
        if not self._compressed:
            if jacobians is not None:
                jacobians[0] = Ha.reshape(-1, 6)
                jacobians[1] = Hb.reshape(-1, 6)
            return e.reshape(-1)
        if jacobians is None:  # an error evaluation: only the norm counts
            out = np.zeros(COMPRESSED_ROWS)
            out[-1] = np.sqrt(np.einsum("ij,ij->", e, e))
            return out
        triangularize(e, Ha, Hb, _scratch(2 * self.features.n), self._Ja, self._Jb, self._z)
        jacobians[0] = self._Ja
        jacobians[1] = self._Jb
        return self._z

def _planes_key(world_T_cam_a: np.ndarray, focal_scale_minus_1: float) -> bytes:
    """What a cast of the planes depends on: the camera-a pose and the focal scale."""
    return world_T_cam_a.tobytes() + np.float64(focal_scale_minus_1).tobytes()


def make_feature_factors(
    key_a: int,
    key_b: int,
    features: PairFeatures,
    body_T_cam: np.ndarray,
    plane_mode: PlaneMode = PlaneMode.FIXED,
    raycast: RayCaster | None = None,
    robust: RobustKernel = RobustKernel.NONE,
    robust_threshold: float | None = None,
) -> list[gtsam.CustomFactor]:
    """One ``CustomFactor`` per feature (the paper's picture; slow: ~one callback each).

    Same arguments as :class:`CdtmPairFactor`; the noise is a 2x2 Gaussian
    (``Sigma_e``), wrapped in ``noiseModel.Robust`` when a kernel is given.
    """
    threshold = robust.default_threshold if robust_threshold is None else robust_threshold
    scale = features.robust_scale if features.robust_scale is not None else np.ones(features.n)
    factors: list[gtsam.CustomFactor] = []
    for i in range(features.n):
        # the kernel judges |S e| / robust_scale: GTSAM's kernel at threshold * scale
        estimator = robust.gtsam_estimator(threshold * float(scale[i]))
        single = features.subset(np.array([i]))
        # The per-feature factor returns the unwhitened residual; GTSAM whitens.
        single.sqrt_info = np.ascontiguousarray(np.eye(2)[None])
        single.robust_scale = None
        pair = CdtmPairFactor(key_a, key_b, single, body_T_cam, plane_mode, raycast)
        # smart=False: GTSAM's "smart" constructor would round a covariance with small
        # off-diagonal terms (~1e-10 rad^2 here) to a diagonal one.
        noise: Any = gtsam.noiseModel.Gaussian.SqrtInformation(features.sqrt_info[i], False)
        if estimator is not None:
            noise = gtsam.noiseModel.Robust.Create(estimator, noise)
        factors.append(gtsam.CustomFactor(noise, [key_a, key_b], pair._error))
    return factors
