"""``cdtm navsim``: the paper's navigation simulation, Tables 1 and 2 (section VI.A).

Flies every case (:mod:`cdtm_graph.studies.navsim`), writes ``table1.md``, ``table1.csv``,
``table2.md`` and ``table2.csv`` into ``--out`` (all four or none, under the rules of
:mod:`cdtm_graph.atomic`: never over a file cdtm did not write) and prints the two markdown
tables.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from cdtm_graph.cli import COMMANDS
from cdtm_graph.cli.outdir import add_out_option, output_dir
from cdtm_graph.errors import CdtmError
from cdtm_graph.sim.settings import DEFAULT_SEED, NOMINAL_SPEED_MPS
from cdtm_graph.studies.settings import (
    BASELINE_PER_ALTITUDE,
    NAVSIM_DURATION_S,
    QUICK_DURATION_S,
    TABLE1_ALTITUDES_M,
    TABLE2_ALTITUDE_M,
    TABLE2_RESOLUTIONS_PX,
    frame_interval_s,
)

if TYPE_CHECKING:
    from cdtm_graph.studies.navsim import NavsimResult, NavsimSettings

#: The interval between frames at the Table 2 altitude (s), as NavsimSettings defaults it.
_TABLE2_INTERVAL_S = frame_interval_s(TABLE2_ALTITUDE_M, BASELINE_PER_ALTITUDE,
                                      NOMINAL_SPEED_MPS)

#: The files written into --out.
OUTPUT_FILES = ("table1.md", "table1.csv", "table2.md", "table2.csv")
#: The writer named in the output directory's manifest.
WRITER = "navsim"


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "navsim",
        help=COMMANDS["navsim"].summary,
        description="Simulate the paper's section VI.A flights (200 m/s, 60 deg FOV, ~110 "
                    "features per frame pair, tactical IMU) at each altitude (Table 1) and "
                    "image resolution (Table 2); report the maximum position error per axis "
                    "of IMU-only navigation (Free), batch smoothing and the incremental "
                    "estimate as each frame arrived, beside the paper's numbers. Writes "
                    "table1.md, table1.csv, table2.md and table2.csv into --out.")
    add_out_option(parser, "output directory", default="cdtm-navsim-out")
    parser.add_argument("--altitudes", type=float, nargs="+", metavar="M",
                        default=list(TABLE1_ALTITUDES_M),
                        help="Table 1 altitudes, m (default: %(default)s)")
    parser.add_argument("--resolutions", type=int, nargs="+", metavar="PX",
                        default=list(TABLE2_RESOLUTIONS_PX),
                        help="Table 2 image sides, px (default: %(default)s)")
    length = parser.add_mutually_exclusive_group()
    length.add_argument("--frames", type=int, metavar="N",
                        help="flight length as the frame count at the Table 2 altitude "
                             f"({TABLE2_ALTITUDE_M:g} m, one frame every "
                             f"{_TABLE2_INTERVAL_S:g} s); "
                             "every case flies that long")
    length.add_argument("--duration-s", type=float, metavar="S",
                        help=f"flight length, s (default: {NAVSIM_DURATION_S:g}; "
                             f"{QUICK_DURATION_S:g} with --quick)")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED,
                        help="seed of every case (default: %(default)s)")
    parser.add_argument("--quick", action="store_true",
                        help=f"short flights ({QUICK_DURATION_S:g} s): a check in seconds, "
                             "not the tables to quote")
    parser.add_argument("--quiet", action="store_true", help="no progress on stderr")
    parser.set_defaults(func=run)


def settings_from_args(args: argparse.Namespace) -> NavsimSettings:
    """The navsim settings the arguments ask for (``CdtmError`` on a bad value; a bad
    ``--frames`` before the simulator is imported)."""
    if args.frames is not None and args.frames < 2:
        raise CdtmError(f"--frames {args.frames}: expected at least 2 frames")
    from cdtm_graph.studies.navsim import NavsimSettings

    settings = NavsimSettings(altitudes_m=tuple(args.altitudes),
                              resolutions_px=tuple(args.resolutions), seed=args.seed)
    if args.frames is not None:
        interval = settings.frame_interval_s(settings.table2_altitude_m)
        return dataclasses.replace(settings, duration_s=(args.frames - 1) * interval)
    if args.duration_s is not None:
        return dataclasses.replace(settings, duration_s=args.duration_s)
    if args.quick:
        return dataclasses.replace(settings, duration_s=QUICK_DURATION_S)
    return settings


def write_tables(result: NavsimResult, directory: Path) -> None:
    """The four table files (into a staging directory: see ``run``)."""
    from cdtm_graph.studies.navsim import table_csv, table_markdown

    for name, table in (("table1", result.table1), ("table2", result.table2)):
        (directory / f"{name}.md").write_text(table_markdown(table))
        (directory / f"{name}.csv").write_text(table_csv(table))


def _progress(done: int, total: int, case: tuple[float, int]) -> None:
    if done < total:
        alt, res = case
        sys.stderr.write(f"navsim: case {done + 1}/{total}: {alt:g} m, {res}x{res} px\n")
        sys.stderr.flush()


def run(args: argparse.Namespace) -> int:
    settings = settings_from_args(args)
    from cdtm_graph.studies.navsim import run_navsim, table_markdown

    out_dir = Path(args.out)
    with output_dir(args, out_dir, WRITER, names=OUTPUT_FILES) as staging:
        result = run_navsim(settings, None if args.quiet else _progress)
        write_tables(result, staging)
    print(table_markdown(result.table1))
    print(table_markdown(result.table2), end="")
    if not args.quiet:
        sys.stderr.write(f"navsim: {result.time_s:.0f} s; wrote {', '.join(OUTPUT_FILES)} "
                         f"to {out_dir}\n")
    return 0
