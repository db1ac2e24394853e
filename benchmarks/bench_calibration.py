"""What the calibration check and the online calibration cost: run times side by side.

Run: ``python benchmarks/bench_calibration.py [--frames 90] [--repeats 3] [--seed 1]``.
The issue's clean flight (``studies.robustness.BASE``: 1 fps, 150 m/s at 1800 m, 150
features), smoothed ``--repeats`` times, interleaved so the machine's drift hits every
variant alike, with the calibration

- ``held``: flight.yaml's as exact, unchecked (``--calibration held``);
- ``checked``: held and checked in a batch side solve (the default);
- ``online``: estimated in the batch (``--calibration online``);

in batch, and held / checked in iSAM2 and the fixed lag (10 s). Prints each variant's
median run time, its ratio to ``held``, the side solve's median time, and the 3-D RMSE
and position ANEES. Ends with one line ``checked_over_held=... online_over_held=...``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from interleaved import interleaved  # noqa: E402 (benchmarks/)

from cdtm_graph.graph import GraphSettings  # noqa: E402
from cdtm_graph.smoother import SmootherMode, SmootherSettings  # noqa: E402
from cdtm_graph.studies.robustness import BASE, SCENARIOS  # noqa: E402
from cdtm_graph.verdict.evaluation import trajectory_errors  # noqa: E402


def variants() -> dict[str, SmootherSettings]:
    checked = SmootherSettings()
    held = dataclasses.replace(checked, graph=GraphSettings(calibration=None))
    online = dataclasses.replace(checked, graph=GraphSettings(calibration_online=True))
    out = {"batch held": held, "batch checked": checked, "batch online": online}
    for mode, lag in (("isam2", None), ("fixed_lag", 10.0)):
        for name, base in (("held", held), ("checked", checked)):
            out[f"{mode} {name}"] = dataclasses.replace(base, mode=SmootherMode.INCREMENTAL,
                                                        lag_s=lag)
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=BASE.frames)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=BASE.seed)
    args = parser.parse_args(argv)
    flight, dtm = SCENARIOS["clean"].flight(dataclasses.replace(BASE, frames=args.frames,
                                                                seed=args.seed))
    runs = variants()
    timed = interleaved(flight, dtm, runs, args.repeats)
    times = timed.times_s
    # the side solve's time, of the last run of each variant that checks
    side = {name: [r.calibration_check.time_s] if r.calibration_check is not None else []
            for name, r in timed.last.items()}
    errors = {name: trajectory_errors(r.estimate, r.covariances, flight.groundtruth)
              for name, r in timed.last.items()}
    print(f"{args.frames} frames, seed {args.seed}, {args.repeats} interleaved runs")
    print(f"{'variant':18} {'median_s':>9} {'/held':>6} {'side_s':>7} {'rmse_3d_m':>10} "
          f"{'anees':>6}")
    median = {name: float(np.median(t)) for name, t in times.items()}
    for name in runs:
        held = median[name.split()[0] + " held"]
        side_s = f"{np.median(side[name]):7.2f}" if side[name] else f"{'-':>7}"
        e = errors[name]
        print(f"{name:18} {median[name]:9.2f} {median[name] / held:6.2f} {side_s} "
              f"{e.rmse_position_3d_m:10.2f} {e.anees_position:6.2f}")
    held = median["batch held"]
    print(f"checked_over_held={median['batch checked'] / held:.2f} "
          f"online_over_held={median['batch online'] / held:.2f} "
          f"isam2_checked_over_held={median['isam2 checked'] / median['isam2 held']:.2f} "
          f"fixedlag_checked_over_held="
          f"{median['fixed_lag checked'] / median['fixed_lag held']:.2f}")


if __name__ == "__main__":
    main()
