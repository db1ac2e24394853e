"""flight.yaml's principal point, checked: one more step of the side solve with ``cx``,
``cy`` free.

A principal point ``d`` px off moves every normalized ray by ``d / f``, which a frame pair
reads as the camera moved by ``height * d / f`` in body axes (5 px at 1800 m: 17 m): not
a mount rotation (a rotation adds a perspective term), so the five parameters of the
calibration check (:mod:`cdtm_graph.calibration.check`) do not take it, and a run holding
it is trusted while wrong (1 px: ANEES 50-78; docs/verdict.md). What tells it are the
roll changes: the body-fixed offset would have to jump within a second, which the IMU
forbids.

The test is the score (Rao) test of the shift at the side solve's free optimum (the five
parameters estimated): the Gauss-Newton step of its graph with the shift's two columns
added to every C-DTM pair factor's rows (:meth:`factors.CdtmPairFactor.
principal_point_columns`). At that optimum the graph's own gradient is zero, so the step
is the shift's alone, and the error it would drop, ``d^T P^-1 d / 2`` (``d`` the shift,
``P`` its covariance: the Schur complement of everything else), is to first order the
likelihood ratio of freeing ``cx``, ``cy``: one elimination, no second solve.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import gtsam
import numpy as np

from cdtm_graph.calibration.clustered import sandwich, side_solve_dims
from cdtm_graph.calibration.noise_bias import corrected_system, noise_gradient
from cdtm_graph.calibration.online import CALIBRATION_KEY
from cdtm_graph.optimizer import step_and_marginals
from factors import CdtmPairFactor

#: The calibration with the shift in the step's linear graph: ``[C(0) (5), dcx, dcy (px)]``
#: (GTSAM's Python takes at most three keys a Jacobian factor: the pair factors' rows hold
#: the two poses and this).
WITH_PRINCIPAL_POINT_KEY = gtsam.symbol("c", 1)

#: The shift's prior 1-sigma in the step (pixels): a regularizer where the flight does not
#: tell it (no roll change), far above any shift the test names.
PRIOR_SIGMA_PX = 50.0


#: The flight contradicts flight.yaml's principal point when freeing it lowers the error
#: by more than this: chi-square(2)'s 99.9% quantile (13.8 / 2) times 2.7, the allowance
#: the five parameters' test makes for what clean flights show
#: (:data:`cdtm_graph.calibration.check.SUSPECT_COST_DROP`). Not fitted: docs/verdict.md
#: gives what it was checked on.
PRINCIPAL_POINT_COST_DROP = 18.7

#: ...and conclusive when it tells each of ``cx``, ``cy`` to this 1-sigma (px): a flight of a
#: few frames, or before its first roll change, tells the shift poorly (a 4-frame log read
#: cx -63 px at a sigma of 8.8 px, drop 25.8), while the issue's 90-frame flight tells it
#: to 0.45 px (cx, along track) and 0.18 px (cy).
PRINCIPAL_POINT_CONCLUSIVE_PX = 1.0

#: ...and specific when its Wald statistic on the cluster-robust covariance exceeds this:
#: chi-square(2)'s 99.9% quantile (13.8) times the same 2.7, as the five's ``SUSPECT_WALD``
#: is chi-square(5)'s. Not fitted: see docs/verdict.md for what it was checked on.
PRINCIPAL_POINT_WALD = 37.3


@dataclass(frozen=True)
class PrincipalPointStep:
    """The side solve's step with the principal point free.

    Attributes:
        shift_px: (2,) the correction to flight.yaml's ``cx``, ``cy`` (pixels).
        covariance_px2: (2, 2) its covariance.
        cost_drop: the error the step drops (half a chi-square: the shift's score
            statistic, ``shift^T covariance^-1 shift / 2``).
        step: the whole step (every variable of the side solve), from which the positions'
            move is read.
        wald: the shift's Wald statistic on its cluster-robust covariance
            (:func:`~cdtm_graph.calibration.clustered.sandwich`, as the five's); NaN where
            the drop is not significant.
        step_without_shift: the same corrected-score step without the shift's columns
            (the five's own correction): ``step`` less this is the shift's move of every
            variable. None where the drop is not significant.
    """

    def position_move_m(self, values: gtsam.Values, keys: Sequence[int]) -> np.ndarray:
        """(F, 3) how far the shift moves the positions of the poses ``keys`` (world, m):
        the step's positions less those of the step without it, both from ``values``."""
        assert self.step_without_shift is not None
        return np.stack([values.atPose3(k).retract(self.step.at(k)).translation()
                         - values.atPose3(k).retract(self.step_without_shift.at(k)).translation()
                         for k in keys])

    shift_px: np.ndarray
    covariance_px2: np.ndarray
    cost_drop: float
    step: gtsam.VectorValues
    wald: float = float("nan")
    step_without_shift: gtsam.VectorValues | None = None

    @property
    def sigma_px(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.covariance_px2), 0.0, None))


