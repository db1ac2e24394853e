"""The Python-driven Levenberg-Marquardt (``cdtm_graph/optimizer.py``) on small problems.

The optimum against a known truth and against GTSAM's own ``LevenbergMarquardtOptimizer``,
the damping rule (Nielsen: x1/3 on a perfect step, x2, x4, ... on rejected ones), the
iteration limit and converged flag, the Cholesky -> QR switch of ``LinearSolver``, and
GTSAM's indeterminant-system exception turned into a one-line :class:`SolverError`.
"""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import B, L, V, X

from cdtm_graph.errors import CdtmError, SolverError
from cdtm_graph.optimizer import LinearSolver, explain_indeterminant, levenberg_marquardt
from cdtm_graph.results import Solver

#: Two converged solutions of one small problem agree to this (tangent norm, rad and m).
SOLUTION_TOL = 1e-9
#: Relative tolerance of a damping factor read back from the damped graph (sqrt, square).
LAMBDA_RTOL = 1e-12


class RecordingSolver(LinearSolver):
    """A ``LinearSolver`` that records the damping lambda of every damped system it solves.

    ``levenberg_marquardt`` appends ``sqrt(lambda) I`` factors, one per variable, after the
    linearized graph: the last factor of the damped graph holds lambda.
    """

    def __init__(self) -> None:
        super().__init__()
        self.lambdas: list[float] = []

    def __call__(self, damped: gtsam.GaussianFactorGraph) -> gtsam.VectorValues:
        A, _ = damped.at(damped.size() - 1).jacobian()
        self.lambdas.append(float(A[0, 0]) ** 2)
        return super().__call__(damped)


# -- small nonlinear problems ----------------------------------------------------------


def _pose(rng: np.random.Generator, angle_rad: float, distance_m: float) -> gtsam.Pose3:
    axis = rng.normal(size=3)
    return gtsam.Pose3(gtsam.Rot3.Expmap(angle_rad * axis / np.linalg.norm(axis)),
                       rng.normal(size=3) * distance_m)


def _pose_chain(rng: np.random.Generator, loop_noise: float
                ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, list[gtsam.Pose3]]:
    """Five poses: a prior on X(0), between factors along the chain and a loop X(0)-X(4).

    With ``loop_noise = 0`` every measurement agrees with the truth, which is then the
    optimum (error 0); otherwise the loop disagrees and the optimum is a compromise.
    The initial values are the truth moved by ~0.3 rad and ~1 m per pose.
    """
    truth = [_pose(rng, 0.2, 0.5)]
    for _ in range(4):
        truth.append(truth[-1].compose(_pose(rng, 0.5, 10.0)))
    pose_noise = gtsam.noiseModel.Diagonal.Sigmas(np.r_[[0.02] * 3, [0.1] * 3])
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(X(0), truth[0], pose_noise))
    for k in range(4):
        graph.add(gtsam.BetweenFactorPose3(X(k), X(k + 1), truth[k].between(truth[k + 1]),
                                           pose_noise))
    loop = truth[0].between(truth[4]).compose(gtsam.Pose3.Expmap(loop_noise * rng.normal(size=6)))
    graph.add(gtsam.BetweenFactorPose3(X(0), X(4), loop, pose_noise))
    initial = gtsam.Values()
    for k, pose in enumerate(truth):
        initial.insert(X(k), pose.compose(gtsam.Pose3.Expmap(np.r_[0.3 * rng.normal(size=3),
                                                                   rng.normal(size=3)])))
    return graph, initial, truth


