"""``cdtm study PARAM``: one sensitivity study of the paper's section VI (Figs. 2-9).

Writes ``study_<param>.csv`` (columns :data:`cdtm_graph.studies.STUDY_COLUMNS`) and
``study_<param>.png`` into ``--out`` (both or neither, under the rules of
:mod:`cdtm_graph.atomic`: the files of other studies there are kept) and prints the table.
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING

from cdtm_graph.atomic import atomic_output_file
from cdtm_graph.cli import COMMANDS
from cdtm_graph.cli.outdir import add_out_option, output_dir
from cdtm_graph.studies.settings import StudyParameter

if TYPE_CHECKING:
    from cdtm_graph.studies.sweeps import StudyResult

#: Significant digits of the CSV numbers (well below the Monte Carlo noise).
CSV_DIGITS = 8
#: Resolution of the PNG: small files, readable labels.
FIGURE_DPI = 100


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "study",
        help=COMMANDS["study"].summary,
        description="Monte Carlo sensitivity study of the two-frame C-DTM solve: for each "
                    "value of PARAM (others nominal), TRIALS random frame pairs are solved; "
                    "the closed-form 1-sigma and the achieved RMS error are reported for the "
                    "camera-2 pose and the ego-motion. Writes study_PARAM.csv and "
                    "study_PARAM.png.")
    parser.add_argument("parameter", choices=[p.value for p in StudyParameter],
                        metavar="PARAM", help="one of: %(choices)s")
    parser.add_argument("--trials", type=int, default=150,
                        help="random trials per value (default: %(default)s, as the paper)")
    parser.add_argument("--values", type=float, nargs="+", metavar="V",
                        help="values to sweep (default: the paper's range)")
    add_out_option(parser, "output directory", default="studies")
    parser.add_argument("--workers", type=int, default=None,
                        help="local worker processes (default: all cores)")
    parser.add_argument("--scheduler", metavar="ADDRESS", default=None,
                        help="run on the Dask cluster of this scheduler (needs cdtm-graph[dask])")
    parser.add_argument("--seed", type=int, default=0, help="master seed (default: 0)")
    parser.set_defaults(func=run)


def write_study_csv(result: StudyResult, path: Path) -> None:
    """The study table as CSV, atomically; NaN where every trial of a value failed."""
    from cdtm_graph.studies.sweeps import STUDY_COLUMNS

    with atomic_output_file(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(STUDY_COLUMNS)
        for row in result.rows:
            writer.writerow([_csv_number(x) for x in row.as_tuple()])


def _csv_number(x: float | int) -> str:
    if isinstance(x, int):
        return str(x)
    return "nan" if math.isnan(x) else f"{x:.{CSV_DIGITS}g}"


def write_study_figure(result: StudyResult, path: Path) -> None:
    """The PNG of :func:`cdtm_graph.plots.studies.study_figure`, atomically."""
    from cdtm_graph.plots.studies import study_figure  # matplotlib only when plotting

    fig = study_figure(result)
    with atomic_output_file(path) as tmp:
        fig.savefig(tmp, format="png", dpi=FIGURE_DPI)


def format_table(result: StudyResult) -> str:
    """The study as a fixed-width text table (metres, degrees), with failure causes."""
    from cdtm_graph.studies.sweeps import TrialStatus

    head = (f"{'value':>8} {'fail':>8}  {'pos2 pred/err [m]':>18}  {'att2 pred/err [deg]':>20}"
            f"  {'t12 pred/err [m]':>17}  {'r12 pred/err [deg]':>19}  causes")
    lines = [head]
    for row, counts in zip(result.rows, result.failure_counts(), strict=True):
        causes = ", ".join(f"{n} {s.name.lower().replace('_', ' ')}"
                           for s, n in counts.items() if n and s is not TrialStatus.OK)
        lines.append(
            f"{row.value:>8g} {row.failures:>3}/{row.trials:<4}"
            f"  {row.pred_sigma_pos2_m:>8.3g} {row.rms_err_pos2_m:>9.3g}"
            f"  {row.pred_sigma_att2_deg:>9.3g} {row.rms_err_att2_deg:>10.3g}"
            f"  {row.pred_sigma_t12_m:>8.3g} {row.rms_err_t12_m:>8.3g}"
            f"  {row.pred_sigma_r12_deg:>9.3g} {row.rms_err_r12_deg:>9.3g}  {causes}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from cdtm_graph.parallel import ParallelSettings
    from cdtm_graph.studies.sweeps import SWEEPS, StudySettings, run_study

    parameter = StudyParameter(args.parameter)
    settings = StudySettings(parameter, values=tuple(args.values) if args.values else None,
                             trials=args.trials, seed=args.seed)
    settings.check()  # bad values fail before any work or output
    parallel = ParallelSettings(workers=args.workers, scheduler_address=args.scheduler)
    csv_name, png_name = f"study_{parameter.value}.csv", f"study_{parameter.value}.png"
    with output_dir(args, args.out, f"study {parameter.value}",
                    names=(csv_name, png_name)) as staging:
        start = time.perf_counter()
        result = run_study(settings, parallel)
        elapsed_s = time.perf_counter() - start
        write_study_csv(result, staging / csv_name)
        write_study_figure(result, staging / png_name)
    csv_path, png_path = args.out / csv_name, args.out / png_name
    sweep = SWEEPS[parameter]
    print(f"study {parameter.value}: {sweep.label}; {settings.trials} trials per value, "
          f"seed {settings.seed}, {elapsed_s:.1f} s")
    print(format_table(result))
    print(f"paper ({sweep.paper_figure}): {sweep.paper_trend}")
    print(f"wrote {csv_path} and {png_path}")
    return 0
