"""The visual front-end: accuracy against the renderer's truth; each check with its fault."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from cdtm_graph.camera import PinholeCamera
from cdtm_graph.errors import CdtmError
from cdtm_graph.frontend import (
    FeatureTracker,
    ImageError,
    MatchStatus,
    TrackerSettings,
    TrackingReport,
    camera_rotations_from_imu,
    track_log,
)
from cdtm_graph.frontend import tracker as tracker_module
from cdtm_graph.frontend.tracker import Replenishment
from cdtm_graph.frontend.two_view import (
    FitMethod,
    _inliers,
    epipolar_residual_rad,
    fit_essential,
    fit_translation_given_rotation,
    triangulate_depths,
)
from cdtm_graph.geometry import so3_exp, so3_log
from cdtm_graph.sim.render import (
    ProceduralTexture,
    Renderer,
    RenderSettings,
    render_flight,
    true_correspondences,
)
from cdtm_graph.sim.simulate import SimulationSettings, simulate
from cdtm_graph.sim.tracking_truth import WRONG_MATCH_PX, match_errors

#: The small flight of these tests: the paper's geometry (1000 m, 200 m/s, 60 deg, 1 fps)
#: at 320x240, so the flight-direction flow is ~55 px per frame.
FLIGHT = SimulationSettings(frames=8, resolution_px=(320, 240))
#: Tracker accuracy on clean renders (measured ~0.2 px median, ~0.6 px p95 at 640x480).
MEDIAN_PX = 0.35
P95_PX = 1.0
#: Gyro-predicted rotation between frames against the truth (gyro noise and bias over 1 s).
ROTATION_TOL_DEG = 0.05


@pytest.fixture(scope="module")
def flight(seed):
    result = simulate(dataclasses.replace(FLIGHT, seed=seed))
    clean = render_flight(result, RenderSettings(seed=seed))
    return result, clean.images


@pytest.fixture(scope="module")
def tracked(flight):
    result, images = flight
    return track_log(result.log, images=images)


def _camera(result):
    return result.log.config.camera.camera


def test_tracked_pixels_match_the_renderers_truth(flight, tracked):
    result, _ = flight
    errors = match_errors(result.terrain, _camera(result), result.world_T_cam, tracked.frames)
    figures = errors.to_dict()
    assert figures["pair_error_median_px"] < MEDIAN_PX, figures
    assert figures["pair_error_p95_px"] < P95_PX, figures
    assert figures["wrong_fraction_after_verification"] < 0.01, figures
    assert figures["matches_kept"] > 100 * (FLIGHT.frames - 1)


def test_tracking_through_a_distorted_lens(seed, rng, flight):
    """Images through a strong radtan lens: prediction and verification go through the
    camera model, the tracks stay as accurate (against the distorted truth)."""
    result, _ = flight
    plain = _camera(result)
    lens = PinholeCamera(plain.width, plain.height, plain.fx, plain.fy, plain.cx, plain.cy,
                         (-0.25, 0.06, 0.001, -0.001))
    renderer = Renderer(result.terrain, lens, ProceduralTexture(seed=seed))
    frames = 4
    images = [renderer.render(result.world_T_cam[k], rng=rng) for k in range(frames)]
    rotations = camera_rotations_from_imu(result.log)
    tracker = FeatureTracker(lens)
    outputs = [tracker.track(images[k], rotations[k]) for k in range(frames)]
    figures = match_errors(result.terrain, lens, result.world_T_cam[:frames], outputs).to_dict()
    assert figures["pair_error_median_px"] < MEDIAN_PX, figures
    assert figures["wrong_fraction_after_verification"] < 0.01, figures
    assert all(o.fit is not None and o.fit.method is FitMethod.ROTATION_PRIOR
               for o in outputs[1:])
    assert min(o.counts()["tracked"] for o in outputs[1:]) > 100


def test_gyro_rotation_between_frames_matches_the_cameras(flight):
    result, _ = flight
    rotations = camera_rotations_from_imu(result.log)
    assert rotations[0] is None
    for k in range(1, FLIGHT.frames):
        truth = result.world_T_cam[k - 1][:3, :3].T @ result.world_T_cam[k][:3, :3]
        assert np.degrees(np.linalg.norm(so3_log(rotations[k].T @ truth))) < ROTATION_TOL_DEG


def test_tracks_csv_rows_follow_the_format(tracked):
    tracks = tracked.tracks
    assert np.all(np.diff(tracks.frame) >= 0)
    key = tracks.frame * (tracks.track_id.max() + 1) + tracks.track_id
    assert np.unique(key).size == key.size  # each track at most once per frame
    ids, counts = np.unique(tracks.track_id, return_counts=True)
    np.testing.assert_array_equal(ids, np.arange(ids.size))  # renumbered, no gaps
    assert counts.min() >= 2  # single sightings dropped
    report = tracked.report
    assert report.n_tracks == ids.size and report.track_lengths.sum() == len(tracks)
    np.testing.assert_array_equal(report.features_per_frame,
                                  np.bincount(tracks.frame, minlength=FLIGHT.frames))
    assert report.pairs_per_frame.min() > 100
    assert report.fits["rotation_prior"] == FLIGHT.frames - 1


def test_features_are_spread_over_the_image_and_replenished(flight, tracked):
    settings = TrackerSettings()
    camera = _camera(flight[0])
    per_cell = int(np.ceil(settings.max_features / settings.cells))
    for out in tracked.frames:
        assert out.track_id.size == settings.max_features  # topped up every frame
        col = np.minimum((out.uv_px[:, 0] + 0.5) // (camera.width / settings.grid_cols),
                         settings.grid_cols - 1)
        row = np.minimum((out.uv_px[:, 1] + 0.5) // (camera.height / settings.grid_rows),
                         settings.grid_rows - 1)
        occupancy = np.bincount((row * settings.grid_cols + col).astype(int),
                                minlength=settings.cells)
        # Cells hold features everywhere but (after the first frame) in the column the
        # ground leaves through: corners there would not reach the next frame. None holds
        # many more than its share (tracked features drift in: new ones never go there).
        empty = occupancy.reshape(settings.grid_rows, settings.grid_cols) == 0
        assert not empty.any() if out.frame == 0 else not empty[:, 1:].any()
        assert occupancy.max() <= 2 * per_cell


def test_exposure_changes_do_not_hurt_tracking(seed, flight):
    result, _ = flight
    jittered = render_flight(result, RenderSettings(seed=seed, exposure_jitter=0.1,
                                                    motion_blur_px=1.0)).images
    # and a harsher one: every other frame 25 % darker
    harsh = [np.clip(im * (0.75 if k % 2 else 1.0), 0, 255).astype(np.uint8)
             for k, im in enumerate(flight[1])]
    for images in (jittered, harsh):
        out = track_log(result.log, images=images)
        figures = match_errors(result.terrain, _camera(result), result.world_T_cam,
                               out.frames).to_dict()
        assert figures["pair_error_median_px"] < MEDIAN_PX, figures
        assert out.report.pairs_per_frame.min() > 100


class _FaultyOpticalFlow:
    """cv2 with a Lucas-Kanade that moves some forward results (the fault), and a backward
    pass that either tracks for real or returns the start exactly (hiding the fault from
    the forward-backward check, so only the epipolar check can find it)."""

    def __init__(self, moved: np.ndarray, offset_px: np.ndarray, hide_from_backward: bool):
        self.moved, self.offset_px, self.hide = moved, offset_px, hide_from_backward
        self.calls = 0

    def __getattr__(self, name):
        return getattr(cv2, name)

    def calcOpticalFlowPyrLK(self, prev, nxt, p0, p1, **kwargs):
        self.calls += 1
        forward = self.calls % 2 == 1
        if not forward and self.hide:
            return p1.copy(), np.ones((len(p0), 1), np.uint8), np.zeros((len(p0), 1), np.float32)
        out, status, err = cv2.calcOpticalFlowPyrLK(prev, nxt, p0, p1, **kwargs)
        if forward:
            out = out.copy()
            out.reshape(-1, 2)[self.moved[: len(p0)]] += self.offset_px.astype(np.float32)
        return out, status, err


@pytest.mark.parametrize("hide_from_backward, caught_as", [
    (False, MatchStatus.FORWARD_BACKWARD), (True, MatchStatus.EPIPOLAR)])
def test_each_check_catches_the_wrong_matches_it_guards_against(rng, flight, monkeypatch,
                                                                hide_from_backward, caught_as):
    """15 % of the matches moved by 4 px across the flight direction (off their epipolar
    lines): the forward-backward check catches them; when they pass it, the epipolar check."""
    result, images = flight
    moved = rng.random(1000) < 0.15
    fault = _FaultyOpticalFlow(moved, np.array([0.0, 4.0]), hide_from_backward)
    tracker = FeatureTracker(_camera(result))
    rotations = camera_rotations_from_imu(result.log)
    tracker.track(images[0])
    monkeypatch.setattr(tracker_module, "cv2", fault)
    out = tracker.track(images[1], rotations[1])
    n = out.prev_track_id.size
    # (those leaving the image end for that reason first)
    faulty = moved[:n] & ~np.isin(out.status, [MatchStatus.LEFT_IMAGE, MatchStatus.LOST])
    assert faulty.sum() > 10
    caught = out.status == caught_as
    assert caught[faulty].mean() > 0.95
    rest = ~moved[:n] & ~np.isin(out.status, [MatchStatus.LEFT_IMAGE, MatchStatus.LOST])
    assert (out.status[rest] == MatchStatus.TRACKED).mean() > 0.95  # the rest are kept


class _BackwardOverAllPoints:
    """cv2 whose Lucas-Kanade also tracks back every point of each forward pass (what the
    tracker did before issue 22) and keeps it, beside the calls the tracker makes."""

    def __init__(self):
        self.forward_points, self.backward_points, self.frames = [], [], []
        self.images: tuple = ()

    def __getattr__(self, name):
        return getattr(cv2, name)

    def calcOpticalFlowPyrLK(self, prev, nxt, p0, p1, **kwargs):
        start = p1.copy()
        out = cv2.calcOpticalFlowPyrLK(prev, nxt, p0, p1, **kwargs)
        if self.frames and prev is self.images[1] and nxt is self.images[0]:  # backward
            self.backward_points.append(len(p0))
        else:
            self.images = (prev, nxt)
            self.forward_points.append(len(p0))
            matched, status, _ = out
            back, back_status, _ = cv2.calcOpticalFlowPyrLK(nxt, prev, matched, p0.copy(),
                                                            **kwargs)
            self.frames.append((p0.reshape(-1, 2), start.reshape(-1, 2),
                                matched.reshape(-1, 2), status.ravel(), back.reshape(-1, 2),
                                back_status.ravel()))
        return out


def test_the_backward_pass_skips_only_what_cannot_change_a_status(flight, monkeypatch):
    """Issue 22: the backward pass tracks back only what the forward pass kept, and every
    feature ends, and is matched, as when all were tracked back (the rule before
    verification applied to a backward pass over every point). Catches tracking back
    everything again (the point counts) and skipping a match the backward pass decides,
    e.g. one leaving the image (its status or matched pixel)."""
    result, images = flight
    rotations = camera_rotations_from_imu(result.log)
    lk = _BackwardOverAllPoints()
    tracker = FeatureTracker(_camera(result))
    s = tracker.settings
    monkeypatch.setattr(tracker_module, "cv2", lk)
    for k, image in enumerate(images):
        out = tracker.track(image, rotations[k])
        if k == 0:
            continue
        p0, guess, matched, status, back, back_status = lk.frames[-1]
        lost = (status == 0) | (back_status == 0) | ~np.isfinite(matched).all(axis=1)
        before = np.full(p0.shape[0], MatchStatus.TRACKED)
        before[~(np.linalg.norm(back - p0, axis=1) <= s.forward_backward_px)] = \
            MatchStatus.FORWARD_BACKWARD
        before[lost] = MatchStatus.LOST
        before[~tracker._inside(np.where(lost[:, None], guess, matched))] = \
            MatchStatus.LEFT_IMAGE
        verified = np.where(out.status == MatchStatus.EPIPOLAR, MatchStatus.TRACKED, out.status)
        np.testing.assert_array_equal(verified, before, err_msg=f"frame {k}")
        np.testing.assert_array_equal(out.matched_uv_px,
                                      np.where(lost[:, None], np.nan, matched.astype(float)))
    # features leave the image every frame (~55 px of flow): fewer are tracked back
    assert sum(lk.backward_points) < 0.9 * sum(lk.forward_points)


def test_replenishment_looks_only_where_the_need_reaches(flight, monkeypatch):
    """Issue 22, ``Replenishment.NEEDED_CELLS``: corners are looked for cell by cell, only
    in the cells the fill level of the need reaches (about half the cells here), and the
    corners chosen are nearly all those the whole image gives (the rest differ next to
    cells not looked at).
    Catches looking at every open cell again (the area), and a cell read at the wrong
    place or its corners put back wrong (the agreement)."""
    result, images = flight
    rotations = camera_rotations_from_imu(result.log)
    cells = TrackerSettings(replenishment=Replenishment.NEEDED_CELLS)
    whole = dataclasses.replace(cells, replenishment=Replenishment.WHOLE_IMAGE)
    tracker = FeatureTracker(_camera(result), cells)
    looked_px = []

    class _Counting:
        def __getattr__(self, name):
            return getattr(cv2, name)

        def goodFeaturesToTrackWithQuality(self, image, *args, **kwargs):
            looked_px.append(image.size)
            return cv2.goodFeaturesToTrackWithQuality(image, *args, **kwargs)

    agree, total, cells_looked = 0, 0, []
    for k, image in enumerate(images[:-1]):
        tracker.track(image, rotations[k])
        gray = tracker._normalized(images[k + 1])
        live = tracker._uv.astype(float)[: tracker.settings.max_features - 40]  # need 40
        monkeypatch.setattr(tracker_module, "cv2", _Counting())
        looked_px.clear()
        new = tracker._detect(gray, live)
        monkeypatch.setattr(tracker_module, "cv2", cv2)
        tracker.settings = whole
        reference = tracker._detect(gray, live)
        tracker.settings = cells
        assert new.shape[0] == reference.shape[0] == 40
        agree += sum(np.any(np.all(reference == q, axis=1)) for q in new)
        total += 40
        cells_looked.append(len(looked_px) / tracker.settings.cells)
    assert agree / total > 0.9, agree / total
    assert np.median(cells_looked) < 0.6, cells_looked


def test_an_unrelated_image_keeps_no_wrong_matches(flight):
    """A frame of other ground (a camera glitch): nothing survives the checks, and
    tracking resumes from fresh corners."""
    result, images = flight
    other = np.ascontiguousarray(images[5][::-1, ::-1])
    tracker = FeatureTracker(_camera(result))
    tracker.track(images[0])
    glitch = tracker.track(other)
    assert (glitch.status == MatchStatus.TRACKED).mean() < 0.05
    assert glitch.track_id.size == TrackerSettings().max_features  # replenished


def test_a_wrong_rotation_prior_falls_back_to_the_five_point_fit(flight):
    result, images = flight
    rotations = camera_rotations_from_imu(result.log)
    wrong = rotations[1] @ so3_exp(np.radians([0.0, 0.0, 3.0]))  # 3 deg yaw error
    tracker = FeatureTracker(_camera(result))
    tracker.track(images[0])
    out = tracker.track(images[1], wrong)
    assert out.fit is not None and out.fit.method is FitMethod.ESSENTIAL
    assert (out.status == MatchStatus.TRACKED).sum() > 100


def test_image_types(flight):
    result, images = flight
    camera = _camera(result)
    tracker = FeatureTracker(camera)
    with pytest.raises(ImageError, match="240 rows x 320 columns"):
        tracker.track(images[0][:100])
    with pytest.raises(ImageError, match="float"):
        tracker.track(images[0].astype(np.float32))
    # colour and 16-bit images of the same scene track like the 8-bit grey ones
    colour = [cv2.cvtColor(im, cv2.COLOR_GRAY2BGR) for im in images[:2]]
    deep = [im.astype(np.uint16) * 257 for im in images[:2]]
    reference = FeatureTracker(camera)
    expected = [reference.track(im) for im in images[:2]][1]
    for pair in (colour, deep):
        t = FeatureTracker(camera)
        got = [t.track(im) for im in pair][1]
        np.testing.assert_array_equal(got.track_id, expected.track_id)
        np.testing.assert_allclose(got.uv_px, expected.uv_px, atol=0.05)
    with pytest.raises(ValueError, match="shape"):
        FeatureTracker(camera).track(images[0], np.eye(2))


@pytest.mark.parametrize("bad", [{"window_px": 20}, {"max_features": 0},
                                 {"forward_backward_px": -1.0}, {"ransac_confidence": 1.0}])
def test_tracker_settings_reject_bad_values(bad):
    with pytest.raises(CdtmError):
        TrackerSettings(**bad)


def test_track_log_needs_an_image_per_frame(flight):
    result, images = flight
    with pytest.raises(CdtmError, match="frame 0 has no image"):
        track_log(result.log)  # the simulated log names no images
    with pytest.raises(CdtmError, match="one per frame"):
        track_log(result.log, images=images[:3])


# -- epipolar geometry ----------------------------------------------------------------


def _two_views(rng: np.random.Generator, n: int = 150):
    """Rays of random ground points seen from two cameras 200 m apart at ~1000 m."""
    points = np.column_stack([rng.uniform(-500, 500, n), rng.uniform(-400, 400, n),
                              rng.uniform(800, 1200, n)])  # in camera a
    a_R_b = so3_exp(np.radians([1.0, -2.0, 3.0]))
    a_t_b = np.array([200.0, 10.0, -5.0])
    in_b = (points - a_t_b) @ a_R_b  # b_R_a (p - t)
    return points / points[:, 2:], in_b / in_b[:, 2:], a_R_b, a_t_b


def test_noiseless_two_view_geometry_is_recovered(rng):
    rays_a, rays_b, a_R_b, a_t_b = _two_views(rng)
    direction = a_t_b / np.linalg.norm(a_t_b)
    assert np.abs(epipolar_residual_rad(rays_a, rays_b, a_R_b, a_t_b)).max() < 1e-12
    fit = fit_translation_given_rotation(rays_a, rays_b, a_R_b, 1e-4, rng)
    assert fit.inliers.all()
    np.testing.assert_allclose(fit.a_t_b, direction, atol=1e-9)
    free = fit_essential(rays_a, rays_b, 1e-4)
    assert free.inliers.all()
    np.testing.assert_allclose(free.a_t_b, direction, atol=1e-6)
    assert np.linalg.norm(so3_log(free.a_R_b.T @ a_R_b)) < 1e-6
    depth_a, depth_b = triangulate_depths(rays_a, rays_b, a_R_b, a_t_b)
    np.testing.assert_allclose(rays_a * depth_a[:, None],
                               (rays_b * depth_b[:, None]) @ a_R_b.T + a_t_b, atol=1e-6)


def test_inlier_scoring_is_the_textbook_formulas_to_the_bit(rng):
    """The scoring shares unit rays and normals between hypotheses and writes the cross
    products out (issue 22): residuals, depths and inliers are the same bits as the
    formulas written plainly with np.cross and np.linalg.norm. Catches any change of the
    arithmetic (a norm by einsum, rays normalized once less, a cross product reordered)."""
    rays_a, rays_b, a_R_b, a_t_b = _two_views(rng, 200)
    rays_b = rays_b + rng.normal(0.0, 2e-3, rays_b.shape)  # some off their planes
    rays_b[::7] = rays_a[::7]  # some without parallax ...
    rays_b[1::7] = 2 * rays_a[1::7] - rays_b[1::7]  # ... some moving backwards: behind
    threshold = 1e-3

    def unit(v):
        norm = np.linalg.norm(v, axis=-1, keepdims=True)
        return v / np.where(norm > 0, norm, 1.0)

    fa, fb, t = unit(rays_a), unit(rays_b @ a_R_b.T), unit(a_t_b)
    det = np.abs(np.einsum("ij,ij->i", np.cross(fb, fa), np.broadcast_to(t, fa.shape)))
    residual = det / np.minimum(np.linalg.norm(np.cross(t, fa), axis=1),
                                np.linalg.norm(np.cross(t, fb), axis=1))
    raw_b = rays_b @ a_R_b.T
    aa, bb = np.einsum("ij,ij->i", rays_a, rays_a), np.einsum("ij,ij->i", raw_b, raw_b)
    ab = np.einsum("ij,ij->i", rays_a, raw_b)
    ta, tb, d = rays_a @ a_t_b, raw_b @ a_t_b, aa * bb - ab * ab
    la, lb = (bb * ta - ab * tb) / d, (ab * ta - aa * tb) / d
    behind = (np.linalg.norm(np.cross(fa, fb), axis=1) > 3 * threshold) & ~((la > 0) & (lb > 0))

    np.testing.assert_array_equal(epipolar_residual_rad(rays_a, rays_b, a_R_b, a_t_b), residual)
    depth_a, depth_b = triangulate_depths(rays_a, rays_b, a_R_b, a_t_b)
    np.testing.assert_array_equal(depth_a, la)
    np.testing.assert_array_equal(depth_b, lb)
    got_residual, got_inliers = _inliers(rays_a, rays_b, a_R_b, a_t_b, threshold)
    np.testing.assert_array_equal(got_residual, residual)
    np.testing.assert_array_equal(got_inliers, (residual <= threshold) & ~behind)
    assert 0 < behind.sum() and 0 < (residual > threshold).sum()


@pytest.mark.parametrize("fitter", ["rotation_prior", "essential"])
def test_ransac_removes_matches_off_their_epipolar_lines(rng, fitter):
    rays_a, rays_b, a_R_b, a_t_b = _two_views(rng, 200)
    f_px = 550.0
    noisy = rays_b.copy()
    noisy[:, :2] += rng.normal(0, 0.2 / f_px, (200, 2))
    wrong = rng.random(200) < 0.3
    # 3-30 px across the (nearly horizontal) epipolar lines
    noisy[wrong, 1] += rng.choice([-1, 1], wrong.sum()) * rng.uniform(3, 30, wrong.sum()) / f_px
    threshold = 1.0 / f_px
    fit = (fit_translation_given_rotation(rays_a, noisy, a_R_b, threshold, rng)
           if fitter == "rotation_prior" else fit_essential(rays_a, noisy, threshold))
    assert not fit.inliers[wrong].any()
    assert fit.inliers[~wrong].mean() > 0.97


def test_too_few_matches_fit_nothing_and_keep_all(rng):
    rays_a, rays_b, a_R_b, _ = _two_views(rng, 5)
    fit = fit_translation_given_rotation(rays_a, rays_b, a_R_b, 1e-3, rng)
    assert fit.method is FitMethod.NONE and fit.inliers.all()


def test_true_correspondences_of_a_rendered_pair_reproject(rng, flight):
    """The truth the accuracy tests use: frame k's truth, cast back, is frame k-1's pixel."""
    result, _ = flight
    camera = _camera(result)
    uv = np.column_stack([rng.uniform(20, 300, 50), rng.uniform(20, 220, 50)])
    forward, seen = true_correspondences(result.terrain, camera, result.world_T_cam[0],
                                         result.world_T_cam[1], uv)
    back, seen_back = true_correspondences(result.terrain, camera, result.world_T_cam[1],
                                           result.world_T_cam[0], forward[seen])
    assert seen.sum() > 30 and seen_back.all()
    np.testing.assert_allclose(back, uv[seen], atol=1e-6)
    assert WRONG_MATCH_PX > 4 * MEDIAN_PX


def test_pure_rotation_keeps_every_match(rng):
    """Hovering (no translation to see): the rotation-prior fit keeps everything."""
    rays_a, _, a_R_b, _ = _two_views(rng)
    rays_b = rays_a @ a_R_b  # pure rotation
    fit = fit_translation_given_rotation(rays_a, rays_b, a_R_b, 1e-4, rng)
    assert fit.inliers.all()


def test_tracking_is_reproducible(flight, tracked):
    again = track_log(flight[0].log, images=flight[1])
    np.testing.assert_array_equal(again.tracks.track_id, tracked.tracks.track_id)
    np.testing.assert_array_equal(again.tracks.uv_px, tracked.tracks.uv_px)


def _report(pairs: list[int], epipolar: list[int]) -> TrackingReport:
    k = len(pairs) + 1
    zeros = np.zeros(k - 1, np.int64)
    return TrackingReport(
        n_frames=k, n_tracks=0, n_single_sightings=0, features_per_frame=np.zeros(k, np.int64),
        pairs_per_frame=np.array(pairs), track_lengths=np.zeros(0, np.int64), rejected={},
        fits={}, imu_rotations=0, seconds_per_frame=0.0,
        ended_per_pair={"lost": zeros + 1, "forward_backward": zeros, "left_image": zeros,
                        "epipolar": np.array(epipolar)},
        weak_pair_features=50)


def test_weak_pairs_warning_is_one_line_naming_the_first_and_counting_the_rest():
    """12 weak pairs of 14: the first 8 named with their main reason, 4 more counted, one
    line; none weak: no warning. Catches a line per pair, an off-by-one at the bound
    (exactly 50 is not weak), a reason taken from the wrong pair."""
    pairs = [10, 50, 49] + [0] * 10 + [120]
    epipolar = [5, 0, 30] + [40 + i for i in range(10)] + [0]
    report = _report(pairs, epipolar)
    np.testing.assert_array_equal(report.weak_pairs(), [0] + list(range(2, 13)))
    line = report.weak_pairs_warning()
    assert line is not None and "\n" not in line
    assert line.startswith("12 of 14 frame pairs keep fewer than 50 features: 0-1 (10 kept, "
                           "5 ended epipolar), 2-3 (49 kept, 30 ended epipolar), 3-4 (0 kept, "
                           "40 ended epipolar)")
    assert "8-9 (0 kept, 45 ended epipolar) and 4 more; expected at least 50" in line
    assert "1-2" not in line and "9-10" not in line
    assert _report([50, 200], [0, 0]).weak_pairs_warning() is None
    assert report.to_dict()["weak_pairs"]["pairs"][:2] == [[0, 1], [2, 3]]
