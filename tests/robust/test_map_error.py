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
from cdtm_graph.robust.map_error import (
    SIGMA_TOL_M,
    BroadErrorSettings,
    BroadMapWatch,
    MapErrorSettings,
    MapErrorWatch,
    _decreasing_root,
    attitude_tilt_covariance,
    broad_map_error,
    curvature_test,
    curvature_tests,
    estimate_map_error,
    run_heights,
)
from cdtm_graph.robust.mismatch import MismatchSettings, TrackHeights
from cdtm_graph.run import smooth_and_evaluate
from cdtm_graph.sim.faults import MismatchKind, TerrainMismatch
from cdtm_graph.sim.map_detail import DetailShape, MapDetail
from cdtm_graph.sim.simulate import simulate_flight
from cdtm_graph.smoother import SmootherSettings
from cdtm_graph.studies.robustness import BASE, SCENARIOS, Mode
from cdtm_graph.verdict import assess

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


def _read(watch: MapErrorWatch, rng: np.random.Generator, map_sigma_m: float, reads: int,
          first_id: int, offset_m: float = 0.0) -> list[float | None]:
    """``reads`` readings of 60 new tracks each (their ``sigma_m`` holding the sigma_h the
    watch uses now, as the judge's do), every height shifted by ``offset_m``."""
    out = []
    for i in range(reads):
        h = _heights(rng, map_sigma_m, n=60)
        sigma = np.sqrt(h.sigma_m**2 - SIGMA_H_M**2 + watch.used_m**2)
        h = dataclasses.replace(h, track_id=h.track_id + first_id + 60 * i,
                                dh_m=h.dh_m + offset_m, sigma_m=sigma)
        out.append(watch.read(i, h))
    return out


def test_a_live_reading_grows_the_map_when_it_shows_and_not_for_an_offset(rng):
    """:class:`MapErrorWatch` on synthetic tracks of the robustness flight's map (stated
    2.4 m). A map as stated under an 8 m offset common to every track (the live estimate's
    own height error) is never grown; a map 1.8x worse is grown once, to about its error;
    a map 3x worse read after it grows it again, to the bound. Mutations tried
    (2026-11-28): the window's median not taken out -> the offset grows the map; the
    judge's heights not read against the stated sigma_h (their ``sigma_m`` holding the
    grown one: every track then too weak to count) -> no second growth; no hysteresis
    (``used_m`` ignored) -> grown at every reading. Each fails."""
    clean = MapErrorWatch(SIGMA_H_M, MapErrorSettings())
    assert _read(clean, rng, SIGMA_H_M, 20, 0, offset_m=8.0) == [None] * 20
    assert clean.used_m == SIGMA_H_M
    watch = MapErrorWatch(SIGMA_H_M, MapErrorSettings())
    worse = _read(watch, rng, 1.8 * SIGMA_H_M, 10, 0)
    grown = [g for g in worse if g is not None]
    assert len(grown) == 1 and grown[0] == pytest.approx(1.8 * SIGMA_H_M, rel=0.15)
    far = [g for g in _read(watch, rng, 3.5 * SIGMA_H_M, 25, 10_000) if g is not None]
    assert far and far[-1] == 3.0 * SIGMA_H_M and watch.used_m == 3.0 * SIGMA_H_M


def test_a_map_worse_than_stated_grows_the_covariance(monkeypatch):
    """A 25-frame flight over 3 m rms of waves the DTM lacks (issue 21), iSAM2: the run is
    made with the map error the tracks show, its tangent planes' slopes regional, and its
    covariance grows; the calibration check after it is given the same map. Catches the
    mechanism switched off (``GraphSettings.map_error=None`` by default: no estimate), the
    second run made with flight.yaml's sigma_h (the height's 1-sigma then stays at the
    stated map's 1.72 m, 2026-11-27; 2.27 m with the slopes regional, 2026-11-28), the
    slopes left the patches' (1.84 m), or the grown map not handed on to the side solves
    (``dtm`` not rebound in ``smooth``'s grown branch). Each tried once."""
    from cdtm_graph.smoother import batch

    checked = []  # the slopes of the map the calibration check was given
    check = batch._calibration_check
    monkeypatch.setattr(batch, "_calibration_check", lambda flight, dtm, *args, **kwargs: (
        checked.append(dtm.slope_sigma_posts) or check(flight, dtm, *args, **kwargs)))
    seed = 1  # a flight whose estimate (3.97 m) grows (seed 2: 2.76 m, not grown)
    detail = MapDetail(DetailShape.WAVES, DETAIL_RMS_M, (40.0, 300.0), seed=seed)
    flight = simulate_flight(dataclasses.replace(BASE, frames=25, seed=seed, map_detail=detail))
    out = smooth_and_evaluate(*flight, Mode.ISAM2.settings(SmootherSettings()))
    me = out.result.map_error
    assert me is not None and me.grown
    assert me.slope_sigma_posts == 1.0 and checked and set(checked) == {1.0}
    assert me.used_m == pytest.approx(TRUE_MAP_M, rel=0.1)  # measured 3.97 m
    assert any(n.startswith("map_error_grown") for n in out.verdict.notes)
    # the height's 1-sigma, which the map's error feeds most: measured 2026-11-28 median
    # 2.54 m grown (its slopes regional; the patches' slopes: 1.84 m), 1.72 m with sigma_h
    # as stated
    up = np.sqrt(pose_covariance_in_world(out.result.estimate.world_T_body,
                                          out.result.covariances.pose)[1][:, 2, 2])
    assert 2.54 / 1.1 < np.median(up) < 2.54 * 1.3


