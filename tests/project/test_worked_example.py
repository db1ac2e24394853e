"""The worked example README, docs/flightlog.md and ``cdtm --help`` show runs as shown: a
flight in latitude and longitude over an EPSG:4326 DEM with EGM96 heights, end to end."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import numpy as np
import pytest

from cdtm_graph.cli import GEODETIC_EXAMPLE, main
from cdtm_graph.flightlog import read_flightlog

ROOT = Path(__file__).resolve().parents[2]
COMMANDS = ["cdtm simulate my_flight --origin 36.5 127.25 120",
            "cdtm smooth my_flight --out my_run --plots"]
#: Kept small: the documented flight has 60 frames; the same commands run on 8.
SMALL = ["--frames", "8"]


def _bash_commands(text: str) -> list[str]:
    blocks = re.findall(r"```bash\n(.*?)```", text, re.S)
    return [line.strip() for block in blocks for line in block.splitlines()
            if line.strip().startswith("cdtm ")]


def test_the_three_places_show_the_same_commands():
    readme = _bash_commands((ROOT / "README.md").read_text())
    docs = _bash_commands((ROOT / "docs" / "flightlog.md").read_text())
    helped = [line.strip() for line in GEODETIC_EXAMPLE.splitlines()]
    for command in COMMANDS:
        assert command in readme and command in docs and command in helped, command


@pytest.mark.slow
def test_the_worked_example_runs_end_to_end(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    simulate, smooth = (shlex.split(c)[1:] for c in COMMANDS)
    assert main(simulate + SMALL) == 0
    assert main(smooth + ["--scene", "--quiet"]) == 0
    run = tmp_path / "my_run"
    assert {"trajectory_geodetic.csv", "trajectory.geojson", "trajectory_dem.png",
            "errors.png", "scene.glb"} <= {p.name for p in run.iterdir()}
    # The smoothed latitudes and longitudes against the true ones (groundtruth.csv is in
    # latitude/longitude too), in metres on the ground: within 4 sigma and a few metres.
    flight = read_flightlog(tmp_path / "my_flight")
    assert (tmp_path / "my_flight" / "groundtruth.csv").read_text().startswith(
        "#t_ns,latitude_deg,longitude_deg,height_m,")
    table = np.loadtxt(run / "trajectory_geodetic.csv", delimiter=",", skiprows=1)
    truth = flight.groundtruth.interpolate(flight.frames.t_ns).position_m
    lat, lon, h, *_ = flight.config.local_frame.world_to_geodetic(truth)
    metres_per_deg_lat = 111_000.0
    north = (table[:, 1] - lat) * metres_per_deg_lat
    east = (table[:, 2] - lon) * metres_per_deg_lat * np.cos(np.radians(36.5))
    up = table[:, 3] - h
    for error, sigma in ((north, table[:, 11]), (east, table[:, 12]), (up, table[:, 13])):
        assert np.all(np.abs(error) < 4.0 * sigma + 0.05), (error, sigma)
        assert np.abs(error).max() < 5.0
