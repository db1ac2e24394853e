"""How far off the initial fix the existing smoothers still converge from (acquisition's pull-in).

For each seed the issue's flight is simulated once; its initial-state prior is then
replaced by the truth moved ``offset`` metres horizontally (direction -35 deg, as the
robustness scenarios) and turned ``heading`` degrees about the body z axis, with a
matching prior (sigma_position = max(offset / k, 50 m), sigma_attitude = max(heading / k,
1 deg), the error at k sigma). Each mode smooths it; a run is *pulled in* when its 3-D
position RMSE is at most 1.5x that of the same flight under its own 50 m prior and its
position ANEES at most 6.

Run: ``python scripts/pull_in.py [--offsets 50 100 ...] [--headings 0 1 3] [--seeds 1 2]
[--frames 90] [--k 1]``
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys

import numpy as np

from cdtm_graph.errors import CdtmError
from cdtm_graph.geometry import quat_wxyz_to_rotation, rotation_to_quat_wxyz, so3_exp
from cdtm_graph.run import smooth_and_evaluate
from cdtm_graph.sim.simulate import simulate
from cdtm_graph.smoother import SmootherSettings
from cdtm_graph.studies.robustness import BASE, Mode


def with_initial_error(log, offset_m: float, heading_deg: float, k_sigma: float):
    """The log with its prior mean at the truth moved by this error, sigmas to match."""
    gt = log.groundtruth
    i0 = int(np.searchsorted(gt.t_ns, log.frames.t_ns[0]))
    angle = math.radians(-35.0)
    position = gt.position_m[i0] + offset_m * np.array([math.cos(angle), math.sin(angle), 0.0])
    R = quat_wxyz_to_rotation(gt.quaternion_wxyz[i0]) @ so3_exp(
        np.array([0.0, 0.0, math.radians(heading_deg)]))
    init = dataclasses.replace(
        log.config.initial_state, position_m=position, quaternion_wxyz=rotation_to_quat_wxyz(R),
        sigma_position_m=max(offset_m / k_sigma, 50.0),
        sigma_attitude_deg=max(heading_deg / k_sigma, 1.0))
    return dataclasses.replace(log, config=dataclasses.replace(log.config, initial_state=init))


def run(log, dtm, mode: Mode) -> tuple[float, float]:
    try:
        out = smooth_and_evaluate(log, dtm, mode.settings(SmootherSettings()))
    except CdtmError:
        return float("nan"), float("nan")
    e = out.errors
    assert e is not None
    return float(e.rmse_position_3d_m), float(e.anees_position or np.nan)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--offsets", type=float, nargs="+",
                        default=[25, 50, 100, 150, 200, 300, 450])
    parser.add_argument("--headings", type=float, nargs="+", default=[0.0, 1.0, 2.0, 3.0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--frames", type=int, default=BASE.frames)
    parser.add_argument("--k", type=float, default=1.0, help="the error is at k sigma")
    parser.add_argument("--modes", nargs="+", default=[m.value for m in Mode])
    args = parser.parse_args(argv)
    margin = max(400.0, 1.5 * max(args.offsets))
    print(f"{'seed':>4} {'offset_m':>8} {'head_deg':>8} {'mode':9} {'rmse3d':>8} "
          f"{'ref':>6} {'anees':>9} pulled_in", flush=True)
    for seed in args.seeds:
        sim = simulate(dataclasses.replace(BASE, frames=args.frames, seed=seed,
                                           region_margin_m=margin))
        log, dtm = sim.log, sim.dtm
        modes = [Mode(m) for m in args.modes]
        ref = {mode: run(log, dtm, mode)[0] for mode in modes}
        for offset in args.offsets:
            for heading in args.headings:
                faulty = with_initial_error(log, offset, heading, args.k)
                for mode in modes:
                    rmse, anees = run(faulty, dtm, mode)
                    ok = rmse <= 1.5 * ref[mode] and anees <= 6.0
                    print(f"{seed:4d} {offset:8.0f} {heading:8.1f} {mode.value:9} {rmse:8.2f} "
                          f"{ref[mode]:6.2f} {anees:9.2f} {'yes' if ok else 'no'}", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
