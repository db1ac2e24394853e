"""``cdtm import euroc|rosbag|px4``: sensor recordings into a ``cdtm-flightlog/1`` directory."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING

from cdtm_graph.atomic import read_manifest
from cdtm_graph.choices import DistortionModel, VerticalDatum
from cdtm_graph.cli import COMMANDS
from cdtm_graph.cli.outdir import OUT_RULES, add_force_option, output_dir
from cdtm_graph.errors import CdtmError, OutputError
from cdtm_graph.flightlog.names import FLIGHT_YAML, FRAMES_CSV, IMU_CSV, LOG_FILES, TRACKS_CSV
from cdtm_graph.importers.options import GnssSource, ImuAxes, ImuNoiseSource, ImuTopics

if TYPE_CHECKING:
    from tqdm import tqdm

    from cdtm_graph.flightlog import FlightLog

#: Who writes an imported log (the output manifest's writer names).
WRITERS = {"euroc": "import euroc", "rosbag": "import rosbag", "px4": "import px4"}

#: The lens models in words (the summary line).
LENS_WORDS = {DistortionModel.NONE: "pinhole lens without distortion",
              DistortionModel.RADTAN: "pinhole lens with radial-tangential distortion",
              DistortionModel.EQUIDISTANT: "fisheye lens (equidistant distortion)"}

_NEXT_STEP = ("next: cdtm track {log}  (features from the images into tracks.csv), then "
              "cdtm smooth {log} --out RUN")


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "import", help=COMMANDS["import"].summary,
        description="Write a cdtm-flightlog/1 directory from sensor recordings: the IMU "
                    "samples, the frame stamps and images (into images/), the calibration "
                    "(Kalibr or EuRoC files) and ground truth when there is some. The log "
                    "has no tracks.csv: run `cdtm track LOG` next (or give --track).")
    sub = parser.add_subparsers(dest="source", required=True, metavar="SOURCE")
    euroc = sub.add_parser(
        "euroc", help="a EuRoC/ASL mav0 folder (imu0, cam0, state_groundtruth_estimate0)",
        description="Import a EuRoC/ASL mav0 folder: imu0/data.csv, cam0/data.csv and "
                    "cam0/data/*, the calibration from cam0/ and imu0/sensor.yaml (or "
                    "Kalibr files), and the initial state from state_groundtruth_estimate0 "
                    "when it covers the first frame.")
    euroc.add_argument("mav0", type=Path, metavar="MAV0_DIR",
                       help="the mav0 folder, or the sequence folder holding it")
    euroc.add_argument("--camera", default="cam0", help="which camera (default %(default)s)")
    euroc.add_argument("--imu", default="imu0", help="which IMU (default %(default)s)")
    _common_options(euroc, kalibr_required=False)
    euroc.set_defaults(func=run)

    bag = sub.add_parser(
        "rosbag", help="a ROS1 .bag or ROS2 bag (sensor_msgs/Imu, Image or CompressedImage)",
        description="Import one IMU topic and one image topic of a ROS1 .bag file or a ROS2 "
                    "bag directory (read with the pure-Python rosbags package: pip install "
                    "'cdtm-graph[rosbag]'). The calibration comes from Kalibr files.")
    bag.add_argument("bag", type=Path, metavar="BAG", help="ROS1 .bag file or ROS2 bag folder")
    bag.add_argument("--imu-topic", help="sensor_msgs/Imu topic (default: rostopic of the "
                                         "Kalibr IMU file)")
    bag.add_argument("--image-topic", help="sensor_msgs/Image or CompressedImage topic "
                                           "(default: rostopic of the camchain's camera)")
    bag.add_argument("--camera", default="cam0",
                     help="the camchain's camera (default %(default)s)")
    bag.add_argument("--stamps", choices=("header", "bag"), default="header",
                     help="message times: header.stamp (default) or the recording time")
    bag.add_argument("--groundtruth", type=Path, metavar="CSV",
                     help="ground truth on the IMU clock: groundtruth.csv columns, EuRoC's "
                          "state_groundtruth_estimate0, or latitude/longitude columns")
    _common_options(bag, kalibr_required=True)
    bag.set_defaults(func=run)

    px4 = sub.add_parser(
        "px4", help="a PX4 flight log (.ulg: IMU, camera triggers, GNSS) and its images",
        description="Import a PX4 ULog file (read with pyulog: pip install 'cdtm-graph[px4]'): "
                    "the IMU from sensor_combined (PX4's FRD body axes, or --imu-axes flu), "
                    "frame times from camera_capture (or camera_trigger) matched in order "
                    "to the images of --images DIR, ground truth and the initial state from "
                    "the GNSS track and vehicle_attitude. The log is geodetic: its origin "
                    "is --origin or the first GNSS fix, its DTM DEM tiles with "
                    "--vertical-datum. The calibration comes from Kalibr files.")
    px4.add_argument("ulog", type=Path, metavar="LOG.ulg", help="the PX4 log")
    px4.add_argument("--images", type=Path, required=True, metavar="DIR",
                     help="the camera's images, one per trigger, in file-name order")
    px4.add_argument("--camera", default="cam0",
                     help="the camchain's camera (default %(default)s)")
    px4.add_argument("--imu-axes", choices=[a.value for a in ImuAxes],
                     default=ImuAxes.FRD.value,
                     help="the log's body axes: frd, PX4's own (default), or flu (x forward, "
                          "y left, z up: ROS base_link, as mavros publishes the IMU), the "
                          "axes the Kalibr calibration was made in")
    px4.add_argument("--imu-topics", choices=[t.value for t in ImuTopics],
                     default=ImuTopics.SENSOR_COMBINED.value,
                     help="sensor_combined (calibrated, default) or raw (sensor_gyro and "
                          "sensor_accel)")
    px4.add_argument("--gnss", choices=[g.value for g in GnssSource],
                     default=GnssSource.GPS.value,
                     help="the ground truth's track: gps (vehicle_gps_position or sensor_gps, "
                          "default) or global_position (vehicle_global_position, the "
                          "estimator's)")
    _common_options(px4, kalibr_required=True)
    px4.set_defaults(func=run)


def _common_options(p: argparse.ArgumentParser, kalibr_required: bool) -> None:
    p.add_argument("--out", type=Path, required=True, metavar="LOG",
                   help=f"the flight log directory to write: {OUT_RULES}")
    add_force_option(p)
    cal = p.add_argument_group("calibration")
    cal.add_argument("--kalibr", type=Path, metavar="CAMCHAIN", required=kalibr_required,
                     help="Kalibr camchain-imucam YAML: intrinsics, lens (radtan, equidistant), "
                          "T_cam_imu (inverted into body_T_cam), timeshift_cam_imu "
                          "(camera.time_offset_s: t_imu = t_cam + shift)"
                          + ("" if kalibr_required else "; default: cam0/sensor.yaml"))
    cal.add_argument("--kalibr-imu", type=Path, metavar="IMU_YAML", required=kalibr_required,
                     help="Kalibr IMU YAML: noise densities, random walks, update_rate"
                          + ("" if kalibr_required else "; default: imu0/sensor.yaml"))
    cal.add_argument("--pixel-sigma-px", type=float, default=0.5,
                     help="1-sigma of a tracked feature's position (default %(default)s px)")
    principal = cal.add_mutually_exclusive_group()
    principal.add_argument("--principal-point-sigma-px", type=float, metavar="PX",
                           help="1-sigma of cx and of cy as the calibration knows them, into "
                                "flight.yaml's camera.principal_point_sigma_px: its effect "
                                "is added to every pose covariance; default: undeclared "
                                "(nothing added)")
    principal.add_argument("--kalibr-results", type=Path, metavar="RESULTS_CAM_TXT",
                           help="instead of --principal-point-sigma-px: Kalibr's "
                                "results-cam.txt (kalibr_calibrate_cameras), whose "
                                "--camera block's 'projection ... +- [...]' gives it (the "
                                "larger of pu's and pv's 1-sigma)")
    cal.add_argument("--imu-noise", choices=[s.value for s in ImuNoiseSource],
                     default=ImuNoiseSource.STATED.value,
                     help="the IMU noise densities flight.yaml gets: the calibration's "
                          "(stated, default), or what the samples scatter where that is "
                          "larger (measured: vibration included); the import measures them "
                          "either way and says when the stated ones are below")
    dtm = p.add_argument_group("terrain")
    dtm.add_argument("--dtm", type=Path, action="append", required=True, metavar="DEM",
                     help="the DTM under the flight (.npz, .asc, .tif in the world frame); "
                          "with --origin, DEM tiles in any CRS: --dtm A.tif --dtm B.tif "
                          "(mosaicked, the first wins where they overlap)")
    dtm.add_argument("--copy-dtm", action="store_true",
                     help="copy the DTM files into the log (default: flight.yaml names them "
                          "where they are)")
    dtm.add_argument("--dtm-sigma-h-m", type=float, metavar="M",
                     help="the DTM's 1-sigma height error (default: 0.08 x grid spacing)")
    dtm.add_argument("--dtm-offset-sigma", type=float, nargs=2, metavar=("H", "V"),
                     help="1-sigma of the whole map's horizontal and vertical offset (m: its "
                          "registration and datum, a DEM product's absolute accuracy; 0 0 "
                          "for a map exactly registered), into flight.yaml's "
                          "dtm.horizontal_offset_sigma_m and dtm.vertical_offset_sigma_m; "
                          "default: undeclared (smoothing then notes map_offset_undeclared)")
    dtm.add_argument("--origin", type=float, nargs=3, metavar=("LAT", "LON", "H"),
                     help="WGS84 latitude, longitude (deg), ellipsoidal height (m) of the "
                          "world origin: the world is the ENU plane there")
    dtm.add_argument("--vertical-datum", choices=[d.value for d in VerticalDatum],
                     help="what the DEM heights are above (with --origin; SRTM and "
                          "Copernicus: egm96)")
    dtm.add_argument("--dtm-crs", metavar="CRS", help="CRS of DEM files that carry none")
    dtm.add_argument("--gravity-mps2", type=float,
                     help="gravity (default 9.80665, with --origin WGS84 normal gravity)")
    init = p.add_argument_group(
        "initial state", "at the first frame; default: the ground truth there. Each given "
                         "value wins over ground truth")
    init.add_argument("--initial-position", type=float, nargs=3, metavar=("X", "Y", "Z"),
                      help="body position in the world frame (m)")
    init.add_argument("--initial-geodetic", type=float, nargs=3, metavar=("LAT", "LON", "H"),
                      help="instead of --initial-position, with --origin: WGS84 position "
                           "(quaternion and velocity then in the local ENU there)")
    init.add_argument("--initial-quaternion", type=float, nargs=4, metavar=("W", "X", "Y", "Z"),
                      help="body -> world attitude")
    init.add_argument("--initial-velocity", type=float, nargs=3, metavar=("VX", "VY", "VZ"),
                      help="velocity in the world frame (m/s)")
    init.add_argument("--initial-gyro-bias", type=float, nargs=3, metavar=("BX", "BY", "BZ"),
                      help="rad/s (default: ground truth's, else 0)")
    init.add_argument("--initial-accel-bias", type=float, nargs=3, metavar=("BX", "BY", "BZ"),
                      help="m/s^2 (default: ground truth's, else 0)")
    init.add_argument("--sigma-position-m", type=float, default=50.0,
                      help="prior sigma (default %(default)s)")
    init.add_argument("--sigma-attitude-deg", type=float, default=1.0,
                      help="prior sigma (default %(default)s)")
    init.add_argument("--sigma-velocity-mps", type=float, default=1.0,
                      help="prior sigma (default %(default)s)")
    init.add_argument("--sigma-gyro-bias", type=float, default=1.0e-4,
                      help="prior sigma, rad/s (default %(default)s)")
    init.add_argument("--sigma-accel-bias", type=float, default=1.0e-2,
                      help="prior sigma, m/s^2 (default %(default)s)")
    p.add_argument("--track", action="store_true",
                   help="also track features through the images into tracks.csv (as "
                        "`cdtm track LOG` does)")
    p.add_argument("--quiet", action="store_true", help="no progress bar, no summary")


def _settings(args: argparse.Namespace):
    from cdtm_graph.geodesy import GeodeticOrigin
    from cdtm_graph.importers import DtmSource, ImportSettings, InitialPrior

    origin = GeodeticOrigin(*args.origin) if args.origin is not None else None
    datum = VerticalDatum(args.vertical_datum) if args.vertical_datum is not None else None
    dtm = DtmSource(tuple(args.dtm), args.dtm_sigma_h_m, origin, datum, args.dtm_crs,
                    args.copy_dtm, tuple(args.dtm_offset_sigma) if args.dtm_offset_sigma
                    else None)
    initial = InitialPrior(
        position_m=args.initial_position,
        geodetic=tuple(args.initial_geodetic) if args.initial_geodetic else None,
        quaternion_wxyz=args.initial_quaternion, velocity_mps=args.initial_velocity,
        gyro_bias=args.initial_gyro_bias, accel_bias=args.initial_accel_bias,
        sigma_position_m=args.sigma_position_m, sigma_attitude_deg=args.sigma_attitude_deg,
        sigma_velocity_mps=args.sigma_velocity_mps, sigma_gyro_bias=args.sigma_gyro_bias,
        sigma_accel_bias=args.sigma_accel_bias)
    principal_point_sigma = args.principal_point_sigma_px
    if args.kalibr_results is not None:
        from cdtm_graph.importers import read_kalibr_principal_point_sigma
        principal_point_sigma = read_kalibr_principal_point_sigma(args.kalibr_results,
                                                                  args.camera)
    return ImportSettings(dtm, args.pixel_sigma_px, args.gravity_mps2, initial,
                          ImuNoiseSource(args.imu_noise), principal_point_sigma)


def _refuse_foreign_log_files(out: Path, writer: str) -> None:
    """Log files in ``--out`` this import did not write (``cdtm track``'s tracks.csv, a
    nav.csv put there by hand, another import's files) would stay beside the new ones and
    be read with them: refused before any work, not silently combined."""
    present = [name for name in LOG_FILES if (out / name).exists()]
    if not present:
        return
    try:
        ours = read_manifest(out) or {}
    except CdtmError:
        ours = {}
    foreign = [name for name in present if ours.get(name) != writer]
    if foreign:
        raise OutputError(f"--out {out}: holds {', '.join(foreign)} that this import did not "
                          "write and that would be read with the imported log; expected them "
                          "removed first (or a new --out)")


class _LazyBar:
    """A progress bar that appears with the first progress report (not before an error)."""

    def __init__(self, unit: str, quiet: bool):
        self.unit, self.quiet = unit, quiet
        self.bar: tqdm | None = None

    def __call__(self, done: int, total: int) -> None:
        if self.quiet:
            return
        if self.bar is None:
            from tqdm import tqdm

            self.bar = tqdm(total=total, unit=self.unit, desc="importing", file=sys.stderr,
                            leave=False)
        self.bar.update(done - self.bar.n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def run(args: argparse.Namespace) -> int:
    from cdtm_graph.importers import import_euroc

    if args.source == "px4":
        _px4_origin(args)
    settings = _settings(args)  # checked before any reading
    out = Path(args.out)
    _refuse_foreign_log_files(out, WRITERS[args.source])
    source = {"euroc": getattr(args, "mav0", None), "rosbag": getattr(args, "bag", None),
              "px4": getattr(args, "ulog", None)}[args.source]
    protected = [source, *args.dtm, *(p for p in (args.kalibr, args.kalibr_imu,
                                                  getattr(args, "groundtruth", None),
                                                  getattr(args, "images", None)) if p)]
    names = [FLIGHT_YAML, IMU_CSV, FRAMES_CSV, *([TRACKS_CSV] if args.track else []),
             *(p.name for p in args.dtm if args.copy_dtm)]
    progress = _LazyBar("msg" if args.source == "rosbag" else "image", args.quiet)
    with output_dir(args, out, WRITERS[args.source], protected=protected, names=names,
                    label="--out") as staging:
        contents = None
        if args.source == "euroc":
            log = import_euroc(args.mav0, staging, out, settings, kalibr=args.kalibr,
                               kalibr_imu=args.kalibr_imu, camera=args.camera, imu=args.imu,
                               progress=progress)
        elif args.source == "px4":
            log = _import_px4(args, staging, out, settings, progress)
        else:
            log, contents = _import_bag(args, staging, out, settings, progress)
        progress.close()
        tracked = (_track(log, staging, args.quiet, _image_sources(args, log))
                   if args.track else None)
    if not args.quiet:
        print(_summary(log, out, contents, tracked))
    rate = _rate_finding(log)
    if rate is not None:  # (said now, not first at the smoothing's verdict)
        print(f"cdtm import: warning: {out / 'flight.yaml'}: {rate}", file=sys.stderr)
    return 0


def _rate_finding(log: FlightLog) -> str | None:
    """The verdict's ``imu_rate_mismatch`` finding on the imported samples against the
    imu.rate_hz the import wrote (a calibration file's, which may be another rate's)."""
    from cdtm_graph.codes import Code
    from cdtm_graph.verdict.imu_faults import check_imu

    imu = log.imu
    found = [f for f in check_imu(imu.t_ns, imu.gyro_radps, imu.acc_mps2,
                                  log.config.imu.rate_hz)
             if f.code is Code.IMU_RATE_MISMATCH]
    return found[0].message if found else None


def _import_bag(args, staging: Path, out: Path, settings, progress):
    from cdtm_graph.importers import (
        BagTopics,
        StampSource,
        import_rosbag,
        read_groundtruth,
        read_kalibr_camchain,
        read_kalibr_imu,
    )

    camera = read_kalibr_camchain(args.kalibr, args.camera)
    imu = read_kalibr_imu(args.kalibr_imu)
    truth = (read_groundtruth(args.groundtruth, settings.dtm.origin)
             if args.groundtruth is not None else None)
    return import_rosbag(args.bag, staging, out, settings, camera=camera, imu=imu,
                         topics=BagTopics(args.imu_topic, args.image_topic), groundtruth=truth,
                         stamps=StampSource(args.stamps), progress=progress)


def _px4_origin(args: argparse.Namespace) -> None:
    """A PX4 log is geodetic: a DEM's vertical datum is required, and the origin defaults to
    the log's first GNSS fix."""
    from cdtm_graph.errors import SensorDataError
    from cdtm_graph.importers.px4 import gnss_origin

    if args.vertical_datum is None:
        raise SensorDataError("a PX4 log is in latitude and longitude; expected --dtm DEM "
                              "tiles with --vertical-datum (SRTM and Copernicus: egm96)")
    if args.origin is None:
        origin = gnss_origin(args.ulog, GnssSource(args.gnss))
        args.origin = [origin.latitude_deg, origin.longitude_deg, origin.height_m]


def _import_px4(args, staging: Path, out: Path, settings, progress):
    from cdtm_graph.importers import read_kalibr_camchain, read_kalibr_imu
    from cdtm_graph.importers.px4 import Px4Options, import_px4

    options = Px4Options(ImuAxes(args.imu_axes), ImuTopics(args.imu_topics),
                         GnssSource(args.gnss))
    return import_px4(args.ulog, args.images, staging, out, settings,
                      camera=read_kalibr_camchain(args.kalibr, args.camera),
                      imu=read_kalibr_imu(args.kalibr_imu), options=options,
                      progress=progress)


def _image_sources(args: argparse.Namespace, log: FlightLog) -> dict[str, str]:
    """What the user knows each imported image as: the EuRoC file it was copied from, or
    the bag it was decoded from (the staging copies vanish with a failed import)."""
    if args.source == "euroc":
        from cdtm_graph.importers.euroc import find_mav0

        data = find_mav0(args.mav0) / args.camera / "data"
        return {name: str(data / PurePosixPath(name).name) for name in log.frames.image}
    if args.source == "px4":
        return {name: str(args.images / PurePosixPath(name).name) for name in log.frames.image}
    return {name: f"{args.bag} (image {PurePosixPath(name).name} decoded from "
                  f"{args.image_topic or 'the image topic'})" for name in log.frames.image}


def _track(log: FlightLog, staging: Path, quiet: bool, sources: dict[str, str]):
    from tqdm import tqdm

    from cdtm_graph.flightlog import write_tracks
    from cdtm_graph.frontend import track_log

    try:
        with tqdm(total=len(log.frames), unit="frame", desc="tracking", file=sys.stderr,
                  disable=quiet, leave=False) as bar:
            result = track_log(log, progress=lambda done, total: bar.update(1))
    except CdtmError as exc:  # name the user's files, not the staging copies
        text = str(exc)
        for name, source in sources.items():
            text = text.replace(str(log.root / name), source)
        exc.args = (text,)
        raise
    write_tracks(result.tracks, staging / TRACKS_CSV)
    return result


def _noise_line(log: FlightLog) -> str:
    """The IMU noise densities the log got, and what the samples showed."""
    imported = log.config.extra.get("import", {})
    imu = log.config.imu
    line = (f"IMU noise {imported.get('imu_noise_source', 'stated')}: "
            f"{imu.gyroscope_noise_density:.3g} rad/s/sqrt(Hz), "
            f"{imu.accelerometer_noise_density:.3g} m/s^2/sqrt(Hz)")
    measured = imported.get("imu_noise_measured")
    if measured:
        gyro, accel = measured["measured_over_stated"]
        line += f" (the samples scatter {gyro:.1f}x and {accel:.1f}x the calibration's)"
    return line


def _summary(log: FlightLog, out: Path, contents, tracked) -> str:
    imu_t, frame_t = log.imu.t_ns, log.frames.t_ns
    span_s = (frame_t[-1] - frame_t[0]) / 1e9
    rate_hz = (len(imu_t) - 1) / max((imu_t[-1] - imu_t[0]) / 1e9, 1e-9)
    cam = log.config.camera
    lines = [f"wrote {out}: {len(log.frames)} frames over {span_s:.1f} s (images in "
             f"{out / 'images'}), {len(log.imu)} IMU samples ({rate_hz:.0f} Hz), "
             f"{'ground truth' if log.groundtruth is not None else 'no ground truth'}",
             f"camera {cam.camera.width}x{cam.camera.height} px, "
             f"{LENS_WORDS[cam.camera.model]}, time offset {cam.time_offset_s * 1e3:g} ms "
             "(t_imu = t_cam + offset)", _noise_line(log)]
    outside = log.config.extra.get("import", {}).get("frames_outside_imu", 0)
    if outside:
        lines.append(f"left out {outside} frames outside the IMU's time span")
    if contents is not None and (contents.duplicate_imu or contents.duplicate_frames):
        lines.append(f"left out {contents.duplicate_imu} IMU and {contents.duplicate_frames} "
                     "image messages repeating an earlier stamp")
    if tracked is not None:
        lines.append(f"wrote {out / TRACKS_CSV}")
        lines.append(tracked.report.summary())
        lines.append(f"next: cdtm smooth {out} --out RUN")
    else:
        lines.append(_NEXT_STEP.format(log=out))
    return "\n".join(lines)
