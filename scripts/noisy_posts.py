"""A map noisier than it states, smoothed with the tangent planes' slopes as the patches
have them and as a grown run takes them (docs/verdict.md, "Noisy posts").

Run: ``PYTHONPATH=$PWD python scripts/noisy_posts.py KIND METRES [--seeds 2 4] [--frames
90] [--noise-seed-offset 100] [--modes batch isam2 fixed_lag]``. KIND: ``white`` (independent
noise of METRES on every post: ``sim.faults.with_dtm_noise``), ``correlated`` (noise of
METRES rms over about two posts), ``coarse`` (a DEM METRES times coarser interpolated back
onto the grid). The robustness study's clean flight; the noise drawn with
``default_rng(seed + offset)``. One line per seed and mode: 3-D RMSE (m), rms 3-D sigma
(m), position ANEES and the verdict without ground truth, with the patches' slopes
(``MapErrorSettings.slope_sigma_posts=None``) and with the default.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

import numpy as np
from scipy.interpolate import RegularGridInterpolator
from scipy.ndimage import gaussian_filter

from cdtm_graph.dtm import Dtm
from cdtm_graph.robust.map_error import MapErrorSettings
from cdtm_graph.run import smooth_and_evaluate
from cdtm_graph.sim.faults import with_dtm_noise
from cdtm_graph.smoother import SmootherSettings
from cdtm_graph.studies.robustness import BASE, SCENARIOS, Mode
from cdtm_graph.verdict import assess


def noisy(dtm: Dtm, kind: str, metres: float, rng: np.random.Generator) -> Dtm:
    """The DTM as the user's map: ``kind`` of error of size ``metres``."""
    if kind == "white":
        return with_dtm_noise(dtm, metres, rng)
    e = np.array(dtm.elevation)
    if kind == "correlated":
        noise = gaussian_filter(rng.standard_normal(e.shape), 1.0)
        e = e + noise * metres / noise.std()
    elif kind == "coarse":
        step = int(metres)
        rows, cols = np.arange(e.shape[0]), np.arange(e.shape[1])
        coarse = RegularGridInterpolator((rows[::step], cols[::step]),
                                         e[::step, ::step], bounds_error=False,
                                         fill_value=None)
        r, c = np.meshgrid(rows, cols, indexing="ij")
        e = coarse(np.stack([r, c], axis=-1))
    else:
        raise SystemExit(f"KIND {kind!r}: expected white, correlated or coarse")
    return Dtm(e, dtm.x0, dtm.y0, dtm.dx, dtm.dy, sigma_h_m=dtm.sigma_h_m)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("kind", choices=["white", "correlated", "coarse"])
    parser.add_argument("metres", type=float)
    parser.add_argument("--seeds", type=int, nargs="+", default=[2])
    parser.add_argument("--frames", type=int, default=BASE.frames)
    parser.add_argument("--noise-seed-offset", type=int, default=0)
    parser.add_argument("--modes", nargs="+", default=[m.value for m in Mode])
    args = parser.parse_args(argv)
    for seed in args.seeds:
        log, dtm = SCENARIOS["clean"].flight(dataclasses.replace(BASE, frames=args.frames,
                                                                 seed=seed))
        user_dtm = noisy(dtm, args.kind, args.metres,
                         np.random.default_rng(seed + args.noise_seed_offset))
        for mode in args.modes:
            for slopes in (None, MapErrorSettings().slope_sigma_posts):
                base = SmootherSettings()
                settings = dataclasses.replace(base, graph=dataclasses.replace(
                    base.graph, map_error=MapErrorSettings(slope_sigma_posts=slopes)))
                out = smooth_and_evaluate(log, user_dtm, Mode(mode).settings(settings))
                e, me = out.errors, out.result.map_error
                assert e is not None and me is not None
                verdict = assess(out.result)  # without ground truth
                sigma = np.sqrt(np.nanmean(np.trace(out.result.covariances.pose[:, 3:, 3:],
                                                    axis1=1, axis2=2)))
                reasons = sorted({r.code.value for r in verdict.reasons})
                print(f"{args.kind} {args.metres:g} seed {seed} {mode:9} slopes "
                      f"{'patch' if slopes is None else f'{slopes:g} post'}: RMSE "
                      f"{e.rmse_position_3d_m:.2f} m, sigma {sigma:.2f} m, ANEES "
                      f"{e.anees_position:.2f}, {verdict.status.value} {reasons}; map read "
                      f"{me.estimated_m:.2f} m, used {me.used_m:.2f} m", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
