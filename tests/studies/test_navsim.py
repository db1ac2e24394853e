"""The paper's navigation simulation (section VI.A, Tables 1-2): accuracy, layout, CLI."""

from __future__ import annotations

import csv
import io

import numpy as np
import pytest

from cdtm_graph.atomic import MANIFEST_NAME
from cdtm_graph.cli import build_parser
from cdtm_graph.cli import main as cdtm_main
from cdtm_graph.cli.navsim import OUTPUT_FILES, settings_from_args
from cdtm_graph.errors import CdtmError, SimulationError
from cdtm_graph.sim.simulate import simulate
from cdtm_graph.studies.navsim import (
    PAPER_TABLE1_M,
    PAPER_TABLE2_M,
    Estimator,
    NavsimSettings,
    TableKind,
    as_arrived_estimate,
    run_navsim,
    table_csv,
    table_markdown,
)
from cdtm_graph.verdict.evaluation import AXES

#: Compensated (either kind) must beat Free by at least this factor: on each horizontal
#: axis and in 3-D. Vertical Free drift comes mostly from one draw of the z accelerometer
#: bias and can be small on a short flight (6 m after 120 s with the test seed), so z is
#: only required not to be worse than Free.
FREE_OVER_COMPENSATED_MIN = 5.0
HORIZONTAL = slice(0, 2)
#: Reduced flight: long enough for Free to drift well past the paper's compensated
#: numbers (tens to hundreds of metres), short enough for seconds of computing.
REDUCED_DURATION_S = 120.0
ALTITUDE_M = 1000.0
#: The as-arrived estimate of frame 0 is the prior mean: only round-off apart (m).
PRIOR_MEAN_ATOL_M = 1e-6
#: A smoothed frame 0 moves off the prior mean by far more than round-off (m); the prior
#: is 5 m (1 sigma) per axis, the smoothed error ~1 m.
SMOOTHED_MOVES_FRAME0_M = 0.1

ROW_LABELS = [
    "Free-x", "Compensated-x (smoothed)", "Compensated-x (as arrived)",
    "Free-y", "Compensated-y (smoothed)", "Compensated-y (as arrived)",
    "Free-z", "Compensated-z (smoothed)", "Compensated-z (as arrived)",
]


@pytest.fixture(scope="module")
def reduced(seed) -> NavsimSettings:
    """One altitude, two resolutions (the 1000x1000 case is both tables' only shared one)."""
    return NavsimSettings(altitudes_m=(ALTITUDE_M,), resolutions_px=(500, 1000),
                          table2_altitude_m=ALTITUDE_M, duration_s=REDUCED_DURATION_S,
                          seed=seed)


@pytest.fixture(scope="module")
def result(reduced):
    return run_navsim(reduced)


@pytest.fixture(scope="module")
def case(result):
    return result.table1.cases[0]


def _max_3d_m(report) -> float:
    """Largest |p_est - p_true| over the evaluated frames (m)."""
    return float(np.max(np.linalg.norm(report.position_error_world_m, axis=1)))


def _assert_far_below_free(case, estimator: Estimator) -> None:
    free = case.max_error_m(Estimator.FREE)
    ours = case.max_error_m(estimator)
    assert np.all(free[HORIZONTAL] >= FREE_OVER_COMPENSATED_MIN * ours[HORIZONTAL]), (free, ours)
    assert free[2] >= ours[2], (free, ours)
    assert (_max_3d_m(case.free)
            >= FREE_OVER_COMPENSATED_MIN * _max_3d_m(case.report(estimator)))


@pytest.mark.slow
def test_compensated_far_below_free_and_below_the_papers_filter(case):
    _assert_far_below_free(case, Estimator.SMOOTHED)
    smoothed = case.max_error_m(Estimator.SMOOTHED)
    paper = np.array([PAPER_TABLE1_M[ALTITUDE_M][("Compensated", a)] for a in AXES])
    assert np.all(smoothed <= paper), (smoothed, paper)
    # Free really drifts: past the paper's compensated numbers horizontally.
    assert np.all(case.max_error_m(Estimator.FREE)[HORIZONTAL] > paper[HORIZONTAL])


