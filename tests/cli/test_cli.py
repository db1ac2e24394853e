"""The ``cdtm`` command line as a user meets it: outputs, JSON, bad input, scripts."""

from __future__ import annotations

import json
import runpy
import shutil
from pathlib import Path

import numpy as np
import pytest

from cdtm_graph.cli import main
from cdtm_graph.outputs import read_trajectory_cov, read_tum

SAMPLE = Path(__file__).resolve().parents[2] / "data" / "sample_flight"
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def smoothed(tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "out"
    assert main(["smooth", str(SAMPLE), "--out", str(out), "--plots", "--quiet"]) == 0
    return out


def test_smooth_writes_every_output_and_they_round_trip(smoothed):
    names = {p.name for p in smoothed.iterdir()}
    assert {"trajectory.tum", "trajectory_cov.txt", "states.csv", "covariances.npz",
            "report.json", "trajectory.png", "errors.png"} <= names
    t_ns, poses = read_tum(smoothed / "trajectory.tum")
    t2, poses2, ori_cov, pos_cov = read_trajectory_cov(smoothed / "trajectory_cov.txt")
    np.testing.assert_array_equal(t_ns, t2)
    np.testing.assert_allclose(poses, poses2, atol=1e-9)
    rows = [line for line in (smoothed / "trajectory_cov.txt").read_text().splitlines()
            if not line.startswith("#")]
    assert all(len(r.split()) == 20 for r in rows)
    for cov in np.r_[ori_cov, pos_cov]:
        np.testing.assert_allclose(cov, cov.T)
        assert np.linalg.eigvalsh(cov).min() > 0
    report = json.loads((smoothed / "report.json").read_text())
    table = report["evaluation"]["table1"]["rows"]
    for axis in "xyz":
        assert table[f"Free-{axis}"] > 5 * table[f"Compensated-{axis}"]
    npz = np.load(smoothed / "covariances.npz", allow_pickle=False)
    assert npz["pose"].shape == (len(t_ns), 6, 6)


def test_demo_writes_into_cdtm_demo_out(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["demo"]) == 0
    assert (tmp_path / "cdtm-demo-out" / "trajectory.tum").is_file()
    text = capsys.readouterr().out
    assert "RMSE compensated" in text and "max error free" in text


def test_analyze_json_has_the_documented_keys(capsys):
    assert main(["analyze", str(SAMPLE), "--pair", "10", "11", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    for key in ("n_features", "theta_names", "theta", "sigma_theta_weighted",
                "sigma_theta_unweighted", "sigma_theta_gtsam", "sigma_c2_weighted",
                "sigma_c2_unweighted", "condition_number", "degenerate"):
        assert key in data
    w = np.array(data["sigma_theta_weighted"])
    g = np.array(data["sigma_theta_gtsam"])
    np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-5 * np.abs(np.diag(w)).min())
    assert data["n_features"] > 6 and len(data["theta"]) == 12


def test_analyze_table_is_in_metres_and_degrees(capsys):
    assert main(["analyze", str(SAMPLE), "--pair", "3", "4"]) == 0
    text = capsys.readouterr().out
    assert "deg" in text and "p2_x" in text and "condition number" in text


def test_an_empty_log_argument_is_named(tmp_path, capsys):
    assert main(["smooth", "", "--out", str(tmp_path / "out"), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err == "cdtm smooth: error: LOG is empty; expected a flight log directory\n"


def test_analyze_refuses_a_pair_it_cannot_analyze_in_one_line(tmp_path, capsys):
    """A pair without common features, and frames beyond groundtruth.csv: one line each,
    exit 1 (they printed tables of inf and nan with exit 0, or named an internal class)."""
    n_frames = len((SAMPLE / "frames.csv").read_text().splitlines()) - 1
    assert main(["analyze", str(SAMPLE), "--pair", "0", str(n_frames - 1)]) == 1
    out, err = capsys.readouterr()
    assert out == "" and len(err.splitlines()) == 1
    assert f"frames A=0 and B={n_frames - 1} share no tracked feature" in err
    log = _broken_copy(tmp_path)
    gt = (log / "groundtruth.csv").read_text().splitlines()
    (log / "groundtruth.csv").write_text("\n".join(gt[:1] + gt[30:]) + "\n")  # from 2.9 s on
    assert main(["analyze", str(log), "--pair", "0", "1"]) == 1
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1
    assert "groundtruth.csv: covers 2.900-" in err and "frame A=0 at 0.000 s is outside it" in err


def _broken_copy(tmp_path: Path) -> Path:
    log = tmp_path / "log"
    shutil.copytree(SAMPLE, log)
    return log


def _replace_line(path: Path, index: int, new: str) -> None:
    lines = path.read_text().splitlines()
    lines[index] = new
    path.write_text("\n".join(lines) + "\n")


def _edit_csv_row(path: Path, row: int, fn) -> None:
    lines = path.read_text().splitlines()
    fields = lines[row].split(",")
    lines[row] = ",".join(fn(fields))
    path.write_text("\n".join(lines) + "\n")


BAD_INPUTS = {
    "unknown_yaml_key": (lambda log: (log / "flight.yaml").write_text(
        (log / "flight.yaml").read_text().replace("gravity_mps2:", "gravity_mps:")), "gravity_mps"),
    "missing_file": (lambda log: (log / "imu.csv").unlink(), "imu.csv"),
    "nan_value": (lambda log: _edit_csv_row(log / "imu.csv", 5, lambda f: f[:3] + ["nan"] + f[4:]),
                  "imu.csv"),
    "inf_value": (lambda log: _edit_csv_row(log / "imu.csv", 7, lambda f: f[:2] + ["inf"] + f[3:]),
                  "imu.csv"),
    "non_increasing_time": (lambda log: _edit_csv_row(
        log / "frames.csv", 3, lambda f: ["1"] + f[1:]), "frames.csv"),
    "short_row": (lambda log: _edit_csv_row(log / "imu.csv", 9, lambda f: f[:4]), "imu.csv"),
    "track_frame_missing": (lambda log: _edit_csv_row(
        log / "tracks.csv", -1, lambda f: ["999"] + f[1:]), "tracks.csv"),
    "pixel_outside_image": (lambda log: _edit_csv_row(
        log / "tracks.csv", 4, lambda f: f[:2] + ["5000.0"] + f[3:]), "tracks.csv"),
    "pickled_dtm": (lambda log: np.savez(log / "dtm.npz", elevation=np.array([object()] * 4),
                                         x0=0.0, y0=0.0, dx=1.0, dy=1.0), "dtm.npz"),
}


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_input_gives_one_line_and_exit_1(tmp_path, capsys, case):
    log = _broken_copy(tmp_path)
    corrupt, must_name = BAD_INPUTS[case]
    corrupt(log)
    out = tmp_path / "out"
    assert main(["smooth", str(log), "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert must_name in err and "Traceback" not in err
    assert not out.exists()  # nothing written half


def test_bad_pair_gives_one_line(capsys):
    assert main(["analyze", str(SAMPLE), "--pair", "3", "9999"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "9999" in err


def test_isam2_script_runs_on_the_sample_log(capsys):
    summary = runpy.run_path(str(ROOT / "scripts" / "isam2_incremental.py"),
                             run_name="not_main")["main"]([])
    assert summary["frames"] > 10
    assert summary["filter_rms_error_m"] < 10.0


def test_terrain_figures_script_reproduces_fig6(tmp_path, capsys):
    """scripts/terrain_figures.py: sigma_h grows about linearly with the grid spacing."""
    curves = runpy.run_path(str(ROOT / "scripts" / "terrain_figures.py"),
                            run_name="not_main")["main"](["--out", str(tmp_path)])
    mean = curves.mean(axis=0)
    assert np.all(np.diff(mean) > 0)
    spacings = np.array([10, 30, 50, 70, 100, 130, 160, 190])
    slope = np.polyfit(spacings, mean, 1)[0]
    assert 0.06 < slope < 0.1  # the paper's 2.4 m at 30 m is 0.08 per metre
    assert (tmp_path / "fig6_sigma_h.png").stat().st_size > 0
    assert (tmp_path / "fig12_cloned_cell.png").stat().st_size > 0


@pytest.mark.parametrize("args, must_name", [
    (["--mode", "incremental", "--gate", "1.5"], "--gate 1.5"),
    (["--lag-s", "5"], "--lag-s needs --mode incremental"),
    (["--mode", "incremental", "--lag-s", "inf"], "--lag-s inf: expected a finite lag > 0"),
    (["--mode", "incremental", "--lag-s", "nan"], "--lag-s nan: expected a finite lag > 0"),
])
def test_bad_smoothing_options_give_one_line(tmp_path, capsys, args, must_name):
    out = tmp_path / "out"
    assert main(["smooth", str(SAMPLE), "--out", str(out), "--quiet", *args]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and must_name in err, err
    assert not out.exists()


def test_gated_incremental_run_reports_rejections(tmp_path):
    """A 90% gate on the clean sample log drops about 10% of the features (the innovations
    are chi-square(2)), reported per frame."""
    out = tmp_path / "out"
    code = main(["smooth", str(SAMPLE), "--out", str(out), "--quiet", "--mode", "incremental",
                 "--gate", "0.9"])
    report = json.loads((out / "report.json").read_text())
    # the outputs are written; the exit status follows the verdict (a 90% gate drops a
    # tenth of the good features, which the verdict may judge against the ground truth)
    assert code == (0 if report["verdict"] == "trusted" else 3)
    counts = report["counts"]
    gated = sum(counts["rejected_per_frame"]["gated"])
    fraction = gated / (gated + counts["n_cdtm_features"])
    assert 0.05 < fraction < 0.2, fraction
