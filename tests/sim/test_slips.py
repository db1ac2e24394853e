"""Tracker slips and map detail: each fault is what its docstring says, on a small flight."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cdtm_graph.sim.faults import MismatchKind, TerrainMismatch
from cdtm_graph.sim.map_detail import DetailShape, MapDetail
from cdtm_graph.sim.simulate import SimulationSettings, simulate, simulate_flight
from cdtm_graph.sim.slips import (
    DRIFT_PX_PER_FRAME,
    JUMP_PX,
    RANGE_FACTOR,
    _closest_approach,
    _sightings,
    with_cluster_drift,
    with_epipolar_wrong_matches,
    with_track_drift,
    with_track_jumps,
)

#: A small flight of the nominal geometry: 8 frames, 60 features.
SMALL = SimulationSettings(frames=8, n_features=60)


@pytest.fixture(scope="module")
def flight():
    return simulate_flight(dataclasses.replace(SMALL, seed=11))


def _cameras(log):
    return log.groundtruth.interpolate(log.frames.t_ns).world_T_body @ log.config.camera.body_T_cam


def _rays(log, rows):
    cams = _cameras(log)[log.tracks.frame[rows]]
    q = log.config.camera.camera.pixels_to_rays(log.tracks.uv_px[rows])
    return cams[:, :3, 3], np.einsum("nij,nj->ni", cams[:, :3, :3], q)


def _miss_m(origins, rays, point):
    """Distance of a point from each ray (m)."""
    d = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    w = point - origins
    return np.linalg.norm(w - np.sum(w * d, axis=1, keepdims=True) * d, axis=1)


def _key(tracks):
    return {(int(f), int(t)): uv for f, t, uv in zip(tracks.frame, tracks.track_id, tracks.uv_px)}


def test_a_jumped_track_follows_one_other_ground_point(flight, rng):
    """Catches a jump that moves only the one sighting (the track would not follow a new
    point: its later rays miss the jump's point) or moves the sightings before it."""
    log, dtm = flight
    out, changed = with_track_jumps(log, dtm, 0.5, rng)
    before = _key(log.tracks)
    jumped = 0
    for track, rows in _sightings(out.tracks).items():
        moved = changed[rows]
        if not moved.any():
            continue
        jumped += 1
        first = int(np.argmax(moved))
        assert moved[first:].all() and first >= 1  # the first sighting stays
        for row in rows[:first]:
            np.testing.assert_array_equal(out.tracks.uv_px[row],
                                          before[(int(out.tracks.frame[row]), track)])
        jump = out.tracks.uv_px[rows[first]] - before[(int(out.tracks.frame[rows[first]]),
                                                       track)]
        assert JUMP_PX[0] - 1e-6 <= np.linalg.norm(jump) <= JUMP_PX[1] + 1e-6
        origins, rays = _rays(out, rows[first:])
        hit = dtm.raycast(origins[0], rays[0]).point[0]
        assert np.max(_miss_m(origins, rays, hit)) < 0.01
    n_long = sum(1 for rows in _sightings(log.tracks).values() if rows.size >= 3)
    assert abs(jumped - 0.5 * n_long) < 4 * np.sqrt(0.25 * n_long) + 0.05 * n_long


def test_a_drifting_track_moves_a_fixed_rate_in_a_fixed_direction(flight, rng):
    """Catches a drift that does not add up frame by frame (a constant offset, a random
    walk) or leaves the rate band."""
    log, _ = flight
    out, changed = with_track_drift(log, 0.4, rng)
    before = _key(log.tracks)
    drifting = 0
    for track, rows in _sightings(out.tracks).items():
        if not changed[rows].any():
            continue
        drifting += 1
        moved = np.array([out.tracks.uv_px[r] - before[(int(out.tracks.frame[r]), track)]
                          for r in rows])
        start = int(np.argmax(changed[rows])) - 1
        frames = out.tracks.frame[rows] - out.tracks.frame[rows[start]]
        velocity = moved[-1] / frames[-1]
        rate = np.linalg.norm(velocity)
        assert DRIFT_PX_PER_FRAME[0] - 1e-9 <= rate <= DRIFT_PX_PER_FRAME[1] + 1e-9
        np.testing.assert_allclose(moved[start:], frames[start:, None] * velocity, atol=1e-9)
    assert drifting > 0


def test_a_drifting_cluster_moves_together(flight, rng):
    """Catches a cluster whose tracks drift each their own way (then it is not coherent:
    the neighbourhood views would see it)."""
    log, _ = flight
    out, changed = with_cluster_drift(log, rng, radius_px=150.0)
    before = _key(log.tracks)
    velocities = []
    for track, rows in _sightings(out.tracks).items():
        if not changed[rows].any():
            continue
        last = rows[-1]
        frames = out.tracks.frame[last] - out.tracks.frame[rows[0]]
        velocities.append((out.tracks.uv_px[last]
                           - before[(int(out.tracks.frame[last]), track)]) / frames)
    assert len(velocities) >= 3
    np.testing.assert_allclose(velocities, np.broadcast_to(velocities[0], (len(velocities), 2)),
                               atol=1e-9)
    assert np.linalg.norm(velocities[0]) == pytest.approx(1.0)


def test_a_wrong_match_on_the_epipolar_line_keeps_the_two_view_geometry(flight, rng):
    """Catches a wrong match off the epipolar line (the epipolar check would then reject
    it: not this fault) or at the true range (then it would not be wrong)."""
    log, _ = flight
    out, changed = with_epipolar_wrong_matches(log, 0.3, rng)
    assert changed.sum() > 20
    keep = _key(log.tracks)
    for track, rows in _sightings(out.tracks).items():
        for before, at in zip(rows[:-1], rows[1:]):
            if not changed[at] or changed[before]:  # (a wrong one after a wrong one: no
                continue                                # true geometry to keep)
            (o_a, o_b), (r_a, r_b) = _rays(out, np.array([before, at]))
            # the wrong pixel's ray meets the earlier ray (the same epipolar plane)...
            normal = np.cross(r_a, o_b - o_a)
            assert abs(normal @ r_b) / (np.linalg.norm(normal) * np.linalg.norm(r_b)) < 1e-7
            # ...at another range than the true pixel's
            true_uv = keep[(int(out.tracks.frame[at]), track)]
            q_true = log.config.camera.camera.pixels_to_rays(true_uv[None])[0]
            r_true = _cameras(log)[out.tracks.frame[at], :3, :3] @ q_true
            factor = (_closest_approach(o_a, r_a, o_b, r_b)
                      / _closest_approach(o_a, r_a, o_b, r_true))
            assert RANGE_FACTOR[0] - 1e-6 <= max(factor, 1 / factor) <= RANGE_FACTOR[1] + 1e-6


@pytest.mark.parametrize("shape", list(DetailShape))
def test_map_detail_has_its_rms_and_its_correlation_length(shape):
    """Catches detail not scaled to its rms or not correlated over its wavelengths (white
    noise would be: its correlation at 10 m is ~0)."""
    detail = MapDetail(shape, 3.0, (40.0, 300.0), 40 if shape is DetailShape.BUMPS else 24,
                       seed=3)
    x = np.arange(0.0, 3000.0, 2.0)
    h = detail.heights(x, x)
    assert np.sqrt(np.mean(h**2)) == pytest.approx(3.0, rel=1e-9)
    lag = 2  # 4 m (2026-11-27, seed 3: waves 0.97, ridges 0.86, bumps 1.00)
    near = np.corrcoef(h[:, :-lag].ravel(), h[:, lag:].ravel())[0, 1]
    far_lag = 500  # 1000 m, beyond the longest wavelength (-0.24, -0.11, -0.05)
    far = np.corrcoef(h[:, :-far_lag].ravel(), h[:, far_lag:].ravel())[0, 1]
    assert near > 0.8
    assert abs(far) < 0.3


def test_map_detail_and_a_hill_change_the_truth_not_the_map():
    """Catches detail added to the DTM too (then it is no map error) or not at all."""
    plain = simulate(dataclasses.replace(SMALL, seed=5))
    waves = simulate(dataclasses.replace(SMALL, seed=5, map_detail=MapDetail(rms_m=3.0)))
    hill = simulate(dataclasses.replace(SMALL, seed=5, terrain_mismatch=TerrainMismatch(
        MismatchKind.HILL, depth_m=15.0, radius_m=1000.0, at_s=3.0)))
    np.testing.assert_array_equal(waves.dtm.elevation, plain.dtm.elevation)
    np.testing.assert_array_equal(hill.dtm.elevation, plain.dtm.elevation)
    def terrain(r):
        return r.log.config.extra["simulation"]["terrain"]

    base = terrain(plain)["dtm_height_error_rms_m"]
    assert terrain(waves)["dtm_height_error_rms_with_detail_m"] > np.hypot(base, 2.5)
    assert terrain(hill)["dtm_height_error_rms_with_mismatch_m"] > base
