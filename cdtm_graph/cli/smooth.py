"""``cdtm smooth LOG --out DIR``: smooth a flight log and write the run directory.

The module imports only the options' vocabulary at the top (``cdtm smooth --help`` and a
usage error load no numerics); the estimator, the outputs and the plots are imported by the
functions that use them.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from cdtm_graph.cli import COMMANDS
from cdtm_graph.cli.outdir import add_out_option, output_dir
from cdtm_graph.errors import CdtmError
from cdtm_graph.smoother.modes import SmootherMode
from factors.modes import PlaneMode, RobustKernel

if TYPE_CHECKING:
    from cdtm_graph.run import RunOutput
    from cdtm_graph.smoother import SmootherSettings

#: Runs with at least this many frames show a progress bar (unless --quiet).
PROGRESS_MIN_FRAMES = 100
#: The plots ``--plots`` may write (errors.png only with ground truth).
PLOT_FILES = ("trajectory.png", "errors.png", "trajectory_dem.png", "verdict.png")
#: The 3-D scene ``--scene`` writes.
SCENE_FILE = "scene.glb"


def add_smoothing_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--mode", choices=[m.value for m in SmootherMode], default="batch",
                   help="batch Levenberg-Marquardt (default) or incremental iSAM2")
    p.add_argument("--plane", choices=[m.value for m in PlaneMode], default="reintersect",
                   help="DTM tangent plane: re-intersect at every linearization (default) "
                        "or fixed at the initial guess (the paper)")
    p.add_argument("--robust", choices=[k.value for k in RobustKernel], default="cauchy",
                   help="per-feature M-estimator (default cauchy: redescending, reached from "
                        "a robust start; none is plain least squares, for studies)")
    p.add_argument("--lag-s", type=float, default=None,
                   help="incremental mode: fixed-lag smoother with this lag (seconds); "
                        "with a wide initial prior at least the fix search's window (6 "
                        "frame intervals)")
    p.add_argument("--gate", type=_gate_probability, default=0.999, metavar="P",
                   help="drop features whose innovation against the prior fails the "
                        "chi-square gate of probability P, as frames arrive (incremental "
                        "mode, and the batch's incremental first pass); 'none' gates "
                        "nothing (default %(default)s)")
    p.add_argument("--calibration", choices=["checked", "online", "held"], default="checked",
                   help="checked (default): take flight.yaml's camera calibration as exact and "
                        "check it in a batch side solve (calibration_suspect when the flight "
                        "contradicts it); online: estimate the time offset, mount rotation and "
                        "focal scale (batch; priors from flight.yaml's camera.calibration, else "
                        "30 ms, 1 deg, 2%%); held: as exact, unchecked")
    p.add_argument("--plots", action="store_true",
                   help="also write trajectory.png (over the DTM: estimate, ground truth, "
                        "IMU-only dead reckoning, 3-sigma ellipses), errors.png (errors "
                        "inside +-3 sigma), verdict.png (the verdict's flags and reasons "
                        "along the flight) and, for a geodetic log, trajectory_dem.png "
                        "(over the DEM in its own coordinates)")
    p.add_argument("--scene", action="store_true",
                   help="also write scene.glb, a 3-D scene for any glTF viewer: the terrain "
                        "under the flight (hillshaded), the estimated (and true) trajectory, "
                        "3-sigma position ellipsoids and camera footprints every N frames")
    p.add_argument("--scene-every", type=_positive_int, default=10, metavar="N",
                   help="frames between ellipsoids and footprints in scene.glb "
                        "(default %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no progress bar, no summary")


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: expected an integer >= 1")
    return value


def _gate_probability(text: str) -> float | None:
    """``--gate``: a probability, or 'none'."""
    if text.strip().lower() == "none":
        return None
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a probability or 'none'") from None


#: What ``cdtm smooth --help`` (and ``cdtm demo --help``) say about the verdict.
VERDICT_HELP = """\
verdict: every run is judged trusted, degraded or failed (report.json: verdict, reasons,
flags per frame, self_checks). Each reason is printed as one line on stderr: what, which
frames (indices of frames.csv) and why, e.g.
  cdtm smooth: degraded: flat_terrain, frames 31-56 (31.0-56.0 s): flat terrain: ...
