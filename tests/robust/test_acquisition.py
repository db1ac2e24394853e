"""Acquisition: the search finds far fixes, says when it cannot, and its parts are exact.

The flights are the issue's (1 fps, 150 m/s at 1800 m, 150 features, 640x480, 60 deg
FOV, 300 m fractal relief, 30 m DTM), cut to the few frames acquisition looks at. The
fractal basic cell is 12 km wide unless a test wants it periodic: the default 3 km cell
repeats inside a 1000 m prior's 3-sigma region, where "ambiguous" is the right answer.
"""

from __future__ import annotations

import dataclasses
import math
import runpy
from pathlib import Path

import numpy as np
import pytest

from cdtm_graph.dtm import Dtm
from cdtm_graph.errors import FlightLogError
from cdtm_graph.flightlog import FlightLog, InitialState
from cdtm_graph.geometry import (
    make_pose,
    quat_wxyz_to_rotation,
    rotation_to_quat_wxyz,
    so3_exp,
    so3_log,
)
from cdtm_graph.imu import dead_reckoning
from cdtm_graph.robust.acquisition import (
    AcquisitionFrame,
    AcquisitionSettings,
    Correction,
    FixVerdict,
    SearchPrior,
    acquire,
    dead_reckoned_window,
    needs_acquisition,
    separation_z,
)
from cdtm_graph.robust.acquisition.cloud import _bilinear, _triangulate_tracks
from cdtm_graph.sim.faults import with_wrong_matches
from cdtm_graph.sim.simulate import SimulationSettings, simulate_flight

ROOT = Path(__file__).resolve().parents[2]
#: Frames acquisition looks at: 5 s of flight, ~200 tracks seen twice or more.
WINDOW = 6
#: The issue's flight with a 1000 m, 3 deg initial error and a matching prior.
FAR = SimulationSettings(
    frames=WINDOW, fps=1.0, speed_mps=150.0, altitude_m=1800.0, n_features=150,
    resolution_px=(640, 480), fov_deg=60.0, terrain_cell_m=12000.0,
    sigma_position_m=1000.0, sigma_attitude_deg=3.0,
    initial_error_m=(1000 * math.cos(0.61), -1000 * math.sin(0.61), 0.0),
    initial_error_deg=(0.0, 0.0, 3.0), region_margin_m=3500.0)
#: A fix within this of the truth is pulled in by every smoother (pull_in_m is 150 m).
FIX_TOLERANCE_M = 50.0
FIX_TOLERANCE_DEG = 1.0


def _truth_correction(log: FlightLog, frames: list[AcquisitionFrame]) -> tuple[np.ndarray, float]:
    """The horizontal offset (2,) and heading turn (deg) that put the first frame on the
    truth."""
    gt = log.groundtruth
    i0 = int(np.searchsorted(gt.t_ns, frames[0].t_ns))
    offset = gt.position_m[i0] - frames[0].world_T_body[:3, 3]
    R = quat_wxyz_to_rotation(gt.quaternion_wxyz[i0]) @ frames[0].world_T_body[:3, :3].T
    return offset[:2], math.degrees(math.atan2(R[1, 0] - R[0, 1], R[0, 0] + R[1, 1]))


@pytest.fixture(scope="module")
def far_flight(seed) -> FlightLog:
    return simulate_flight(dataclasses.replace(FAR, seed=seed))


def _acquire(log: FlightLog, dtm: Dtm, settings: AcquisitionSettings | None = None):
    frames, prior = dead_reckoned_window(log, WINDOW)
    return acquire(frames, log.config.camera, dtm, prior, settings), frames


