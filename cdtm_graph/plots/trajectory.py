"""Trajectory over the DTM hillshade with covariance ellipses, and errors inside ±3σ.

Figures are built on ``matplotlib.figure.Figure`` directly (no pyplot state), written
to PNG and returned so callers and tests can inspect the axes.
"""

from __future__ import annotations

import math
import os

import numpy as np
from matplotlib.collections import EllipseCollection
from matplotlib.colors import LightSource
from matplotlib.figure import Figure

from cdtm_graph.dtm import Dtm
from cdtm_graph.flightlog import States
from cdtm_graph.results import TrajectoryEstimate

#: Ellipses and error bounds are drawn at this many standard deviations (for a 2-D
#: Gaussian, 98.9% of the probability lies inside the ellipse).
N_SIGMA = 3.0
#: Roughly this many ellipses along the track when ``ellipse_every`` is not given.
DEFAULT_ELLIPSE_COUNT = 25
#: Auto-magnification makes the largest ellipse's major axis about this fraction of the
#: plotted extent (when the true-size ellipses would be smaller).
ELLIPSE_TARGET_FRACTION = 0.04
#: Margin around the track, as a fraction of its extent.
VIEW_MARGIN = 0.08
#: A hillshade of more cells than this along an axis is decimated first (speed; the
#: PNG has fewer pixels than that anyway).
MAX_HILLSHADE_CELLS = 1200
DPI = 110
#: How each track is drawn. The ground truth goes over the estimate (dashed, thinner), so
#: both show where they coincide; IMU-only dead reckoning underneath both.
ESTIMATE_STYLE = dict(color="tab:red", lw=2.2, zorder=3, label="estimate")
TRUTH_STYLE = dict(color="black", lw=1.1, ls=(0, (4, 2)), zorder=5, label="ground truth")
FREE_STYLE = dict(color="tab:orange", lw=1.2, ls=":", zorder=2)
FREE_LABEL = "IMU only (dead reckoning)"
ELLIPSE_ZORDER = 4


def ellipse_scale_factor(largest_axis_m: float, extent_m: float,
                          requested: float | None = None) -> float:
    """The factor ellipses are drawn at: ``requested`` (>= 1), or the smallest of 1, 2, 5,
    10, ... that makes the largest ellipse's major axis about ``ELLIPSE_TARGET_FRACTION``
    of the plotted extent.

    Raises:
        ValueError: ``requested`` below 1.
    """
    if requested is not None:
        if not requested >= 1.0:
            raise ValueError(f"ellipse_magnification must be >= 1, got {requested}")
        return float(requested)
    if not largest_axis_m > 0:
        return 1.0
    return _nice_factor(ELLIPSE_TARGET_FRACTION * extent_m / largest_axis_m)


def ellipse_label(every: int, magnification: float) -> str:
    """The legend entry of the ellipses, with their scale."""
    scale = "true size" if magnification == 1.0 else f"magnified ×{magnification:g}"
    return f"{N_SIGMA:g}σ horizontal, {scale} (every {every} frames)"


def plot_tracks(ax, estimate_xy: np.ndarray, truth_xy: np.ndarray,
                free_xy: np.ndarray | None) -> None:
    """The estimate, the ground truth over it, IMU-only dead reckoning under both; the
    IMU-only label says when its track leaves the view (the view is the estimate's)."""
    if free_xy is not None and free_xy.size:
        x0, x1 = ax.get_xlim()
        y0, y1 = ax.get_ylim()
        outside = np.any((free_xy[:, 0] < min(x0, x1)) | (free_xy[:, 0] > max(x0, x1))
                         | (free_xy[:, 1] < min(y0, y1)) | (free_xy[:, 1] > max(y0, y1)))
        ax.plot(free_xy[:, 0], free_xy[:, 1], **FREE_STYLE,
                label=FREE_LABEL + ("; leaves the view" if outside else ""))
    ax.plot(estimate_xy[:, 0], estimate_xy[:, 1], **ESTIMATE_STYLE)
    if truth_xy.size:
        ax.plot(truth_xy[:, 0], truth_xy[:, 1], **TRUTH_STYLE)


def _nice_factor(x: float) -> float:
    """The smallest of 1, 2, 5, 10, 20, 50, ... that is >= x (x >= 1)."""
    if x <= 1.0:
        return 1.0
    exponent = math.floor(math.log10(x))
    for mantissa in (1.0, 2.0, 5.0, 10.0):
        value = mantissa * 10.0**exponent
        if value >= x * (1 - 1e-12):
            return value
    return 10.0 ** (exponent + 1)


