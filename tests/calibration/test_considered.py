"""The principal point as a considered parameter (``cdtm_graph.calibration.considered``):
its sensitivity against re-solves with the principal point moved, the covariance it adds,
and flights whose principal point is off by what flight.yaml declares."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import X

from cdtm_graph.calibration import check
from cdtm_graph.calibration import considered as considered_module
from cdtm_graph.calibration.check import pinned_solve
from cdtm_graph.calibration.considered import considered, principal_point_sensitivity
from cdtm_graph.calibration.extra_parts import WITH_PART_KEY, with_part
from cdtm_graph.calibration.online import CALIBRATION_KEY
from cdtm_graph.calibration.principal_point import principal_point_part
from cdtm_graph.flightlog import FlightLog
from cdtm_graph.graph import GraphSettings
from cdtm_graph.graph.builders import DEFAULT_CALIBRATION_SIGMAS
from cdtm_graph.run import smooth_and_evaluate
from cdtm_graph.sim.faults import with_calibration_error
from cdtm_graph.sim.simulate import simulate_flight
from cdtm_graph.smoother import IncrementalSmoother, SmootherMode, SmootherSettings, smooth
from cdtm_graph.studies.robustness import BASE
from cdtm_graph.verdict.rules import assess


def declared(flight: FlightLog, sigma_px: float | None) -> FlightLog:
    """``flight`` whose flight.yaml declares the principal point's 1-sigma ``sigma_px``."""
    camera = dataclasses.replace(flight.config.camera, principal_point_sigma_px=sigma_px)
    return dataclasses.replace(flight, config=dataclasses.replace(flight.config,
                                                                  camera=camera))


@pytest.fixture(scope="module")
def short_flight():
    """The robustness study's flight, 30 frames (seed 1), and its batch run."""
    flight, dtm = simulate_flight(dataclasses.replace(BASE, frames=30, seed=1))
    return flight, dtm, smooth(flight, dtm)


def test_the_sensitivity_is_the_regression_in_the_joint_marginal(short_flight):
    """``S = d x / d (cx, cy)`` (the side solve's graph, the principal point's columns
    added, solved with it pinned at 1 px less pinned at 0) against the other way to get
    it: in the joint Gaussian of each pose and the principal point (any prior on it), the
    regression ``Sigma_xc Sigma_cc^-1``, which is ``-H_xx^-1 H_xc`` exactly. Every pose's
    response (tangent: rotation, body-axis translation) within 1e-6 of the largest.
    Measured 2026-11-28: 3.1-3.6 m per px. Mutations: the pin at 0 not taken off (the
    side solve's own residual step left in), the pin's mean on the five instead of the
    principal point, and the sign of ``S`` flipped: each fails.

    (Central differences of the nonlinear pinned solve itself cannot be this test: its
    Levenberg-Marquardt leaves a 0.05 px shift where it starts, a step that small losing to
    the re-intersected planes' kinks, and at 0.25 px it differs 8-13% from ``S`` with the
    kernel off: the pair factors' planes and weights. The product's own response is the
    slow test below.)"""
    flight, dtm, result = short_flight
    solve = pinned_solve(flight, dtm, GraphSettings(), result, DEFAULT_CALIBRATION_SIGMAS)
    camera = flight.config.camera.camera
    S = principal_point_sensitivity(solve, camera)
    assert S is not None and S.shape == (30, 6, 2)
    part = principal_point_part(camera)
    augmented, _ = with_part(solve.linear, solve.values, solve.factors, part)
    m = solve.values.atVector(CALIBRATION_KEY).size
    prior = np.zeros((2, m + 2))
    prior[:, m:] = np.eye(2) / 3.0  # (any prior)
    augmented.add(WITH_PART_KEY, prior, np.zeros(2), gtsam.noiseModel.Unit.Create(2))
    tree = augmented.eliminateMultifrontal(function=gtsam.EliminateQR)  # (as the side solve)
    c = slice(6 + m, None)
    for j in range(30):
        ordering = gtsam.Ordering()
        ordering.push_back(X(j))
        ordering.push_back(WITH_PART_KEY)
        information, _ = tree.joint(X(j), WITH_PART_KEY, gtsam.EliminateQR).hessian(ordering)
        joint = np.linalg.inv(information)
        regression = np.linalg.solve(joint[c, c], joint[:6, c].T).T
        scale = np.abs(regression[3:]).max()
        assert 1.0 < scale < 10.0  # metres per px at 1800 m
        np.testing.assert_allclose(S[j], regression, atol=1e-6 * scale)


