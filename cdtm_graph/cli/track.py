"""``cdtm track LOG``: the images named in frames.csv to LOG/tracks.csv, with a short report.

Outputs follow :mod:`cdtm_graph.atomic`'s rules, for two single files:

* **Checked before the work.** ``LOG/tracks.csv`` (absent, or a file with ``--force``) and
  the ``--report`` path (a new file in an existing directory, or a report ``cdtm track``
  wrote earlier: JSON whose ``"format"`` is :data:`REPORT_FORMAT`; never another file, a
  directory, nor one of the log's own files) are checked, and their temporary files
  created beside them, before the images are tracked: a bad path fails at once.
* **Credited.** In a log cdtm wrote (it holds a manifest), tracks.csv is then listed as
  ``track``'s: rerunning ``cdtm simulate`` or an import there refuses to replace it.
* **Complete or not at all.** A run that tracks nothing writes nothing. Otherwise both
  files are written to their temporary files first, then renamed into place, the report
  first: if tracks.csv cannot be renamed, the report is put back as it was. On any
  failure the temporary files are removed and both paths are as they were.

Frame pairs keeping fewer than a quarter of ``--max-features`` are named in one warning
line on stderr (:meth:`~cdtm_graph.frontend.track_log.TrackingReport.weak_pairs_warning`);
the report gives every pair's count and the reasons its features ended.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from cdtm_graph.atomic import credit_file, fsync_path, signals_deferred, temporary_beside
from cdtm_graph.cli import COMMANDS
from cdtm_graph.errors import CdtmError, OutputError
from cdtm_graph.flightlog.names import FRAMES_CSV, LOG_FILES, TRACKS_CSV
from cdtm_graph.frontend.settings import TrackerSettings

if TYPE_CHECKING:
    from cdtm_graph.flightlog import FlightLog
    from cdtm_graph.frontend.track_log import TrackingReport

_DEFAULTS = TrackerSettings()

#: The marker of a report ``cdtm track`` wrote (its ``"format"`` key): only a file holding
#: it may be replaced by ``--report``.
REPORT_FORMAT = "cdtm-track-report/1"
#: The keys of the reports cdtm track wrote before it marked them (replaced as its own).
_UNMARKED_REPORT_KEYS = frozenset({
    "frames", "tracks", "single_sightings_dropped", "features_per_frame", "pairs_per_frame",
    "track_length_frames", "rejected", "epipolar_fits", "imu_rotations",
    "seconds_per_frame_median"})
#: A report is a few kB; a larger file is not one (and is not read whole to find out).
REPORT_MAX_BYTES = 1 << 20

REPORT_HELP = (
    "also write the report as JSON to FILE: a new file in an existing directory, or a "
    f"report cdtm track wrote earlier (JSON with \"format\": \"{REPORT_FORMAT}\"), which is "
    "replaced. Any other existing file, a directory, and the log's own files (flight.yaml, "
    "the CSV files, the DTM, the images) are refused, with or without --force. Checked "
    "before tracking; tracks.csv and the report are written together or not at all")


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "track", help=COMMANDS["track"].summary,
        description="Read the images named in frames.csv, track features through them "
                    "(Lucas-Kanade with IMU-predicted rotation, forward-backward check, "
                    "epipolar RANSAC, bucketed corners) and write LOG/tracks.csv. A run "
                    "in which no feature is tracked from one frame to the next writes "
                    "nothing.")
    parser.add_argument("log", type=Path, metavar="LOG", help="flight log directory")
    parser.add_argument("--force", action="store_true",
                        help=f"replace an existing {TRACKS_CSV} (only it: --force never "
                             "lets --report overwrite a file)")
    parser.add_argument("--max-features", type=int, default=_DEFAULTS.max_features,
                        help="live features per image (default %(default)s)")
    parser.add_argument("--no-imu", action="store_true",
                        help="do not use the gyro's rotation to predict and verify matches "
                             "(the five-point essential matrix verifies them)")
    parser.add_argument("--report", metavar="FILE", help=REPORT_HELP)
    parser.add_argument("--quiet", action="store_true",
                        help="no progress bar, no report (the weak-pairs warning stays)")
    parser.set_defaults(func=run)


# --------------------------------------------------------------------------- checks


#: Who the log's manifest (if it has one) says wrote the tracks.csv ``cdtm track`` wrote.
WRITER = "track"


def _check_tracks_target(target: Path, force: bool) -> None:
    """LOG/tracks.csv: absent, or a file replaced with ``--force``."""
    if not os.path.lexists(target):
        return
    if target.is_dir():
        raise OutputError(f"{target}: is a directory; expected the {TRACKS_CSV} file "
                          "this command writes, or no such entry (move the directory)")
    if not target.is_file():
        raise OutputError(f"{target}: is not a regular file (a broken link, a FIFO, a "
                          f"device); expected the {TRACKS_CSV} file this command writes, "
                          "or no such entry")
    if not force:
        raise OutputError(f"{target}: exists; expected --force to replace it")


def _is_track_report(path: Path, shown: str) -> bool:
    """Whether the regular file ``path`` is a report ``cdtm track`` wrote."""
    try:
        if path.stat().st_size > REPORT_MAX_BYTES:
            return False
        data = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, ValueError):
        return False
    except OSError as exc:
        raise OutputError(f"{shown}: cannot be read ({exc.strerror}); expected a new file "
                          "or a report cdtm track wrote earlier") from None
    return isinstance(data, dict) and (data.get("format") == REPORT_FORMAT
                                       or set(data) == _UNMARKED_REPORT_KEYS)


def _report_expected() -> str:
    return (f"expected a new file in an existing directory, or a report cdtm track wrote "
            f"earlier (JSON with \"format\": \"{REPORT_FORMAT}\")")


def _check_report_path(given: str) -> Path:
    """The ``--report`` path, absolute, if it may be a file: a regular file, or a new name
    in an existing directory (whose file is whose: :func:`_check_report_owner`)."""
    shown = f"--report {given}"
    expected = _report_expected()
    if given.endswith(("/", os.sep)) or Path(given).name in ("", ".", ".."):
        raise OutputError(f"{shown}: names a directory; {expected}")
    path = Path(os.path.normpath(os.path.abspath(given)))
    if os.path.lexists(path):
        if path.is_symlink():
            raise OutputError(f"{shown}: is a symbolic link; {expected}")
        if path.is_dir():
            raise OutputError(f"{shown}: is a directory; {expected}, e.g. "
                              f"{Path(given) / 'track_report.json'}")
        if not path.is_file():
            raise OutputError(f"{shown}: is not a regular file; {expected}")
        return path
    probe = path.parent
    while not os.path.lexists(probe):
        probe = probe.parent
    if not probe.is_dir():
        raise OutputError(f"{shown}: {probe} is not a directory; {expected}")
    if probe != path.parent:
        raise OutputError(f"{shown}: directory {path.parent} does not exist; {expected}")
    return path


def _check_report_owner(report: Path, given: str) -> None:
    """An existing report file must be one ``cdtm track`` wrote."""
    shown = f"--report {given}"
    if os.path.lexists(report) and not _is_track_report(report, shown):
        raise OutputError(f"{shown}: exists and is not a report cdtm track wrote; "
                          f"{_report_expected()} (cdtm never overwrites what it did not "
                          "write: move it, or choose another path)")


def _check_report_apart_from_inputs(report: Path, given: str, flight: FlightLog) -> None:
    """The report must not be one of the log's files (even one it does not have yet)."""
    root = flight.root
    inputs = [root / name for name in LOG_FILES]
    inputs += list(flight.config.dtm.paths)
    inputs += [root / name for name in flight.frames.image if name]
    real = os.path.realpath(report)
    exists = os.path.lexists(report)
    for item in inputs:
        if os.path.realpath(item) == real or (
                exists and os.path.exists(item) and os.path.samefile(item, report)):
            raise OutputError(f"--report {given}: is the flight log's {item}; expected a "
                              "path apart from the log's own files (flight.yaml, the CSV "
                              "files, the DTM, the images)")


