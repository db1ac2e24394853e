"""The ``cdtm`` command line: one module per subcommand, one catch point for errors.

Each subcommand module defines ``register(subparsers)``, which adds its parser (its
one-line summary from :data:`COMMANDS`, and a description) and sets ``func`` to a
``run(args) -> int``. Only the module of the command given is imported: ``cdtm --version``,
``cdtm --help`` and a mistyped command name answer without loading the numerics. A usage
error (exit 2) prints the usage of the (sub)command it belongs to. User mistakes
(:class:`CdtmError`, missing files) and the system's refusals (disk full, I/O errors)
become one line on stderr and exit code 1; anything else is a bug and keeps its
traceback. A smoothing run that wrote its outputs exits 0 when its verdict is trusted
and 3 when degraded or failed (:mod:`cdtm_graph.verdict`), each reason one line on
stderr. SIGTERM is handled as SIGINT: a ``KeyboardInterrupt`` unwinds (staging
directories are removed, outputs stay as they were) and the exit code is 130.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import os
import signal
import sys
import threading
from collections.abc import Iterator
from typing import NamedTuple

from cdtm_graph import __version__
from cdtm_graph.errors import CdtmError


class Command(NamedTuple):
    """A subcommand: the module under ``cdtm_graph.cli`` that registers it, and the one
    line ``cdtm --help`` lists it with."""

    module: str
    summary: str


#: The subcommands, in the order ``cdtm --help`` lists them.
COMMANDS: dict[str, Command] = {
    "demo": Command("demo", "smooth the bundled sample log into ./cdtm-demo-out "
                            "(--images: render, track and smooth a flight)"),
    "smooth": Command("smooth", "smooth a flight log (IMU + C-DTM factors)"),
    "smooth-many": Command("smooth_many", "smooth many logs in parallel and evaluate them "
                                          "together"),
    "evaluate": Command("evaluate", "compare run directories: one table and figures"),
    "import": Command("import_", "turn a EuRoC folder or a ROS bag into a flight log"),
    "track": Command("track", "track features through the log's images into tracks.csv"),
    "simulate": Command("simulate", "write a simulated flight log: terrain, IMU, ray-cast "
                                    "feature tracks (and images)"),
    "analyze": Command("analyze", "closed-form C-DTM error analysis of a frame pair "
                                  "(eqs. 9-32)"),
    "study": Command("study", "sweep one parameter as in the paper's Figs. 2-9 (predicted vs "
                              "achieved accuracy)"),
    "navsim": Command("navsim", "the paper's navigation simulation: Free vs Compensated max "
                                "errors (Tables 1-2)"),
    "accuracy-map": Command("accuracy_map", "map the predicted camera-2 accuracy (closed "
                                            "form) over a DTM"),
}


#: The worked example ``cdtm --help`` ends with (README and docs/flightlog.md tell it whole;
#: tests/project/test_worked_example.py runs it).
GEODETIC_EXAMPLE = """\
exit status: 0 success (cdtm smooth, cdtm demo: the run's verdict is trusted); 3 outputs
written but the verdict is degraded or failed (each reason one line on stderr); 1 bad
input or nothing written (one line on stderr); 2 usage error (a mistyped option or
command: the command's usage on stderr); 130 interrupted.

worked example: a flight in latitude/longitude over an EPSG:4326 DEM with EGM96 heights
(as SRTM and Copernicus GLO-30 tiles come), end to end:
  cdtm simulate my_flight --origin 36.5 127.25 120
  cdtm smooth my_flight --out my_run --plots
  flight.yaml:  origin: {latitude_deg: 36.5, longitude_deg: 127.25, height_m: 120.0}
                dtm: {path: dem.tif, vertical_datum: egm96}  (a real flight: its tiles,
                path: [N36E127.tif, N36E128.tif])
                initial_state: latitude_deg/longitude_deg/height_m (attitude, velocity
                in the local ENU there) instead of position_m
  nav.csv, groundtruth.csv: #t_ns,latitude_deg,longitude_deg,height_m,qw,qx,qy,qz,ve,vn,vu
  my_run/trajectory_geodetic.csv (lat, lon, ellipsoidal height, 1-sigma north/east/up),
  my_run/trajectory.geojson, my_run/trajectory_dem.png (over the DEM in its own CRS);
  my_run/groundtruth.tum beside my_run/trajectory.tum (same frames, same world frame):
    evo_ape tum my_run/groundtruth.tum my_run/trajectory.tum
  cdtm smooth ... --scene adds my_run/scene.glb (3-D, any glTF viewer)
from sensor recordings:
  cdtm import euroc MH_01/mav0 --dtm DEM --out my_log [--kalibr camchain-imucam.yaml]
  cdtm import rosbag flight.bag --kalibr CAMCHAIN --kalibr-imu IMU_YAML --dtm DEM --out my_log
  cdtm track my_log && cdtm smooth my_log --out my_run
"""


#: ``build_parser(only=ALL)``: every subcommand's parser (for tests and documentation).
ALL = "*"


def build_parser(only: str | None = ALL) -> argparse.ArgumentParser:
    """The ``cdtm`` parser. ``only``: the one subcommand whose module is imported and
    registered in full (the others are listed by name and summary; None: none is);
    ``ALL``: every one."""
    parser = argparse.ArgumentParser(
        prog="cdtm",
        description="C-DTM navigation: smooth flight logs from camera, IMU and a DTM; "
                    "analyse and predict accuracy (Kupervasser et al.).",
        epilog=GEODETIC_EXAMPLE, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, command in COMMANDS.items():
        if only is ALL or name == only:
            importlib.import_module(f"cdtm_graph.cli.{command.module}").register(sub)
        else:
            sub.add_parser(name, help=command.summary, add_help=False)
    return parser


def _command_named(argv: list[str]) -> str | None:
    """The subcommand ``argv`` names (its first word that is not an option), if any."""
    word = next((a for a in argv if not a.startswith("-")), None)
    return word if word in COMMANDS else None


def _innermost_parser(parser: argparse.ArgumentParser,
                      args: argparse.Namespace) -> argparse.ArgumentParser:
    """The parser of the (sub)subcommand ``args`` were parsed into (``cdtm import euroc``)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            chosen = action.choices.get(getattr(args, action.dest, None) or "")
            if chosen is not None:
                return _innermost_parser(chosen, args)
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """``argv`` parsed; a usage error exits 2 with the usage of the command it is in
    (argparse itself reports an unknown option with the top-level usage)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(only=_command_named(argv))
    args, unknown = parser.parse_known_args(argv)
    if unknown:
        _innermost_parser(parser, args).error(f"unrecognized arguments: {' '.join(unknown)}")
    return args


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM raises KeyboardInterrupt while the command runs (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _caused_by_interrupt(exc: BaseException) -> bool:
    """Whether ``exc`` comes from a KeyboardInterrupt: a signal handled inside a compiled
    callback (numba, GTSAM) resurfaces as e.g. a SystemError chained to it."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        if isinstance(current, KeyboardInterrupt):
            return True
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return False


#: Commands that compile no numerical kernel (no announcement to set up).
QUICK = frozenset({"evaluate"})


def main(argv: list[str] | None = None) -> int:
    command = "cdtm"
    try:
        with _sigterm_as_interrupt():  # from the start: the imports take a second or two
            args = parse_args(argv)
            command = f"cdtm {args.command}"
            logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                                format="%(levelname)s %(name)s: %(message)s")
            if args.command in QUICK:
                return int(args.func(args) or 0)
            from cdtm_graph.cli.compiling import announced

            with announced(command, quiet=getattr(args, "quiet", False)):
                return int(args.func(args) or 0)
    except CdtmError as exc:
        print(f"{command}: error: {exc}", file=sys.stderr)
        return 1
    except BrokenPipeError:  # e.g. `cdtm ... | head`: the reader left; stop quietly
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 1
    except OSError as exc:  # missing file, no permission, disk full, I/O error...
        if exc.errno is None:
            raise
        where = f": {exc.filename}" if exc.filename else ""
        print(f"{command}: error: {exc.strerror}{where}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        if not _caused_by_interrupt(exc):
            raise
        print(f"{command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
