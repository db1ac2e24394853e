"""Levenberg-Marquardt driven from Python over ``graph.linearize`` (no per-call copies).

GTSAM's optimizers hand every ``CustomFactor`` call a fresh copy of all values, which
makes an iteration quadratic in the flight length (DESIGN.md, "Performance notes");
``graph.linearize(values)`` called from here does not copy.
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable, Sequence
from typing import TypeVar

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

from cdtm_graph.errors import SolverError
from cdtm_graph.results import Solver, SolverStats, StateCovariances
from factors.calibration import CALIBRATION_DIM

log = logging.getLogger(__name__)

_T = TypeVar("_T")


_SYMBOL = re.compile(r"Symbol:\s*([a-zA-Z])(\d+)")


def explain_indeterminant(exc: RuntimeError) -> SolverError:
    """Turn GTSAM's 'indeterminant system near variable ...' into one clear line."""
    text = " ".join(str(exc).split())
    match = _SYMBOL.search(text)
    if not match:
        return SolverError(f"GTSAM could not solve the system: {text}")
    char, index = match.group(1).upper(), int(match.group(2))
    cause = {
        "X": "the pose is unobservable: no C-DTM features near this frame, flat terrain "
             "under it, or an IMU gap",
        "V": "the velocity is unobservable: check the IMU samples around this frame",
        "B": "the IMU bias is unobservable: check the IMU samples and the bias priors",
    }.get(char, "check the inputs around this variable")
    return SolverError(f"indeterminant system near {char}({index}): {cause}")


def _damping_factors(keys: list[tuple[int, int]], lam: float) -> gtsam.GaussianFactorGraph:
    """``lambda I`` on every variable, as unit-noise Jacobian factors."""
    damping = gtsam.GaussianFactorGraph()
    s = np.sqrt(lam)
    # one matrix, right side and noise model per dimension (not per key: at 1000 frames
    # making them was a tenth of a solve)
    parts = {dim: (s * np.eye(dim), np.zeros(dim), gtsam.noiseModel.Unit.Create(dim))
             for dim in {dim for _, dim in keys}}
    for key, dim in keys:
        damping.add(key, *parts[dim])
    return damping


class LinearSolver:
    """Cholesky (fast) where it works; QR where it fails, and from the second failure in a
    row on for good.

    The information of an IMU + C-DTM system spans ~1e-4 (pose prior) to ~1e10 (bias
    random walk); Cholesky squares that condition number and may lose small pivots. It
    fails on a batch's first system more often than not (a nav.csv guess: the robust
    kernel gives the features far off their planes almost no weight, and the damping
    alone holds their poses) and then works on every later one: one failure is a
    system, two in a row are the problem.
    """

    #: Cholesky failures in a row after which QR is used for good.
    FAILURES_FOR_GOOD = 2

    def __init__(self) -> None:
        self.qr = False  # QR for good
        self._failures = 0  # Cholesky failures in a row
        # the last solve's linearization, when it is at the values that solve returned (a
        # converged solve's final check): the marginals need just that
        self._linearized: tuple[gtsam.Values, gtsam.GaussianFactorGraph | None] | None = None

    def __call__(self, damped: gtsam.GaussianFactorGraph) -> gtsam.VectorValues:
        if not self.qr:
            try:
                solution = damped.optimize()
                self._failures = 0
                return solution
            except RuntimeError:
                self._failures += 1
                self.qr = self._failures >= self.FAILURES_FOR_GOOD
        return damped.optimize(gtsam.EliminateQR)

    def remember(self, values: gtsam.Values | None,
                 linear: gtsam.GaussianFactorGraph | None = None) -> None:
        """Keep a solve's final linearization at the values it returns (None: forget)."""
        self._linearized = None if values is None else (values, linear)

    def linearized_at(self, values: gtsam.Values) -> gtsam.GaussianFactorGraph | None:
        """The last solve's graph linearized at ``values``, if these are (the same
        object as) the values it returned and it ended on that linearization; else None."""
        if self._linearized is not None and self._linearized[0] is values:
            return self._linearized[1]
        return None


#: A rejected step predicted to gain less than this fraction of the error ends the solve.
_SMALL_STEP_RELATIVE = 1e-4


