"""Regenerate ``cdtm_graph/data/sample_images``: a tiny rendered flight (README, tests).

Four frames of the paper's geometry (1000 m, 200 m/s, 60 deg FOV, 1 fps) at 320x240, the
images rendered from the true terrain (which differs from the log's 30 m DTM), and no
tracks.csv: ``cdtm track`` (or ``cdtm_graph.frontend.track_log``) makes it. Deterministic.

Usage::

    python scripts/make_sample_images.py [OUT]     # default: cdtm_graph/data/sample_images
"""

from __future__ import annotations

import sys
from pathlib import Path

from cdtm_graph.atomic import atomic_output_dir
from cdtm_graph.flightlog import TRACKS_CSV
from cdtm_graph.sim.render import RenderSettings, render_flight
from cdtm_graph.sim.simulate import WRITER, SimulationSettings, simulate, write_simulation_files

REPO = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO / "cdtm_graph" / "data" / "sample_images"

SAMPLE_SETTINGS = SimulationSettings(frames=4, resolution_px=(320, 240), n_features=60,
                                     groundtruth_rate_hz=10.0, seed=20261123)


def make_sample_images(out: str | Path = DEFAULT_OUT) -> Path:
    """Write the image log to ``out`` (replacing an older one) and return its directory."""
    result = simulate(SAMPLE_SETTINGS)
    images = render_flight(result, RenderSettings()).images
    with atomic_output_dir(out, writer=WRITER) as staging:
        write_simulation_files(result, staging, out, images)
        (staging / TRACKS_CSV).unlink()  # the images are the data: track them
    return Path(out)


if __name__ == "__main__":
    target = make_sample_images(sys.argv[1] if len(sys.argv) > 1 else DEFAULT_OUT)
    size = sum(f.stat().st_size for f in target.rglob("*") if f.is_file())
    print(f"wrote {target} ({size / 1e6:.2f} MB)")
