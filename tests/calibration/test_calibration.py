"""Online camera calibration: the factor's calibration Jacobians, config keys, and the
faults it is for (focal length, mount, time offset) recovered on simulated flights."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import X

from cdtm_graph.calibration import check as calibration_check
from cdtm_graph.calibration.check import thinned
from cdtm_graph.flightlog import CalibrationSigmas, read_flightlog, write_flightlog
from cdtm_graph.graph import GraphSettings
from cdtm_graph.run import smooth_and_evaluate
from cdtm_graph.sim.faults import with_calibration_error
from cdtm_graph.sim.simulate import SimulationSettings, simulate_flight
from cdtm_graph.smoother import SmootherMode, SmootherSettings
from cdtm_graph.studies.robustness import BASE, SCENARIOS, Mode
from cdtm_graph.verdict.rules import assess
from factors import CdtmPairFactor, PlaneMode, RobustKernel
from factors.calibration import CALIBRATION_DIM, CalibrationLink

N_CONFIGURATIONS = 30
#: Central differences with a 1e-6 step agree with the exact derivatives to ~2e-7
#: relative on the pose columns (the pose's retraction), ~5e-9 on the calibration's.
JACOBIAN_RTOL = 1e-6
CALIBRATION_JACOBIAN_RTOL = 1e-7


def _random_calibration(rng) -> np.ndarray:
    return np.r_[rng.uniform(-0.05, 0.05), np.radians(rng.uniform(-1, 1, 3)),
                 rng.uniform(-0.02, 0.02)]


def _link(rng, key=None, value=None) -> CalibrationLink:
    twist = lambda: np.r_[rng.normal(0, 0.1, 3), rng.normal(0, 60, 3)]  # noqa: E731
    return CalibrationLink(key, twist(), twist(),
                           np.zeros(CALIBRATION_DIM) if value is None else value)


@pytest.mark.parametrize("mode", [PlaneMode.FIXED, PlaneMode.REINTERSECT])
def test_calibration_and_pose_jacobians_match_central_differences(manifold, rng, mode):
    """Every column, the focal scale's (analytic, the planes held where REINTERSECT casts
    them again) among them."""
    worst = worst_calibration = 0.0
    for _ in range(N_CONFIGURATIONS):
        terrain = manifold.WavyTerrain(
            amplitude_m=rng.uniform(10, 60), wavelength_m=rng.uniform(300, 900)
        )
        body_T_cam, Ta, Tb, feats = manifold.random_pair(rng, terrain)
        fac = CdtmPairFactor(X(0), X(1), feats, body_T_cam, mode, raycast=terrain.raycast,
                             calibration=_link(rng, gtsam.symbol("C", 0)))
        c = _random_calibration(rng)

        def residual(Ta=Ta, Tb=Tb, c=c, fac=fac):
            return fac.evaluate_calibrated(Ta, Tb, c, want_jacobians=False)[0].ravel()

        _, Ha, Hb, Hc = fac.evaluate_calibrated(Ta, Tb, c)
        num_a = manifold.numerical_pose_jacobian(lambda T: residual(Ta=T), Ta)
        num_b = manifold.numerical_pose_jacobian(lambda T: residual(Tb=T), Tb)
        num_c = manifold.numerical_jacobian(lambda x: residual(c=x), c)
        for exact, num in ((Ha.reshape(-1, 6), num_a), (Hb.reshape(-1, 6), num_b),
                           (Hc.reshape(-1, CALIBRATION_DIM), num_c)):
            # each column on its own scale (seconds, radians and a scale factor differ)
            scale = np.maximum(np.abs(num).max(axis=0), 1e-12)
            worst = max(worst, float((np.abs(exact - num).max(axis=0) / scale).max()))
        scale = np.maximum(np.abs(num_c).max(axis=0), 1e-12)
        worst_calibration = max(worst_calibration, float(
            (np.abs(Hc.reshape(-1, CALIBRATION_DIM) - num_c).max(axis=0) / scale).max()))
    assert worst < JACOBIAN_RTOL
    assert worst_calibration < CALIBRATION_JACOBIAN_RTOL


def test_zero_calibration_leaves_the_factor_unchanged(manifold, rng):
    """At the nominal (zero) calibration the residual and pose Jacobians are the
    factor's without a calibration."""
    terrain = manifold.WavyTerrain(amplitude_m=40.0, wavelength_m=600.0)
    body_T_cam, Ta, Tb, feats = manifold.random_pair(rng, terrain)
    plain = CdtmPairFactor(X(0), X(1), feats, body_T_cam, PlaneMode.REINTERSECT,
                           raycast=terrain.raycast, robust=RobustKernel.CAUCHY)
    linked = plain.with_calibration(_link(rng, gtsam.symbol("C", 0)))
    e0, Ha0, Hb0 = (a.copy() for a in plain.evaluate(Ta, Tb))
    e1, Ha1, Hb1, _ = linked.evaluate_calibrated(Ta, Tb, np.zeros(CALIBRATION_DIM))
    np.testing.assert_allclose(e1, e0, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(Ha1, Ha0, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(Hb1, Hb0, rtol=1e-12, atol=1e-12)


def test_robust_rows_weigh_the_calibration_columns_alike(manifold, rng):
    """With a kernel, every Jacobian row is the plain one times the feature's sqrt
    weight (GTSAM's robust linearization), the calibration's included."""
    terrain = manifold.WavyTerrain(amplitude_m=40.0, wavelength_m=600.0)
    body_T_cam, Ta, Tb, feats = manifold.random_pair(rng, terrain, pixel_noise=2e-2)
    link = _link(rng, gtsam.symbol("C", 0))
    c = _random_calibration(rng)
    robust = CdtmPairFactor(X(0), X(1), feats, body_T_cam, PlaneMode.FIXED,
                            robust=RobustKernel.CAUCHY, robust_threshold=0.5, calibration=link)
    e_r, Ha_r, _, Hc_r = robust.evaluate_calibrated(Ta, Tb, c)
    e_p, Ha_p, _, Hc_p = robust.evaluate_calibrated(Ta, Tb, c, robust=False)
    sw = np.linalg.norm(e_r, axis=1) / np.linalg.norm(e_p, axis=1)
    assert sw.min() < 0.9  # the kernel is active
    np.testing.assert_allclose(Ha_r, sw[:, None, None] * Ha_p, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(Hc_r, sw[:, None, None] * Hc_p, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("n", [4, 40])
def test_gtsam_linearization_holds_the_calibration_block(manifold, rng, n):
    """Short pairs give GTSAM the raw rows, tall ones a triangle with the same Hessian
    and gradient over [X(a), X(b), C(0)]."""
    terrain = manifold.WavyTerrain(amplitude_m=40.0, wavelength_m=600.0)
    body_T_cam, Ta, Tb, feats = manifold.random_pair(rng, terrain, n=n)
    key = gtsam.symbol("C", 0)
    fac = CdtmPairFactor(X(0), X(1), feats, body_T_cam, PlaneMode.FIXED,
                         calibration=_link(rng, key))
    c = _random_calibration(rng)
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(Ta))
    values.insert(X(1), gtsam.Pose3(Tb))
    values.insert(key, c)
    A, b = fac.factor.linearize(values).jacobian()
    e, Ha, Hb, Hc = fac.evaluate_calibrated(Ta, Tb, c)
    H = np.concatenate([Ha.reshape(-1, 6), Hb.reshape(-1, 6),
                        Hc.reshape(-1, CALIBRATION_DIM)], axis=1)
    np.testing.assert_allclose(A.T @ A, H.T @ H, rtol=1e-8, atol=1e-8 * np.abs(H.T @ H).max())
    np.testing.assert_allclose(A.T @ b, -H.T @ e.ravel(), rtol=1e-8,
                               atol=1e-8 * np.abs(H.T @ e.ravel()).max())
    np.testing.assert_allclose(fac.factor.error(values), 0.5 * np.sum(e ** 2), rtol=1e-10)


# --------------------------------------------------------------------------- flight.yaml

_SIGMAS = "    time_offset_sigma_s: 0.03\n    mount_sigma_deg: 1.0\n    focal_scale_sigma: 0.02"


@pytest.fixture
def with_calibration_block(flightlog_files):
    """Factory: _with_calibration_block"""
    def make(root, block: str) -> int:
        path = root / "flight.yaml"
        line = flightlog_files.line_of(path, "pixel_sigma_px:") + 1
        flightlog_files.insert_line(path, line, "  calibration:\n" + block)
        return line

    return make


def test_calibration_sigmas_read_and_written_back(
    with_calibration_block, flightlog_files, small_log, tmp_path
):
    with_calibration_block(small_log.root, _SIGMAS)
    back = read_flightlog(small_log.root)
    assert back.config.camera.calibration == CalibrationSigmas(0.03, 1.0, 0.02)
    write_flightlog(back, tmp_path / "again")
    flightlog_files.write_dtm(tmp_path / "again" / "dtm.npz")
    assert read_flightlog(tmp_path / "again").config.camera.calibration == \
        back.config.camera.calibration


@pytest.mark.parametrize("block, words", [
    (_SIGMAS.replace("0.03", "0"), ("camera.calibration.time_offset_sigma_s", "[1e-06, 1] s")),
    (_SIGMAS.replace("1.0", "1e300"), ("camera.calibration.mount_sigma_deg", "deg")),
    (_SIGMAS.replace("0.02", "-0.01"), ("camera.calibration.focal_scale_sigma", "[1e-06, 0.5]")),
    (_SIGMAS.replace("0.02", "wide"), ("camera.calibration.focal_scale_sigma",)),
])
def test_calibration_sigma_beyond_sense_is_one_line_naming_the_key(
    with_calibration_block, flightlog_files, small_log, block, words
):
    line = with_calibration_block(small_log.root, block)
    # the offending value's line: the block's first key is on the line after "calibration:"
    index = next(i for i, text in enumerate(block.split("\n")) if words[0].split(".")[-1] in text)
    flightlog_files.expect_error(small_log.root, "flight.yaml", line + 1 + index, *words)


def test_calibration_with_a_missing_or_unknown_key_is_refused(
    with_calibration_block, flightlog_files, small_log
):
    line = with_calibration_block(small_log.root, _SIGMAS.replace("    focal_scale_sigma: 0.02",
                                                             "    focal_sigma: 0.02"))
    flightlog_files.expect_error(
        small_log.root, "flight.yaml", line + 3, "unknown key 'camera.calibration.focal_sigma'"
    )


# --------------------------------------------------------------------------- simulated faults

#: The prior of the tests' online calibration: 30 ms, 1 degree, 2%.
SIGMAS = CalibrationSigmas(time_offset_sigma_s=0.03, mount_sigma_deg=1.0, focal_scale_sigma=0.02)
ONLINE = SmootherSettings(graph=GraphSettings(calibration=SIGMAS, calibration_online=True))
#: The faults of issue 10 (sim.faults conventions: the yaml's focal is the true one times
#: 1.01, its mount the true one turned by (0.3, 0.4, 0) deg, the stamps 20 ms late) and
#: the corrections that undo them.
FAULTS = {
    "focal1pct": (dict(focal_scale=1.01), "focal_scale", 1 / 1.01),
    "mount05deg": (dict(mount_rotation_deg=(0.3, 0.4, 0.0)), "mount", (-0.3, -0.4, 0.0)),
    "late20ms": (dict(time_offset_s=0.02), "time_offset", -0.02),
}
#: Noiseless recovery: the time offset moves each pose along its frame's twist (first
#: order: 0.2 ms off at 20 ms in a turn); the mount and the focal scale are exact.
RECOVERY_TOL = {"time_offset": 1e-3, "mount": 5e-3, "focal_scale": 5e-5}
#: ...and the parameters not at fault stay at the nominal, but for what the first-order
#: time model leaves to them (a 20 ms offset: 0.005 deg of mount, 2.6e-4 of focal scale).
CROSSTALK_TOL = {"time_offset": 1e-3, "mount": 1e-2, "focal_scale": 5e-4}


def _estimated(c, part: str):
    return {"time_offset": c.time_offset_correction_s, "mount": c.mount_correction_deg,
            "focal_scale": c.focal_scale}[part]


@pytest.fixture(scope="module")
def noiseless_flight(seed):
    """A noiseless flight that says so: its yaml's pixel noise 0.01 px. (At the nominal
    0.5 px the batch takes out the bias that noise would leave,
    ``cdtm_graph.calibration.noise_bias``:
    a step that scales with the stated variance, ~2e-3 of focal scale here.)"""
    log, dtm = simulate_flight(SimulationSettings(frames=30, altitude_m=1000.0, relief_m=300.0,
                                                  seed=seed, noiseless=True))
    camera = dataclasses.replace(log.config.camera, pixel_sigma_px=0.01)
    return dataclasses.replace(log, config=dataclasses.replace(log.config, camera=camera)), dtm


@pytest.mark.slow
@pytest.mark.parametrize("fault", sorted(FAULTS))
def test_noiseless_flight_recovers_the_calibration_truth(noiseless_flight, fault):
    flight, dtm = noiseless_flight
    kwargs, part, truth = FAULTS[fault]
    out = smooth_and_evaluate(with_calibration_error(flight, **kwargs), dtm, ONLINE)
    c = out.result.calibration
    np.testing.assert_allclose(_estimated(c, part), truth, atol=RECOVERY_TOL[part])
    for other in set(RECOVERY_TOL) - {part}:  # the others stay at the nominal
        nominal = {"time_offset": 0.0, "mount": (0.0, 0.0, 0.0), "focal_scale": 1.0}[other]
        np.testing.assert_allclose(_estimated(c, other), nominal, atol=CROSSTALK_TOL[other])
    assert not c.unobservable


#: The issue's flight (1 fps, 150 m/s at 1800 m), 60 frames. Done-when of issue 10: each
#: calibration error with online calibration within 1.5 times the clean RMSE, ANEES <= 6.
FLIGHT = dataclasses.replace(BASE, frames=60)  # BASE's seed: the study's flight
RMSE_RATIO_MAX = 1.5
ANEES_MAX = 6.0


def _rmse_3d(out) -> float:
    return float(np.linalg.norm(out.errors.rmse_position_m))


@pytest.fixture(scope="module")
def clean_rmse_m() -> float:
    flight, dtm = SCENARIOS["clean"].flight(FLIGHT)
    return _rmse_3d(smooth_and_evaluate(flight, dtm, SmootherSettings()))


@pytest.mark.slow
@pytest.mark.parametrize("fault", sorted(FAULTS))
def test_calibration_errors_are_absorbed_online(clean_rmse_m, fault):
    flight, dtm = SCENARIOS[fault].flight(FLIGHT)
    out = smooth_and_evaluate(flight, dtm, ONLINE)
    assert _rmse_3d(out) <= RMSE_RATIO_MAX * clean_rmse_m
    assert out.errors.anees_position <= ANEES_MAX
    _, part, truth = FAULTS[fault]
    c = out.result.calibration
    sigma = {"time_offset": c.sigmas[0], "mount": c.sigmas[1:4], "focal_scale": c.sigmas[4]}
    # within 4 posterior sigmas (the mount's about the other axes is held by the IMU's
    # attitude, a few tenths of a degree)
    np.testing.assert_array_less(np.abs(np.asarray(_estimated(c, part)) - truth),
                                 4 * np.maximum(sigma[part], 0.05 * (part == "mount")))


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["isam2", "fixed_lag", "batch_no_marginals"])
def test_a_focal_error_held_by_default_is_flagged_suspect_without_ground_truth(mode):
    """By default every mode holds flight.yaml's calibration and checks it in a batch
    side solve: the 1% focal error is found (the side solve's scale within 4 sigmas of
    the truth) and the run is ``calibration_suspect``, never trusted (also a run without
    covariances, which claims none: any significant correction matters). The batch's
    default: :func:`test_the_calibration_is_named_only_beyond_the_residuals_scatter`."""
    flight, dtm = SCENARIOS["focal1pct"].flight(FLIGHT)
    settings = {"batch": SmootherSettings(),
                "isam2": SmootherSettings(mode=SmootherMode.INCREMENTAL),
                "fixed_lag": SmootherSettings(mode=SmootherMode.INCREMENTAL, lag_s=10.0),
                "batch_no_marginals": SmootherSettings(marginals=False)}[mode]
    out = smooth_and_evaluate(flight, dtm, settings)
    assert out.result.calibration is None
    check = out.result.calibration_check
    assert check.suspect
    assert abs(check.estimate.focal_scale - 1 / 1.01) < 4 * check.estimate.sigmas[4]
    assert out.verdict.status.value != "trusted"
    assert "calibration_suspect" in [r.code for r in out.verdict.reasons]
    assert out.report["calibration_check"]["suspect"]


def test_the_side_solve_thins_a_long_log_to_every_nth_frame():
    """Over ``MAX_FRAMES`` the side solve keeps every n-th frame with exactly the sightings
    in it (renumbered), the IMU whole; a short log is left as it is."""
    flight, _ = SCENARIOS["clean"].flight(FLIGHT)
    assert thinned(flight, FLIGHT.frames)[0] is flight
    sub, kept = thinned(flight, 25)  # 60 frames: every 3rd, 20 frames
    assert kept.tolist() == list(range(0, 60, 3))
    np.testing.assert_array_equal(sub.frames.t_ns, flight.frames.t_ns[kept])
    assert sub.imu is flight.imu
    rows = np.isin(flight.tracks.frame, kept)
    np.testing.assert_array_equal(kept[sub.tracks.frame], flight.tracks.frame[rows])
    np.testing.assert_array_equal(sub.tracks.track_id, flight.tracks.track_id[rows])
    np.testing.assert_array_equal(sub.tracks.uv_px, flight.tracks.uv_px[rows])


@pytest.mark.slow
def test_a_focal_error_is_flagged_by_a_thinned_side_solve(monkeypatch):
    """With the side solve down to every third frame (as on long logs), the 1% focal
    error is still found and the run is ``calibration_suspect``; a clean run is not."""
    monkeypatch.setattr(calibration_check, "MAX_FRAMES", FLIGHT.frames // 3)
    for name, suspect in (("focal1pct", True), ("clean", False)):
        flight, dtm = SCENARIOS[name].flight(FLIGHT)
        out = smooth_and_evaluate(flight, dtm, SmootherSettings())
        check = out.result.calibration_check
        assert check.n_frames == FLIGHT.frames // 3
        assert check.suspect is suspect
        assert ("calibration_suspect" in [r.code for r in out.verdict.reasons]) is suspect
        if suspect:
            assert abs(check.estimate.focal_scale - 1 / 1.01) < 4 * check.estimate.sigmas[4]


@pytest.mark.slow
def test_a_focal_error_held_unchecked_is_caught_only_by_ground_truth():
    """``--calibration held``: the 1% focal error goes into the height, which no
    self-check sees; only ground truth shows it (why the check is on by default). It
    bends the IMU bias steps as a walk stated too small does (the gyro's spread 2.11,
    grown, 2026-11-27): the note says the calibration is unchecked. Mutation tried: that
    clause left out of ``verdict.rules._random_walk_notes`` fails the last assertion."""
    flight, dtm = SCENARIOS["focal1pct"].flight(FLIGHT)
    out = smooth_and_evaluate(flight, dtm, SmootherSettings(graph=GraphSettings(calibration=None)))
    assert out.result.calibration is None and out.result.calibration_check is None
    assert [r.code for r in out.verdict.reasons] == ["confidently_wrong"]
    grown = [n for n in out.verdict.notes if n.startswith("imu_random_walk_grown")]
    assert grown and all("calibration is held unchecked" in n for n in grown)


#: Clean short flights of the issue's camera, many seeds, default settings: the verdicts,
#: and the side solve's focal scale (the online estimate from the run's solution): before
#: the noise's bias was taken out its mean z-score was -2.0 over such seeds.
CLEAN_SEEDS = range(1, 21)
CLEAN_FLIGHT = dataclasses.replace(BASE, frames=30)
#: Done-when of issue 10: clean flights stay trusted on at least 95% of the seeds.
MIN_TRUSTED_SHARE = 0.95
#: The mean of 20 z-scores of an unbiased estimate: sigma 0.22 (0.25 with the measured
#: spread 1.1); 4 of those.
MAX_MEAN_Z = 1.0


@pytest.fixture(scope="module")
def clean_seeds(clean_flights):
    """The clean flights smoothed with default settings (batch), shared with the verdict
    and consistency tests."""
    return clean_flights.runs_of(CLEAN_SEEDS, CLEAN_FLIGHT.frames)


@pytest.mark.slow
def test_clean_flights_stay_trusted_with_the_calibration_checked(clean_seeds):
    assert all(out.result.calibration_check is not None for out in clean_seeds)  # the default
    assert not any(out.result.calibration_check.suspect for out in clean_seeds)
    trusted = [out.verdict.status.value == "trusted" for out in clean_seeds]
    assert np.mean(trusted) >= MIN_TRUSTED_SHARE


@pytest.mark.slow
def test_the_focal_scale_estimated_on_clean_flights_is_unbiased(clean_seeds):
    z = np.array([out.result.calibration_check.z[4] for out in clean_seeds])
    assert abs(z.mean()) < MAX_MEAN_Z


def test_a_short_flight_cannot_tell_its_calibration_and_says_so():
    """Twelve frames of a straight flight, the mount turned 1 deg in yaw in flight.yaml
    (a turn tells it from the heading; there is none): the side solve is significant
    (cost drop 147.7) but tells the calibration poorly. The check does not believe it: a
    note, no reason of its own. Mutation: ``suspect`` without ``conclusive`` ->
    ``calibration_suspect`` named: this test fails.

    (Until 2026-11-27 the flight was the clean one: its side solve dropped 42.8 because the
    incremental pass of the batch's initial guess, still leaving the prior, left clean
    tracks out as off the map, two ``map_mismatch`` reasons on a clean flight. Settled
    (issue 21, build 5), it drops 11.4, not significant, as seeds 2-30 read 6.7-26.6.)"""
    # Seed-sensitive (2026-11-27): the flight measured is kept, its literal seed the point.
    flight, dtm = simulate_flight(SimulationSettings(frames=12, seed=2))
    flight = with_calibration_error(flight, mount_rotation_deg=(0.0, 0.0, 1.0))
    out = smooth_and_evaluate(flight, dtm, SmootherSettings())
    check = out.result.calibration_check
    assert check.significant and not check.conclusive and not check.suspect
    assert "calibration_suspect" not in [r.code for r in out.verdict.reasons]
    assert any(n.startswith("calibration_unresolved: ") for n in out.verdict.notes)


def test_a_mount_yaw_on_a_straight_flight_is_unobservable_and_noted(seed):
    """Eight frames before the first turn: the mount's yaw barely moves the features
    (only a turn tells it from the heading); said in a note, not hidden."""
    flight, dtm = simulate_flight(SimulationSettings(frames=8, altitude_m=1000.0, relief_m=300.0,
                                                  seed=seed))
    out = smooth_and_evaluate(flight, dtm, ONLINE)
    c = out.result.calibration
    assert "mount" in c.unobservable and "focal_scale" not in c.unobservable
    assert any(n.startswith("calibration_unobservable: ") and "mount" in n
               for n in out.verdict.notes)


@pytest.mark.slow
def test_an_incremental_run_on_a_clean_flight_is_checked_and_trusted(clean_flights):
    flight, dtm = clean_flights.flight(CLEAN_FLIGHT.seed, CLEAN_FLIGHT.frames)
    # Mode.ISAM2's settings are SmootherSettings(mode=SmootherMode.INCREMENTAL)
    out = clean_flights.run(CLEAN_FLIGHT.seed, CLEAN_FLIGHT.frames, Mode.ISAM2)
    assert out.result.calibration is None
    check = out.result.calibration_check
    assert not check.suspect and not check.significant
    assert out.verdict.status.value == "trusted"
    assert not any(n.startswith("calibration_") for n in out.verdict.notes)
    # estimating it is batch only: asked of an incremental run, it is checked instead,
    # and said so
    online = dataclasses.replace(ONLINE, mode=SmootherMode.INCREMENTAL)
    asked = smooth_and_evaluate(flight, dtm, online)
    assert asked.result.calibration is None and asked.result.calibration_check is not None
    assert any(n.startswith("calibration_not_estimated: ") for n in asked.verdict.notes)
    # held as flight.yaml writes it: no side solve
    held = dataclasses.replace(SmootherSettings(mode=SmootherMode.INCREMENTAL),
                               graph=GraphSettings(calibration=None))
    assert smooth_and_evaluate(flight, dtm, held).result.calibration_check is None


#: Issue 21, measured 2026-11-27 (30 frames, batch): 15% wrong matches on the epipolar
#: line (seed 2): the residuals at 2.46 times their expectation; the focal scale -5.9
#: sigma after the model's debiasing, -3.3 after the measured scatter's; the run's
#: positions at a mean NEES of 14.3 -> 5.5 from the side solve's (before: named
#: ``calibration_suspect``); Wald 17.0. A 1% focal error (seed 1): scatter 1.00, Wald 102.
SCATTERED_MIN = 2.0
FAULT_SCATTER_MAX = 1.1


@pytest.mark.parametrize("scenario, seed, suspect", [("wrong_epipolar15", 2, False),
                                                     ("focal1pct", CLEAN_FLIGHT.seed, True)])
def test_the_calibration_is_named_only_beyond_the_residuals_scatter(scenario, seed, suspect):
    """Wrong matches along the epipolar line pull the focal scale low as noise does, by
    more than the model's noise: the check debiases at the scatter the residuals show and
    judges the correction on the cluster-robust covariance; the flight's significant,
    conclusive correction is then within the run's covariance (a note), while a real 1%
    focal error, whose residuals sit at their expectation, is still named. Mutations: the
    debiasing at the measured scatter off (``noise_scale`` 1 in the check) -> the
    positions at NEES 14.3, named ``calibration_suspect`` before: fails; ``SUSPECT_WALD``
    above the fault's 102 -> the focal error unnamed: fails."""
    from cdtm_graph.calibration.check import SUSPECT_NEES, SUSPECT_WALD

    flight, dtm = SCENARIOS[scenario].flight(dataclasses.replace(CLEAN_FLIGHT, seed=seed))
    out = smooth_and_evaluate(flight, dtm, SmootherSettings())
    check = out.result.calibration_check
    assert check.suspect is suspect
    assert ("calibration_suspect" in [r.code for r in out.verdict.reasons]) is suspect
    assert check.significant and check.conclusive
    if suspect:
        assert check.residual_scatter < FAULT_SCATTER_MAX and check.wald > SUSPECT_WALD
        assert abs(check.estimate.focal_scale - 1 / 1.01) < 4 * check.estimate.sigmas[4]
        assert out.report["calibration_check"]["suspect"]
    else:
        assert check.residual_scatter > SCATTERED_MIN
        assert check.position_nees < SUSPECT_NEES
        assert any(n.startswith("calibration_") for n in out.verdict.notes)


@pytest.mark.slow
def test_a_time_offset_that_drove_features_out_is_named_for_them():
    """Stamps 20 ms late on a 45-frame flight: the track tests leave 1373 features out as
    off the map, and the run's positions stay within their covariance of the side solve's
    (NEES 4.7; ANEES 5.9 against ground truth). Before, the verdict blamed the map
    (``map_mismatch``) and noted the calibration (``calibration_held``, the offset at -48
    sigma, W 1672); now it names the calibration, the rejections noted as its doing
    (2026-11-28; the 90-frame flight in every mode: docs/verdict.md). Mutation: the
    verdict's ``held_specific`` branch switched off -> ``map_mismatch`` named: fails."""
    flight, dtm = SCENARIOS["late20ms"].flight(dataclasses.replace(BASE, frames=45))
    out = smooth_and_evaluate(flight, dtm, SmootherSettings())
    check = out.result.calibration_check
    assert check.held_specific and not check.suspect
    blind = assess(out.result)  # without ground truth (with it, also ``overconfident``)
    assert [r.code for r in blind.reasons] == ["calibration_suspect"]
    assert any(n.startswith("map_mismatch: ") for n in blind.notes)
    assert "map_mismatch" not in [r.code for r in out.verdict.reasons]
    assert abs(check.estimate.time_offset_correction_s + 0.02) < 4 * check.estimate.sigmas[0]


def test_the_free_solve_starts_on_the_pinned_solves_linearization(clean_flights, monkeypatch):
    """In a batch run's check the pinned solve ends on a linearization at its answer; the
    free solve starts on it, the pin left out (``without_pin``), and that changes nothing:
    the check is bit for bit the one made with a fresh linearization. Mutations tried:
    ``without_pin`` keeping the pin (the free solve starts pinned: the estimate and the
    cost drop move) and returning None always (the reuse gone: the first assertion)."""
    flight, dtm = clean_flights.flight(1, 30)
    result = clean_flights.run(1, 30).result
    sigmas = GraphSettings().calibration
    started = []
    real_lm = calibration_check.levenberg_marquardt

    def lm(*args, **kwargs):
        started.append(kwargs.get("linear_at_start") is not None)
        return real_lm(*args, **kwargs)

    monkeypatch.setattr(calibration_check, "levenberg_marquardt", lm)
    reused = calibration_check.check_calibration(flight, dtm, GraphSettings(), result, sigmas)
    assert started == [False, True]
    monkeypatch.setattr(calibration_check, "without_pin", lambda linear, free: None)
    fresh = calibration_check.check_calibration(flight, dtm, GraphSettings(), result, sigmas)
    assert reused.cost_drop == fresh.cost_drop
    np.testing.assert_array_equal(reused.z, fresh.z)
    assert reused.position_nees == fresh.position_nees
