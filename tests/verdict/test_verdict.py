"""Tests of cdtm_graph.verdict.rules: the per-frame flags, the self-checks, the rules, and one
simulated flight per fault through the library and the CLI (verdict, frames, exit code)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import gtsam
import numpy as np
import pytest
import yaml
from scipy import integrate

from cdtm_graph.cli import main
from cdtm_graph.constants import chi2_quantile
from cdtm_graph.geometry import (
    make_pose,
    rigid_motion_to_tangent,
    rigid_motion_transfer,
    so3_exp,
)
from cdtm_graph.graph import cdtm_information, insert_state
from cdtm_graph.graph.log_graph import build_log_graph
from cdtm_graph.imu import initial_bias
from cdtm_graph.results import (
    BroadMapError,
    GraphCounts,
    PositionPrior,
    RandomWalkEstimate,
    SmootherResult,
    Solver,
    SolverStats,
    StateCovariances,
    TrajectoryEstimate,
)
from cdtm_graph.run import smooth_and_evaluate
from cdtm_graph.sim.faults import FlatGround, with_dtm_ending, with_imu_gap
from cdtm_graph.sim.simulate import simulate_flight, write_simulated_log
from cdtm_graph.smoother import SmootherMode, SmootherSettings
from cdtm_graph.studies.robustness import BASE, Mode
from cdtm_graph.verdict.evaluation import CovarianceVerdict, NeesConsistency
from cdtm_graph.verdict.imu_faults import imu_gaps
from cdtm_graph.verdict.rules import (
    Status,
    VerdictSettings,
    assess,
    fix_geometry,
    newest_frame_flags,
    truncated_chi2_2dof_mean,
    window_half_width,
    window_information,
)

NS = 1_000_000_000
#: The test flights: the issue's (1800 m, 150 m/s, ~150 features, 1 fps), 25 frames.
SHORT = dataclasses.replace(BASE, frames=25)
#: Seeds and length of the clean flights that must stay trusted (at least 19 of 20).
CLEAN_SEEDS = tuple(range(1, 21))
CLEAN_FRAMES = 30
MIN_TRUSTED_CLEAN = 19


def _smooth(flight, dtm, mode: SmootherMode = SmootherMode.BATCH):
    return smooth_and_evaluate(flight, dtm, SmootherSettings(mode=mode))


def _codes(verdict) -> list[str]:
    return [r.code for r in verdict.reasons]


def _only(verdict, code: str):
    """The one reason with ``code`` (fails if there are none or several)."""
    found = [r for r in verdict.reasons if r.code == code]
    assert len(found) == 1, verdict.lines()
    return found[0]


# --------------------------------------------------------------------------- formulas


def test_truncated_chi2_mean_is_the_integral():
    from scipy.stats import chi2  # the independent reference (seconds to import: here only)

    c = chi2.ppf(0.999, 2)
    mean, _ = integrate.quad(lambda x: x * chi2.pdf(x, 2), 0.0, c)
    assert truncated_chi2_2dof_mean(0.999) == pytest.approx(mean / 0.999, rel=1e-9)


def test_rigid_motion_transfer_moves_the_centre_of_a_rotation(rng):
    at, about = rng.normal(size=3) * 100, rng.normal(size=3) * 100
    omega, t = rng.normal(size=3) * 1e-3, rng.normal(size=3)
    moved = rigid_motion_transfer(at, about) @ np.r_[omega, t]
    np.testing.assert_allclose(moved, np.r_[omega, t + np.cross(omega, at - about)],
                               rtol=1e-12)
    # information written about one point and moved to another is that of the other
    J_about = rng.normal(size=(8, 6))  # rows on [omega, t] about `about`
    J_at = J_about @ np.linalg.inv(rigid_motion_transfer(at, about))
    A = rigid_motion_transfer(at, about)
    np.testing.assert_allclose(A.T @ (J_at.T @ J_at) @ A, J_about.T @ J_about, rtol=1e-9)


def test_rigid_motion_to_tangent_matches_gtsam(manifold, rng):
    """A small rigid motion of the world, applied to a pose, against the pose's tangent
    (GTSAM's localCoordinates: right perturbation, body frame)."""
    pose = make_pose(manifold.random_rotation(rng, math.pi), rng.normal(size=3) * 500)
    about = rng.normal(size=3) * 500
    delta = np.r_[rng.normal(size=3) * 1e-6, rng.normal(size=3) * 1e-3]
    R = so3_exp(delta[:3])
    moved = make_pose(R @ pose[:3, :3], R @ (pose[:3, 3] - about) + about + delta[3:])
    xi = gtsam.Pose3(pose).localCoordinates(gtsam.Pose3(moved))
    np.testing.assert_allclose(rigid_motion_to_tangent(pose, about) @ delta, xi,
                               rtol=1e-5, atol=1e-12)


def test_imu_gaps_name_the_frames_whose_interval_they_overlap():
    frames = np.arange(6) * NS
    imu = np.arange(0, 5 * NS + 1, NS // 100)  # 100 Hz
    imu = imu[(imu < int(2.2 * NS)) | (imu >= int(3.7 * NS))]  # 1.5 s missing
    inside, whole = imu_gaps(frames, imu)
    assert inside[0] == 0.0 and whole[0] == 0.0
    np.testing.assert_allclose(inside[[3, 4]], [0.81, 0.7], rtol=1e-9)
    np.testing.assert_allclose(whole[[3, 4]], 1.51, rtol=1e-9)  # the whole stretch
    np.testing.assert_allclose(inside[[1, 2, 5]], 0.01, rtol=1e-9)


# --------------------------------------------------------------------------- geometry


@pytest.fixture(scope="module")
def flat_and_hilly():
    """The C-DTM information at the true poses of two 8-frame flights, over flat ground and
    over 300 m of relief."""
    out = {}
    for name, relief in (("flat", 0.0), ("hilly", 300.0)):
        flight, dtm = simulate_flight(dataclasses.replace(SHORT, frames=8, relief_m=relief,
                                                          noiseless=True))
        truth = flight.groundtruth.interpolate(flight.frames.t_ns)
        values = gtsam.Values()
        bias = initial_bias(flight.config.initial_state)
        for k in range(len(flight.frames)):
            insert_state(values, k, truth.world_T_body[k], truth.velocity_mps[k], bias)
        built = build_log_graph(flight, dtm, SmootherSettings().graph, values)
        info = cdtm_information(built.cdtm, truth.world_T_body.__getitem__,
                                len(flight.frames))
        out[name] = (info, truth.world_T_body[:, :3, 3])
    return out


def test_flat_ground_gives_no_horizontal_fix(flat_and_hilly):
    """Over flat ground a rigid move of the poses keeps every ray on the same plane: the
    horizontal position gets nothing, the height a lot; over hills both get information."""
    settings = VerdictSettings()
    for name, (info, position) in flat_and_hilly.items():
        geometry = fix_geometry(window_information(info, position, 5))
        if name == "flat":
            assert np.all(geometry.flatness[1:] < 1e-12), geometry.flatness
        else:
            assert np.all(geometry.flatness[1:] > 2 * settings.flat_slope**2), geometry.flatness
        assert np.all(geometry.vertical[1:] > 0)


# --------------------------------------------------------------------------- rules


def _result(k: int = 30, features: int = 150, converged: bool = True, flags=None,
            rejected=None, chi2_scale: float = 1.0, nis_median: float = float("nan"),
            dt_s: float = 1.0, speed_mps: float | None = None) -> SmootherResult:
    """A synthetic run: K frames on a straight line (150 m apart, or flown at
    ``speed_mps``), ``features`` per frame, residuals at ``chi2_scale`` times their
    expectation, hilly-terrain-like C-DTM information."""
    t_ns = (np.arange(k) * dt_s * NS).astype(np.int64)
    step_m = 150.0 if speed_mps is None else speed_mps * dt_s
    poses = np.stack([make_pose(np.eye(3), [step_m * i, 0.0, 1800.0]) for i in range(k)])
    velocity = np.tile([step_m / dt_s, 0.0, 0.0], (k, 1))
    features_per_frame = np.full(k, features)
    features_per_frame[0] = 0
    info = np.zeros((k, 6, 6))
    info[1:] = np.diag([1e6, 1e6, 1e6, 0.2, 0.3, 2.0]) * features / 150.0
    expected = truncated_chi2_2dof_mean(0.999)
    return SmootherResult(
        TrajectoryEstimate(t_ns, poses, velocity, np.zeros((k, 3)), np.zeros((k, 3))),
        StateCovariances(np.tile(np.eye(6), (k, 1, 1)), np.tile(np.eye(3), (k, 1, 1)),
                         np.tile(np.eye(6), (k, 1, 1))),
        SolverStats(Solver.LEVENBERG_MARQUARDT, 5, 1e6, 1e3, converged, 1.0,
                    innovation_nis_median=nis_median),
        GraphCounts(k, 1000, 5000, 4000, int(features_per_frame.sum()), k - 1, k - 1,
                    features_per_frame, 0, np.zeros(k, int),
                    rejected if rejected is not None else {"missed_dtm": np.zeros(k, int)},
                    features_per_frame * expected * chi2_scale),
        flags=flags or {}, cdtm_information=info)


def _without_features(result: SmootherResult, frames) -> SmootherResult:
    features = result.counts.features_per_frame.copy()
    features[list(frames)] = 0
    return dataclasses.replace(result, counts=dataclasses.replace(
        result.counts, features_per_frame=features))


def test_a_clean_synthetic_run_is_trusted():
    verdict = assess(_result())
    assert verdict.status is Status.TRUSTED and verdict.reasons == () and verdict.flags == {}
    assert verdict.self_checks.passed
    assert verdict.self_checks.residual_chi2 == pytest.approx(1.0)
    assert Status.TRUSTED.exit_code == 0 and Status.DEGRADED.exit_code == 3
    assert Status.FAILED.exit_code == 3


def test_a_solver_that_did_not_converge_fails_the_run():
    verdict = assess(_result(converged=False))
    assert verdict.status is Status.FAILED and _codes(verdict) == ["not_converged"]


def test_a_rejection_reason_nobody_knew_slots_in_as_heavy_rejection():
    """Another developer adds a reason (here ``cloud``): its frames are flagged and named,
    with no change to the verdict; ``too_old`` (the fixed lag's window) is not a fault."""
    k = 30
    cloud = np.zeros(k, int)
    cloud[10:20] = 120  # 120 of 270 offered: 44%
    too_old = np.full(k, 100)
    verdict = assess(_result(k, rejected={"cloud": cloud, "too_old": too_old}))
    reason = _only(verdict, "heavy_rejection")
    assert verdict.status is Status.DEGRADED
    assert 5 <= reason.first_frame <= 10 and 19 <= reason.last_frame <= 24
    assert "cloud" in reason.message
    assert all("too_old" not in names for names in verdict.flags.values())


@pytest.mark.parametrize("per_frame, status", [(12, Status.TRUSTED), (20, Status.DEGRADED),
                                               (90, Status.FAILED)])
def test_map_mismatch_over_the_flight(per_frame, status):
    """A forest the DTM lacks drops 12-13% of the features all along (measured): under
    the window's 20%, over the run's 10%; here 13% (20 of 150 a frame) is a reason for the
    whole run, 8% (12) is not. A fix 1000 m off had ~90% dropped: most of the terrain
    disagrees with the map, the run fails (``wrong_fix``). Clean flights dropped at most
    6.7%."""
    k = 30
    mismatch = np.full(k, per_frame)
    mismatch[0] = 0
    verdict = assess(_result(k, features=150 - per_frame,
                             rejected={"map_mismatch": mismatch}))
    assert verdict.status is status
    if status is Status.TRUSTED:
        return
    run_wide = [r for r in verdict.reasons
                if r.code == "map_mismatch" and (r.first_frame, r.last_frame) == (0, k - 1)]
    assert len(run_wide) == 1 and "whole flight" in run_wide[0].message
    assert ("wrong_fix" in _codes(verdict)) is (status is Status.FAILED)
    # the windows flag their frames only where at least 20% went
    flagged = any("map_mismatch" in names for names in verdict.flags.values())
    assert flagged is (per_frame / 150 >= 0.2)


def _cut(result: SmootherResult, k: int) -> SmootherResult:
    """The synthetic run as far as frame k (its newest)."""
    c, e = result.counts, result.estimate
    return dataclasses.replace(
        result, estimate=TrajectoryEstimate(e.t_ns[:k + 1], e.world_T_body[:k + 1],
                                            e.velocity_mps[:k + 1], e.gyro_bias[:k + 1],
                                            e.accel_bias[:k + 1]),
        counts=dataclasses.replace(
            c, features_per_frame=c.features_per_frame[:k + 1],
            outliers_per_frame=c.outliers_per_frame[:k + 1],
            rejected_per_frame={r: v[:k + 1] for r, v in c.rejected_per_frame.items()},
            residual_chi2_per_frame=c.residual_chi2_per_frame[:k + 1]),
        cdtm_information=result.cdtm_information[:k + 1])


def test_a_live_updates_flags_are_the_verdicts_on_the_run_as_far_as_it_has_come():
    """``newest_frame_flags`` (what ``FrameUpdate.flags`` reports, from the frames within
    half a window before the newest) is, frame by frame, what :func:`assess` flags on the
    newest frame of the run cut there: the same rules on what has arrived. A burst of
    features off the map (frames 10-19), one frame without any (25), a stretch of few
    (30-35), rays off the map (40-46), then 10 features (47-48) and 22. The ``2 * half``
    frames before the newest (what ``FrameFlags`` passes) give the flags of the whole run
    so far; ``half`` would not (frame 52: 47-48's own windows cut before the off-map
    frames, so they count as few). ``map_mismatch`` starts at frame 11 (240 of 900
    offered in its window so far; frame 10, the burst's first, 120 of 900). Mutations
    (each fails): the window's share over the newest frame alone (``half`` 0 in
    ``newest_frame_flags``: from frame 10); no rule's code in the newest flags; ``half``
    frames in the slice's assert."""
    k = 60
    result = _result(k)
    features = result.counts.features_per_frame.copy()
    mismatch, missed = np.zeros(k, int), np.zeros(k, int)
    mismatch[10:20] = 120
    features[10:20] = 30
    features[25] = 0
    features[30:36] = 8
    missed[40:47], features[40:47] = 140, 10
    features[47:49], features[49:] = 10, 22
    result = dataclasses.replace(result, counts=dataclasses.replace(
        result.counts, features_per_frame=features,
        rejected_per_frame={"map_mismatch": mismatch, "missed_dtm": missed},
        residual_chi2_per_frame=features * truncated_chi2_2dof_mean(0.999)))
    half = window_half_width(result.estimate.t_ns, VerdictSettings().window_s)

    def newest(first: int, j: int) -> list[str]:
        return sorted(newest_frame_flags(
            features[first:j + 1].astype(float),
            {"map_mismatch": mismatch[first:j + 1], "missed_dtm": missed[first:j + 1]},
            first, half))

    flagged: dict[str, list[int]] = {}
    for j in range(1, k):
        live = newest(0, j)
        assert live == sorted(assess(_cut(result, j)).flags.get(j, [])), j
        assert newest(max(0, j - 2 * half), j) == live, j
        for code in live:
            flagged.setdefault(code, []).append(j)
    assert set(flagged) == {"map_mismatch", "few_features", "no_features", "off_dtm"}
    assert flagged["map_mismatch"][0] == 11 and flagged["no_features"] == [25]


def test_a_short_stretch_is_a_flag_not_a_reason():
    """One frame without features: the IMU bridges it; flagged, still trusted."""
    result = _without_features(_result(), [12])
    verdict = assess(result)
    assert verdict.status is Status.TRUSTED and verdict.flags == {12: ["no_features"]}


def test_mostly_unfixed_frames_fail_the_run():
    result = _without_features(_result(), range(5, 25))
    verdict = assess(result)
    assert verdict.status is Status.FAILED
    no_fix = _only(verdict, "no_fix")
    assert (no_fix.first_frame, no_fix.last_frame) == (5, 24)
    assert (_only(verdict, "no_features").first_frame,
            _only(verdict, "no_features").last_frame) == (5, 24)


def test_a_flag_the_smoother_sets_is_kept_and_reported():
    verdict = assess(_result(flags={k: ["acquisition_lost"] for k in range(8, 14)}))
    reason = _only(verdict, "acquisition_lost")
    assert (reason.first_frame, reason.last_frame) == (8, 13)
    assert verdict.status is Status.DEGRADED


def test_assess_is_idempotent_on_its_own_flags():
    result = _without_features(_result(), [12])
    first = assess(result)
    again = assess(dataclasses.replace(result, flags=first.flags))
    assert again.flags == first.flags and again.reasons == first.reasons


@pytest.mark.parametrize("scale, code, status", [
    (1.0, None, Status.TRUSTED), (0.8, None, Status.TRUSTED),
    (1.4, "residual_chi2", Status.DEGRADED), (0.5, None, Status.TRUSTED),
    (2.0, "misfit", Status.FAILED)])
def test_residual_chi2_self_check(scale, code, status):
    verdict = assess(_result(chi2_scale=scale))
    assert verdict.self_checks.passed is (code is None)
    assert verdict.status is status
    run_wide = [c for c in _codes(verdict) if c != "residual_misfit"]
    assert run_wide == ([code] if code else [])
    assert ("residual_misfit" in _codes(verdict)) is (code is not None)
    # residuals well below their expectation: a cautious noise model, said as a note
    assert any(n.startswith("residual_chi2") for n in verdict.notes) is (scale == 0.5)


@pytest.mark.parametrize("median, passes, note", [
    (1.39, True, False), (2.5, False, False), (0.5, True, True), (float("nan"), True, False)])
def test_innovation_self_check(median, passes, note):
    verdict = assess(_result(nis_median=median))
    assert ("innovation_nis" in _codes(verdict)) is not passes
    assert any(n.startswith("innovation_nis") for n in verdict.notes) is note


def test_window_is_set_in_seconds():
    assert window_half_width(np.arange(10) * NS, 10.0) == 5
    assert window_half_width(np.arange(10) * NS // 2, 10.0) == 10  # 2 fps
    assert window_half_width(np.arange(10) * 30 * NS, 10.0) == 1  # at least one


def _walks(grown: bool, held: bool) -> RandomWalkEstimate:
    """The random-walk check of a flight.yaml stating the walks 10x low (the robustness
    flight's seed 1: ratios 4.3 and 4.7), grown 7x and 5x, or not grown, or held only at
    the bound (30x) with the ratios still 4."""
    used = (7.0, 5.0) if grown and held else (30.0, 30.0) if grown else (1.0, 1.0)
    final = (1.2, 1.1) if held else (4.0, 4.0)
    return RandomWalkEstimate(1.9e-6, 3e-4, 4.33, 4.66, (1.14, 1.23), (0.26, 0.26),
                              (0.64, 0.89), 89, 1.9e-6 * used[0], 3e-4 * used[1], final,
                              30.0, held, 4 if grown else 0, 1.0)


@pytest.mark.parametrize("grown, held", [(True, True), (True, False), (False, True)])
def test_random_walks_grown_are_a_note_and_beyond_the_bound_a_reason(grown, held):
    """Walks the run grew and that then hold the bias steps: the note
    ``imu_random_walk_grown`` with the figures, the run trusted; still exceeded at the
    bound: ``imu_random_walk`` (degraded) with the advice; as stated: nothing. Catches
    the rule switched off (``_random_walk_check`` returning ``[]``) and the note given
    for walks not grown; each tried once, 2026-11-27."""
    verdict = assess(dataclasses.replace(_result(), imu_random_walk=_walks(grown, held)))
    notes = [n for n in verdict.notes if n.startswith("imu_random_walk_grown")]
    if not held:
        reason = _only(verdict, "imu_random_walk")
        assert verdict.status is Status.DEGRADED and notes == []
        assert "4.3x (gyro)" in reason.message and "grown 30x" in reason.message
        assert "imu.gyroscope_random_walk" in reason.message  # the advice
    elif grown:
        assert verdict.status is Status.TRUSTED and len(notes) == 1
        assert "7x (gyro" in notes[0] and "5x (accelerometer" in notes[0]
    else:
        assert verdict.status is Status.TRUSTED and notes == []


# --------------------------------------------------------------------------- consistency


def test_consistency_of_honest_correlated_errors(rng):
    """Honest covariances with errors correlated over ~20 frames: about 95% inside the
    bound (binomial bounds over 40 independent blocks), and the words say consistent."""
    blocks = rng.chisquare(3, size=200)
    nees = np.repeat(blocks, 20)  # 4000 frames, 200 independent values
    c = NeesConsistency.of(nees, 3)
    assert c is not None and c.verdict is CovarianceVerdict.CONSISTENT
    sd = math.sqrt(0.95 * 0.05 / 200)
    assert abs(c.inside_fraction - 0.95) < 4 * sd
    assert c.percentiles[50.0] == pytest.approx(chi2_quantile(0.5, 3), rel=0.25)


@pytest.mark.parametrize("scale, words", [(4.0, CovarianceVerdict.OPTIMISTIC),
                                          (0.05, CovarianceVerdict.CONSERVATIVE)])
def test_consistency_words(rng, scale, words):
    c = NeesConsistency.of(scale * rng.chisquare(3, size=500), 3)
    assert c is not None and c.verdict is words


# --------------------------------------------------------------------------- faults


@pytest.mark.slow
def test_clean_flights_stay_trusted(clean_flights):
    """20 seeds of the issue's flight, 30 frames, batch: measured 20 of 20 trusted. Catches
    a rule that cries wolf on clean data (tried 2026-11-27: the outlier self-check 20x too
    tight, max_outlier_fraction 0.0005, leaves 9 of 20 trusted). The runs are the
    calibration tests', shared."""
    verdicts = [out.verdict for out in clean_flights.runs_of(CLEAN_SEEDS, CLEAN_FRAMES)]
    trusted = [v.status is Status.TRUSTED for v in verdicts]
    assert sum(trusted) >= MIN_TRUSTED_CLEAN, [v.lines() for v in verdicts]


def test_few_features_degrade_every_frame():
    out = _smooth(*simulate_flight(dataclasses.replace(SHORT, n_features=8)))
    reason = _only(out.verdict, "few_features")
    assert out.verdict.status is Status.DEGRADED
    assert (reason.first_frame, reason.last_frame) == (1, SHORT.frames - 1)


def test_a_dtm_ending_under_the_flight_names_the_frames_off_it():
    flight, dtm = simulate_flight(SHORT)
    out = _smooth(flight, with_dtm_ending(flight, dtm, 15.0))
    reason = _only(out.verdict, "off_dtm")
    assert out.verdict.status is Status.DEGRADED
    # the footprint reaches ~5 s ahead: the frames from ~10 s on see past the end
    assert 10 <= reason.first_frame <= 17 and reason.last_frame == SHORT.frames - 1
    assert "IMU alone" in reason.message


def test_a_dtm_ending_early_fails_the_run():
    flight, dtm = simulate_flight(SHORT)
    out = _smooth(flight, with_dtm_ending(flight, dtm, 3.0))
    assert out.verdict.status is Status.FAILED and "no_fix" in _codes(out.verdict)


def test_an_imu_gap_names_its_frame():
    flight, dtm = simulate_flight(SHORT)
    out = _smooth(with_imu_gap(flight, 10.5, 0.5), dtm)
    reason = _only(out.verdict, "imu_gap")
    assert (reason.first_frame, reason.last_frame) == (11, 11)
    assert out.verdict.status is Status.DEGRADED


@pytest.mark.slow
def test_a_long_imu_gap_in_a_turn_is_named_and_stays_honest():
    """2 s without IMU samples in the turn: before the gap's maneuver-model noise
    (imu_faults.py) this run went ~400 m off with its covariance none the wiser; now the
    interval across the gap is uncertain as it should be, the error stays metres and
    within its covariance, and the gap is still a reason (degraded), with or without
    ground truth."""
    flight, dtm = simulate_flight(SHORT)
    flight = with_imu_gap(flight, 10.0, 2.0)
    out = _smooth(flight, dtm)
    # 2.56 m measured 2026-11-27 (~400 m before the gap model): a 1.3x regression bound
    assert out.errors is not None and out.errors.rmse_position_3d_m < 1.3 * 2.56
    assert out.errors.anees_position <= 6.0
    assert "confidently_wrong" not in _codes(out.verdict)
    blind = assess(out.result, None, flight.imu.t_ns)
    assert blind.status is Status.DEGRADED
    assert (_only(blind, "imu_gap").first_frame, _only(blind, "imu_gap").last_frame) == (11, 12)


@pytest.mark.slow
@pytest.mark.parametrize("pixel_sigma_px, status", [(1.5, Status.TRUSTED),
                                                     (0.17, Status.FAILED)])
def test_a_misstated_pixel_noise_is_named(pixel_sigma_px, status):
    """flight.yaml says 1.5 px where the tracker gives 0.5 px: residuals 0.11 of their
    expectation (measured), the innovations likewise: a cautious noise model, named in
    notes; says 0.17 px: residuals several times their expectation, a misfit (failed)."""
    flight, dtm = simulate_flight(SHORT)
    camera = dataclasses.replace(flight.config.camera, pixel_sigma_px=pixel_sigma_px)
    flight = dataclasses.replace(flight, config=dataclasses.replace(flight.config,
                                                                    camera=camera))
    out = _smooth(flight, dtm, SmootherMode.INCREMENTAL)
    assert out.verdict.status is status
    if status is Status.TRUSTED:
        assert {n.split(":")[0] for n in out.verdict.notes} == {"residual_chi2",
                                                                "innovation_nis"}
        assert out.verdict.self_checks.residual_chi2 < 0.5
        assert out.errors is not None and out.errors.anees_position < 3.0  # cautious
    else:
        assert "misfit" in _codes(out.verdict)


def test_an_incremental_clean_run_passes_its_self_checks(clean_flights):
    out = clean_flights.run(3, CLEAN_FRAMES, Mode.ISAM2)  # shared with the consistency tests
    checks = out.verdict.self_checks
    assert checks.passed and out.verdict.status is Status.TRUSTED
    assert 1.0 < checks.innovation_nis_median < 2.0


# --------------------------------------------------------------------------- CLI


@pytest.fixture(scope="module")
def lake_log(tmp_path_factory) -> Path:
    """A straight 30-frame flight over 20 s of flat ground (a lake under the track from 5
    to 25 s, in the truth and the DTM): the frames of ~10-20 s see nothing else."""
    settings = dataclasses.replace(SHORT, frames=30, turn_deg=0.0,
                                   flat_ground=FlatGround(at_s=5.0, duration_s=20.0,
                                                          half_width_m=1300.0))
    return write_simulated_log(settings, tmp_path_factory.mktemp("lake") / "log")


def test_a_flat_lake_is_degraded_with_its_frames_on_stderr(lake_log, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["smooth", str(lake_log), "--out", str(out), "--quiet"]) == 3
    err = [line for line in capsys.readouterr().err.strip().splitlines()
           if not line.startswith("cdtm smooth: note: ")]  # (a straight flight: the
    # calibration check is unresolved, a note)
    flat = [line for line in err if line.startswith("cdtm smooth: degraded: flat_terrain, ")]
    assert len(flat) == 1 and all(line.startswith("cdtm smooth: degraded: ") for line in err)
    report = json.loads((out / "report.json").read_text())
    assert report["verdict"] == "degraded" and len(report["reasons"]) == len(err)
    (reason,) = [r for r in report["reasons"] if r["code"] == "flat_terrain"]
    # inside the frames that see the lake at all, covering most of those that see only
    # the lake (10-20 s; measured: from 13, the windows of 10-12 reach the shore's
    # features, which the robust defaults now keep more of)
    assert 5 <= reason["first_frame"] <= 13 and 18 <= reason["last_frame"] <= 25
    assert all("flat_terrain" in report["flags"][str(k)]
               for k in range(reason["first_frame"], reason["last_frame"] + 1))


def test_a_dtm_elsewhere_is_refused_with_exit_1(tmp_path, capsys):
    log = write_simulated_log(dataclasses.replace(SHORT, frames=6), tmp_path / "log")
    config = yaml.safe_load((log / "flight.yaml").read_text())
    config["dtm"]["origin_enu_m"] = [100_000.0, 0.0, 0.0]  # the DTM 100 km off
    (log / "flight.yaml").write_text(yaml.safe_dump(config))
    out = tmp_path / "run"
    assert main(["smooth", str(log), "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("cdtm smooth: error: ")
    assert "expected the DTM under the flight" in err[0]
    assert not out.exists() or not any(out.iterdir())


# --------------------------------------------------------------------------- each rule bites
# (issue 21, build 7: every verdict rule has a test that fails when it is switched off;
# these are the rules whose switch-off tests/verdict did not notice on 2026-11-27)


def test_outliers_beyond_one_percent_degrade_the_run():
    """2% of the features beyond the chi-square(2) 99.9% test at the solution (0.1%
    expected): ``outliers``, degraded; 0.7%: trusted. Mutation: the ``outliers`` rule
    switched off -> the first run trusted: fails."""
    for per_frame, status in ((3, Status.DEGRADED), (1, Status.TRUSTED)):
        result = _result()
        outliers = np.where(np.arange(result.counts.n_frames) >= 1, per_frame, 0)
        result = dataclasses.replace(result, counts=dataclasses.replace(
            result.counts, n_outliers=int(outliers.sum()), outliers_per_frame=outliers))
        verdict = assess(result)
        assert verdict.status is status, verdict.lines()
        assert ("outliers" in _codes(verdict)) is (status is Status.DEGRADED)
        assert verdict.self_checks.outlier_fraction == pytest.approx(per_frame / 150)


def _errors_of(result: SmootherResult, offset_m: np.ndarray):
    """The errors of ``result`` against a truth ``offset_m`` (K,) metres west of each
    estimate: with the synthetic run's unit position covariance, NEES = offset^2."""
    from cdtm_graph.flightlog import States
    from cdtm_graph.verdict.evaluation import trajectory_errors

    est = result.estimate
    k = len(est)
    position = est.world_T_body[:, :3, 3] - np.c_[offset_m, np.zeros((k, 2))]
    truth = States(est.t_ns, position, np.tile([1.0, 0.0, 0.0, 0.0], (k, 1)), np.zeros((k, 3)))
    return trajectory_errors(est, result.covariances, truth)


@pytest.mark.parametrize("n_off, offset_m, code", [
    (0, 1.0, None),                       # NEES 1 everywhere: honest
    (12, 3.0, "overconfident"),           # 12 of 30 at NEES 9: 60% inside 7.81
    (20, 5.0, "confidently_wrong")])      # 20 of 30 at NEES 25: 67% beyond 16.3
def test_errors_beyond_the_covariance_are_named_with_ground_truth(n_off, offset_m, code):
    """With ground truth: fewer than 80% of the frames inside chi-square(3)'s 95% bound
    is ``overconfident`` (degraded); more than half beyond its 99.9% bound is
    ``confidently_wrong`` (failed). Mutations: either rule switched off -> its case
    passes as trusted: fails."""
    result = _result()
    k = result.counts.n_frames
    offset = np.where(np.arange(k) < n_off, offset_m, 1.0)
    verdict = assess(result, _errors_of(result, offset))
    assert [c for c in _codes(verdict)] == ([code] if code else []), verdict.lines()
    expected = {None: Status.TRUSTED, "overconfident": Status.DEGRADED,
                "confidently_wrong": Status.FAILED}[code]
    assert verdict.status is expected


def _calibration(observable: bool = True):
    from cdtm_graph.calibration.online import CalibrationEstimate

    return CalibrationEstimate(
        0.0, 0.0, np.zeros(3), 1.01, 500.0, 500.0, np.full(5, 1e-3), np.full(5, 1e-2),
        np.eye(5) * 1e-6, {"time_offset": True, "mount": observable, "focal_scale": True})


def _check(cost_drop: float, position_nees: float, conclusive: bool = True,
           wald: float = 1e3):
    """A calibration check's findings, ``suspect`` as the check decides it."""
    from cdtm_graph.calibration.check import (
        SUSPECT_COST_DROP,
        SUSPECT_NEES,
        SUSPECT_WALD,
        CalibrationCheck,
    )

    suspect = (cost_drop > SUSPECT_COST_DROP and position_nees > SUSPECT_NEES and conclusive
               and wald > SUSPECT_WALD)
    return CalibrationCheck(_calibration(), np.zeros(5), position_nees, cost_drop,
                            conclusive, suspect, 0.1, 30, 2.0, wald)


@pytest.mark.parametrize("cost_drop, position_nees, conclusive, wald, code, note", [
    (100.0, 50.0, True, 1e3, "calibration_suspect", None),
    (100.0, 50.0, False, 1e3, None, "calibration_unresolved"),
    (100.0, 1.0, True, 1e3, None, "calibration_held"),
    (100.0, 50.0, True, 20.0, None, "calibration_confounded"),
    (10.0, 50.0, True, 1e3, None, None)])
def test_the_calibration_check_is_a_reason_or_a_note(cost_drop, position_nees, conclusive,
                                                     wald, code, note):
    """The side solve's findings (:class:`~cdtm_graph.calibration.check.CalibrationCheck`)
    as the verdict reads them: significant, far from the run, conclusive and specific is
    ``calibration_suspect`` (degraded); not conclusive a note ``calibration_unresolved``;
    within the run's covariance a note ``calibration_held``; not specific (the map's
    shared error and the residuals' scatter explain it: Wald below ``SUSPECT_WALD``) a
    note ``calibration_confounded``; not significant nothing. Mutations: each of the four
    switched off -> its case: fails."""
    verdict = assess(dataclasses.replace(_result(), calibration_check=_check(
        cost_drop, position_nees, conclusive, wald)))
    assert _codes(verdict) == ([code] if code else []), verdict.lines()
    assert verdict.status is (Status.DEGRADED if code else Status.TRUSTED)
    named = [n.split(":")[0] for n in verdict.notes if n.startswith("calibration")]
    assert named == ([note] if note else [])


@pytest.mark.parametrize("five_drop, pp_drop, pp_nees, pp_wald, rival, code, note", [
    (6.0, 80.0, 70.0, 100.0, False, "calibration_suspect", None),
    (40.0, 80.0, 70.0, 100.0, False, "calibration_suspect", None),
    (6.0, 80.0, 3.0, 100.0, False, None, "calibration_held"),
    (6.0, 80.0, 70.0, 100.0, True, None, "calibration_confounded"),
    (6.0, 80.0, 70.0, 18.0, False, None, "calibration_confounded"),
    (6.0, 10.0, 70.0, float("nan"), False, None, None),
    (6.0, 80.0, 70.0, 100.0, False, None, "calibration_unresolved")])
def test_a_principal_point_off_is_named_by_the_calibration_check(
        five_drop, pp_drop, pp_nees, pp_wald, rival, code, note):
    """The principal point's step (:mod:`cdtm_graph.calibration.principal_point`) with the
    five parameters not significant: freeing ``cx``, ``cy`` lowers the error beyond 18.7,
    specifically (a Wald beyond 37.3 on the cluster-robust covariance) and the run's
    positions lie beyond their covariance from where it moves them: ``calibration_suspect``,
    whose advice names cx, cy (the online calibration does not estimate them); within the
    covariance a note ``calibration_held``; beside a rival fault of the data (``outliers``)
    or not specific (wrong matches on the epipolar line read W 15-19) a note
    ``calibration_confounded``; below the bound nothing; the five significant but
    confounded (a Wald of 20), the principal point still named. Mutations: the principal
    point's significance left out of ``CalibrationCheck.significant`` -> the first, third,
    fourth, fifth and last cases fail; the five's ``confounded`` judged before it -> the second
    fails; its specificity left out -> the fifth fails; a shift told to 5 px (a short
    flight) is a note ``calibration_unresolved``, its conclusiveness left out -> the last
    fails."""
    from cdtm_graph.calibration.extra_parts import PartCheck
    from cdtm_graph.calibration.principal_point import principal_point_part
    from cdtm_graph.camera import PinholeCamera

    check = dataclasses.replace(
        _check(five_drop, 50.0, True, 20.0),
        principal_point=PartCheck(
            principal_point_part(PinholeCamera.from_fov(640, 480, 60.0)), np.array([2.1, 1.9]),
            np.array([0.45, 5.0 if note == "calibration_unresolved" else 0.2]), pp_drop,
            pp_nees, pp_wald))
    k = 30
    result = dataclasses.replace(_result(k), calibration_check=check)
    if rival:
        per_frame = np.where(np.arange(k) >= 1, 3, 0)
        result = dataclasses.replace(result, counts=dataclasses.replace(
            result.counts, n_outliers=int(per_frame.sum()), outliers_per_frame=per_frame))
    verdict = assess(result)
    assert [c for c in _codes(verdict) if c != "outliers"] == ([code] if code else []), \
        verdict.lines()
    named = [n.split(":")[0] for n in verdict.notes if n.startswith("calibration")]
    assert named == ([note] if note else [])
    if code:
        message = next(r.message for r in verdict.reasons if r.code == code)
        assert "cx by +2.1 px" in message and "correct flight.yaml's principal point" in message


@pytest.mark.parametrize("case, position_nees, wald, codes, note", [
    ("whole_flight", 1.0, 1e3, ["calibration_suspect"], "map_mismatch"),
    ("whole_flight_moved", 50.0, 1e3, ["calibration_suspect"], "map_mismatch"),
    ("not_specific", 1.0, 20.0, ["map_mismatch"], "calibration_held"),
    ("beside_outliers", 1.0, 1e3, ["outliers", "map_mismatch"], "calibration_held"),
    ("a_stretch", 1.0, 1e3, ["map_mismatch"], "calibration_held"),
])
def test_a_calibration_fault_that_drove_features_out_is_named_for_them(
        case, position_nees, wald, codes, note):
    """A specific correction (W beyond 55) beside features left out as off the map over
    the whole flight (20 of 150 a frame: a run-wide ``map_mismatch``) takes them as its
    doing: ``calibration_suspect``, the rejections one note, whether the positions feel it
    or not (``late20ms``: a 20 ms offset left 3925 features out, W 1948-2101, the
    positions at NEES 2.6-6.6, 2026-11-28). Not when the map's shared error explains the
    correction as well (W 20), nor beside another fault of the data (``outliers``: the
    review's find), nor when the features went over one stretch only (frames 10-15: a
    fault of the map there). Mutations: the ``held_specific`` branch switched off ->
    ``whole_flight`` fails; ``DRIVEN_OUT`` taken from any stretch, not the whole flight ->
    ``a_stretch`` fails; the other rivals ignored -> ``beside_outliers`` fails."""
    k = 30
    mismatch = np.full(k, 20)
    if case == "a_stretch":
        mismatch = np.zeros(k, int)
        mismatch[10:16] = 60
    mismatch[0] = 0
    result = dataclasses.replace(
        _result(k, features=130, rejected={"map_mismatch": mismatch}),
        calibration_check=_check(100.0, position_nees, True, wald))
    if case == "beside_outliers":
        per_frame = np.where(np.arange(k) >= 1, 3, 0)  # 2%: outliers
        result = dataclasses.replace(result, counts=dataclasses.replace(
            result.counts, n_outliers=int(per_frame.sum()), outliers_per_frame=per_frame))
    verdict = assess(result)
    assert sorted(set(_codes(verdict))) == sorted(codes), verdict.lines()
    mine = [n for n in verdict.notes if n.startswith(note + ":")]
    assert len(mine) == 1, verdict.notes
    if note == "map_mismatch":
        assert mine[0].startswith("map_mismatch: frames 0-29")
        assert "as the calibration named drives" in mine[0]
        assert "over the whole flight (map_mismatch)" in verdict.reasons[0].message


def test_a_calibration_finding_beside_a_rival_fault_is_a_note():
    """Issue 21: a suspect calibration beside a reason that moves the side solve alike
    (here ``outliers``: wrong matches) is a note ``calibration_confounded`` naming it, the
    run degraded by its own reason alone; beside a reason a calibration fault itself
    causes (``confidently_wrong``) it is still named. Mutation: the rivals' test in
    ``_calibration_check`` switched off -> ``calibration_suspect`` beside ``outliers``:
    fails."""
    check = _check(100.0, 50.0)
    result = _result()
    outliers = np.where(np.arange(result.counts.n_frames) >= 1, 3, 0)  # 2%: outliers
    counts = dataclasses.replace(result.counts, n_outliers=int(outliers.sum()),
                                 outliers_per_frame=outliers)
    verdict = assess(dataclasses.replace(result, calibration_check=check, counts=counts))
    assert "outliers" in _codes(verdict) and "calibration_suspect" not in _codes(verdict)
    notes = [n for n in verdict.notes if n.startswith("calibration_confounded: ")]
    assert len(notes) == 1 and "outliers" in notes[0], verdict.lines()
    result = dataclasses.replace(_result(), calibration_check=check)
    offset = np.full(result.counts.n_frames, 5.0)  # NEES 25 everywhere: confidently wrong
    faulty = assess(result, _errors_of(result, offset))
    assert sorted(_codes(faulty)) == ["calibration_suspect", "confidently_wrong"]


@pytest.mark.parametrize("sigma_m, off_m, beside, code, note", [
    (1.2, 3.0, None, "initial_position", None),
    (1.2, 3.0, "outliers", None, "initial_position_confounded"),
    (1.2, 3.0, "calibration", None, "initial_position_confounded"),
    (50.0, 250.0, None, None, "initial_position_not_held"),
    (1.2, 1.0, None, None, None),
], ids=["held", "beside_outliers", "beside_calibration", "not_held", "honest"])
def test_a_prior_the_data_contradict_is_a_reason_only_where_it_holds_the_frame(
        sigma_m, off_m, beside, code, note):
    """``initial_position``: the first frame's estimate (1 m sigma each axis) ``off_m`` from
    flight.yaml's prior. At 1.2 m the prior weighs 69% of the frame: 3 m off is 4.5 sigma
    from the data's fix (9.8 m off) and moved the frame 6.8 m: a reason, or beside
    ``outliers`` (the data may be off) or ``calibration_suspect`` a note; 250 m off a 50 m
    prior is 5 sigma but moved the frame 0.1 m: a note; 1 m off at 1.2 m is nothing.
    Mutations: the rivals' test switched off -> ``beside_outliers`` fails; the prior
    judged before the calibration check (as first merged) -> ``beside_calibration``
    fails; the pull's test switched off -> ``not_held`` fails."""
    result = _result()
    x0 = result.estimate.world_T_body[0, :3, 3]
    result = dataclasses.replace(result, position_prior=PositionPrior(
        x0 - np.array([off_m, 0.0, 0.0]), sigma_m))
    if beside == "outliers":
        per_frame = np.where(np.arange(result.counts.n_frames) >= 1, 3, 0)  # 2%: outliers
        result = dataclasses.replace(result, counts=dataclasses.replace(
            result.counts, n_outliers=int(per_frame.sum()), outliers_per_frame=per_frame))
    if beside == "calibration":
        result = dataclasses.replace(result, calibration_check=_check(100.0, 50.0))
    verdict = assess(result)
    assert ("initial_position" in _codes(verdict)) is (code is not None), verdict.lines()
    assert [n.split(":")[0] for n in verdict.notes if n.startswith("initial_position")] == (
        [note] if note else [])
    if code:
        reason = next(r for r in verdict.reasons if r.code == code)
        assert (reason.first_frame, reason.last_frame) == (0, 0)
        assert all(figure in reason.message for figure in ("4.5 sigma", "9.8 m", "6.82 m"))


@pytest.mark.parametrize("estimated, used, first, code, note", [
    (3.5, 3.5, float("nan"), None, "map_error_grown"),
    (6.6, 7.2, 7.8, None, "map_error_grown"),
    (8.3, 2.4, float("nan"), "map_error", None),
], ids=["grown", "held_at_the_bound", "beyond"])
def test_a_map_read_beyond_what_a_run_grows_it_to_is_a_reason(estimated, used, first, code,
                                                              note):
    """``map_error_grown`` (a note: the covariances hold the grown sigma_h; held at the
    bound after a first reading beyond it, the note says so) against ``map_error`` (a
    reason): the tracks read the map beyond 3x its stated 2.4 m in the run kept, which
    then holds the stated sigma_h. Mutation: the rule switched off -> ``beyond`` is
    trusted: fails."""
    from cdtm_graph.results import MapErrorEstimate

    result = dataclasses.replace(_result(), map_error=MapErrorEstimate(
        2.4, estimated, 300, used, 7.2, first))
    verdict = assess(result)
    assert _codes(verdict) == ([code] if code else []), verdict.lines()
    assert [n.split(":")[0] for n in verdict.notes if n.startswith("map_error")] == (
        [note] if note else [])
    if code:
        assert f"{estimated:.2f} m rms" in verdict.reasons[0].message
    if first == first:  # held at the bound: the first reading named
        assert any(f"the first run read {first:.2f} m" in n for n in verdict.notes)


@pytest.mark.parametrize("solver", [Solver.ISAM2, Solver.FIXED_LAG], ids=lambda s: s.value)
def test_a_map_grown_as_the_run_went_is_said_so(solver):
    """A run whose incremental pass grew the map as it went (``MapErrorEstimate.grown_at``)
    and was kept. Read within the bound: the note names where it grew, that a fixed lag's
    frames let go before hold the stated map (a full history's factors all took it), and
    says what the end read without printing NaN when too few tracks were left to read.
    Read beyond: the reason ``map_error`` alone, saying the run grew part of it (the note
    would say "its covariances hold it" beside it). Mutations tried (2026-11-28): the
    note not left out when beyond -> both appear; the mode not told apart -> the iSAM2
    note says "the stated"; the NaN not worded -> "nan m": each fails."""
    from cdtm_graph.results import MapErrorEstimate

    base = dataclasses.replace(_result(), stats=dataclasses.replace(_result().stats,
                                                                    solver=solver))
    grown_at = ((25, 5.5), (45, 6.6))
    for estimated in (6.4, float("nan")):
        verdict = assess(dataclasses.replace(base, map_error=MapErrorEstimate(
            2.4, estimated, 300 if estimated == estimated else 12, 6.6, 7.2,
            grown_at=grown_at)))
        notes = [n for n in verdict.notes if n.startswith("map_error_grown")]
        assert _codes(verdict) == [] and len(notes) == 1, verdict.lines()
        assert "5.50 m from frame 25, 6.60 m from frame 45" in notes[0]
        assert ("the frames it had let go the stated" in notes[0]) == (
            solver is Solver.FIXED_LAG)
        assert "nan" not in notes[0]
    beyond = assess(dataclasses.replace(base, map_error=MapErrorEstimate(
        2.4, 8.3, 300, 6.6, 7.2, grown_at=grown_at)))
    assert _codes(beyond) == ["map_error"], beyond.lines()
    assert not any(n.startswith("map_error_grown") for n in beyond.notes)
    assert "grew it as it went, to 6.60 m from frame 45" in beyond.reasons[0].message


def test_a_calibration_part_the_flight_did_not_tell_is_a_note():
    """``calibration_unobservable``: a part estimated online that kept its prior's sigma is
    a note, not a reason. Mutation: the note switched off -> fails."""
    told = assess(dataclasses.replace(_result(), calibration=_calibration(True)))
    untold = assess(dataclasses.replace(_result(), calibration=_calibration(False)))
    assert not any(n.startswith("calibration_unobservable") for n in told.notes)
    notes = [n for n in untold.notes if n.startswith("calibration_unobservable: ")]
    assert len(notes) == 1 and "mount" in notes[0]
    assert untold.status is Status.TRUSTED


def test_a_map_offset_flight_yaml_does_not_declare_is_a_note():
    """``map_offset_undeclared``: no sigma for the whole map's offset is a note; declared,
    none. Mutation: the note switched off -> fails."""
    from cdtm_graph.results import MapOffset

    undeclared = assess(dataclasses.replace(_result(), map_offset=MapOffset()))
    declared = assess(dataclasses.replace(_result(), map_offset=MapOffset(5.0, 10.0)))
    assert any(n.startswith("map_offset_undeclared: ") for n in undeclared.notes)
    assert not any(n.startswith("map_offset_undeclared") for n in declared.notes)
    assert undeclared.status is declared.status is Status.TRUSTED


def test_a_smoother_event_is_a_reason_however_short():
    """``search_beyond_lag`` on one frame (an event, :data:`SMOOTHER_EVENTS`) is a reason;
    another smoother flag on one frame is only a flag (the IMU bridges a short stretch).
    Mutation: events judged by the stretch's length -> the first run trusted: fails."""
    event = assess(_result(flags={6: ["search_beyond_lag"]}))
    assert _codes(event) == ["search_beyond_lag"] and event.status is Status.DEGRADED
    short = assess(_result(flags={6: ["acquisition_lost"]}))
    assert short.reasons == () and short.flags == {6: ["acquisition_lost"]}


def _footprint_information(k: int, free_rotation_info: float) -> np.ndarray:
    """(K, 6, 6) per-frame C-DTM information whose horizontal position comes mostly with
    a tilt (a lever of 1800 m: the camera's height), the tilt told apart by
    ``free_rotation_info`` alone; horizontal 0.2 of the height's (not flat)."""
    lever = 1800.0
    ax = np.array([0.0, lever, 0.0, 1.0, 0.0, 0.0])
    ay = np.array([-lever, 0.0, 0.0, 0.0, 1.0, 0.0])
    info = (0.2 * (np.outer(ax, ax) + np.outer(ay, ay)) + np.diag([0.0, 0, 1e3, 0, 0, 1])
            + free_rotation_info * np.diag([1.0, 1, 0, 0, 0, 0]))
    out = np.zeros((k, 6, 6))
    out[1:] = info
    return out


@pytest.mark.parametrize("free_rotation_info, narrow", [(1e4, True), (1e5, False)])
def test_a_narrow_footprint_is_named(free_rotation_info, narrow):
    """Horizontal information that a tilt explains: once the attitude is free 1.5% of it
    is left (under 6%): ``narrow_fov`` over the flight, degraded; with the tilt told
    apart (13% left), trusted. Mutation: the ``narrow_fov`` rule switched off -> the
    first case trusted: fails."""
    result = _result()
    result = dataclasses.replace(result, cdtm_information=_footprint_information(
        result.counts.n_frames, free_rotation_info))
    verdict = assess(result)
    assert _codes(verdict) == (["narrow_fov"] if narrow else []), verdict.lines()
    assert verdict.status is (Status.DEGRADED if narrow else Status.TRUSTED)


def test_a_named_calibration_takes_the_broad_map_error_as_its_own():
    """A 1% focal error bends the ground the cameras triangulate over each footprint
    (``focal1pct``, 90 frames: shape evidence 20-40, ``broad_map_error`` over frames 26-28
    and 58-65 in batch and iSAM2). The calibration check is still named
    (``calibration_suspect``: broad map error is no rival of it), and the broad map error
    is then a note, its frames flagged. Mutations: ``Code.BROAD_MAP_ERROR`` back in
    ``CALIBRATION_RIVALS`` (as merged on 2026-11-27: focal1pct then lost
    ``calibration_suspect`` in batch and iSAM2) -> fails; ``_explained_by_calibration``
    not applied -> both named: fails (each tried)."""
    result = _result()
    k = result.counts.n_frames
    evidence = np.full(k, 12.0)
    evidence[:7] = evidence[-7:] = np.nan
    evidence[12:17] = 25.0
    shaped = dataclasses.replace(result, calibration_check=_check(100.0, 50.0),
                                 broad_map_error=BroadMapError(
                                     evidence, evidence, np.full(k, 3.2), np.full(k, 5.9),
                                     np.full(k, 230)))
    verdict = assess(shaped)
    assert _codes(verdict) == ["calibration_suspect"], verdict.lines()
    notes = [n for n in verdict.notes if n.startswith("broad_map_error: frames 12-16")]
    assert len(notes) == 1, verdict.lines()
    assert sorted(k for k, v in verdict.flags.items() if "broad_map_error" in v) == list(
        range(12, 17))


def _shaped(evidence: np.ndarray, lag_s: float | None = None, dt_s: float = 1.0,
            speed_mps: float | None = None) -> SmootherResult:
    """A run whose shape evidence is ``evidence`` (NaN on the 7 frames at each end whose
    windows the flight's ends cut), a frame every ``dt_s``."""
    result = _result(k=evidence.size, dt_s=dt_s, speed_mps=speed_mps)
    evidence = evidence.copy()
    evidence[:7] = evidence[-7:] = np.nan
    k = evidence.size
    shaped = dataclasses.replace(result, broad_map_error=BroadMapError(
        evidence, evidence, np.full(k, 3.2), np.full(k, 5.9), np.full(k, 230)))
    if lag_s is not None:
        shaped = dataclasses.replace(shaped, settings={"mode": "incremental", "lag_s": lag_s})
    return shaped


@pytest.mark.parametrize("frames, named", [(range(12, 17), True), (range(12, 14), False),
                                           ((), False)])
def test_a_broad_map_error_is_named_over_its_stretch(frames, named):
    """``broad_map_error`` (issue 21, build 4): the frames whose shape evidence exceeds
    ``broad_map.peak`` (20) over at least ``min_stretch_s`` are a reason, with the map's
    tilt and curvature in the message; two frames are a flag only; evidence at the
    sustained bound (12, as clean batch runs: 3.4-14.5 at their highest frame) is nothing
    however long; a fixed-lag run, whose statistic is taken at the poses one update holds
    (:class:`~cdtm_graph.robust.map_error.BroadMapWatch`), is held to the same bounds.
    Mutations: ``_broad_map_test`` left out of ``assess`` -> the reason is missing: fails;
    the comparison turned (``evidence < bound``) -> clean frames named: fails (each tried,
    2026-11-27); the fixed lag's old bound of 28 back -> not named there: fails (tried,
    2026-11-28)."""
    evidence = np.full(30, 12.0)
    evidence[list(frames)] = 25.0
    shaped = _shaped(evidence)
    verdict = assess(shaped)
    assert (_codes(verdict) == ["broad_map_error"]) is named, verdict.lines()
    if named:
        reason = _only(verdict, "broad_map_error")
        assert (reason.first_frame, reason.last_frame) == (12, 16)
        assert reason.status is Status.DEGRADED
        assert "tilt by 3.2 m and curve by 5.9 m over a kilometre" in reason.message
        assert "statistic 25 at frame 12, more than 20;" in reason.message, reason.message
    else:
        assert verdict.status is Status.TRUSTED
    flagged = sorted(k for k, v in verdict.flags.items() if "broad_map_error" in v)
    assert flagged == list(frames)
    fixed_lag = assess(dataclasses.replace(shaped, settings={"mode": "incremental",
                                                             "lag_s": 10.0}))
    assert _codes(fixed_lag) == _codes(verdict) and fixed_lag.flags == verdict.flags


@pytest.mark.parametrize("whole_peak, named", [(25.0, True), (12.0, False), (None, False)])
def test_a_fixed_lags_whole_flight_reading_of_the_shape_is_judged_too(whole_peak, named):
    """A fixed lag reads the map's shape at the poses its window held, and (since
    2026-11-28) at the calibration check's batch solve of the whole flight
    (``broad_map_error_whole``): either beyond the bounds names it (``hill15`` seed 8:
    the window's reading peaked at 14.9 over 600 m, the whole flight's held above 12 for
    1651 m: named; 60 flights over clean ground or ground detail, none). Here the
    window's reading stays at 12 and the whole flight's peaks at 25 over frames 12-16:
    named there, with the whole flight's figures; at 12, or without it, not. Mutation: the
    whole flight's reading left out of ``_broad_map_test`` -> fails."""
    watch = _shaped(np.full(30, 12.0), lag_s=10.0)
    result = watch
    if whole_peak is not None:
        evidence = np.full(30, 12.0)
        evidence[12:17] = whole_peak
        evidence[:7] = evidence[-7:] = np.nan
        result = dataclasses.replace(watch, broad_map_error_whole=BroadMapError(
            evidence, evidence, np.full(30, 1.3), np.full(30, 3.7), np.full(30, 230)))
    verdict = assess(result)
    assert (_codes(verdict) == ["broad_map_error"]) is named, verdict.lines()
    if named:
        reason = _only(verdict, "broad_map_error")
        assert (reason.first_frame, reason.last_frame) == (12, 16)
        assert "tilt by 1.3 m and curve by 3.7 m" in reason.message


@pytest.mark.parametrize("speed_mps, seconds, named", [
    (150.0, 10, True), (150.0, 14, True), (150.0, 9, False), (60.0, 21, False),
    (60.0, 24, True)])
@pytest.mark.parametrize("dt_s", [1.0, 0.5])
def test_a_shape_held_as_long_as_a_hill_is_named_below_the_peak(speed_mps, seconds, named,
                                                                 dt_s):
    """A hill under the footprint's edge bends it less than the peak bound but for as long
    as the footprint takes to cross it (hill15 seeds 2 and 8 at 150 m/s: 19-22 at most,
    above 12 for 13-18 s, where ground detail held 12 for at most 7 s in batch and iSAM2,
    2026-11-28): evidence of 16 while the aircraft flies ``broad_map.sustained_m`` (1425 m:
    10 s at 150 m/s is, 9 s is not, at a frame a second or two a second) is
    ``broad_map_error`` in batch; so is 24 s at 60 m/s (1.44 km), not 21 s (1.26 km: ground
    bumps held 12 that long at 60 m/s), nor 16 interrupted by a frame at 12 (two stretches);
    nor differently in a fixed-lag run (its statistic taken at the poses one update holds:
    clean, waves, ridges and bumps held 12 for at most 5 frames there, 2026-11-28). A
    stretch held long with one frame beyond the peak says both. Mutations: the sustained
    rule off (only
    ``peak``) -> the long stretches are not named: fails; the distance counted from the
    second frame (``flown_m[a + 1:b + 1]``) -> 10 s at 150 m/s not named: fails; a bound in
    seconds (10 s: the first version) -> 21 s at 60 m/s named: fails; in frames (``b - a +
    1`` frames of 150 m) -> 9 s at two frames a second named: fails; the fixed lag without
    the sustained bound (as before its statistic was taken as it goes) -> not named there:
    fails (each tried, 2026-11-28)."""
    frames = int(round(seconds / dt_s))
    evidence = np.full(int(60 / dt_s), 6.0)
    evidence[12:12 + frames] = 16.0
    verdict = assess(_shaped(evidence, dt_s=dt_s, speed_mps=speed_mps))
    assert (_codes(verdict) == ["broad_map_error"]) is named, verdict.lines()
    km = speed_mps * seconds / 1000.0
    if named:
        reason = _only(verdict, "broad_map_error")
        assert (reason.first_frame, reason.last_frame) == (12, 11 + frames)
        assert (f"statistic 16 at frame 12, above 12 for {seconds} s, {km:.1f} km flown:"
                in reason.message), reason.message
    fixed_lag = assess(_shaped(evidence, lag_s=10.0, dt_s=dt_s, speed_mps=speed_mps))
    assert (_codes(fixed_lag) == ["broad_map_error"]) is named, fixed_lag.lines()
    if named:  # one frame beyond the peak inside: both said
        peaked = evidence.copy()
        peaked[14] = 25.0
        reason = _only(assess(_shaped(peaked, dt_s=dt_s, speed_mps=speed_mps)),
                       "broad_map_error")
        assert (f"statistic 25 at frame 14, more than 20, above 12 for {seconds} s, "
                f"{km:.1f} km flown:" in reason.message), reason.message
    broken = evidence.copy()
    broken[12 + frames // 2] = 12.0
    assert assess(_shaped(broken, dt_s=dt_s, speed_mps=speed_mps)).status is Status.TRUSTED