@pytest.mark.slow
def test_a_map_far_worse_than_stated_is_named(seed, monkeypatch):
    """Noise on every post of a map that states 2.4 m (30 frames, batch). 14 m: the tracks
    read 9.9 m, beyond the 3x a run grows sigma_h to, and again at that bound: the run
    keeps 2.4 m, ``map_error`` beside the rejections (RMSE 9.4 m, ANEES 13.3). 10 m: the
    first run reads 7.8 m, beyond; the run made again at the bound reads 6.2 m and is
    kept there, a note naming the first reading, `trusted` at ANEES 3.17 (RMSE 5.95 m,
    sigma 5.1 m; 5.7 before its planes' slopes were made regional, 2026-11-28). (10 m on
    seed + 2, which read beyond twice before, is now kept at the bound too: RMSE 3.25 m,
    ANEES 1.14.) The side solves after the run (the calibration check, the IMU walks'
    check) use the map the run kept: its regional slopes at the bound, the grid's own when
    the run at the bound is not kept. Mutations: the rule switched off
    (``_map_error_check`` returning ``[]``) -> fails; the kept run's map not handed on
    (``dtm`` not rebound in ``smooth``'s bound branch; the run itself unchanged, its
    calibration check's position NEES 1.99 -> 0.98) -> fails."""
    from cdtm_graph.sim.faults import with_dtm_noise
    from cdtm_graph.smoother import batch

    seen: list[float] = []  # the slopes of the map each side solve was given

    def spied(solve):
        def spy(flight, dtm, *args, **kwargs):
            seen.append(dtm.slope_sigma_posts)
            return solve(flight, dtm, *args, **kwargs)
        return spy

    for name in ("_calibration_check", "check_random_walks"):
        monkeypatch.setattr(batch, name, spied(getattr(batch, name)))
    runs = {}
    log, dtm = SCENARIOS["clean"].flight(dataclasses.replace(BASE, frames=30, seed=seed))
    for noise_m in (14.0, 10.0):
        seen.clear()
        out = smooth_and_evaluate(log, with_dtm_noise(dtm, noise_m,
                                                      np.random.default_rng(seed)),
                                  SmootherSettings())
        runs[noise_m] = (out.result.map_error, assess(out.result), out.errors, list(seen))
    me, verdict, _, sides = runs[14.0]
    assert me is not None and me.beyond and me.used_m == me.stated_m
    assert "map_error" in [r.code for r in verdict.reasons], verdict.lines()
    assert me.slope_sigma_posts == 0.0 and sides == [0.0, 0.0]
    me, verdict, errors, sides = runs[10.0]
    assert me is not None and me.used_m == me.bound_m and me.first_estimated_m > me.bound_m
    assert me.slope_sigma_posts == 1.0 and sides == [1.0, 1.0]
    assert "map_error" not in [r.code for r in verdict.reasons]
    assert any(n.startswith("map_error_grown") and "the first run read" in n
               for n in verdict.notes)
    assert errors is not None and errors.anees_position < 3.17 * 1.3


@pytest.mark.slow  # three 60-frame flights, each smoothed two or three times (~25 s)
@pytest.mark.parametrize("mode", list(Mode), ids=lambda m: m.value)
def test_a_grown_map_takes_its_tangent_planes_slopes_regionally(mode):
    """10 m of white noise on every post of a map stating 2.4 m (the 60-frame flight, seed
    2): the tracks read 7.7-8.8 m, and the run made again at the 3x bound (7.2 m) is kept.
    It held the heights' error, not the patches' tilt, about 10 sqrt(2) / 30 m (25 deg),
    which the factor read as horizontal information: ANEES 15.9 batch, 19.6 iSAM2 (RMSE
    6.1 m, `trusted`); the fixed lag's run at the bound read beyond again and kept 2.4 m
    (ANEES 65, RMSE 14.7 m, `map_error`). With the planes' slopes from the DTM smoothed
    over one post (``MapErrorSettings.slope_sigma_posts``), every mode keeps the bound:
    ANEES 4.41 / 4.02 / 4.60 at RMSE 5.6 / 5.1 / 7.4 m (measured 2026-11-28), `trusted`.
    (Since its first pass grows the map as it goes, iSAM2's reads 6.57 m at its end, within
    the bound, and its run made again there: ANEES 3.78, RMSE 4.95 m.)
    Mutations tried: the regional normals not applied (``Dtm._regional`` returning the
    patches') -> ANEES 15.9 / 19.6, the fixed lag keeps 2.4 m: fails in every mode; so
    does ``slope_sigma_posts=None``."""
    from cdtm_graph.sim.faults import with_dtm_noise

    seed = 2
    log, dtm = SCENARIOS["clean"].flight(dataclasses.replace(BASE, frames=60, seed=seed))
    out = smooth_and_evaluate(log, with_dtm_noise(dtm, 10.0, np.random.default_rng(seed)),
                              mode.settings(SmootherSettings()))
    me = out.result.map_error
    assert me is not None and 2.5 * me.stated_m < me.used_m <= me.bound_m
    assert me.slope_sigma_posts == 1.0
    assert out.errors is not None and out.errors.anees_position < 5.5, out.errors.anees_position
    verdict = assess(out.result)  # no ground truth
    assert verdict.status.value == "trusted", verdict.lines()
    assert any(n.startswith("map_error_grown") and "smoothed over 1 post" in n
               for n in verdict.notes)


