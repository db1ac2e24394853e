"""``cdtm evaluate`` and ``cdtm smooth-many``: many runs in one table and figures (issue 23).

Logs are tiny simulations (6 frames, 40 features per pair, as tests/test_cli_safety.py's):
a smoothing run takes about a second.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from cdtm_graph.atomic import MANIFEST_NAME, read_manifest
from cdtm_graph.cli import main
from cdtm_graph.cli.evaluate import EVALUATE_FILES
from cdtm_graph.errors import CdtmError
from cdtm_graph.outputs import read_run, read_tum, write_trajectory_tum
from cdtm_graph.sim.simulate import SimulationSettings, write_simulated_log
from cdtm_graph.verdict.comparison import REPORT_AGREEMENT_M, TABLE_COLUMNS, run_series

#: Exit statuses of a smoothing run that wrote its outputs (the verdict of a 6-frame log is
#: not what these tests are about).
WROTE_OUTPUTS = (0, 3)
#: Three modes, as `cdtm smooth` options.
MODES = {"batch": [], "isam2": ["--mode", "incremental"],
         "lag": ["--mode", "incremental", "--lag-s", "3"]}


def _log(directory: Path, seed: int) -> Path:
    settings = SimulationSettings(frames=6, n_features=40, seed=seed, resolution_px=(640, 480))
    return write_simulated_log(settings, directory)


@pytest.fixture(scope="module")
def logs(tmp_path_factory, seed) -> list[Path]:
    root = tmp_path_factory.mktemp("logs")
    return [_log(root / f"log{i}", seed % 1000 + i) for i in range(4)]


@pytest.fixture(scope="module")
def runs(logs, tmp_path_factory) -> list[Path]:
    """Runs of three modes over two logs."""
    root = tmp_path_factory.mktemp("runs")
    out = []
    for log in logs[:2]:
        for mode, options in MODES.items():
            run = root / f"{log.name}_{mode}"
            assert main(["smooth", str(log), "--out", str(run), "--quiet", *options]) in \
                WROTE_OUTPUTS
            out.append(run)
    return out


@pytest.fixture(scope="module")
def singles(logs, tmp_path_factory) -> dict[str, Path]:
    """Each log through `cdtm smooth`, as a user runs one."""
    root = tmp_path_factory.mktemp("singles")
    out = {}
    for log in logs:
        out[log.name] = root / log.name
        assert main(["smooth", str(log), "--out", str(out[log.name]), "--quiet"]) in \
            WROTE_OUTPUTS
    return out


def _one_line(err: str, *words: str) -> None:
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert len(lines) == 1, err
    for word in words:
        assert word in lines[0], (word, lines[0])


def test_evaluate_writes_one_row_per_run_and_the_three_figures(runs, tmp_path, capsys):
    """Three modes over two logs: the table holds report.json's figures for each run, the
    figures one box / line per run.

    Catches: a column read from the wrong report key or axis (the CSV is compared with
    each report.json), a run left out of a figure, outputs not under the manifest."""
    out = tmp_path / "eval"
    assert main(["evaluate", *map(str, runs), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert set(read_manifest(out)) == set(EVALUATE_FILES)
    with open(out / "evaluation.csv") as f:
        table = list(csv.DictReader(f))
    assert tuple(table[0]) == TABLE_COLUMNS
    assert [row["run"] for row in table] == [r.name for r in runs]
    for row, run in zip(table, runs, strict=True):
        report = json.loads((run / "report.json").read_text())
        c = report["evaluation"]["compensated"]
        for a in "xyz":
            assert float(row[f"rmse_{a}_m"]) == c["rmse_position_m"][a]
            assert float(row[f"max_{a}_m"]) == c["max_abs_position_error_m"][a]
        assert float(row["anees_position"]) == c["anees_position"]
        consistency = c["position_consistency"]
        assert float(row["nees_p90"]) == consistency["nees_percentiles"]["p90"]
        assert float(row["inside_95"]) == consistency["inside_fraction"]
        assert row["verdict"] == report["verdict"]
        assert float(row["time_s"]) == report["timings_s"]["total"]
    assert [row["mode"] for row in table[:3]] == ["batch", "incremental",
                                                  "incremental, lag 3 s"]
    markdown = (out / "evaluation.md").read_text()
    assert markdown == printed and markdown.count("\n") == 2 + len(runs)
    for name in EVALUATE_FILES[2:]:
        assert (out / name).read_bytes()[:4] == b"\x89PNG"


def test_the_figures_show_every_run(runs, tmp_path):
    """One box per run in each panel, one error line per run and axis, one NEES line per run
    beside the chi-square bounds; the per-frame series agree with report.json.

    Catches: a run dropped from a figure; series from files of another run."""
    from cdtm_graph.plots.comparison import (
        plot_error_boxplots,
        plot_errors_over_time,
        plot_nees_over_time,
    )
    from cdtm_graph.verdict.comparison import NEES_DOF
    from cdtm_graph.verdict.evaluation import nees_bound

    runs = runs[::2]  # three runs are enough to see none is dropped
    names = [r.name for r in runs]
    series = [run_series(read_run(r)) for r in runs]
    boxes = plot_error_boxplots(tmp_path / "b.png", names, series)
    for ax in boxes.axes:
        assert [t.get_text() for t in ax.get_xticklabels()] == names
    over_time = plot_errors_over_time(tmp_path / "e.png", names, series)
    for ax in over_time.axes:
        labelled = [ln for ln in ax.lines if not ln.get_label().startswith("_")]
        assert [ln.get_label() for ln in labelled] == names
    nees = plot_nees_over_time(tmp_path / "n.png", names, series)
    lines = nees.axes[0].lines
    assert sum(ln.get_label().split(" (")[0] in names for ln in lines) == len(runs)
    assert any(np.allclose(ln.get_ydata(), nees_bound(NEES_DOF)) for ln in lines)
    for run, s in zip(runs, series, strict=True):
        report = json.loads((run / "report.json").read_text())
        assert s.rmse_position_3d_m == pytest.approx(
            report["evaluation"]["compensated"]["rmse_position_3d_m"], abs=REPORT_AGREEMENT_M)


def test_files_of_two_runs_mixed_are_named_not_averaged(runs, tmp_path):
    """A run directory whose groundtruth.tum belongs to another log is refused.

    Catches: series taken without checking them against report.json."""
    mixed = tmp_path / "mixed"
    shutil.copytree(runs[0], mixed)
    t_ns, world_T_body = read_tum(mixed / "groundtruth.tum")
    world_T_body[:, 0, 3] += 0.5  # another flight's truth, half a metre east
    write_trajectory_tum(mixed / "groundtruth.tum", t_ns, world_T_body)
    with pytest.raises(CdtmError, match="expected the files of one run"):
        run_series(read_run(mixed))


@pytest.mark.parametrize("case, words", [
    ("not_a_run", ["not a run directory (no report.json)"]),
    ("missing", ["does not exist"]),
    ("no_truth", ["no ground truth", "groundtruth.tum"]),
    ("truncated_npz", ["covariances.npz: cannot read"]),
    ("empty_npz", ["covariances.npz: cannot read"]),
])
def test_evaluate_bad_input_is_one_line_and_nothing_written(runs, logs, tmp_path, capsys,
                                                            case, words):
    """A log instead of a run, a missing directory, a run without ground truth, a run whose
    covariances.npz is cut short or empty: one line naming it, exit 1, no --out.

    Catches: a traceback (the cut npz was zipfile's BadZipFile, the empty one numpy's
    EOFError: a hostile-input hunt's find, 2026-11-28), or a table written without the
    run."""
    bad = {"not_a_run": logs[0], "missing": tmp_path / "nothing"}.get(case)
    if case in ("no_truth", "truncated_npz", "empty_npz"):
        bad = tmp_path / case
        shutil.copytree(runs[0], bad)
    if case == "no_truth":
        (bad / "groundtruth.tum").unlink()
    if case == "truncated_npz":
        npz = bad / "covariances.npz"
        npz.write_bytes(npz.read_bytes()[:300])
    if case == "empty_npz":
        (bad / "covariances.npz").write_bytes(b"")
    out = tmp_path / "eval"
    assert main(["evaluate", str(runs[0]), str(bad), "--out", str(out)]) == 1
    _one_line(capsys.readouterr().err, str(bad), *words)
    assert not out.exists()


@pytest.mark.slow
def test_smooth_many_gives_each_log_the_run_cdtm_smooth_gives_it(logs, singles, tmp_path,
                                                                 capsys):
    """smooth-many (in one process: --workers 1) writes DIR/<log> exactly as four single
    runs, each its own cdtm output directory, and the evaluation beside them; a rerun
    keeps a user's file in DIR.

    Catches: other settings or files than cdtm smooth's, runs not under their own
    manifest (a later `cdtm smooth --out DIR/log0` refused), the evaluation missing."""
    out = tmp_path / "many"
    code = main(["smooth-many", *map(str, logs), "--out", str(out), "--workers", "1",
                 "--quiet"])
    assert code in WROTE_OUTPUTS
    for log in logs:
        single = singles[log.name]
        many = out / log.name
        assert read_manifest(many) == read_manifest(single)
        assert (many / "trajectory.tum").read_text() == (single / "trajectory.tum").read_text()
        a, b = (json.loads((d / "report.json").read_text())["evaluation"]
                for d in (many, single))
        assert a == b
    assert set(read_manifest(out)) == set(EVALUATE_FILES)
    assert {p.name for p in out.iterdir()} == {*EVALUATE_FILES, MANIFEST_NAME,
                                               *(log.name for log in logs)}


@pytest.mark.slow
def test_smooth_many_tasks_run_on_worker_processes(logs, singles, tmp_path):
    """smooth-many's task on two local worker processes (its default backend): the same
    trajectories as `cdtm smooth`.

    Catches: a task that cannot be pickled or run in a worker process."""
    import argparse

    from cdtm_graph.cli.smooth_many import _TASK_OPTIONS, SmoothTask, smooth_task
    from cdtm_graph.parallel import ParallelSettings, map_tasks

    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    from cdtm_graph.cli import smooth_many

    smooth_many.register(sub)
    args = parser.parse_args(["smooth-many", "L", "--out", "O"])
    options = {k: getattr(args, k) for k in _TASK_OPTIONS}
    tasks = [SmoothTask(str(log), str(tmp_path / log.name), options) for log in logs[:2]]
    done = map_tasks(smooth_task, tasks, ParallelSettings(workers=2))
    assert [d.out for d in done] == [t.out for t in tasks]
    for log in logs[:2]:
        assert (tmp_path / log.name / "trajectory.tum").read_text() == (
            singles[log.name] / "trajectory.tum").read_text()


def test_smooth_many_bad_input_is_one_line_before_any_work(logs, tmp_path, capsys):
    """A log without ground truth, a missing log, an --out holding a user's files: one
    line, exit 1, nothing written.

    Catches: a run smoothed (minutes) before the evaluation refuses it."""
    no_truth = tmp_path / "no_truth"
    shutil.copytree(logs[0], no_truth)
    (no_truth / "groundtruth.csv").unlink()
    out = tmp_path / "many"
    assert main(["smooth-many", str(logs[1]), str(no_truth), "--out", str(out)]) == 1
    _one_line(capsys.readouterr().err, str(no_truth), "no groundtruth.csv")
    assert main(["smooth-many", str(logs[1]), str(tmp_path / "nope"), "--out", str(out)]) == 1
    _one_line(capsys.readouterr().err, "nope", "does not exist")
    assert not out.exists()
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.md").write_text("mine")
    assert main(["smooth-many", str(logs[1]), "--out", str(mine)]) == 1
    _one_line(capsys.readouterr().err, "notes.md", "not written by cdtm")
    assert [p.name for p in mine.iterdir()] == ["notes.md"]


@pytest.mark.slow
def test_smooth_many_rerun_keeps_what_it_did_not_write(logs, tmp_path, capsys):
    """A rerun into the same DIR replaces its runs and evaluation and keeps a user's notes
    beside them (in DIR and in a run's directory).

    Catches: DIR refused on the rerun (its runs are not in DIR's manifest), or the user's
    files replaced or deleted."""
    out = tmp_path / "many"
    argv = ["smooth-many", str(logs[0]), "--out", str(out), "--workers", "1", "--quiet"]
    assert main(argv) in WROTE_OUTPUTS
    (out / "notes.md").write_text("mine")
    (out / logs[0].name / "seen.txt").write_text("mine too")
    assert main(argv) in WROTE_OUTPUTS
    assert (out / "notes.md").read_text() == "mine"
    assert (out / logs[0].name / "seen.txt").read_text() == "mine too"
    assert set(read_manifest(out)) == set(EVALUATE_FILES)


def test_smooth_many_writes_logs_of_one_name_inside_out_and_nothing_else(logs, tmp_path,
                                                                          monkeypatch):
    """Two logs of one folder name, given as ``../d1/log`` and ``../d2/log``: their runs
    are ``DIR/d1_log`` and ``DIR/d2_log``, and an earlier run at ``./d1/log`` is left as it
    was. Mutation tried: the run directories named as the table names runs (the path as
    given): the runs went to ``./d1/log`` and ``./d2/log``, outside DIR, replacing the
    earlier run's report.json (a hostile-input hunt's find, 2026-11-28)."""
    for d in ("d1", "d2"):
        shutil.copytree(logs[0], tmp_path / d / "log")
    cwd = tmp_path / "cwd"
    (cwd / "d1").mkdir(parents=True)
    assert main(["smooth", str(logs[1]), "--out", str(cwd / "d1" / "log"), "--quiet"]) in \
        WROTE_OUTPUTS
    before = {p.name: p.read_bytes() for p in (cwd / "d1" / "log").iterdir()}
    monkeypatch.chdir(cwd)
    (cwd / "out").mkdir()
    assert main(["smooth-many", "../d1/log", "../d2/log", "--out", "out", "--workers", "1",
                 "--quiet"]) in WROTE_OUTPUTS
    assert {p.name: p.read_bytes() for p in (cwd / "d1" / "log").iterdir()} == before
    assert sorted(p.name for p in cwd.iterdir()) == ["d1", "out"]
    assert (cwd / "out" / "d1_log" / "report.json").is_file()
    assert (cwd / "out" / "d2_log" / "report.json").is_file()


def test_smooth_many_reads_every_log_before_any_work(logs, tmp_path, capsys, monkeypatch):
    """A log whose flight.yaml is bad (an IMU rate of 0) beside a good one: its one line,
    exit 1, and no run of the good one left in DIR; a log named as an evaluation file, a
    log given twice, a lag under two frame intervals and ground truth on another clock are
    refused alike, no run begun. Mutations tried: the logs not read before the work (the
    good log's run was left in DIR without the evaluation); the lag and the ground truth
    not checked up front (each run refused the lag itself, after the work began; the
    evaluation refused the ground truth after every run)."""
    bad = tmp_path / "bad"
    shutil.copytree(logs[0], bad)
    text = (bad / "flight.yaml").read_text()
    assert "rate_hz:" in text
    (bad / "flight.yaml").write_text(
        "\n".join("  rate_hz: 0" if line.strip().startswith("rate_hz:") else line
                  for line in text.splitlines()) + "\n")
    out = tmp_path / "many"
    assert main(["smooth-many", str(logs[1]), str(bad), "--out", str(out), "--workers",
                 "1"]) == 1
    _one_line(capsys.readouterr().err, "rate_hz")
    assert not out.exists()
    named = tmp_path / "evaluation.csv"
    shutil.copytree(logs[0], named)
    assert main(["smooth-many", str(named), "--out", str(out)]) == 1
    _one_line(capsys.readouterr().err, "DIR/evaluation.csv")
    assert main(["smooth-many", str(logs[0]), str(logs[0]) + "/", "--out", str(out)]) == 1
    _one_line(capsys.readouterr().err, "given twice")
    # what each run would refuse or find, found first: a lag under two frame intervals,
    # ground truth on another clock
    from cdtm_graph.cli import smooth_many
    monkeypatch.setattr(smooth_many, "smooth_task",
                        lambda task: pytest.fail(f"a run began: {task.log}"))
    assert main(["smooth-many", str(logs[1]), "--out", str(out), "--mode", "incremental",
                 "--lag-s", "0.5", "--workers", "1"]) == 1
    _one_line(capsys.readouterr().err, "holds fewer than two frames")
    clock = tmp_path / "clock"
    shutil.copytree(logs[0], clock)
    rows = (clock / "groundtruth.csv").read_text().splitlines()
    (clock / "groundtruth.csv").write_text("\n".join(
        row if row.startswith("#") or not row else
        f"{int(row.split(',', 1)[0]) + 10**12},{row.split(',', 1)[1]}" for row in rows) + "\n")
    assert main(["smooth-many", str(logs[1]), str(clock), "--out", str(out), "--workers",
                 "1"]) == 1
    _one_line(capsys.readouterr().err, "groundtruth.csv: its times cover none of the frames")
    assert not out.exists()


def test_ground_truth_on_another_clock_is_named_by_smooth_and_evaluate(logs, tmp_path,
                                                                       capsys):
    """groundtruth.csv's stamps all moved by 1e12 ns (an epoch against frames from 0): the
    run is made (ground truth is for evaluation only), `cdtm smooth` says on stderr that
    it covers none of the frames, and `cdtm evaluate` says so of the run, not that its log
    had none. Mutation tried: the warning off (the run said `trusted`, RMSE nan, no word:
    a hostile-input hunt's find, 2026-11-28)."""
    log = tmp_path / "clock"
    shutil.copytree(logs[0], log)
    path = log / "groundtruth.csv"
    rows = path.read_text().splitlines()
    path.write_text("\n".join(row if row.startswith("#") or not row else
                              f"{int(row.split(',', 1)[0]) + 10**12},{row.split(',', 1)[1]}"
                              for row in rows) + "\n")
    run = tmp_path / "run"
    assert main(["smooth", str(log), "--out", str(run)]) in WROTE_OUTPUTS
    captured = capsys.readouterr()
    assert "nan" not in captured.out
    warning = [line for line in captured.err.splitlines() if "warning" in line]
    assert len(warning) == 1
    assert "groundtruth.csv: its times cover none of the frames" in warning[0]
    assert main(["evaluate", str(run), "--out", str(tmp_path / "eval")]) == 1
    _one_line(capsys.readouterr().err, "covered none of its frames")
