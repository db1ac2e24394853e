"""The tracker on real aerial frames (issue 24): 30 CLIF 2007 frames of a city from ~2.8 km,
banked 34 deg, against a bare OpenCV loop computed here as the reference.

The frames (``../shared/data/clif2007``, beside the repository; its README gives the source
and the POS columns) come with no calibration: the focal length is a guess (2200 px, the
scene's scale), the principal point the image centre. Over a near-planar scene ~80
baselines away the five-point pose is barely determined; before the fix the tracker kept a
median of 2 features per pair where the bare loop keeps ~173.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cdtm_graph.camera import PinholeCamera
from cdtm_graph.cli import main
from cdtm_graph.frontend import FeatureTracker, load_image
from cdtm_graph.frontend.two_view import FitMethod

CLIF = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "clif2007"

pytestmark = pytest.mark.skipif(
    not (CLIF / "jpg").is_dir(),
    reason=f"{CLIF} is absent (the real CLIF 2007 frames the CI checkout has beside the "
           "repository)")

#: The guessed focal length (px) and the range a user's guess may be off by.
FOCAL_PX = 2200.0
FOCAL_RANGE_PX = (1100.0, 4400.0)
#: The issue's bounds: per pair at least this share of the bare loop's median ...
SHARE_OF_BARE_MEDIAN = 0.8
#: ... and no pair under WEAK where the bare loop keeps more than STRONG.
WEAK, STRONG = 50, 100
#: Regression bound near the measured figure: the fewest features a pair kept, with and
#: without the rotation prior, at 1100-4400 px: 177-184 (2026-11-27; 0-2 in most pairs
#: before the fix).
MIN_PAIR_FEATURES = 165
#: The frames hold few wrong matches (the bare loop's RANSAC drops ~1 of 174 a pair): the
#: most any pair lost to the epipolar check, over the same runs, was 8 (2026-11-27).
MAX_EPIPOLAR_PER_PAIR = 10


def _pos() -> np.ndarray:
    """(30, 14) the POS rows (heading, pitch, roll deg, lat, lon, alt, GPS s, week, ...)."""
    return np.array([np.loadtxt(p, delimiter=",") for p in sorted((CLIF / "pos").glob("*.txt"))])


@pytest.fixture(scope="module")
def frames() -> tuple[list[Path], list[np.ndarray], np.ndarray]:
    paths = sorted((CLIF / "jpg").glob("*.jpg"))
    return paths, [load_image(p) for p in paths], _pos()


def _camera(images: list[np.ndarray], focal_px: float) -> PinholeCamera:
    h, w = images[0].shape[:2]
    return PinholeCamera(w, h, focal_px, focal_px, (w - 1) / 2, (h - 1) / 2)


def bare_loop(images: list[np.ndarray], camera: PinholeCamera) -> np.ndarray:
    """(K-1,) RANSAC inliers per frame pair of a textbook loop: Shi-Tomasi corners (200),
    pyramidal Lucas-Kanade 21x21 over 5 levels forward and back (< 1 px), the essential
    matrix by RANSAC at 1 px, topped up to 200 when fewer than 150 remain."""
    cv2.setRNGSeed(0)
    K = np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1.0]])
    lk = {"winSize": (21, 21), "maxLevel": 5}
    grays = [im if im.ndim == 2 else cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) for im in images]
    pts = cv2.goodFeaturesToTrack(grays[0], 200, 0.01, 10)
    counts = []
    for prev, cur in zip(grays[:-1], grays[1:]):
        nxt, st, _ = cv2.calcOpticalFlowPyrLK(prev, cur, pts, None, **lk)
        back, st_back, _ = cv2.calcOpticalFlowPyrLK(cur, prev, nxt, None, **lk)
        fb = np.linalg.norm((back - pts).reshape(-1, 2), axis=1)
        good = (st.ravel() == 1) & (st_back.ravel() == 1) & (fb < 1.0)
        _, mask = cv2.findEssentialMat(pts[good], nxt[good], K, cv2.RANSAC, 0.999, 1.0)
        inliers = mask.ravel() == 1
        counts.append(int(inliers.sum()))
        pts = nxt[good][inliers]
        if len(pts) < 150:
            keep_out = np.full(cur.shape, 255, np.uint8)
            for u, v in pts.reshape(-1, 2):
                cv2.circle(keep_out, (int(u), int(v)), 10, 0, -1)
            new = cv2.goodFeaturesToTrack(cur, 200 - len(pts), 0.01, 10, mask=keep_out)
            if new is not None:
                pts = np.concatenate([pts, new]).astype(np.float32)
    return np.array(counts)


@pytest.fixture(scope="module")
def bare_counts(frames) -> np.ndarray:
    _, images, _ = frames
    return bare_loop(images, _camera(images, FOCAL_PX))


def _assert_like_the_bare_loop(per_pair: np.ndarray, bare: np.ndarray) -> None:
    """The issue's bounds, and the regression bound."""
    assert per_pair.size == bare.size
    assert per_pair.min() >= SHARE_OF_BARE_MEDIAN * np.median(bare), (per_pair, bare)
    assert not np.any((per_pair < WEAK) & (bare > STRONG)), (per_pair, bare)
    assert per_pair.min() >= MIN_PAIR_FEATURES, per_pair


