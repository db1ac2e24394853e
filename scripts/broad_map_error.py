"""The map's smooth error over kilometres (issue 21, build 4): each run's RMSE, ANEES,
verdict and the shape evidence the verdict's ``broad_map_error`` reads (its highest frame,
the map's tilt and curvature there over a kilometre, and the longest stretch above the
verdict's sustained bound, in km flown, as the verdict counts it:
``VerdictSettings.broad_map``'s, in every mode: a fixed lag's statistic is the one it took
as it went, ``map_error.BroadMapWatch``).

Run: ``python scripts/broad_map_error.py RUN...``, each RUN ``scenario/seed/mode[/frames]``:
a scenario of ``cdtm_graph.studies.robustness.SCENARIOS``, ``waves`` (3 m of waves,
40-200 m, laid out by the seed: ``scripts/detail_seeds.py``'s) or
``hill:HEIGHT_M,SIGMA_M,AT_S`` (a smooth hill the DTM lacks); mode batch, isam2 or
fixed_lag. E.g. ``python scripts/broad_map_error.py hill15/1/batch clean/1/fixed_lag
hill:10,700,30/1/batch``.
"""

from __future__ import annotations

import dataclasses
import sys

import numpy as np

from cdtm_graph.dtm import Dtm
from cdtm_graph.flightlog import FlightLog
from cdtm_graph.run import smooth_and_evaluate
from cdtm_graph.sim.faults import MismatchKind, TerrainMismatch
from cdtm_graph.sim.map_detail import DetailShape, MapDetail
from cdtm_graph.smoother import SmootherSettings
from cdtm_graph.studies.robustness import BASE, SCENARIOS, Mode, Scenario
from cdtm_graph.verdict import VerdictSettings
from cdtm_graph.verdict.rules import sustained_stretches


def flight(name: str, seed: int, frames: int) -> tuple[FlightLog, Dtm]:
    """The named scenario's flight (module docstring)."""
    base = dataclasses.replace(BASE, frames=frames, seed=seed)
    if name == "waves":
        detail = MapDetail(DetailShape.WAVES, 3.0, (40.0, 200.0), seed=seed)
        return SCENARIOS["clean"].flight(dataclasses.replace(base, map_detail=detail))
    if name.startswith("hill:"):
        height_m, sigma_m, at_s = (float(v) for v in name[5:].split(","))
        return Scenario(name, dict(terrain_mismatch=TerrainMismatch(
            MismatchKind.HILL, depth_m=height_m, radius_m=sigma_m, at_s=at_s))).flight(base)
    return SCENARIOS[name].flight(base)


def main(argv: list[str]) -> None:
    bounds = VerdictSettings().broad_map
    sustained = bounds.peak if bounds.sustained is None else bounds.sustained
    print("| run | mode | RMSE 3-D (m) | ANEES | shape evidence, highest (frame) | tilt, bend (m) "
          f"| above {sustained:g} (km flown) | verdict: reasons |\n"
          "|---|---|---|---|---|---|---|---|")
    for spec in argv:
        name, seed, mode, *rest = spec.split("/")
        log, dtm = flight(name, int(seed), int(rest[0]) if rest else BASE.frames)
        out = smooth_and_evaluate(log, dtm, Mode(mode).settings(SmootherSettings()))
        e = out.errors
        assert e is not None
        broad = out.result.broad_map_error
        stat = "- | - | -"
        if broad is not None and np.isfinite(broad.evidence).any():
            k = int(np.nanargmax(broad.evidence))
            longest_km = max((m for _, _, m in sustained_stretches(out.result, sustained)),
                             default=0.0) / 1000.0
            stat = (f"{broad.evidence[k]:.1f} ({k}) | {broad.tilt_m[k]:.1f}, "
                    f"{broad.bend_m[k]:.1f} | {longest_km:.2f}")
        reasons = ", ".join(f"{r.code} {r.first_frame}-{r.last_frame}"
                            for r in out.verdict.reasons)
        print(f"| {name}/{seed} | {mode} | {np.linalg.norm(e.rmse_position_m):.2f} | "
              f"{e.anees_position:.2f} | {stat} | {out.verdict.status.value}"
              f"{': ' + reasons if reasons else ''} |", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