@pytest.mark.slow
@pytest.mark.parametrize("wrong_fraction", [0.0, 0.15, 0.30])
def test_a_fix_1000_m_and_3_deg_off_is_acquired(rng, far_flight, wrong_fraction):
    """Acquired within the smoothers' pull-in of the truth, with up to 30% of the sightings
    moved to random pixels (about half the pairs of sightings then hold a wrong one)."""
    log, dtm = far_flight
    if wrong_fraction:
        log = with_wrong_matches(log, wrong_fraction, rng)[0]
    result, frames = _acquire(log, dtm)
    true_offset, true_heading = _truth_correction(log, frames)
    assert result.verdict is FixVerdict.ACQUIRED, result.reason
    assert np.linalg.norm(true_offset) > 900  # the prior really was that far off
    fix = result.correction
    assert fix is not None
    assert np.linalg.norm(fix.translation_world_m[:2] - true_offset) < FIX_TOLERANCE_M
    assert abs(fix.heading_deg - true_heading) < FIX_TOLERANCE_DEG
    assert result.hypotheses[1].separation_z >= AcquisitionSettings().separation_z
    assert result.searched.half_width_m == pytest.approx((3000.0, 3000.0))


@pytest.mark.slow
def test_the_corrected_first_state_is_near_the_truth_in_all_six_degrees(seed, far_flight):
    """Tilt too: the C-DTM refinement fits the whole rotation (the error here is 2, -2 and
    3 deg about the body axes)."""
    log, dtm = simulate_flight(
        dataclasses.replace(FAR, seed=seed, initial_error_deg=(2.0, -2.0, 3.0))
    )
    result, frames = _acquire(log, dtm)
    assert result.verdict is FixVerdict.ACQUIRED, result.reason
    pose, _ = result.correction.apply_to_state(frames[0].world_T_body,
                                               log.config.initial_state.velocity_mps)
    gt = log.groundtruth
    i0 = int(np.searchsorted(gt.t_ns, frames[0].t_ns))
    error = so3_log(pose[:3, :3].T @ quat_wxyz_to_rotation(gt.quaternion_wxyz[i0]))
    assert np.degrees(np.abs(error)).max() < FIX_TOLERANCE_DEG
    assert np.linalg.norm(pose[:3, 3] - gt.position_m[i0]) < FIX_TOLERANCE_M


@pytest.mark.slow
def test_noiseless_window_is_corrected_to_the_truth(seed):
    """No pixel, IMU or DTM error: the refined fix puts the first state on the truth."""
    log, dtm = simulate_flight(dataclasses.replace(
        FAR, seed=seed, noiseless=True, initial_error_m=None, initial_error_deg=None))
    true_frames, prior = dead_reckoned_window(log, WINDOW)  # noiseless: the truth itself
    wrong = Correction(so3_exp(np.radians([0.0, 0.0, -2.5])), np.array([-640.0, 710.0, 25.0]),
                       np.array([0.4, -0.3, 0.1]))
    poses = wrong.apply(np.stack([f.world_T_body for f in true_frames]),
                        np.array([f.t_ns for f in true_frames]), prior.velocity_world_mps,
                        prior.gravity_mps2)
    frames = [dataclasses.replace(f, world_T_body=p) for f, p in zip(true_frames, poses)]
    _, velocity = wrong.apply_to_state(true_frames[0].world_T_body, prior.velocity_world_mps)
    prior = dataclasses.replace(prior, velocity_world_mps=velocity)
    # (the exact DTM is the 5 m truth: search it on a 30 m grid all the same)
    result = acquire(frames, log.config.camera, dtm, prior, AcquisitionSettings(offset_step_m=30.0))
    assert result.verdict is FixVerdict.ACQUIRED, result.reason
    pose, v = result.correction.apply_to_state(frames[0].world_T_body, velocity)
    assert np.linalg.norm(pose[:3, 3] - true_frames[0].world_T_body[:3, 3]) < 0.5
    assert np.degrees(np.linalg.norm(so3_log(
        pose[:3, :3].T @ true_frames[0].world_T_body[:3, :3]))) < 0.01
    assert np.linalg.norm(v - log.config.initial_state.velocity_mps) < 0.05


