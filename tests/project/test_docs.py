"""The documentation's examples stay true: the example log of docs/flightlog.md reads and
smooths as the page says."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from cdtm_graph.flightlog import load_log_and_dtm
from cdtm_graph.smoother import smooth

ROOT = Path(__file__).resolve().parents[2]


def _example_files() -> tuple[dict[str, str], str]:
    """The files of "A complete example" (name -> text) and the python that makes the DTM."""
    page = (ROOT / "docs" / "flightlog.md").read_text()
    section = page.split("## A complete example", 1)[1].split("\n## ", 1)[0]
    files = {name: text for name, text in re.findall(
        r"^`([\w.]+)`[^\n]*:\n```[a-z]*\n(.*?)```", section, re.S | re.M)}
    python = re.search(r"```python\n(.*?)```", section, re.S)
    assert python is not None
    return files, python.group(1)


def test_the_example_log_of_the_format_reference_smooths(tmp_path, monkeypatch):
    files, make_dtm = _example_files()
    assert set(files) >= {"flight.yaml", "imu.csv", "frames.csv", "tracks.csv"}
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    monkeypatch.chdir(tmp_path)
    exec(compile(make_dtm, "docs/flightlog.md", "exec"), {})  # noqa: S102
    flight, dtm = load_log_and_dtm(tmp_path)
    assert len(flight.frames) == 2 and len(flight.tracks) == 8
    result = smooth(flight, dtm)
    assert result.counts.n_cdtm_features == 4  # as the page says
    assert result.settings["initial_values"] == "nav.csv"
    truth = flight.groundtruth.interpolate(flight.frames.t_ns).position_m
    assert np.abs(result.estimate.position_m - truth).max() < 5.0  # nav.csv was 4 m off
