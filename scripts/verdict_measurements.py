"""Print what the verdict's rules test, per simulated flight: the measurements behind the
thresholds of :class:`cdtm_graph.verdict.rules.VerdictSettings` (docs/verdict.md).

Run: ``python scripts/verdict_measurements.py [SCENARIO ...] [--seeds 1 2 3] [--frames N]
[--modes batch fixed_lag isam2]`` (default: every scenario below and of the robustness
matrix, seed 1, the issue's 90-frame flight, batch). One line per flight:

    verdict (with ground truth) / blind (without), 3-D RMSE, position ANEES, share of
    frames inside the chi-square(3) 95% bound, map-mismatch share over the run and its
    largest 10 s window share, the largest window share of the other rejections,
    flatness (horizontal over height information of the C-DTM fix: min and median over
    the windows), the smallest attitude-free share, the fewest features in a frame, the
    residual chi-square over its expectation (run, and the windows' range), the share
    of outliers, the innovations' median (incremental), and the reasons' codes.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

import numpy as np

from cdtm_graph.flightlog import FlightLog
from cdtm_graph.run import smooth_and_evaluate
from cdtm_graph.smoother import SmootherSettings
from cdtm_graph.studies.robustness import BASE, SCENARIOS, Mode, Scenario
from cdtm_graph.verdict.rules import (
    VerdictSettings,
    assess,
    fix_geometry,
    unit_height_information,
    window_half_width,
    window_information,
    window_sum,
)


def _pixel_sigma(scale: float):
    """flight.yaml states ``scale`` times the simulated pixel noise."""
    def fault(log: FlightLog, rng: np.random.Generator) -> FlightLog:
        camera = dataclasses.replace(log.config.camera,
                                     pixel_sigma_px=log.config.camera.pixel_sigma_px * scale)
        return dataclasses.replace(log, config=dataclasses.replace(log.config, camera=camera))
    return fault


#: Flights beside the robustness matrix's: weak geometries and a misstated noise model.
EXTRA: dict[str, Scenario] = {s.name: s for s in (
    Scenario("few15", dict(n_features=15)),
    Scenario("few30", dict(n_features=30)),
    Scenario("few60", dict(n_features=60)),
    Scenario("relief0", dict(relief_m=0.0)),
    Scenario("relief20", dict(relief_m=20.0)),
    Scenario("relief50", dict(relief_m=50.0)),
    Scenario("relief100", dict(relief_m=100.0)),
    Scenario("fov20", dict(fov_deg=20.0)),
    Scenario("sigma_half", fault=_pixel_sigma(0.5)),
    Scenario("sigma_x3", fault=_pixel_sigma(3.0)),
)}


def measure(scenario: Scenario, seed: int, frames: int, mode: Mode) -> str:
    base = dataclasses.replace(BASE, frames=frames, seed=seed)
    flight, dtm = scenario.flight(base)
    out = smooth_and_evaluate(flight, dtm, mode.settings(SmootherSettings()))
    result, errors, verdict = out.result, out.errors, out.verdict
    blind = assess(result, None, flight.imu.t_ns)
    counts = result.counts
    settings = VerdictSettings()
    half = window_half_width(result.estimate.t_ns, settings.window_s)
    rejected = {r: np.asarray(v, dtype=float) for r, v in counts.rejected_per_frame.items()
                if r != "too_old"}
    offered = np.asarray(counts.features_per_frame, dtype=float) + sum(
        rejected.values(), np.zeros(len(result.estimate)))
    window_offered = np.maximum(window_sum(offered, half), 1.0)
    mismatch = rejected.get("map_mismatch", np.zeros_like(offered))
    others = sum((v for r, v in rejected.items()
                  if r not in ("map_mismatch", "missed_dtm")), np.zeros_like(offered))
    geometry = fix_geometry(window_information(
        unit_height_information(np.asarray(result.cdtm_information)),
        result.estimate.position_m, half))
    checks = verdict.self_checks
    window_chi2 = checks.residual_chi2_per_window[1:]
    consistency = errors.position_consistency if errors is not None else None
    codes = sorted({r.code for r in verdict.reasons})
    return (f"{scenario.name:11} s{seed:<2} {mode.value:9} {verdict.status.value:8} "
            f"blind={blind.status.value:8} rmse3={errors.rmse_position_3d_m:7.2f} "
            f"anees={errors.anees_position:7.2f} inside={consistency.inside_fraction:.2f} "
            f"mm_run={mismatch.sum() / max(offered.sum(), 1):.3f} "
            f"mm_win={np.max(window_sum(mismatch, half)[1:] / window_offered[1:]):.3f} "
            f"other_win={np.max(window_sum(others, half)[1:] / window_offered[1:]):.3f} "
            f"flat_min={np.nanmin(geometry.flatness[1:]):.2g} "
            f"flat_med={np.nanmedian(geometry.flatness[1:]):.2g} "
            f"free_min={np.nanmin(geometry.attitude_free_fraction[1:]):.3f} "
            f"feat_min={int(np.min(counts.features_per_frame[1:]))} "
            f"chi2={checks.residual_chi2:.3f} "
            f"chi2_win=[{np.nanmin(window_chi2):.2f},{np.nanmax(window_chi2):.2f}] "
            f"out={checks.outlier_fraction:.4f} nis={checks.innovation_nis_median:.2f} "
            f"{' '.join(codes)}")


def main(argv: list[str] | None = None) -> None:
    scenarios = {**SCENARIOS, **EXTRA}
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenarios", nargs="*", default=[n for n in scenarios
                                                         if n != "dtm_elsewhere"])
    parser.add_argument("--seeds", type=int, nargs="+", default=[BASE.seed])
    parser.add_argument("--frames", type=int, default=BASE.frames)
    parser.add_argument("--modes", nargs="+", default=[Mode.BATCH.value])
    args = parser.parse_args(argv)
    for seed in args.seeds:
        for name in args.scenarios:
            for mode in args.modes:
                print(measure(scenarios[name], seed, args.frames, Mode(mode)), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