def _write_log(root: Path, paths: list[Path], pos: np.ndarray, images: list[np.ndarray]) -> None:
    """A minimal flight log around the frames: frames.csv from the GPS times, the guessed
    intrinsics, a flat DTM at ground level (2810 m below), a still IMU (tracked --no-imu)."""
    root.mkdir()
    (root / "images").mkdir()
    t_ns = np.rint((pos[:, 6] - pos[0, 6]) * 1e9).astype(np.int64)
    rows = []
    for t, path in zip(t_ns, paths):
        shutil.copyfile(path, root / "images" / path.name)
        rows.append(f"{t},images/{path.name}")
    (root / "frames.csv").write_text("#t_ns,image\n" + "\n".join(rows) + "\n")
    (root / "imu.csv").write_text("#t_ns,gyro_x,gyro_y,gyro_z,acc_x,acc_y,acc_z\n" + "".join(
        f"{t},0,0,0,0,0,9.80665\n" for t in range(0, int(t_ns[-1]) + 100_000_000, 100_000_000)))
    np.savez(root / "dtm.npz", elevation=np.zeros((50, 50)), x0=-25_000.0, y0=-25_000.0,
             dx=1000.0, dy=1000.0)
    h, w = images[0].shape[:2]
    (root / "flight.yaml").write_text(f"""format: cdtm-flightlog/1
gravity_mps2: 9.80665
dtm:
  path: dtm.npz
camera:
  resolution: [{w}, {h}]
  intrinsics: [{FOCAL_PX}, {FOCAL_PX}, {(w - 1) / 2}, {(h - 1) / 2}]
  pixel_sigma_px: 0.5
  body_T_cam:
    translation_m: [0.0, 0.0, 0.0]
    quaternion_wxyz: [0.0, 1.0, 0.0, 0.0]
imu:
  rate_hz: 10
  gyroscope_noise_density: 1.7e-4
  accelerometer_noise_density: 2.0e-3
  gyroscope_random_walk: 1.9e-5
  accelerometer_random_walk: 3.0e-3
initial_state:
  position_m: [0.0, 0.0, 2810.0]
  quaternion_wxyz: [1.0, 0.0, 0.0, 0.0]
  velocity_mps: [0.0, 51.0, 0.0]
  gyro_bias: [0.0, 0.0, 0.0]
  accel_bias: [0.0, 0.0, 0.0]
  sigma_position_m: 50.0
  sigma_attitude_deg: 5.0
  sigma_velocity_mps: 2.0
  sigma_gyro_bias: 1.0e-4
  sigma_accel_bias: 1.0e-2
""")


def test_cdtm_track_keeps_as_many_features_as_a_bare_opencv_loop(frames, bare_counts, tmp_path,
                                                                  capsys):
    """``cdtm track LOG --no-imu`` on the real frames: every pair within the issue's bounds
    of the bare loop, the per-pair counts and reasons in the report, no warning.

    Catches: the five-point pose picked by ``cv2.recoverPose`` again (it counts no point
    past 50 baselines as in front: median 2 per pair, 0 in 18 of 29)."""
    paths, images, pos = frames
    log = tmp_path / "clif"
    _write_log(log, paths, pos, images)
    report = tmp_path / "report.json"
    assert main(["track", str(log), "--no-imu", "--quiet", "--report", str(report)]) == 0
    assert capsys.readouterr().err == ""  # no weak pair, no warning
    data = json.loads(report.read_text())
    per_pair = np.array(data["per_pair"]["features"])
    _assert_like_the_bare_loop(per_pair, bare_counts)
    assert np.median(bare_counts) > 150  # the reference itself works here (~173)
    assert data["weak_pairs"]["pairs"] == []
    ended = {name: np.array(v) for name, v in data["per_pair"]["ended"].items()}
    assert ended["epipolar"].sum() < 0.02 * per_pair.sum()  # 3581 of ~3700 before


def _track(images: list[np.ndarray], focal_px: float,
           rotations: list[np.ndarray | None] | None = None) -> tuple[np.ndarray, list]:
    """(K-1,) features kept per pair and the pairs' fits; at most MAX_EPIPOLAR_PER_PAIR
    ended by the epipolar check in any pair."""
    tracker = FeatureTracker(_camera(images, focal_px))
    outs = [tracker.track(im, None if rotations is None else rotations[k])
            for k, im in enumerate(images)]
    epipolar = np.array([o.counts()["epipolar"] for o in outs[1:]])
    assert epipolar.max() <= MAX_EPIPOLAR_PER_PAIR, epipolar
    return np.array([o.counts()["tracked"] for o in outs[1:]]), [o.fit for o in outs[1:]]