@pytest.mark.slow  # a 90-frame flight fed in each mode (~8 s)
@pytest.mark.parametrize("mode, measured", [(Mode.ISAM2, 3.29), (Mode.FIXED_LAG, 3.49)],
                         ids=["isam2", "fixed_lag"])
def test_the_live_path_grows_a_map_worse_than_stated_as_it_goes(live, mode, measured):
    """10 m of white noise on every post of a map stating 2.4 m (the robustness flight,
    seed 2), fed to the live API frame by frame: its updates report sigma_h as stated
    until the tracks read the map worse (:class:`MapErrorWatch`), then go on with the
    error read (6.3 m from frame 25 in iSAM2, 6.0 m from frame 45 in the fixed lag) and
    regional slopes, the factors already in the solver too. Mean live position NEES over
    frames 10-89, measured 2026-11-28: 3.29 iSAM2, 3.49 fixed lag (12.33 and 9.22
    without; the frames after the growth 1.31 and 1.81). A live user cannot be smoothed
    again, so before the first reading the covariance is still the stated map's.
    Mutations tried: the watch off (``live_every_rounds=None``) -> 12.3 / 9.2: fails;
    the factors already in the solver not moved (``SolverWindow.on_map`` returning at
    once) -> iSAM2's first factors keep 2.4 m (and its NEES 4.52): fails."""
    from cdtm_graph.sim.faults import with_dtm_noise

    seed = 2
    log, dtm = SCENARIOS["clean"].flight(dataclasses.replace(BASE, seed=seed))
    noisy = with_dtm_noise(dtm, 10.0, np.random.default_rng(seed + 100))
    nees, smoother, updates = live.live_updates(log, noisy, mode.settings(SmootherSettings()))
    nees = nees[10:]  # (the prior's start apart)
    assert smoother.map_grown and 25 <= smoother.map_grown[0][0] <= 50
    first = smoother.map_grown[0][0]
    assert all(u.map_sigma_h_m == SIGMA_H_M for u in updates[:first])
    assert updates[-1].map_sigma_h_m == smoother.map_grown[-1][1] > 2 * SIGMA_H_M
    if mode is Mode.ISAM2:  # a full history's factors all took it, the first ones too
        held = {f.features.noise.sigma_h_m for f in smoother._window.live_factors()}
        assert held == {smoother.map_grown[-1][1]}, held
    assert nees.mean() < measured * 1.3, nees.mean()


def test_a_map_grown_by_a_runs_last_round_is_iterated_to():
    """10 m of noise on the posts (30 frames, seed 2, iSAM2): the map reads worse only at
    the run's end, in ``finalize``'s rounds (frame 29). The growth changes the factors, so
    the solver must iterate after it as after tracks left out: the error reported is the
    graph's as it ends. Mutation tried (2026-11-28, the review's find): a growth not
    counted as a round's change (``TrackRounds.run``) -> final error 6155 against the
    graph's 5070: fails."""
    from cdtm_graph.sim.faults import with_dtm_noise
    from cdtm_graph.smoother.incremental import IncrementalSmoother

    log, dtm = SCENARIOS["clean"].flight(dataclasses.replace(BASE, frames=30, seed=2))
    noisy = with_dtm_noise(dtm, 10.0, np.random.default_rng(102))
    smoother = IncrementalSmoother(log.config, noisy, Mode.ISAM2.settings(SmootherSettings()),
                                   frame_interval_s=1.0)
    smoother.feed(log)
    assert smoother.map_grown and smoother.map_grown[-1][0] == 29
    assert smoother.final_error == pytest.approx(smoother._window.backend.error(), rel=1e-9)


def test_a_run_made_again_after_a_grown_map_holds_it(monkeypatch):
    """The 25-frame waves flight whose map is grown at the run's end (iSAM2, seed 1): the
    run made again with the grown sigma_h, and a run made again for the IMU's random walks
    after it, hold the map as it is (no reading as they go: ``live_every_rounds`` None),
    else they would grow it again from the grown sigma_h as if stated, up to 3x of it (the
    review's find: 12.5 m on a map grown to 7.2 m). The walks' check is made to grow.
    Mutation tried (2026-11-28): the walks' run made again with the run's own settings ->
    fails."""
    from types import SimpleNamespace

    from cdtm_graph.smoother import batch

    made = []  # each run's live reading setting
    once = batch._smooth_once
    monkeypatch.setattr(batch, "_smooth_once", lambda flight, dtm, settings, *a: (
        made.append(settings.graph.map_error.live_every_rounds) or once(
            flight, dtm, settings, *a)))
    monkeypatch.setattr(batch, "check_random_walks", lambda flight, *a, **k: SimpleNamespace(
        grown=True, scales=(2.0, 2.0),
        used_gyro=2 * flight.config.imu.gyroscope_random_walk,
        used_accel=2 * flight.config.imu.accelerometer_random_walk))
    seed = 1
    detail = MapDetail(DetailShape.WAVES, DETAIL_RMS_M, (40.0, 300.0), seed=seed)
    flight = simulate_flight(dataclasses.replace(BASE, frames=25, seed=seed, map_detail=detail))
    result = batch.smooth(*flight, Mode.ISAM2.settings(SmootherSettings()))
    assert result.map_error is not None and result.map_error.grown
    assert made == [1, None, None] and result.map_error.grown_at == ()


