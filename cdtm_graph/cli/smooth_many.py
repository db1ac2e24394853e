"""``cdtm smooth-many LOG... --out DIR``: smooth many logs in parallel, then evaluate them.

Each log is smoothed exactly as ``cdtm smooth LOG --out DIR/<log's name>`` would (the same
function, the same files and manifest; logs of one name are told apart by their parent
folders: ``DIR/d1_log``, ``DIR/d2_log``), on local processes (all cores) or on the workers
of a Dask cluster (``--scheduler``: they must see the logs and DIR at the same paths);
then ``cdtm evaluate`` writes the table and figures of all the runs into DIR.

Every output directory (DIR and each run's) is checked, and every log read with its DTM,
before any work. A run that fails while smoothing (a solver error) stops the command with
its one line (exit 1): the runs finished by then stay, each complete under its own
manifest; the evaluation is not written, and a rerun into DIR writes it.
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import dataclass
from pathlib import Path

from cdtm_graph.atomic import check_output_dir
from cdtm_graph.cli import COMMANDS
from cdtm_graph.cli.evaluate import EVALUATE_FILES, EVALUATE_WRITER, write_evaluation
from cdtm_graph.cli.outdir import add_out_option
from cdtm_graph.cli.smooth import (
    PLOT_FILES,
    SCENE_FILE,
    VERDICT_HELP,
    _positive_int,
    add_smoothing_options,
    settings_from_args,
    smooth_log_to_dir,
)
from cdtm_graph.errors import CdtmError

#: The options of ``cdtm smooth`` each task takes over (the rest are smooth-many's own).
_TASK_OPTIONS = ("mode", "plane", "robust", "lag_s", "gate", "calibration", "plots", "scene",
                 "scene_every", "force")


@dataclass(frozen=True)
class SmoothTask:
    """One log to smooth into one run directory, with ``cdtm smooth``'s options."""

    log: str
    out: str
    options: dict


@dataclass(frozen=True)
class SmoothDone:
    """What a task reports back: the verdict, its exit status and stderr lines."""

    log: str
    out: str
    verdict: str
    exit_code: int
    lines: tuple[str, ...]
    time_s: float


def smooth_task(task: SmoothTask) -> SmoothDone:
    """Run one ``cdtm smooth`` (in a worker process or on a Dask worker)."""
    args = argparse.Namespace(**task.options, quiet=True, command="smooth")
    out = smooth_log_to_dir(task.log, Path(task.out), args)
    return SmoothDone(task.log, task.out, out.verdict.status.value,
                      out.verdict.status.exit_code, tuple(out.verdict.lines()),
                      float(out.report["timings_s"]["total"]))