@pytest.mark.parametrize("relief_m, verdicts", [
    (0.0, {FixVerdict.NO_INFORMATION}),
    (10.0, {FixVerdict.NO_INFORMATION, FixVerdict.AMBIGUOUS}),
])
def test_flat_terrain_is_never_acquired(seed, relief_m, verdicts):
    log, dtm = simulate_flight(dataclasses.replace(FAR, seed=seed, relief_m=relief_m))
    result, _ = _acquire(log, dtm)
    assert result.verdict in verdicts, result.reason
    assert result.correction is None


def test_repeating_terrain_is_ambiguous_and_lists_the_copies(seed):
    """A 3 km cell tiled: from a 1000 m prior the 3-sigma region holds the truth and two
    copies of it, which fit the same."""
    log, dtm = simulate_flight(dataclasses.replace(FAR, seed=seed, terrain_cell_m=3000.0))
    result, frames = _acquire(log, dtm)
    assert result.verdict is FixVerdict.AMBIGUOUS, result.reason
    assert result.correction is None
    true_offset, _ = _truth_correction(log, frames)
    tied = [h for h in result.hypotheses if h.separation_z < AcquisitionSettings().separation_z]
    offsets = np.array([h.offset_world_m[:2] for h in tied])
    assert len(tied) >= 2
    assert np.min(np.linalg.norm(offsets - true_offset, axis=1)) < FIX_TOLERANCE_M
    # every tie is the truth moved by whole periods of the cell
    periods = (offsets - true_offset) / 3000.0
    assert np.allclose(periods, np.round(periods), atol=FIX_TOLERANCE_M / 3000.0)


@pytest.mark.parametrize("sigma_m, verdict", [
    (200.0, FixVerdict.NO_INFORMATION),  # the truth 5 sigma out: nothing inside fits
    (300.0, FixVerdict.AT_EDGE),  # 3.3 sigma: the best fix refines out of the region
])
def test_a_prior_that_misses_the_truth_is_not_acquired(far_flight, sigma_m, verdict):
    log, dtm = far_flight
    frames, prior = dead_reckoned_window(log, WINDOW)
    prior = dataclasses.replace(prior, position_covariance_world=np.eye(3) * sigma_m ** 2)
    result = acquire(frames, log.config.camera, dtm, prior)
    assert result.verdict is verdict, result.reason
    assert result.correction is None


def test_too_few_tracks_is_no_information(far_flight):
    log, dtm = far_flight
    frames, prior = dead_reckoned_window(log, WINDOW)
    few = [dataclasses.replace(f, track_id=f.track_id[:10], uv_px=f.uv_px[:10]) for f in frames]
    result = acquire(few, log.config.camera, dtm, prior)
    assert result.verdict is FixVerdict.NO_INFORMATION
    assert "triangulate" in result.reason


def test_needs_acquisition_against_the_measured_pull_in():
    """The simulator's default prior (50 m, 1 deg) is within the pull-in; 1000 m is not."""
    defaults = SimulationSettings()
    default = SearchPrior.from_initial_state(
        _prior(defaults.sigma_position_m, defaults.sigma_attitude_deg), 9.81)
    assert not needs_acquisition(default.position_covariance_world, default.heading_sigma_rad)
    assert needs_acquisition(np.eye(3) * 1000.0 ** 2, math.radians(3.0))
    assert needs_acquisition(np.eye(3) * 60.0 ** 2, math.radians(1.0))  # 180 m > 150 m
    assert needs_acquisition(np.eye(3) * 50.0 ** 2, math.radians(4.0))  # 12 deg > 9 deg
    # only the horizontal spread counts (altitude is not searched)
    assert not needs_acquisition(np.diag([40.0, 40.0, 1000.0]) ** 2, math.radians(1.0))


def _prior(sigma_m: float, sigma_deg: float) -> InitialState:
    return InitialState(np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros(3), np.zeros(3),
                        np.zeros(3), sigma_m, sigma_deg, 1.0, 1e-4, 1e-2)


