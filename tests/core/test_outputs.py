"""Tests of cdtm_graph.outputs: run-directory files, round trips, frames, atomicity."""

from __future__ import annotations

import json
import math
from pathlib import Path

import gtsam
import numpy as np
import pytest

from cdtm_graph.atomic import MANIFEST_NAME, read_manifest
from cdtm_graph.errors import CdtmError
from cdtm_graph.geometry import make_pose, quat_wxyz_to_rotation, so3_log
from cdtm_graph.outputs import (
    COV_COLUMNS,
    COVARIANCES_NPZ,
    POSE_COVARIANCE_CONVENTION,
    REPORT_JSON,
    STATES_COLUMNS,
    STATES_CSV,
    TRAJECTORY_COV,
    TRAJECTORY_TUM,
    format_t_s,
    parse_t_s,
    read_trajectory_cov,
    read_tum,
    write_run,
)
from cdtm_graph.results import (
    SmootherResult,
    StateCovariances,
    TrajectoryEstimate,
)

T0_NS = 1_403_636_579_758_555_392  # an epoch in ns: float64 seconds cannot hold it to 1 ns
POSE_TOL = 1e-9
#: Relative tolerance of covariances read back (written in shortest round-trip form, so
#: only the rotation's round-off remains).
COV_REL_TOL = 1e-12
#: The numerical Jacobian of the world-frame error is a central difference (O(h^2)).
NUMERICAL_COV_REL_TOL = 1e-6


@pytest.fixture
def result(synthetic, rng: np.random.Generator) -> SmootherResult:
    return synthetic.synthetic_result(rng)


@pytest.fixture
def run_dir(tmp_path: Path, result: SmootherResult) -> Path:
    out = tmp_path / "run"
    write_run(out, result, {"timings": {"total_s": 1.25, "bad": float("nan")}})
    return out


def _data_lines(path: Path) -> list[list[str]]:
    return [line.split() for line in path.read_text().splitlines()
            if line.strip() and not line.startswith("#")]


# --------------------------------------------------------------------------- time format


@pytest.mark.parametrize("t_ns, text", [
    (T0_NS, "1403636579.758555392"), (0, "0.000000000"), (1, "0.000000001"),
    (-1, "-0.000000001"), (-1_500_000_000, "-1.500000000")])
def test_t_s_is_written_exactly_with_nine_decimals(t_ns, text):
    assert format_t_s(t_ns) == text
    assert parse_t_s(text) == t_ns


def test_parse_t_s_accepts_other_float_syntax():
    assert parse_t_s("1.5e9") == 1_500_000_000 * 1_000_000_000
    assert parse_t_s("12") == 12_000_000_000
    with pytest.raises(ValueError):
        parse_t_s("nan")


# --------------------------------------------------------------------------- round trips


def test_run_directory_has_exactly_the_run_files(run_dir: Path):
    files = [TRAJECTORY_TUM, TRAJECTORY_COV, STATES_CSV, COVARIANCES_NPZ, REPORT_JSON]
    assert sorted(p.name for p in run_dir.iterdir()) == sorted([*files, MANIFEST_NAME])
    assert read_manifest(run_dir) == dict.fromkeys(files, "smooth")


def test_tum_round_trip(synthetic, run_dir: Path, result: SmootherResult):
    t_ns, T = read_tum(run_dir / TRAJECTORY_TUM)
    np.testing.assert_array_equal(t_ns, result.estimate.t_ns)
    for T_read, T_written in zip(T, result.estimate.world_T_body, strict=True):
        delta = gtsam.Pose3(T_written).localCoordinates(gtsam.Pose3(T_read))
        assert np.max(np.abs(delta)) < POSE_TOL
    # What evo does: numpy's loader with '#' comments, 8 float columns.
    table = np.loadtxt(run_dir / TRAJECTORY_TUM, comments="#")
    assert table.shape == (synthetic.FRAMES, 8)
    np.testing.assert_allclose(table[:, 1:4], result.estimate.position_m, rtol=0, atol=1e-9)


def test_tum_quaternion_is_xyzw_and_rotates_body_to_world(run_dir: Path, result: SmootherResult):
    row = _data_lines(run_dir / TRAJECTORY_TUM)[0]
    qx, qy, qz, qw = map(float, row[4:8])
    R = quat_wxyz_to_rotation(np.array([qw, qx, qy, qz]))
    np.testing.assert_allclose(R, result.estimate.world_T_body[0, :3, :3], atol=1e-12)


def test_trajectory_cov_has_20_columns_and_a_world_frame_header(synthetic, run_dir: Path):
    text = (run_dir / TRAJECTORY_COV).read_text()
    header = text.splitlines()[0]
    assert header.startswith("#") and "world frame" in header
    assert header.split()[1:21] == list(COV_COLUMNS)
    rows = _data_lines(run_dir / TRAJECTORY_COV)
    assert len(rows) == synthetic.FRAMES and {len(r) for r in rows} == {20}