@pytest.mark.slow
def test_as_arrived_is_worse_than_smoothed_but_far_below_free(case):
    smoothed = case.max_error_m(Estimator.SMOOTHED)
    arrived = case.max_error_m(Estimator.AS_ARRIVED)
    # A smoother uses later frames for earlier ones; a filter-like estimate cannot.
    assert arrived.mean() >= smoothed.mean(), (arrived, smoothed)
    _assert_far_below_free(case, Estimator.AS_ARRIVED)
    # Frame 0 (the prior, no image pair yet) is left out; every other frame is in.
    assert case.as_arrived.n_frames_evaluated == case.frames - 1
    assert case.smoothed.n_frames_evaluated == case.frames
    assert case.free.n_frames_evaluated == case.frames


@pytest.mark.slow
def test_as_arrived_estimate_is_never_revised_by_later_frames(reduced):
    sim = simulate(reduced.simulation(3000.0, 500))  # the cheapest flight: 41 frames
    flight = sim.log
    arrived = as_arrived_estimate(flight, sim.dtm)
    prior = flight.config.initial_state.world_T_body[:3, 3]
    # Frame 0 keeps the estimate it had on arrival, the prior mean, although the later
    # frames (which the smoother uses) move it.
    np.testing.assert_allclose(arrived.position_m[0], prior, atol=PRIOR_MEAN_ATOL_M)
    from cdtm_graph.smoother import SmootherSettings, smooth
    smoothed = smooth(flight, sim.dtm, SmootherSettings(marginals=False)).estimate
    assert np.linalg.norm(smoothed.position_m[0] - prior) > SMOOTHED_MOVES_FRAME0_M


def test_frame_interval_keeps_the_baseline_a_fifth_of_the_altitude():
    settings = NavsimSettings()
    assert settings.frame_interval_s(1000.0) == pytest.approx(1.0)
    assert settings.frame_interval_s(3000.0) == pytest.approx(3.0)
    # 300 s of flight: every whole interval, the first frame at t = 0.
    assert [settings.frames(a) for a in (700.0, 1000.0, 3000.0)] == [429, 301, 101]
    sim = settings.simulation(3000.0, 4000)
    assert sim.resolution_px == (4000, 4000) and sim.fps == pytest.approx(1 / 3)
    assert sim.speed_mps == 200.0 and sim.fov_deg == 60.0 and 100 <= sim.n_features <= 120


@pytest.mark.slow
def test_a_case_both_tables_share_is_flown_once(result):
    assert result.table2.columns == (500, 1000)
    assert result.table2.cases[1] is result.table1.cases[0]
    assert result.table2.cases[0].resolution_px == 500


def _markdown_rows(text: str) -> list[list[str]]:
    return [[c.strip() for c in line.strip().strip("|").split("|")]
            for line in text.splitlines() if line.startswith("|")]


@pytest.mark.slow
def test_markdown_has_the_papers_rows_and_columns_with_its_numbers_beside_ours(result):
    rows = _markdown_rows(table_markdown(result.table1))
    assert rows[0] == ["Flight height", "1000 m", "paper"]
    body = rows[2:]
    assert [r[0] for r in body] == ROW_LABELS
    case = result.table1.cases[0]
    for r, row in zip(body, result.table1.rows(), strict=True):
        assert float(r[1]) == pytest.approx(
            case.max_error_m(row.estimator)[AXES.index(row.axis)], abs=0.5)
        paper = PAPER_TABLE1_M[ALTITUDE_M][(row.estimator.paper_row, row.axis)]
        assert r[2] == f"{paper:g}"
    assert body[0][2] == "130" and body[1][2] == "20"  # Free-x, Compensated-x at 1000 m

    rows2 = _markdown_rows(table_markdown(result.table2))
    assert rows2[0] == ["Resolution", "500x500", "paper", "1000x1000", "paper"]
    body2 = {r[0]: r[1:] for r in rows2[2:]}
    assert list(body2) == ROW_LABELS
    assert body2["Free-x"][1] == "–"  # the paper's Table 2 has no Free rows
    assert body2["Compensated-x (smoothed)"][1] == "50"
    assert body2["Compensated-z (as arrived)"][1] == "35"
    assert body2["Compensated-y (smoothed)"][3] == "20"


