"""Many runs side by side (``cdtm evaluate``): one table row and per-frame series per run.

Pure: no file I/O (:func:`cdtm_graph.outputs.read_run` reads a run directory, the CLI
writes, :mod:`cdtm_graph.plots.comparison` draws). The table's figures are report.json's
(``evaluation.compensated``: RMSE and maximum per axis, ANEES, the per-frame NEES
consistency); the per-frame series are taken again from the run's files by
:func:`cdtm_graph.verdict.evaluation.trajectory_errors`, the function that filled report.json,
and must agree with it (:data:`REPORT_AGREEMENT_M`): a run directory whose files were
mixed with another run's is named, not averaged.
"""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import PurePath
from typing import Any

import numpy as np

from cdtm_graph.errors import CdtmError
from cdtm_graph.flightlog import States
from cdtm_graph.geometry import rotation_to_quat_wxyz
from cdtm_graph.outputs import REPORT_JSON, RunFiles
from cdtm_graph.results import StateCovariances, TrajectoryEstimate
from cdtm_graph.verdict.evaluation import NEES_PERCENTILES, POSITION_DOF, trajectory_errors

NS_PER_S = 1_000_000_000
#: The position RMSE taken again from a run's files must equal report.json's to this (m).
REPORT_AGREEMENT_M = 1e-3
#: Degrees of freedom of the per-frame NEES the series and the figures show (position).
NEES_DOF = POSITION_DOF


@dataclass(frozen=True)
class RunSeries:
    """One run's errors frame by frame, at the frames its ground truth covers (M).

    Attributes:
        frame: (M,) indices of the run's frames (frames.csv).
        t_s: (M,) seconds since the run's first frame.
        position_error_world_m: (M, 3) estimate - truth, world axes (ENU).
        position_sigma_world_m: (M, 3) 1-sigma of the world-frame position covariance.
        position_nees: (M,) per-frame NEES of the position (3 dof; NaN without a
            covariance).
        rmse_position_3d_m: of ``position_error_world_m``.
    """

    frame: np.ndarray
    t_s: np.ndarray
    position_error_world_m: np.ndarray
    position_sigma_world_m: np.ndarray
    position_nees: np.ndarray
    rmse_position_3d_m: float


@dataclass(frozen=True)
class RunRow:
    """One run's line of the table (report.json's figures).

    Attributes:
        name: how the table names the run (its directory).
        log: the flight log it smoothed. mode: solver and the settings that differ from
            the defaults, in words.
        n_frames: frames evaluated against ground truth.
        rmse_position_m, max_abs_position_error_m: (x, y, z) world axes, m.
        rmse_position_3d_m: m.
        anees_position, anees_pose: mean NEES (3 and 6 expected), None without.
        nees_percentiles: NEES_PERCENTILES -> per-frame position NEES there.
        inside_fraction: share of frames inside the chi-square(3) 95% bound (~0.95).
        verdict: trusted, degraded or failed. reasons: ``code frames a-b`` each.
        time_s: the run's total time (report.json ``timings_s.total``).
    """

    name: str
    log: str
    mode: str
    n_frames: int
    rmse_position_m: tuple[float, float, float]
    rmse_position_3d_m: float
    max_abs_position_error_m: tuple[float, float, float]
    anees_position: float | None
    anees_pose: float | None
    nees_percentiles: dict[float, float | None]
    inside_fraction: float | None
    verdict: str
    reasons: tuple[str, ...]
    time_s: float | None


def run_series(files: RunFiles) -> RunSeries:
    """The per-frame errors, sigmas and NEES of a run read back (it needs ground truth).

    Raises:
        CdtmError: no ground truth, or the files disagree with report.json's RMSE.
    """
    if files.groundtruth_t_ns is None or files.groundtruth_world_T_body is None:
        raise CdtmError(f"{files.directory}: no ground truth; expected runs of logs with "
                        "ground truth")
    k = len(files.t_ns)
    zeros = np.zeros((k, 3))
    estimate = TrajectoryEstimate(files.t_ns, files.world_T_body, zeros, zeros, zeros)
    covariances = StateCovariances(files.pose_covariance, np.zeros((k, 3, 3)),
                                   np.zeros((k, 6, 6)))
    T_true = files.groundtruth_world_T_body
    m = len(files.groundtruth_t_ns)
    truth = States(files.groundtruth_t_ns, T_true[:, :3, 3],
                   rotation_to_quat_wxyz(T_true[:, :3, :3]), np.zeros((m, 3)))
    errors = trajectory_errors(estimate, covariances, truth)
    reported = _compensated(files).get("rmse_position_3d_m")
    if reported is None or not abs(errors.rmse_position_3d_m - reported) <= REPORT_AGREEMENT_M:
        raise CdtmError(f"{files.directory}: the position RMSE of its trajectory and ground "
                        f"truth files, {errors.rmse_position_3d_m:.4f} m, is not {REPORT_JSON}'s "
                        f"{reported}; expected the files of one run")
    frame = np.flatnonzero(errors.evaluated)
    sigma = (errors.position_sigma_world_m if errors.position_sigma_world_m is not None
             else np.full((m, 3), np.nan))
    nees = errors.position_nees if errors.position_nees is not None else np.full(m, np.nan)
    return RunSeries(frame, (errors.t_ns - files.t_ns[0]) / NS_PER_S,
                     errors.position_error_world_m, sigma, nees, errors.rmse_position_3d_m)


def _compensated(files: RunFiles) -> dict[str, Any]:
    evaluation = files.report.get("evaluation")
    compensated = evaluation.get("compensated") if isinstance(evaluation, dict) else None
    if not isinstance(compensated, dict):
        raise CdtmError(f"{files.directory / REPORT_JSON}: no evaluation against ground "
                        "truth; expected runs of logs with ground truth")
    return compensated


