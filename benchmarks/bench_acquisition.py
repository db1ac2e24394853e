"""Speed of :func:`cdtm_graph.robust.acquisition.acquire` on the issue's flight.

Scenario: 1 fps, 150 m/s at 1800 m, 150 features, 640x480, 60 deg FOV, 300 m fractal
relief (12 km cell), 30 m DTM; the first 6 frames dead-reckoned from a prior 1000 m and
3 deg off with a matching sigma (search: +-3000 m, +-9 deg).

Run ``python benchmarks/bench_acquisition.py [--repeats 7] [--window 6]``; it prints the
median wall time of a search and where it goes (one profiled run: the heading profile's
triangulations, the terrain correlation, the C-DTM refinement of the modes).
"""

from __future__ import annotations

import argparse
import cProfile
import dataclasses
import pstats
import sys
import time

import numpy as np

from cdtm_graph.robust.acquisition import AcquisitionSettings, acquire, dead_reckoned_window
from cdtm_graph.studies.robustness import BASE, SCENARIOS

STAGES = {"make_cloud": "point clouds (heading profile and searched headings)",
          "best_over_headings": "terrain correlation over the offsets",
          "refine": "C-DTM refinement of the modes"}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--window", type=int, default=6)
    args = parser.parse_args(argv)
    settings = dataclasses.replace(BASE, frames=args.window, terrain_cell_m=12000.0,
                                   **SCENARIOS["far1000"].simulation)
    log, dtm = SCENARIOS["clean"].flight(settings)
    frames, prior = dead_reckoned_window(log, args.window)
    search = AcquisitionSettings()
    result = acquire(frames, log.config.camera, dtm, prior, search)  # numba compiles here
    times = []
    for _ in range(args.repeats):
        start = time.perf_counter()
        result = acquire(frames, log.config.camera, dtm, prior, search)
        times.append(time.perf_counter() - start)
    r = result.searched
    print(f"verdict={result.verdict.value} offsets_per_heading={r.n_offsets} "
          f"headings={len(r.search_headings_deg)} tracks={r.n_tracks} "
          f"features={r.n_features} modes={len(result.hypotheses)}")
    print(f"acquire_median_s={np.median(times):.3f} min_s={np.min(times):.3f} "
          f"max_s={np.max(times):.3f}")
    profile = cProfile.Profile()
    profile.runcall(acquire, frames, log.config.camera, dtm, prior, search)
    stats = pstats.Stats(profile).stats  # type: ignore[attr-defined]
    total = sum(v[3] for (_, _, name), v in stats.items() if name == "acquire")
    for (_, _, name), (_, _, _, cumulative, _) in sorted(stats.items()):
        if name in STAGES:
            print(f"  {STAGES[name]}: {cumulative:.3f} s of {total:.3f} s (profiled)")


if __name__ == "__main__":
    main(sys.argv[1:])