def _rosenbrock(start: tuple[float, float, float] = (-1.2, 1.0, 0.5)
                ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """Rosenbrock's residuals on V(0) = (a, b, c): r = (10 (b - a^2), 1 - a, c).

    Optimum (1, 1, 0) with zero error. From the default start (error 12.225) the
    Gauss-Newton step lands at (1, -3.84, 0), error 1171.28: LM must reject it.
    """
    def error(this: gtsam.CustomFactor, values: gtsam.Values,
              jacobians: list[np.ndarray] | None) -> np.ndarray:
        a, b, c = values.atVector(this.keys()[0])
        if jacobians is not None:
            jacobians[0] = np.array([[-20.0 * a, 10.0, 0.0], [-1.0, 0.0, 0.0],
                                     [0.0, 0.0, 1.0]])
        return np.array([10.0 * (b - a * a), 1.0 - a, c])

    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(3), gtsam.KeyVector([V(0)]),
                                 error))
    values = gtsam.Values()
    values.insert(V(0), np.array(start))
    return graph, values


def _pose_error(a: gtsam.Pose3, b: gtsam.Pose3) -> float:
    return float(np.linalg.norm(a.localCoordinates(b)))


# -- the optimum -----------------------------------------------------------------------


def test_recovers_the_truth_of_a_consistent_pose_chain(rng):
    graph, initial, truth = _pose_chain(rng, loop_noise=0.0)
    assert graph.error(initial) > 1e3  # a real nonlinear solve, not a start at the answer
    values, stats = levenberg_marquardt(graph, initial, max_iterations=100,
                                        relative_error_tol=1e-14)
    for k, pose in enumerate(truth):
        assert _pose_error(values.atPose3(X(k)), pose) < SOLUTION_TOL
    assert stats.converged and stats.final_error < 1e-18
    assert stats.initial_error == graph.error(initial)
    assert stats.final_error == graph.error(values)


def test_reaches_the_optimum_gtsam_levenberg_marquardt_reaches(rng):
    """An inconsistent loop: the optimum is a compromise, and both optimizers find it."""
    graph, initial, _ = _pose_chain(rng, loop_noise=0.05)
    values, stats = levenberg_marquardt(graph, initial, max_iterations=100,
                                        relative_error_tol=1e-14)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    params.setRelativeErrorTol(0.0)  # run GTSAM to its limit: the reference
    params.setAbsoluteErrorTol(0.0)
    reference = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
    assert stats.converged
    assert stats.final_error > 1.0  # the loop disagrees: a non-zero minimum
    assert stats.final_error == pytest.approx(graph.error(reference), rel=1e-12)
    for k in range(5):
        assert _pose_error(values.atPose3(X(k)), reference.atPose3(X(k))) < SOLUTION_TOL


def test_a_converged_solve_keeps_its_final_linearization_for_the_marginals(rng):
    """The solve that ends on a linearization at its answer (no step left) hands it on:
    the same linear system a fresh ``linearize`` at the answer gives, and nothing for any
    other values or after a solve stopped by its iteration limit."""
    graph, initial, _ = _pose_chain(rng, loop_noise=0.05)
    solver = LinearSolver()
    values, stats = levenberg_marquardt(graph, initial, max_iterations=100,
                                        relative_error_tol=1e-14, solver=solver)
    assert stats.converged
    kept = solver.linearized_at(values)
    assert kept is not None
    fresh = graph.linearize(values)
    for i in range(fresh.size()):
        A_kept, b_kept = kept.at(i).jacobian()
        A_fresh, b_fresh = fresh.at(i).jacobian()
        np.testing.assert_array_equal(A_kept, A_fresh)
        np.testing.assert_array_equal(b_kept, b_fresh)
    assert solver.linearized_at(gtsam.Values(values)) is None  # an equal copy: not known
    levenberg_marquardt(graph, initial, max_iterations=1, relative_error_tol=1e-14,
                        solver=solver)
    assert solver.linearized_at(values) is None  # a later solve forgets the earlier one


# -- damping, iterations, convergence --------------------------------------------------


