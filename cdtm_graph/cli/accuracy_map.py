"""``cdtm accuracy-map DTM``: predicted camera-2 accuracy over a DTM, before flying.

Writes ``accuracy_map.npz`` and ``accuracy_map.png`` into ``--out`` (both or neither,
under the rules of :mod:`cdtm_graph.atomic`). The npz holds:

* ``x_m`` (nx,), ``y_m`` (ny,): node coordinates (world, m);
* ``sigma_pos2_m``, ``sigma_att2_deg`` (ny, nx): predicted 1-sigma (norms over the three
  axes / Euler angles), NaN where degenerate;
* ``degenerate`` (ny, nx) bool, ``reason_codes`` (ny, nx) int bit codes, and
  ``reason_names``: the name of bit k at index k (``few_features``, ``narrow_fov``, ...);
* ``n_features`` (ny, nx), and the settings as scalars (``altitude_m``, ``fov_deg``, ...).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from cdtm_graph.analysis.map_options import (
    MAX_ABS_HEADING_DEG,
    MAX_FEATURES,
    MAX_NODES,
    MAX_ROTATION_DEG,
    RESOLUTION_RANGE_PX,
    AltitudeReference,
)
from cdtm_graph.atomic import atomic_output_file
from cdtm_graph.cli import COMMANDS
from cdtm_graph.cli.outdir import add_out_option, output_dir

if TYPE_CHECKING:
    from cdtm_graph.analysis.accuracy_map import AccuracyMap

#: Resolution of the PNG: readable labels, files under ~200 kB (the hillshade is busy).
FIGURE_DPI = 80
#: The files written into --out.
OUTPUT_FILES = ("accuracy_map.npz", "accuracy_map.png")


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "accuracy-map",
        help=COMMANDS["accuracy-map"].summary,
        description="Place the two-frame C-DTM geometry at every node of a grid over the DTM "
                    "and predict the camera-2 pose 1-sigma in closed form (weighted eq. 13, "
                    "Sigma_C2), with noiseless features at the true geometry. Degenerate "
                    "nodes are flagged with their reasons.")
    parser.add_argument("dtm", type=Path, metavar="DTM", help="DTM file (.npz, .asc, .tif)")
    parser.add_argument("--altitude-m", "--alt-m", type=float, required=True,
                        help="camera altitude [m] (see --altitude-ref)")
    parser.add_argument("--altitude-ref", "--alt-ref", choices=[r.value for r in AltitudeReference],
                        default=AltitudeReference.MEAN_TERRAIN.value,
                        help="altitude above the DTM's mean height (constant-altitude flight, "
                             "default) or above the ground below the camera")
    parser.add_argument("--fov-deg", type=float, required=True, help="horizontal FOV [deg]")
    parser.add_argument("--resolution-px", type=int, default=400,
                        help=f"image width = height [px], {RESOLUTION_RANGE_PX[0]} to "
                             f"{RESOLUTION_RANGE_PX[1]} (default: %(default)s)")
    parser.add_argument("--features", type=int, default=170,
                        help=f"features per frame pair, 1 to {MAX_FEATURES} "
                             "(default: %(default)s)")
    parser.add_argument("--baseline-m", type=float, default=40.0,
                        help="baseline |p12| [m] (default: %(default)s)")
    parser.add_argument("--rotation-deg", type=float, default=10.0,
                        help="rotation between the frames [deg], 0 to "
                             f"{MAX_ROTATION_DEG:g} (default: %(default)s)")
    parser.add_argument("--pixel-sigma-px", "--sigma-px", type=float, default=0.5,
                        help="registration error, 1 sigma [px] (default: %(default)s)")
    parser.add_argument("--sigma-h-m", type=float, default=None,
                        help="DTM height error, 1 sigma [m] (default: from the grid spacing)")
    parser.add_argument("--heading-deg", type=float, default=0.0,
                        help="flight direction, counter-clockwise from +x [deg], finite, "
                             f"within +-{MAX_ABS_HEADING_DEG:g} (default: 0)")
    parser.add_argument("--step-m", type=float, default=None,
                        help="node spacing [m] (default: 40 nodes along the longer side); "
                             f"at most {MAX_NODES:.0e} nodes in all")
    parser.add_argument("--workers", type=int, default=None,
                        help="local worker processes (default: all cores)")
    add_out_option(parser, "output directory", default="accuracy_map")
    parser.set_defaults(func=run)


def write_accuracy_map_npz(result: AccuracyMap, path: Path) -> None:
    """The map's arrays and settings as ``.npz`` (keys in the module docstring), atomically."""
    import numpy as np

    from cdtm_graph.analysis.accuracy_map import DEGENERACY_CODE_NAMES

    s = result.settings
    with atomic_output_file(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, x_m=result.x_m, y_m=result.y_m, sigma_pos2_m=result.sigma_pos2_m,
                 sigma_att2_deg=result.sigma_att2_deg, degenerate=result.degenerate,
                 reason_codes=result.reason_codes,
                 reason_names=np.array(DEGENERACY_CODE_NAMES), n_features=result.n_features,
                 altitude_m=s.altitude_m, altitude_reference=s.altitude_reference.value,
                 fov_deg=s.fov_deg, resolution_px=s.resolution_px,
                 n_features_requested=s.n_features, baseline_m=s.baseline_m,
                 rotation_deg=s.rotation_deg, pixel_sigma_px=s.pixel_sigma_px,
                 heading_deg=s.heading_deg)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from cdtm_graph.analysis.accuracy_map import (
        DEGENERACY_CODE_NAMES,
        AccuracyMapSettings,
        accuracy_map,
    )
    from cdtm_graph.dtm import load_dtm
    from cdtm_graph.parallel import ParallelSettings

    settings = AccuracyMapSettings(
        altitude_m=args.altitude_m, fov_deg=args.fov_deg, resolution_px=args.resolution_px,
        n_features=args.features, baseline_m=args.baseline_m, rotation_deg=args.rotation_deg,
        pixel_sigma_px=args.pixel_sigma_px, sigma_h_m=args.sigma_h_m, heading_deg=args.heading_deg,
        step_m=args.step_m, altitude_reference=AltitudeReference(args.altitude_ref))
    settings.check()  # before reading the DTM: a bad flag fails fast
    with output_dir(args, args.out, "accuracy-map", protected=[args.dtm],
                    names=OUTPUT_FILES) as staging:
        dtm = load_dtm(args.dtm)
        result = accuracy_map(dtm, settings, ParallelSettings(workers=args.workers))
        write_accuracy_map_npz(result, staging / OUTPUT_FILES[0])
        from cdtm_graph.plots.accuracy_map import accuracy_map_figure  # matplotlib: plots

        fig = accuracy_map_figure(result, dtm)
        with atomic_output_file(staging / OUTPUT_FILES[1]) as tmp:
            fig.savefig(tmp, format="png", dpi=FIGURE_DPI)
    npz_path, png_path = (args.out / name for name in OUTPUT_FILES)
    good = ~result.degenerate
    print(f"accuracy map of {args.dtm}: {result.x_m.size} x {result.y_m.size} nodes, "
          f"sigma_h {settings.noise(dtm).sigma_h_m:.2f} m")
    if good.any():
        pos, att = result.sigma_pos2_m[good], result.sigma_att2_deg[good]
        print(f"  position 1-sigma [m]:   median {np.median(pos):.3g}, "
              f"5-95% {np.percentile(pos, 5):.3g}..{np.percentile(pos, 95):.3g}")
        print(f"  attitude 1-sigma [deg]: median {np.median(att):.3g}, "
              f"5-95% {np.percentile(att, 5):.3g}..{np.percentile(att, 95):.3g}")
    print(f"  degenerate nodes: {int(result.degenerate.sum())} of {result.degenerate.size}")
    for bit, name in enumerate(DEGENERACY_CODE_NAMES):
        count = int(np.sum(result.reason_codes & (1 << bit) != 0))
        if count:
            print(f"    {name}: {count}")
    print(f"wrote {npz_path} and {png_path}")
    return 0
