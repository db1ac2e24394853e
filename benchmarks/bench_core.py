"""Core speed: C-DTM linearization vs GTSAM's native BetweenFactorPose3, two-frame solve, rays/s.

Run: ``python benchmarks/bench_core.py``. Ends with one line:
``linearize_us_per_feature=X native_between_us=Y ratio=X/Y two_frame_solve_ms=Z rays_per_s=R``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cdtm_graph.analysis.two_frame import solve_two_frame  # noqa: E402
from cdtm_graph.graph import dtm_ray_caster  # noqa: E402
from cdtm_graph.sim.scenario import PairScenario, make_terrain, sample_pair  # noqa: E402
from factors import CdtmPairFactor, PairFeatures, PlaneMode  # noqa: E402

N_PAIRS = 200
REPEATS = 5


def _best(fn, repeats: int = REPEATS) -> float:
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def measure_linearize(plane_mode: PlaneMode = PlaneMode.FIXED) -> tuple[float, float, int]:
    """(C-DTM us per feature, native Between us per factor, features) in one run."""
    scenario = PairScenario()
    terrain = make_terrain(scenario, seed=1)
    rng = np.random.default_rng(1)
    raycast = dtm_ray_caster(terrain.dtm)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    n_features = 0
    keep = []
    for i in range(N_PAIRS):
        s = sample_pair(scenario, terrain, rng)
        wTc_a, wTc_b = s.world_T_body_a @ s.body_T_cam, s.world_T_body_b @ s.body_T_cam
        ray = s.q_a @ wTc_a[:3, :3].T
        G, N, ok = raycast(np.broadcast_to(wTc_a[:3, 3], ray.shape), ray)
        feats = PairFeatures.build(wTc_a, wTc_b, s.q_a[ok], s.q_b[ok], G[ok], N[ok], scenario.noise)
        f = CdtmPairFactor(X(2 * i), X(2 * i + 1), feats, s.body_T_cam, plane_mode, raycast)
        keep.append(f)
        graph.add(f.factor)
        values.insert(X(2 * i), gtsam.Pose3(s.world_T_body_a))
        values.insert(X(2 * i + 1), gtsam.Pose3(s.world_T_body_b))
        n_features += feats.n
    graph.linearize(values)  # warm-up (numba compile)
    t_cdtm = _best(lambda: graph.linearize(values))

    between = gtsam.NonlinearFactorGraph()
    noise = gtsam.noiseModel.Isotropic.Sigma(6, 0.1)
    for j in range(n_features):
        i = j % N_PAIRS
        between.add(gtsam.BetweenFactorPose3(X(2 * i), X(2 * i + 1), gtsam.Pose3(), noise))
    t_native = _best(lambda: between.linearize(values))
    return 1e6 * t_cdtm / n_features, 1e6 * t_native / n_features, n_features


def measure_two_frame_ms(trials: int = 100) -> float:
    """Median wall time of a nominal two-frame solve (170 features, re-intersecting planes)."""
    scenario = PairScenario()
    terrain = make_terrain(scenario, seed=2)
    rng = np.random.default_rng(2)
    raycast = dtm_ray_caster(terrain.dtm)
    samples = [sample_pair(scenario, terrain, rng) for _ in range(trials)]
    times = []
    for s in samples:
        t0 = time.perf_counter()
        solve_two_frame(s.q_a, s.q_b, raycast, s.initial_a, s.initial_b, s.body_T_cam,
                        scenario.noise)
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times[5:]))


def main() -> None:
    from bench_raycast import measure_rays_per_s

    lin_us, native_us, n = measure_linearize()
    lin_re_us, _, _ = measure_linearize(PlaneMode.REINTERSECT)
    print(f"C-DTM linearize: {lin_us:.3f} us/feature fixed planes, {lin_re_us:.3f} us/feature "
          f"re-intersecting ({n} features in {N_PAIRS} pair factors)")
    print(f"GTSAM BetweenFactorPose3 linearize: {native_us:.3f} us/factor")
    solve_ms = measure_two_frame_ms()
    print(f"two-frame solve (170 features): median {solve_ms:.2f} ms")
    rays = measure_rays_per_s()
    print(f"ray casting 1000x1000 DTM: {rays:.3g} rays/s")
    print(f"linearize_us_per_feature={lin_us:.3f} native_between_us={native_us:.3f} "
          f"ratio={lin_us / native_us:.2f} two_frame_solve_ms={solve_ms:.2f} rays_per_s={rays:.0f}")


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    main()