def test_a_solve_given_its_start_error_and_linearization_is_the_solve_that_makes_them(rng):
    """``error_at_start`` and ``linear_at_start`` (the calibration check's free solve
    continuing its pinned one) save their computation and change nothing: the same values
    and statistics, bit for bit, as a solve that makes them itself. Mutation tried: the
    linearization used at every iteration, not only the first (the solve then stops on
    the start's step: the values differ)."""
    graph, initial, _ = _pose_chain(rng, loop_noise=0.05)
    values, stats = levenberg_marquardt(graph, initial, max_iterations=100,
                                        relative_error_tol=1e-14)
    given, given_stats = levenberg_marquardt(
        graph, initial, max_iterations=100, relative_error_tol=1e-14,
        error_at_start=graph.error(initial), linear_at_start=graph.linearize(initial))
    assert given_stats.iterations == stats.iterations > 2
    assert given_stats.final_error == stats.final_error
    for k in range(5):
        np.testing.assert_array_equal(given.atPose3(X(k)).matrix(), values.atPose3(X(k)).matrix())


def test_a_rejected_step_doubles_the_growth_of_lambda():
    """From (-1.2, 1) the Gauss-Newton step raises the error 100-fold: the first trial
    at the initial lambda is rejected and lambda grows by 2, then 4, ... until a step
    lowers the error."""
    graph, values = _rosenbrock()
    solver = RecordingSolver()
    lambda_initial = 1e-5
    levenberg_marquardt(graph, values, max_iterations=1, relative_error_tol=1e-12,
                        lambda_initial=lambda_initial, solver=solver)
    lams = solver.lambdas
    assert lams[0] == pytest.approx(lambda_initial, rel=LAMBDA_RTOL)
    assert len(lams) >= 2, "the Gauss-Newton step raises the error: it must be rejected"
    for i in range(1, len(lams)):  # one iteration: every trial but the last was rejected
        assert lams[i] / lams[i - 1] == pytest.approx(2.0**i, rel=LAMBDA_RTOL)


def test_a_perfect_step_divides_lambda_by_three():
    """On a linear problem the model's predicted decrease is the actual one (rho = 1):
    Nielsen's factor max(1/3, 1 - (2 rho - 1)^3) is 1/3."""
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorVector(V(0), np.array([3.0, -4.0, 5.0]),
                                      gtsam.noiseModel.Isotropic.Sigma(3, 0.1)))
    values = gtsam.Values()
    values.insert(V(0), np.zeros(3))
    solver = RecordingSolver()
    solution, stats = levenberg_marquardt(graph, values, max_iterations=2,
                                          relative_error_tol=1e-12, lambda_initial=1e-3,
                                          solver=solver)
    assert solver.lambdas[:2] == pytest.approx([1e-3, 1e-3 / 3], rel=LAMBDA_RTOL)
    np.testing.assert_allclose(solution.atVector(V(0)), [3.0, -4.0, 5.0], atol=1e-9)


@pytest.mark.parametrize("max_iterations", [1, 2, 3])
def test_max_iterations_is_respected_and_not_converged(max_iterations):
    graph, values = _rosenbrock()
    start = graph.error(values)
    result, stats = levenberg_marquardt(graph, values, max_iterations=max_iterations,
                                        relative_error_tol=1e-12)
    assert stats.iterations == max_iterations
    assert not stats.converged
    assert stats.final_error == graph.error(result) < start  # accepted steps only descend


def test_converges_to_the_rosenbrock_minimum():
    graph, values = _rosenbrock()
    result, stats = levenberg_marquardt(graph, values, max_iterations=200,
                                        relative_error_tol=1e-12)
    assert stats.converged and stats.iterations < 200
    np.testing.assert_allclose(result.atVector(V(0)), [1.0, 1.0, 0.0], atol=SOLUTION_TOL)
    assert stats.solver is Solver.LEVENBERG_MARQUARDT
    assert stats.initial_error == pytest.approx(12.225)


def test_at_the_optimum_no_step_is_taken_and_the_solve_converges():
    graph, values = _rosenbrock((1.0, 1.0, 0.0))
    result, stats = levenberg_marquardt(graph, values, max_iterations=50,
                                        relative_error_tol=1e-12)
    assert stats.converged and stats.iterations == 1
    assert stats.final_error == 0.0
    np.testing.assert_array_equal(result.atVector(V(0)), [1.0, 1.0, 0.0])


