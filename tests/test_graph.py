"""Graph builders: pairing of track observations, shared DTM error, priors."""

from __future__ import annotations

import numpy as np

from cdtm_graph.camera import PinholeCamera
from cdtm_graph.flightlog import Tracks
from cdtm_graph.graph import frame_pair_observations


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
    from cdtm_graph.dtm import Dtm
    from cdtm_graph.geometry import make_pose
    from cdtm_graph.graph import FramePairObservations, GraphSettings, cdtm_factors
    from cdtm_graph.scenario import DOWNWARD_BODY_T_CAM
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
