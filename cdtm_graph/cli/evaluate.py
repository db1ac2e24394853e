"""``cdtm evaluate RUN... --out DIR``: several run directories in one table and figures."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from cdtm_graph.cli import COMMANDS
from cdtm_graph.cli.outdir import add_out_option, output_dir

#: The files ``cdtm evaluate`` (and ``cdtm smooth-many``) write, and who the manifest says
#: wrote them.
EVALUATE_WRITER = "evaluate"
TABLE_CSV = "evaluation.csv"
TABLE_MARKDOWN = "evaluation.md"
BOXPLOT_PNG = "errors_boxplot.png"
ERRORS_OVER_TIME_PNG = "errors_over_time.png"
NEES_OVER_TIME_PNG = "nees_over_time.png"
EVALUATE_FILES = (TABLE_CSV, TABLE_MARKDOWN, BOXPLOT_PNG, ERRORS_OVER_TIME_PNG,
                  NEES_OVER_TIME_PNG)

DESCRIPTION = f"""\
Compare run directories of cdtm smooth (any mix of logs, modes and settings; each with
ground truth) in one table and three figures written into --out:
  {TABLE_CSV}, {TABLE_MARKDOWN}  one row per run: RMSE and maximum error per axis (m),
      3-D RMSE, ANEES (position 3, pose 6 expected), per-frame position NEES percentiles
      and the share of frames inside the chi-square(3) 95% bound (~95% expected), the
      verdict and its reasons, the run's time
  {BOXPLOT_PNG}  |position error| per frame, one box per run (x, y, z, 3-D)
  {ERRORS_OVER_TIME_PNG}  each run's error per axis inside its +-3 sigma
  {NEES_OVER_TIME_PNG}  each run's per-frame NEES against the chi-square(3) bounds
The table's figures are report.json's; the per-frame ones are taken from trajectory.tum,
groundtruth.tum and covariances.npz."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("evaluate", help=COMMANDS["evaluate"].summary,
                       description=DESCRIPTION,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", metavar="RUN", help="run directories of cdtm smooth")
    add_out_option(p, "directory for the table and the figures")
    p.add_argument("--quiet", action="store_true", help="do not print the table")
    p.set_defaults(func=run)


def write_evaluation(runs: Sequence[str | os.PathLike], out_dir: str | os.PathLike,
                     args: argparse.Namespace, *, protected: Sequence[str | os.PathLike] = (),
                     force: bool | None = None) -> str:
    """Read the runs, write the table and figures into ``out_dir`` (atomically, under the
    --out rules); the Markdown table.

    Args:
        force: overrides ``args.force`` (``smooth-many``, which checked ``out_dir``
            before it wrote its runs there).

    Raises:
        CdtmError: a directory that is not a run, or a run without ground truth (one line
            naming it); ``out_dir`` may not be written.
    """
    from cdtm_graph.outputs import read_run
    from cdtm_graph.plots.comparison import (
        plot_error_boxplots,
        plot_errors_over_time,
        plot_nees_over_time,
    )
    from cdtm_graph.verdict.comparison import (
        run_names,
        run_row,
        run_series,
        table_csv,
        table_markdown,
    )

    if force is not None:
        args = argparse.Namespace(**{**vars(args), "force": force})
    with output_dir(args, out_dir, EVALUATE_WRITER, protected=protected,
                    names=EVALUATE_FILES) as staging:
        names = run_names([os.fspath(r) for r in runs])
        files = [read_run(r, require_groundtruth=True) for r in runs]
        series = [run_series(f) for f in files]
        rows = [run_row(name, f) for name, f in zip(names, files, strict=True)]
        markdown = table_markdown(rows)
        (staging / TABLE_CSV).write_text(table_csv(rows))
        (staging / TABLE_MARKDOWN).write_text(markdown)
        plot_error_boxplots(staging / BOXPLOT_PNG, names, series)
        plot_errors_over_time(staging / ERRORS_OVER_TIME_PNG, names, series)
        plot_nees_over_time(staging / NEES_OVER_TIME_PNG, names, series)
    return markdown


def run(args: argparse.Namespace) -> int:
    out_dir = Path(args.out)
    markdown = write_evaluation(args.runs, out_dir, args, protected=args.runs)
    if not args.quiet:
        print(markdown, end="")
        print(f"-> {out_dir}: {', '.join(EVALUATE_FILES)}", file=sys.stderr)
    return 0