# -- Cholesky -> QR ----------------------------------------------------------------------

#: 1 - the cosine between the two columns of the near-singular system below: GTSAM's
#: Cholesky (which squares the condition number, ~4e10 here) calls it indeterminant,
#: QR (condition ~2e5) solves it to ~1e-11.
NEAR_PARALLEL = 1e-5


def _near_singular_system(scale: float = 1.0) -> tuple[gtsam.GaussianFactorGraph, np.ndarray]:
    A = scale * np.array([[1.0, 1.0], [1.0, 1.0 + NEAR_PARALLEL]])
    x_true = np.array([1.0, 2.0])
    graph = gtsam.GaussianFactorGraph()
    graph.add(X(0), A[:, :1].copy(), X(1), A[:, 1:].copy(), A @ x_true,
              gtsam.noiseModel.Unit.Create(2))
    return graph, x_true


def test_cholesky_fails_where_qr_solves():
    """The premise of the switch, on GTSAM itself."""
    graph, x_true = _near_singular_system()
    with pytest.raises(RuntimeError, match="(?i)indetermina"):
        graph.optimize()
    solution = graph.optimize(gtsam.EliminateQR)
    np.testing.assert_allclose([solution.at(X(0))[0], solution.at(X(1))[0]], x_true, atol=1e-9)


def test_linear_solver_tries_cholesky_again_after_one_failure_and_not_after_two():
    solver = LinearSolver()
    well_posed = gtsam.GaussianFactorGraph()
    well_posed.add(X(0), np.eye(2), np.array([1.0, 2.0]), gtsam.noiseModel.Unit.Create(2))
    np.testing.assert_allclose(solver(well_posed).at(X(0)), [1.0, 2.0])
    assert not solver.qr  # Cholesky while it works

    graph, x_true = _near_singular_system()
    solution = solver(graph)  # QR solves what Cholesky cannot
    np.testing.assert_allclose([solution.at(X(0))[0], solution.at(X(1))[0]], x_true, atol=1e-9)
    assert not solver.qr  # one failure: a system (a batch's first), not the problem
    solver(well_posed)
    solver(graph)
    assert not solver.qr  # failures apart do not add up
    solver(graph)
    assert solver.qr  # two in a row: QR for good, no Cholesky attempt per iteration
    np.testing.assert_allclose(solver(well_posed).at(X(0)), [1.0, 2.0])
    assert solver.qr


def test_levenberg_marquardt_solves_through_qr_when_cholesky_fails():
    """A least-squares problem on V(0) whose information (1e12, nearly rank 2) swamps the
    damping: Cholesky fails on the damped system, QR finishes the solve."""
    A = np.array([[1.0, 1.0, 0.0], [1.0, 1.0 + NEAR_PARALLEL, 0.0], [0.0, 0.0, 1.0]])
    v_true = np.array([1.0, 2.0, 3.0])
    b = A @ v_true

    def error(this: gtsam.CustomFactor, values: gtsam.Values,
              jacobians: list[np.ndarray] | None) -> np.ndarray:
        if jacobians is not None:
            jacobians[0] = A
        return A @ values.atVector(this.keys()[0]) - b

    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(3, 1e-6),
                                 gtsam.KeyVector([V(0)]), error))
    values = gtsam.Values()
    values.insert(V(0), np.zeros(3))
    solver = LinearSolver()
    result, stats = levenberg_marquardt(graph, values, max_iterations=50,
                                        relative_error_tol=1e-12, solver=solver)
    assert solver.qr
    assert stats.converged
    np.testing.assert_allclose(result.atVector(V(0)), v_true, atol=SOLUTION_TOL)


# -- indeterminant systems ---------------------------------------------------------------


