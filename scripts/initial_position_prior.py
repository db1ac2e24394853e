"""flight.yaml's initial position against the data: the verdict's ``initial_position`` on
the robustness study's flights, one line per run (docs/verdict.md's table).

Run: ``python scripts/initial_position_prior.py SCENARIO OFF_M SIGMA_M --seeds 0 1 2
[--modes batch isam2 fixed_lag] [--frames 60]``: flight.yaml's initial position moved
``OFF_M`` from the truth in a seeded direction (0: drawn within ``SIGMA_M``) and its sigma
stated as ``SIGMA_M``. Each line: the conflict's statistic and the prior's pull in sigmas
(:meth:`cdtm_graph.results.PositionPrior.conflict`), the first frame's error, RMSE,
ANEES, and the verdict judged without ground truth with its ``initial_position`` notes.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys

import numpy as np

from cdtm_graph.run import smooth_and_evaluate
from cdtm_graph.smoother import SmootherSettings
from cdtm_graph.studies.robustness import BASE, SCENARIOS, Mode
from cdtm_graph.verdict.rules import assess


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenario", choices=list(SCENARIOS))
    parser.add_argument("off_m", type=float)
    parser.add_argument("sigma_m", type=float)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--modes", nargs="+", default=[m.value for m in Mode])
    parser.add_argument("--frames", type=int, default=60)
    args = parser.parse_args(argv)
    for seed in args.seeds:
        log, dtm = SCENARIOS[args.scenario].flight(
            dataclasses.replace(BASE, frames=args.frames, seed=seed))
        gt = log.groundtruth
        assert gt is not None
        truth = gt.position_m[np.searchsorted(gt.t_ns, log.frames.t_ns[0])]
        rng = np.random.default_rng(1000 + seed)
        direction = rng.standard_normal(3)
        error = (args.off_m * direction / np.linalg.norm(direction) if args.off_m
                 else args.sigma_m * rng.standard_normal(3))
        init = dataclasses.replace(log.config.initial_state, position_m=truth + error,
                                   sigma_position_m=args.sigma_m)
        log = dataclasses.replace(log, config=dataclasses.replace(log.config,
                                                                  initial_state=init))
        for mode in args.modes:
            out = smooth_and_evaluate(log, dtm, Mode(mode).settings(SmootherSettings()))
            result, errors = out.result, out.errors
            assert errors is not None
            conflict = result.initial_position_conflict()
            verdict = assess(result)
            notes = [n.split(":")[0] for n in verdict.notes if n.startswith("initial_position")]
            figures = ("-" if conflict is None else
                       f"{math.sqrt(conflict.nis):.2f} {math.sqrt(conflict.pull_nees):.2f}")
            print(f"{args.scenario} {args.off_m:g}/{args.sigma_m:g} seed {seed} {mode}: "
                  f"conflict, pull (sigma) {figures}; first frame "
                  f"{np.linalg.norm(errors.position_error_world_m[0]):.1f} m, RMSE "
                  f"{errors.rmse_position_3d_m:.2f} m, ANEES {errors.anees_position:.2f}; "
                  f"{verdict.status.value} {','.join(r.code for r in verdict.reasons)} "
                  f"{' '.join(notes)}", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