def test_the_added_covariance_is_the_declared_variance_through_the_sensitivity(short_flight):
    """``P + sigma^2 S S^T`` frame by frame, the rest of the covariances untouched, nothing
    added for 0 px. The frames a thinned solve leaves out take ``S`` interpolated in time,
    entry by entry: exactly, for a response linear in time given at 4 of 30 frames; and on
    the same flight thinned to 10 of 30 frames, the added position covariance within 22%
    of the full solve's, frame by frame (relative Frobenius norm; measured 2026-11-28:
    17%, as much at the solved frames as between them: the thinned graph's own ``S``).
    Mutations: sigma not squared (2 px declared) fails the first; every frame given the
    first solved frame's response (31% on the flight) or the next solved frame's (28%)
    fails both interpolation checks."""
    flight, dtm, result = short_flight
    camera = flight.config.camera.camera
    solve = pinned_solve(flight, dtm, GraphSettings(), result, DEFAULT_CALIBRATION_SIGMAS)
    S = principal_point_sensitivity(solve, camera)
    covariances, added = considered(result.covariances, flight.frames.t_ns, solve, camera, 2.0)
    assert added is not None and added.frames_solved == 30
    np.testing.assert_allclose(covariances.pose - result.covariances.pose,
                               4.0 * S @ np.swapaxes(S, 1, 2), atol=1e-12)
    assert covariances.velocity is result.covariances.velocity
    assert covariances.bias is result.covariances.bias
    none, nothing = considered(result.covariances, flight.frames.t_ns, solve, camera, 0.0)
    assert none is result.covariances and nothing is None

    base = np.arange(12.0).reshape(6, 2) - 5.0
    kept = np.array([0, 7, 19, 29])
    with pytest.MonkeyPatch.context() as patch:  # (a response linear in time, 4 frames solved)
        patch.setattr(considered_module, "principal_point_sensitivity",
                      lambda pinned, camera: (kept + 1.0)[:, None, None] * base)
        _, linear = considered(result.covariances, flight.frames.t_ns,
                               dataclasses.replace(solve, kept=kept), camera, 1.0)
    assert linear is not None
    expected = (np.arange(30) + 1.0)[:, None, None] * base  # (1 fps: time is the frame)
    np.testing.assert_allclose(linear.pose_cov_added, expected @ np.swapaxes(expected, 1, 2),
                               rtol=1e-9)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(check, "MAX_FRAMES", 10)
        thin = pinned_solve(flight, dtm, GraphSettings(), result, DEFAULT_CALIBRATION_SIGMAS)
    assert thin.kept.size <= 10
    _, thinned = considered(result.covariances, flight.frames.t_ns, thin, camera, 2.0)
    assert thinned is not None and thinned.frames_solved == thin.kept.size
    a, b = thinned.pose_cov_added[:, 3:, 3:], added.pose_cov_added[:, 3:, 3:]
    assert np.max(np.linalg.norm(a - b, axis=(1, 2)) / np.linalg.norm(b, axis=(1, 2))) < 0.22


@pytest.mark.parametrize("graph", [GraphSettings(calibration=None),
                                   GraphSettings(calibration_online=True)],
                         ids=["held unchecked", "online"])