@pytest.mark.slow
def test_csv_holds_the_same_table_unrounded(result):
    for table, paper in ((result.table1, PAPER_TABLE1_M), (result.table2, PAPER_TABLE2_M)):
        rows = list(csv.reader(io.StringIO(table_csv(table))))
        labels = [table.column_label(c) for c in table.columns]
        assert rows[0] == ["row"] + [x for lab in labels for x in (lab, f"{lab} paper")]
        assert [r[0] for r in rows[1:]] == ROW_LABELS
        for r, row in zip(rows[1:], table.rows(), strict=True):
            for j, (col, case) in enumerate(zip(table.columns, table.cases, strict=True)):
                ours = case.max_error_m(row.estimator)[AXES.index(row.axis)]
                assert float(r[1 + 2 * j]) == ours
                expected = paper.get(col, {}).get((row.estimator.paper_row, row.axis))
                assert r[2 + 2 * j] == ("" if expected is None else f"{expected:g}")
    assert result.table1.kind is TableKind.ALTITUDE
    assert result.table2.kind is TableKind.RESOLUTION


@pytest.mark.parametrize("changes", [
    dict(altitudes_m=(-700.0,)),
    dict(altitudes_m=()),
    dict(altitudes_m=(1000.0, 1000.0)),
    dict(resolutions_px=(500.5,)),
    dict(duration_s=0.5),   # one frame at 1000 m
    dict(seed=-1),  # an invalid seed: the literal is the point
])
def test_bad_settings_are_user_errors(changes):
    with pytest.raises(SimulationError):
        NavsimSettings(**changes)


def test_frames_option_sets_the_duration_at_the_table2_altitude():
    args = build_parser().parse_args(["navsim", "--frames", "31"])
    settings = settings_from_args(args)
    assert settings.duration_s == pytest.approx(30.0)
    assert settings.frames(settings.table2_altitude_m) == 31
    with pytest.raises(CdtmError):
        settings_from_args(build_parser().parse_args(["navsim", "--frames", "1"]))


@pytest.mark.slow
def test_cli_writes_the_four_tables_and_prints_them(seed, tmp_path, capsys):
    out = tmp_path / "navsim"
    code = cdtm_main(["navsim", "--out", str(out), "--quick", "--altitudes", "3000",
                      "--resolutions", "1000", "--seed", str(seed), "--quiet"])
    assert code == 0
    assert sorted(p.name for p in out.iterdir()) == sorted([*OUTPUT_FILES, MANIFEST_NAME])
    printed = capsys.readouterr().out
    table1 = (out / "table1.md").read_text()
    table2 = (out / "table2.md").read_text()
    assert table1 in printed and table2 in printed
    assert _markdown_rows(table1)[0] == ["Flight height", "3000 m", "paper"]
    rows = list(csv.reader(io.StringIO((out / "table2.csv").read_text())))
    assert rows[0] == ["row", "1000x1000", "1000x1000 paper"] and len(rows) == 10
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporaries


@pytest.mark.parametrize("argv, word", [
    (["--altitudes", "-700"], "altitudes_m"),
    (["--resolutions", "0"], "resolutions_px"),
    (["--frames", "1"], "--frames"),
])
def test_cli_bad_argument_is_one_line_exit_1_and_writes_nothing(tmp_path, capsys, argv, word):
    out = tmp_path / "navsim"
    code = cdtm_main(["navsim", "--out", str(out), *argv])
    assert code == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("cdtm navsim: error:") and word in err[0]
    assert not out.exists()


def test_cli_refuses_to_replace_a_directory_that_is_not_its_own(tmp_path, capsys):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    code = cdtm_main(["navsim", "--out", str(out), "--quick"])
    assert code == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'notes.txt'" in err[0] and "not written by cdtm" in err[0]
    assert (out / "notes.txt").read_text() == "keep me"
    assert [p.name for p in out.iterdir()] == ["notes.txt"]
