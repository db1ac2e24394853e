"""scripts/flat_earth_error.py as a test: a perfect IMU of a geodetic flight, integrated back.

The truth comes from PROJ alone (a geodesic at constant height, placed in the world by the
local frame's conversions); the IMU readings from the mechanization equations with
:mod:`cdtm_graph.geodesy`'s gravity and Earth rate. If gravity, the Earth rate or the
frame were wrong, integrating the readings back would not land on the PROJ track.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
flat_earth_error = pytest.importorskip("flat_earth_error")

from cdtm_graph.geodesy import GeodeticOrigin, LocalFrame  # noqa: E402

DURATION_S = 20.0
#: An exact model integrated by RK4 at 200 Hz lands on the PROJ track to round-off.
EARTH_MODEL_TOL_M = 1e-5
#: GTSAM over 1 s intervals: the hold of each sample over its 5 ms step dominates.
GTSAM_TOL_M = 2e-3


@pytest.fixture(scope="module")
def flight():
    frame = LocalFrame(GeodeticOrigin(36.5, 127.0, 1000.0))
    return frame, flat_earth_error.Truth(frame, 60.0, 250.0, 1000.0)


def _final_error(flight, t, p) -> float:
    _, truth = flight
    return float(np.linalg.norm(p[-1] - truth.position(t[-1:])[0]))


@pytest.mark.slow
def test_earth_aware_integration_lands_on_the_proj_track(flight):
    frame, truth = flight
    t, p = flat_earth_error.integrate_rk4(frame, truth, DURATION_S, 200.0, "earth", True)
    assert _final_error(flight, t, p) < EARTH_MODEL_TOL_M
    t, p = flat_earth_error.integrate_gtsam(frame, truth, DURATION_S, 200.0)
    assert _final_error(flight, t, p) < GTSAM_TOL_M


def test_the_flat_model_drifts(flight):
    frame, truth = flight
    t, p = flat_earth_error.integrate_rk4(frame, truth, DURATION_S, 200.0, "flat", False)
    # After 20 s the curvature alone is worth ~ (g d / R) t^2 / 6 ~ 0.5 m, the Earth rate more.
    assert _final_error(flight, t, p) > 1.0
    assert math.isfinite(_final_error(flight, t, p))
