"""The map's height error estimated from the tracks (:mod:`cdtm_graph.robust.map_error`):
recovered from track heights, grown on a flight over ground detail the DTM lacks, left
alone on clean flights."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from cdtm_graph.graph import GraphSettings, feature_noise
from cdtm_graph.results import pose_covariance_in_world
from cdtm_graph.robust.map_error import estimate_map_error, run_heights
from cdtm_graph.robust.mismatch import TrackHeights
from cdtm_graph.run import smooth_and_evaluate
from cdtm_graph.sim.map_detail import DetailShape, MapDetail
from cdtm_graph.sim.simulate import simulate_flight
from cdtm_graph.smoother import SmootherSettings
from cdtm_graph.studies.robustness import BASE, Mode

SIGMA_H_M = 2.4  # the robustness flight's stated DTM error (30 m posts, Fig. 6)
DETAIL_RMS_M = 3.0
#: the map error a flight with DETAIL_RMS_M of detail has: the DTM's own and the detail's
TRUE_MAP_M = math.hypot(SIGMA_H_M, DETAIL_RMS_M)


def _heights(rng: np.random.Generator, map_sigma_m: float, n: int = 600,
             outliers: float = 0.0) -> TrackHeights:
    """Tracks seen 6 times whose other variance (triangulation) is 0.2-1 sigma_h^2, their
    heights off the DTM by N(0, other + map_sigma^2), ``outliers`` of them 15-30 m up."""
    other_var = rng.uniform(0.2, 1.0, n) * SIGMA_H_M**2
    dh = rng.normal(0.0, np.sqrt(other_var + map_sigma_m**2))
    up = rng.random(n) < outliers
    dh[up] = rng.uniform(15.0, 30.0, int(up.sum()))
    return TrackHeights(np.arange(n), np.zeros((n, 3)), np.full(n, 6), dh,
                        np.sqrt(other_var + SIGMA_H_M**2), np.zeros(n))


@pytest.mark.parametrize("outliers", [0.0, 0.25])
def test_the_estimate_recovers_the_map_error_the_tracks_show(rng, outliers):
    """Catches an estimator that forgets the tracks' own variance (``v = 0``: the stated
    map's read above 2.4 m), one without the trimming (``TRIM_ROUNDS = 1``, the plain
    median: 5.16 m with 25% of the tracks on buildings), or one that grows a map far worse
    than stated (no ``max_ratio``). Each tried once, 2026-11-27."""
    worse = estimate_map_error(_heights(rng, TRUE_MAP_M, outliers=outliers), SIGMA_H_M)
    assert worse.grown and worse.used_m == worse.estimated_m
    # measured 2026-11-27: 3.83 and 3.49 m (the plain median read 5.16 m with the outliers)
    assert worse.estimated_m == pytest.approx(TRUE_MAP_M, rel=0.06 if outliers == 0 else 0.15)
    stated = estimate_map_error(_heights(rng, SIGMA_H_M, outliers=outliers / 5), SIGMA_H_M)
    assert not stated.grown and stated.used_m == SIGMA_H_M
    assert stated.estimated_m == pytest.approx(SIGMA_H_M, rel=0.15)
    # a map off by far more than stated is a fault for the track tests, not a noise level
    wrong = estimate_map_error(_heights(rng, 5 * SIGMA_H_M), SIGMA_H_M)
    assert not wrong.grown and wrong.beyond and wrong.bound_m == 3 * SIGMA_H_M


def test_a_map_worse_than_stated_grows_the_covariance():
    """A 25-frame flight over 3 m rms of waves the DTM lacks (issue 21), iSAM2: the run is
    made with the map error the tracks show and its covariance grows. Catches the
    mechanism switched off (``GraphSettings.map_error=None`` by default: no estimate), or
    the second run made with flight.yaml's sigma_h (the height's 1-sigma then stays at
    the stated map's 1.72 m; tried once, 2026-11-27)."""
    seed = 1  # a flight whose estimate (3.97 m) grows (seed 2: 2.76 m, not grown)
    detail = MapDetail(DetailShape.WAVES, DETAIL_RMS_M, (40.0, 300.0), seed=seed)
    flight = simulate_flight(dataclasses.replace(BASE, frames=25, seed=seed, map_detail=detail))
    out = smooth_and_evaluate(*flight, Mode.ISAM2.settings(SmootherSettings()))
    me = out.result.map_error
    assert me is not None and me.grown
    assert me.used_m == pytest.approx(TRUE_MAP_M, rel=0.1)  # measured 3.97 m
    assert any(n.startswith("map_error_grown") for n in out.verdict.notes)
    # the height's 1-sigma, which the map's error feeds most: measured 2026-11-27 median
    # 1.84 m grown, 1.72 m with sigma_h as stated (the horizontal ones grow 1.05-1.06x)
    up = np.sqrt(pose_covariance_in_world(out.result.estimate.world_T_body,
                                          out.result.covariances.pose)[1][:, 2, 2])
    assert 1.78 < np.median(up) < 1.84 * 1.3


@pytest.mark.slow
def test_clean_flights_keep_their_stated_map_error(clean_flights):
    """The 20 clean 30-frame flights the verdict tests read: none grown (their runs are
    then bit for bit what they were without the mechanism). Catches a margin without the
    spread of a short flight's estimate (``spread_z = 0``: seeds 4 and 5 grow), or an
    estimate biased up (the tracks' own variance left out)."""
    ratios = []
    for out in clean_flights.runs_of(range(1, 21), 30):
        me = out.result.map_error
        assert me is not None and not me.grown
        ratios.append(me.estimated_m / me.stated_m)
    # measured 2026-11-27: 0.47-1.30 (seeds 4 and 5: 1.28 and 1.30 over 145 and 132 tracks,
    # under their 1 + 4.5 / sqrt(n) = 1.37 and 1.39)
    assert max(ratios) < 1.35


def test_sightings_that_waited_for_a_fix_are_not_read_as_map_error(clean_flights):
    """A frame whose sightings waited for a fix never found is not placed by the ground:
    its tracks say nothing of the map. Catches ``run_heights`` reading them (seen
    2026-11-27: a 1000 m start over terrain repeating every 3 km, no fix, read "beyond
    the bound" and was smoothed twice more, 7.5 -> 17.4 s)."""
    flight, dtm = clean_flights.flight(1, 30)
    estimate = clean_flights.run(1, 30).result.estimate
    noise = feature_noise(flight.config, dtm, GraphSettings())
    every = run_heights(flight, dtm, noise, estimate)
    assert len(every.dh_m) > 100
    late = run_heights(flight, dtm, noise, estimate, np.arange(15))
    assert 0 < len(late.dh_m) < len(every.dh_m)
    assert len(run_heights(flight, dtm, noise, estimate, np.arange(30)).dh_m) == 0
    assert np.isnan(estimate_map_error(
        run_heights(flight, dtm, noise, estimate, np.arange(30)), SIGMA_H_M).estimated_m)