def principal_point_step(linear: gtsam.GaussianFactorGraph, values: gtsam.Values,
                         factors: Sequence[CdtmPairFactor], fx_px: float, fy_px: float,
                         noise_scale: float = 1.0,
                         gradient: dict[int, np.ndarray] | None = None
                         ) -> PrincipalPointStep | None:
    """The Gauss-Newton step of the side solve at ``values`` with the principal point free.

    Args:
        linear: the side solve's graph linearized at ``values`` (its C-DTM pair factors
            among them, each holding ``CALIBRATION_KEY``). values: its optimum.
        factors: those C-DTM pair factors. fx_px, fy_px: flight.yaml's focal lengths (the
            shift's columns in pixels).
        noise_scale: the noise's variance over the model's, as for the five
            (:func:`~cdtm_graph.calibration.noise_bias.debiased`).
        gradient: ``noise_gradient(factors, values, (fx_px, fy_px))``, if the caller has
            it (the model's noise; the calibration's part (7,) with the shift's).

    Returns None when ``linear`` does not hold one factor per C-DTM pair factor of those
    keys (nothing to test against).
    """
    pairs = {(f.key_a, f.key_b) for f in factors}
    c = values.atVector(CALIBRATION_KEY)
    m = c.size
    augmented = gtsam.GaussianFactorGraph()
    replaced = 0
    for i in range(linear.size()):
        part = linear.at(i)
        keys = list(part.keys())
        if CALIBRATION_KEY not in keys:
            augmented.push_back(part)
        elif len(keys) == 3 and keys[2] == CALIBRATION_KEY and (keys[0], keys[1]) in pairs:
            replaced += 1
        elif keys == [CALIBRATION_KEY]:  # the calibration's prior: zero on the shift
            A, b = part.jacobian()
            augmented.add(WITH_PRINCIPAL_POINT_KEY, np.hstack([A, np.zeros((A.shape[0], 2))]),
                          b, gtsam.noiseModel.Unit.Create(A.shape[0]))
        else:
            return None
    if replaced != len(factors):
        return None
    to_px = np.array([1.0 / fx_px, 1.0 / fy_px])
    rows = []
    for f in factors:
        Ta, Tb = values.atPose3(f.key_a).matrix(), values.atPose3(f.key_b).matrix()
        e, Ha, Hb, Hc = f.evaluate_calibrated(Ta, Tb, c)
        Hk = np.concatenate([Hc, f.principal_point_columns(Ta, Tb, c) * to_px], axis=2)
        rows.append((f, e, Ha, Hb, Hk))
        # the rows in square-root information form (as the factor compresses its own)
        stacked = np.concatenate([Ha.reshape(-1, 6), Hb.reshape(-1, 6),
                                  Hk.reshape(-1, m + 2), -e.reshape(-1, 1)], axis=1)
        R: np.ndarray = np.linalg.qr(stacked, mode="r")  # type: ignore[assignment]
        augmented.add(f.key_a, R[:, :6], f.key_b, R[:, 6:12], WITH_PRINCIPAL_POINT_KEY,
                      R[:, 12:-1], R[:, -1], gtsam.noiseModel.Unit.Create(R.shape[0]))
    prior = np.zeros((2, m + 2))
    prior[:, m:] = np.eye(2) / PRIOR_SIGMA_PX
    augmented.add(WITH_PRINCIPAL_POINT_KEY, prior, np.zeros(2), gtsam.noiseModel.Unit.Create(2))
    # the corrected score, as the five's step has it (:mod:`~cdtm_graph.calibration.
    # noise_bias`): the pixel noise biases the shift too (+3 px in cx, 7 sigma, on a clean
    # flight without it)
    if gradient is None:
        gradient = noise_gradient(factors, values, (fx_px, fy_px))
    gradient = {key: noise_scale * g for key, g in gradient.items()}
    hessian_form, jacobian_form = corrected_system(augmented, {
        WITH_PRINCIPAL_POINT_KEY if key == CALIBRATION_KEY else key: g
        for key, g in gradient.items()})
    step, (covariance,) = step_and_marginals(hessian_form, [WITH_PRINCIPAL_POINT_KEY],
                                             qr_form=jacobian_form)
    shift = np.asarray(step.at(WITH_PRINCIPAL_POINT_KEY), dtype=float)[m:]
    covariance = covariance[m:, m:]
    drop = 0.5 * float(shift @ np.linalg.solve(covariance, shift))
    wald, without = float("nan"), None
    if drop > PRINCIPAL_POINT_COST_DROP:  # (a dense solve and an elimination: only where
        # they decide) the five's own step, the same corrected score without the shift
        gradient[CALIBRATION_KEY] = gradient[CALIBRATION_KEY][:m]
        hessian_form, jacobian_form = corrected_system(linear, gradient)
        without, _ = step_and_marginals(hessian_form, [], qr_form=jacobian_form)
        dims = {WITH_PRINCIPAL_POINT_KEY if key == CALIBRATION_KEY else key:
                m + 2 if key == CALIBRATION_KEY else dim
                for key, dim in side_solve_dims(values).items()}
        # (the residuals as the step leaves them, to first order: the spread is read at
        # the estimate with the shift, as the five's is read at their corrected estimate;
        # at the free optimum the shift's own misfit, correlated over the ground, would
        # count as spread: 5 px read W 65-74, no more than 2 px)
        k = np.asarray(step.at(WITH_PRINCIPAL_POINT_KEY), dtype=float)
        after = [(f, e + Ha @ step.at(f.key_a) + Hb @ step.at(f.key_b) + Hk @ k, Ha, Hb, Hk)
                 for f, e, Ha, Hb, Hk in rows]
        robust = sandwich(augmented, dims, WITH_PRINCIPAL_POINT_KEY, after)[m:, m:]
        wald = float(shift @ np.linalg.solve(robust, shift))
    return PrincipalPointStep(shift, covariance, drop, step, wald, without)