@pytest.mark.slow  # a 90-frame fixed-lag flight fed (~4 s)
def test_the_live_path_does_not_take_clutter_for_a_worse_map(live):
    """A forest the DTM lacks (20% of the ground, trees 15-25 m: the robustness study's
    ``forest``, seed 1), fed to the live fixed lag: the track tests drop the trees, and
    their heights, all above the ground, would read as a map 1.5-2x worse than stated
    (4.9 m at frame 20 over 22 tracks); the watch does not read the map while the round's
    tracks fit clutter above the ground (:meth:`TrackJudge.last_round_heights`), so
    sigma_h stays as stated. Mutation tried (2026-11-28): that rule off -> grown at frame
    20, and in ``smooth()`` the run's ANEES 3.25 -> 5.03, 1313 -> 466 features dropped."""
    log, dtm = SCENARIOS["forest"].flight(dataclasses.replace(BASE, seed=1))
    _, smoother, updates = live.live_updates(log, dtm,
                                             Mode.FIXED_LAG.settings(SmootherSettings()))
    assert smoother.map_grown == () and {u.map_sigma_h_m for u in updates} == {SIGMA_H_M}


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
    # nor do the incremental passes as they go (:class:`MapErrorWatch`; its live ratio
    # 1.5: on 16 clean 90-frame flights per mode, seeds 1-16, the readings reached 1.29x
    # at most, 2026-11-28). (Their runs' ends may: one of these 16 reads 1.48x over 132
    # tracks, as before the watch.)
    for mode in (Mode.ISAM2, Mode.FIXED_LAG):
        for out in clean_flights.runs_of(range(1, 9), 30, mode):
            me = out.result.map_error
            assert me is not None and not me.grown_at


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


# ------------------------------------------------- the map's error over kilometres (build 4)

#: The issue's flight seen from above: 150 m/s, a footprint 2 km across, ~235 tracks in a
#: 10 s window (measured on the 90-frame flight, 2026-11-27).
SPEED_MPS, HALF_WIDTH_M, TRACKS_PER_S = 150.0, 1000.0, 23.5


