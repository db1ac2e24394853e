"""Lens models end to end: a log simulated through an equidistant (fisheye) lens smooths as
accurately as one through a radtan lens, and only when flight.yaml states the lens."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cdtm_graph.camera import DistortionModel
from cdtm_graph.dtm import save_dtm_npz
from cdtm_graph.errors import SimulationError
from cdtm_graph.flightlog import read_flightlog, write_flightlog
from cdtm_graph.run import smooth_and_evaluate
from cdtm_graph.sim.simulate import DTM_FILENAME, SimulationSettings, simulate
from cdtm_graph.smoother import SmootherSettings

#: EuRoC MH cam0 (Kalibr pinhole-radtan) and TUM-VI cam0 (Kalibr pinhole-equidistant).
RADTAN = ("radtan", (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05))
EQUIDISTANT = ("equidistant", (0.0034823894022493434, 0.0007150348452162257,
                               -0.0020532361418706202, 0.00020293673591811182))
#: The seeds of the measurement below and of docs/flightlog.md: the literal seeds are the
#: point (the figures quoted are these flights').
SEEDS = (0, 1, 2, 3)
#: Short flights (12 frames, 80 features a pair): the 3-D position RMSE is 1-5 m, against
#: a 50 m prior. Measured (seeds 0-3): radtan 3.44/5.05/3.62/2.37 m, equidistant
#: 1.15/1.81/2.29/2.56 m; stating no lens for the equidistant logs: 203-243 m.
FRAMES, FEATURES = 12, 80
#: The equidistant mean may exceed the radtan mean by this factor at most.
ACCURACY_RATIO = 1.5
#: Regression bound: 1.3x the worst 3-D RMSE (m) of the eight runs, 4.30 measured
#: 2026-11-27 (radtan).
MAX_RMSE_M = 1.3 * 4.30


def _settings(lens: tuple[str, tuple[float, ...]], seed: int) -> SimulationSettings:
    return SimulationSettings(frames=FRAMES, n_features=FEATURES, seed=seed,
                              distortion_model=lens[0], distortion_coeffs=lens[1])


def _rmse_3d_m(log, dtm) -> float:
    out = smooth_and_evaluate(log, dtm, SmootherSettings())
    return float(np.linalg.norm(out.errors.rmse_position_m))


def test_the_simulator_projects_through_the_lens():
    result = simulate(_settings(EQUIDISTANT, SEEDS[0]))
    camera = result.log.config.camera.camera
    assert camera.model is DistortionModel.EQUIDISTANT
    tracks = result.log.tracks
    ground = result.ground_points_m[tracks.track_id]
    world_T_cam = result.world_T_cam[tracks.frame]
    in_cam = np.einsum("nji,nj->ni", world_T_cam[:, :3, :3], ground - world_T_cam[:, :3, 3])
    np.testing.assert_allclose(camera.rays_to_pixels(in_cam), result.uv_true_px, atol=1e-9)
    plain = dataclasses.replace(camera, distortion=(), distortion_model="none")
    assert np.abs(plain.rays_to_pixels(in_cam) - result.uv_true_px).max() > 10.0


@pytest.mark.slow
def test_an_equidistant_log_smooths_as_accurately_as_a_radtan_one(tmp_path):
    rmse: dict[str, list[float]] = {"radtan": [], "equidistant": [], "unstated": []}
    for seed in SEEDS:
        for name, lens in (("radtan", RADTAN), ("equidistant", EQUIDISTANT)):
            result = simulate(_settings(lens, seed))
            log = result.log
            if seed == 0:  # through the files: flight.yaml carries the lens
                write_flightlog(log, tmp_path / name)
                save_dtm_npz(result.dtm, tmp_path / name / DTM_FILENAME)
                assert read_flightlog(tmp_path / name).config.camera.camera == \
                    log.config.camera.camera
            rmse[name].append(_rmse_3d_m(log, result.dtm))
            if name == "equidistant":
                cam = log.config.camera
                unstated = dataclasses.replace(cam, camera=dataclasses.replace(
                    cam.camera, distortion=(), distortion_model="none"))
                wrong = dataclasses.replace(log, config=dataclasses.replace(log.config,
                                                                            camera=unstated))
                rmse["unstated"].append(_rmse_3d_m(wrong, result.dtm))
    mean = {name: float(np.mean(values)) for name, values in rmse.items()}
    assert max(rmse["radtan"] + rmse["equidistant"]) < MAX_RMSE_M, rmse
    assert mean["equidistant"] <= ACCURACY_RATIO * mean["radtan"], rmse
    assert mean["unstated"] > 20.0 * mean["equidistant"], rmse


@pytest.mark.parametrize("lens", [("equidistant", (0.1, 0.0, 0.0)), ("fisheye", (0.1,) * 4)])
def test_the_simulator_refuses_a_bad_lens(lens):
    with pytest.raises(SimulationError, match="distortion"):
        _settings(lens, 0)


def test_cdtm_simulate_takes_the_lens(tmp_path, capsys):
    from cdtm_graph.cli import main

    coeffs = [str(c) for c in EQUIDISTANT[1]]
    assert main(["simulate", str(tmp_path / "fisheye"), "--frames", "3", "--features", "40",
                 "--distortion-model", "equidistant", "--distortion-coeffs", *coeffs]) == 0
    camera = read_flightlog(tmp_path / "fisheye").config.camera.camera
    assert camera.model is DistortionModel.EQUIDISTANT
    assert camera.distortion == EQUIDISTANT[1]
    assert main(["simulate", str(tmp_path / "bad"), "--distortion-model", "equidistant",
                 "--distortion-coeffs", "0.1"]) == 1
    assert "must have 4 coefficients" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
