"""How much of a fixed-lag frame update is compiled work: the time inside numba kernels.

Run: ``python benchmarks/bench_kernels_in_run.py [--frames 600]``. The fixed lag (10 s,
live, ``bench_smoother.py``'s flight) with every defence, then bare (no defence, as
``bench_robust.py``'s last step); every numba kernel the package calls from Python is
timed where it is called, and each frame's kernel time is summed. Prints, per variant,
the median update, the median time in kernels, and the kernels taking the most of it.
What is neither kernel nor GTSAM is Python and numpy between them: what fusing steps
into fewer compiled passes could save, and no more. (Kernels that kernels call are
counted in their caller; the wrappers add ~1 us a call.)
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import importlib
import pkgutil
import sys
import time
from pathlib import Path

import numpy as np
from numba.core.registry import CPUDispatcher

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cdtm_graph  # noqa: E402
import factors  # noqa: E402
from cdtm_graph.sim.simulate import SimulationSettings, simulate_flight  # noqa: E402
from cdtm_graph.smoother import SmootherMode, SmootherSettings, smooth  # noqa: E402
from cdtm_graph.smoother.incremental import IncrementalSmoother  # noqa: E402
from factors import RobustKernel  # noqa: E402

FROM_FRAME = 200


def time_kernels(spent: dict[str, float]) -> None:
    """Every module's numba kernels replaced, where the module calls them, by a wrapper
    adding its time to ``spent`` (by kernel name)."""
    timed: dict[int, object] = {}
    for package in (cdtm_graph, factors):
        for info in pkgutil.walk_packages(package.__path__, package.__name__ + "."):
            if info.name.endswith("__main__") or any(
                    part in info.name for part in (".sim", ".studies", ".plots", ".cli")):
                continue
            module = importlib.import_module(info.name)
            for name, kernel in list(vars(module).items()):
                if isinstance(kernel, CPUDispatcher):
                    if id(kernel) not in timed:
                        timed[id(kernel)] = _timed(kernel, spent)
                    setattr(module, name, timed[id(kernel)])


def _timed(kernel: CPUDispatcher, spent: dict[str, float]):
    label = f"{kernel.py_func.__module__}.{kernel.py_func.__name__}"

    def call(*args, **kwargs):
        start = time.perf_counter()
        out = kernel(*args, **kwargs)
        spent[label] += time.perf_counter() - start
        return out

    return call


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--top", type=int, default=12)
    args = parser.parse_args(argv)
    flight, dtm = simulate_flight(SimulationSettings(
        frames=args.frames, fps=2.0, n_features=170, nav="noisy_truth", seed=5))
    live = SmootherSettings(mode=SmootherMode.INCREMENTAL, lag_s=10.0,
                            keep_exit_covariances=False)
    # every kernel compiled (or loaded from numba's cache) before the wrappers go in: a
    # kernel compiled later would find a wrapper, not a kernel, where it calls another
    smooth(flight, dtm, SmootherSettings(max_iterations=1))
    smooth(flight, dtm, live)

    spent: dict[str, float] = collections.defaultdict(float)
    time_kernels(spent)
    frames: list[dict[str, float]] = []
    add_frame = IncrementalSmoother.add_frame

    def timed_add_frame(self, *a, **k):
        spent.clear()
        start = time.perf_counter()
        out = add_frame(self, *a, **k)
        frames.append({**spent, "": time.perf_counter() - start})
        return out

    IncrementalSmoother.add_frame = timed_add_frame  # type: ignore[method-assign]
    bare = dataclasses.replace(live, acquisition=None, innovation_gate=None,
                               graph=dataclasses.replace(
                                   live.graph, robust=RobustKernel.NONE, epipolar=None,
                                   grazing_turn_cells=None, mismatch=None, clutter=None,
                                   calibration=None))
    for name, settings in (("every defence", live), ("bare", bare)):
        frames.clear()
        smooth(flight, dtm, settings)
        kept = frames[FROM_FRAME:]
        total = 1e3 * np.array([f[""] for f in kept])
        inside = 1e3 * np.array([sum(v for k, v in f.items() if k) for f in kept])
        print(f"{name}: median update {np.median(total):.2f} ms, in compiled kernels "
              f"{np.median(inside):.2f} ms (frames {FROM_FRAME}-{args.frames})")
        labels = {k for f in kept for k in f if k}
        rows = sorted(((1e3 * float(np.median([f.get(k, 0.0) for f in kept])), k)
                       for k in labels), reverse=True)
        for ms, label in rows[:args.top]:
            print(f"  {label:50} {ms:.3f} ms")


if __name__ == "__main__":
    main()
