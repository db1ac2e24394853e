"""Where the clean flights' covariance is pessimistic: the batch's position ANEES over
seeds with one source of error or weighting switched off at a time (issue 21, build 7).

Run: ``python scripts/consistency_sources.py [--frames 30] [--seeds 1 16]
[--runs default no_robust exact_dtm both no_shared] [--at-same-estimate]``.
Prints, per run, the mean ANEES over the seeds and the mean of error^2 / variance per world
axis (1 each for an honest covariance). ``--at-same-estimate``: also the covariance alone,
the default run's estimate with the marginals of its graph rebuilt with and without the
robust kernel (docs/verdict.md, "Where the pessimism comes from").
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np
from gtsam.symbol_shorthand import X

from cdtm_graph.calibration.check import estimate_values
from cdtm_graph.graph.log_graph import build_log_graph
from cdtm_graph.optimizer import key_marginals
from cdtm_graph.results import position_move_nees
from cdtm_graph.run import smooth_and_evaluate
from cdtm_graph.sim.simulate import simulate_flight
from cdtm_graph.smoother import SmootherSettings
from cdtm_graph.studies.robustness import BASE
from factors import RobustKernel

#: run name -> (simulation changes, graph setting changes)
RUNS = {
    "default": ({}, {}),
    "no_robust": ({}, {"robust": RobustKernel.NONE}),
    "exact_dtm": ({"exact_dtm": True}, {}),
    "both": ({"exact_dtm": True}, {"robust": RobustKernel.NONE}),
    "no_shared": ({}, {"shared_dtm_error": False}),
}


def world_position_nees_terms(world_T_body: np.ndarray, pose_cov: np.ndarray,
                              truth_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per frame: the position NEES (K,) (:func:`cdtm_graph.results.position_move_nees`)
    and error^2 / variance per world axis (K, 3)."""
    R = world_T_body[:, :3, :3]
    variance = np.einsum("kij,kjl,kil->ki", R, pose_cov[:, 3:, 3:], R)  # diag(R P R^T)
    err = world_T_body[:, :3, 3] - truth_m
    return position_move_nees(world_T_body, pose_cov, truth_m), err**2 / variance


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--seeds", type=int, nargs=2, default=(1, 16), metavar=("FIRST", "LAST"))
    parser.add_argument("--runs", nargs="+", choices=list(RUNS), default=list(RUNS))
    parser.add_argument("--at-same-estimate", action="store_true")
    args = parser.parse_args(argv)
    seeds = range(args.seeds[0], args.seeds[1] + 1)
    for name in args.runs:
        sim_changes, graph_changes = RUNS[name]
        anees, axes, same = [], [], []
        for seed in seeds:
            flight, dtm = simulate_flight(dataclasses.replace(BASE, frames=args.frames,
                                                              seed=seed, **sim_changes))
            base = SmootherSettings()
            settings = dataclasses.replace(base, graph=dataclasses.replace(base.graph,
                                                                           **graph_changes))
            result = smooth_and_evaluate(flight, dtm, settings).result
            truth = flight.groundtruth.interpolate(flight.frames.t_ns).position_m
            est = result.estimate
            nees, per_axis = world_position_nees_terms(est.world_T_body,
                                                       result.covariances.pose, truth)
            anees.append(nees.mean())
            axes.append(per_axis.mean(axis=0))
            if args.at_same_estimate and name == "default":
                values = estimate_values(est, np.arange(len(est.world_T_body)))
                row = []
                for kernel in (base.graph.robust, RobustKernel.NONE):
                    graph = build_log_graph(flight, dtm, dataclasses.replace(
                        base.graph, robust=kernel), values).graph
                    cov = np.stack(key_marginals(graph, values,
                                                 [X(k) for k in range(len(truth))]))
                    row.append(world_position_nees_terms(est.world_T_body, cov, truth)[0].mean())
                same.append(row)
        a, x = np.array(anees), np.array(axes).mean(axis=0)
        print(f"{name:10s} mean ANEES {a.mean():.2f} (seeds {args.seeds[0]}-{args.seeds[1]}, "
              f"{args.frames} frames; per run {np.round(a, 2).tolist()}); error^2/variance "
              f"x {x[0]:.2f} y {x[1]:.2f} z {x[2]:.2f}")
        if same:
            s = np.array(same).mean(axis=0)
            print(f"{'':10s} at the same estimate: marginals with the kernel {s[0]:.2f}, "
                  f"without {s[1]:.2f} (x{s[1] / s[0]:.3f})")


if __name__ == "__main__":
    main()