@pytest.mark.parametrize("focal_px", FOCAL_RANGE_PX)
def test_a_focal_length_guessed_2x_off_keeps_the_matches(frames, bare_counts, focal_px):
    """The five-point path at half and twice the guessed focal length (the bare loop keeps
    as many at any of them).

    Catches: inliers judged on the pose decomposed from the fitted matrix instead of on
    the matrix (at 4400 px one pair kept 131 of 188: the matrix USAC polishes through a
    wrong focal lies off the essential manifold); the per-match cheirality test on the
    five-point fit (at 1100 px it ended 16 correct matches of pair 0-1: the translation
    direction is barely determined, and with it the side of the camera a match is on)."""
    _, images, _ = frames
    per_pair, fits = _track(images, focal_px)
    _assert_like_the_bare_loop(per_pair, bare_counts)
    assert all(f is not None and f.method is FitMethod.ESSENTIAL for f in fits)


def test_every_third_frame_a_sequence_the_fix_was_not_tuned_on(frames):
    """A held-out variant (no other real frames of this kind are at hand): every third
    frame, ~90 px of flow and a 108 m baseline a pair. The tracker keeps the issue's bounds
    against the bare loop on the same sequence: measured 174 / 126 (median / min) against
    its 108 / 9 (2026-11-27; docs/frontend.md lists the other variants). (Up to 14 matches
    a pair end at the epipolar check here, against 8 for consecutive frames.)

    Catches: a bound fitted to the 30 px flow of consecutive frames (e.g. the prediction's
    search window, or the epipolar check's threshold, read off that flow), or any of the
    fixes above undone (the five-point pose then ends nearly every match here too)."""
    _, images, _ = frames
    sequence = images[::3]
    bare = bare_loop(sequence, _camera(sequence, FOCAL_PX))
    tracker = FeatureTracker(_camera(sequence, FOCAL_PX))
    outs = [tracker.track(im) for im in sequence]
    per_pair = np.array([o.counts()["tracked"] for o in outs[1:]])
    assert per_pair.size == bare.size == 9
    assert per_pair.min() >= SHARE_OF_BARE_MEDIAN * np.median(bare), (per_pair, bare)
    assert not np.any((per_pair < WEAK) & (bare > STRONG)), (per_pair, bare)
    assert np.median(per_pair) >= 150, per_pair  # (174 measured)


def pos_camera_rotations(pos: np.ndarray) -> list[np.ndarray | None]:
    """``cam_prev_R_cam`` per frame from the POS attitudes (heading, pitch, roll: z-y-x
    Euler angles of the body in north-east-down), the camera mounted with its axes along
    the body's (x forward, y right, z down). That mounting was found from the frames: of
    the 24 axis-aligned ones it is the only one under which the rotation explains at
    least 95 % of the matches in each of the first 11 pairs (2026-11-27; under any
    other the five-point fit takes over in most pairs, and 186-199 features stay)."""
    ned_R_body = Rotation.from_euler("ZYX", pos[:, :3], degrees=True).as_matrix()
    return [None] + [ned_R_body[k - 1].T @ ned_R_body[k] for k in range(1, len(pos))]


@pytest.mark.parametrize("focal_px", [FOCAL_RANGE_PX[0], FOCAL_PX, FOCAL_RANGE_PX[1]])
def test_the_rotation_prior_from_real_attitudes(frames, bare_counts, focal_px):
    """The IMU path, fed the aircraft's real rotations (0.6-1.2 deg between frames, in a
    34 deg bank), at the guessed focal length and 2x off.

    Catches: the prior compared with the five-point fit only below 60 % (at 1100 px it
    explained 64-88 % of the matches, all correct: 123-148 kept); the first pair's
    phase-correlation shift added to the rotated prediction, which holds the rotation's
    flow already (at 4400 px, 58 of 200 features failed forward-backward); a prior
    that goes unused (at 2200 px it must verify most pairs itself)."""
    _, images, pos = frames
    per_pair, fits = _track(images, focal_px, pos_camera_rotations(pos))
    _assert_like_the_bare_loop(per_pair, bare_counts)
    if focal_px == FOCAL_PX:
        prior = sum(f.method is FitMethod.ROTATION_PRIOR for f in fits)
        assert prior >= 0.9 * len(fits)


def test_weak_pairs_are_named_in_one_warning_line(frames, tmp_path, capsys):
    """A frame of other ground (frame 2 turned 180 deg): the two pairs around it are
    named, with their counts and why their features ended, in one line on stderr (also
    with --quiet), and the report lists them.

    Catches: no warning, a warning line per pair, a weak pair left out."""
    paths, images, pos = frames
    log = tmp_path / "clif"
    _write_log(log, paths[:5], pos[:5], images[:5])
    turned = log / "images" / paths[2].name
    cv2.imwrite(str(turned), cv2.rotate(images[2], cv2.ROTATE_180))
    report = tmp_path / "report.json"
    assert main(["track", str(log), "--no-imu", "--quiet", "--report", str(report)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    line = err[0]
    assert line.startswith("cdtm track: warning: 2 of 4 frame pairs keep fewer than 50")
    assert " 1-2 (" in line and " 2-3 (" in line and "0-1" not in line and "3-4" not in line
    data = json.loads(report.read_text())
    assert data["weak_pairs"] == {"below_features": 50, "pairs": [[1, 2], [2, 3]]}
    features = data["per_pair"]["features"]
    assert features[0] > 150 and features[3] > 150
