"""Calibration parts the side solve does not estimate, tested by one more step.

The calibration check (:mod:`cdtm_graph.calibration.check`) estimates five parameters.
Others a user can get wrong (the principal point: :mod:`~cdtm_graph.calibration.
principal_point`) are each tested by the score (Rao) test at the side solve's free
optimum: the Gauss-Newton step of its graph with the part's columns added to every C-DTM
pair factor's rows. At that optimum
the graph's own gradient is zero, so the step is the part's alone, and the error it would
drop, ``d^T P^-1 d / 2`` (``d`` the part's correction, ``P`` its covariance: the Schur
complement of everything else), is to first order the likelihood ratio of freeing it: one
elimination, no second solve. The step is the corrected score's, as the five's
(:mod:`~cdtm_graph.calibration.noise_bias`): the pixel noise biases a part as it biases
the focal scale.

A part is named (the verdict's ``calibration_suspect``) when its drop is significant, the
step tells it (``conclusive_sigma``), it is specific (its Wald statistic on the
cluster-robust covariance, :func:`~cdtm_graph.calibration.clustered.sandwich`, as the
five's) and it matters (the positions' move of the part alone, beyond their covariance).
The thresholds follow the five's: chi-square(d)'s 99.9% quantile (halved for the drop)
times the 2.7 clean flights show.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import gtsam
import numpy as np

from cdtm_graph.calibration.clustered import sandwich, side_solve_dims
from cdtm_graph.calibration.noise_bias import corrected_system
from cdtm_graph.calibration.online import CALIBRATION_KEY
from cdtm_graph.optimizer import step_and_marginals
from factors import CdtmPairFactor

#: The calibration with the part in the step's linear graph: ``[C(0) (5), the part]``
#: (GTSAM's Python takes at most three keys a Jacobian factor: the pair factors' rows hold
#: the two poses and this).
WITH_PART_KEY = gtsam.symbol("c", 1)

#: The allowance the five parameters' tests make for what clean flights show
#: (:data:`cdtm_graph.calibration.check.SUSPECT_COST_DROP`), kept for every part.
CLEAN_ALLOWANCE = 2.7

#: chi-square(d)'s 99.9% quantile, d = 1..3 (no scipy.stats at import).
CHI2_999 = {1: 10.828, 2: 13.816, 3: 16.266}

#: (f, Ta, Tb, c, Ha, Hb) -> the part's whitened, reweighted columns (n, 2, d): the pair
#: factor, its poses (4, 4), the calibration (5,), its pose Jacobians (n, 2, 6).
Columns = Callable[[CdtmPairFactor, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                    np.ndarray], np.ndarray]


@dataclass(frozen=True)
class ExtraPart:
    """A calibration part, how the step sees it and when it is named.

    Attributes:
        name: its name in report.json and the verdict (``principal_point``).
        labels: its components' names in flight.yaml's terms (``cx``, ``cy``).
        unit: their unit (``px``, ``m``).
        columns: its columns (:data:`Columns`).
        noise_part: its part of the noise's expected gradient, from
            :func:`~cdtm_graph.calibration.noise_bias.noise_gradient`'s dict (at the
            model's noise).
        prior_sigma: the step's prior 1-sigma on it (a regularizer where the flight does
            not tell it, far above what the test names).
        conclusive_sigma: the step tells it when every component's 1-sigma is below this.
        advice: what the user corrects.
    """

    name: str
    labels: tuple[str, ...]
    unit: str
    columns: Columns
    noise_part: Callable[[dict[int, np.ndarray]], np.ndarray]
    prior_sigma: float
    conclusive_sigma: float
    advice: str

    @property
    def dim(self) -> int:
        return len(self.labels)

    @property
    def cost_drop(self) -> float:
        """The significance bound on the drop (half a chi-square)."""
        return round(CHI2_999[self.dim] / 2 * CLEAN_ALLOWANCE, 1)

    @property
    def wald(self) -> float:
        """The specificity bound on the Wald statistic."""
        return round(CHI2_999[self.dim] * CLEAN_ALLOWANCE, 1)


@dataclass(frozen=True)
class ScoreStep:
    """The side solve's step with a part free.

    Attributes:
        correction: (d,) the part's correction to flight.yaml.
        covariance: (d, d) its covariance.
        cost_drop: the error the step drops (half a chi-square: the part's score
            statistic, ``correction^T covariance^-1 correction / 2``).
        step: the whole step (every variable of the side solve).
        wald: the correction's Wald statistic on its cluster-robust covariance; NaN where
            the drop is not significant.
        step_without: the same corrected-score step without the part's columns (the
            five's own correction): ``step`` less this is the part's move of every
            variable. None where the drop is not significant.
    """

    correction: np.ndarray
    covariance: np.ndarray
    cost_drop: float
    step: gtsam.VectorValues
    wald: float = float("nan")
    step_without: gtsam.VectorValues | None = None

    @property
    def sigma(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    def position_move_m(self, values: gtsam.Values, keys: Sequence[int]) -> np.ndarray:
        """(F, 3) how far the part alone moves the positions of the poses ``keys`` (world,
        m): the step's positions less those of the step without it, both from ``values``."""
        assert self.step_without is not None
        return np.stack([values.atPose3(k).retract(self.step.at(k)).translation()
                         - values.atPose3(k).retract(self.step_without.at(k)).translation()
                         for k in keys])


