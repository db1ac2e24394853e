"""The verdict along the flight: which frames carry which flag, and the reasons' spans.

``verdict.png`` (``cdtm smooth --plots``): frames of frames.csv on the x axis; one row
per flag code with a mark at every flagged frame; each reason shaded over its frames in
the colour of what it makes the run (degraded, failed), its code written on it and a bar
on its code's row (a reason such as ``overconfident`` flags no single frame); the
reasons' lines (what the CLI prints) under the axes.
"""

from __future__ import annotations

import os
import textwrap

import numpy as np
from matplotlib.figure import Figure

from cdtm_graph.plots.trajectory import DPI
from cdtm_graph.verdict.outcome import Status, Verdict

#: Colour of each status (the title's and the reasons' spans).
STATUS_COLOURS = {Status.TRUSTED: "tab:green", Status.DEGRADED: "tab:orange",
                  Status.FAILED: "tab:red"}
#: Reason lines under the axes are wrapped at this many characters; at most this many
#: lines are shown (report.json has them all).
WRAP_CHARS = 130
MAX_TEXT_LINES = 14


def plot_verdict(path: str | os.PathLike, verdict: Verdict, n_frames: int) -> Figure:
    """Flags per frame and the reasons' spans along the flight.

    Args:
        path: PNG to write.
        verdict: the run's verdict (``RunOutput.verdict``).
        n_frames: frames in the run (the x axis: 0 .. n_frames - 1).

    Returns:
        The figure (already saved). ``fig.axes[0]`` holds one scatter per flag code,
        labelled with the code, at the flagged frames.
    """
    codes = sorted({name for names in verdict.flags.values() for name in names}
                   | {r.code for r in verdict.reasons if r.first_frame != 0
                      or r.last_frame != n_frames - 1})
    text_lines = [line for r in verdict.reasons
                  for line in textwrap.wrap(r.line(), WRAP_CHARS, subsequent_indent="    ")]
    shown = text_lines[:MAX_TEXT_LINES]
    if len(text_lines) > MAX_TEXT_LINES:
        shown.append(f"... ({len(text_lines) - MAX_TEXT_LINES} more lines: report.json)")
    rows = max(1, len(codes))
    fig = Figure(figsize=(10.0, 1.6 + 0.35 * rows + 0.16 * len(shown)), dpi=DPI,
                 layout="constrained")
    ax = fig.add_subplot()
    for reason in verdict.reasons:
        colour = STATUS_COLOURS[reason.status]
        ax.axvspan(reason.first_frame - 0.5, reason.last_frame + 0.5, color=colour,
                   alpha=0.15, lw=0, zorder=0)
        ax.text((reason.first_frame + reason.last_frame) / 2, rows - 0.45, reason.code,
                ha="center", va="top", fontsize=7, color=colour, clip_on=True)
    for reason in verdict.reasons:  # a bar on its code's row over its frames
        if reason.code in codes:
            ax.hlines(codes.index(reason.code), reason.first_frame - 0.4,
                      reason.last_frame + 0.4, color=STATUS_COLOURS[reason.status], lw=7,
                      alpha=0.45, zorder=1)
    for row, code in enumerate(codes):
        frames = np.array(sorted(k for k, names in verdict.flags.items() if code in names))
        ax.scatter(frames, np.full(frames.shape, row), marker="s", s=14, color="tab:purple",
                   label=code, zorder=2)
    ax.set_yticks(range(len(codes)), codes, fontsize=8)
    ax.set_ylim(-0.7, rows - 0.3)
    ax.set_xlim(-0.5, max(n_frames, 1) - 0.5)
    ax.set_xlabel("frame (index in frames.csv)")
    ax.grid(True, axis="x", alpha=0.3)
    flagged = len(verdict.flags)
    ax.set_title(f"verdict: {verdict.status.value}; {len(verdict.reasons)} reason(s), "
                 f"{flagged} of {n_frames} frames flagged", fontsize=10,
                 color=STATUS_COLOURS[verdict.status])
    if not codes:
        ax.text(0.5, 0.5, "no frame flagged", transform=ax.transAxes, ha="center",
                va="center", color="0.4")
    if shown:
        ax.set_xlabel("frame (index in frames.csv)\n\n" + "\n".join(shown), fontsize=7,
                      loc="left")
    fig.savefig(path)
    return fig
