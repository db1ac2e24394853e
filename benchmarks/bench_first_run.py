"""What the first `cdtm demo` after an install costs beside the second: numba's compilation.

Run: ``python benchmarks/bench_first_run.py [--repeats 2] [--kernels] [--images]
[--compile]``. Each repeat runs ``python -m cdtm_graph demo --out TMP/out`` twice in fresh
processes with one new, empty ``NUMBA_CACHE_DIR`` (as a fresh install has: nothing
compiled), so the first run loads every kernel it calls from the package's prebuilt copies
(:mod:`factors.jit`), or compiles those it has none of, and the second loads them from
numba's cache or the prebuilt copies. Prints each pair's wall times (s) and their ratio,
then the medians; issue 22 asks for first/second <= 2. ``--compile``: the prebuilt kernels
off (``CDTM_COMPILE_KERNELS=1``), so the first run compiles every kernel it calls: what a
platform without prebuilt kernels pays (another Python, numba or CPU architecture).

``--kernels``: the first run also lists what it compiled, from numba's ``numba:compile``
events (the ones ``cdtm_graph/cli/compiling.py`` announces): per kernel the CPU time spent
compiling it alone (kernels it calls and compiles on the way are counted in theirs; CPU
time: what a loaded machine inflates least), and how many signatures (argument types) it
was compiled for, the signatures beside it.
``--images``: ``cdtm demo --images`` instead (render, track, smooth).

This compares the first run with the second on this checkout; to compare two checkouts,
run it in each in turn (``cd OTHER && python benchmarks/bench_first_run.py``: the script
runs the package beside it).
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from factors.jit import COMPILE_ALL  # noqa: E402  (the checkout beside this file)

# Run inside the child with --kernels: the demo under a listener of numba's compile events.
_PROFILED = r"""
import collections, json, sys, time
from numba.core import event
from cdtm_graph.cli import main

stack, spent, signatures = [], collections.Counter(), collections.defaultdict(list)

class Listener(event.Listener):
    def on_start(self, ev):
        stack.append([ev.data["dispatcher"], time.process_time(), 0.0])
    def on_end(self, ev):
        dispatcher, started, nested = stack.pop()
        total = time.process_time() - started
        name = f"{dispatcher.py_func.__module__}.{dispatcher.py_func.__qualname__}"
        spent[name] += total - nested
        signatures[name].append(", ".join(str(a) for a in ev.data["args"]))
        if stack:
            stack[-1][2] += total

event.register("numba:compile", Listener())
code = main(sys.argv[1:])
json.dump({"spent_s": spent, "signatures": signatures}, open(sys.argv[0], "w"))
sys.exit(code)
"""


def run_demo(out: Path, cache: Path, images: bool, profile: Path | None, compile_all: bool
             ) -> tuple[float, float]:
    """One ``cdtm demo`` in a fresh process with numba's cache in ``cache``: its wall time
    and its CPU time (user + system, s; what a loaded machine does not inflate)."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache),
           "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    env.pop(COMPILE_ALL, None)
    if compile_all:
        env[COMPILE_ALL] = "1"
    demo = ["demo", "--out", str(out)] + (["--images"] if images else [])
    if profile is None:
        command = [sys.executable, "-m", "cdtm_graph", *demo]
    else:
        command = [sys.executable, "-c", _PROFILED.replace("sys.argv[0]", repr(str(profile))),
                   *demo]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run(command, env=env, cwd=out.parent, stdout=subprocess.DEVNULL,
                          stderr=subprocess.PIPE, text=True)
    elapsed = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode not in (0, 3):
        sys.exit(f"cdtm demo failed ({done.returncode}):\n{done.stderr}")
    return elapsed, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def print_kernels(profile: Path) -> None:
    import json

    data = json.loads(profile.read_text())
    spent, signatures = data["spent_s"], data["signatures"]
    print(f"compiled {sum(len(s) for s in signatures.values())} signatures of "
          f"{len(signatures)} kernels in {sum(spent.values()):.1f} s of CPU:")
    for name, seconds in sorted(spent.items(), key=lambda item: -item[1]):
        sigs = signatures[name]
        print(f"  {seconds:6.2f} s  {len(sigs)}x  {name}")
        for sig in sigs if len(sigs) > 1 else ():
            print(f"                   ({sig})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--kernels", action="store_true",
                        help="list what the first run compiled (first repeat)")
    parser.add_argument("--images", action="store_true", help="cdtm demo --images")
    parser.add_argument("--compile", action="store_true",
                        help="the prebuilt kernels off: the first run compiles them")
    args = parser.parse_args()
    first: list[tuple[float, float]] = []
    second: list[tuple[float, float]] = []
    for repeat in range(args.repeats):
        with tempfile.TemporaryDirectory(prefix="cdtm-first-run-") as tmp:
            cache = Path(tmp) / "numba-cache"
            cache.mkdir()
            profile = Path(tmp) / "kernels.json" if args.kernels and repeat == 0 else None
            first.append(run_demo(Path(tmp) / "out", cache, args.images, profile, args.compile))
            second.append(run_demo(Path(tmp) / "out", cache, args.images, None, args.compile))
            (wall_1, cpu_1), (wall_2, cpu_2) = first[-1], second[-1]
            print(f"first {wall_1:.1f} s (CPU {cpu_1:.1f} s), second {wall_2:.1f} s "
                  f"(CPU {cpu_2:.1f} s): ratio {wall_1 / wall_2:.2f} (CPU {cpu_1 / cpu_2:.2f})",
                  flush=True)
            if profile is not None:
                print_kernels(profile)
    def median(values: list[float]) -> float:
        return statistics.median(values)

    print(f"median: first {median([w for w, _ in first]):.1f} s (CPU "
          f"{median([c for _, c in first]):.1f} s), second {median([w for w, _ in second]):.1f} s "
          f"(CPU {median([c for _, c in second]):.1f} s), ratio "
          f"{median([a[0] / b[0] for a, b in zip(first, second)]):.2f} (CPU "
          f"{median([a[1] / b[1] for a, b in zip(first, second)]):.2f}); "
          f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