def test_correction_of_the_window_is_dead_reckoning_from_the_corrected_state(far_flight):
    """The search moves the window as dead reckoning from the corrected first state would:
    turned specific force, same velocity and gravity."""
    log, _ = far_flight
    init = log.config.initial_state
    t = log.frames.t_ns
    c = Correction(so3_exp(np.radians([1.0, -2.0, 5.0])), np.array([120.0, -40.0, 7.0]),
                   np.array([0.5, -0.2, 0.3]))
    free = dead_reckoning(log.config, log.imu, t)
    moved = c.apply(free.world_T_body, t, init.velocity_mps, log.config.gravity_mps2)
    pose, velocity = c.apply_to_state(init.world_T_body, init.velocity_mps)
    corrected = dataclasses.replace(init, position_m=pose[:3, 3], velocity_mps=velocity,
                                    quaternion_wxyz=rotation_to_quat_wxyz(pose[:3, :3]))
    config = dataclasses.replace(log.config, initial_state=corrected)
    again = dead_reckoning(config, log.imu, t).world_T_body
    assert np.abs(moved[:, :3, 3] - again[:, :3, 3]).max() < 1e-3
    assert np.abs(moved[:, :3, :3] - again[:, :3, :3]).max() < 1e-9


def test_bilinear_kernel_is_the_dtm_surface(rng):
    elevation = rng.normal(0, 50, (7, 9))
    elevation[3, 4] = np.nan
    dtm = Dtm(elevation, 100.0, 500.0, 30.0, -25.0)
    x = rng.uniform(95.0, 100.0 + 8 * 30.0 + 5.0, 400)
    y = rng.uniform(500.0 - 6 * 25.0 - 5.0, 505.0, 400)
    x[:3] = [100.0, 340.0, 220.0]  # the corners and an interior node
    y[:3] = [500.0, 350.0, 425.0]
    expected = dtm.height(x, y)
    got = np.array([_bilinear(dtm.elevation, dtm.x0, dtm.y0, dtm.dx, dtm.dy, a, b)
                    for a, b in zip(x, y)])
    assert np.array_equal(np.isnan(got), np.isnan(expected))
    assert np.allclose(got[~np.isnan(got)], expected[~np.isnan(expected)], atol=1e-9)


def test_triangulation_is_exact_and_drops_a_wrong_sighting(rng):
    points = rng.uniform([-500, -500, -100], [500, 500, 100], (20, 3))
    centres = np.zeros((20, 5, 3))
    centres[:, :, 0] = np.arange(5) * 150.0
    centres[:, :, 2] = 1800.0
    rays = points[:, None, :] - centres
    rays[3, 2] = (points[7] - centres[3, 2])  # a wrong match: another point
    rays /= np.linalg.norm(rays, axis=2, keepdims=True)
    starts = np.arange(21) * 5
    X, angle, z_spread = _triangulate_tracks(centres.reshape(-1, 3), rays.reshape(-1, 3),
                                             starts, 1e-3)
    assert np.abs(X - points).max() < 1e-6
    angle = angle.reshape(20, 5)
    assert angle[3, 2] > 1e-3 and np.delete(angle.ravel(), 3 * 5 + 2).max() < 1e-9
    assert np.all((z_spread > 0) & np.isfinite(z_spread))


def test_separation_z_asks_for_a_gain_that_is_large_and_consistent(rng):
    a = rng.chisquare(2, 300)
    assert separation_z(a, a) == 0.0
    assert separation_z(a, a - 1.0) == 0.0  # b fits better
    assert separation_z(a, a + 1.0 + rng.normal(0, 0.5, 300)) > 10.0
    one_track = a.copy()
    one_track[0] += 1000.0  # the whole gain in one track: Vuong sees no consistency
    assert separation_z(a, one_track) < 1.5
    assert separation_z(a, a + 1e-6) < 0.1  # round-off, however consistent


