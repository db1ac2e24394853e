"""Figure of an accuracy map: predicted 1-sigma heat maps over a hillshade of the DTM.

Two panels, camera-2 position [m] and attitude [deg]; nodes where the geometry is
degenerate (section V.B) are shaded red, with their reasons in the legend.
"""

from __future__ import annotations

import numpy as np
from matplotlib.colors import LightSource, ListedColormap, LogNorm, Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Patch
from matplotlib.ticker import FormatStrFormatter

from cdtm_graph.analysis.accuracy_map import DEGENERACY_CODE_NAMES, AccuracyMap
from cdtm_graph.dtm import Dtm

#: Opacity of the heat map over the hillshade.
_HEAT_ALPHA = 0.65
#: Degenerate nodes: a translucent red, so the terrain that explains them stays visible.
_DEGENERATE_COLOR = "tab:red"
_DEGENERATE_ALPHA = 0.45
#: The colour scale spans these percentiles of the finite values ...
_COLOR_PERCENTILES = (2.0, 98.0)
#: ... in log scale when they differ by more than this factor.
_LOG_COLOR_RATIO = 5.0


def _north_up(dtm: Dtm) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """Elevation with row 0 at the largest y and column 0 at the smallest x, and its extent."""
    e = np.asarray(dtm.elevation)
    if dtm.dy > 0:
        e = e[::-1]
    if dtm.dx < 0:
        e = e[:, ::-1]
    xmin, xmax, ymin, ymax = dtm.bounds
    return e, (xmin, xmax, ymin, ymax)


def _norm(values: np.ndarray) -> Normalize:
    """Colour scale over the bulk of the finite values; log when they span a decade.

    Nodes next to a degenerate region or the map edge can be orders of magnitude worse
    than the rest; clipping at percentiles keeps the bulk readable.
    """
    finite = values[np.isfinite(values) & (values > 0)]
    if finite.size == 0:
        return Normalize(0.0, 1.0)
    lo, hi = np.percentile(finite, _COLOR_PERCENTILES)
    if hi > _LOG_COLOR_RATIO * lo:
        return LogNorm(lo, hi)
    return Normalize(lo, max(hi, lo * (1 + 1e-9)))


def _edges(centres: np.ndarray) -> np.ndarray:
    """Cell edges around node coordinates (uniform spacing; one node: +-0.5)."""
    step = centres[1] - centres[0] if centres.size > 1 else 1.0
    return np.concatenate([centres - step / 2, [centres[-1] + step / 2]])


def accuracy_map_figure(result: AccuracyMap, dtm: Dtm) -> Figure:
    """Heat maps of the predicted camera-2 1-sigma over the DTM's hillshade.

    Args:
        result: the map.
        dtm: the DTM it was computed on.

    Returns:
        A matplotlib figure (no pyplot state; save with ``fig.savefig``).
    """
    elevation, extent = _north_up(dtm)
    filled = np.where(np.isfinite(elevation), elevation, np.nanmin(elevation))
    shade = LightSource(azdeg=315, altdeg=45).hillshade(
        filled, vert_exag=1.0, dx=abs(dtm.dx), dy=abs(dtm.dy))
    x_edges, y_edges = _edges(result.x_m), _edges(result.y_m)
    degenerate = result.degenerate
    s = result.settings
    fig = Figure(figsize=(11.5, 5.0), layout="constrained")
    panels = ((result.sigma_pos2_m, "camera-2 position 1-sigma [m]"),
              (result.sigma_att2_deg, "camera-2 attitude 1-sigma [deg]"))
    for k, (values, label) in enumerate(panels):
        ax = fig.add_subplot(1, 2, k + 1)
        ax.imshow(shade, cmap="gray", extent=extent, origin="upper", interpolation="bilinear")
        mesh = ax.pcolormesh(x_edges, y_edges, np.ma.masked_invalid(values), cmap="viridis",
                             norm=_norm(values), alpha=_HEAT_ALPHA, shading="flat")
        bar = fig.colorbar(mesh, ax=ax, label=label, shrink=0.85, extend="both")
        bar.ax.yaxis.set_major_formatter(FormatStrFormatter("%.3g"))
        bar.ax.yaxis.set_minor_formatter(FormatStrFormatter("%.3g"))
        if degenerate.any():
            ax.pcolormesh(x_edges, y_edges, np.ma.masked_where(~degenerate, degenerate),
                          cmap=ListedColormap([_DEGENERATE_COLOR]), alpha=_DEGENERATE_ALPHA,
                          shading="flat")
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        if k == 0 and degenerate.any():
            bits = np.bitwise_or.reduce(result.reason_codes[degenerate].ravel())
            reasons = ", ".join(name for b, name in enumerate(DEGENERACY_CODE_NAMES)
                                if bits & (1 << b))
            ax.legend(handles=[Patch(facecolor=_DEGENERATE_COLOR, alpha=_DEGENERATE_ALPHA,
                                     label=f"degenerate ({reasons})")],
                      loc="lower left", fontsize=8)
    fig.suptitle(f"Predicted accuracy (closed form): altitude {s.altitude_m:g} m "
                 f"({s.altitude_reference.value}), FOV {s.fov_deg:g} deg, "
                 f"{s.resolution_px} px, {s.n_features} features, baseline {s.baseline_m:g} m, "
                 f"rotation {s.rotation_deg:g} deg, {s.pixel_sigma_px:g} px", fontsize=10)
    return fig
