"""Graph builders: pairing of track observations, shared DTM error, priors."""

from __future__ import annotations

import numpy as np

from cdtm_graph.camera import PinholeCamera
from cdtm_graph.flightlog import Tracks
from cdtm_graph.graph import frame_pair_observations, mean_pairs_per_track


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
    assert mean_pairs_per_track(pairs) == 1.5  # 3 pairs over 2 tracks with pairs
