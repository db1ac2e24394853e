"""The ``cdtm`` command line: one module per subcommand, one catch point for errors.

Each subcommand module defines ``register(subparsers)``, which adds its parser and sets
``func`` to a ``run(args) -> int``. User mistakes (:class:`CdtmError`, missing files)
and the system's refusals (disk full, I/O errors) become one line on stderr and exit code
1; anything else is a bug and keeps its traceback. A smoothing run that wrote its
outputs exits 0 when its verdict is trusted and 3 when degraded or failed
(:mod:`cdtm_graph.verdict`), each reason one line on stderr. SIGTERM is handled as SIGINT: a
``KeyboardInterrupt`` unwinds (staging directories are removed, outputs stay as they
were) and the exit code is 130.
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

from cdtm_graph.errors import CdtmError

#: Subcommand modules, in the order ``cdtm --help`` lists them.
SUBCOMMANDS = ("demo", "smooth", "smooth_many", "evaluate", "import_", "track", "simulate",
               "analyze", "study", "navsim", "accuracy_map")


#: The worked example ``cdtm --help`` ends with (README and docs/flightlog.md tell it whole;
#: tests/test_worked_example.py runs it).
GEODETIC_EXAMPLE = """\
exit status: 0 success (cdtm smooth, cdtm demo: the run's verdict is trusted); 3 outputs
written but the verdict is degraded or failed (each reason one line on stderr); 1 bad
input or nothing written (one line on stderr); 130 interrupted.

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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cdtm",
        description="C-DTM navigation: smooth flight logs from camera, IMU and a DTM; "
                    "analyse and predict accuracy (Kupervasser et al.).",
        epilog=GEODETIC_EXAMPLE, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in SUBCOMMANDS:
        try:
            module = importlib.import_module(f"cdtm_graph.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"cdtm_graph.cli.{name}":
                raise
            continue  # subcommand not built yet
        module.register(sub)
    return parser


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


def main(argv: list[str] | None = None) -> int:
    command = "cdtm"
    try:
        with _sigterm_as_interrupt():  # from the start: the imports take a second or two
            parser = build_parser()
            args = parser.parse_args(argv)
            command = f"cdtm {args.command}"
            logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                                format="%(levelname)s %(name)s: %(message)s")
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