def test_trajectory_cov_round_trip_matches_an_independent_world_frame_computation(
    manifold, synthetic, run_dir: Path, result: SmootherResult
):
    t_ns, T, ori_cov, pos_cov = read_trajectory_cov(run_dir / TRAJECTORY_COV)
    np.testing.assert_array_equal(t_ns, result.estimate.t_ns)
    for k in range(synthetic.FRAMES):
        T0 = result.estimate.world_T_body[k]
        assert np.max(np.abs(gtsam.Pose3(T0).localCoordinates(gtsam.Pose3(T[k])))) < POSE_TOL
        R0, p0 = T0[:3, :3], T0[:3, 3]

        # World-frame error of the perturbed pose T0 Exp(xi): rotation about world axes,
        # position difference. Its Jacobian maps the body-frame tangent covariance.
        def world_error(T_pert, R0=R0, p0=p0):
            return np.concatenate([so3_log(T_pert[:3, :3] @ R0.T), T_pert[:3, 3] - p0])

        J = manifold.numerical_pose_jacobian(world_error, T0)
        expected = J @ result.covariances.pose[k] @ J.T
        np.testing.assert_allclose(ori_cov[k], expected[:3, :3], rtol=NUMERICAL_COV_REL_TOL,
                                   atol=NUMERICAL_COV_REL_TOL * np.abs(expected[:3, :3]).max())
        np.testing.assert_allclose(pos_cov[k], expected[3:, 3:], rtol=NUMERICAL_COV_REL_TOL,
                                   atol=NUMERICAL_COV_REL_TOL * np.abs(expected[3:, 3:]).max())
    for cov in (ori_cov, pos_cov):
        np.testing.assert_array_equal(cov, np.swapaxes(cov, 1, 2))
        assert np.all(np.linalg.eigvalsh(cov) > 0)


def test_quarter_turn_swaps_the_x_and_y_variances(
    synthetic, tmp_path: Path, rng: np.random.Generator
):
    base = synthetic.synthetic_result(rng, k=1)
    Rz90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    pose_cov = np.diag([1e-6, 2e-6, 3e-6, 1.0, 4.0, 9.0])[None]
    result = SmootherResult(
        TrajectoryEstimate(base.estimate.t_ns, make_pose(Rz90, [1.0, 2.0, 3.0])[None],
                           base.estimate.velocity_mps, base.estimate.gyro_bias,
                           base.estimate.accel_bias),
        StateCovariances(pose_cov, base.covariances.velocity, base.covariances.bias),
        base.stats, base.counts)
    write_run(tmp_path / "run", result, {})
    _, _, ori_cov, pos_cov = read_trajectory_cov(tmp_path / "run" / TRAJECTORY_COV)
    # Body x points to world y: the body-x variance becomes the world-y variance.
    np.testing.assert_allclose(ori_cov[0], np.diag([2e-6, 1e-6, 3e-6]), rtol=1e-12, atol=1e-20)
    np.testing.assert_allclose(pos_cov[0], np.diag([4.0, 1.0, 9.0]), rtol=1e-12, atol=1e-15)


def test_states_csv_columns_and_sigmas(synthetic, run_dir: Path, result: SmootherResult):
    lines = (run_dir / STATES_CSV).read_text().splitlines()
    assert lines[0].split(",") == list(STATES_COLUMNS)
    rows = [line.split(",") for line in lines[1:]]
    assert len(rows) == synthetic.FRAMES
    t_ns = np.array([int(r[0]) for r in rows], dtype=np.int64)
    np.testing.assert_array_equal(t_ns, result.estimate.t_ns)
    table = np.array([[float(x) for x in r[1:]] for r in rows])
    col = {name: i - 1 for i, name in enumerate(STATES_COLUMNS)}
    est, cov = result.estimate, result.covariances
    np.testing.assert_array_equal(table[:, col["px"]:col["pz"] + 1], est.position_m)
    R = quat_wxyz_to_rotation(table[:, col["qw"]:col["qz"] + 1])
    np.testing.assert_allclose(R, est.world_T_body[:, :3, :3], atol=1e-12)
    np.testing.assert_array_equal(table[:, col["vx"]:col["vz"] + 1], est.velocity_mps)
    np.testing.assert_array_equal(table[:, col["bgx"]:col["bgz"] + 1], est.gyro_bias)
    np.testing.assert_array_equal(table[:, col["bax"]:col["baz"] + 1], est.accel_bias)
    R_wb = est.world_T_body[:, :3, :3]
    pos_world = R_wb @ cov.pose[:, 3:, 3:] @ np.swapaxes(R_wb, 1, 2)
    ori_world = R_wb @ cov.pose[:, :3, :3] @ np.swapaxes(R_wb, 1, 2)
    sd = lambda c: np.sqrt(np.diagonal(c, axis1=1, axis2=2))  # noqa: E731
    np.testing.assert_allclose(table[:, col["sigma_px"]:col["sigma_pz"] + 1], sd(pos_world),
                               rtol=1e-12)
    np.testing.assert_allclose(table[:, col["sigma_rx"]:col["sigma_rz"] + 1], sd(ori_world),
                               rtol=1e-12)
    np.testing.assert_allclose(table[:, col["sigma_vx"]:col["sigma_vz"] + 1],
                               sd(cov.velocity), rtol=1e-12)
    # GTSAM's bias covariance is [accel, gyro].
    np.testing.assert_allclose(table[:, col["sigma_bgx"]:col["sigma_bgz"] + 1],
                               sd(cov.bias[:, 3:, 3:]), rtol=1e-12)
    np.testing.assert_allclose(table[:, col["sigma_bax"]:col["sigma_baz"] + 1],
                               sd(cov.bias[:, :3, :3]), rtol=1e-12)