@dataclass(frozen=True)
class PrincipalPointCheck:
    """What the step with the principal point free found (report.json
    ``calibration_check.principal_point``).

    Attributes:
        shift_px: (2,) the correction to flight.yaml's ``cx``, ``cy`` (pixels).
        sigma_px: (2,) its 1-sigmas.
        cost_drop: the error the step drops (:class:`PrincipalPointStep`).
        position_nees: mean over frames of how far the shift alone moves the positions
            (the step less the five's own step), squared Mahalanobis distance in the run's
            position covariance; NaN where the drop is not significant (not computed).
        wald: :attr:`PrincipalPointStep.wald`.
    """

    shift_px: np.ndarray
    sigma_px: np.ndarray
    cost_drop: float
    position_nees: float
    wald: float = float("nan")

    @property
    def significant(self) -> bool:
        return self.cost_drop > PRINCIPAL_POINT_COST_DROP

    @property
    def specific(self) -> bool:
        return self.wald > PRINCIPAL_POINT_WALD

    @property
    def conclusive(self) -> bool:
        return bool(np.max(self.sigma_px) < PRINCIPAL_POINT_CONCLUSIVE_PX)

    def describe(self) -> str:
        """The finding in words (appended to the calibration check's)."""
        z = self.shift_px / self.sigma_px
        return (f"one more step with the principal point free moves cx by "
                f"{self.shift_px[0]:+.1f} px ({z[0]:+.1f} sigma) and cy by "
                f"{self.shift_px[1]:+.1f} px ({z[1]:+.1f} sigma), lowering the error by "
                f"{self.cost_drop:.1f} more ({PRINCIPAL_POINT_COST_DROP:.1f} is chance at "
                f"99.9%)" + (f", a Wald statistic of {self.wald:.1f} against the map's shared "
                             f"error and the residuals' scatter ({PRINCIPAL_POINT_WALD:.1f} "
                             "needed)" if np.isfinite(self.wald) else "")
                + f", and the run's positions lie at a mean NEES of {self.position_nees:.1f} "
                "from where it moves them")

    def to_dict(self) -> dict:
        return {"shift_px": self.shift_px.tolist(), "sigma_px": self.sigma_px.tolist(),
                "cost_drop": self.cost_drop,
                "position_nees": (self.position_nees if np.isfinite(self.position_nees)
                                  else None),
                "wald": self.wald if np.isfinite(self.wald) else None}
