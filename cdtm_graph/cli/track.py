"""``cdtm track LOG``: the images named in frames.csv to LOG/tracks.csv, with a short report."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from tqdm import tqdm

from cdtm_graph.atomic import atomic_output_file
from cdtm_graph.errors import CdtmError
from cdtm_graph.flightlog import TRACKS_CSV, read_flightlog, write_tracks
from cdtm_graph.frontend import TrackerSettings, track_log

_DEFAULTS = TrackerSettings()


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "track", help="track features through the log's images into tracks.csv",
        description="Read the images named in frames.csv, track features through them "
                    "(Lucas-Kanade with IMU-predicted rotation, forward-backward check, "
                    "epipolar RANSAC, bucketed corners) and write LOG/tracks.csv.")
    parser.add_argument("log", type=Path, metavar="LOG", help="flight log directory")
    parser.add_argument("--force", action="store_true",
                        help=f"replace an existing {TRACKS_CSV}")
    parser.add_argument("--max-features", type=int, default=_DEFAULTS.max_features,
                        help="live features per image (default %(default)s)")
    parser.add_argument("--no-imu", action="store_true",
                        help="do not use the gyro's rotation to predict and verify matches "
                             "(the five-point essential matrix verifies them)")
    parser.add_argument("--report", type=Path, metavar="FILE",
                        help="also write the report as JSON to FILE")
    parser.add_argument("--quiet", action="store_true", help="no progress bar, no report")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    target = args.log / TRACKS_CSV
    if target.exists() and not args.force:
        raise CdtmError(f"{target}: exists; expected --force to replace it")
    settings = TrackerSettings(max_features=args.max_features)
    flight = read_flightlog(args.log, read_tracks=False)  # checks every frame has an image
    with tqdm(total=len(flight.frames), unit="frame", desc="tracking", file=sys.stderr,
              disable=args.quiet, leave=False) as bar:
        result = track_log(flight, settings, use_imu=not args.no_imu,
                           progress=lambda done, total: bar.update(1))
    write_tracks(result.tracks, target)
    if args.report is not None:
        with atomic_output_file(args.report) as tmp:
            tmp.write_text(json.dumps(result.report.to_dict(), indent=2) + "\n")
    if not args.quiet:
        print(f"wrote {target}")
        print(result.report.summary())
    return 0
