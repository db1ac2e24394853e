"""Online calibration against the calibration faults of issue 10: each flight smoothed
(batch) with the calibration held and estimated online.

Run: ``python scripts/calibration_matrix.py [--frames N] [--seed S] [--sigmas DT_S MOUNT_DEG
FOCAL] [--scenarios NAME ...]`` (default: the issue's flight, 90 frames, seed 1; clean,
focal1pct, mount05deg, late20ms; prior 0.03 s, 1 deg, 0.02).
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from cdtm_graph.flightlog import CalibrationSigmas
from cdtm_graph.graph import GraphSettings
from cdtm_graph.run import smooth_and_evaluate
from cdtm_graph.smoother import SmootherSettings
from cdtm_graph.studies.robustness import BASE, SCENARIOS


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=BASE.frames)
    parser.add_argument("--seed", type=int, default=BASE.seed)
    parser.add_argument("--sigmas", type=float, nargs=3, default=(0.03, 1.0, 0.02))
    parser.add_argument("--scenarios", nargs="+",
                        default=["clean", "focal1pct", "mount05deg", "late20ms"])
    args = parser.parse_args(argv)
    base = dataclasses.replace(BASE, frames=args.frames, seed=args.seed)
    sigmas = CalibrationSigmas(*args.sigmas)
    for name in args.scenarios:
        flight, dtm = SCENARIOS[name].flight(base)
        for calibration in (None, sigmas):
            start = time.perf_counter()
            out = smooth_and_evaluate(flight, dtm, SmootherSettings(
                graph=GraphSettings(calibration=calibration)))
            took = time.perf_counter() - start
            e, c = out.errors, out.result.calibration
            assert e is not None  # simulated: ground truth
            line = (f"{name:11} {'online' if c else 'held':6} rmse_3d "
                    f"{np.linalg.norm(e.rmse_position_m):6.2f} m  anees {e.anees_position:7.2f}  "
                    f"{out.verdict.status.value:8} {took:5.1f} s "
                    f"{' '.join(r.code for r in out.verdict.reasons)}")
            if c is not None:
                line += (f"\n{'':19}dt {c.time_offset_correction_s * 1e3:+.2f} ms, mount "
                         f"{np.round(c.mount_correction_deg, 3)} deg, focal scale "
                         f"{c.focal_scale:.5f}; sigmas {np.round(c.sigmas, 5)}; "
                         f"unobservable {c.unobservable or 'none'}")
            print(line, flush=True)


if __name__ == "__main__":
    main()
