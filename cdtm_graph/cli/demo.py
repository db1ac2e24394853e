"""``cdtm demo``: smooth the bundled sample log into ./cdtm-demo-out and print the errors.

``cdtm demo --images`` runs the whole chain instead: a small flight is simulated and
rendered (images of the true terrain, which differs from the log's DTM), its images are
tracked into tracks.csv, and the tracks smoothed; the errors are printed beside those
of the same flight smoothed from its ideal ray-cast tracks.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from cdtm_graph.atomic import read_manifest
from cdtm_graph.cli import COMMANDS
from cdtm_graph.cli.outdir import add_force_option
from cdtm_graph.cli.smooth import VERDICT_HELP, print_verdict, smooth_log_to_dir, summary
from cdtm_graph.data import sample_flight_path

#: The rendered demo flight: the paper's geometry (1000 m, 200 m/s, 60 deg), 1 fps.
IMAGE_DEMO_FRAMES = 30
IMAGE_DEMO_RESOLUTION_PX = (640, 480)
#: File beside tracks.csv keeping the simulator's ideal tracks for comparison.
RAYCAST_TRACKS = "tracks_raycast.csv"


#: What ``cdtm demo --help`` says it does.
DESCRIPTION = """\
Smooth the sample flight log that comes with the package (40 simulated frames over
fractal terrain, 200 Hz IMU, ground truth) as `cdtm smooth --plots` does, into --out, and
print its errors beside IMU-only navigation.
With --images: simulate a small flight, render its images, track them into tracks.csv and
smooth the tracks, beside the same flight smoothed from its ideal ray-cast tracks.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help=COMMANDS["demo"].summary,
                       description=DESCRIPTION,
                       epilog=VERDICT_HELP,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=None, metavar="DIR",
                   help="output directory (default cdtm-demo-out, or cdtm-demo-images-out "
                        "with --images, holding the rendered log and the run)")
    add_force_option(p)
    p.add_argument("--images", action="store_true",
                   help="images -> tracks -> trajectory on a small rendered flight")
    p.set_defaults(func=run, mode="batch", plane="reintersect", robust="cauchy", lag_s=None,
                   gate=0.999, plots=True, quiet=False)


def run(args: argparse.Namespace) -> int:
    from cdtm_graph.outputs import RUN_WRITER

    if args.images:
        return run_images(Path(args.out or "cdtm-demo-images-out"), args)
    out_dir = Path(args.out or "cdtm-demo-out")
    sample_log = sample_flight_path()
    out = smooth_log_to_dir(str(sample_log), out_dir, args)
    print(f"sample log: {sample_log}")
    print(summary(out, out_dir))
    written = sorted(n for n, w in (read_manifest(out_dir) or {}).items() if w == RUN_WRITER)
    print(f"wrote {', '.join(written)}")
    return print_verdict(out, "cdtm demo")


def run_images(out_dir: Path, args: argparse.Namespace) -> int:
    """Simulate, render, track, smooth; OUT/log is the flight log, OUT/run the run.

    OUT, OUT/log and OUT/run are checked before any work; the log (its rendered images,
    the tracked tracks.csv and the ray-cast one beside it) is published whole or not at
    all, so an interrupted demo leaves OUT as it was."""
    from tqdm import tqdm

    from cdtm_graph.atomic import check_output_dir
    from cdtm_graph.cli.outdir import output_dir
    from cdtm_graph.cli.smooth import PLOT_FILES, settings_from_args
    from cdtm_graph.flightlog import TRACKS_CSV, write_tracks
    from cdtm_graph.frontend import track_log
    from cdtm_graph.outputs import ALL_RUN_FILES
    from cdtm_graph.run import smooth_and_evaluate
    from cdtm_graph.run.prepare import load_log_and_dtm
    from cdtm_graph.sim.render import RenderSettings, render_flight
    from cdtm_graph.sim.simulate import SimulationSettings, simulate, write_simulation_files

    force = bool(args.force)
    log_dir, run_dir = out_dir / "log", out_dir / "run"
    check_output_dir(out_dir, force=force, label="--out")
    check_output_dir(log_dir, force=force, label="--out", writer=DEMO_LOG_WRITER,
                     names=[TRACKS_CSV, RAYCAST_TRACKS])
    check_output_dir(run_dir, force=force, label="--out", protected=[log_dir],
                     names=[*ALL_RUN_FILES, *PLOT_FILES])
    settings = SimulationSettings(frames=IMAGE_DEMO_FRAMES, resolution_px=IMAGE_DEMO_RESOLUTION_PX)
    result = simulate(settings)
    with tqdm(total=settings.frames, unit="frame", desc="rendering", file=sys.stderr,
              leave=False) as bar:
        rendered = render_flight(result, RenderSettings(),
                                 progress=lambda done, total: bar.update(1))
    with output_dir(args, log_dir, DEMO_LOG_WRITER) as staging:
        write_simulation_files(result, staging, log_dir, rendered.images)
        (staging / TRACKS_CSV).replace(staging / RAYCAST_TRACKS)
        flight, dtm = load_log_and_dtm(staging)  # images, no tracks.csv
        with tqdm(total=settings.frames, unit="frame", desc="tracking", file=sys.stderr,
                  leave=False) as bar:
            tracked = track_log(flight, progress=lambda done, total: bar.update(1))
        write_tracks(tracked.tracks, staging / TRACKS_CSV)

    width, height = settings.resolution_px
    print(f"rendered {settings.frames} frames {width}x{height} of a flight at "
          f"{settings.altitude_m:g} m, {settings.speed_mps:g} m/s, {settings.fps:g} fps "
          f"({rendered.seconds_per_frame:.2f} s per frame) -> {log_dir}")
    print(tracked.report.summary())
    out = smooth_log_to_dir(str(log_dir), run_dir, args)
    print("from the images' tracks:")
    print(summary(out, run_dir))
    flight, dtm = load_log_and_dtm(log_dir)
    ideal_log = dataclasses.replace(flight, tracks=result.log.tracks)
    ideal = smooth_and_evaluate(ideal_log, dtm, settings_from_args(args)).errors
    e = out.errors
    if ideal is not None and e is not None:
        fmt = " ".join(f"{x:.2f}" for x in ideal.rmse_position_m)
        print(f"from the ideal ray-cast tracks ({RAYCAST_TRACKS}): RMSE x y z {fmt} m, "
              f"position ANEES {ideal.anees_position:.2f}; images/ideal RMSE ratio "
              f"{e.rmse_position_3d_m / ideal.rmse_position_3d_m:.2f}")
    return print_verdict(out, "cdtm demo")


#: Who the rendered log's manifest says wrote it (simulated, rendered and tracked).
DEMO_LOG_WRITER = "demo --images"
