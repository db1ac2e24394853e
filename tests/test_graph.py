"""Graph builders: pairing of track observations, shared DTM error, priors, the IMU stream."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from cdtm_graph.camera import PinholeCamera
from cdtm_graph.errors import SolverError
from cdtm_graph.flightlog import ImuSamples, Tracks
from cdtm_graph.gating import chi2_2dof_quantile, innovation_mahalanobis
from cdtm_graph.imu import ImuIntervals, ImuStream, SampleHold
from cdtm_graph.sim.simulate import SimulationSettings, simulate_flight
from cdtm_graph.smoother import IncrementalSmoother
from cdtm_graph.tracks import TrackTable, frame_pair_observations


def test_pairs_are_grouped_by_frame_pair_with_their_rank_in_the_track():
    # track 7 seen in frames 2, 3 and 7; track 9 in 3 and 7; track 4 only once
    tracks = Tracks(frame=np.array([2, 3, 3, 4, 7, 7]), track_id=np.array([7, 7, 9, 4, 7, 9]),
                    uv_px=np.arange(12, dtype=float).reshape(6, 2) * 10)
    camera = PinholeCamera.from_fov(400, 400, 60)
    pairs = frame_pair_observations(tracks, camera)
    got = {(p.frame_a, p.frame_b): (p.track_id.tolist(), p.track_pair_index.tolist())
           for p in pairs}
    assert got == {(2, 3): ([7], [1]), (3, 7): ([7, 9], [2, 1])}
    pair_23 = pairs[0]
    np.testing.assert_allclose(pair_23.q_a, camera.pixels_to_rays(tracks.uv_px[[0]]))
    np.testing.assert_allclose(pair_23.q_b, camera.pixels_to_rays(tracks.uv_px[[1]]))


def test_features_with_nan_rays_are_dropped_and_counted():
    """A pixel the distortion model cannot invert has a NaN ray: no factor row, counted."""
    from cdtm_graph.camera import DOWNWARD_BODY_T_CAM
    from cdtm_graph.dtm import Dtm
    from cdtm_graph.geometry import make_pose
    from cdtm_graph.graph import GraphSettings, cdtm_factors
    from cdtm_graph.tracks import FramePairObservations
    from factors import FeatureNoise

    x = np.arange(0.0, 2000.0, 50.0)
    elevation = 30.0 * np.sin(x / 300.0)[None, :] * np.cos(x / 400.0)[:, None]
    dtm = Dtm(elevation, 0.0, 0.0, 50.0, 50.0, sigma_h_m=2.0)
    rng = np.random.default_rng(5)
    q_a = np.c_[rng.uniform(-0.3, 0.3, (10, 2)), np.ones(10)]
    q_b = q_a.copy()
    q_a[3, 0] = np.nan
    q_b[7, 1] = np.nan
    pair = FramePairObservations(0, 1, q_a, q_b, np.arange(10), np.ones(10, dtype=int))
    poses = [make_pose(np.eye(3), [1000.0, 1000.0, 800.0]),
             make_pose(np.eye(3), [1040.0, 1000.0, 800.0])]
    noise = FeatureNoise((1e-3, 1e-3), 2.0)
    build = cdtm_factors([pair], poses, DOWNWARD_BODY_T_CAM, dtm, noise, GraphSettings())
    assert build.n_features == 8 and build.n_missed == 2
    e, _, _ = build.factors[0].evaluate(poses[0], poses[1])
    assert np.isfinite(e).all()


def _pim_state(pim):
    return np.r_[pim.deltaRij().matrix().ravel(), pim.deltaPij(), pim.deltaVij(),
                 pim.preintMeasCov().ravel(), pim.deltaTij()]


@pytest.mark.parametrize("hold", list(SampleHold))
def test_imu_stream_gives_the_interval_preintegration_exactly(hold, rng):
    """Samples fed in random chunks, integrated as far as they fix the holds, give the
    same preintegration as the whole interval at once, also when they ran past the frame."""
    flight, _ = simulate_flight(SimulationSettings(frames=4, features=10, seed=3))
    imu, t_frames = flight.imu, flight.frames.t_ns
    reference = ImuIntervals(flight.config, imu, hold)
    bias = gtsam.imuBias.ConstantBias(np.array([0.01, -0.02, 0.03]), np.array([1e-3, 0, -2e-3]))
    stream_intervals = ImuIntervals(flight.config, ImuSamples(imu.t_ns[:0], imu.gyro_radps[:0],
                                                              imu.acc_mps2[:0]), hold)
    stream = ImuStream(stream_intervals)
    sent = 0
    for k in range(len(t_frames) - 1):
        stream.start(int(t_frames[k]), bias)
        # live: chunks up to the next frame; the last interval also overshoots it
        end = int(np.searchsorted(imu.t_ns, t_frames[k + 1])) + (1 if k < 2 else 40)
        while sent < end:
            step = min(int(rng.integers(1, 30)), end - sent)
            stream_intervals.imu = ImuSamples(imu.t_ns[:sent + step], imu.gyro_radps[:sent + step],
                                              imu.acc_mps2[:sent + step])
            sent += step
            stream.advance()
        got = stream.finish(int(t_frames[k + 1]))
        want = reference.preintegrate(int(t_frames[k]), int(t_frames[k + 1]), bias)
        np.testing.assert_array_equal(_pim_state(got), _pim_state(want))


def test_live_fed_incremental_run_equals_imu_given_up_front():
    """run() feeds the IMU as it would arrive (add_imu between frames): same estimates and
    covariances as a smoother given the whole IMU at construction."""
    flight, dtm = simulate_flight(SimulationSettings(frames=8, features=40, seed=4))
    live = IncrementalSmoother(flight.config, dtm).run(flight)
    upfront = IncrementalSmoother(flight.config, dtm, imu=flight.imu).run(flight)
    np.testing.assert_array_equal(live.estimate.world_T_body, upfront.estimate.world_T_body)
    np.testing.assert_array_equal(live.covariances.pose, upfront.covariances.pose)
    assert all(t > 0 for t in live.stats.imu_times_s[1:])
    assert all(t == 0 for t in upfront.stats.imu_times_s)


def _samples(imu, a, b):
    return ImuSamples(imu.t_ns[a:b], imu.gyro_radps[a:b], imu.acc_mps2[a:b])


def test_a_frame_ahead_of_its_imu_can_be_retried():
    """A frame whose interval the IMU does not yet cover is refused with nothing changed;
    fed the missing samples, the same frame goes through and the run equals a normal one."""
    flight, dtm = simulate_flight(SimulationSettings(frames=5, features=40, seed=4))
    imu, t = flight.imu, flight.frames.t_ns
    reference = IncrementalSmoother(flight.config, dtm, imu=flight.imu).run(flight)
    smoother = IncrementalSmoother(flight.config, dtm)
    tracks = flight.tracks
    sent = 0
    for k in range(len(t)):
        rows = tracks.frame == k
        cover = int(np.searchsorted(imu.t_ns, t[k])) + 1
        if k == 2:  # three samples short of the frame time
            smoother.add_imu(_samples(imu, sent, cover - 3))
            sent = cover - 3
            with pytest.raises(SolverError, match="does not cover"):
                smoother.add_frame(int(t[k]), tracks.track_id[rows], tracks.uv_px[rows])
        smoother.add_frame(int(t[k]), tracks.track_id[rows], tracks.uv_px[rows],
                           _samples(imu, sent, cover))
        sent = cover
    smoother.finalize(3)
    np.testing.assert_array_equal(smoother.estimate().world_T_body,
                                  reference.estimate.world_T_body)


def test_imu_running_ahead_of_the_camera_is_held_back():
    """With camera latency the IMU arrives past each frame before the frame does: the
    stream learns the lead and stops integrating into the next interval; the estimates
    stay those of the IMU given up front."""
    flight, dtm = simulate_flight(SimulationSettings(frames=6, features=40, seed=4))
    imu, t = flight.imu, flight.frames.t_ns
    reference = IncrementalSmoother(flight.config, dtm, imu=flight.imu).run(flight)
    smoother = IncrementalSmoother(flight.config, dtm)
    tracks = flight.tracks
    lead = 7  # samples past the frame time that arrive before the frame
    sent, redone = 0, []
    for k in range(len(t)):
        upto = int(np.searchsorted(imu.t_ns, t[k])) + lead
        smoother.add_imu(_samples(imu, sent, upto))
        sent = upto
        redone.append(smoother._stream._done_ns > t[k])  # integrated past this frame?
        rows = tracks.frame == k
        smoother.add_frame(int(t[k]), tracks.track_id[rows], tracks.uv_px[rows])
    assert redone[1] and not any(redone[2:])
    assert smoother._stream.holdback_ns >= imu.t_ns[lead - 1] - imu.t_ns[0]
    smoother.finalize(3)
    np.testing.assert_array_equal(smoother.estimate().world_T_body,
                                  reference.estimate.world_T_body)


def test_frames_without_tracks_and_returning_track_ids():
    """A frame with no tracks may come as empty lists; a track id forgotten by the fixed
    lag and seen again counts once among the log's tracks."""
    flight, dtm = simulate_flight(SimulationSettings(frames=4, features=30, seed=4))
    smoother = IncrementalSmoother(flight.config, dtm, imu=flight.imu)
    update = smoother.add_frame(int(flight.frames.t_ns[0]), [], [])
    assert update.n_features == 0
    table = TrackTable()
    q = np.c_[np.zeros((2, 2)), np.ones(2)]
    table.add_frame(0, np.array([3, 4]), q)
    table.forget_before(1)
    table.add_frame(1, np.array([4, 5]), q)
    assert table.n_tracks == 3