def _strip(rng: np.random.Generator, duration_s: float = 40.0
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tracks' ground points along a straight flight (x along the track), their mean times
    (s) and the frames' times (1 fps)."""
    n = int(TRACKS_PER_S * duration_s)
    t_s = rng.uniform(0.0, duration_s, n)
    xy = np.column_stack([SPEED_MPS * t_s + rng.uniform(-700.0, 700.0, n),
                          rng.uniform(-HALF_WIDTH_M, HALF_WIDTH_M, n)])
    return xy, t_s, np.arange(0.0, duration_s + 0.5)


def _waves(rng: np.random.Generator, xy: np.ndarray, rms_m: float = 3.0,
           wavelength_m: tuple[float, float] = (40.0, 200.0), n: int = 24) -> np.ndarray:
    """Ground detail the DTM lacks at ``xy``: plane waves, wavelengths log-uniform in the
    band, scaled to ``rms_m`` (:class:`~cdtm_graph.sim.map_detail.MapDetail`'s WAVES)."""
    wavelengths = np.exp(rng.uniform(*np.log(wavelength_m), n))
    angle, phase = rng.uniform(0, np.pi, n), rng.uniform(0, 2 * np.pi, n)
    k = 2 * np.pi / wavelengths
    along = xy[:, :1] * np.cos(angle) + xy[:, 1:] * np.sin(angle)
    return rms_m * np.sqrt(2.0 / n) * np.sin(k * along + phase).sum(axis=1)


#: The tilt an attitude sigma of 0.03 deg (the batch's on the issue's flight: 0.56 m over
#: a kilometre) gives the ground, per axis.
ATTITUDE_TILT_M = 0.56


def _broad(xy, t_s, frame_t_s, dh, sigma_m: float = 3.0, tilt_sigma_m: float = ATTITUDE_TILT_M,
           **settings):
    n = dh.size
    heights = TrackHeights(np.arange(n), np.column_stack([xy, np.zeros(n)]), np.full(n, 8),
                           dh, np.full(n, sigma_m), np.zeros(n))
    tilt_cov = np.tile(np.eye(2) * tilt_sigma_m**2, (frame_t_s.size, 1, 1))
    return broad_map_error(heights, t_s, frame_t_s, tilt_cov, BroadErrorSettings(**settings))


#: The verdict's bound on the shape evidence in batch and iSAM2
#: (``VerdictSettings.broad_map.peak``).
EVIDENCE_BOUND = 20.0


@pytest.mark.parametrize("blocks", [0.0, 0.15])
def test_a_smooth_hill_shapes_the_tracks_beyond_ground_detail(rng, blocks):
    """The shape evidence over 40 s of the issue's footprint: ground detail (3 m rms of
    waves, 40-200 m) with the triangulation's scatter stays under the verdict's 20 (as the
    clean and detail batch runs: 3.4-14.5); a 15 m hill of 1 km sigma the estimate half absorbs
    (its mean over each window taken off, as the estimate flies low) goes beyond it at the
    frames over the hill, and reads its curvature (15 m / (1 km)^2: 7.5 m over a
    kilometre); 15% of the tracks on blocks 15-30 m up (a town) change neither. Mutations:
    the gate off (``rounds=1``) -> the blocks bend the surface and hide the hill: fails;
    the shape read from the offset term (``_SHAPE``'s last row on ``a``) -> fails (each
    tried once, 2026-11-27)."""
    xy, t_s, frame_t_s = _strip(rng)
    n = t_s.size
    up = rng.random(n) < blocks
    detail = (_waves(rng, xy) + rng.normal(0.0, 2.0, n)
              + np.where(up, rng.uniform(15.0, 30.0, n), 0.0))
    flat = _broad(xy, t_s, frame_t_s, detail)
    judged = np.isfinite(flat.evidence)
    assert judged.sum() == frame_t_s.size - 14  # windows cut by the ends are not judged
    # measured 2026-11-27: 8.2 and, the blocks' tracks all kept (the run's track tests
    # drop most of them before), 17.8; 1.6-6.3 and 2.7-12.2 over 18 other seeds
    assert np.nanmax(flat.evidence) < EVIDENCE_BOUND, np.nanmax(flat.evidence)
    centre = np.array([SPEED_MPS * 20.0, 0.0])
    hill = 15.0 * np.exp(-0.5 * np.sum((xy - centre) ** 2, axis=1) / 1000.0**2)
    # the estimate takes each window's mean as its own height
    absorbed = np.array([hill[np.abs(t_s - t) <= 5.0].mean() for t in t_s])
    hilly = _broad(xy, t_s, frame_t_s, detail + hill - 0.5 * absorbed)
    k = int(np.nanargmax(hilly.evidence))
    assert hilly.evidence[k] > 2 * EVIDENCE_BOUND and abs(k - 20) <= 4, (hilly.evidence[k], k)
    assert hilly.bend_m[k] == pytest.approx(7.5, rel=0.35)
    assert np.all(hilly.n_tracks[judged] >= 150)


def test_a_tilt_the_attitude_sigma_allows_is_not_the_maps():
    """An attitude error tilts the ground triangulated from its cameras: a roll of 3 of
    its sigmas (0.09 deg: 1.7 m over a kilometre) over flat ground is no map error, the
    same tilt at a tenth of that sigma is. And the tilt's covariance is the attitude's
    turned into the world and scaled by the kilometre. Mutation: the attitude's tilt
    covariance not added in ``curvature_test`` -> the first is flagged: fails (tried,
    2026-11-27)."""
    rng = np.random.default_rng(3)  # a seed of its own: the noise only
    xy, t_s, frame_t_s = _strip(rng)
    tilt_m = 3 * ATTITUDE_TILT_M
    dh = tilt_m * xy[:, 1] / 1000.0 + rng.normal(0.0, 2.0, t_s.size)
    honest = _broad(xy, t_s, frame_t_s, dh, sigma_m=2.0)
    assert np.nanmax(honest.evidence) < EVIDENCE_BOUND
    told = _broad(xy, t_s, frame_t_s, dh, sigma_m=2.0, tilt_sigma_m=0.1 * ATTITUDE_TILT_M)
    assert np.nanmin(told.evidence) > EVIDENCE_BOUND, np.nanmin(told.evidence)
    assert np.nanmedian(told.tilt_m) == pytest.approx(tilt_m, rel=0.2)
    # a roll (about the world's x, the body's y after a quarter turn of heading)
    sigma_rad = np.radians([0.03, 0.01, 0.2])
    yaw = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    cov = attitude_tilt_covariance(yaw, np.diag(sigma_rad**2), 1000.0)
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), 1000.0 * sigma_rad[[0, 1]], rtol=1e-12)


@pytest.mark.slow  # a 45-frame flight smoothed (8 s)
def test_a_hill_the_dtm_lacks_is_named_without_ground_truth():
    """A 15 m hill of 1 km sigma the DTM lacks under the issue's flight at 25 s (45
    frames, batch, default settings): the run flies low at a small covariance (measured
    2026-11-27: RMSE 6.7 m, ANEES 27.5; ``trusted`` before build 4), and the verdict
    without ground truth names ``broad_map_error`` over the frames near the hill (23-29;
    shape evidence 38 against the bound 20). Mutation: the look switched off by default
    (``GraphSettings.broad_map_error = None``) -> no reason: fails (tried, 2026-11-27)."""
    hill = TerrainMismatch(MismatchKind.HILL, depth_m=15.0, radius_m=1000.0, at_s=25.0)
    # seed 1: the robustness study's flight (docs/design.md's table)
    flight, dtm = simulate_flight(dataclasses.replace(BASE, frames=45, seed=1,
                                                      terrain_mismatch=hill))
    out = smooth_and_evaluate(flight, dtm, Mode.BATCH.settings(SmootherSettings()))
    assert out.errors is not None and out.errors.anees_position > 6.0  # the run is wrong
    verdict = assess(out.result)  # no ground truth
    named = [r for r in verdict.reasons if r.code == "broad_map_error"]
    assert len(named) == 1, verdict.lines()
    assert named[0].first_frame <= 25 <= named[0].last_frame
    broad = out.result.broad_map_error
    assert broad is not None and EVIDENCE_BOUND < np.nanmax(broad.evidence) < 60.0


