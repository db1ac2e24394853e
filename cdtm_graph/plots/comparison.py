"""Figures of many runs side by side (``cdtm evaluate``), from :mod:`cdtm_graph.verdict.comparison`.

* ``errors_boxplot.png``: the per-frame |position error| of each run, one box per run,
  per world axis and in 3-D (as OpenVINS' ov_eval compares runs);
* ``errors_over_time.png``: each run's position error per axis with its ±3σ bounds;
* ``nees_over_time.png``: each run's per-frame position NEES against chi-square(3): the
  95% bound the verdict reads, the median expected and the 5% quantile under which a
  median reads conservative.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import NullFormatter, ScalarFormatter

from cdtm_graph.plots.trajectory import DPI, N_SIGMA
from cdtm_graph.verdict.comparison import NEES_DOF, RunSeries
from cdtm_graph.verdict.evaluation import (
    NEES_BOUND_PROBABILITY,
    ConsistencyBounds,
    NeesConsistency,
    nees_bound,
)

AXIS_NAMES = ("x (east)", "y (north)", "z (up)")


def _colours(n: int) -> list:
    from matplotlib import colormaps

    cmap = colormaps["tab10" if n <= 10 else "tab20"]
    return [cmap(i % cmap.N) for i in range(n)]


def plot_error_boxplots(path: str | os.PathLike, names: Sequence[str],
                        series: Sequence[RunSeries]) -> Figure:
    """|position error| per frame, one box per run: x, y, z and 3-D (four panels).

    Returns:
        The figure (already saved); each panel holds one box per run, in order.
    """
    fig = Figure(figsize=(max(6.0, 1.2 + 0.9 * len(names)) * 2, 7.0), dpi=DPI,
                 layout="constrained")
    axes = fig.subplots(2, 2).ravel()
    for a, ax in enumerate(axes):
        if a < 3:
            data = [np.abs(s.position_error_world_m[:, a]) for s in series]
            ax.set_title(f"|error| {AXIS_NAMES[a]}", fontsize=9)
        else:
            data = [np.linalg.norm(s.position_error_world_m, axis=1) for s in series]
            ax.set_title("|error| 3-D", fontsize=9)
        ax.boxplot(data, tick_labels=list(names), showfliers=True)
        ax.set_ylabel("m")
        ax.tick_params(axis="x", labelrotation=30, labelsize=8)
        ax.grid(True, axis="y", alpha=0.3)
    fig.suptitle("Position error per frame (estimate - truth), one box per run")
    fig.savefig(path)
    return fig


def plot_errors_over_time(path: str | os.PathLike, names: Sequence[str],
                          series: Sequence[RunSeries]) -> Figure:
    """Each run's position error per axis (solid) inside its ±3σ bounds (dashed).

    Returns:
        The figure (already saved): three rows (x, y, z); per run one error line labelled
        with the run's name and two bound lines.
    """
    fig = Figure(figsize=(9.0, 8.0), dpi=DPI, layout="constrained")
    axes = fig.subplots(3, 1, sharex=True)
    for name, s, colour in zip(names, series, _colours(len(names)), strict=True):
        for a, ax in enumerate(axes):
            bound = N_SIGMA * s.position_sigma_world_m[:, a]
            ax.plot(s.t_s, s.position_error_world_m[:, a], color=colour, lw=1.1, label=name)
            ax.plot(s.t_s, bound, color=colour, lw=0.8, ls="--")
            ax.plot(s.t_s, -bound, color=colour, lw=0.8, ls="--")
    for a, ax in enumerate(axes):
        ax.set_ylabel(f"{AXIS_NAMES[a]}, m")
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=7, ncol=2)
    axes[0].set_title(f"Position error (solid) and ±{N_SIGMA:g}σ (dashed)")
    axes[-1].set_xlabel("time since the run's first frame, s")
    fig.savefig(path)
    return fig


def plot_nees_over_time(path: str | os.PathLike, names: Sequence[str],
                        series: Sequence[RunSeries]) -> Figure:
    """Each run's per-frame position NEES (log scale) against chi-square(3): its 95% bound
    (what the verdict's share inside reads) and its median.

    Returns:
        The figure (already saved); one line per run labelled with its name, and the two
        horizontal reference lines.
    """
    fig = Figure(figsize=(11.0, 4.5), dpi=DPI, layout="constrained")
    ax = fig.add_subplot()
    for name, s, colour in zip(names, series, _colours(len(names)), strict=True):
        consistency = NeesConsistency.of(s.position_nees, NEES_DOF)
        share = (f" ({100 * consistency.inside_fraction:.0f}% inside)"
                 if consistency is not None else "")
        ax.plot(s.t_s, s.position_nees, color=colour, lw=1.0, marker=".", ms=3,
                label=f"{name}{share}")
    bound = nees_bound(NEES_DOF)
    median = nees_bound(NEES_DOF, 0.5)
    low_q = ConsistencyBounds().conservative_median_quantile
    low = nees_bound(NEES_DOF, low_q)
    ax.axhline(bound, color="black", lw=1.0, ls="--",
               label=f"chi-square({NEES_DOF}) {100 * NEES_BOUND_PROBABILITY:.0f}% bound "
                     f"{bound:.2f}")
    ax.axhline(median, color="0.5", lw=0.8, ls=":", label=f"median expected {median:.2f}")
    ax.axhline(low, color="black", lw=0.8, ls="-.",
               label=f"{100 * low_q:.0f}% quantile {low:.2f} (a median below: conservative)")
    ax.set_yscale("log")
    ax.yaxis.set_major_formatter(ScalarFormatter())
    ax.yaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("time since the run's first frame, s")
    ax.set_ylabel(f"position NEES ({NEES_DOF} dof)")
    ax.set_title("Per-frame NEES: an honest covariance keeps ~95% of frames under the bound")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7)
    fig.savefig(path)
    return fig
