"""Start-up time of the ``cdtm`` command line: whole processes, as a user waits for them.

Times ``python -m cdtm_graph smooth --help`` (the parser of the heaviest command) and
``python -m cdtm_graph --version`` (the interpreter and the package's ``__init__``: the
floor; 7cb9496 has no ``--version`` and answers it with a usage error, exit 2, from the
same top-level parser), best of ``--repeats`` each, every process fresh (``PYTHONPATH``
the checkout).
With ``--ref DIR`` (e.g. ``/work/wt-old``, commit 7cb9496) the same commands of that
checkout run interleaved with this one's (A B A B ...), so the machine's drift hits both
alike. ``--real`` adds a short real command: ``simulate`` of a 4-frame flight into a
temporary directory (best of the repeats, which also warms the numba cache on the first).

Run: ``python benchmarks/bench_startup.py [--repeats 5] [--ref /work/wt-old] [--real]``;
prints one line per command and checkout (best and median, s) and the load average.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: The commands timed: name -> the arguments after ``python -m cdtm_graph``.
COMMANDS = {"smooth --help": ["smooth", "--help"], "--version": ["--version"]}
#: ``--real``: a short real command (its output directory appended, new each time).
REAL = ("simulate", ["simulate", "--frames", "4", "--features", "20"])


def run_once(checkout: Path, args: list[str]) -> float:
    """Wall seconds of one fresh ``python -m cdtm_graph ARGS`` of ``checkout``."""
    env = {**os.environ, "PYTHONPATH": str(checkout)}
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "cdtm_graph", *args], cwd=checkout, env=env,
                          stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    elapsed = time.perf_counter() - start
    if done.returncode not in (0, 3) and not (args == ["--version"] and done.returncode == 2):
        # (7cb9496 has no --version: its usage error parses the same top-level parser)
        raise SystemExit(f"{checkout}: cdtm {' '.join(args)}: exit {done.returncode}: "
                         f"{done.stderr.strip()[-300:]}")
    return elapsed


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5, help="runs per command and checkout")
    parser.add_argument("--ref", type=Path, help="another checkout, timed interleaved")
    parser.add_argument("--real", action="store_true", help=f"also time `cdtm {REAL[0]}` (short)")
    args = parser.parse_args()
    checkouts = {"this": ROOT} | ({"ref": args.ref.resolve()} if args.ref else {})
    commands = dict(COMMANDS)
    times: dict[tuple[str, str], list[float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.repeats):
            for label, checkout in checkouts.items():
                if args.real:
                    out = Path(tmp) / f"{label}-{i}"
                    commands[REAL[0]] = [*REAL[1][:1], str(out), *REAL[1][1:]]
                for name, cmd in commands.items():
                    times.setdefault((name, label), []).append(run_once(checkout, cmd))
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}; "
          f"{os.cpu_count()} cores; best of {args.repeats} (median)")
    for name in commands:
        parts = []
        for label, checkout in checkouts.items():
            t = times[(name, label)]
            parts.append(f"{label} ({checkout}) {min(t):.3f} s ({statistics.median(t):.3f})")
        ratio = ""
        if args.ref:
            ratio = f"; this/ref {min(times[(name, 'this')]) / min(times[(name, 'ref')]):.2f}"
        print(f"cdtm {name}: " + "; ".join(parts) + ratio)
    return 0


if __name__ == "__main__":
    sys.exit(main())