@pytest.mark.slow  # a 90-frame flight smoothed (3 s)
def test_a_hill_under_the_footprints_edge_is_named_by_how_long_it_bends_it():
    """The robustness study's hill (15 m, 1 km sigma, at 45 s) on the flight of seed 8,
    where it passes under the footprint's edge: the shape evidence peaks under the verdict's
    20 (measured 2026-11-28: 18.6) but stays above 12 for 13 s, where ground detail held 12
    for at most 7 s (clean, waves, ridges, bumps, seeds 0-29, batch). The run is wrong
    (RMSE 1.8, 1.8, 3.2 m in x, y, z; ANEES 31.6) and was ``trusted`` without ground truth
    before the sustained rule; now ``broad_map_error`` is named over the hill. Mutation:
    the sustained rule off (``BroadMapBounds.sustained`` None) -> no reason: fails (tried,
    2026-11-28)."""
    # seed 8: the flight the hill was missed on (issue 21's table), not conftest's
    flight, dtm = SCENARIOS["hill15"].flight(dataclasses.replace(BASE, frames=90, seed=8))
    out = smooth_and_evaluate(flight, dtm, Mode.BATCH.settings(SmootherSettings()))
    assert out.errors is not None and out.errors.anees_position > 6.0  # the run is wrong
    broad = out.result.broad_map_error
    assert broad is not None and 12.0 < np.nanmax(broad.evidence) < EVIDENCE_BOUND
    verdict = assess(out.result)  # no ground truth
    named = [r for r in verdict.reasons if r.code == "broad_map_error"]
    assert len(named) == 1, verdict.lines()
    assert (named[0].first_frame, named[0].last_frame) == (38, 50), named[0]  # the hill: 45 s
    assert "at frame 48, above 12 for 13 s, " in named[0].message, named[0].message


def test_ground_points_on_a_line_leave_the_shape_unknown_not_an_error(rng):
    """A window whose ground points lie on one line (a footprint a few pixels wide) cannot
    tell a curvature across it: the statistic is finite, never an exception. Mutation:
    ``np.linalg.solve`` for the final ``pinv`` -> LinAlgError: fails (tried, 2026-11-27)."""
    x = rng.uniform(-1000.0, 1000.0, 200)
    xy = np.column_stack([x, np.zeros_like(x)])
    chi2, tilt_m, bend_m, kept = curvature_test(xy, rng.normal(0.0, 2.0, 200), np.full(200, 2.0),
                                                np.zeros((2, 2)), BroadErrorSettings())
    assert np.isfinite(chi2) and np.isfinite(tilt_m) and np.isfinite(bend_m) and kept > 150


def _one_window_reference(xy_m, dh_m, sigma_m, tilt_cov, settings):
    """The shape fit one window at a time as it was written first (``np.linalg.lstsq``
    round by round; the covariance from ``pinv(A^T A)``): the reference the batched fit is
    held to."""
    xy_m = xy_m - xy_m.mean(axis=0)
    x, y = xy_m[:, 0] / settings.scale_m, xy_m[:, 1] / settings.scale_m
    terms = np.column_stack([np.ones_like(x), x, y, x * x, x * y, y * y])
    root_w = 1.0 / sigma_m
    keep = np.ones(dh_m.size, bool)
    for _ in range(settings.rounds):
        A, b = terms[keep] * root_w[keep, None], dh_m[keep] * root_w[keep]
        coef = np.linalg.lstsq(A, b, rcond=None)[0]
        scale2 = max(float(np.sum((b - A @ coef) ** 2)) / max(int(keep.sum()) - 6, 1), 1e-12)
        off = np.abs(dh_m - terms @ coef) * root_w
        now = off <= settings.gate * 1.4826 * float(np.median(off))
        if np.array_equal(now, keep) or now.sum() <= 6:
            break
        keep = now
    shape_of = np.array([[0, 1, 0, 0, 0, 0], [0, 0, 1, 0, 0, 0], [0, 0, 0, 1, 0, 1]], float)
    cov = shape_of @ np.linalg.pinv(A.T @ A) @ shape_of.T * scale2
    cov[:2, :2] += tilt_cov
    shape = shape_of @ coef
    per_km = 1000.0 / settings.scale_m
    return (float(shape @ np.linalg.pinv(cov) @ shape), float(np.hypot(*shape[:2])) * per_km,
            0.5 * abs(float(shape[2])) * per_km**2, int(keep.sum()))


