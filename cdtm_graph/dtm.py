"""Digital Terrain Map: a regular height grid with a bilinear surface, its readers and ray casting.

The DTM is the paper's terrain model: the C-DTM constraint casts a camera ray into it to
find the ground point ``G_E`` and the upward normal ``N`` there (DESIGN.md, "The C-DTM
factor"). Conventions (docs/flightlog.md, "DTM files"):

* ``elevation[r, c]`` is the world height z (metres, ENU) at ``x = x0 + c*dx``,
  ``y = y0 + r*dy``; ``dx`` and ``dy`` may be negative (``dy < 0`` for north-up rasters).
* Between samples the surface is bilinear. A query outside the grid, or in a cell one of
  whose four corners is NaN (no data), has no height: NaN.

Ray casting is exact: the ray's xy projection is walked cell by cell in order
(Amanatides-Woo traversal) and in each cell the height along the ray is a quadratic in
the ray parameter, solved in closed form. The first cell with a root wins, so a grazing
hill in front of the far terrain is never stepped over (a fixed-step marcher can).

This module knows nothing of GTSAM; readers are the only I/O and raise :class:`DtmError`
naming the file, the line where there is one, and what was expected.
"""

from __future__ import annotations

import contextlib
import copy
import enum
import logging
import math
import os
import struct
import tokenize
import warnings
import zipfile
import zlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from cdtm_graph.errors import DtmError, why_not_a_file
from factors.jit import njit

if TYPE_CHECKING:  # trimesh is imported lazily: it is slow to import and only to_trimesh needs it
    import trimesh

__all__ = [
    "SIGMA_H_PER_GRID_SPACING",
    "Dtm",
    "RayHits",
    "RayStatus",
    "load_dtm",
    "save_dtm_npz",
    "sigma_h_from_grid_spacing",
]

SIGMA_H_PER_GRID_SPACING = 0.08
"""Slope k of the linear DTM height-error model ``sigma_h = k * grid spacing`` (paper Fig. 6).

The paper reports sigma_h of about 2.4 m for its 30 m grid over a 3x3 km terrain with
300 m relief, and that sigma_h grows linearly with grid spacing (10..190 m): k = 2.4/30.
``cdtm_graph.sim.terrain.sigma_h_vs_grid_spacing`` measures the same curve on our synthetic
nominal terrain (``terrain.fractal_terrain()``), and its tests check it stays close to this
line. The formula lives here (not in ``terrain``) so that ``dtm`` imports nothing from the
package but ``errors``.
"""


def sigma_h_from_grid_spacing(spacing_m: float) -> float:
    """1-sigma DTM height error (m) from the grid spacing, the paper's Fig. 6 model.

    ``sigma_h = SIGMA_H_PER_GRID_SPACING * spacing_m`` (0.08 m per metre of spacing, i.e.
    2.4 m at 30 m). Calibrated on the paper's nominal terrain (3x3 km, 300 m relief); see
    ``cdtm_graph.sim.terrain.sigma_h_vs_grid_spacing`` for the measurement that backs it.

    Args:
        spacing_m: DTM grid spacing in metres (> 0).

    Returns:
        sigma_h in metres.
    """
    spacing_m = float(spacing_m)
    if not (math.isfinite(spacing_m) and spacing_m > 0.0):
        raise DtmError(f"grid spacing {spacing_m!r} m is invalid, expected a finite value > 0")
    return SIGMA_H_PER_GRID_SPACING * spacing_m


_EDGE_TOL_CELLS = 1e-9
"""Points this close (in cells) outside the grid edge count as on it (rounding of x0 + c*dx)."""


class RayStatus(enum.IntEnum):
    """Outcome of one ray cast.

    HIT: the ray meets the bilinear surface at ``t > 0``; a ray starting on the surface
        (to rounding) and heading into it hits at ``t = 0``.
    MISS: the ray leaves the grid (or never enters it) without meeting the terrain, or it
        starts below the terrain (its first point over the grid is under the surface).
    NODATA: before any hit the ray reaches, below the DTM's highest sample, a cell one of
        whose corners is NaN, so whether it would have hit there is unknown.
    """

    HIT = 0
    MISS = 1
    NODATA = 2


@dataclass(frozen=True)
class RayHits:
    """Result of :meth:`Dtm.raycast` for N rays.

    Attributes:
        point: (N, 3) world hit points (m), NaN where no hit.
        t: (N,) ray parameters, ``point = origin + t * direction`` with the direction as
            given (not normalized), NaN where no hit.
        normal: (N, 3) upward normal ``(-dh/dx, -dh/dy, 1)`` of the bilinear patch at the
            hit, not unit length, NaN where no hit.
        status: (N,) int8 :class:`RayStatus` values.
    """

    point: np.ndarray
    t: np.ndarray
    normal: np.ndarray
    status: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        """(N,) bool: True where the ray hit the terrain."""
        return self.status == RayStatus.HIT


