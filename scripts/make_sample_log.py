"""Regenerate ``cdtm_graph/data/sample_flight``: the small flight log of ``cdtm demo``, tests.

The paper's section VI.A flight, shortened: 40 frames at 1 fps (39 s), 1000 m above a
cloned 3x3 km fractal cell with 300 m of relief, 200 m/s, a 60 degree 400x400 camera,
120 features per frame pair (the paper used 100 and 120), a 30 m DTM (sigma_h 2.4 m),
IMU at 200 Hz with flight.yaml's noise. Ground truth at 10 Hz (plus the frame times)
keeps the log under 2 MB. Deterministic: the same seed gives the same log.

Usage::

    python scripts/make_sample_log.py [OUT]     # default: cdtm_graph/data/sample_flight
"""

from __future__ import annotations

import sys
from pathlib import Path

from cdtm_graph.sim.simulate import SimulationSettings, write_simulated_log

REPO = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO / "cdtm_graph" / "data" / "sample_flight"

SAMPLE_SETTINGS = SimulationSettings(
    frames=40,
    fps=1.0,
    altitude_m=1000.0,
    speed_mps=200.0,
    n_features=120,
    relief_m=300.0,
    dtm_spacing_m=30.0,
    groundtruth_rate_hz=10.0,
    seed=20240601,
)


def make_sample_log(out: str | Path = DEFAULT_OUT) -> Path:
    """Write the sample log to ``out`` (replacing an older one) and return its directory."""
    return write_simulated_log(SAMPLE_SETTINGS, out)


if __name__ == "__main__":
    target = make_sample_log(sys.argv[1] if len(sys.argv) > 1 else DEFAULT_OUT)
    size = sum(f.stat().st_size for f in target.iterdir())
    print(f"wrote {target} ({size / 1e6:.2f} MB)")