@pytest.mark.parametrize("change, message", [
    (lambda fs: fs[:1], "at least 2 frames"),
    (lambda fs: [fs[0], dataclasses.replace(fs[1], t_ns=fs[0].t_ns)], "not after"),
    (lambda fs: [fs[0], dataclasses.replace(fs[1], track_id=np.r_[fs[1].track_id[:1],
                                                                  fs[1].track_id[:-1]])],
     "seen twice"),
    (lambda fs: [fs[0], dataclasses.replace(fs[1], uv_px=fs[1].uv_px[:-1])], "pixels"),
])
def test_inconsistent_frames_are_refused_in_one_line(far_flight, change, message):
    log, dtm = far_flight
    frames, prior = dead_reckoned_window(log, WINDOW)
    with pytest.raises(FlightLogError, match=message):
        acquire(change(frames), log.config.camera, dtm, prior)


def test_a_prior_from_a_smoother_covariance_is_in_the_world_frame():
    """Body-frame [rotation, translation] covariance of a pose turned 90 deg about z:
    body x is world y."""
    pose = make_pose(so3_exp(np.array([0.0, 0.0, np.pi / 2])), np.zeros(3))
    cov = np.diag(np.r_[np.radians([0.5, 1.0, 3.0]) ** 2, [400.0 ** 2, 100.0 ** 2, 50.0 ** 2]])
    prior = SearchPrior.from_pose_covariance(pose, cov, np.zeros(3), 1.0, 9.81)
    assert np.allclose(np.sqrt(np.diag(prior.position_covariance_world)), [100.0, 400.0, 50.0])
    assert prior.heading_sigma_rad == pytest.approx(np.radians(3.0))
    assert prior.tilt_sigma_rad == pytest.approx(np.radians(1.0))


def test_a_bad_prior_is_refused():
    with pytest.raises(ValueError, match="positive definite"):
        SearchPrior(np.diag([1.0, 0.0, 1.0]), 0.1, 0.1, np.zeros(3), 1.0, 9.81)
    with pytest.raises(ValueError, match="heading_sigma_rad"):
        SearchPrior(np.eye(3), 0.0, 0.1, np.zeros(3), 1.0, 9.81)


def test_identity_correction_changes_nothing(far_flight):
    log, _ = far_flight
    frames, prior = dead_reckoned_window(log, WINDOW)
    poses = np.stack([f.world_T_body for f in frames])
    same = Correction.identity().apply(poses, np.array([f.t_ns for f in frames]),
                                       prior.velocity_world_mps, prior.gravity_mps2)
    assert np.abs(same - poses).max() < 1e-9
    assert np.allclose(Correction.identity().apply_to_state(make_pose(np.eye(3), np.ones(3)),
                                                            np.ones(3))[0][:3, 3], 1.0)


@pytest.mark.slow
def test_the_demo_acquires_then_every_mode_smooths_as_from_a_clean_prior():
    """scripts/acquisition_demo.py on a short far300 flight: acquired up front, or by the
    smoothers' own search on the log as it is, every mode is within 1.5x of the clean
    prior's error, with a consistent covariance. Without a search too, since the
    incremental modes settle their estimate from the prior (issue 21, build 5; measured
    2026-11-27: iSAM2 4.51 m at ANEES 1.89, fixed lag 5.25 m at 2.52, where iSAM2 ended
    324 m and the fixed lag 345 m off at ANEES ~10^4). Mutation: no settling
    (``Settling.reported`` returning the marginal at once) -> this test fails."""
    demo = runpy.run_path(str(ROOT / "scripts" / "acquisition_demo.py"))["demo"]
    result, rows = demo("far300", frames=15)
    assert result.verdict is FixVerdict.ACQUIRED, result.reason
    by = {(r.label, r.mode.value): r for r in rows}
    for mode in ("batch", "isam2", "fixed_lag"):
        clean = by[("clean prior", mode)]
        for label in ("acquired", "as logged", "no search"):
            assert by[(label, mode)].rmse_3d_m <= 1.5 * clean.rmse_3d_m, (label, mode)
            assert by[(label, mode)].anees <= 6.0, (label, mode)