def levenberg_marquardt(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, max_iterations: int,
    relative_error_tol: float, lambda_initial: float = 1e-5,
    solver: LinearSolver | None = None, error_at_start: float | None = None,
    linear_at_start: gtsam.GaussianFactorGraph | None = None,
) -> tuple[gtsam.Values, SolverStats]:
    """Levenberg-Marquardt driven from Python on ``graph.linearize`` (no per-call copies).

    Damping ``lambda I`` follows Nielsen's rule: on a step with gain ratio rho the
    damping shrinks by ``max(1/3, 1 - (2 rho - 1)^3)``; on a rejected step it grows by
    a factor that doubles with each rejection. This rejects far fewer steps than
    multiplying by ten both ways.

    ``error_at_start`` and ``linear_at_start``: ``graph``'s error at ``values`` and its
    linearization there, when the caller has them (a side solve that continues another
    on the same factors): not computed again.

    Raises:
        SolverError: the linear system is indeterminant (names the variable).
    """
    start = time.perf_counter()
    keys = [(k, _dim_of(k)) for k in values.keys()]
    error = graph.error(values) if error_at_start is None else error_at_start
    initial_error = error
    lam, nu = lambda_initial, 2.0
    solve = solver or LinearSolver()  # pass one along to keep its Cholesky/QR verdict
    solve.remember(None)
    iterations = 0
    converged = False
    try:
        while iterations < max_iterations:
            iterations += 1
            if iterations == 1 and linear_at_start is not None:
                linear = linear_at_start
            else:
                linear = graph.linearize(values)
            linear_error_at_zero = None
            accepted = False
            while lam < 1e12:
                damped = gtsam.GaussianFactorGraph()
                damped.push_back(linear)
                damped.push_back(_damping_factors(keys, lam))
                delta = solve(damped)
                # predicted decrease of the linear model (its value at zero, not the robust
                # loss: IRLS rows are sqrt(w)-scaled, so the two differ under a kernel)
                if linear_error_at_zero is None:
                    linear_error_at_zero = linear.error(gtsam.VectorValues.Zero(delta))
                predicted = linear_error_at_zero - linear.error(delta)
                if predicted <= relative_error_tol * error:
                    break  # at the optimum: no step can gain more than the tolerance
                candidate = values.retract(delta)
                new_error = graph.error(candidate)
                rho = (error - new_error) / predicted if predicted > 0 else -1.0
                if new_error < error and rho > 0:
                    accepted = True
                    lam *= max(1 / 3, 1 - (2 * rho - 1) ** 3)
                    nu = 2.0
                    break
                if predicted <= _SMALL_STEP_RELATIVE * error:
                    break  # a rejected step this small: the kinks of re-intersected planes
                    # (or round-off) decide, not curvature; damping more will not gain
                lam *= nu
                nu *= 2
            if not accepted:
                converged = True  # no descent left at any damping
                solve.remember(values, linear)
                break
            decrease = (error - new_error) / max(error, 1e-300)
            values, error = candidate, new_error
            log.debug("LM iteration %d: error %.6g (lambda %.1e)", iterations, error, lam)
            if decrease < relative_error_tol:
                converged = True
                break
    except RuntimeError as exc:
        raise explain_indeterminant(exc) from None
    return values, SolverStats(Solver.LEVENBERG_MARQUARDT, iterations, initial_error, error,
                               converged, time.perf_counter() - start)


#: Tangent dimension of each key type (DESIGN.md keys).
_DIMENSIONS = {"x": 6, "v": 3, "b": 6, "c": CALIBRATION_DIM}


def _dim_of(key: int) -> int:
    return _DIMENSIONS[chr(gtsam.Symbol(key).chr())]


def marginals(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
              K: int, qr_only: bool = False,
              linear: gtsam.GaussianFactorGraph | None = None) -> StateCovariances:
    """Per-frame marginals from a Bayes tree of the graph linearized at ``values``
    (``linear``, if the caller has it already).

    Cholesky first (as ``gtsam.Marginals``); where it declares the system indeterminant,
    which happens on these wide-range systems (information from ~1e-4 for the pose prior
    to ~1e10 for the bias random walk), QR, which does not square the condition number.
    """
    keys = [X(k) for k in range(K)] + [V(k) for k in range(K)] + [B(k) for k in range(K)]
    cov = key_marginals(graph, values, keys, qr_only, linear)
    return StateCovariances(np.stack(cov[:K]), np.stack(cov[K:2 * K]), np.stack(cov[2 * K:]))


def key_marginals(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                  keys: list[int], qr_only: bool = False,
                  linear: gtsam.GaussianFactorGraph | None = None) -> list[np.ndarray]:
    """The marginal covariance of each key (as :func:`marginals`)."""
    if linear is None:
        linear = graph.linearize(values)
    return _on_bayes_tree(linear, lambda tree, qr: [_marginal(tree, qr, k) for k in keys],
                          qr_only)


def step_and_marginals(linear: gtsam.GaussianFactorGraph, keys: Sequence[int],
                       qr_form: gtsam.GaussianFactorGraph | None = None
                       ) -> tuple[gtsam.VectorValues, list[np.ndarray]]:
    """The solution of ``linear`` (its ``optimize()``) and the marginal covariance of each
    key, from one elimination (Cholesky; QR where it fails, of ``qr_form`` if given: the
    same system in Jacobian factors, as QR drops a Hessian factor's linear term)."""
    return _on_bayes_tree(linear, lambda tree, qr: (tree.optimize(),
                                                    [_marginal(tree, qr, k) for k in keys]),
                          qr_form=qr_form)


def _on_bayes_tree(linear: gtsam.GaussianFactorGraph,
                   use: Callable[[gtsam.GaussianBayesTree, bool], _T], qr_only: bool = False,
                   qr_form: gtsam.GaussianFactorGraph | None = None) -> _T:
    """``use(tree, qr)`` of ``linear``'s Bayes tree: Cholesky's, QR's (of ``qr_form`` if
    given) where Cholesky declares the system indeterminant (or ``qr_only``)."""
    for qr in (True,) if qr_only else (False, True):
        try:
            tree = ((linear if qr_form is None else qr_form).eliminateMultifrontal(
                function=gtsam.EliminateQR) if qr else linear.eliminateMultifrontal())
            return use(tree, qr)
        except RuntimeError as exc:
            error = exc
    raise explain_indeterminant(error) from None


def _marginal(tree: gtsam.GaussianBayesTree, qr: bool, key: int) -> np.ndarray:
    marginal = tree.marginalFactor(key, gtsam.EliminateQR) if qr else tree.marginalFactor(key)
    # information() includes the conditional's noise model (QR leaves sigmas)
    return np.linalg.inv(marginal.information())
