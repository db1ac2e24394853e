"""What the robust defaults cost on a clean log: batch time and accuracy, side by side.

Run: ``python benchmarks/bench_robust.py [--frames 300] [--repeats 3]``. One clean
simulated flight (a nav.csv INS solution as the batch's initial guess, as in
bench_smoother.py), smoothed in turn, ``--repeats`` times interleaved so the machine's
drift hits every variant alike, with:

- ``defaults``: every defence on (Cauchy kernel, epipolar check, grazing rays, track tests
  against the DTM, clutter, fix acquisition) and flight.yaml's calibration checked by a
  side solve after the run (issue 10's ``calibration_suspect``);
- ``held``: the same, the calibration held unchecked (``--calibration held``): the robust
  defaults alone;
- ``robust none``: ``held`` without the kernel (``--robust none``);
- ``bare``: no defence and no check (the estimator before the robustness work).

Prints each variant's median batch time, its ratio to ``robust none`` and to ``bare``,
and its 3-D RMSE and position ANEES; then each variant's fixed-lag (10 s) median update
from frame 100 on (the calibration check runs after a run, never in an update). Ends with
one line ``held_over_robust_none=... held_over_bare=... check_over_held=...
fixedlag_held_over_bare=...``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from interleaved import interleaved  # noqa: E402 (benchmarks/)

from cdtm_graph.evaluation import trajectory_errors  # noqa: E402
from cdtm_graph.sim.simulate import SimulationSettings, simulate_flight  # noqa: E402
from cdtm_graph.smoother import SmootherMode, SmootherSettings  # noqa: E402
from cdtm_graph.smoother.incremental import IncrementalSmoother  # noqa: E402
from factors import RobustKernel  # noqa: E402


def variants() -> dict[str, SmootherSettings]:
    defaults = SmootherSettings()
    held = dataclasses.replace(defaults, graph=dataclasses.replace(defaults.graph,
                                                                   calibration=None))
    bare_graph = dataclasses.replace(held.graph, robust=RobustKernel.NONE, epipolar=None,
                                     grazing_turn_cells=None, mismatch=None, clutter=None)
    return {
        "defaults": defaults,
        "held": held,
        "robust none": dataclasses.replace(
            held, graph=dataclasses.replace(held.graph, robust=RobustKernel.NONE)),
        "bare": dataclasses.replace(held, graph=bare_graph, acquisition=None),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--fps", type=float, default=2.0)
    parser.add_argument("--features", type=int, default=170)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    flight, dtm = simulate_flight(SimulationSettings(
        frames=args.frames, fps=args.fps, n_features=args.features, seed=args.seed,
        nav="noisy_truth"))
    runs = variants()
    timed = interleaved(flight, dtm, runs, args.repeats)
    times = timed.times_s
    errors = {name: trajectory_errors(r.estimate, r.covariances, flight.groundtruth)
              for name, r in timed.last.items()}
    base_none = float(np.median(times["robust none"]))
    base_bare = float(np.median(times["bare"]))
    print(f"{args.frames} frames, {args.features} features, {args.repeats} interleaved runs")
    print(f"{'variant':12} {'median_s':>9} {'/none':>6} {'/bare':>6} {'rmse_3d_m':>10} "
          f"{'anees':>6}")
    for name in runs:
        t = float(np.median(times[name]))
        e = errors[name]
        print(f"{name:12} {t:9.2f} {t / base_none:6.2f} {t / base_bare:6.2f} "
              f"{e.rmse_position_3d_m:10.2f} {e.anees_position:6.2f}")
    lag_ms = {}
    for name, settings in runs.items():
        if name == "defaults":
            continue  # the same updates as "held"
        lag = dataclasses.replace(settings, mode=SmootherMode.INCREMENTAL, lag_s=10.0)
        smoother = IncrementalSmoother(flight.config, dtm, lag, imu=flight.imu,
                                       frame_interval_s=1.0 / args.fps)
        smoother.run(flight)
        lag_ms[name] = 1e3 * float(np.median(smoother.update_times_s[100:]))
        print(f"fixed lag 10 s, {name:12} median update {lag_ms[name]:.2f} ms")
    t = float(np.median(times["held"]))
    print(f"held_over_robust_none={t / base_none:.2f} held_over_bare={t / base_bare:.2f} "
          f"check_over_held={float(np.median(times['defaults'])) / t:.2f} "
          f"fixedlag_held_over_bare={lag_ms['held'] / lag_ms['bare']:.2f}")


if __name__ == "__main__":
    main()
