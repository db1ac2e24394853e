"""The C-DTM estimate less the bias its noise leaves: one corrected-score step.

A C-DTM factor holds the first observation ``q_a`` exact and its whitening fixed, while
the residual's noise grows and shrinks with the poses (``q_a``'s pixel noise moves the
ground point by its range from camera a) and with the focal scale. Least squares then
leans toward where the noise looks small: at the truth the expected gradient of the cost
is not zero but half the gradient of the noise's expected cost
(:meth:`factors.CdtmPairFactor.noise_cost_gradient`), an errors-in-variables bias. It
is small for the poses the IMU holds, but a focal scale estimated online takes it whole:
2.5 sigma low on the issue's flight with pixel noise alone (docs/design.md, "Calibration
online"), and the heights with it.

The corrected score subtracts that expectation; one Newton step of it from the solution
removes the bias to first order (it is a fraction of a sigma to a few sigmas, well inside
the linearization).
"""

from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np

from cdtm_graph.optimizer import step_and_marginals
from factors import CdtmPairFactor
from factors.calibrated_pair import RayJacobian


def noise_gradient(factors: Sequence[CdtmPairFactor], values: gtsam.Values,
                   principal_point_px: tuple[float, float] | None = None,
                   ray_jacobian: RayJacobian | None = None) -> dict[int, np.ndarray]:
    """Half the gradient of the C-DTM noise's expected cost, per variable key (the pose
    tangents' and, when the factors hold it, the calibration's). ``principal_point_px``
    (flight.yaml's fx, fy): the calibration's part also holds a principal point shift's,
    (7,): ``[C(0), dcx, dcy (px)]`` (:mod:`cdtm_graph.calibration.principal_point`; the
    lens's ``ray_jacobian`` as :meth:`factors.CdtmPairFactor.principal_point_columns`)."""
    out: dict[int, np.ndarray] = {}
    to_px = None if principal_point_px is None else 1.0 / np.asarray(principal_point_px)
    for f in factors:
        Ta, Tb = values.atPose3(f.key_a).matrix(), values.atPose3(f.key_b).matrix()
        key_c = None if f.calibration is None else f.calibration.key
        c = values.atVector(key_c) if key_c is not None else None
        g = 0.5 * f.noise_cost_gradient(Ta, Tb, c, principal_point=to_px is not None,
                                        ray_jacobian=ray_jacobian)
        if to_px is not None and key_c is not None:
            g[-2:] *= to_px
        parts = [(f.key_a, g[:6]), (f.key_b, g[6:12])]
        if key_c is not None:
            parts.append((key_c, g[12:]))
        for key, part in parts:
            out[key] = out.get(key, 0.0) + part
    return out


def debiased(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
             factors: Sequence[CdtmPairFactor], noise_scale: float = 1.0,
             linear: gtsam.GaussianFactorGraph | None = None,
             marginal_keys: Sequence[int] = (),
             gradient: dict[int, np.ndarray] | None = None
             ) -> tuple[gtsam.Values, list[np.ndarray]]:
    """``values`` moved by one corrected-score step: the Gauss-Newton step of ``graph``
    at ``values`` with the noise's expected gradient taken out of its gradient; and the
    marginal covariance of each of ``marginal_keys``, from the same elimination.

    Args:
        graph: the whole graph (``factors`` among its factors). values: its solution.
        factors: the C-DTM pair factors.
        noise_scale: the noise's variance over the model's (the expected gradient grows
            with it: :func:`cdtm_graph.calibration.clustered.residual_scatter`).
        linear: ``graph`` linearized at ``values``, if the solve has it (``LinearSolver.
            linearized_at``); it gains the noise's terms here.
        marginal_keys: the keys whose covariance is wanted. They are taken at ``values``
            (the solve's linearization, which the step needs anyway; the gradient's terms
            add no information), not at the moved values: one elimination, not a second
            linearization and elimination. The step is a fraction of a sigma.
        gradient: :func:`noise_gradient` of ``factors`` at ``values``, if the caller has it
            (at the model's noise: ``noise_scale`` multiplies it here).
    """
    hessian_form, jacobian_form = corrected_system(
        graph.linearize(values) if linear is None else linear,
        {key: noise_scale * g for key, g in (noise_gradient(factors, values) if gradient is None
                                             else gradient).items()})
    step, covariances = step_and_marginals(hessian_form, marginal_keys, qr_form=jacobian_form)
    return values.retract(step), covariances


def corrected_system(linear: gtsam.GaussianFactorGraph, gradient: dict[int, np.ndarray]
                     ) -> tuple[gtsam.GaussianFactorGraph, gtsam.GaussianFactorGraph]:
    """``linear`` with ``gradient`` (per key) taken out of its gradient, twice: with Hessian
    factors (Cholesky's form) and with Jacobian factors (QR's: its elimination drops a
    Hessian factor's linear term). Graphs of their own: ``linear`` stays as it was."""
    hessian_form, jacobian_form = gtsam.GaussianFactorGraph(), gtsam.GaussianFactorGraph()
    hessian_form.push_back(linear)
    jacobian_form.push_back(linear)
    for key, g in gradient.items():
        # a zero Hessian and the linear term: the step solves H d = -grad + g
        hessian_form.push_back(gtsam.HessianFactor(key, np.zeros((g.size, g.size)), g, 0.0))
        # the same term as |eps d - g / eps|^2 / 2, whose eps^2 on the diagonal is far
        # below any information here (1e-12 against ~1e-4 for the loosest prior)
        jacobian_form.add(key, _EPS * np.eye(g.size), g / _EPS,
                          gtsam.noiseModel.Unit.Create(g.size))
    return hessian_form, jacobian_form


#: The gradient's Jacobian form for QR (:func:`debiased`).
_EPS = 1e-6