def test_covariances_npz_keeps_gtsam_order_and_says_so(run_dir: Path, result: SmootherResult):
    with np.load(run_dir / COVARIANCES_NPZ, allow_pickle=False) as npz:
        np.testing.assert_array_equal(npz["t_ns"], result.estimate.t_ns)
        np.testing.assert_array_equal(npz["pose"], result.covariances.pose)
        np.testing.assert_array_equal(npz["velocity"], result.covariances.velocity)
        np.testing.assert_array_equal(npz["bias"], result.covariances.bias)
        assert str(npz["convention"]) == POSE_COVARIANCE_CONVENTION
        assert "[rot, trans]" in str(npz["convention"])
        assert "[accel" in str(npz["bias_convention"])


def _reject_constant(token: str):
    raise AssertionError(f"report.json contains the non-JSON token {token}")


def test_report_json_is_strict_json_with_counts_stats_and_the_callers_report(synthetic,
        run_dir: Path, result: SmootherResult):
    text = (run_dir / REPORT_JSON).read_text()
    report = json.loads(text, parse_constant=_reject_constant)
    assert report["counts"]["n_frames"] == synthetic.FRAMES
    assert report["counts"]["features_per_frame"] == list(range(synthetic.FRAMES))
    assert report["solver"]["iterations"] == 4
    assert report["solver"]["final_error"] is None  # NaN
    assert report["solver"]["update_times_s"] == [0.1, None]  # inf
    assert report["settings"]["huber_k"] == 1.345
    assert report["flags"] == {"3": ["no_features"], "7": ["degenerate"]}
    assert report["timings"] == {"total_s": 1.25, "bad": None}
    assert "[rot, trans]" in report["conventions"]["covariances.npz/pose"]


def test_report_keys_that_clash_are_refused_before_writing(tmp_path: Path, result):
    with pytest.raises(ValueError, match="counts"):
        write_run(tmp_path / "run", result, {"counts": 1})
    assert not (tmp_path / "run").exists()


# --------------------------------------------------------------------------- atomicity


def _siblings(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir())


def test_extra_files_are_written_inside_the_run_directory(tmp_path: Path, result):
    write_run(tmp_path / "run", result, {},
              extra_files=[("note.txt", lambda p: p.write_text("hello"))])
    assert (tmp_path / "run" / "note.txt").read_text() == "hello"


def test_failing_extra_writer_leaves_no_directory(tmp_path: Path, result):
    def boom(path: Path) -> None:
        path.write_text("half")
        raise RuntimeError("plot failed")

    with pytest.raises(RuntimeError, match="plot failed"):
        write_run(tmp_path / "run", result, {}, extra_files=[("a.png", boom)])
    assert _siblings(tmp_path) == []  # neither the run nor a temporary directory


def test_failing_extra_writer_keeps_the_old_run(synthetic, tmp_path: Path, result, rng):
    out = tmp_path / "run"
    write_run(out, result, {"attempt": 1})
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def boom(path: Path) -> None:
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        write_run(
            out, synthetic.synthetic_result(rng), {"attempt": 2}, extra_files=[("a.png", boom)]
        )
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert _siblings(tmp_path) == ["run"]


@pytest.mark.parametrize("name", ["report.json", "sub/a.png", "../a.png", "", "."])
def test_bad_extra_file_names_are_refused(tmp_path: Path, result, name):
    with pytest.raises(ValueError):
        write_run(tmp_path / "run", result, {}, extra_files=[(name, lambda p: None)])
    assert not (tmp_path / "run").exists()


