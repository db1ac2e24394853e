"""The side solve's calibration judged against the other explanations of its data.

The side solve (:mod:`cdtm_graph.calibration.check`) models each C-DTM residual as
independent noise of the size ``sigma_h`` and the pixel noise say. Two other faults then
move its calibration, the focal scale first (it trades with the map's height):

* **More scatter than the model**: ground detail the DTM lacks, tracker slips, wrong
  matches on the epipolar line. The noise's errors-in-variables bias, which
  :func:`~cdtm_graph.calibration.noise_bias.debiased` takes out at the model's size,
  grows with the scatter: on the issue's flight with 15% wrong matches on the epipolar
  line, the residuals at 3.1 times their expectation left the focal scale at -8 sigma
  after the model's correction, -2.9 after the measured one. :func:`residual_scatter`
  measures it (the truncated chi-square the verdict's self-check uses, at the calibrated
  solution, so that a calibration fault's own misfit is not counted), and the check
  debiases with it.
* **Errors shared by neighbouring features**: the ground detail is correlated over
  hundreds of metres, and every sighting of one ground point shares it whole, while the
  model's covariance takes each residual as a draw of its own.
  :func:`clustered_covariance` measures the spread instead: the cluster-robust
  ("sandwich") covariance, the C-DTM residuals grouped by the ground cell their DTM point
  lies in (``CELL_M``).

The calibration is named only when its correction stands out of both (a Wald statistic on
this covariance: ``SUSPECT_WALD`` in :mod:`cdtm_graph.calibration.check`).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import gtsam
import numpy as np

from cdtm_graph.calibration.online import CALIBRATION_KEY
from cdtm_graph.robust.gating import (
    CHI2_2DOF_999,
    OUTLIER_TEST_PROBABILITY,
    mahalanobis_2d,
    truncated_chi2_2dof_mean,
)
from factors import CdtmPairFactor
from factors.calibration import CALIBRATION_DIM

#: Ground cells (m) whose features' residuals are taken as one draw of the map's error:
#: longer than the detail's wavelengths (40-300 m in the simulator's shapes), so that
#: neighbouring cells are nearly independent; ~100-150 cells on the issue's flight.
CELL_M = 500.0

#: Dimension of each kind of variable of the side solve's graph (poses, velocities,
#: IMU biases; the calibration apart).
_DIM = {"x": 6, "v": 3, "b": 6}


def residual_scatter(factors: Sequence[CdtmPairFactor], values: gtsam.Values,
                     floor: float = 1.0) -> float:
    """The C-DTM features' squared Mahalanobis distances (the full measurement noise, each
    truncated at the chi-square(2) 99.9% test as the verdict's self-check has it) over
    their expectation, at ``values`` (with the calibration's ``CALIBRATION_KEY``); at
    least ``floor`` (1: less scatter never makes the five's check bolder)."""
    c = values.atVector(CALIBRATION_KEY)
    total, n = 0.0, 0
    for f in factors:
        Ta, Tb = values.atPose3(f.key_a).matrix(), values.atPose3(f.key_b).matrix()
        e = f.evaluate_calibrated(Ta, Tb, c, False, robust=False)[0]
        d = mahalanobis_2d(e, f.features.whitened_full_covariance())
        total += float(np.minimum(d, CHI2_2DOF_999).sum())
        n += d.size
    if n == 0:
        return max(1.0, floor)
    return max(total / n / truncated_chi2_2dof_mean(OUTLIER_TEST_PROBABILITY), floor)


def clustered_covariance(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                         factors: Sequence[CdtmPairFactor], cell_m: float = CELL_M
                         ) -> np.ndarray:
    """The calibration's (5, 5) cluster-robust covariance at ``values``:

        V = P - A (sum_i J_i^T J_i) A^T + G / (G - 1) sum_g (A s_g)(A s_g)^T,

    ``P = A H A^T`` the model's (``H`` the graph's Hessian), ``A`` the calibration's rows
    of ``H^-1``, ``J_i``, ``e_i`` feature i's whitened (robustly reweighted) Jacobian and
    residual, ``s_g = sum_{i in g} J_i^T e_i`` over the features whose DTM point lies in
    ground cell g (``cell_m``), G the cells. The IMU and prior factors keep their model
    part. Only a spread beyond the model's is taken (the difference's positive part).

    Args:
        graph: the side solve's whole graph (``factors`` among its factors). values: its
            solution, with ``CALIBRATION_KEY``. factors: its C-DTM pair factors (each
            linked to ``CALIBRATION_KEY``).
    """
    c = values.atVector(CALIBRATION_KEY)

    def rows():
        for f in factors:
            Ta, Tb = values.atPose3(f.key_a).matrix(), values.atPose3(f.key_b).matrix()
            yield f, *f.evaluate_calibrated(Ta, Tb, c)

    return sandwich(graph.linearize(values), side_solve_dims(values), CALIBRATION_KEY, rows(),
                    cell_m)


def sandwich(linear: gtsam.GaussianFactorGraph, dims: dict[int, int], key: int,
             rows: Iterable[tuple[CdtmPairFactor, np.ndarray, np.ndarray, np.ndarray,
                                  np.ndarray]],
             cell_m: float = CELL_M) -> np.ndarray:
    """The cluster-robust covariance of the variable ``key`` of the linear system
    ``linear`` (:func:`clustered_covariance`'s formula), its C-DTM features' rows given by
    ``rows``: per pair factor ``(factor, e, Ha, Hb, Hk)``, its whitened residuals (n, 2)
    and Jacobians w.r.t. ``X(a)``, ``X(b)`` (n, 2, 6) and ``key`` (n, 2, d).

    Args:
        dims: every variable of ``linear`` and its dimension, in the order of the dense
            Hessian.
    """
    ordering = gtsam.Ordering()
    offset: dict[int, int] = {}
    n = 0
    for k, dim in dims.items():
        ordering.push_back(k)
        offset[k] = n
        n += dim
    d = dims[key]
    H, _ = linear.hessian(ordering)
    c0 = offset[key]
    target = slice(c0, c0 + d)
    unit = np.zeros((n, d))
    unit[target] = np.eye(d)
    A = np.linalg.solve(H, unit).T  # (d, n)
    model = np.zeros((d, d))
    scores, ground = [], []
    for f, e, Ha, Hb, Hk in rows:
        a, b = offset[f.key_a], offset[f.key_b]
        # each feature's residual rows through A: (m, 2, d)
        B = Ha @ A[:, a:a + 6].T + Hb @ A[:, b:b + 6].T + Hk @ A[:, target].T
        model += np.einsum("mki,mkj->ij", B, B)
        scores.append(np.einsum("mki,mk->mi", B, e))
        ground.append(f.features.G_E[:, :2])
    P = A[:, target]
    if not scores:
        return P
    cell = np.floor(np.concatenate(ground) / cell_m).astype(np.int64)
    label = np.unique(cell, axis=0, return_inverse=True)[1].ravel()
    G = int(label.max()) + 1
    per_cell = np.zeros((G, d))
    np.add.at(per_cell, label, np.concatenate(scores))
    extra = per_cell.T @ per_cell * (G / max(G - 1, 1)) - model
    w, vectors = np.linalg.eigh(0.5 * (extra + extra.T))
    return P + (vectors * np.maximum(w, 0.0)) @ vectors.T


def side_solve_dims(values: gtsam.Values) -> dict[int, int]:
    """Every variable of the side solve and its dimension, in ``values``' order."""
    return {key: CALIBRATION_DIM if key == CALIBRATION_KEY
            else _DIM[chr(gtsam.Symbol(key).chr())] for key in values.keys()}
