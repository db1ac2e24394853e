"""Point clouds of the window's tracks and their correlation with the DTM (TERCOM-like).

Under a heading hypothesis the window is re-propagated and every track triangulated
robustly; the cloud is then moved over horizontal offsets and, at each, its vertical
offset and tilt are fitted in closed form and its heights scored against the DTM with a
truncated quadratic. The inner loops are numba kernels.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cdtm_graph.geometry import so3_exp
from cdtm_graph.robust.acquisition.window import Correction, Problem
from factors.jit import njit


@njit(cache=True)
def _solve_symmetric3(a00, a01, a02, a11, a12, a22, b0, b1, b2):
    """Solve the symmetric 3x3 system by cofactors (no LAPACK call in the inner loops);
    NaN when singular."""
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    det = a00 * c00 + a01 * c01 + a02 * c02
    if det == 0.0:
        return np.nan, np.nan, np.nan
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    return ((c00 * b0 + c01 * b1 + c02 * b2) / det, (c01 * b0 + c11 * b1 + c12 * b2) / det,
            (c02 * b0 + c12 * b1 + c22 * b2) / det)


@njit(cache=True)
def _midpoint(c, d, use, lo, hi, weighted, at):
    """The point nearest (least squares) to the rays ``lo:hi`` flagged in ``use``, and
    the (2, 2) entry of the inverse normal matrix. ``weighted``: each ray weighs
    ``1 / depth^2`` at the point ``at`` (angles instead of distances)."""
    a00 = a01 = a02 = a11 = a12 = a22 = b0 = b1 = b2 = 0.0
    for i in range(lo, hi):
        if not use[i - lo]:
            continue
        w = 1.0
        if weighted:
            w = 1.0 / ((at[0] - c[i, 0]) ** 2 + (at[1] - c[i, 1]) ** 2 + (at[2] - c[i, 2]) ** 2)
        dx, dy, dz = d[i, 0], d[i, 1], d[i, 2]
        p00, p01, p02 = w * (1.0 - dx * dx), -w * dx * dy, -w * dx * dz
        p11, p12, p22 = w * (1.0 - dy * dy), -w * dy * dz, w * (1.0 - dz * dz)
        a00 += p00
        a01 += p01
        a02 += p02
        a11 += p11
        a12 += p12
        a22 += p22
        b0 += p00 * c[i, 0] + p01 * c[i, 1] + p02 * c[i, 2]
        b1 += p01 * c[i, 0] + p11 * c[i, 1] + p12 * c[i, 2]
        b2 += p02 * c[i, 0] + p12 * c[i, 1] + p22 * c[i, 2]
    x, y, z = _solve_symmetric3(a00, a01, a02, a11, a12, a22, b0, b1, b2)
    zz = _solve_symmetric3(a00, a01, a02, a11, a12, a22, 0.0, 0.0, 1.0)[2]
    return np.array([x, y, z]), zz


@njit(cache=True)
def _ray_angle(c, d, i, X):
    """Angle (rad, small-angle) between ray i and the direction from its camera to X."""
    v0 = X[0] - c[i, 0]
    v1 = X[1] - c[i, 1]
    v2 = X[2] - c[i, 2]
    depth = v0 * d[i, 0] + v1 * d[i, 1] + v2 * d[i, 2]
    if depth <= 0.0:
        return 1e9  # behind the camera
    p0 = v0 - depth * d[i, 0]
    p1 = v1 - depth * d[i, 1]
    p2 = v2 - depth * d[i, 2]
    return math.sqrt(p0 * p0 + p1 * p1 + p2 * p2) / depth


@njit(cache=True)
def _triangulate_tracks(c, d, starts, tol):
    """Robust multi-view triangulation of every track.

    Each pair of a track's sightings proposes the point nearest both rays; the proposal
    most sightings agree with (angle < ``tol``; ties: the longer baseline) wins and is
    re-fitted to its inliers twice, rays weighted as angles.

    Args:
        c: (n, 3) camera centres. d: (n, 3) unit rays (world). starts: (T + 1,).
        tol: inlier angle (rad).

    Returns:
        X (T, 3) points (NaN where fewer than two sightings agree), angle (n,) of every
        sighting to its track's point, and z_spread (T,): the height standard deviation
        of the point for unit angular noise of the rays (m/rad).
    """
    T = starts.size - 1
    X = np.full((T, 3), np.nan)
    angle = np.full(c.shape[0], 1e9)
    z_spread = np.full(T, np.nan)
    origin = np.zeros(3)
    for t in range(T):
        lo, hi = starts[t], starts[t + 1]
        m = hi - lo
        use = np.zeros(m, dtype=np.bool_)
        best_n, best_baseline = 1, -1.0
        best = origin
        for k in range(m):
            for l in range(k + 1, m):
                use[:] = False
                use[k] = True
                use[l] = True
                P = _midpoint(c, d, use, lo, hi, False, origin)[0]
                if _ray_angle(c, d, lo + k, P) > tol or _ray_angle(c, d, lo + l, P) > tol:
                    continue
                n = 0
                for s in range(m):
                    if _ray_angle(c, d, lo + s, P) < tol:
                        n += 1
                baseline = math.sqrt(((c[lo + k] - c[lo + l]) ** 2).sum())
                if n > best_n or (n == best_n and baseline > best_baseline):
                    best_n, best_baseline, best = n, baseline, P
        if best_n < 2:
            continue
        zz = np.nan
        for _ in range(2):
            n = 0
            for s in range(m):
                use[s] = _ray_angle(c, d, lo + s, best) < tol
                n += use[s]
            if n < 2:
                break
            best, zz = _midpoint(c, d, use, lo, hi, True, best)
        n = 0
        for s in range(m):
            angle[lo + s] = _ray_angle(c, d, lo + s, best)
            n += angle[lo + s] < tol
        if n < 2 or not zz > 0.0:
            continue
        X[t] = best
        z_spread[t] = math.sqrt(zz)
    return X, angle, z_spread


@njit(cache=True)
def _bilinear(elev, x0, y0, dx, dy, x, y):
    """The bilinear surface of :meth:`cdtm_graph.dtm.Dtm.height` at one point (NaN off
    the grid or over no data)."""
    rows, cols = elev.shape
    u = (x - x0) / dx
    v = (y - y0) / dy
    if not (u >= 0.0 and u <= cols - 1 and v >= 0.0 and v <= rows - 1):
        return np.nan
    j = min(int(u), cols - 2)
    i = min(int(v), rows - 2)
    a = u - j
    b = v - i
    h00 = elev[i, j]
    h01 = elev[i, j + 1]
    h10 = elev[i + 1, j]
    h11 = elev[i + 1, j + 1]
    return h00 + (h01 - h00) * a + (h10 - h00) * b + (h00 - h01 - h10 + h11) * a * b


@njit(cache=True)
def _select(values, n, k):
    """The k-th smallest of ``values[:n]`` (reorders them; Hoare's selection)."""
    lo, hi = 0, n - 1
    while lo < hi:
        pivot = values[(lo + hi) // 2]
        i, j = lo, hi
        while i <= j:
            while values[i] < pivot:
                i += 1
            while values[j] > pivot:
                j -= 1
            if i <= j:
                values[i], values[j] = values[j], values[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    return values[k]


@njit(cache=True)
def _fit_plane(elev, x0, y0, dx, dy, px, py, pz, xr, yr, w, ox, oy, tau, slope_info,
               diff, scratch, costs):
    """Score one horizontal offset: robust fit of a vertical offset and tilt, truncated cost.

    ``diff_i = h(p_i + o) - z_i`` is fitted by ``c + a xr_i + b yr_i`` (weights ``w_i =
    1 / sigma_i^2``, a ridge ``slope_info`` on the tilt: the attitude prior) from the
    median, by three reweightings keeping points within ``tau`` sigmas. Points off the
    DTM cost ``tau^2``.

    Returns:
        (cost, c, a, b); per-point costs in ``costs``.
    """
    n = px.size
    m = 0
    for i in range(n):
        diff[i] = _bilinear(elev, x0, y0, dx, dy, px[i] + ox, py[i] + oy) - pz[i]
        if diff[i] == diff[i]:
            scratch[m] = diff[i]
            m += 1
    if m < 3:
        costs[:] = tau * tau
        return np.inf, np.nan, 0.0, 0.0
    c = _select(scratch, m, m // 2)
    a = 0.0
    b = 0.0
    tau2 = tau * tau
    for _ in range(3):
        s00 = s01 = s02 = s11 = s12 = s22 = r0 = r1 = r2 = 0.0
        for i in range(n):
            r = diff[i] - c - a * xr[i] - b * yr[i]
            if not (r * r * w[i] < tau2):  # NaN (off the DTM) fails too
                continue
            wi = w[i]
            s00 += wi
            s01 += wi * xr[i]
            s02 += wi * yr[i]
            s11 += wi * xr[i] * xr[i]
            s12 += wi * xr[i] * yr[i]
            s22 += wi * yr[i] * yr[i]
            r0 += wi * diff[i]
            r1 += wi * diff[i] * xr[i]
            r2 += wi * diff[i] * yr[i]
        if s00 <= 0.0:
            break
        c1, a1, b1 = _solve_symmetric3(s00, s01, s02, s11 + slope_info, s12,
                                       s22 + slope_info, r0, r1, r2)
        if c1 != c1:  # singular: keep the last fit
            break
        c, a, b = c1, a1, b1
    total = slope_info * (a * a + b * b)
    for i in range(n):
        r = diff[i] - c - a * xr[i] - b * yr[i]
        e = r * r * w[i]
        costs[i] = e if e < tau2 else tau2
        total += costs[i]
    return total, c, a, b


@njit(cache=True)
def _score_offsets(elev, x0, y0, dx, dy, px, py, pz, xr, yr, w, offsets, tau, slope_info):
    """:func:`_fit_plane` at each of the offsets (M, 2). (numba's ``prange`` over the
    offsets ran slower than one thread on the 2-core sandbox: left serial.)

    Returns:
        cost, vertical offset c, tilt a, b: (M,) each.
    """
    M, n = offsets.shape[0], px.size
    cost = np.empty(M)
    cz = np.empty(M)
    ca = np.empty(M)
    cb = np.empty(M)
    diff = np.empty(n)
    scratch = np.empty(n)
    costs = np.empty(n)
    for m in range(M):
        cost[m], cz[m], ca[m], cb[m] = _fit_plane(
            elev, x0, y0, dx, dy, px, py, pz, xr, yr, w, offsets[m, 0], offsets[m, 1], tau,
            slope_info, diff, scratch, costs)
    return cost, cz, ca, cb


@njit(cache=True)
def _point_costs(elev, x0, y0, dx, dy, px, py, pz, xr, yr, w, ox, oy, tau, slope_info):
    """Per-point costs (n,) of one offset (as :func:`_score_offsets` scores it)."""
    n = px.size
    costs = np.empty(n)
    _fit_plane(elev, x0, y0, dx, dy, px, py, pz, xr, yr, w, ox, oy, tau, slope_info,
               np.empty(n), np.empty(n), costs)
    return costs


@dataclass(frozen=True)
class Cloud:
    """The window's tracks triangulated under one heading.

    Attributes:
        heading_rad: the heading hypothesis.
        ray_costs: (T,) per track, the truncated angular costs of its sightings.
        points: (T, 3) (NaN where not triangulated). sigma_m: (T,) height sigma against
            the DTM.
    """

    heading_rad: float
    ray_costs: np.ndarray
    points: np.ndarray
    sigma_m: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        return np.isfinite(self.points[:, 0])


def make_cloud(problem: Problem, heading_rad: float) -> Cloud:
    """The window's tracks triangulated under a heading hypothesis (a turn of the first
    state about world z), with the truncated angular costs of their sightings."""
    w, sigma, tau = problem.window, problem.ray_sigma_rad, problem.tau
    c = Correction(so3_exp(np.array([0.0, 0.0, heading_rad])), np.zeros(3), np.zeros(3))
    world_T_cam = problem.poses(c) @ problem.camera.body_T_cam
    centres = np.ascontiguousarray(world_T_cam[w.frame, :3, 3])
    rays = np.einsum("nij,nj->ni", world_T_cam[w.frame, :3, :3], w.q)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    X, angle, z_spread = _triangulate_tracks(centres, rays, w.starts, tau * sigma)
    ray_costs = np.bincount(w.track_of, np.minimum((angle / sigma) ** 2, tau ** 2),
                            minlength=w.n_tracks)
    height_sigma = np.hypot(z_spread * sigma, problem.settings.height_sigma_m)
    return Cloud(heading_rad, ray_costs, X, height_sigma)


@dataclass(frozen=True)
class _Points:
    """A cloud's valid points as the kernels take them (contiguous float64)."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    x_rel: np.ndarray  # about the centroid: the tilt's lever
    y_rel: np.ndarray
    weight: np.ndarray  # 1 / sigma^2

    @classmethod
    def of(cls, cloud: Cloud) -> _Points:
        ok = cloud.valid
        P = cloud.points[ok]
        centre = P.mean(axis=0) if len(P) else np.zeros(3)  # (no track triangulated)
        return cls(*(np.ascontiguousarray(v) for v in (
            P[:, 0], P[:, 1], P[:, 2], P[:, 0] - centre[0], P[:, 1] - centre[1],
            1.0 / cloud.sigma_m[ok] ** 2)))


def _slope_info(problem: Problem) -> float:
    """The tilt's ridge: the attitude prior as a slope (m/m), in information."""
    return 1.0 / max(math.tan(problem.prior.tilt_sigma_rad), 1e-6) ** 2


def score_offsets(problem: Problem, cloud: Cloud, offsets: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Total cost (M,) and vertical offset (M,) of each horizontal offset (M, 2) under
    the cloud's heading: every track counted (its rays, then its height, or the
    truncation if it did not triangulate)."""
    d, p = problem.dtm, _Points.of(cloud)
    cost, cz, _, _ = _score_offsets(
        problem.elevation, d.x0, d.y0, d.dx, d.dy, p.x, p.y, p.z, p.x_rel, p.y_rel, p.weight,
        np.ascontiguousarray(offsets, dtype=float), problem.tau, _slope_info(problem))
    fixed = cloud.ray_costs.sum() + problem.tau ** 2 * int((~cloud.valid).sum())
    return cost + fixed, cz


def best_over_headings(problem: Problem, clouds: Sequence[Cloud], offsets: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per offset (M, 2): the lowest cost over the clouds' headings, which cloud gave it,
    and its vertical offset, (M,) each."""
    best = np.full(offsets.shape[0], np.inf)
    index = np.zeros(offsets.shape[0], dtype=np.int64)
    vertical = np.full(offsets.shape[0], np.nan)
    for n, cloud in enumerate(clouds):
        cost, cz = score_offsets(problem, cloud, offsets)
        better = cost < best
        best[better], index[better], vertical[better] = cost[better], n, cz[better]
    return best, index, vertical


def track_costs(problem: Problem, cloud: Cloud, offset_xy: np.ndarray) -> np.ndarray:
    """(T,) per-track costs of one offset under the cloud's heading (as
    :func:`score_offsets` sums them)."""
    d, p = problem.dtm, _Points.of(cloud)
    height = np.full(problem.window.n_tracks, problem.tau ** 2)
    height[cloud.valid] = _point_costs(
        problem.elevation, d.x0, d.y0, d.dx, d.dy, p.x, p.y, p.z, p.x_rel, p.y_rel, p.weight,
        float(offset_xy[0]), float(offset_xy[1]), problem.tau, _slope_info(problem))
    return cloud.ray_costs + height