def _view(xy: list[np.ndarray], dtm: Dtm) -> tuple[float, float, float, float]:
    """(xmin, xmax, ymin, ymax) around the tracks, with a margin; the DTM if no track."""
    pts = np.concatenate([p for p in xy if p.size], axis=0) if any(p.size for p in xy) else None
    if pts is None or not np.all(np.isfinite(pts)):
        return dtm.bounds
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    span = max(float(np.max(hi - lo)), 10.0 * dtm.grid_spacing_m)
    pad = VIEW_MARGIN * span
    centre = (lo + hi) / 2
    half = (hi - lo) / 2 + pad  # pad > 0 even for a track along one axis
    return (centre[0] - half[0], centre[0] + half[0], centre[1] - half[1], centre[1] + half[1])


def _hillshade(ax, dtm: Dtm, view: tuple[float, float, float, float],
               vert_exag: float, cell_m: tuple[float, float] | None = None) -> None:
    """Draw the hillshade of the part of the DTM inside ``view`` (north up).

    ``cell_m``: the cell size (x, y) in metres when the grid's own units are not metres
    (a DEM in degrees), so that slopes shade true.
    """
    elev = np.asarray(dtm.elevation)
    x = dtm.x0 + dtm.dx * np.arange(elev.shape[1])
    y = dtm.y0 + dtm.dy * np.arange(elev.shape[0])
    cols = np.flatnonzero((x >= view[0] - abs(dtm.dx)) & (x <= view[1] + abs(dtm.dx)))
    rows = np.flatnonzero((y >= view[2] - abs(dtm.dy)) & (y <= view[3] + abs(dtm.dy)))
    if cols.size < 2 or rows.size < 2:
        return  # the track is off the map: nothing to shade
    step = max(1, int(math.ceil(max(cols.size, rows.size) / MAX_HILLSHADE_CELLS)))
    cols, rows = cols[::step], rows[::step]
    z = elev[np.ix_(rows, cols)]
    xs, ys = x[cols], y[rows]
    # Raster orientation for imshow(origin="upper") and LightSource: first row north,
    # first column west.
    if ys[0] < ys[-1]:
        z, ys = z[::-1], ys[::-1]
    if xs[0] > xs[-1]:
        z, xs = z[:, ::-1], xs[::-1]
    nodata = ~np.isfinite(z)
    if nodata.all():
        return
    filled = np.where(nodata, np.nanmean(z), z)
    cell_x, cell_y = cell_m if cell_m is not None else (abs(dtm.dx), abs(dtm.dy))
    shade = LightSource(azdeg=315, altdeg=45).hillshade(
        filled, vert_exag=vert_exag, dx=cell_x * step, dy=cell_y * step)
    shade = np.ma.masked_array(shade, nodata)
    half_dx, half_dy = abs(dtm.dx) * step / 2, abs(dtm.dy) * step / 2
    ax.imshow(shade, cmap="gray", vmin=0, vmax=1, origin="upper", interpolation="bilinear",
              extent=(xs[0] - half_dx, xs[-1] + half_dx, ys[-1] - half_dy, ys[0] + half_dy),
              zorder=0)