def test_a_run_without_the_calibration_check_considers_it_too(short_flight, graph):
    """``--calibration held`` makes no side solve, and ``online`` none that pins the
    calibration: a declared principal point is still considered, from a first solve of
    its own, the same as the checked run's to the frame. Mutation: considered only where
    the check made its first solve (the declared key silently ignored): both fail."""
    flight, dtm, _ = short_flight
    checked = smooth(declared(flight, 0.5), dtm).considered_principal_point
    result = smooth(declared(flight, 0.5), dtm, SmootherSettings(graph=graph))
    assert result.calibration_check is None
    added = result.considered_principal_point
    assert checked is not None and added is not None and added.sigma_px == 0.5
    np.testing.assert_allclose(added.position_sigma_m, checked.position_sigma_m, rtol=0.05)


def test_the_initial_position_test_takes_the_declared_share_as_the_data_s(short_flight):
    """flight.yaml's position prior against the first frame (the verdict's
    ``initial_position``): the data's fix carries the principal point's share and the prior
    does not, as with the map's offset. So the share of the frame the data tell is the
    same declared or not (the test's dof), and the data's fix is allowed its larger spread
    (the statistic no larger). Mutation: the share counted in the frame's covariance but
    not beside the map's offset: the frame reads as held by the prior in one direction
    more (dof 2 of 3; measured 2026-11-28), and that direction goes untested."""
    flight, dtm, _ = short_flight
    truth = flight.groundtruth.interpolate(flight.frames.t_ns[:1]).position_m[0]
    init = dataclasses.replace(flight.config.initial_state, position_m=truth + [1.5, -1.0, 0.5],
                               sigma_position_m=2.0)
    tight = dataclasses.replace(flight, config=dataclasses.replace(flight.config,
                                                                   initial_state=init))
    result = smooth(tight, dtm)
    solve = pinned_solve(tight, dtm, GraphSettings(), result, DEFAULT_CALIBRATION_SIGMAS)
    covariances, added = considered(result.covariances, tight.frames.t_ns, solve,
                                    tight.config.camera.camera, 1.0)
    with_share = dataclasses.replace(result, covariances=covariances,
                                     considered_principal_point=added)
    plain, declared_ = result.initial_position_conflict(), with_share.initial_position_conflict()
    assert plain is not None and declared_ is not None
    assert declared_.dof == plain.dof
    assert declared_.nis <= plain.nis * (1 + 1e-9), (declared_.nis, plain.nis)


def test_the_verdict_notes_the_declared_share(short_flight):
    """``principal_point_considered``: a note (the status unchanged) saying what the
    declared principal point adds to the position 1-sigma and its share of the position
    variance; none where nothing is declared. Measured 2026-11-28 (30 frames, seed 1, 1
    px): 3.49 m (up to 3.83 m), 68% of the variance. Mutation: the note left out: fails."""
    flight, dtm, result = short_flight
    solve = pinned_solve(flight, dtm, GraphSettings(), result, DEFAULT_CALIBRATION_SIGMAS)
    covariances, added = considered(result.covariances, flight.frames.t_ns, solve,
                                    flight.config.camera.camera, 1.0)
    with_share = dataclasses.replace(result, covariances=covariances,
                                     considered_principal_point=added)
    plain, noted = assess(result), assess(with_share)
    assert noted.status is plain.status
    assert not any(n.startswith("principal_point_considered") for n in plain.notes)
    (note,) = [n for n in noted.notes if n.startswith("principal_point_considered: ")]
    assert "known to 1 px, adds 3." in note and "of the position variance" in note, note