def mode_words(settings: Mapping[str, Any]) -> str:
    """report.json's settings in a few words: ``batch``, ``incremental, lag 10 s``, with
    the calibration, plane and kernel when not the defaults."""
    graph = settings.get("graph") or {}
    words = [str(settings.get("mode", "?"))]
    if settings.get("lag_s") is not None:
        words[0] += f", lag {settings['lag_s']:g} s"
    if graph.get("calibration_online"):
        words.append("calibration online")
    elif "calibration" in graph and graph["calibration"] is None:
        words.append("calibration held")
    if graph.get("plane_mode", "reintersect") != "reintersect":
        words.append(f"plane {graph['plane_mode']}")
    if graph.get("robust", "cauchy") != "cauchy":
        words.append(f"robust {graph['robust']}")
    return ", ".join(words)


def run_row(name: str, files: RunFiles) -> RunRow:
    """The table's row of a run, from its report.json."""
    report = files.report
    c = _compensated(files)
    consistency = c.get("position_consistency") or {}
    percentiles = consistency.get("nees_percentiles") or {}
    reasons = tuple(
        f"{r.get('code')} frames {r.get('first_frame')}-{r.get('last_frame')}"
        for r in report.get("reasons") or [] if isinstance(r, dict))
    return RunRow(
        name=name, log=str(report.get("input", "")),
        mode=mode_words(report.get("settings") or {}),
        n_frames=int(c.get("n_frames_evaluated") or 0),
        rmse_position_m=_xyz(c.get("rmse_position_m")),
        rmse_position_3d_m=_number(c.get("rmse_position_3d_m")),
        max_abs_position_error_m=_xyz(c.get("max_abs_position_error_m")),
        anees_position=c.get("anees_position"), anees_pose=c.get("anees_pose"),
        nees_percentiles={p: percentiles.get(f"p{p:g}") for p in NEES_PERCENTILES},
        inside_fraction=consistency.get("inside_fraction"),
        verdict=str(report.get("verdict", "?")), reasons=reasons,
        time_s=(report.get("timings_s") or {}).get("total"))


def _number(value: Any) -> float:
    return math.nan if value is None else float(value)


def _xyz(per_axis: Any) -> tuple[float, float, float]:
    """report.json's ``{"x": .., "y": .., "z": ..}`` (None where not finite) as floats."""
    d = per_axis if isinstance(per_axis, dict) else {}
    return _number(d.get("x")), _number(d.get("y")), _number(d.get("z"))


def _g(value: float | None, digits: int = 3) -> str:
    if value is None or not math.isfinite(value):
        return ""
    return f"{value:.{digits}g}"


#: The table's columns: header, value as text (the CSV keeps full precision).
_COLUMNS: tuple[tuple[str, Callable[[RunRow], Any]], ...] = (
    ("run", lambda r: r.name),
    ("log", lambda r: r.log),
    ("mode", lambda r: r.mode),
    ("frames", lambda r: r.n_frames),
    ("rmse_x_m", lambda r: r.rmse_position_m[0]),
    ("rmse_y_m", lambda r: r.rmse_position_m[1]),
    ("rmse_z_m", lambda r: r.rmse_position_m[2]),
    ("rmse_3d_m", lambda r: r.rmse_position_3d_m),
    ("max_x_m", lambda r: r.max_abs_position_error_m[0]),
    ("max_y_m", lambda r: r.max_abs_position_error_m[1]),
    ("max_z_m", lambda r: r.max_abs_position_error_m[2]),
    ("anees_position", lambda r: r.anees_position),
    ("anees_pose", lambda r: r.anees_pose),
    *((f"nees_p{p:g}", (lambda r, p=p: r.nees_percentiles.get(p))) for p in NEES_PERCENTILES),
    ("inside_95", lambda r: r.inside_fraction),
    ("verdict", lambda r: r.verdict),
    ("reasons", lambda r: "; ".join(r.reasons)),
    ("time_s", lambda r: r.time_s),
)
TABLE_COLUMNS = tuple(name for name, _ in _COLUMNS)


def table_csv(rows: Sequence[RunRow]) -> str:
    """The table as CSV (one header line; floats in shortest round-trip form, empty where
    there is no value)."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(TABLE_COLUMNS)
    for row in rows:
        values = [get(row) for _, get in _COLUMNS]
        writer.writerow(["" if v is None or (isinstance(v, float) and not math.isfinite(v))
                         else repr(v) if isinstance(v, float) else v for v in values])
    return out.getvalue()


def table_markdown(rows: Sequence[RunRow]) -> str:
    """The table as Markdown (3 significant digits, the inside share in percent)."""
    def cell(name: str, value: Any) -> str:
        if name == "inside_95":
            return "" if value is None else f"{100 * value:.0f}%"
        if isinstance(value, float) or value is None:
            return _g(value, 4 if name == "time_s" else 3)
        return str(value).replace("|", "\\|")

    lines = ["| " + " | ".join(TABLE_COLUMNS) + " |",
             "|" + "|".join("---" for _ in TABLE_COLUMNS) + "|"]
    for row in rows:
        lines.append("| " + " | ".join(cell(name, get(row)) for name, get in _COLUMNS) + " |")
    return "\n".join(lines) + "\n"


def run_names(directories: Sequence[str]) -> list[str]:
    """How the table names each run: its directory's name, or the path as given when two
    runs share a name."""
    base = [PurePath(os.path.normpath(d)).name or str(d) for d in directories]
    return [b if base.count(b) == 1 else str(d) for b, d in zip(base, directories, strict=True)]
