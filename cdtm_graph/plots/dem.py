"""The trajectory over the DEM in the DEM's own coordinates (longitude/latitude, UTM...).

For geodetic logs: the track, ground truth, IMU-only dead reckoning and 3-sigma
horizontal ellipses are converted from the world frame into the DEM file's CRS (each
ellipse's outline point by point, so it is exact in any projection) and drawn over the
hillshade of the DEM as stored. Ellipses of a few metres on a track of kilometres are
magnified about their centres (by 1, 2, 5, 10, ...), the factor in the legend.
"""

from __future__ import annotations

import math
import os

import numpy as np
from matplotlib.figure import Figure

from cdtm_graph.dem import DemWindow
from cdtm_graph.flightlog import States
from cdtm_graph.geodesy import LocalFrame
from cdtm_graph.plots.trajectory import (
    DEFAULT_ELLIPSE_COUNT,
    DPI,
    ELLIPSE_ZORDER,
    N_SIGMA,
    VIEW_MARGIN,
    _hillshade,
    ellipse_label,
    ellipse_scale_factor,
    plot_tracks,
)
from cdtm_graph.results import TrajectoryEstimate

#: Points on each ellipse outline.
_ELLIPSE_POINTS = 48
#: Metres per degree of latitude, for shading a grid in degrees.
_METRES_PER_DEGREE = 111_320.0


def _ellipse_outlines(position_m: np.ndarray, cov_xy: np.ndarray,
                      magnification: float = 1.0) -> np.ndarray:
    """(n, P, 2) world x, y of the N_SIGMA ellipses of (n, 2, 2) covariances, scaled
    about their centres by ``magnification``."""
    eigval, eigvec = np.linalg.eigh(cov_xy)
    semi = magnification * N_SIGMA * np.sqrt(np.clip(eigval, 0.0, None))  # (n, 2)
    angle = np.linspace(0.0, 2 * math.pi, _ELLIPSE_POINTS)
    unit = np.stack([np.cos(angle), np.sin(angle)], axis=1)  # (P, 2)
    local = unit[None] * semi[:, None, :]  # along the eigenvectors
    return position_m[:, None, :2] + np.einsum("nij,npj->npi", eigvec, local)


def plot_trajectory_over_dem(path: str | os.PathLike, window: DemWindow, frame: LocalFrame,
                             estimate: TrajectoryEstimate, position_cov_world: np.ndarray,
                             groundtruth: States | None = None,
                             vert_exag: float = 1.0, free: TrajectoryEstimate | None = None,
                             ellipse_magnification: float | None = None) -> Figure:
    """Plan view in the DEM's CRS: hillshade, estimate, ground truth over it, IMU-only
    dead reckoning, 3-sigma ellipses.

    Args:
        path: PNG to write.
        window: the DEM under the flight as stored (:func:`cdtm_graph.dem.read_dem_window`).
        frame: the log's local frame (world -> geodetic).
        estimate: K frames. position_cov_world: (K, 3, 3) m^2, world frame.
        groundtruth: true states, or None.
        vert_exag: vertical exaggeration of the hillshade.
        free: the IMU-only (dead-reckoning) trajectory, or None.
        ellipse_magnification: scale of the ellipses about their centres (>= 1); None
            picks the smallest of 1, 2, 5, 10, ... that makes them visible (the legend
            states it).

    Returns:
        The figure (already saved).
    """
    from pyproj import CRS

    crs = CRS.from_wkt(window.crs_wkt)

    def to_crs(p_world: np.ndarray) -> np.ndarray:
        lat, lon, _ = frame.world_to_geodetic(p_world)
        return np.column_stack(window.to_crs(lat, lon))

    est = to_crs(estimate.position_m)
    truth = to_crs(groundtruth.position_m) if groundtruth is not None else np.zeros((0, 2))
    pts = np.vstack([est, truth])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = VIEW_MARGIN * max(float(np.max(hi - lo)), 10 * abs(window.grid.dx))
    view = (lo[0] - pad, hi[0] + pad, lo[1] - pad, hi[1] + pad)
    geographic = crs.is_geographic
    y_scale = 1.0 / math.cos(math.radians(float(np.mean(est[:, 1])))) if geographic else 1.0

    aspect = y_scale * (view[3] - view[2]) / max(view[1] - view[0], 1e-12)
    fig = Figure(figsize=(8.0, float(np.clip(8.0 * aspect, 3.0, 9.0)) + 1.0), dpi=DPI,
                 layout="constrained")
    ax = fig.add_subplot()
    cell = None
    if geographic:  # hillshade slopes in metres, not per degree (a sphere is enough here)
        cell = (abs(window.grid.dx) * _METRES_PER_DEGREE / y_scale,
                abs(window.grid.dy) * _METRES_PER_DEGREE)
    _hillshade(ax, window.grid, view, vert_exag, cell)
    ax.set_xlim(view[0], view[1])
    ax.set_ylim(view[2], view[3])
    plot_tracks(ax, est, truth, to_crs(free.position_m) if free is not None else None)
    k = len(estimate)
    every = max(1, k // DEFAULT_ELLIPSE_COUNT)
    pick = np.arange(0, k, every)
    cov = np.asarray(position_cov_world, dtype=float)[pick][:, :2, :2]
    ok = np.all(np.isfinite(cov), axis=(1, 2))
    if ok.any():
        world_xy = np.vstack([estimate.position_m[:, :2]]
                             + ([groundtruth.position_m[:, :2]] if groundtruth is not None
                                else []))
        extent_m = float(np.max(world_xy.max(axis=0) - world_xy.min(axis=0)))
        largest_m = 2 * N_SIGMA * float(np.sqrt(np.max(np.linalg.eigvalsh(cov[ok]))))
        magnification = ellipse_scale_factor(largest_m, extent_m, ellipse_magnification)
        outlines = _ellipse_outlines(estimate.position_m[pick][ok], cov[ok], magnification)
        heights = np.repeat(estimate.position_m[pick][ok][:, 2], _ELLIPSE_POINTS)
        flat = to_crs(np.column_stack([outlines.reshape(-1, 2), heights]))
        for outline in flat.reshape(outlines.shape):
            ax.plot(outline[:, 0], outline[:, 1], color="tab:blue", lw=0.8,
                    zorder=ELLIPSE_ZORDER)
        ax.plot([], [], color="tab:blue", lw=0.8, label=ellipse_label(every, magnification))
    ax.set_aspect(y_scale)
    ax.ticklabel_format(useOffset=False, style="plain")
    if geographic:
        ax.set_xlabel("longitude, deg")
        ax.set_ylabel("latitude, deg")
    else:
        x_axis, y_axis = crs.axis_info[:2]
        ax.set_xlabel(f"{x_axis.name.lower()}, {x_axis.unit_name}")
        ax.set_ylabel(f"{y_axis.name.lower()}, {y_axis.unit_name}")
    files = ", ".join(p.name for p in window.paths)
    ax.set_title(f"Trajectory over the DEM in {crs.name} ({files})", fontsize=9)
    ax.legend(loc="best", fontsize=8)
    fig.savefig(path)
    return fig