def plot_trajectory_over_dtm(
    path: str | os.PathLike,
    dtm: Dtm,
    estimate: TrajectoryEstimate,
    position_cov_world: np.ndarray,
    groundtruth: States | None = None,
    ellipse_every: int | None = None,
    ellipse_magnification: float | None = None,
    vert_exag: float = 1.0,
    free: TrajectoryEstimate | None = None,
) -> Figure:
    """Plan view: DTM hillshade, estimated track, ground truth over it, IMU-only dead
    reckoning, 3σ horizontal ellipses.

    Args:
        path: PNG to write.
        dtm: the terrain.
        estimate: K frames.
        position_cov_world: (K, 3, 3) world-frame position covariance, m^2 (e.g. from
            ``pose_covariance_in_world``); its horizontal (x, y) block gives the ellipses.
        groundtruth: true states to draw, or None.
        ellipse_every: draw an ellipse every this many frames (default: ~25 in all).
        ellipse_magnification: scale factor of the ellipses (>= 1); None picks the
            smallest of 1, 2, 5, 10, ... that makes them visible. Any factor other than 1
            is stated in the title.
        vert_exag: vertical exaggeration of the hillshade.
        free: the IMU-only (dead-reckoning) trajectory the summary compares against, or
            None. The view is the estimate's and the truth's; the label says when the
            IMU-only track leaves it.

    Returns:
        The figure (already saved).
    """
    xy_est = np.asarray(estimate.position_m)[:, :2]
    k = xy_est.shape[0]
    cov = np.asarray(position_cov_world, dtype=float)
    if cov.shape != (k, 3, 3):
        raise ValueError(f"position_cov_world has shape {cov.shape}, expected ({k}, 3, 3)")
    xy_true = (np.asarray(groundtruth.position_m)[:, :2] if groundtruth is not None
               else np.zeros((0, 2)))
    view = _view([xy_est, xy_true], dtm)

    # Size the figure to the view's aspect so a long, thin track is not lost in margins.
    aspect = (view[3] - view[2]) / max(view[1] - view[0], 1e-9)
    fig = Figure(figsize=(8.0, float(np.clip(8.0 * aspect, 3.0, 9.0)) + 1.0), dpi=DPI,
                 layout="constrained")
    ax = fig.add_subplot()
    _hillshade(ax, dtm, view, vert_exag)
    ax.set_xlim(view[0], view[1])
    ax.set_ylim(view[2], view[3])
    plot_tracks(ax, xy_est, xy_true,
                np.asarray(free.position_m)[:, :2] if free is not None else None)

    every = ellipse_every or max(1, k // DEFAULT_ELLIPSE_COUNT)
    pick = np.arange(0, k, every)
    horizontal = cov[pick][:, :2, :2]
    ok = np.all(np.isfinite(horizontal), axis=(1, 2))
    pick, horizontal = pick[ok], horizontal[ok]
    magnification = 1.0
    if pick.size:
        eigval, eigvec = np.linalg.eigh(horizontal)  # ascending: column 1 is the major axis
        semi = N_SIGMA * np.sqrt(np.clip(eigval, 0.0, None))  # (n, 2) minor, major
        extent = max(view[1] - view[0], view[3] - view[2])
        largest = float(np.max(semi[:, 1])) * 2
        magnification = ellipse_scale_factor(largest, extent, ellipse_magnification)
        angle_deg = np.degrees(np.arctan2(eigvec[:, 1, 1], eigvec[:, 0, 1]))
        ax.add_collection(EllipseCollection(
            widths=2 * semi[:, 1] * magnification, heights=2 * semi[:, 0] * magnification,
            angles=angle_deg, units="xy", offsets=xy_est[pick],
            offset_transform=ax.transData, facecolors="none", edgecolors="tab:blue",
            linewidths=1.0, zorder=ELLIPSE_ZORDER))
        ax.plot([], [], color="tab:blue", lw=1.0, label=ellipse_label(every, magnification))

    scale = ("true scale" if magnification == 1.0
             else f"magnified ×{magnification:g}")
    ax.set_title(f"Trajectory over DTM hillshade; {N_SIGMA:g}σ ellipses {scale}")
    ax.set_xlim(view[0], view[1])
    ax.set_ylim(view[2], view[3])
    ax.set_aspect("equal")
    ax.set_xlabel("world x (east), m")
    ax.set_ylabel("world y (north), m")
    ax.legend(loc="best", fontsize=8)
    fig.savefig(path)
    return fig


def plot_errors(path: str | os.PathLike, t_s: np.ndarray, errors_xyz: np.ndarray,
                sigma_xyz: np.ndarray) -> Figure:
    """Per-axis position error against time inside its ±3σ bounds (three rows).

    Args:
        path: PNG to write.
        t_s: (K,) times, s.
        errors_xyz: (K, 3) estimate - truth, world axes, m.
        sigma_xyz: (K, 3) 1-sigma, m (NaN where unknown).

    Returns:
        The figure (already saved). Each axis' y-limits contain both the errors and the
        ±3σ bounds.
    """
    t = np.asarray(t_s, dtype=float)
    err = np.asarray(errors_xyz, dtype=float)
    sig = np.asarray(sigma_xyz, dtype=float)
    if err.shape != (t.shape[0], 3) or sig.shape != err.shape:
        raise ValueError(f"errors_xyz {err.shape} and sigma_xyz {sig.shape} must be "
                         f"({t.shape[0]}, 3)")
    fig = Figure(figsize=(8.0, 7.0), dpi=DPI, layout="constrained")
    axes = fig.subplots(3, 1, sharex=True)
    for a, (ax, name) in enumerate(zip(axes, ("x (east)", "y (north)", "z (up)"), strict=True)):
        bound = N_SIGMA * sig[:, a]
        ax.fill_between(t, -bound, bound, color="tab:blue", alpha=0.2, lw=0,
                        label=f"±{N_SIGMA:g}σ")
        ax.plot(t, bound, color="tab:blue", lw=0.8)
        ax.plot(t, -bound, color="tab:blue", lw=0.8)
        ax.plot(t, err[:, a], color="tab:red", lw=1.0, label="error")
        values = np.concatenate([np.abs(err[:, a]), bound])
        values = values[np.isfinite(values)]
        top = float(values.max()) if values.size else 1.0
        top = top * 1.1 if top > 0 else 1.0
        ax.set_ylim(-top, top)
        ax.set_ylabel(f"{name}, m")
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[0].set_title(f"Position error (estimate - truth) with ±{N_SIGMA:g}σ bounds")
    axes[-1].set_xlabel("time, s")
    fig.savefig(path)
    return fig