def _check_tracked(report: TrackingReport, log: Path, target: Path, existed: bool) -> None:
    """Refuse tracks that tie no two frames together: the smoother would refuse them."""
    if report.pairs_per_frame.any():
        return
    k = report.n_frames
    found = (f"{report.n_single_sightings} feature(s) found, each in one frame only"
             if report.n_single_sightings else "no feature found in any image")
    frames = f"frames 0-{k - 1}" if k > 1 else "one frame"
    kept = f"{target} left as it was" if existed else "nothing written"
    raise CdtmError(f"{log / FRAMES_CSV}: no feature could be tracked from one frame to "
                    f"the next in its {k} image(s) ({frames}: {found}); expected "
                    "overlapping images with texture to track (blank, saturated or "
                    f"unrelated images?); {kept}")


# --------------------------------------------------------------------------- writing


@contextlib.contextmanager
def _temporary_file(target: Path, shown: str) -> Iterator[Path]:
    """An empty temporary file beside ``target``, removed on exit unless renamed."""
    try:
        tmp = temporary_beside(target)
    except OSError as exc:
        raise OutputError(f"{shown}: cannot write in {target.parent}: {exc.strerror}; "
                          "expected a writable directory") from None
    try:
        yield tmp
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def _write_text(path: Path, text: str) -> None:
    with open(path, "w", encoding="utf-8") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())


