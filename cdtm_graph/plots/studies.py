"""Figures of the sensitivity studies, laid out like the paper's Figs. 2-9.

(a) camera-2 position and attitude, (b) ego-motion translation and rotation: the
closed-form prediction as a line, the Monte Carlo RMS error as markers, lengths on the
left axis and angles on the right. A strip below shows the share of failed trials
(degenerate or not converged), so a breakdown reads as failures, not as wild numbers:
values with fewer than :data:`MIN_GOOD_TRIALS_PLOTTED` good trials are not drawn above it
(the CSV keeps them, with their counts).
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import FormatStrFormatter

from cdtm_graph.studies.sweeps import SWEEPS, StudyResult

#: Values with fewer good trials than this are left out of the curves (too noisy to show).
MIN_GOOD_TRIALS_PLOTTED = 10
#: A y axis spanning more than this ratio is drawn in log scale.
_LOG_SCALE_RATIO = 10.0
#: Free space above the data, as a fraction of the axis span (the legend goes there).
_LEGEND_HEADROOM = 0.6
_LENGTH_COLOR = "tab:blue"
_ANGLE_COLOR = "tab:red"


def _scale_axis(ax, *columns: np.ndarray) -> None:
    """Log scale for a wide range, else linear from zero; headroom at the top for the legend."""
    values = np.concatenate([c[np.isfinite(c) & (c > 0)] for c in columns])
    if values.size == 0:
        return
    lo, hi = values.min(), values.max()
    if hi > _LOG_SCALE_RATIO * lo:
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(FormatStrFormatter("%.3g"))
        ax.yaxis.set_minor_formatter(FormatStrFormatter("%.3g"))
        ax.set_ylim(lo / 1.2, hi * (hi / lo) ** _LEGEND_HEADROOM)
    else:  # from zero: a 10 % wiggle must not look like a trend
        ax.set_ylim(0.0, hi * (1 + _LEGEND_HEADROOM))


def _panel(ax, x: np.ndarray, result: StudyResult, length: str, angle: str,
           length_label: str, angle_label: str, title: str) -> None:
    good = result.column("trials") - result.column("failures") >= MIN_GOOD_TRIALS_PLOTTED

    def column(name: str) -> np.ndarray:
        return np.where(good, result.column(name), np.nan)

    pred_l, err_l = column(f"pred_sigma_{length}"), column(f"rms_err_{length}")
    pred_a, err_a = column(f"pred_sigma_{angle}"), column(f"rms_err_{angle}")
    ax.plot(x, pred_l, "-", color=_LENGTH_COLOR, label=f"{length_label}: predicted 1-sigma")
    ax.plot(x, err_l, "o", color=_LENGTH_COLOR, mfc="none", label=f"{length_label}: RMS error")
    ax.set_ylabel(f"{length_label} [m]", color=_LENGTH_COLOR)
    ax.tick_params(axis="y", colors=_LENGTH_COLOR)
    _scale_axis(ax, pred_l, err_l)
    twin = ax.twinx()
    twin.plot(x, pred_a, "--", color=_ANGLE_COLOR, label=f"{angle_label}: predicted 1-sigma")
    twin.plot(x, err_a, "s", color=_ANGLE_COLOR, mfc="none", label=f"{angle_label}: RMS error")
    twin.set_ylabel(f"{angle_label} [deg]", color=_ANGLE_COLOR)
    twin.tick_params(axis="y", colors=_ANGLE_COLOR)
    _scale_axis(twin, pred_a, err_a)
    ax.set_title(title, fontsize=10)
    ax.grid(True, alpha=0.3)
    lines = ax.get_lines() + twin.get_lines()
    ax.legend(lines, [line.get_label() for line in lines], fontsize=7, loc="upper right")


def study_figure(result: StudyResult) -> Figure:
    """The two-panel figure of one study (no pyplot state; save with ``fig.savefig``).

    Args:
        result: a finished study.

    Returns:
        A matplotlib figure, 11 x 5.5 inches.
    """
    sweep = SWEEPS[result.parameter]
    x = np.asarray(result.values, dtype=float)
    fig = Figure(figsize=(11, 5.5), layout="constrained")
    grid = fig.add_gridspec(2, 2, height_ratios=(4, 1))
    ax_a = fig.add_subplot(grid[0, 0])
    ax_b = fig.add_subplot(grid[0, 1])
    _panel(ax_a, x, result, "pos2_m", "att2_deg", "position", "attitude",
           "(a) camera pose at the second frame")
    _panel(ax_b, x, result, "t12_m", "r12_deg", "translation |p12|", "rotation |alpha12|",
           "(b) recovered ego-motion")
    failed = 100.0 * result.column("failures") / result.column("trials")
    width = 0.6 * np.min(np.diff(np.sort(x))) if x.size > 1 else 1.0
    for col in range(2):
        ax_f = fig.add_subplot(grid[1, col], sharex=(ax_a, ax_b)[col])
        ax_f.bar(x, failed, width=width, color="0.4")
        ax_f.set_ylim(0, 100)
        ax_f.set_ylabel("failed [%]")
        ax_f.set_title(f"failed trials (values with < {MIN_GOOD_TRIALS_PLOTTED} good trials "
                       "are not drawn above)", fontsize=8)
        ax_f.set_xlabel(sweep.label)
        ax_f.grid(True, alpha=0.3)
    trials = int(result.settings.trials)
    fig.suptitle(f"C-DTM two-frame accuracy vs {sweep.label} ({trials} trials per value, "
                 f"seed {result.settings.seed}; cf. paper {sweep.paper_figure})", fontsize=11)
    return fig
