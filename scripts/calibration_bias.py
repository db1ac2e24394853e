"""The online calibration's bias on clean flights: each part's z-score (estimate over its
posterior sigma, the truth being zero) over seeds, with the noise's bias taken out
(``cdtm_graph.calibration.noise_bias``) or, with ``--uncorrected``, left in.

Run: ``python scripts/calibration_bias.py [--frames N] [--seeds A B] [--uncorrected]``
(default: the issue's camera and flight, 30 frames, seeds 1-12, corrected).
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

import cdtm_graph.smoother.batch as batch
from cdtm_graph.graph import DEFAULT_CALIBRATION_SIGMAS, GraphSettings
from cdtm_graph.run import smooth_and_evaluate
from cdtm_graph.smoother import SmootherSettings
from cdtm_graph.studies.robustness import BASE, SCENARIOS


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--seeds", type=int, nargs=2, default=(1, 12), metavar=("FIRST", "LAST"))
    parser.add_argument("--uncorrected", action="store_true",
                        help="leave the noise's bias in (the estimate before the fix)")
    args = parser.parse_args(argv)
    if args.uncorrected:
        batch.debiased = lambda graph, values, factors, **_: (values, [])  # type: ignore[assignment]
    online = SmootherSettings(graph=GraphSettings(calibration=DEFAULT_CALIBRATION_SIGMAS,
                                                  calibration_online=True))
    rows = []
    for seed in range(args.seeds[0], args.seeds[1] + 1):
        flight, dtm = SCENARIOS["clean"].flight(dataclasses.replace(BASE, frames=args.frames,
                                                                    seed=seed))
        out = smooth_and_evaluate(flight, dtm, online)
        c, e = out.result.calibration, out.errors
        assert c is not None and e is not None
        value = np.r_[c.time_offset_correction_s, c.mount_correction_deg, c.focal_scale - 1]
        rows.append(value / c.sigmas)
        print(f"seed {seed:3d}  rmse_3d {np.linalg.norm(e.rmse_position_m):5.2f} m  anees "
              f"{e.anees_position:5.2f}  {out.verdict.status.value:8}  focal scale "
              f"{c.focal_scale:.5f}  z [dt, mount x y z, focal] {np.round(rows[-1], 2)}",
              flush=True)
    z = np.array(rows)
    print(f"mean z {np.round(z.mean(axis=0), 2)}  (standard error "
          f"{np.round(z.std(axis=0) / np.sqrt(len(z)), 2)})  rms z "
          f"{np.round(np.sqrt((z ** 2).mean(axis=0)), 2)}")


if __name__ == "__main__":
    main()
