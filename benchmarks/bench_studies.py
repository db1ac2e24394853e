"""Time all six sensitivity studies (paper Figs. 2-9) at the paper's 150 trials per value.

Run: ``PYTHONPATH=. python benchmarks/bench_studies.py [--trials 150] [--workers N]
[--out DIR]``. The six studies go to one process pool as one batch of tasks (per-task
work ~0.4 s, so pool start-up and the idle tail are paid once). With ``--out`` the CSVs
and figures are written as ``cdtm study`` writes them. The last line is
``all_sweeps_s=<seconds>``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from cdtm_graph.cli.study import format_table, write_study_csv, write_study_figure
from cdtm_graph.parallel import ParallelSettings
from cdtm_graph.studies.sweeps import StudyParameter, StudySettings, run_studies


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=150)
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--quiet", action="store_true", help="no tables")
    args = parser.parse_args()
    studies = [StudySettings(p, trials=args.trials, seed=args.seed) for p in StudyParameter]
    parallel = ParallelSettings(workers=args.workers)
    n_trials = sum(len(s.resolved_values()) * s.trials for s in studies)
    print(f"{len(studies)} sweeps, {n_trials} trials, {parallel.n_local_workers()} workers")
    start = time.perf_counter()
    results = run_studies(studies, parallel)
    elapsed_s = time.perf_counter() - start
    for result in results:
        failures = int(sum(r.failures for r in result.rows))
        features = np.mean([o.n_features.mean() for o in result.outcomes])
        print(f"{result.parameter.value:>10}: {len(result.values)} values, "
              f"{failures} failed trials, {features:.0f} features per trial on average")
        if not args.quiet:
            print(format_table(result))
        if args.out is not None:
            write_study_csv(result, args.out / f"study_{result.parameter.value}.csv")
            write_study_figure(result, args.out / f"study_{result.parameter.value}.png")
    print(f"per_trial_core_ms={1e3 * elapsed_s * parallel.n_local_workers() / n_trials:.2f}")
    print(f"all_sweeps_s={elapsed_s:.1f}")


if __name__ == "__main__":
    main()
