"""Shared test helpers: central differences on the manifold, random poses, scenes.

Imported by ``tests/conftest.py`` only, which hands them to the tests as fixtures."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from cdtm_graph.geometry import make_pose, so3_exp
from factors import FeatureNoise, PairFeatures

#: Step of the central differences: the truncation error is O(step^2), rounding O(eps/step).
CENTRAL_DIFF_STEP = 1e-6


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """GTSAM's Pose3 retraction used by the tests: [omega, v] -> 4x4 (Expmap)."""
    import gtsam

    return gtsam.Pose3.Expmap(np.asarray(xi, dtype=float)).matrix()


def numerical_pose_jacobian(
    fn: Callable[[np.ndarray], np.ndarray], T: np.ndarray, step: float = CENTRAL_DIFF_STEP
) -> np.ndarray:
    """d fn(T Exp(xi)) / d xi at xi = 0 by central differences, GTSAM tangent order.

    Args:
        fn: maps a 4x4 pose to a flat vector (m,).
        T: (4, 4) linearization point.

    Returns:
        (m, 6) Jacobian.
    """
    cols = []
    for j in range(6):
        d = np.zeros(6)
        d[j] = step
        cols.append((fn(T @ se3_exp(d)) - fn(T @ se3_exp(-d))) / (2 * step))
    return np.stack(cols, axis=-1)


def numerical_jacobian(
    fn: Callable[[np.ndarray], np.ndarray], x: np.ndarray, step: float = CENTRAL_DIFF_STEP
) -> np.ndarray:
    """d fn / d x for a vector x by central differences, (m, len(x))."""
    x = np.asarray(x, dtype=float)
    cols = []
    for j in range(x.size):
        d = np.zeros_like(x)
        d.flat[j] = step
        cols.append((fn(x + d) - fn(x - d)) / (2 * step))
    return np.stack(cols, axis=-1)


def random_rotation(rng: np.random.Generator, max_angle_rad: float) -> np.ndarray:
    """A rotation of angle below ``max_angle_rad`` about a random axis."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return so3_exp(axis * rng.uniform(0, max_angle_rad))


def downward_body_T_cam(rng: np.random.Generator) -> np.ndarray:
    """A non-identity camera mounting: looking down (cam z = -body z), tilted and offset."""
    R_down = np.diag([1.0, -1.0, -1.0])  # cam x = body x, cam y = -body y, cam z = -body z
    return make_pose(random_rotation(rng, 0.1) @ R_down, rng.uniform(-0.5, 0.5, 3))


class WavyTerrain:
    """A smooth analytic terrain with an exact (Newton) ray caster, for reintersection tests."""

    def __init__(self, amplitude_m: float = 40.0, wavelength_m: float = 600.0, base_m: float = 0.0):
        self.a, self.k, self.base = amplitude_m, 2 * np.pi / wavelength_m, base_m

    def height(self, x, y):
        return self.base + self.a * np.sin(self.k * x) * np.cos(0.7 * self.k * y)

    def normal(self, x, y):
        hx = self.a * self.k * np.cos(self.k * x) * np.cos(0.7 * self.k * y)
        hy = -self.a * 0.7 * self.k * np.sin(self.k * x) * np.sin(0.7 * self.k * y)
        return np.stack([-hx, -hy, np.ones_like(hx)], axis=-1)

    def raycast(self, origins, directions):
        d = np.asarray(directions, dtype=float)
        o = np.broadcast_to(np.asarray(origins, dtype=float), d.shape)
        t = (o[:, 2] - self.base) / -d[:, 2]
        for _ in range(60):
            x = o + t[:, None] * d
            fval = x[:, 2] - self.height(x[:, 0], x[:, 1])
            n = self.normal(x[:, 0], x[:, 1])
            t = t - fval / np.einsum("ni,ni->n", n, d)
        x = o + t[:, None] * d
        valid = np.abs(x[:, 2] - self.height(x[:, 0], x[:, 1])) < 1e-9
        return x, self.normal(x[:, 0], x[:, 1]), valid


#: The feature noise of :func:`random_pair` (pixels of a 350 px focal length, normalized).
PAIR_NOISE = FeatureNoise(sigma_q_xy=(0.5 / 350, 0.5 / 340), sigma_h_m=2.4,
                          sigma_qa_xy=(1.4e-3, 1.5e-3))


def random_pair(rng, terrain: WavyTerrain | None = None, n: int = 12, pixel_noise: float = 2e-3):
    """Two body poses ~40 m apart over terrain, a non-identity mounting and n features."""
    body_T_cam = downward_body_T_cam(rng)
    wTb_a = make_pose(random_rotation(rng, 0.2),
                      np.r_[rng.uniform(-200, 200, 2), 500 + rng.uniform(-50, 50)])
    step = make_pose(random_rotation(rng, 0.17), np.r_[40.0, 0, 0] + rng.normal(0, 5, 3))
    wTb_b = wTb_a @ step
    wTc_a, wTc_b = wTb_a @ body_T_cam, wTb_b @ body_T_cam
    q_a = np.c_[rng.uniform(-0.4, 0.4, (n, 2)), np.ones(n)]
    ray = q_a @ wTc_a[:3, :3].T
    if terrain is None:
        G = wTc_a[:3, 3] + rng.uniform(300, 700, n)[:, None] * ray
        N = np.c_[rng.uniform(-0.6, 0.6, (n, 2)), np.ones(n)]
    else:
        G, N, valid = terrain.raycast(np.broadcast_to(wTc_a[:3, 3], ray.shape), ray)
        assert valid.all()
    g_b = (G - wTc_b[:3, 3]) @ wTc_b[:3, :3]
    q_b = g_b / g_b[:, 2:3]
    q_b[:, :2] += rng.normal(0, pixel_noise, (n, 2))  # non-zero residuals exercise every term
    feats = PairFeatures.build(wTc_a, wTc_b, q_a, q_b, G, N, PAIR_NOISE)
    return body_T_cam, wTb_a, wTb_b, feats
