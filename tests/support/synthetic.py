"""Made-up results and terrains several test folders share.

Imported by ``tests/conftest.py`` only (the ``synthetic`` fixture).
"""

from __future__ import annotations

import math

import numpy as np

from cdtm_graph.dtm import Dtm
from cdtm_graph.geometry import make_pose
from cdtm_graph.results import (
    GraphCounts,
    SmootherResult,
    Solver,
    SolverStats,
    StateCovariances,
    TrajectoryEstimate,
)
from tests.support.manifold import random_rotation

#: Frames of :func:`synthetic_result` unless asked.
FRAMES = 40
T0_NS = 1_403_636_579_758_555_392  # an epoch in ns: float64 seconds cannot hold it to 1 ns
FRAME_DT_NS = 100_000_123


def random_spd(rng: np.random.Generator, n: int, k: int, scale: np.ndarray) -> np.ndarray:
    """(k, n, n) random SPD matrices with standard deviations around ``scale`` (n,)."""
    a = rng.normal(size=(k, n, n))
    c = a @ np.swapaxes(a, 1, 2) / n + 0.1 * np.eye(n)
    return scale[:, None] * c * scale[None, :]


def synthetic_result(rng: np.random.Generator, k: int = FRAMES) -> SmootherResult:
    """A made-up run of k frames: random poses, SPD covariances, counts, settings, flags."""
    poses = np.stack([make_pose(random_rotation(rng, math.pi * 0.95),
                                rng.uniform(-5000, 5000, 3) + [0, 0, 1000]) for _ in range(k)])
    estimate = TrajectoryEstimate(
        t_ns=T0_NS + FRAME_DT_NS * np.arange(k, dtype=np.int64),
        world_T_body=poses,
        velocity_mps=rng.normal(scale=50.0, size=(k, 3)),
        gyro_bias=rng.normal(scale=1e-4, size=(k, 3)),
        accel_bias=rng.normal(scale=1e-2, size=(k, 3)))
    # Tiny rotation variances (1e-10 rad^2 and below) must survive the text format.
    covariances = StateCovariances(
        pose=random_spd(rng, 6, k, np.array([1e-5, 2e-5, 3e-5, 5.0, 7.0, 11.0])),
        velocity=random_spd(rng, 3, k, np.array([0.1, 0.2, 0.3])),
        # [accel, gyro]: very different scales, so a swap shows.
        bias=random_spd(rng, 6, k, np.array([1e-2, 1e-2, 1e-2, 1e-5, 1e-5, 1e-5])))
    return SmootherResult(
        estimate=estimate, covariances=covariances,
        stats=SolverStats(solver=Solver.LEVENBERG_MARQUARDT, iterations=4, initial_error=1.5e6,
                          final_error=float("nan"), converged=True, time_s=0.25,
                          update_times_s=(0.1, float("inf"))),
        counts=GraphCounts(n_frames=k, n_tracks=12, n_observations=300, n_feature_pairs=250,
                           n_cdtm_features=240, n_cdtm_factors=k - 1,
                           n_imu_factors=k - 1,
                           features_per_frame=np.arange(k, dtype=np.int64),
                           rejected_per_frame={"missed_dtm": np.full(k, 2)}),
        settings={"plane_mode": "fixed", "huber_k": np.float64(1.345)},
        flags={np.int64(3): ["no_features"], 7: ["degenerate"]})


def smooth_native_dtm() -> Dtm:
    """A smooth world terrain 25-30 km from the origin (where the ground has dropped ~90 m
    below the tangent plane and the vertical leans by 0.3 deg)."""
    x = 25000.0 + np.arange(201) * 30.0
    y = 15000.0 + np.arange(171) * 30.0
    gx, gy = np.meshgrid(x, y)
    z = (400.0 + 150.0 * np.sin(2 * np.pi * gx / 6000.0) * np.cos(2 * np.pi * gy / 4500.0)
         - (gx**2 + gy**2) / (2 * 6.37e6))
    return Dtm(z, x[0], y[0], 30.0, 30.0)
