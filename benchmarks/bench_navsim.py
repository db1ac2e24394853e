"""Cost of one ``cdtm navsim`` case: simulate, batch smooth (+ Free), incremental as-arrived.

Run: ``python benchmarks/bench_navsim.py --altitude 1000 --resolution 1000``. Flies one
case of the paper's section VI.A (:mod:`cdtm_graph.studies.navsim`, default 300 s) after a short
warm-up (numba caches, imports), then ends with one line:
``frames=... simulate_s=... batch_s=... incremental_s=... total_s=... peak_mb=...``
"""

from __future__ import annotations

import argparse
import dataclasses
import resource
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cdtm_graph.studies.navsim import (  # noqa: E402
    QUICK_DURATION_S,
    Estimator,
    NavsimSettings,
    run_case,
)

#: The warm-up flight is this short (s): enough to compile and import everything.
WARMUP_DURATION_S = 10.0


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--altitude", type=float, default=1000.0, help="m")
    parser.add_argument("--resolution", type=int, default=1000, help="image side, px")
    parser.add_argument("--duration-s", type=float, default=NavsimSettings().duration_s)
    parser.add_argument("--quick", action="store_true",
                        help=f"a {QUICK_DURATION_S:g} s flight")
    args = parser.parse_args(argv)
    duration = QUICK_DURATION_S if args.quick else args.duration_s
    settings = NavsimSettings(duration_s=duration)

    run_case(dataclasses.replace(settings, duration_s=WARMUP_DURATION_S), args.altitude,
             args.resolution)
    case = run_case(settings, args.altitude, args.resolution)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    for estimator in Estimator:
        errors = " ".join(f"{v:8.1f}" for v in case.max_error_m(estimator))
        print(f"{estimator.value:26} max |error| x y z: {errors} m")
    t = case.timings_s
    print(f"frames={case.frames} simulate_s={t['simulate']:.2f} batch_s={t['batch']:.2f} "
          f"incremental_s={t['incremental']:.2f} total_s={sum(t.values()):.2f} "
          f"peak_mb={peak_mb:.0f}")


if __name__ == "__main__":
    main()