@pytest.mark.parametrize("strip_m", [None, 1.0, 0.1])
def test_windows_fitted_together_give_each_window_alone(rng, strip_m):
    """:func:`curvature_tests` fits a stack of windows padded to one length at once (a
    1000-frame flight's 980 windows took 0.8 s one by one, 2026-11-28): each window's
    statistic, tilt, bend and kept count are those of the window fitted alone by the
    first, per-window least squares, whatever the padding holds; blocks (gated round by
    round), 7 points, windows of ground points in a strip ``strip_m`` wide (nearly
    degenerate) and on a line included. Mutations tried: the padding kept in the median
    (``_medians`` over every row), the padding in the windows' centres
    (``xy_m.mean(axis=1)``), the fit by the normal equations (``pinv(A^T A) A^T b``: a
    0.1 m strip read chi-square 2e12 against 0.8): each fails."""
    settings = BroadErrorSettings()
    sizes = [80, 250, 140, 61, 7]
    P = max(sizes) + 7
    xy, dh, sigma = np.full((5, P, 2), 9e9), np.full((5, P), -7e3), np.full((5, P), 1e-3)
    valid = np.zeros((5, P), bool)
    alone, tilt_cov = [], np.stack([np.eye(2) * 0.01 * w for w in range(5)])
    for w, n in enumerate(sizes):
        ground = rng.uniform(-1200.0, 1200.0, (n, 2))
        if strip_m is not None:
            ground[:, 1] = rng.uniform(-strip_m / 2, strip_m / 2, n)
        if w == 3:
            ground[:, 1] = 0.0  # on a line: the curvature across it unknown
        turn = rng.uniform(0.0, np.pi)
        ground = ground @ np.array([[np.cos(turn), np.sin(turn)], [-np.sin(turn), np.cos(turn)]])
        ground += rng.uniform(-5e4, 5e4, 2)
        s_m = rng.uniform(1.0, 4.0, n)
        height = 2e-6 * w * np.sum((ground - ground.mean(axis=0)) ** 2, axis=1) \
            + rng.normal(0.0, 1.0, n) * s_m
        height[rng.random(n) < 0.2 * (w % 2)] += 25.0  # blocks on a fifth of two windows
        at = rng.permutation(P)[:n]  # (the window's tracks anywhere in its row)
        xy[w, at], dh[w, at], sigma[w, at], valid[w, at] = ground, height, s_m, True
        alone.append(_one_window_reference(ground, height, s_m, tilt_cov[w], settings))
    together = np.column_stack(curvature_tests(xy, dh, sigma, valid, tilt_cov, settings))
    # (in a strip the covariance's pinv(A^T A) holds a condition number of ~1e13: the
    # same formula summed in another order moves the statistic by ~1e-4)
    rtol = 1e-6 if strip_m is None else 1e-3
    np.testing.assert_allclose(together[:, :3], np.array(alone)[:, :3], rtol=rtol, atol=1e-9)
    assert together[:, 3].tolist() == [a[3] for a in alone]
    assert together[1, 3] < sizes[1]  # the blocks gated out


def test_each_frame_window_holds_the_tracks_within_half_its_span(rng):
    """:func:`broad_map_error` takes a frame's window as a run of the tracks sorted by
    time: it holds exactly the tracks with ``|t - t_frame| <= window_s / 2`` (ties on the
    edges, equal times, tracks out of order), ``n_tracks`` counts them; with no usable
    track at all, every window is empty, not an error. Mutations tried: the margin's
    exact mask dropped (``valid &= ...`` removed) and the empty case unguarded (an
    IndexError, the review's find, 2026-11-28): each fails."""
    frame_t_s = np.arange(0.0, 30.01, 0.5)
    # (7.5 - 1e-9 and 17.5 + 1e-9: just outside frame 12.5's window, inside its margin)
    t_s = np.r_[np.repeat(np.arange(0.0, 30.01, 0.5), 3), np.full(40, 12.5),
                7.5 - 1e-9, 17.5 + 1e-9]
    t_s = t_s[rng.permutation(t_s.size)]
    xy = rng.uniform(-900.0, 900.0, (t_s.size, 2))
    out = _broad(xy, t_s, frame_t_s, np.zeros(t_s.size), min_tracks=10**6)
    half = 0.5 * BroadErrorSettings().window_s
    judged = (frame_t_s - half >= 0.0) & (frame_t_s + half <= frame_t_s[-1])
    expected = [int(np.sum(np.abs(t_s - f) <= half)) if j else 0
                for f, j in zip(frame_t_s, judged)]
    assert out.n_tracks.tolist() == expected
    nothing = _broad(xy, t_s, frame_t_s, np.full(t_s.size, np.nan))
    assert not nothing.n_tracks.any() and np.isnan(nothing.evidence).all()