def run_dir_names(logs: list[str]) -> list[str]:
    """Each log's run directory under DIR: the log's folder name; for logs of one name,
    with as many of their parent folders (``d1_log``, ``d2_log``) as tell them apart.
    Always one plain name inside DIR (never ``..``, never a path).

    Raises:
        CdtmError: a log given twice; a name the evaluation writes into DIR."""
    real = [os.path.realpath(log) for log in logs]
    for i, path in enumerate(real):
        if path in real[:i]:
            raise CdtmError(f"{logs[i]}: given twice (as {logs[real.index(path)]}); "
                            "expected each log once")
    # (named as given, links not followed: a link is a way to name a log)
    paths = [Path(os.path.abspath(log)) for log in logs]
    parts = [[p for p in path.parts if p not in ("/", "")] or ["log"] for path in paths]
    depth = [1] * len(paths)
    while True:
        names = ["_".join(p[-d:]) for p, d in zip(parts, depth, strict=True)]
        clashing = [i for i, n in enumerate(names) if names.count(n) > 1
                    and depth[i] < len(parts[i])]
        if not clashing:
            break
        for i in clashing:
            depth[i] += 1
    for log, name in zip(logs, names, strict=True):
        if names.count(name) > 1:
            raise CdtmError(f"{log}: its run would be DIR/{name}, as another log's; expected "
                            "logs whose folders tell them apart (rename or link one)")
        if name in EVALUATE_FILES:
            raise CdtmError(f"{log}: its run would be DIR/{name}, a file the evaluation "
                            f"writes there; expected a log folder named otherwise (not "
                            f"{', '.join(EVALUATE_FILES)}: rename or link it)")
    return names


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "smooth-many", help=COMMANDS["smooth-many"].summary,
        description="Smooth each LOG as `cdtm smooth LOG --out DIR/<LOG's name>` would, in "
                    "parallel (local processes on all cores, or a Dask cluster with "
                    "--scheduler), then write `cdtm evaluate`'s table and figures of all "
                    "the runs into DIR. Every log needs ground truth (groundtruth.csv).",
        epilog=VERDICT_HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("logs", nargs="+", metavar="LOG", help="flight log directories")
    add_out_option(p, "directory of the runs (one per log, named as the log) and the "
                      "evaluation")
    add_smoothing_options(p)
    p.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="a running Dask scheduler (e.g. tcp://10.0.0.5:8786) whose workers "
                        "see the logs and DIR at the same paths; default: local processes")
    p.add_argument("--workers", type=_positive_int, default=None, metavar="N",
                   help="local worker processes (default: every core)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from cdtm_graph.flightlog import GROUNDTRUTH_CSV
    from cdtm_graph.outputs import ALL_RUN_FILES, RUN_WRITER
    from cdtm_graph.parallel import ParallelSettings, map_tasks

    settings_from_args(args)  # bad smoothing options: one line before any work
    for log in args.logs:
        path = Path(log)
        if not path.is_dir():
            what = "does not exist" if not path.exists() else "is not a directory"
            raise CdtmError(f"{log}: {what}; expected a flight log directory")
        if not (path / GROUNDTRUTH_CSV).is_file():
            raise CdtmError(f"{log}: no {GROUNDTRUTH_CSV}; expected logs with ground truth "
                            "(smooth-many evaluates its runs against it; cdtm smooth runs "
                            "a log without)")
    out_dir = Path(args.out)
    run_dirs = [out_dir / name for name in run_dir_names(args.logs)]
    # Every output directory checked before any work (each run's again as it is written).
    check_output_dir(out_dir, force=args.force, protected=args.logs, names=EVALUATE_FILES,
                     label="--out", writer=EVALUATE_WRITER)
    run_files = [*ALL_RUN_FILES, *(PLOT_FILES if args.plots else ()),
                  *((SCENE_FILE,) if args.scene else ())]
    for run_dir in run_dirs:
        check_output_dir(run_dir, force=args.force, protected=args.logs, names=run_files,
                         label="--out", writer=RUN_WRITER)
    # Every log read (and its DTM) and checked as its run will check it, before any work:
    # a bad one is its one line now, not after the others' runs (which would stay,
    # without their evaluation).
    import numpy as np

    from cdtm_graph.run.prepare import load_log_and_dtm
    from cdtm_graph.smoother.incremental import check_lag
    from cdtm_graph.verdict.preflight import check_imu_span
    lag_s = settings_from_args(args).lag_s
    for log in args.logs:
        flight, _ = load_log_and_dtm(log)
        check_imu_span(flight)
        if len(flight.frames) > 1:
            check_lag(lag_s, float(np.median(np.diff(flight.frames.t_ns))) * 1e-9)
        truth = flight.groundtruth
        if truth is not None and not truth.covers(flight.frames.t_ns).any():
            raise CdtmError(f"{Path(log) / GROUNDTRUTH_CSV}: its times cover none of the "
                            "frames; expected ground truth on the IMU's clock, over the "
                            "flight (smooth-many evaluates its runs against it)")
    options = {k: getattr(args, k) for k in _TASK_OPTIONS}
    tasks = [SmoothTask(str(log), str(d), options) for log, d in zip(args.logs, run_dirs,
                                                                         strict=True)]
    parallel = ParallelSettings(workers=args.workers, scheduler_address=args.scheduler)
    done = map_tasks(smooth_task, tasks, parallel)
    for d in done:
        for line in d.lines:
            print(f"cdtm smooth-many: {d.log}: {line}", file=sys.stderr)
    # The evaluation goes beside the runs: DIR was checked above, and the runs now in it
    # are this command's (force: they hold their own manifests, not DIR's).
    markdown = write_evaluation(run_dirs, out_dir, args, force=True)
    if not args.quiet:
        for d in done:
            print(f"{d.log} -> {d.out}: {d.verdict} ({d.time_s:.2f} s)")
        print(markdown, end="")
    return max(d.exit_code for d in done)
