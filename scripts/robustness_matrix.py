"""Print the scenario x mode table of :mod:`cdtm_graph.studies.robustness`.

Run: ``python scripts/robustness_matrix.py [SCENARIO ...] [--modes batch isam2 fixed_lag]
[--frames N] [--seed S]`` (default: every scenario, every mode, the issue's 90-frame flight).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

from cdtm_graph.studies.robustness import BASE, HEADER, SCENARIOS, Mode, run


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenarios", nargs="*", default=list(SCENARIOS))
    parser.add_argument("--modes", nargs="+", default=[m.value for m in Mode])
    parser.add_argument("--frames", type=int, default=BASE.frames)
    parser.add_argument("--seed", type=int, default=BASE.seed)
    args = parser.parse_args(argv)
    base = dataclasses.replace(BASE, frames=args.frames, seed=args.seed)
    print(HEADER, flush=True)
    for name in args.scenarios:
        flight, dtm = SCENARIOS[name].flight(base)
        for mode in args.modes:
            print(run(flight, dtm, name, Mode(mode)).row(), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