def test_innovation_distance_is_chi_square_2_for_a_linear_gaussian_model(rng):
    """e = H dx + v with dx ~ N(0, P), v ~ N(0, I): d is chi-square(2), and the gate of
    probability p passes a fraction p."""
    n = 20000
    L = rng.normal(size=(12, 12))
    P = L @ L.T * 0.01 + np.diag(rng.uniform(0.001, 0.1, 12))
    H_a, H_b = rng.normal(size=(n, 2, 6)), rng.normal(size=(n, 2, 6))
    dx = rng.multivariate_normal(np.zeros(12), P, n)
    e = np.einsum("nij,nj->ni", np.concatenate([H_a, H_b], axis=2), dx) + rng.normal(size=(n, 2))
    d = innovation_mahalanobis(e, H_a, H_b, P)
    assert abs(d.mean() - 2.0) < 4 * 2.0 / np.sqrt(n)  # chi2_2: mean 2, std 2
    for p in (0.9, 0.99):
        passed = np.mean(d <= chi2_2dof_quantile(p))
        assert abs(passed - p) < 4 * np.sqrt(p * (1 - p) / n)
    with pytest.raises(ValueError):
        chi2_2dof_quantile(1.0)


def test_the_innovation_gate_drops_gross_outliers_before_they_enter():
    """Bad matches (2% of observations moved 15-25 px) are gated out as they arrive: the
    incremental run stays near the clean one, where without a gate it does not."""
    import dataclasses

    from cdtm_graph.run import smooth_and_evaluate
    from cdtm_graph.smoother import SmootherMode, SmootherSettings

    flight, dtm = simulate_flight(SimulationSettings(frames=30, features=80, seed=6))
    rng = np.random.default_rng(8)
    uv = flight.tracks.uv_px.copy()
    bad = rng.random(len(uv)) < 0.02
    angle = rng.uniform(0, 2 * np.pi, int(bad.sum()))
    shift = rng.uniform(15, 25, angle.size)[:, None] * np.c_[np.cos(angle), np.sin(angle)]
    uv[bad] = np.clip(uv[bad] + shift, 0, 399)
    corrupted = dataclasses.replace(flight, tracks=dataclasses.replace(flight.tracks, uv_px=uv))
    runs = {gate: smooth_and_evaluate(corrupted, dtm, SmootherSettings(
        mode=SmootherMode.INCREMENTAL, innovation_gate=gate)) for gate in (None, 0.999)}
    clean = smooth_and_evaluate(flight, dtm, SmootherSettings(mode=SmootherMode.INCREMENTAL))
    gated = runs[0.999].result.counts
    assert gated.n_gated == gated.gated_per_frame.sum() >= bad.sum()  # each enters <= 2 pairs
    rmse = {g: np.linalg.norm(r.errors.rmse_position_m) for g, r in runs.items()}
    assert rmse[0.999] < 0.5 * rmse[None]
    assert rmse[0.999] < 2 * np.linalg.norm(clean.errors.rmse_position_m)
