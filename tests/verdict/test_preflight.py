"""cdtm_graph.verdict.preflight: no IMU-only result presented as a smoothing result; DTM
coverage."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cdtm_graph.dtm import Dtm
from cdtm_graph.errors import FlightLogError, NoConstraintError
from cdtm_graph.flightlog import FlightLog, Tracks
from cdtm_graph.sim.simulate import SimulationResult, SimulationSettings, simulate
from cdtm_graph.smoother import SmootherSettings, smooth
from cdtm_graph.verdict.preflight import check_constraints, dtm_coverage


@pytest.fixture(scope="module")
def sim(seed) -> SimulationResult:
    return simulate(SimulationSettings(frames=8, n_features=40, seed=seed % 997,
                                       noiseless=True, turn_deg=0.0))


def _true_body_poses(sim: SimulationResult) -> np.ndarray:
    return sim.world_T_cam @ np.linalg.inv(sim.log.config.camera.body_T_cam)


def _shifted(dtm: Dtm, dx_m: float = 0.0, dz_m: float = 0.0) -> Dtm:
    return Dtm(dtm.elevation + dz_m, dtm.x0 + dx_m, dtm.y0, dtm.dx, dtm.dy, dtm.sigma_h_m)


def test_every_observation_meets_the_dtm_from_the_true_poses(sim):
    coverage = dtm_coverage(sim.log, sim.dtm, _true_body_poses(sim))
    np.testing.assert_array_equal(coverage.n_observations,
                                  np.bincount(sim.log.tracks.frame, minlength=8))
    np.testing.assert_array_equal(coverage.n_on_dtm, coverage.n_observations)
    assert coverage.frames_off_dtm.size == 0


def test_partial_coverage_is_not_refused_and_names_the_frames_off_the_dtm(sim):
    """A DTM that ends mid-flight: the check passes (the verdict's business), and the
    coverage from the true poses says which frames see no DTM."""
    poses = _true_body_poses(sim)
    x_mid = float(np.mean(poses[[3, 4], 0, 3]))
    cols = int(np.floor((x_mid - sim.dtm.x0) / sim.dtm.dx))  # the flight goes east
    cropped = Dtm(sim.dtm.elevation[:, :cols], sim.dtm.x0, sim.dtm.y0, sim.dtm.dx,
                  sim.dtm.dy, sim.dtm.sigma_h_m)
    check_constraints(sim.log, cropped)  # no error
    coverage = dtm_coverage(sim.log, cropped, poses)
    fraction = coverage.fraction
    assert fraction[0] == 1.0 and 0 < coverage.frames_off_dtm.size
    assert np.all(coverage.frames_off_dtm >= 4)
    assert np.all(np.diff(fraction[~np.isnan(fraction)]) <= 0)  # less and less on the DTM


def test_a_dtm_elsewhere_is_refused_with_where_both_are(sim):
    with pytest.raises(NoConstraintError) as info:
        check_constraints(sim.log, _shifted(sim.dtm, dx_m=5e5))
    message = str(info.value)
    assert "no observed ray meets the DTM" in message and "dtm.origin_enu_m" in message
    assert "\n" not in message


def test_a_flight_below_the_terrain_is_told_so(sim):
    with pytest.raises(NoConstraintError, match="below the terrain"):
        check_constraints(sim.log, _shifted(sim.dtm, dz_m=5000.0))


def test_without_frame_0_observations_the_check_uses_dead_reckoning(sim):
    tracks = sim.log.tracks
    keep = tracks.frame > 0
    log = dataclasses.replace(sim.log, tracks=Tracks(tracks.frame[keep], tracks.track_id[keep],
                                                     tracks.uv_px[keep]))
    coverage = check_constraints(log, sim.dtm)
    assert coverage.n_observations[0] == 0 and coverage.n_on_dtm.sum() > 0
    with pytest.raises(NoConstraintError):
        check_constraints(log, _shifted(sim.dtm, dx_m=5e5))


@pytest.mark.parametrize("case, words", [
    ("no tracks", "cdtm track"),
    ("empty tracks", "no observations"),
    ("single sightings", "no track is seen in two frames"),
])
def test_library_smooth_refuses_a_log_without_constraint(sim, case, words):
    """The same error for library users as on the command line, before any solving."""
    tracks = sim.log.tracks
    if case == "no tracks":
        changed: Tracks | None = None
    elif case == "empty tracks":
        changed = Tracks(tracks.frame[:0], tracks.track_id[:0], tracks.uv_px[:0])
    else:
        changed = Tracks(tracks.frame, np.arange(len(tracks)), tracks.uv_px)
    log: FlightLog = dataclasses.replace(sim.log, tracks=changed)
    with pytest.raises(NoConstraintError, match=words):
        smooth(log, sim.dtm, SmootherSettings())


@pytest.mark.parametrize("end", ["first", "last"])
def test_a_frame_outside_the_imus_span_is_one_line_naming_the_log(sim, end):
    """Frames moved off the IMU's clock (a camera stamp on another epoch, a wrong
    camera.time_offset_s) so that the first or the last lies outside imu.csv's samples:
    refused before any solving with frames.csv's path, the frame and both spans. Mutation
    tried: the check off (a solver error about a frame interval, naming no file: a
    hostile-input hunt's find, 2026-11-28)."""
    frames = sim.log.frames
    imu_t = sim.log.imu.t_ns
    shift = (imu_t[0] - frames.t_ns[0] - 1) if end == "first" else (imu_t[-1] - frames.t_ns[-1] + 1)
    moved = dataclasses.replace(sim.log, frames=dataclasses.replace(
        frames, t_ns=frames.t_ns + shift))
    with pytest.raises(FlightLogError) as info:
        smooth(moved, sim.dtm, SmootherSettings())
    message = str(info.value)
    k = 0 if end == "first" else len(frames) - 1
    assert "frames.csv: frame " + str(k) in message and "imu.csv's samples" in message
    assert "; expected every frame within the IMU's span" in message and "\n" not in message
