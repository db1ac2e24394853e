"""Terrain figures of the paper: the DTM height error vs grid spacing (Fig. 6) and a
basic cell cloned over a flight region (Figs. 11-12).

Run: ``python scripts/terrain_figures.py [--out docs/figures]``. Prints the Fig. 6 table
(grid spacing, measured sigma_h, the 0.08 x spacing model) over several terrain seeds.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import LightSource  # noqa: E402

from cdtm_graph.dtm import sigma_h_from_grid_spacing  # noqa: E402
from cdtm_graph.sim.terrain import (  # noqa: E402
    clone_basic_cell,
    fractal_terrain,
    sigma_h_vs_grid_spacing,
)

SPACINGS_M = (10, 30, 50, 70, 100, 130, 160, 190)
SEEDS = range(5)


def main(argv: list[str] | None = None) -> np.ndarray:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/figures")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    curves = np.array([sigma_h_vs_grid_spacing(fractal_terrain(seed=s), SPACINGS_M)
                       for s in SEEDS])
    model = np.array([sigma_h_from_grid_spacing(s) for s in SPACINGS_M])
    print("spacing_m  sigma_h_mean_m  sigma_h_min_m  sigma_h_max_m  model_m")
    for i, s in enumerate(SPACINGS_M):
        print(f"{s:9d}  {curves[:, i].mean():14.2f}  {curves[:, i].min():13.2f}  "
              f"{curves[:, i].max():13.2f}  {model[i]:7.2f}")

    fig, ax = plt.subplots(figsize=(5.5, 4))
    for c in curves:
        ax.plot(SPACINGS_M, c, color="0.7", lw=1)
    ax.plot(SPACINGS_M, curves.mean(axis=0), "o-",
            label=f"measured (mean of {len(SEEDS)} terrains)")
    ax.plot(SPACINGS_M, model, "k--", label="model 0.08 x spacing (2.4 m at 30 m)")
    ax.set_xlabel("DTM grid spacing, m")
    ax.set_ylabel("DTM height error sigma_h, m")
    ax.set_title("Fig. 6: DTM height error vs grid spacing\n3x3 km fractal terrain, 300 m relief")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "fig6_sigma_h.png", dpi=110)

    cell = fractal_terrain(size_m=3000.0, spacing_m=20.0, seed=0)
    tiled = clone_basic_cell(cell, 4, 2)
    xmin, xmax, ymin, ymax = tiled.bounds
    shade = LightSource(azdeg=315, altdeg=45).hillshade(
        np.asarray(tiled.elevation), vert_exag=2, dx=tiled.dx, dy=tiled.dy)
    fig, ax = plt.subplots(figsize=(8, 4.2))
    ax.imshow(shade, cmap="gray", origin="lower", extent=(xmin, xmax, ymin, ymax))
    ax.set_title("Figs. 11-12: a 3x3 km basic cell cloned 4x2 (mirrored, seamless)")
    ax.set_xlabel("x, m")
    ax.set_ylabel("y, m")
    fig.tight_layout()
    fig.savefig(out / "fig12_cloned_cell.png", dpi=60)
    return curves


if __name__ == "__main__":
    main()
