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
and its 3-D RMSE and position ANEES. Then the fixed lag (10 s) as a live system runs it
(``keep_exit_covariances=False``, as ``bench_smoother.py``): the median update from
frame ``--lag-from`` on, the defences taken off one step at a time (``held``; ``robust
none``; no track tests; no epipolar check or grazing test either; ``bare + gate``: no
kernel and no fix search either; ``bare``: no innovation gate either), each step's
share beside it; interleaved as the batch (the calibration check runs after a run, never
in an update). Ends with one line ``held_over_robust_none=... held_over_bare=...
check_over_held=... fixedlag_held_over_bare=... fixedlag_held_ms=... fixedlag_bare_ms=...``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from interleaved import interleaved  # noqa: E402 (benchmarks/)

from cdtm_graph.sim.simulate import SimulationSettings, simulate_flight  # noqa: E402
from cdtm_graph.smoother import SmootherMode, SmootherSettings, smooth  # noqa: E402
from cdtm_graph.verdict.evaluation import trajectory_errors  # noqa: E402
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
    parser.add_argument("--lag-from", type=int, default=100,
                        help="fixed-lag figures from this frame on")
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
    lag = lag_variants(runs["held"])
    lag_ms: dict[str, list[float]] = {name: [] for name in lag}
    for _ in range(args.repeats):  # interleaved, as the batch
        for name, settings in lag.items():
            result = smooth(flight, dtm, settings)
            lag_ms[name].append(1e3 * float(np.median(result.stats.update_times_s[args.lag_from:])))
    median_ms = {name: float(np.median(v)) for name, v in lag_ms.items()}
    print(f"fixed lag 10 s, live (no exit covariances), median update from frame "
          f"{args.lag_from}; each step takes one more defence off")
    print(f"{'variant':34} {'median_ms':>9} {'step_ms':>8} {'runs_ms':>20}")
    names = list(lag)
    for i, name in enumerate(names):
        step = median_ms[name] - median_ms[names[i + 1]] if i + 1 < len(names) else 0.0
        runs_ms = ", ".join(f"{v:.2f}" for v in lag_ms[name])
        print(f"{name:34} {median_ms[name]:9.2f} {step:8.2f} {runs_ms:>20}")
    t = float(np.median(times["held"]))
    held_ms, bare_ms = median_ms[names[0]], median_ms[names[-1]]
    print(f"held_over_robust_none={t / base_none:.2f} held_over_bare={t / base_bare:.2f} "
          f"check_over_held={float(np.median(times['defaults'])) / t:.2f} "
          f"fixedlag_held_over_bare={held_ms / bare_ms:.2f} fixedlag_held_ms={held_ms:.2f} "
          f"fixedlag_bare_ms={bare_ms:.2f}")


def lag_variants(held: SmootherSettings) -> dict[str, SmootherSettings]:
    """The fixed lag (10 s, live) with every defence, then one more taken off at each
    step: the track tests (and the clutter fit), the epipolar check and grazing test,
    the kernel and the fix search, the innovation gate."""
    live = dataclasses.replace(held, mode=SmootherMode.INCREMENTAL, lag_s=10.0,
                               keep_exit_covariances=False)
    steps = {
        "every defence (held)": {},
        "- track tests, clutter": dict(mismatch=None, clutter=None),
        "- epipolar check, grazing test": dict(epipolar=None, grazing_turn_cells=None),
        "- kernel, fix search (bare + gate)": dict(robust=RobustKernel.NONE),
        "- innovation gate (bare)": {},
    }
    out, graph = {}, live.graph
    for name, off in steps.items():
        graph = dataclasses.replace(graph, **off)
        live = dataclasses.replace(live, graph=graph)
        if name.startswith("- kernel"):
            live = dataclasses.replace(live, acquisition=None)
        if name.startswith("- innovation gate"):
            live = dataclasses.replace(live, innovation_gate=None)
        out[name] = live
    return out


if __name__ == "__main__":
    main()