def test_the_watch_judges_each_window_once_it_has_closed(rng):
    """:class:`BroadMapWatch` (the fixed lag's statistic, taken as the run goes): a frame
    is due once the newest frame lies half a window past it and its window began after
    the poses settled (``judged_from``), and only once; judged in rounds, the frames read
    what :func:`broad_map_error` reads over the same tracks at once, and the evidence is
    its 5 s mean. Mutations tried (2026-11-28): the settled start dropped from ``due`` ->
    frames 0-9 due: fails; ``next_frame`` not advanced -> frames judged again: fails; the
    evidence left as the windows' statistic (no 5 s mean in ``result``): fails."""
    frame_t_s = np.arange(0.0, 40.01, 1.0)
    t_s = rng.uniform(0.0, 40.0, 4000)
    xy = rng.uniform(-900.0, 900.0, (t_s.size, 2))
    dh = 2.0 * (xy[:, 0] / 1000.0) ** 2 + rng.normal(0.0, 3.0, t_s.size)  # a bowl, seen
    heights = TrackHeights(np.arange(t_s.size), np.column_stack([xy, np.zeros(t_s.size)]),
                           np.full(t_s.size, 8), dh, np.full(t_s.size, 3.0),
                           np.zeros(t_s.size))
    tilt = np.tile(np.eye(2) * ATTITUDE_TILT_M**2, (frame_t_s.size, 1, 1))
    at_once = broad_map_error(heights, t_s, frame_t_s, tilt)
    watch = BroadMapWatch(BroadErrorSettings(), MismatchSettings())
    assert watch.due(frame_t_s[:20], None).size == 0  # the poses not settled: nothing
    judged: list[int] = []
    for k in range(5, 41, 5):  # a round every 5 frames, the poses settled at frame 5
        due = watch.due(frame_t_s[:k + 1], 5)
        judged += due.tolist()
        watch.judge(due, heights, t_s, frame_t_s[:k + 1], tilt[due])
    assert judged == list(range(10, 36))  # windows inside [frame 5, frame 40]
    out = watch.result((frame_t_s * 1e9).astype(np.int64))
    np.testing.assert_allclose(out.shape_chi2[10:36], at_once.shape_chi2[10:36], rtol=1e-12)
    assert np.isnan(out.shape_chi2[:10]).all() and np.isnan(out.shape_chi2[36:]).all()
    np.testing.assert_allclose(out.evidence[12:34], at_once.evidence[12:34], rtol=1e-12)
    assert np.isnan(out.evidence[:12]).all() and np.nanmax(out.evidence) > EVIDENCE_BOUND


@pytest.mark.slow  # three 90-frame fixed-lag flights smoothed (8 s)
@pytest.mark.parametrize("scenario, seed, named, frame", [
    ("hill15", 2, True, 51), ("clean", 15, False, None),
    ("hill15", 8, True, 46),  # the seed the watch alone missed (2026-11-28)
])
def test_a_fixed_lag_reads_the_maps_shape_at_the_poses_it_holds(scenario, seed, named, frame):
    """A fixed lag's frames keep the estimates they left the window with; tracks
    triangulated at those poses read their relative errors as shape (clean seed 15: 24.4,
    above 12 over 2.1 km: the batch's bounds would name it), so the verdict held the fixed
    lag to 28 and no sustained bound, and missed the robustness study's hill on seed 2
    (21.7; ANEES 10.2, ``trusted`` without ground truth). Taken as it goes, at the poses
    one update holds (:class:`BroadMapWatch`), the batch's bounds apply: the hill (19.4 at
    frame 51, above 12 for 1.95 km) is named, the clean flight (6.2) is not (measured
    2026-11-28). Mutation tried: the watch off (the statistic after the run, at the exit
    poses, judged by the same bounds) -> clean seed 15 named: fails. The watch missed the
    hill on seed 8 (14.9, above 12 for 600 m; ANEES 12.3, ``trusted``): the run's shape is
    also read at the calibration check's batch solve of the whole flight
    (``broad_map_error_whole``: 18.8 at frame 46, above 12 for 1651 m), and either names
    it (the clean flight reads 6.2 and less there). Mutation: that reading left out of
    the verdict -> seed 8 not named: fails."""
    flight, dtm = SCENARIOS[scenario].flight(dataclasses.replace(BASE, frames=90, seed=seed))
    out = smooth_and_evaluate(flight, dtm, Mode.FIXED_LAG.settings(SmootherSettings()))
    assert out.errors is not None and (out.errors.anees_position > 6.0) is named
    broad = out.result.broad_map_error
    assert broad is not None and np.isfinite(broad.evidence).sum() > 50
    verdict = assess(out.result)  # no ground truth
    codes = [r.code for r in verdict.reasons]
    assert ("broad_map_error" in codes) is named, verdict.lines()
    if named:
        reason = next(r for r in verdict.reasons if r.code == "broad_map_error")
        assert reason.first_frame <= frame <= reason.last_frame, reason


def test_the_map_sigma_is_solved_to_its_tolerance_and_ends_on_any_bound():
    """The bisection behind the map sigma (:func:`_decreasing_root`, scipy's brentq before
    2026-11-28): the median of ``d / s^2`` over equal heights at chi-square(1)'s median
    (``s = sqrt(d / target)``, where brentq raised on the round-off of ``f(high)``), to
    ``SIGMA_TOL_M``; an infinite bound (heights beyond floating point) ends after its 200
    halvings. Mutations tried: ``low = mid`` and ``high = mid`` swapped, the cap removed
    (the second call never returns): each fails."""
    d, target = np.full(11, 49.51), 0.4549364231195724
    root = _decreasing_root(lambda s: float(np.median(d / s**2)) - target, 1e-9,
                            float(np.sqrt(d.max() / target)) * 2, SIGMA_TOL_M)
    assert abs(root - np.sqrt(49.51 / target)) <= SIGMA_TOL_M
    assert _decreasing_root(lambda s: -1.0, 0.0, math.inf, SIGMA_TOL_M) == math.inf