exit status: 0 trusted; 3 outputs written but degraded or failed; 1 bad input or nothing
written (one line on stderr); 2 usage error (this usage on stderr); 130 interrupted.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("smooth", help=COMMANDS["smooth"].summary,
                       description="Smooth a cdtm-flightlog/1 directory and write "
                                   "trajectory.tum, trajectory_cov.txt, states.csv, "
                                   "covariances.npz and report.json into --out.",
                       epilog=VERDICT_HELP,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("log", help="flight log directory")
    add_out_option(p, "output directory")
    add_smoothing_options(p)
    p.set_defaults(func=run)


def settings_from_args(args: argparse.Namespace) -> SmootherSettings:
    """The settings the options ask for; a bad value is one line (``CdtmError``) before
    the estimator is imported."""
    if args.lag_s is not None and not (math.isfinite(args.lag_s) and args.lag_s > 0):
        raise CdtmError(f"--lag-s {args.lag_s}: expected a finite lag > 0 seconds (without "
                        "--lag-s: the full history)")
    if args.lag_s is not None and args.mode != "incremental":
        raise CdtmError("--lag-s needs --mode incremental")
    if args.gate is not None and not 0.0 < args.gate < 1.0:
        raise CdtmError(f"--gate {args.gate}: expected a probability strictly between 0 and 1")
    from cdtm_graph.graph import GraphSettings
    from cdtm_graph.smoother import SmootherSettings

    graph = GraphSettings(plane_mode=PlaneMode(args.plane), robust=RobustKernel(args.robust))
    calibration = getattr(args, "calibration", "checked")  # (parsers without the option)
    if calibration == "held":
        graph = replace(graph, calibration=None)
    elif calibration == "online":
        graph = replace(graph, calibration_online=True)
    return SmootherSettings(
        graph=graph,
        mode=SmootherMode(args.mode), lag_s=args.lag_s, innovation_gate=args.gate)


def progress_bar(quiet: bool):
    """A one-line progress bar on stderr for long runs, or None."""
    if quiet:
        return None

    def show(done: int, total: int) -> None:
        if total < PROGRESS_MIN_FRAMES:
            return
        width = 30
        filled = width * done // total
        bar = "#" * filled + "." * (width - filled)
        sys.stderr.write(f"\rsmoothing [{bar}] {done}/{total} frames")
        if done == total:
            sys.stderr.write("\n")
        sys.stderr.flush()

    return show


def plot_writers(out: RunOutput, dtm, flight) -> list:
    from cdtm_graph.plots.trajectory import plot_errors, plot_trajectory_over_dtm
    from cdtm_graph.plots.verdict import plot_verdict
    from cdtm_graph.results import pose_covariance_in_world

    est = out.result.estimate
    _, pos_cov = pose_covariance_in_world(est.world_T_body, out.result.covariances.pose)
    writers = [("trajectory.png",
                lambda p: plot_trajectory_over_dtm(p, dtm, est, pos_cov, flight.groundtruth,
                                                   free=out.free)),
               ("verdict.png", lambda p: plot_verdict(p, out.verdict, len(est)))]
    frame, cfg = flight.config.local_frame, flight.config.dtm
    if frame is not None:
        from cdtm_graph.dem import read_dem_window
        from cdtm_graph.plots.dem import plot_trajectory_over_dem
        from cdtm_graph.run.prepare import dem_region_m

        window = read_dem_window(cfg.paths, frame, dem_region_m(flight), cfg.vertical_datum,
                                 cfg.crs)
        writers.append(("trajectory_dem.png", lambda p: plot_trajectory_over_dem(
            p, window, frame, est, pos_cov, flight.groundtruth, free=out.free)))
    e = out.errors
    if e is not None and e.position_sigma_world_m is not None:
        sigma = e.position_sigma_world_m
        writers.append(("errors.png", lambda p: plot_errors(
            p, (e.t_ns - e.t_ns[0]) * 1e-9, e.position_error_world_m, sigma)))
    return writers


def scene_writer(out: RunOutput, dtm, flight, every: int) -> tuple:
    """``("scene.glb", writer)`` for the run's extra files (``--scene``)."""
    from cdtm_graph.plots.scene import SceneSettings, write_scene

    est = out.result.estimate
    return (SCENE_FILE, lambda p: write_scene(p, dtm, est, out.result.covariances.pose,
                                              flight.config.camera, flight.groundtruth,
                                              SceneSettings(every=every)))


def summary(out: RunOutput, out_dir: Path) -> str:
    r = out.result
    total_s = out.report["timings_s"]["total"]
    left_out = ", ".join(f"{int(n.sum())} {reason.replace('_', ' ')}"
                         for reason, n in r.counts.rejected_per_frame.items() if n.sum())
    lines = [f"{r.counts.n_frames} frames, {r.counts.n_cdtm_features} C-DTM features "
             f"({r.counts.n_outliers} beyond the chi-square test at the solution"
             f"{'; left out: ' + left_out if left_out else ''}), {r.stats.solver.value} "
             f"smoothing in {total_s:.2f} s -> {out_dir}"]
    e, f = out.errors, out.free_errors
    if e is not None and f is not None and e.n_frames_evaluated:
        fmt = lambda v: " ".join(f"{x:8.2f}" for x in v)  # noqa: E731
        lines += [f"{'':24}{'x':>8} {'y':>8} {'z':>8}   (m, world)",
                  f"{'RMSE compensated':24}{fmt(e.rmse_position_m)}",
                  f"{'max error compensated':24}{fmt(e.max_abs_position_error_m)}",
                  f"{'max error free (IMU)':24}{fmt(f.max_abs_position_error_m)}"]
        consistency = e.position_consistency
        if consistency is not None:
            lines.append(f"position covariance {consistency.summary()}")
            lines.append("  (smoothed errors are correlated over many frames: one flight's "
                         "share inside the bound is a hint, many flights' a test)")
    checks = out.verdict.self_checks
    if checks.residual_chi2 == checks.residual_chi2:  # not NaN
        nis = ("" if checks.innovation_nis_median != checks.innovation_nis_median else
               f"; innovations median {checks.innovation_nis_median:.2f}, mean "
               f"{checks.innovation_nis_mean:.2f} (chi-square(2): 1.39, 2)")
        lines.append(f"self-checks {'passed' if checks.passed else 'FAILED'}: residual "
                     f"chi-square {checks.residual_chi2:.2f} x expected, "
                     f"{100 * checks.outlier_fraction:.2f}% beyond the 99.9% test{nis}")
    flagged = len(out.verdict.flags)
    lines.append(f"verdict: {out.verdict.status.value}"
                 + (f" ({len(out.verdict.reasons)} reason(s) on stderr)"
                    if out.verdict.reasons else "")
                 + (f"; {flagged} frame(s) flagged in report.json" if flagged else ""))
    return "\n".join(lines)


def print_verdict(out: RunOutput, command: str = "cdtm smooth") -> int:
    """Each reason as one line on stderr; the exit status (0 trusted, 3 otherwise)."""
    for line in out.verdict.lines():
        print(f"{command}: {line}", file=sys.stderr)
    return out.verdict.status.exit_code


def smooth_log_to_dir(log_dir: str, out_dir: Path, args: argparse.Namespace) -> RunOutput:
    """Smooth ``log_dir`` into ``out_dir``; the output directory is checked (and its staging
    directory made) before the log is read, so a bad ``--out`` fails before any work."""
    settings = settings_from_args(args)
    from cdtm_graph.outputs import ALL_RUN_FILES, RUN_WRITER, write_run_files
    from cdtm_graph.run import smooth_and_evaluate
    from cdtm_graph.run.prepare import load_log_and_dtm

    # (the geodetic files only come with an origin; unknown before the log is read)
    scene = bool(getattr(args, "scene", False))
    names = [*ALL_RUN_FILES, *(PLOT_FILES if args.plots else ()),
             *((SCENE_FILE,) if scene else ())]
    with output_dir(args, out_dir, RUN_WRITER, protected=[log_dir], names=names) as staging:
        flight, dtm = load_log_and_dtm(log_dir)
        out = smooth_and_evaluate(flight, dtm, settings, progress_bar(args.quiet))
        extras = plot_writers(out, dtm, flight) if args.plots else []
        if scene:
            extras.append(scene_writer(out, dtm, flight, args.scene_every))
        write_run_files(staging, out.result, out.report, extras,
                        frame=flight.config.local_frame, groundtruth=flight.groundtruth)
    return out


def run(args: argparse.Namespace) -> int:
    if not str(args.log).strip():
        raise CdtmError("LOG is empty; expected a flight log directory")
    out_dir = Path(args.out)
    out = smooth_log_to_dir(args.log, out_dir, args)
    if not args.quiet:
        print(summary(out, out_dir))
    if out.errors is not None and out.errors.n_frames_evaluated == 0:
        from cdtm_graph.flightlog import GROUNDTRUTH_CSV
        print(f"cdtm smooth: warning: {Path(args.log) / GROUNDTRUTH_CSV}: "
              + GROUNDTRUTH_ELSEWHERE, file=sys.stderr)
    return print_verdict(out)


#: A log's ground truth that covers none of its frames (a clock mismatch, most likely).
GROUNDTRUTH_ELSEWHERE = ("its times cover none of the frames: no error was computed "
                         "(expected ground truth on the IMU's clock, over the flight)")