def test_each_live_update_carries_the_geometric_share(short_flight):
    """The incremental smoother's per-frame covariance (what a live system reads) holds a
    declared principal point's share before any side solve, in its geometric form: within
    13% of the solved ``S``'s position sigma frame by frame (measured 2026-11-28, its
    misfit's spread in: -8.1% to +3.2% here; -13% to +16% on the 90-frame flight, seeds
    1-2), the estimate unchanged. Mutations: the live share left out; ``range /
    f`` taken without the range (1 m): both fail."""
    flight, dtm, result = short_flight
    solved = considered(result.covariances, flight.frames.t_ns,
                        pinned_solve(flight, dtm, GraphSettings(), result,
                                     DEFAULT_CALIBRATION_SIGMAS),
                        flight.config.camera.camera, 1.0)[1]
    assert solved is not None
    updates = {}
    for name, sigma in (("plain", None), ("declared", 1.0)):
        log = declared(flight, sigma)
        smoother = IncrementalSmoother(log.config, dtm, SmootherSettings(
            mode=SmootherMode.INCREMENTAL, lag_s=10.0), imu=log.imu)
        tracks = log.tracks
        updates[name] = [smoother.add_frame(int(t), tracks.track_id[tracks.frame == k],
                                            tracks.uv_px[tracks.frame == k])
                         for k, t in enumerate(log.frames.t_ns)]
    for k, (plain, live) in enumerate(zip(updates["plain"], updates["declared"])):
        np.testing.assert_array_equal(live.world_T_body, plain.world_T_body)
        share = (live.pose_covariance - plain.pose_covariance)[3:, 3:]
        sigma = np.sqrt(np.linalg.eigvalsh(share)[-1])
        assert abs(sigma / solved.position_sigma_m[k] - 1) < 0.13, (k, sigma)


#: Measured 2026-11-28 (the 90-frame flight, seed 1, cx and cy 1 px off): per mode, the
#: median over frames of ``|move - S d| / |S d|`` (the run's estimate moved by the shift,
#: against the sensitivity's prediction) and the position ANEES without and with the shift
#: declared at 1 px.
MEASURED = {SmootherMode.BATCH: (0.039, 13.74, 2.73),
            SmootherMode.INCREMENTAL: (0.074, 13.80, 2.83),
            "fixed_lag": (0.103, 10.14, 2.66)}


@pytest.mark.slow
@pytest.mark.parametrize("mode", list(MEASURED), ids=lambda m: getattr(m, "value", m))
def test_a_principal_point_off_by_its_declared_sigma_is_inside_the_covariance(mode):
    """cx, cy 1 px off (a 1-based convention). The run's estimate moves by what the
    sensitivity predicts, ``S d``: the median frame within 1.3x the measured misfit
    (:data:`MEASURED`) and the moves' median length within 10% of the predicted (a
    sigma 1.5x off would read 0.67 or 1.5). Declaring 1 px puts the position ANEES near
    chi-square(3)'s mean, where the same run declaring nothing is far beyond (bounds:
    0.75x and 1.3x the measured); the estimate itself is unchanged, and report.json states
    what was added (a median position sigma of 3.39 m, measured). Mutations: ``S``
    scaled by 1.5 fails the move; the term left out (``considered`` returning the
    covariances as they are) fails the ANEES: every mode."""
    misfit, anees_plain, anees_covered = MEASURED[mode]
    flight, dtm = simulate_flight(dataclasses.replace(BASE, seed=1))
    off = with_calibration_error(flight, principal_point_px=(1.0, 1.0))
    settings = (SmootherSettings(mode=SmootherMode.INCREMENTAL, lag_s=10.0)
                if mode == "fixed_lag" else SmootherSettings(mode=mode))
    clean = smooth(flight, dtm, settings)
    plain = smooth_and_evaluate(off, dtm, settings)
    covered = smooth_and_evaluate(declared(off, 1.0), dtm, settings)

    solve = pinned_solve(off, dtm, GraphSettings(), plain.result, DEFAULT_CALIBRATION_SIGMAS)
    S = principal_point_sensitivity(solve, flight.config.camera.camera)
    assert S is not None
    world_T_body = plain.result.estimate.world_T_body
    predicted = np.einsum("fij,fj->fi", world_T_body[:, :3, :3], S[:, 3:] @ np.ones(2))
    move = world_T_body[:, :3, 3] - clean.estimate.world_T_body[:, :3, 3]
    size = np.linalg.norm(predicted, axis=1)
    assert np.median(np.linalg.norm(move - predicted, axis=1) / size) < 1.3 * misfit
    assert 0.9 < np.median(np.linalg.norm(move, axis=1) / size) < 1.1

    np.testing.assert_array_equal(covered.result.estimate.world_T_body, world_T_body)
    assert plain.result.considered_principal_point is None
    added = covered.report["considered_principal_point"]
    assert added["sigma_px"] == 1.0 and 3.0 < added["position_sigma_added_m"]["median"] < 3.8
    assert plain.errors.anees_position > 0.75 * anees_plain, plain.errors.anees_position
    assert 1.0 < covered.errors.anees_position < 1.3 * anees_covered, (
        covered.errors.anees_position)