def _publish(tracks_tmp: Path, target: Path, report_tmp: Path | None, report: Path | None,
             force: bool, report_given: str | None) -> None:
    """Rename the report, then tracks.csv, into place; put the report back as it was if
    tracks.csv cannot be. The targets are checked again: something may have appeared
    meanwhile."""
    _check_tracks_target(target, force)
    if report is None or report_tmp is None or report_given is None:
        os.replace(tracks_tmp, target)
        credit_file(target.parent, target.name, WRITER)
        fsync_path(target.parent)
        return
    _check_report_owner(_check_report_path(report_given), report_given)  # still ours
    existed = os.path.lexists(report)
    with contextlib.ExitStack() as stack:
        backup = None
        if existed:  # a copy to put back (a report is small)
            backup = stack.enter_context(_temporary_file(report, f"--report {report_given}"))
            shutil.copyfile(report, backup)
            shutil.copymode(report, backup)
        os.replace(report_tmp, report)
        try:
            os.replace(tracks_tmp, target)
        except BaseException as exc:
            try:
                if backup is not None:
                    os.replace(backup, report)
                else:
                    os.unlink(report)
            except OSError as undo:
                raise OutputError(
                    f"{target}: cannot be written ({getattr(exc, 'strerror', None) or exc}), "
                    f"and --report {report_given} could not be put back as it was "
                    f"({undo.strerror}); expected a writable place: it holds this run's "
                    "report, which does not match the tracks.csv there") from None
            raise
    credit_file(target.parent, target.name, WRITER)
    fsync_path(report.parent)
    fsync_path(target.parent)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from cdtm_graph.flightlog import read_flightlog, write_tracks
    from cdtm_graph.frontend import track_log

    target = args.log / TRACKS_CSV
    _check_tracks_target(target, args.force)
    given = args.report
    report = _check_report_path(given) if given is not None else None
    settings = TrackerSettings(max_features=args.max_features)
    flight = read_flightlog(args.log, read_tracks=False)  # checks every frame has an image
    if report is not None:
        _check_report_apart_from_inputs(report, given, flight)
        _check_report_owner(report, given)
    existed = os.path.lexists(target)
    with contextlib.ExitStack() as stack:
        # The temporary files now: an unwritable place fails before the tracking.
        tracks_tmp = stack.enter_context(_temporary_file(target, str(target)))
        report_tmp = None
        if report is not None:
            report_tmp = stack.enter_context(_temporary_file(report, f"--report {given}"))
        with tqdm(total=len(flight.frames), unit="frame", desc="tracking", file=sys.stderr,
                  disable=args.quiet, leave=False) as bar:
            result = track_log(flight, settings, use_imu=not args.no_imu,
                               progress=lambda done, total: bar.update(1))
        _check_tracked(result.report, args.log, target, existed)
        try:
            write_tracks(result.tracks, tracks_tmp)
            if report_tmp is not None:
                data = {"format": REPORT_FORMAT, **result.report.to_dict()}
                _write_text(report_tmp, json.dumps(data, indent=2) + "\n")
            with signals_deferred():
                _publish(tracks_tmp, target, report_tmp, report, args.force, given)
        except OSError as exc:
            where, kept = ((f"{target}", "it is as it was") if report is None else
                           (f"{target} and --report {given}", "both are as they were"))
            raise OutputError(f"{where}: cannot be written ({exc.strerror or exc}); expected "
                              f"a writable place with room; nothing written, {kept}"
                              ) from None
    if not args.quiet:
        print(f"wrote {target}" + (f" and {given}" if given is not None else ""))
        print(result.report.summary())
    warning = result.report.weak_pairs_warning()
    if warning is not None:  # a finding, shown with --quiet too
        print(f"cdtm track: warning: {warning}", file=sys.stderr)
    return 0