class Dtm:
    """Regular grid DTM, bilinear surface.

    ``elevation[r, c]`` is the height at ``x = x0 + c*dx``, ``y = y0 + r*dy`` (dy may be
    negative). All coordinates are world ENU metres.

    Attributes:
        elevation: (rows, cols) float64 heights in metres, NaN for no data; read-only.
        x0, y0: world coordinates (m) of sample ``elevation[0, 0]``.
        dx, dy: sample spacing along columns (x) and rows (y) in metres; nonzero, may be
            negative.
        sigma_h_m: the 1-sigma height error given by the user, or None to derive it from
            the grid spacing (see :meth:`sigma_h`).
    """

    def __init__(
        self,
        elevation: np.ndarray,
        x0: float,
        y0: float,
        dx: float,
        dy: float,
        sigma_h_m: float | None = None,
    ):
        """Validate and store the grid.

        Args:
            elevation: (rows, cols) real heights (m), rows, cols >= 2; NaN marks no data.
            x0, y0: world position (m) of ``elevation[0, 0]``.
            dx, dy: finite, nonzero spacings (m).
            sigma_h_m: optional 1-sigma height error (m), finite and >= 0.

        Raises:
            DtmError: on any violation, saying what was expected.
        """
        elev = np.asarray(elevation)
        if elev.dtype.kind not in "fiu":
            raise DtmError(
                f"elevation has dtype {elev.dtype}, expected a real numeric (float) array"
            )
        if elev.ndim != 2:
            raise DtmError(f"elevation has shape {elev.shape}, expected a 2-D (rows, cols) array")
        if elev.shape[0] < 2 or elev.shape[1] < 2:
            raise DtmError(f"elevation has shape {elev.shape}, expected at least 2x2 samples")
        elev = np.array(elev, dtype=np.float64, order="C")  # own copy: made read-only below
        if np.isinf(elev).any():
            raise DtmError("elevation contains +-inf, expected finite heights or NaN for no data")
        if np.isnan(elev).all():
            raise DtmError("elevation is all NaN (no data), expected at least one valid cell")
        for name, value in (("x0", x0), ("y0", y0), ("dx", dx), ("dy", dy)):
            try:
                v = float(value)
            except (TypeError, ValueError):
                raise DtmError(f"{name} = {value!r}, expected a finite number") from None
            if not math.isfinite(v):
                raise DtmError(f"{name} = {v!r}, expected a finite number")
        if float(dx) == 0.0 or float(dy) == 0.0:
            raise DtmError(f"grid spacing dx = {dx!r}, dy = {dy!r}, expected both nonzero")
        if sigma_h_m is not None:
            sigma_h_m = float(sigma_h_m)
            if not (math.isfinite(sigma_h_m) and sigma_h_m >= 0.0):
                raise DtmError(f"sigma_h_m = {sigma_h_m!r}, expected a finite value >= 0")
        elev.flags.writeable = False  # per-cell caches below depend on it
        self.elevation: np.ndarray = elev
        self.x0 = float(x0)
        self.y0 = float(y0)
        self.dx = float(dx)
        self.dy = float(dy)
        self.sigma_h_m = sigma_h_m
        # A bilinear patch lies between its corner extremes, so the corner max bounds the
        # cell: a ray above it can skip the cell exactly. NaN marks a no-data cell.
        # (pairwise maxima, not a max over a stack of the four: no 4x copy of the grid)
        self._cell_max = np.maximum(np.maximum(elev[:-1, :-1], elev[:-1, 1:]),
                                    np.maximum(elev[1:, :-1], elev[1:, 1:]))
        if np.isnan(self._cell_max).all():
            raise DtmError("no cell has four valid corners, expected at least one valid cell")
        self._z_top = float(np.nanmax(elev))
        # the grid the tangent planes take their slopes from, where it is not this one
        # (:meth:`with_regional_slopes`)
        self._slope_elevation: np.ndarray | None = None
        self.slope_sigma_posts = 0.0

    def __repr__(self) -> str:
        slopes = (f", slope_sigma_posts={self.slope_sigma_posts}" if self.slope_sigma_posts
                  else "")
        return (
            f"Dtm(shape={self.shape}, x0={self.x0}, y0={self.y0}, dx={self.dx}, dy={self.dy}, "
            f"sigma_h_m={self.sigma_h_m}{slopes})"
        )

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of the elevation grid."""
        return self.elevation.shape  # type: ignore[return-value]

    @property
    def grid_spacing_m(self) -> float:
        """The coarser of the two spacings, ``max(|dx|, |dy|)`` (m)."""
        return max(abs(self.dx), abs(self.dy))

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) of the sample positions (m): the extent of the surface."""
        rows, cols = self.shape
        xa, xb = self.x0, self.x0 + (cols - 1) * self.dx
        ya, yb = self.y0, self.y0 + (rows - 1) * self.dy
        return (min(xa, xb), max(xa, xb), min(ya, yb), max(ya, yb))

    def sigma_h(self) -> float:
        """1-sigma height error (m): ``sigma_h_m`` if given, else the Fig. 6 spacing model."""
        if self.sigma_h_m is not None:
            return self.sigma_h_m
        return sigma_h_from_grid_spacing(self.grid_spacing_m)

    def with_regional_slopes(self, sigma_posts: float) -> Dtm:
        """This DTM with its tangent planes' slopes (:meth:`tangent_planes`, the C-DTM
        factor's) taken from the grid smoothed by a Gaussian of ``sigma_posts`` posts (along
        each axis: in metres ``sigma_posts * |dx|`` and ``* |dy|``): a weighted plane fit
        over about ``2 sigma_posts + 1`` posts a side, as terrain-referenced navigation
        linearizes a map whose posts are noisy (SITAN's regional slopes). The planes'
        points, the heights, the rays' hits: the grid's own (shared, not copied).

        Why: an error of ``s`` metres on each post tilts the bilinear patch by about
        ``s sqrt(2) / spacing`` (10 m on 30 m posts: 25 deg), which the factor reads as
        horizontal information the map does not hold: a grown sigma_h carries the heights'
        error, not that (docs/verdict.md, "Noisy posts"). No-data posts stay out of the
        smoothing (the weights renormalized over the valid ones); the outermost posts are
        padded with themselves, which flattens the slope of the edge cells a little (0.21
        for 0.3 in the last cell).

        Raises:
            ValueError: ``sigma_posts`` not a finite number > 0.
        """
        if not (math.isfinite(sigma_posts) and sigma_posts > 0):
            raise ValueError(f"sigma_posts = {sigma_posts!r}, expected a finite number > 0")
        from scipy.ndimage import gaussian_filter  # (a grown run's only: not at start-up)

        valid = np.isfinite(self.elevation)
        smoothed = gaussian_filter(np.where(valid, self.elevation, 0.0), sigma_posts,
                                   mode="nearest")
        with np.errstate(invalid="ignore", divide="ignore"):
            np.divide(smoothed, gaussian_filter(valid.astype(float), sigma_posts,
                                                mode="nearest"), out=smoothed)
        smoothed[~valid] = np.nan
        smoothed.flags.writeable = False
        out = copy.copy(self)  # (the grid and its per-cell caches shared: read-only)
        out._slope_elevation = smoothed
        out.slope_sigma_posts = float(sigma_posts)
        return out

    # -- surface queries -------------------------------------------------------------

    def _surface(self, x: np.ndarray, y: np.ndarray, normals: bool,
                 elevation: np.ndarray | None = None):
        """The broadcast shape, flat heights and (with ``normals``) upward normals (of
        ``elevation``, a grid of this one's shape and spacing; default: this one's)."""
        xb, yb = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
        h = np.empty(xb.size)
        normal = np.empty((xb.size if normals else 0, 3))
        grid = self.elevation if elevation is None else elevation
        # compiled: callers ask for one point (a camera's ground) as often as for thousands
        _surface_kernel(grid, self.x0, self.y0, self.dx, self.dy,
                        np.ascontiguousarray(xb).reshape(-1), np.ascontiguousarray(yb).reshape(-1),
                        h, normal)
        return xb.shape, h, normal

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bilinear height of the surface.

        Args:
            x, y: world coordinates (m), any broadcastable shapes.

        Returns:
            Heights (m) with the broadcast shape; NaN outside the grid or in a cell touching
            no data.
        """
        shape, h, _ = self._surface(x, y, normals=False)
        return h.reshape(shape)

    def height_and_normal(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bilinear height and the upward normal of the bilinear patch.

        The normal is ``(-dh/dx, -dh/dy, 1)`` (not unit length). On a cell boundary, where
        the bilinear surface has a kink, the derivative of the cell with the lower index
        along each axis is used (the last cell on the far edge).

        Args:
            x, y: world coordinates (m), broadcastable shapes; the result is flattened.

        Returns:
            (N,) heights (m) and (N, 3) normals; NaN where there is no height.
        """
        _, h, normal = self._surface(x, y, normals=True)
        return h, normal

    # -- ray casting -----------------------------------------------------------------

    def raycast(self, origins: np.ndarray, directions: np.ndarray) -> RayHits:
        """First intersection of rays with the bilinear surface, exact.

        The ray is ``origin + t * direction`` for ``t > 0``; directions need not be unit.
        See :class:`RayStatus` for what MISS and NODATA mean (a ray starting below the
        terrain, or entering the grid from the side below the surface, is a MISS; one
        starting on the surface and rising off it looks for the next crossing).
        Non-finite or zero-length rays are MISS.

        Args:
            origins: (N, 3) or (3,) world ray origins (m).
            directions: (N, 3) or (3,) world ray directions; broadcast against origins.

        Returns:
            :class:`RayHits` with N rays (N = 1 if both inputs are (3,)).
        """
        o = np.asarray(origins, dtype=np.float64)
        d = np.asarray(directions, dtype=np.float64)
        if o.shape[-1:] != (3,) or d.shape[-1:] != (3,) or o.ndim > 2 or d.ndim > 2:
            raise ValueError(
                f"origins {o.shape} and directions {d.shape}: expected (N, 3) or (3,) arrays"
            )
        o, d = np.broadcast_arrays(np.atleast_2d(o), np.atleast_2d(d))
        o = np.ascontiguousarray(o)
        d = np.ascontiguousarray(d)
        n = o.shape[0]
        point = np.full((n, 3), np.nan)
        t = np.full(n, np.nan)
        normal = np.full((n, 3), np.nan)
        status = np.full(n, RayStatus.MISS, dtype=np.int8)
        _raycast_kernel(
            self.elevation,
            self._cell_max,
            self.x0,
            self.y0,
            self.dx,
            self.dy,
            self._z_top,
            o,
            d,
            point,
            t,
            normal,
            status,
        )
        return RayHits(point=point, t=t, normal=normal, status=status)

    def tangent_planes(
        self, origins: np.ndarray, directions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The C-DTM factor's ray caster: ``(points (N,3), normals (N,3), hit (N,))``.

        Same exact first hit as :meth:`raycast`, without its input checks: the
        re-intersecting factor calls this at every linearization.

        Args:
            origins: (N, 3) or (3,) ray origins. directions: (N, 3) ray directions.
        """
        d = np.ascontiguousarray(directions, dtype=np.float64)
        n = d.shape[0]
        origins = np.asarray(origins, dtype=np.float64)
        if origins.shape == (3,):  # one camera: allocation and fill inside numba
            point, normal, hit = _tangent_planes_kernel(
                self.elevation, self._cell_max, self.x0, self.y0, self.dx, self.dy,
                self._z_top, origins, d)
            return point, self._regional(point, normal, hit), hit
        o = np.ascontiguousarray(np.broadcast_to(origins, d.shape))
        point = np.empty((n, 3))
        t = np.empty(n)
        normal = np.empty((n, 3))
        status = np.empty(n, dtype=np.int8)
        point.fill(np.nan)
        normal.fill(np.nan)
        status.fill(RayStatus.MISS)
        _raycast_kernel(self.elevation, self._cell_max, self.x0, self.y0, self.dx, self.dy,
                        self._z_top, o, d, point, t, normal, status)
        hit = status == RayStatus.HIT
        return point, self._regional(point, normal, hit), hit

    def _regional(self, point: np.ndarray, normal: np.ndarray, hit: np.ndarray) -> np.ndarray:
        """``normal`` with the regional slopes at the hits, if this DTM has them."""
        if self._slope_elevation is None or not hit.any():
            return normal
        _, _, regional = self._surface(point[hit, 0], point[hit, 1], normals=True,
                                       elevation=self._slope_elevation)
        out = normal.copy()
        # (a hit whose smoothed neighbourhood holds no data keeps its patch's slope)
        ok = np.isfinite(regional).all(axis=1)
        rows = np.flatnonzero(hit)[ok]
        out[rows] = regional[ok]
        return out

    # -- conversions -----------------------------------------------------------------

    def to_trimesh(self) -> trimesh.Trimesh:
        """Triangle mesh of the grid: two triangles per valid cell, vertices at the samples.

        Each cell is split along its (r, c)-(r+1, c+1) diagonal; faces are wound so their
        normals point up (+z) whatever the signs of dx, dy. Cells touching no data are
        skipped and NaN samples are not vertices. Within a cell the triangles differ from
        the bilinear surface by at most ``|h00 - h01 - h10 + h11| / 4``.

        Returns:
            A ``trimesh.Trimesh`` in world coordinates (m), built with ``process=False``.
        """
        import trimesh

        rows, cols = self.shape
        e = self.elevation
        valid = np.isfinite(e)
        vertex_id = np.full(e.shape, -1, dtype=np.int64)
        vertex_id[valid] = np.arange(int(valid.sum()))
        rr, cc = np.nonzero(valid)
        vertices = np.column_stack([self.x0 + cc * self.dx, self.y0 + rr * self.dy, e[rr, cc]])
        ci, cj = np.nonzero(np.isfinite(self._cell_max))
        v00 = vertex_id[ci, cj]
        v01 = vertex_id[ci, cj + 1]
        v10 = vertex_id[ci + 1, cj]
        v11 = vertex_id[ci + 1, cj + 1]
        if self.dx * self.dy > 0:
            tri_a, tri_b = (v00, v01, v11), (v00, v11, v10)
        else:  # one axis mirrored: reverse the winding to keep normals up
            tri_a, tri_b = (v00, v11, v01), (v00, v10, v11)
        faces = np.concatenate([np.column_stack(tri_a), np.column_stack(tri_b)])
        return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)

    def resample(self, spacing_m: float) -> Dtm:
        """Bilinear resampling onto a regular grid of another spacing over the same extent.

        The new grid starts at the same corner sample ``(x0, y0)`` with spacings of the same
        signs as ``dx``, ``dy`` and magnitude ``spacing_m``, and holds as many samples as fit
        inside the original extent (the far edge is dropped if the extent is not a multiple
        of the spacing). Samples are point values of the bilinear surface (NaN where it has
        none). ``sigma_h_m`` is not carried over: a resampled DTM has a different error.

        Args:
            spacing_m: new spacing (m), > 0.

        Returns:
            The resampled :class:`Dtm`.

        Raises:
            DtmError: if the spacing is invalid or leaves fewer than 2 samples on an axis.
        """
        spacing_m = float(spacing_m)
        if not (math.isfinite(spacing_m) and spacing_m > 0.0):
            raise DtmError(f"resample spacing {spacing_m!r} m, expected a finite value > 0")
        rows, cols = self.shape
        extent_x = (cols - 1) * abs(self.dx)
        extent_y = (rows - 1) * abs(self.dy)
        # The relative slack keeps an exact multiple (e.g. 3000 m / 30 m) from losing its
        # last sample to rounding.
        n_cols = int(math.floor(extent_x / spacing_m * (1 + 1e-12))) + 1
        n_rows = int(math.floor(extent_y / spacing_m * (1 + 1e-12))) + 1
        if n_cols < 2 or n_rows < 2:
            raise DtmError(
                f"resample spacing {spacing_m} m exceeds the extent "
                f"{extent_x:g} x {extent_y:g} m, expected a spacing giving at least 2x2 samples"
            )
        new_dx = math.copysign(spacing_m, self.dx)
        new_dy = math.copysign(spacing_m, self.dy)
        xs = self.x0 + np.arange(n_cols) * new_dx
        ys = self.y0 + np.arange(n_rows) * new_dy
        # Clamp onto the original extent: the last sample may overshoot it by rounding.
        xmin, xmax, ymin, ymax = self.bounds
        xs = np.clip(xs, xmin, xmax)
        ys = np.clip(ys, ymin, ymax)
        heights = self.height(xs[None, :], ys[:, None])
        return Dtm(heights, self.x0, self.y0, new_dx, new_dy)


# ---------------------------------------------------------------------------------------
# Ray casting kernel
# ---------------------------------------------------------------------------------------


@njit(cache=True, parallel=False, inline="always")
def _smallest_root(A: float, B: float, C: float, s_lim: float) -> float:
    """Smallest root in [0, s_lim] of ``A s^2 + B s + C`` with ``C > 0``, or -1.0 if none."""
    if A == 0.0:
        if B < 0.0:
            s = -C / B
            if s <= s_lim:
                return s
        return -1.0
    disc = B * B - 4.0 * A * C
    if disc < 0.0:
        return -1.0
    sq = math.sqrt(disc)
    # Numerically stable pair of roots (no cancellation): q/A and C/q.
    q = -0.5 * (B + sq) if B >= 0.0 else -0.5 * (B - sq)
    r1 = q / A
    r2 = C / q if q != 0.0 else math.inf  # q == 0 needs B == 0 and A*C == 0: not here
    lo = min(r1, r2)
    hi = max(r1, r2)
    if 0.0 <= lo <= s_lim:
        return lo
    if 0.0 <= hi <= s_lim:
        return hi
    return -1.0


@njit(cache=True)
def _surface_kernel(elev, x0, y0, dx, dy, x, y, h, normal):
    """Bilinear height of each point (NaN outside the grid, a hair of tolerance at its
    edge) and, if ``normal`` has rows, the patch's upward normal ``(-dh/dx, -dh/dy, 1)``
    (NaN with the height). Points on the last row/column use the last cell."""
    rows, cols = elev.shape
    eps = _EDGE_TOL_CELLS
    for p in range(x.shape[0]):
        u = (x[p] - x0) / dx
        v = (y[p] - y0) / dy
        inside = (u >= -eps) and (u <= cols - 1 + eps) and (v >= -eps) and (v <= rows - 1 + eps)
        j = min(max(int(np.floor(u)) if inside else 0, 0), cols - 2)
        i = min(max(int(np.floor(v)) if inside else 0, 0), rows - 2)
        a = min(max(u - j, 0.0), 1.0)
        b = min(max(v - i, 0.0), 1.0)
        h00, h01, h10, h11 = elev[i, j], elev[i, j + 1], elev[i + 1, j], elev[i + 1, j + 1]
        ha, hb, k = h01 - h00, h10 - h00, h00 - h01 - h10 + h11
        h[p] = h00 + ha * a + hb * b + k * a * b if inside else np.nan
        if normal.shape[0]:
            if np.isnan(h[p]):
                normal[p, 0] = normal[p, 1] = normal[p, 2] = np.nan
            else:
                normal[p, 0] = -(ha + k * b) / dx
                normal[p, 1] = -(hb + k * a) / dy
                normal[p, 2] = 1.0


@njit(cache=True, parallel=False)
def _raycast_kernel(
    elev, cell_max, x0, y0, dx, dy, z_top, origins, directions, point, t_out, normal, status
):
    """Exact first hit of each ray with the bilinear surface (outputs pre-filled NaN/MISS).

    Works in grid index space ``u = (x - x0)/dx``, ``v = (y - y0)/dy``, where cell (i, j)
    is ``[j, j+1] x [i, i+1]`` and negative spacings just flip the walk direction. Per cell,
    with ``s`` the ray parameter from the cell entry and ``(a, b)`` the local coordinates,
    ``z_ray(s) - h(a(s), b(s)) = A s^2 + B s + C`` is solved in closed form.
    """
    n_rows, n_cols = elev.shape
    u_max = n_cols - 1.0
    v_max = n_rows - 1.0
    inv_dx = 1.0 / dx
    inv_dy = 1.0 / dy
    for r in range(origins.shape[0]):
        ox = origins[r, 0]
        oy = origins[r, 1]
        oz = origins[r, 2]
        ddx = directions[r, 0]
        ddy = directions[r, 1]
        ddz = directions[r, 2]
        if not (
            math.isfinite(ox)
            and math.isfinite(oy)
            and math.isfinite(oz)
            and math.isfinite(ddx)
            and math.isfinite(ddy)
            and math.isfinite(ddz)
        ):
            continue
        if ddx == 0.0 and ddy == 0.0 and ddz == 0.0:
            continue
        u0 = (ox - x0) * inv_dx
        du = ddx * inv_dx
        v0 = (oy - y0) * inv_dy
        dv = ddy * inv_dy

        # Clip t to the grid's footprint (slab method) ...
        t_lo = 0.0
        t_hi = math.inf
        if du != 0.0:
            ta = -u0 / du
            tb = (u_max - u0) / du
            if ta > tb:
                ta, tb = tb, ta
            t_lo = max(t_lo, ta)
            t_hi = min(t_hi, tb)
        elif u0 < -_EDGE_TOL_CELLS or u0 > u_max + _EDGE_TOL_CELLS:
            continue
        if dv != 0.0:
            ta = -v0 / dv
            tb = (v_max - v0) / dv
            if ta > tb:
                ta, tb = tb, ta
            t_lo = max(t_lo, ta)
            t_hi = min(t_hi, tb)
        elif v0 < -_EDGE_TOL_CELLS or v0 > v_max + _EDGE_TOL_CELLS:
            continue
        # ... and to the part below the highest sample: above it nothing can be hit, and
        # starting there skips most of a high camera's ray at no cost to exactness.
        if ddz < 0.0:
            t_lo = max(t_lo, (z_top - oz) / ddz)
        elif ddz > 0.0:
            t_hi = min(t_hi, (z_top - oz) / ddz)
        elif oz > z_top:
            continue
        if not (t_lo <= t_hi):
            continue

        # First cell; clamping handles the far edge and rounding just outside the grid.
        t_en = t_lo
        j = int(math.floor(u0 + t_en * du))
        i = int(math.floor(v0 + t_en * dv))
        j = min(max(j, 0), n_cols - 2)
        i = min(max(i, 0), n_rows - 2)
        if du > 0.0:
            step_j = 1
            t_nu = (j + 1 - u0) / du
        elif du < 0.0:
            step_j = -1
            t_nu = (j - u0) / du
        else:
            step_j = 0
            t_nu = math.inf
        if dv > 0.0:
            step_i = 1
            t_nv = (i + 1 - v0) / dv
        elif dv < 0.0:
            step_i = -1
            t_nv = (i - v0) / dv
        else:
            step_i = 0
            t_nv = math.inf

        first = True
        while True:
            t_ex = min(t_nu, t_nv, t_hi)
            if t_ex < t_en:  # boundary crossing already passed by rounding
                t_ex = t_en
            c_max = cell_max[i, j]
            if c_max != c_max:  # NaN: a corner has no data
                status[r] = 2
                break
            z_en = oz + ddz * t_en
            z_ex = oz + ddz * t_ex
            if min(z_en, z_ex) <= c_max:  # else the ray is above the whole patch: skip it
                h00 = elev[i, j]
                h01 = elev[i, j + 1]
                h10 = elev[i + 1, j]
                h11 = elev[i + 1, j + 1]
                a = u0 + t_en * du - j
                b = v0 + t_en * dv - i
                ha = h01 - h00
                hb = h10 - h00
                k = h00 - h01 - h10 + h11
                C = z_en - (h00 + ha * a + hb * b + k * a * b)
                A = -k * du * dv
                B = ddz - (ha * du + hb * dv + k * (a * dv + b * du))
                s_max = t_ex - t_en
                # A root a hair past the exit (rounding) still belongs here: the next cell
                # may not exist (grid edge).
                s_lim = s_max * (1.0 + 1e-9) + 1e-15 * abs(t_en)
                if C > 0.0:
                    s_hit = _smallest_root(A, B, C, s_lim)
                elif not first:
                    # The previous cell's exit root was lost to rounding: hit at entry.
                    s_hit = 0.0
                elif C < -1e-9 * (abs(z_en) + 1.0):
                    break  # the ray starts below the terrain: MISS
                elif B > 0.0:
                    # Starts on the surface (to rounding) and rises off it: the next
                    # crossing, if any, is the other root of A s^2 + B s = 0.
                    s_hit = -B / A if A < 0.0 and -B / A <= s_lim else -1.0
                else:
                    s_hit = 0.0  # starts on the surface, going into it
                if s_hit > s_max:
                    s_hit = s_max
                if s_hit >= 0.0:
                    t_hit = t_en + s_hit
                    a_hit = min(max(a + s_hit * du, 0.0), 1.0)
                    b_hit = min(max(b + s_hit * dv, 0.0), 1.0)
                    t_out[r] = t_hit
                    point[r, 0] = ox + t_hit * ddx
                    point[r, 1] = oy + t_hit * ddy
                    point[r, 2] = oz + t_hit * ddz
                    normal[r, 0] = -(ha + k * b_hit) * inv_dx
                    normal[r, 1] = -(hb + k * a_hit) * inv_dy
                    normal[r, 2] = 1.0
                    status[r] = 0
                    break
            first = False
            if t_ex >= t_hi:
                break  # left the grid (or rose above the terrain) without a hit: MISS
            # Step to the next cell; on an exact corner crossing step both axes.
            if t_nu <= t_nv:
                j += step_j
                t_nu = (j + (1 if step_j > 0 else 0) - u0) / du
            if t_nv <= t_ex:
                i += step_i
                t_nv = (i + (1 if step_i > 0 else 0) - v0) / dv
            if j < 0 or j > n_cols - 2 or i < 0 or i > n_rows - 2:
                break
            t_en = t_ex


@njit(cache=True)
def _tangent_planes_kernel(elev, cell_max, x0, y0, dx, dy, z_top, origin, directions):
    """``_raycast_kernel`` for rays from one origin, returning ``(points, normals, hit)``:
    the per-linearization caller pays one dispatch, not a dozen numpy calls."""
    n = directions.shape[0]
    origins = np.empty((n, 3))
    for r in range(n):
        origins[r, 0] = origin[0]
        origins[r, 1] = origin[1]
        origins[r, 2] = origin[2]
    point = np.full((n, 3), np.nan)
    normal = np.full((n, 3), np.nan)
    t = np.empty(n)
    status = np.full(n, np.int8(RayStatus.MISS))
    _raycast_kernel(elev, cell_max, x0, y0, dx, dy, z_top, origins, directions, point, t,
                    normal, status)
    hit = np.empty(n, np.bool_)
    for r in range(n):
        hit[r] = status[r] == np.int8(RayStatus.HIT)
    return point, normal, hit


# ---------------------------------------------------------------------------------------
# Readers and writer
# ---------------------------------------------------------------------------------------


def grazing_hits(dtm: Dtm, origin: np.ndarray, directions: np.ndarray, points: np.ndarray,
                 normals: np.ndarray, angle_rad: float | np.ndarray, jump: float = 4.0
                 ) -> np.ndarray:
    """Rays whose first hit jumps to another surface when the ray turns a little.

    The C-DTM factor linearizes each feature on the tangent plane at its hit. Where the
    ray grazes a ridge (the paper's Fig. 1) a small pose change moves the hit behind the
    ridge, far along the ground, and the linearization is meaningless. Each ray is turned
    by ``angle_rad`` four ways (up, down, left, right of its own direction). On a smooth
    surface the hit then moves by about ``range * angle / cos(incidence)``; a ray is
    grazing when a turned ray's hit moves ``jump`` times farther than that, or misses.

    Args:
        dtm: the terrain. origin: (3,) the camera. directions: (n, 3) the rays.
        points, normals: (n, 3) their hits and upward normals ``(-dh/dx, -dh/dy, 1)``.
        angle_rad: the turn, scalar or (n,).
        jump: how many times the smooth-surface displacement a hit may move.

    Returns:
        (n,) bool, True for grazing rays.
    """
    d = np.ascontiguousarray(directions, dtype=np.float64)
    angle = np.ascontiguousarray(np.broadcast_to(np.asarray(angle_rad, dtype=np.float64),
                                                 d.shape[:1]))
    # one compiled pass: a frame's few hundred rays are too few for numpy's per-call cost
    return _grazing_kernel(dtm.elevation, dtm._cell_max, dtm.x0, dtm.y0, dtm.dx, dtm.dy,
                           dtm._z_top, np.asarray(origin, dtype=np.float64), d,
                           np.ascontiguousarray(points, dtype=np.float64),
                           np.ascontiguousarray(normals, dtype=np.float64), angle, float(jump))


@njit(cache=True)
def _grazing_kernel(elev, cell_max, x0, y0, dx, dy, z_top, origin, directions, points,
                    normals, angle, jump):
    """:func:`grazing_hits`: the four turned rays of every ray cast in one call."""
    n = directions.shape[0]
    turned = np.empty((4 * n, 3))
    smooth_m = np.empty(n)
    for r in range(n):
        # (scalars, not small arrays: allocating them per ray cost more than the casts)
        norm = np.sqrt(directions[r, 0] ** 2 + directions[r, 1] ** 2 + directions[r, 2] ** 2)
        norm = norm if norm > 0.0 else np.nan  # no direction: NaN rays, judged grazing
        d0, d1, d2 = directions[r, 0] / norm, directions[r, 1] / norm, directions[r, 2] / norm
        # two unit vectors perpendicular to the ray: u = d x h, v = d x u
        h0, h1, h2 = (0.0, 0.0, 1.0) if abs(d2) < 0.9 else (1.0, 0.0, 0.0)
        u0, u1, u2 = d1 * h2 - d2 * h1, d2 * h0 - d0 * h2, d0 * h1 - d1 * h0
        norm = np.sqrt(u0**2 + u1**2 + u2**2)
        u0, u1, u2 = u0 / norm, u1 / norm, u2 / norm
        v0, v1, v2 = d1 * u2 - d2 * u1, d2 * u0 - d0 * u2, d0 * u1 - d1 * u0
        a = angle[r]
        turned[r, 0], turned[r, 1], turned[r, 2] = d0 + a * u0, d1 + a * u1, d2 + a * u2
        turned[n + r, 0], turned[n + r, 1], turned[n + r, 2] = d0 - a * u0, d1 - a * u1, d2 - a * u2
        turned[2 * n + r, 0], turned[2 * n + r, 1], turned[2 * n + r, 2] = (
            d0 + a * v0, d1 + a * v1, d2 + a * v2)
        turned[3 * n + r, 0], turned[3 * n + r, 1], turned[3 * n + r, 2] = (
            d0 - a * v0, d1 - a * v1, d2 - a * v2)
        nx, ny, nz = normals[r, 0], normals[r, 1], normals[r, 2]
        cos_incidence = abs(d0 * nx + d1 * ny + d2 * nz) / np.sqrt(nx**2 + ny**2 + nz**2)
        range_m = np.sqrt((points[r, 0] - origin[0]) ** 2 + (points[r, 1] - origin[1]) ** 2
                          + (points[r, 2] - origin[2]) ** 2)
        smooth_m[r] = range_m * a / max(cos_incidence, 1e-3)
    origins = np.empty((4 * n, 3))
    for r in range(4 * n):  # (element by element: a row store costs ~1 s of compilation)
        origins[r, 0], origins[r, 1], origins[r, 2] = origin[0], origin[1], origin[2]
    hit_point = np.full((4 * n, 3), np.nan)
    hit_normal = np.full((4 * n, 3), np.nan)
    t = np.empty(4 * n)
    status = np.full(4 * n, np.int8(RayStatus.MISS))
    _raycast_kernel(elev, cell_max, x0, y0, dx, dy, z_top, origins, turned, hit_point, t,
                    hit_normal, status)
    grazing = np.zeros(n, dtype=np.bool_)
    for w in range(4):
        for r in range(n):
            i = w * n + r
            moved = np.sqrt((hit_point[i, 0] - points[r, 0]) ** 2
                            + (hit_point[i, 1] - points[r, 1]) ** 2
                            + (hit_point[i, 2] - points[r, 2]) ** 2)
            if status[i] != np.int8(RayStatus.HIT) or not moved <= jump * smooth_m[r]:
                grazing[r] = True
    return grazing


#: A point counts as visible if the first terrain hit toward it lies within this of it (m).
OCCLUSION_TOLERANCE_M = 1.0


def visible_from(occluder: Dtm, world_T_cam: np.ndarray, points: np.ndarray,
                 candidate: np.ndarray, tolerance_m: float = OCCLUSION_TOLERANCE_M
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Which ground points a camera sees: in front of it and unoccluded by the terrain.

    Args:
        occluder: the terrain that may hide points.
        world_T_cam: (4, 4) the camera.
        points: (n, 3) world points. candidate: (n,) bool, points worth checking.
        tolerance_m: how far before the point the first terrain hit may be.

    Returns:
        ``visible`` (n,) bool and the points in the camera frame (n, 3).
    """
    to_cam = points - world_T_cam[:3, 3]
    dist = np.linalg.norm(to_cam, axis=1)
    back = occluder.raycast(np.broadcast_to(world_T_cam[:3, 3], to_cam.shape),
                            np.where(candidate[:, None], to_cam, [0.0, 0.0, -1.0]))
    visible = candidate & back.hit & (np.abs(back.t * dist - dist) < tolerance_m)
    p_cam = to_cam @ world_T_cam[:3, :3]
    return visible & (p_cam[:, 2] > 0), p_cam


@dataclass
class GdalNotes:
    """What GDAL said during a read, collected by :func:`gdal_quiet` instead of printed.

    Attributes:
        messages: GDAL's warnings and errors (rasterio logs them), in order.
        not_georeferenced: rasterio warned that the raster has no geotransform (it then
            reports the identity transform).
    """

    messages: list[str] = field(default_factory=list)
    not_georeferenced: bool = False


class _Collect(logging.Handler):
    def __init__(self, notes: GdalNotes):
        super().__init__(logging.WARNING)
        self.notes = notes

    def emit(self, record: logging.LogRecord) -> None:
        self.notes.messages.append(record.getMessage())


@contextlib.contextmanager
def gdal_quiet() -> Iterator[GdalNotes]:
    """Collect GDAL's chatter during a rasterio read instead of printing it.

    A damaged GeoTIFF makes GDAL log a warning per tag and per block it cannot read
    (rasterio passes them to the ``rasterio`` loggers) and rasterio warn
    ``NotGeoreferencedWarning``: ten lines before the one error line. Inside the block
    they go to the yielded :class:`GdalNotes`, for the error message to quote.
    """
    notes = GdalNotes()
    logger = logging.getLogger("rasterio")
    handler = _Collect(notes)
    propagate = logger.propagate
    logger.addHandler(handler)
    logger.propagate = False
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                yield notes
            finally:
                for w in caught:
                    if w.category.__name__ == "NotGeoreferencedWarning":
                        notes.not_georeferenced = True
                    else:
                        notes.messages.append(str(w.message))
    finally:
        logger.removeHandler(handler)
        logger.propagate = propagate


def gdal_reason(exc: BaseException, notes: GdalNotes) -> str:
    """The most telling line of a rasterio failure: the GDAL error it chains (rasterio's
    own says "See previous exception for details"), else its text, else GDAL's first
    warning."""
    detail = exc
    while detail.__cause__ is not None:
        detail = detail.__cause__
    text = _short(str(detail))
    if not text or "See previous exception" in text:
        text = _short(notes.messages[0]) if notes.messages else type(exc).__name__
    return text


def load_dtm(
    path: str | os.PathLike,
    origin_enu_m: Sequence[float] = (0.0, 0.0, 0.0),
    sigma_h_m: float | None = None,
) -> Dtm:
    """Read a DTM file (docs/flightlog.md, "DTM files") into world coordinates.

    The format follows the suffix: ``.npz``, ``.asc`` (ESRI ASCII grid) or ``.tif``/
    ``.tiff`` (GeoTIFF, needs rasterio). Samples are at pixel/cell centres.

    Args:
        path: the file.
        origin_enu_m: (3,) subtracted from the file's x, y and z to give world ENU metres.
        sigma_h_m: optional 1-sigma height error (m) passed to :class:`Dtm`.

    Returns:
        The :class:`Dtm`.

    Raises:
        DtmError: naming the file (and line, for ``.asc``), what is wrong and what was
            expected.
    """
    path = Path(path)
    try:
        origin = np.asarray(origin_enu_m, dtype=float)
    except (TypeError, ValueError):
        raise DtmError(f"{path}: origin_enu_m = {origin_enu_m!r}, expected 3 numbers") from None
    if origin.shape != (3,) or not np.isfinite(origin).all():
        raise DtmError(f"{path}: origin_enu_m = {origin_enu_m!r}, expected 3 finite numbers")
    suffix = path.suffix.lower()
    readers = {".npz": _read_npz, ".asc": _read_asc, ".tif": _read_tif, ".tiff": _read_tif}
    if suffix not in readers:
        raise DtmError(f"{path}: unknown DTM file type {suffix!r}, expected .npz, .asc or .tif")
    if not path.is_file():
        raise DtmError(f"{path}: {why_not_a_file(path)}, expected a DTM file")
    try:
        elevation, x0, y0, dx, dy = readers[suffix](path)
        _refuse_degrees(path, elevation.shape, x0, y0, dx, dy)
        return Dtm(
            elevation - origin[2], x0 - origin[0], y0 - origin[1], dx, dy, sigma_h_m=sigma_h_m
        )
    except DtmError as exc:
        text = str(exc)
        raise DtmError(text if text.startswith(f"{path}: ") else f"{path}: {text}") from None
    except MemoryError as exc:  # a grid (or a damaged header's) larger than the memory
        raise DtmError(f"{path}: the grid does not fit in memory ({exc or 'MemoryError'}); "
                       "expected a DTM this machine can hold (crop it to the flight)") from None


#: A grid read as metres whose spacing is finer than this and whose coordinates all fit
#: longitudes and latitudes is taken for a grid in degrees (SRTM 1" = 0.00028, 30" = 0.0083).
DEGREE_LIKE_SPACING = 0.01


def _refuse_degrees(path: Path, shape: tuple[int, ...], x0: float, y0: float, dx: float,
                    dy: float) -> None:
    """A grid in degrees read as metres would be a map of 0.0003 m cells: refuse it."""
    rows, cols = shape
    x1, y1 = x0 + (cols - 1) * dx, y0 + (rows - 1) * dy
    if (max(abs(dx), abs(dy)) < DEGREE_LIKE_SPACING
            and all(-180.0 <= x <= 360.0 for x in (x0, x1))
            and all(-90.0 <= y <= 90.0 for y in (y0, y1))):
        raise DtmError(
            f"{path}: spacing {abs(dx):.6g} x {abs(dy):.6g} at x {x0:.6g}..{x1:.6g}, "
            f"y {y0:.6g}..{y1:.6g} looks like degrees of longitude and latitude, and the file "
            "carries no CRS; expected a metric grid, or a georeferenced DEM (GeoTIFF with its "
            "CRS, or .asc with a .prj) with a top-level origin: in flight.yaml")


def save_dtm_npz(dtm: Dtm, path: str | os.PathLike) -> None:
    """Write a DTM in the ``.npz`` format of docs/flightlog.md, atomically.

    The arrays go to a temporary file in the target directory which then replaces
    ``path``, so a reader never sees a half-written file. ``sigma_h_m`` is not part of the
    format (it belongs in flight.yaml) and is not written.

    Args:
        dtm: the DTM.
        path: target file; must end in ``.npz``.
    """
    path = Path(path)
    if path.suffix.lower() != ".npz":
        raise DtmError(f"{path}: cannot write a DTM here, expected a path ending in .npz")
    from cdtm_graph.atomic import atomic_output_file

    with atomic_output_file(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, elevation=np.asarray(dtm.elevation), x0=np.float64(dtm.x0),
                 y0=np.float64(dtm.y0), dx=np.float64(dtm.dx), dy=np.float64(dtm.dy))


_NPZ_SCALARS = ("x0", "y0", "dx", "dy")


#: What numpy's loader raises on a damaged or truncated ``.npz`` (zip directory, CRC,
#: deflate stream, ``.npy`` header, short data): all reported alike, as a damaged file.
_NPZ_DAMAGE = (OSError, EOFError, ValueError, zipfile.BadZipFile, zlib.error,
               NotImplementedError, RuntimeError, KeyError, struct.error, SyntaxError,
               tokenize.TokenError)


def _short(text: str, limit: int = 160) -> str:
    """One line of at most ``limit`` characters (zipfile quotes whole binary headers)."""
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _npz_damaged(path: Path, exc: BaseException) -> DtmError:
    detail = _short(str(exc)) or type(exc).__name__
    return DtmError(f"{path}: not a readable .npz archive ({detail}): the file is damaged, "
                    "truncated or not an .npz; expected a complete numpy .npz file")


def _read_npz(path: Path) -> tuple[np.ndarray, float, float, float, float]:
    """Arrays of a ``.npz`` DTM; other keys in the archive are ignored."""
    try:
        archive = np.load(path, allow_pickle=False)
    except _NPZ_DAMAGE as exc:
        raise _npz_damaged(path, exc) from None
    if not isinstance(archive, np.lib.npyio.NpzFile):
        raise DtmError(f"{path}: holds a single array, expected an .npz archive of arrays")
    with archive:
        missing = [k for k in ("elevation", *_NPZ_SCALARS) if k not in archive.files]
        if missing:
            raise DtmError(
                f"{path}: missing array(s) {', '.join(missing)}, expected elevation, x0, y0, dx, dy"
            )
        values = {}
        for key in ("elevation", *_NPZ_SCALARS):
            try:
                values[key] = archive[key]
            except ValueError as exc:
                if "allow_pickle" in str(exc):  # object arrays need pickle, refused here
                    raise DtmError(
                        f"{path}: array '{key}' cannot be read without pickle ({exc}), "
                        "expected a plain numeric array"
                    ) from None
                raise _npz_damaged(path, exc) from None
            except _NPZ_DAMAGE as exc:
                raise _npz_damaged(path, exc) from None
    elevation = values["elevation"]
    if elevation.dtype.kind not in "fiu" or elevation.ndim != 2:
        raise DtmError(
            f"{path}: 'elevation' has dtype {elevation.dtype} and shape {elevation.shape}, "
            "expected a 2-D float array (rows, cols)"
        )
    scalars = []
    for key in _NPZ_SCALARS:
        v = values[key]
        if v.shape != () or v.dtype.kind not in "fiu":
            raise DtmError(
                f"{path}: '{key}' has dtype {v.dtype} and shape {v.shape}, "
                "expected a numeric scalar"
            )
        scalars.append(float(v))
    x0, y0, dx, dy = scalars
    return elevation.astype(np.float64), x0, y0, dx, dy


_ASC_KEYS = ("ncols", "nrows", "xllcorner", "xllcenter", "yllcorner", "yllcenter", "cellsize",
             "nodata_value")


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _read_asc(path: Path) -> tuple[np.ndarray, float, float, float, float]:
    """ESRI ASCII grid: header ``key value`` lines, then ``nrows`` rows of ``ncols`` values,
    north row first. Returns the grid as read (row 0 north) with ``dy = -cellsize``."""
    try:
        text = path.read_text(encoding="ascii")
    except (OSError, UnicodeDecodeError) as exc:
        raise DtmError(f"{path}: cannot read ({exc}), "
                       "expected an ESRI ASCII grid text file") from None
    lines = text.splitlines()
    header: dict[str, tuple[str, int]] = {}
    n = 0
    while n < len(lines):
        tokens = lines[n].split()
        if not tokens:
            n += 1
            continue
        if _is_number(tokens[0]):
            break
        key = tokens[0].lower()
        if key not in _ASC_KEYS or len(tokens) != 2:
            raise DtmError(
                f"{path}: line {n + 1}: bad header line {lines[n].strip()!r}, expected "
                "'<key> <value>' with key one of ncols, nrows, xllcorner|xllcenter, "
                "yllcorner|yllcenter, cellsize, NODATA_value"
            )
        if key in header:
            raise DtmError(
                f"{path}: line {n + 1}: header key '{tokens[0]}' repeated, expected once"
            )
        header[key] = (tokens[1], n + 1)
        n += 1
    data_start = n  # 0-based index of the first data line

    def need(key: str) -> tuple[str, int]:
        if key not in header:
            raise DtmError(
                f"{path}: line {data_start + 1}: header ends without '{key}', expected "
                "ncols, nrows, xllcorner|xllcenter, yllcorner|yllcenter and cellsize"
            )
        return header[key]

    def as_int(key: str) -> int:
        token, line = need(key)
        try:
            value = int(token)
        except ValueError:
            value = 0
        if value < 1:
            raise DtmError(f"{path}: line {line}: {key} = {token!r}, expected a positive integer")
        return value

    def as_float(key: str, token: str, line: int) -> float:
        try:
            value = float(token)
        except ValueError:
            value = math.nan
        if not math.isfinite(value):
            raise DtmError(f"{path}: line {line}: {key} = {token!r}, expected a finite number")
        return value

    def corner_or_centre(axis: str) -> tuple[float, bool]:
        corner, centre = f"{axis}llcorner", f"{axis}llcenter"
        if corner in header and centre in header:
            line = max(header[corner][1], header[centre][1])
            raise DtmError(
                f"{path}: line {line}: both {corner} and {centre} given, expected one of them"
            )
        if corner in header:
            return as_float(corner, *header[corner]), True
        if centre in header:
            return as_float(centre, *header[centre]), False
        raise DtmError(
            f"{path}: line {data_start + 1}: header ends without {corner} or {centre}, "
            "expected one of them"
        )

    n_cols = as_int("ncols")
    n_rows = as_int("nrows")
    x_ll, x_is_corner = corner_or_centre("x")
    y_ll, y_is_corner = corner_or_centre("y")
    cellsize = as_float("cellsize", *need("cellsize"))
    if cellsize <= 0.0:
        raise DtmError(
            f"{path}: line {header['cellsize'][1]}: cellsize = {cellsize!r}, expected > 0"
        )
    nodata = as_float("NODATA_value", *header["nodata_value"]) if "nodata_value" in header else None

    # Rows are collected as read, not into an (nrows, ncols) array made from the header: a
    # header claiming more than the file holds fails on the data, not on the allocation.
    data: list[np.ndarray] = []
    row = 0
    last_line = data_start
    for n in range(data_start, len(lines)):
        tokens = lines[n].split()
        if not tokens:
            continue
        last_line = n + 1
        if row >= n_rows:
            raise DtmError(
                f"{path}: line {n + 1}: more data rows than nrows = {n_rows}, "
                f"expected {n_rows} rows"
            )
        if len(tokens) != n_cols:
            raise DtmError(
                f"{path}: line {n + 1}: {len(tokens)} values, expected ncols = {n_cols} "
                f"(header line {header['ncols'][1]})"
            )
        try:
            values = np.array(tokens, dtype=np.float64)
        except ValueError:
            bad = next(tok for tok in tokens if not _is_number(tok))
            raise DtmError(f"{path}: line {n + 1}: value {bad!r} is not a number") from None
        if not np.isfinite(values).all():
            bad = tokens[int(np.flatnonzero(~np.isfinite(values))[0])]
            raise DtmError(
                f"{path}: line {n + 1}: value {bad!r}, expected a finite number "
                "(mark no data with NODATA_value)"
            )
        data.append(values)
        row += 1
    if row < n_rows:
        raise DtmError(
            f"{path}: line {last_line}: file ends after {row} data rows, expected nrows = {n_rows}"
        )
    elevation = np.array(data, dtype=np.float64)
    if nodata is not None:
        elevation[elevation == nodata] = np.nan
    # Samples sit at cell centres; a corner registration is half a cell off. Row 0 is the
    # northernmost row, so y decreases with the row index.
    x0 = x_ll + (0.5 * cellsize if x_is_corner else 0.0)
    y_south = y_ll + (0.5 * cellsize if y_is_corner else 0.0)
    y0 = y_south + (n_rows - 1) * cellsize
    return elevation, x0, y0, cellsize, -cellsize


def _read_tif(path: Path) -> tuple[np.ndarray, float, float, float, float]:
    """GeoTIFF band 1 via rasterio: affine transform to pixel centres, nodata/mask -> NaN."""
    try:
        import rasterio
    except ImportError:
        raise DtmError(
            f"{path}: reading GeoTIFF needs rasterio, expected it installed: "
            "pip install 'cdtm-graph[geotiff]' (the geotiff extra)"
        ) from None
    stage = "open"
    with gdal_quiet() as notes:
        try:
            with rasterio.open(path) as src:
                transform = src.transform
                crs = src.crs
                if src.count < 1:
                    raise DtmError(f"{path}: has no raster band, expected one elevation band")
                stage = "read"
                band = src.read(1, masked=True)
        except DtmError:
            raise
        except MemoryError:
            raise  # load_dtm says the grid does not fit
        except Exception as exc:  # rasterio raises its own error types; report them all alike
            if stage == "open":
                raise DtmError(f"{path}: not a readable GeoTIFF: the file is damaged, "
                               f"truncated or of another format ({gdal_reason(exc, notes)}); "
                               "expected a complete GeoTIFF") from None
            raise DtmError(f"{path}: the GeoTIFF is damaged or truncated: its pixels cannot "
                           f"be read ({gdal_reason(exc, notes)}); expected a complete "
                           "GeoTIFF") from None
    if notes.not_georeferenced:
        io_errors = [m for m in notes.messages if "error" in m.lower()]
        if io_errors:  # the georeferencing tags are there but cannot be read
            raise DtmError(f"{path}: the GeoTIFF is damaged or truncated: its georeferencing "
                           f"cannot be read ({_short(io_errors[0])}); expected a complete "
                           "GeoTIFF")
        raise DtmError(f"{path}: the GeoTIFF has no georeferencing (no geotransform), so its "
                       "pixels have no coordinates; expected a georeferenced GeoTIFF")
    if crs is not None and getattr(crs, "is_geographic", False):
        raise DtmError(
            f"{path}: CRS {crs} is geographic (degrees); expected a metric projected CRS, or "
            "a top-level origin: (latitude_deg, longitude_deg, height_m) in flight.yaml to "
            "read it in the local ENU"
        )
    a, b, c, d, e, f = (float(transform[k]) for k in range(6))
    if b != 0.0 or d != 0.0:
        raise DtmError(
            f"{path}: affine transform is rotated or sheared (b={b}, d={d}), "
            "expected a north-up or axis-aligned grid"
        )
    elevation = np.ma.filled(np.ma.asarray(band).astype(np.float64), np.nan)
    # (c, f) is the outer corner of pixel (0, 0); samples are at pixel centres.
    return elevation, c + 0.5 * a, f + 0.5 * e, a, e