def test_mismatched_shapes_are_refused(tmp_path: Path, result):
    bad = SmootherResult(result.estimate,
                         StateCovariances(result.covariances.pose[:-1],
                                          result.covariances.velocity, result.covariances.bias),
                         result.stats, result.counts)
    with pytest.raises(ValueError, match="covariances.pose"):
        write_run(tmp_path / "run", bad, {})


# --------------------------------------------------------------------------- bad files

GOOD_TUM_LINE = "1.000000000 1 2 3 0 0 0 1"


@pytest.mark.parametrize("content, line, message", [
    ("# header\n" + GOOD_TUM_LINE + " 7\n", 2, "columns"),
    (GOOD_TUM_LINE + "\n1.5 1 2 x 0 0 0 1\n", 2, "number"),
    (GOOD_TUM_LINE + "\n1.5 1 2 3 0 0 0 2\n", 2, "quaternion"),
    (GOOD_TUM_LINE + "\n0.5 1 2 3 0 0 0 1\n", 2, "increas"),
    (GOOD_TUM_LINE + "\n1.5 1 2 inf 0 0 0 1\n", 2, "finite"),
    ("# only a header\n", 1, "no data"),
])
def test_read_tum_names_file_and_line(tmp_path: Path, content, line, message):
    path = tmp_path / "t.tum"
    path.write_text(content)
    with pytest.raises(CdtmError, match=message) as info:
        read_tum(path)
    assert f"{path}:{line}:" in str(info.value)


def test_read_trajectory_cov_rejects_a_tum_file(tmp_path: Path):
    path = tmp_path / "cov.txt"
    path.write_text(GOOD_TUM_LINE + "\n")
    with pytest.raises(CdtmError, match=f"{path}:1: 8 columns; expected 20"):
        read_trajectory_cov(path)


def test_missing_file_is_a_cdtm_error(tmp_path: Path):
    with pytest.raises(CdtmError, match="cannot read"):
        read_tum(tmp_path / "absent.tum")


# --------------------------------------------------------------------------- ground truth


def test_groundtruth_tum_holds_the_truth_at_the_frames_it_covers(tmp_path: Path, result,
                                                                  synthetic):
    """groundtruth.tum: the true poses at exactly the frame times of trajectory.tum that the
    ground truth covers, world frame, so evo associates them one to one.

    Catches: writing the ground truth at its own (IMU) rate or at frames outside its
    range (evo would match other pairs), or not writing it (issue 23's evo finding)."""
    from cdtm_graph.flightlog import States
    from cdtm_graph.verdict.evaluation import trajectory_errors

    est = result.estimate
    # Truth at twice the frame rate, starting after frame 3 and ending before the last.
    frames = est.t_ns[3:-1]
    t_truth = np.sort(np.r_[frames, frames[:-1] + synthetic.FRAME_DT_NS // 2])
    offset = np.array([1.0, -2.0, 0.5])
    truth_xyz = np.interp(t_truth, est.t_ns, est.position_m[:, 0])
    position = np.column_stack([truth_xyz, np.interp(t_truth, est.t_ns, est.position_m[:, 1]),
                                np.interp(t_truth, est.t_ns, est.position_m[:, 2])]) + offset
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (len(t_truth), 1))
    truth = States(t_truth, position, quat, np.zeros((len(t_truth), 3)))
    write_run(tmp_path / "run", result, {}, groundtruth=truth)
    t_gt, T_gt = read_tum(tmp_path / "run" / "groundtruth.tum")
    np.testing.assert_array_equal(t_gt, est.t_ns[3:-1])
    assert read_manifest(tmp_path / "run")["groundtruth.tum"] == "smooth"
    assert not (tmp_path / "run" / "groundtruth_geodetic.csv").exists()  # no origin
    # APE as evo computes it (translation part, no alignment) equals the run's 3-D RMSE.
    t_est, T_est = read_tum(tmp_path / "run" / "trajectory.tum")
    pick = np.isin(t_est, t_gt)
    ape = np.linalg.norm(T_est[pick, :3, 3] - T_gt[:, :3, 3], axis=1)
    errors = trajectory_errors(est, None, truth)
    assert math.sqrt(np.mean(ape**2)) == pytest.approx(errors.rmse_position_3d_m, abs=1e-9)


def test_no_groundtruth_file_without_a_frame_inside_the_truth(tmp_path: Path, result):
    """A ground truth that covers no frame gives no (empty) groundtruth.tum.

    Catches: an empty groundtruth.tum, which evo refuses with a traceback."""
    from cdtm_graph.flightlog import States

    t = np.array([0, 1], dtype=np.int64)  # long before the first frame
    truth = States(t, np.zeros((2, 3)), np.tile([1.0, 0, 0, 0], (2, 1)), np.zeros((2, 3)))
    write_run(tmp_path / "run", result, {}, groundtruth=truth)
    assert not (tmp_path / "run" / "groundtruth.tum").exists()