#: One pair factor's rows with a part's columns: the factor, its residuals (n, 2), its
#: Jacobians of pose a, pose b (n, 2, 6) and of the calibration with the part (n, 2, m + d).
PartRows = tuple[CdtmPairFactor, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def with_part(linear: gtsam.GaussianFactorGraph, values: gtsam.Values,
              factors: Sequence[CdtmPairFactor], part: ExtraPart
              ) -> tuple[gtsam.GaussianFactorGraph, list[PartRows]] | None:
    """``linear`` with ``part``'s columns added to every C-DTM pair factor's rows: the
    calibration key becomes :data:`WITH_PART_KEY` (``[C(0), the part]``; its priors zero on
    the part, which gets none here).

    Args:
        linear: a side solve's graph linearized at ``values`` (its C-DTM pair factors
            among them, each holding ``CALIBRATION_KEY``).
        factors: those C-DTM pair factors. part: the part.

    Returns the graph and each pair factor's rows; None when ``linear`` does not hold one
    factor per C-DTM pair factor of those keys (nothing to add to).
    """
    pairs = {(f.key_a, f.key_b) for f in factors}
    c = values.atVector(CALIBRATION_KEY)
    m, d = c.size, part.dim
    augmented = gtsam.GaussianFactorGraph()
    replaced = 0
    for i in range(linear.size()):
        factor = linear.at(i)
        keys = list(factor.keys())
        if CALIBRATION_KEY not in keys:
            augmented.push_back(factor)
        elif len(keys) == 3 and keys[2] == CALIBRATION_KEY and (keys[0], keys[1]) in pairs:
            replaced += 1
        elif keys == [CALIBRATION_KEY]:  # the calibration's prior: zero on the part
            A, b = factor.jacobian()
            augmented.add(WITH_PART_KEY, np.hstack([A, np.zeros((A.shape[0], d))]), b,
                          gtsam.noiseModel.Unit.Create(A.shape[0]))
        else:
            return None
    if replaced != len(factors):
        return None
    rows: list[PartRows] = []
    for f in factors:
        Ta, Tb = values.atPose3(f.key_a).matrix(), values.atPose3(f.key_b).matrix()
        e, Ha, Hb, Hc = f.evaluate_calibrated(Ta, Tb, c)
        Hk = np.concatenate([Hc, part.columns(f, Ta, Tb, c, Ha, Hb)], axis=2)
        rows.append((f, e, Ha, Hb, Hk))
        # the rows in square-root information form (as the factor compresses its own)
        stacked = np.concatenate([Ha.reshape(-1, 6), Hb.reshape(-1, 6),
                                  Hk.reshape(-1, m + d), -e.reshape(-1, 1)], axis=1)
        R: np.ndarray = np.linalg.qr(stacked, mode="r")  # type: ignore[assignment]
        augmented.add(f.key_a, R[:, :6], f.key_b, R[:, 6:12], WITH_PART_KEY, R[:, 12:-1],
                      R[:, -1], gtsam.noiseModel.Unit.Create(R.shape[0]))
    return augmented, rows


def score_step(linear: gtsam.GaussianFactorGraph, values: gtsam.Values,
               factors: Sequence[CdtmPairFactor], part: ExtraPart,
               gradient: dict[int, np.ndarray], noise_scale: float = 1.0
               ) -> ScoreStep | None:
    """The corrected-score Gauss-Newton step of the side solve at ``values`` with ``part``
    free.

    Args:
        linear: the side solve's graph linearized at ``values`` (its C-DTM pair factors
            among them, each holding ``CALIBRATION_KEY``). values: its optimum.
        factors: those C-DTM pair factors. part: what is freed.
        gradient: the noise's expected gradient (:func:`~cdtm_graph.calibration.
            noise_bias.noise_gradient`, the model's noise; the calibration's part may hold
            more than the five, which are its first entries).
        noise_scale: the noise's variance over the model's (the residuals' scatter as
            measured).

    Returns None when ``linear`` does not hold one factor per C-DTM pair factor of those
    keys (nothing to test against).
    """
    built = with_part(linear, values, factors, part)
    if built is None:
        return None
    augmented, rows = built
    m, d = values.atVector(CALIBRATION_KEY).size, part.dim
    prior = np.zeros((d, m + d))
    prior[:, m:] = np.eye(d) / part.prior_sigma
    augmented.add(WITH_PART_KEY, prior, np.zeros(d), gtsam.noiseModel.Unit.Create(d))
    five = {key: noise_scale * (g[:m] if key == CALIBRATION_KEY else g)
            for key, g in gradient.items()}
    hessian_form, jacobian_form = corrected_system(augmented, {
        **{key: g for key, g in five.items() if key != CALIBRATION_KEY},
        WITH_PART_KEY: np.concatenate([five.get(CALIBRATION_KEY, np.zeros(m)),
                                       noise_scale * part.noise_part(gradient)])})
    step, (covariance,) = step_and_marginals(hessian_form, [WITH_PART_KEY],
                                             qr_form=jacobian_form)
    k = np.asarray(step.at(WITH_PART_KEY), dtype=float)
    correction, covariance = k[m:], covariance[m:, m:]
    drop = 0.5 * float(correction @ np.linalg.solve(covariance, correction))
    wald, without = float("nan"), None
    if drop > part.cost_drop:  # (a dense solve and an elimination: only where they decide)
        # the five's own step: the same corrected score without the part
        hessian_form, jacobian_form = corrected_system(linear, five)
        without, _ = step_and_marginals(hessian_form, [], qr_form=jacobian_form)
        dims = {WITH_PART_KEY if key == CALIBRATION_KEY else key:
                m + d if key == CALIBRATION_KEY else dim
                for key, dim in side_solve_dims(values).items()}
        # (the residuals as the step leaves them, to first order: the spread is read at
        # the estimate with the part, as the five's is read at their corrected estimate;
        # at the free optimum the part's own misfit, correlated over the ground, would
        # count as spread: a principal point 5 px off read W 65-74, no more than 2 px)
        after = [(f, e + Ha @ step.at(f.key_a) + Hb @ step.at(f.key_b) + Hk @ k, Ha, Hb, Hk)
                 for f, e, Ha, Hb, Hk in rows]
        robust = sandwich(augmented, dims, WITH_PART_KEY, after)[m:, m:]
        wald = float(correction @ np.linalg.solve(robust, correction))
    return ScoreStep(correction, covariance, drop, step, wald, without)


@dataclass(frozen=True)
class PartCheck:
    """What the step with a part free found (report.json ``calibration_check.<name>``).

    Attributes:
        part: the part.
        correction: (d,) the correction to flight.yaml's values (the part's unit).
        sigma: (d,) its 1-sigmas.
        cost_drop: the error the step drops (:class:`ScoreStep`).
        position_nees: mean over frames of how far the part alone moves the positions (the
            step less the five's own step), squared Mahalanobis distance in the run's
            position covariance; NaN where the drop is not significant (not computed).
        wald: :attr:`ScoreStep.wald`.
    """

    part: ExtraPart
    correction: np.ndarray
    sigma: np.ndarray
    cost_drop: float
    position_nees: float
    wald: float = float("nan")

    @property
    def significant(self) -> bool:
        return self.cost_drop > self.part.cost_drop

    @property
    def specific(self) -> bool:
        return self.wald > self.part.wald

    @property
    def conclusive(self) -> bool:
        return bool(np.max(self.sigma) < self.part.conclusive_sigma)

    def describe(self) -> str:
        """The finding in words (appended to the calibration check's)."""
        z = self.correction / self.sigma
        moves = ", ".join(f"{label} by {x:+.1f} {self.part.unit} ({zi:+.1f} sigma)"
                          for label, x, zi in zip(self.part.labels, self.correction, z,
                                                  strict=True))
        return (f"one more step with the {self.part.name.replace('_', ' ')} free moves "
                f"{moves}, lowering the error by {self.cost_drop:.1f} more "
                f"({self.part.cost_drop:.1f} is chance at 99.9%)"
                + (f", a Wald statistic of {self.wald:.1f} against the map's shared error and "
                   f"the residuals' scatter ({self.part.wald:.1f} needed)"
                   if np.isfinite(self.wald) else "")
                + (f", and the run's positions lie at a mean NEES of {self.position_nees:.1f} "
                   "from where it moves them" if np.isfinite(self.position_nees) else ""))

    def to_dict(self) -> dict:
        return {"correction": self.correction.tolist(), "sigma": self.sigma.tolist(),
                "labels": list(self.part.labels), "unit": self.part.unit,
                "cost_drop": self.cost_drop,
                "position_nees": (self.position_nees if np.isfinite(self.position_nees)
                                  else None),
                "wald": self.wald if np.isfinite(self.wald) else None}
