"""Images -> tracks -> trajectory against the same flight smoothed from its ideal tracks.

For each seed: a rendered flight over relief (the paper's geometry: 1000 m above a 3x3 km
fractal cell of 300 m relief, 200 m/s, 60 deg FOV, 1 fps, 640x480; the images show the
true 5 m terrain, the log's DTM is it resampled to 30 m) is tracked with the default
:class:`~cdtm_graph.frontend.TrackerSettings` and smoothed; the same flight's ray-cast
tracks (``cdtm simulate``'s, 0.5 px noise) are the ideal baseline. Clean images, and
with +-10 % exposure jitter and 1 px of motion blur. Three smoother configurations:
the current defaults (``SmootherSettings()``), batch with a Cauchy kernel, incremental
with a 99.9 % innovation gate.

Run: ``python benchmarks/bench_images_to_trajectory.py [--seeds 0 1 2] [--frames 60]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cdtm_graph.frontend import track_log  # noqa: E402
from cdtm_graph.graph import GraphSettings  # noqa: E402
from cdtm_graph.run import smooth_and_evaluate  # noqa: E402
from cdtm_graph.sim.render import RenderSettings, render_flight  # noqa: E402
from cdtm_graph.sim.simulate import SimulationSettings, simulate  # noqa: E402
from cdtm_graph.smoother import SmootherMode, SmootherSettings  # noqa: E402
from factors import RobustKernel  # noqa: E402

CONFIGS = {
    "defaults": SmootherSettings(),
    "cauchy": SmootherSettings(graph=GraphSettings(robust=RobustKernel.CAUCHY)),
    "incremental_gate_0.999": SmootherSettings(mode=SmootherMode.INCREMENTAL,
                                               innovation_gate=0.999),
}
CONDITIONS = {
    "clean": {},
    "jitter_10pct_blur_1px": {"exposure_jitter": 0.1, "motion_blur_px": 1.0},
}


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--frames", type=int, default=60)
    args = parser.parse_args(argv)
    rows = []
    print(f"{'seed':>4} {'images':22} {'smoother':22} {'RMSE ideal':>10} {'RMSE images':>11} "
          f"{'ratio':>6} {'ANEES ideal':>11} {'ANEES images':>12}")
    for seed in args.seeds:
        result = simulate(SimulationSettings(frames=args.frames, resolution_px=(640, 480),
                                             seed=seed))
        logs = {}
        for condition, options in CONDITIONS.items():
            images = render_flight(result, RenderSettings(seed=seed, **options)).images
            logs[condition] = dataclasses.replace(result.log,
                                                  tracks=track_log(result.log,
                                                                   images=images).tracks)
        for name, settings in CONFIGS.items():
            ideal = smooth_and_evaluate(result.log, result.dtm, settings).errors
            for condition, log in logs.items():
                e = smooth_and_evaluate(log, result.dtm, settings).errors
                assert e is not None and ideal is not None
                row = {"seed": seed, "images": condition, "smoother": name,
                       "rmse_ideal_m": ideal.rmse_position_3d_m,
                       "rmse_images_m": e.rmse_position_3d_m,
                       "ratio": e.rmse_position_3d_m / ideal.rmse_position_3d_m,
                       "anees_position_ideal": ideal.anees_position,
                       "anees_position_images": e.anees_position}
                rows.append(row)
                print(f"{seed:4d} {condition:22} {name:22} {row['rmse_ideal_m']:10.2f} "
                      f"{row['rmse_images_m']:11.2f} {row['ratio']:6.2f} "
                      f"{row['anees_position_ideal']:11.2f} {row['anees_position_images']:12.2f}",
                      flush=True)
    for condition in CONDITIONS:
        for name in CONFIGS:
            sel = [r for r in rows if r["images"] == condition and r["smoother"] == name]
            ratios = np.array([r["ratio"] for r in sel])
            anees = np.array([r["anees_position_images"] for r in sel])
            print(f"{condition:22} {name:22} ratio {ratios.min():.2f}-{ratios.max():.2f}, "
                  f"position ANEES {anees.min():.2f}-{anees.max():.2f}")
    return rows


if __name__ == "__main__":
    main()