def _gtsam_indeterminant(key: int, dim: int) -> RuntimeError:
    """GTSAM's own exception for ``key``: one rank-deficient Jacobian row on it."""
    graph = gtsam.GaussianFactorGraph()
    graph.add(key, np.eye(1, dim), np.zeros(1), gtsam.noiseModel.Unit.Create(1))
    with pytest.raises(RuntimeError) as caught:
        graph.optimize(gtsam.EliminateQR)
    return caught.value


@pytest.mark.parametrize(("key", "dim", "expected"), [
    (X(3), 6, "indeterminant system near X(3): the pose is unobservable: no C-DTM features "
              "near this frame, flat terrain under it, or an IMU gap"),
    (V(12), 3, "indeterminant system near V(12): the velocity is unobservable: check the IMU "
               "samples around this frame"),
    (B(0), 6, "indeterminant system near B(0): the IMU bias is unobservable: check the IMU "
              "samples and the bias priors"),
    (L(7), 3, "indeterminant system near L(7): check the inputs around this variable"),
], ids=["pose", "velocity", "bias", "other"])
def test_explain_indeterminant_names_the_variable_and_cause(key, dim, expected):
    exc = _gtsam_indeterminant(key, dim)
    assert "\n" in str(exc)  # GTSAM's text spans lines and names the key as "Symbol: x3"
    error = explain_indeterminant(exc)
    assert isinstance(error, SolverError) and isinstance(error, CdtmError)
    assert str(error) == expected


def test_explain_indeterminant_keeps_an_unknown_message_on_one_line():
    error = explain_indeterminant(RuntimeError("something\n  else failed"))
    assert str(error) == "GTSAM could not solve the system: something else failed"


def _unobservable_rotation_graph() -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """A chain X(0)-X(1)-X(2) fixed by a prior, and X(3) held by a position fix alone:
    nothing constrains X(3)'s rotation."""
    noise = gtsam.noiseModel.Isotropic.Sigma(6, 0.1)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), noise))
    step = gtsam.Pose3(gtsam.Rot3.Yaw(0.1), gtsam.Point3(10.0, 0.0, 0.0))
    for k in range(2):
        graph.add(gtsam.BetweenFactorPose3(X(k), X(k + 1), step, noise))
    graph.add(gtsam.GPSFactor(X(3), gtsam.Point3(30.0, 1.0, 0.0),
                              gtsam.noiseModel.Isotropic.Sigma(3, 1.0)))
    values = gtsam.Values()
    for k in range(4):
        values.insert(X(k), gtsam.Pose3(gtsam.Rot3.Roll(0.2), gtsam.Point3(10.0 * k, 0.0, 1.0)))
    return graph, values


def test_unobservable_pose_raises_one_line_solver_error_from_gauss_newton():
    """Undamped (lambda 0: Gauss-Newton), neither Cholesky nor QR can solve for X(3)."""
    graph, values = _unobservable_rotation_graph()
    with pytest.raises(SolverError) as err:
        levenberg_marquardt(graph, values, max_iterations=10, relative_error_tol=1e-12,
                            lambda_initial=0.0)
    message = str(err.value)
    assert message.startswith("indeterminant system near X(3): the pose is unobservable")
    assert "\n" not in message


def test_damping_keeps_an_unobservable_direction_where_it_was():
    """With the default damping the solve succeeds and leaves X(3)'s unobservable rotation
    at its initial value: the optimizer cannot report it, the marginals must (the
    smoother's covariance step raises the SolverError)."""
    graph, values = _unobservable_rotation_graph()
    result, stats = levenberg_marquardt(graph, values, max_iterations=50,
                                        relative_error_tol=1e-12)
    assert stats.converged
    np.testing.assert_allclose(result.atPose3(X(3)).translation(), [30.0, 1.0, 0.0], atol=1e-6)
    rotation_change = gtsam.Rot3.Logmap(values.atPose3(X(3)).rotation().between(
        result.atPose3(X(3)).rotation()))
    np.testing.assert_allclose(rotation_change, 0.0, atol=1e-12)
    with pytest.raises(RuntimeError, match="(?i)indetermina"):
        gtsam.Marginals(graph, result).marginalCovariance(X(3))