@pytest.mark.slow
def test_a_fixed_lag_carries_its_own_response_s_misfit_at_a_large_sigma():
    """A principal point known to 10 px only (cx, cy off by (8, -6) px: a typical draw),
    in the fixed lag, whose own response strays ~9% from the whole flight's ``S``: with the
    misfit's spread added (:data:`~cdtm_graph.calibration.considered.
    FIXED_LAG_RESPONSE_MISFIT`) the position ANEES stays near its 1 px value. Measured
    2026-11-28 (the 90-frame flight, seed 1): 1.59; 4.55 without the spread (a hostile
    hunt's find: 10.1 at 20 px, 26.2 at 50 px; with it 1.4-1.5). Mutation: the misfit
    left out (0): fails."""
    flight, dtm = simulate_flight(dataclasses.replace(BASE, seed=1))
    off = declared(with_calibration_error(flight, principal_point_px=(8.0, -6.0)), 10.0)
    out = smooth_and_evaluate(off, dtm, SmootherSettings(mode=SmootherMode.INCREMENTAL,
                                                         lag_s=10.0))
    assert out.errors is not None
    assert 1.0 < out.errors.anees_position < 1.3 * 1.59, out.errors.anees_position


@pytest.mark.slow
@pytest.mark.parametrize(("tilt_deg", "sigma_px", "rms_along_axis"), [(2.0, 20.0, 0.52),
                                                                    (30.0, 10.0, 0.47)])
def test_the_live_share_holds_at_a_large_sigma(tilt_deg, sigma_px, rms_along_axis):
    """The fixed lag's live updates with a principal point known to 20 px (a near-nadir
    camera) or 10 px (tilted 30 deg forward), off by (0.8, -0.6) sigma: no frame's
    position error beyond 3 sigma (NEES 14.16, frames 10-89), and along the optical axis
    the error's z-scores within 1.3x the measured rms. Measured 2026-11-28 (the 90-frame
    flight, seed 1): mean NEES 1.08 and 0.74, none beyond; rms along the axis 0.52 and
    0.47. Without the live response's misfit the near-nadir case read mean NEES 10.9, 26
    of 80 beyond (a hunt's find); without the optical axis's share the tilted one read
    rms 1.28-1.65 along it (a review's). Mutations: ``LIVE_RESPONSE_MISFIT`` 0 fails the
    first, the optical axis's share left out the second."""
    flight, dtm = simulate_flight(dataclasses.replace(BASE, seed=1, camera_tilt_deg=tilt_deg))
    log = declared(with_calibration_error(
        flight, principal_point_px=(0.8 * sigma_px, -0.6 * sigma_px)), sigma_px)
    truth = flight.groundtruth.interpolate(flight.frames.t_ns).position_m
    smoother = IncrementalSmoother(log.config, dtm, SmootherSettings(
        mode=SmootherMode.INCREMENTAL, lag_s=10.0), imu=log.imu)
    axis_body = log.config.camera.body_T_cam[:3, 2]
    tracks, nees, along = log.tracks, [], []
    for k, t in enumerate(log.frames.t_ns):
        update = smoother.add_frame(int(t), tracks.track_id[tracks.frame == k],
                                    tracks.uv_px[tracks.frame == k])
        R = update.world_T_body[:3, :3]
        error, covariance = update.world_T_body[:3, 3] - truth[k], \
            R @ update.pose_covariance[3:, 3:] @ R.T
        nees.append(error @ np.linalg.solve(covariance, error))
        axis = R @ axis_body
        along.append(error @ axis / np.sqrt(axis @ covariance @ axis))
    assert max(nees[10:]) < 14.16, max(nees[10:])
    assert np.sqrt(np.mean(np.square(along[10:]))) < 1.3 * rms_along_axis
