"""Online calibration against the calibration faults of issue 10: each flight smoothed in
batch with the calibration held (unchecked), held and checked in a batch side solve (the
default), and estimated online, and in the incremental modes (held and checked).

Run: ``python scripts/calibration_matrix.py [--frames N] [--seed S] [--sigmas DT_S MOUNT_DEG
FOCAL] [--scenarios NAME ...] [--runs held checked online isam2 fixed_lag]`` (default: the issue's
flight, 90 frames, seed 1; clean, focal1pct, mount05deg, late20ms; the default prior
30 ms, 1 deg, 2%; every run).
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from cdtm_graph.flightlog import CalibrationSigmas
from cdtm_graph.graph import DEFAULT_CALIBRATION_SIGMAS, GraphSettings
from cdtm_graph.run import smooth_and_evaluate
from cdtm_graph.smoother import SmootherMode, SmootherSettings
from cdtm_graph.studies.robustness import BASE, SCENARIOS

RUNS = ("held", "checked", "online", "isam2", "fixed_lag")


def _settings(run: str, sigmas: CalibrationSigmas) -> SmootherSettings:
    """held: unchecked; checked (the default): held and checked in a side solve; online:
    estimated (batch); isam2, fixed_lag: their defaults (held and checked)."""
    graph = GraphSettings(calibration=None if run == "held" else sigmas,
                          calibration_online=run == "online")
    if run in ("held", "checked", "online"):
        return SmootherSettings(graph=graph)
    return SmootherSettings(graph=graph, mode=SmootherMode.INCREMENTAL,
                            lag_s=10.0 if run == "fixed_lag" else None)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=BASE.frames)
    parser.add_argument("--seed", type=int, default=BASE.seed)
    d = DEFAULT_CALIBRATION_SIGMAS
    parser.add_argument("--sigmas", type=float, nargs=3,
                        default=(d.time_offset_sigma_s, d.mount_sigma_deg, d.focal_scale_sigma))
    parser.add_argument("--scenarios", nargs="+",
                        default=["clean", "focal1pct", "mount05deg", "late20ms"])
    parser.add_argument("--runs", nargs="+", choices=RUNS, default=list(RUNS))
    args = parser.parse_args(argv)
    base = dataclasses.replace(BASE, frames=args.frames, seed=args.seed)
    sigmas = CalibrationSigmas(*args.sigmas)
    for name in args.scenarios:
        flight, dtm = SCENARIOS[name].flight(base)
        for run in args.runs:
            start = time.perf_counter()
            out = smooth_and_evaluate(flight, dtm, _settings(run, sigmas))
            took = time.perf_counter() - start
            e, c, check = out.errors, out.result.calibration, out.result.calibration_check
            assert e is not None  # simulated: ground truth
            line = (f"{name:11} {run:9} rmse_3d {np.linalg.norm(e.rmse_position_m):6.2f} m  "
                    f"anees {e.anees_position:7.2f}  {out.verdict.status.value:8} {took:5.1f} s "
                    f"{' '.join(r.code for r in out.verdict.reasons)}")
            if c is not None:
                line += (f"\n{'':21}dt {c.time_offset_correction_s * 1e3:+.2f} ms, mount "
                         f"{np.round(c.mount_correction_deg, 3)} deg, focal scale "
                         f"{c.focal_scale:.5f}; sigmas {np.round(c.sigmas, 5)}; "
                         f"unobservable {c.unobservable or 'none'}")
            if check is not None:
                line += (f"\n{'':21}side solve ({check.time_s:.1f} s): z "
                         f"{np.round(check.z, 1)}, position NEES {check.position_nees:.1f}, "
                         f"cost drop {check.cost_drop:.1f}, "
                         f"{'conclusive' if check.conclusive else 'inconclusive'}, "
                         f"{'suspect' if check.suspect else 'not suspect'}")
            print(line, flush=True)


if __name__ == "__main__":
    main()
