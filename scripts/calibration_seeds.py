"""Clean flights over seeds with the default settings, every mode: the verdicts and the
calibration check's findings (issue 10: clean flights stay trusted on 95% of the seeds).

Run: ``python scripts/calibration_seeds.py [--frames N] [--seeds A B] [--scenario NAME]``
(default: the issue's 90-frame flight, seeds 1-20, clean; ``--scenario detail_waves``:
the same flights over ground detail the DTM lacks, issue 21).
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from cdtm_graph.run import smooth_and_evaluate
from cdtm_graph.smoother import SmootherSettings
from cdtm_graph.studies.robustness import BASE, SCENARIOS, Mode


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=BASE.frames)
    parser.add_argument("--seeds", type=int, nargs=2, default=(1, 20), metavar=("FIRST", "LAST"))
    parser.add_argument("--scenario", default="clean", choices=sorted(SCENARIOS))
    args = parser.parse_args(argv)
    rows: dict[Mode, list[tuple]] = {mode: [] for mode in Mode}
    for seed in range(args.seeds[0], args.seeds[1] + 1):
        flight, dtm = SCENARIOS[args.scenario].flight(dataclasses.replace(BASE, frames=args.frames,
                                                                    seed=seed))
        line = f"seed {seed:3d}"
        for mode in Mode:
            out = smooth_and_evaluate(flight, dtm, mode.settings(SmootherSettings()))
            e, check = out.errors, out.result.calibration_check
            assert e is not None and check is not None
            rmse = float(np.linalg.norm(e.rmse_position_m))
            rows[mode].append((out.verdict.status.value, rmse, e.anees_position, check.suspect,
                               check.cost_drop, check.position_nees, check.time_s))
            reasons = "".join(f" {r.code}" for r in out.verdict.reasons)
            line += (f" | {mode.value} {out.verdict.status.value} {rmse:.2f} m "
                     f"{e.anees_position:.2f} drop {check.cost_drop:.1f} nees "
                     f"{check.position_nees:.1f} scatter {check.residual_scatter:.2f} wald "
                     f"{check.wald:.1f}{reasons}")
        print(line, flush=True)
    for mode, r in rows.items():
        drops = [x[4] for x in r]
        print(f"{mode.value:9} trusted {sum(x[0] == 'trusted' for x in r)}/{len(r)}, suspect "
              f"{sum(x[3] for x in r)}, rmse_3d mean {np.mean([x[1] for x in r]):.2f} m, anees "
              f"mean {np.mean([x[2] for x in r]):.2f}, cost drop {min(drops):.1f}-"
              f"{max(drops):.1f}, position NEES max {max(x[5] for x in r):.1f}, side solve "
              f"mean {np.mean([x[6] for x in r]):.2f} s")


if __name__ == "__main__":
    main()
