"""``cdtm simulate OUT``: write a simulated flight log (with its DTM, and images) to a directory."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from cdtm_graph.choices import DistortionModel, VerticalDatum
from cdtm_graph.cli import COMMANDS
from cdtm_graph.cli.outdir import OUT_RULES, add_force_option, output_dir
from cdtm_graph.errors import CdtmError
from cdtm_graph.sim.settings import (
    DEFAULT_SEED,
    NOMINAL_ALTITUDE_M,
    NOMINAL_DTM_SPACING_M,
    NOMINAL_FEATURES,
    NOMINAL_FPS,
    NOMINAL_FRAMES,
    NOMINAL_RELIEF_M,
    NOMINAL_RESOLUTION_PX,
    NOMINAL_SPEED_MPS,
    NavMode,
    RenderSettings,
)

_RENDER_DEFAULTS = RenderSettings()


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "simulate",
        help=COMMANDS["simulate"].summary,
        description="Simulate a flight over terrain (the paper's section VI.A: a cloned 3x3 km "
                    "fractal cell, or a DTM file) with an IMU and a downward camera, and write "
                    "it as a cdtm-flightlog/1 directory holding its DTM (dtm.npz). With "
                    "--images, also render what the camera sees into images/ (the true "
                    "terrain, which differs from the log's DTM) and list them in frames.csv; "
                    "tracks.csv still holds the ideal ray-cast tracks (cdtm track --force "
                    "replaces them with tracks from the images).")
    parser.add_argument("out", type=Path, metavar="OUT",
                        help=f"log directory to write: {OUT_RULES}")
    add_force_option(parser)
    parser.add_argument("--terrain", type=Path, metavar="DTMFILE",
                        help="fly over this DTM (.npz, .asc, .tif) instead of a fractal "
                             "terrain; it is then also the log's DTM")
    parser.add_argument("--altitude-m", "--alt-m", type=float, default=NOMINAL_ALTITUDE_M,
                        help="altitude above the terrain's mean height, m (default %(default)s)")
    parser.add_argument("--speed-mps", type=float, default=NOMINAL_SPEED_MPS,
                        help="ground speed, m/s (default %(default)s)")
    parser.add_argument("--frames", type=int, default=NOMINAL_FRAMES,
                        help="number of camera frames (default %(default)s)")
    parser.add_argument("--fps", type=float, default=NOMINAL_FPS,
                        help="frame rate, Hz (default %(default)s)")
    parser.add_argument("--resolution", type=int, nargs=2, metavar=("W", "H"),
                        default=list(NOMINAL_RESOLUTION_PX),
                        help="image width and height, pixels (default %(default)s)")
    parser.add_argument("--distortion-model", choices=[m.value for m in DistortionModel],
                        default=DistortionModel.NONE.value,
                        help="the lens the features are projected through (default "
                             "%(default)s): radtan (k1 k2 p1 p2 [k3]) or equidistant (fisheye, "
                             "k1 k2 k3 k4)")
    parser.add_argument("--distortion-coeffs", type=float, nargs="+", default=[], metavar="K",
                        help="the lens's coefficients")
    parser.add_argument("--features", type=int, default=NOMINAL_FEATURES,
                        help="features per consecutive frame pair (default %(default)s)")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED,
                        help="seed of every random draw (default %(default)s)")
    parser.add_argument("--noiseless", action="store_true",
                        help="no IMU noise or bias, no pixel noise, the DTM is the truth")
    parser.add_argument("--exact-dtm", action="store_true",
                        help="the log's DTM is the true terrain (not resampled)")
    parser.add_argument("--dtm-spacing-m", type=float, default=NOMINAL_DTM_SPACING_M,
                        help="grid spacing of the log's DTM, the truth resampled, m (default "
                             "%(default)s; not used with --terrain, --exact-dtm, --noiseless)")
    parser.add_argument("--relief-m", type=float, default=NOMINAL_RELIEF_M,
                        help="relief (max - min) of the fractal terrain cell, m "
                             "(default %(default)s; not used with --terrain)")
    parser.add_argument("--nav", choices=[m.value for m in NavMode], default=NavMode.NONE.value,
                        help="write nav.csv: none, IMU dead reckoning, or noisy truth "
                             "(default %(default)s)")
    geo = parser.add_argument_group(
        "geodetic log", "place the flight on the Earth: lat/lon inputs and a DEM tile")
    geo.add_argument("--origin", type=float, nargs=3, metavar=("LAT", "LON", "H"),
                     help="WGS84 latitude, longitude (deg) and ellipsoidal height (m) of the "
                          "world origin: writes dem.tif instead of dtm.npz, and the initial "
                          "state, nav.csv and groundtruth.csv in latitude/longitude/height; "
                          "the IMU senses the Earth's rotation and WGS84 normal gravity")
    geo.add_argument("--dem-crs", default="EPSG:4326",
                     help="CRS of dem.tif (default %(default)s, as SRTM and Copernicus)")
    geo.add_argument("--vertical-datum", choices=[d.value for d in VerticalDatum],
                     default=VerticalDatum.EGM96.value,
                     help="heights of dem.tif above the geoid or the ellipsoid "
                          "(default %(default)s)")
    images = parser.add_argument_group("images (--images)")
    images.add_argument("--images", action="store_true",
                        help="render the camera's images into OUT/images/")
    images.add_argument("--orthophoto", type=Path, metavar="TIF",
                        help="ground texture from this orthophoto GeoTIFF (the DTM's CRS; "
                             "needs rasterio) instead of a procedural one")
    images.add_argument("--exposure-jitter", type=float, default=_RENDER_DEFAULTS.exposure_jitter,
                        help="relative exposure change per frame, uniform in +-this "
                             "(default %(default)s)")
    images.add_argument("--motion-blur-px", type=float, default=_RENDER_DEFAULTS.motion_blur_px,
                        help="motion blur along the image motion, pixels (default %(default)s)")
    images.add_argument("--image-noise-dn", type=float, default=_RENDER_DEFAULTS.noise_sigma_dn,
                        help="sensor noise, 8-bit digital numbers (default %(default)s)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from cdtm_graph.geodesy import GeodeticOrigin
    from cdtm_graph.sim.render import OrthophotoTexture, render_flight
    from cdtm_graph.sim.simulate import (
        WRITER,
        SimulationSettings,
        simulate,
        write_simulation_files,
    )

    settings = SimulationSettings(
        terrain=args.terrain, altitude_m=args.altitude_m, speed_mps=args.speed_mps,
        frames=args.frames,
        fps=args.fps, n_features=args.features, seed=args.seed, noiseless=args.noiseless,
        exact_dtm=args.exact_dtm, dtm_spacing_m=args.dtm_spacing_m, relief_m=args.relief_m,
        nav=args.nav, resolution_px=tuple(args.resolution),
        distortion_model=args.distortion_model, distortion_coeffs=tuple(args.distortion_coeffs),
        origin=GeodeticOrigin(*args.origin) if args.origin is not None else None)
    render = None
    if args.images:  # settings checked before the (long) simulation
        render = RenderSettings(exposure_jitter=args.exposure_jitter,
                                motion_blur_px=args.motion_blur_px,
                                noise_sigma_dn=args.image_noise_dn, seed=args.seed)
        if args.origin is not None:
            raise CdtmError("--images with --origin: rendering a geodetic log is not supported "
                            "yet; expected one of the two")
    texture = OrthophotoTexture.from_geotiff(args.orthophoto) if args.orthophoto else None
    out = args.out
    protected = [p for p in (args.terrain, args.orthophoto) if p is not None]
    with output_dir(args, out, WRITER, protected=protected, label="OUT") as staging:
        result = simulate(settings)
        rendered = None
        if render is not None:
            with tqdm(total=settings.frames, unit="frame", desc="rendering", file=sys.stderr,
                      leave=False) as bar:
                rendered = render_flight(result, render, texture,
                                         progress=lambda done, total: bar.update(1))
        if args.origin is None:
            write_simulation_files(result, staging, out,
                                   None if rendered is None else rendered.images)
        else:
            from cdtm_graph.sim.geodetic import write_geodetic_simulation_files

            write_geodetic_simulation_files(
                result, staging, dem_crs=args.dem_crs,
                vertical_datum=VerticalDatum(args.vertical_datum))
    stats = result.stats
    rows, cols = result.dtm.shape
    print(f"wrote {out}: {len(result.log.frames)} frames, {stats.n_tracks} tracks, "
          f"{stats.n_observations} observations ({stats.pairs_per_frame.mean():.0f} features "
          f"per frame pair), DTM {rows}x{cols} at {result.dtm.grid_spacing_m:g} m "
          f"(sigma_h {result.dtm.sigma_h():g} m)")
    if rendered is not None:
        width, height = settings.resolution_px
        print(f"rendered {len(rendered.images)} images {width}x{height} into {out / 'images'} "
              f"({rendered.seconds_per_frame:.2f} s per frame)")
    return 0
