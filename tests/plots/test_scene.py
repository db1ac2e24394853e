"""``cdtm smooth --scene``: scene.glb loads back with trimesh and holds the run's geometry."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from cdtm_graph.cli import main
from cdtm_graph.data import sample_flight_path
from cdtm_graph.outputs import read_trajectory_cov
from cdtm_graph.plots.scene import FOOTPRINT_LIFT_M, MAX_TERRAIN_SIDE, WORLD_TO_GLTF, scene_frames
from cdtm_graph.run.prepare import load_log_and_dtm

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = sample_flight_path()
#: glTF stores float32: within 10 km of the offset, a few millimetres.
FLOAT32_TOL_M = 5e-3


def _world(scene: trimesh.Scene, name: str) -> np.ndarray:
    """A node's vertices back in the world frame (east, north, up)."""
    offset = np.asarray(scene.metadata["world_offset_m"])
    return np.asarray(scene.geometry[name].vertices, dtype=float) @ WORLD_TO_GLTF + offset


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> tuple[Path, trimesh.Scene]:
    out = tmp_path_factory.mktemp("scene") / "run"
    assert main(["smooth", str(SAMPLE), "--out", str(out), "--scene", "--scene-every", "10",
                 "--quiet"]) == 0
    return out, trimesh.load(out / "scene.glb", file_type="glb")


def test_the_scene_holds_terrain_trajectories_ellipsoids_and_footprints(run):
    out, scene = run
    frames = [0, 10, 20, 30, 39]  # 40 frames, every 10, and the last
    expected = {"terrain", "trajectory_estimated", "trajectory_estimated_line",
                "trajectory_true", "trajectory_true_line",
                *(f"sigma3_frame_{k:05d}" for k in frames),
                *(f"footprint_frame_{k:05d}" for k in frames)}
    assert set(scene.geometry) == expected
    assert '"scene.glb": "smooth"' in (out / ".cdtm-run.json").read_text()


def test_the_estimated_line_passes_through_the_smoothed_positions(run):
    out, scene = run
    _, poses, _, _ = read_trajectory_cov(out / "trajectory_cov.txt")
    line = _world(scene, "trajectory_estimated_line")
    positions = poses[:, :3, 3]
    # every smoothed position is a vertex of the line, and nothing else is
    gap = np.linalg.norm(line[:, None, :] - positions[None, :, :], axis=2)
    assert gap.min(axis=0).max() < FLOAT32_TOL_M and gap.min(axis=1).max() < FLOAT32_TOL_M
    tube = _world(scene, "trajectory_estimated")
    assert np.all(tube.min(axis=0) < positions.min(axis=0))  # the tube encloses the line
    assert np.all(tube.max(axis=0) > positions.max(axis=0))


def test_ellipsoids_are_the_3_sigma_surfaces_of_the_position_covariance(run):
    out, scene = run
    _, poses, _, position_cov = read_trajectory_cov(out / "trajectory_cov.txt")
    for k in (0, 20, 39):
        vertices = _world(scene, f"sigma3_frame_{k:05d}") - poses[k, :3, 3]
        info = np.linalg.inv(position_cov[k])  # world frame
        mahalanobis = np.sqrt(np.einsum("ni,ij,nj->n", vertices, info, vertices))
        np.testing.assert_allclose(mahalanobis, 3.0, rtol=0, atol=3e-3)


def test_terrain_and_footprints_lie_on_the_dtm(run):
    _, scene = run
    _, dtm = load_log_and_dtm(SAMPLE)
    terrain = _world(scene, "terrain")
    assert len(terrain) <= MAX_TERRAIN_SIDE ** 2
    xmin, xmax, ymin, ymax = dtm.bounds  # float32 puts edge samples a hair outside
    x, y = np.clip(terrain[:, 0], xmin, xmax), np.clip(terrain[:, 1], ymin, ymax)
    np.testing.assert_allclose(terrain[:, 2], dtm.height(x, y), atol=FLOAT32_TOL_M)
    colours = scene.geometry["terrain"].visual.vertex_colors
    assert len(np.unique(colours[:, :3], axis=0)) > 100  # shaded, not one flat colour
    lo, hi = terrain.min(axis=0), terrain.max(axis=0)
    for k in (0, 39):
        corners = _world(scene, f"footprint_frame_{k:05d}")
        assert len(corners) == 4
        np.testing.assert_allclose(corners[:, 2] - dtm.height(corners[:, 0], corners[:, 1]),
                                   FOOTPRINT_LIFT_M, atol=FLOAT32_TOL_M)
        assert np.all(corners[:, :2] >= lo[:2]) and np.all(corners[:, :2] <= hi[:2])


@pytest.mark.parametrize("k_frames, every, expected", [
    (40, 10, [0, 10, 20, 30, 39]), (41, 10, [0, 10, 20, 30, 40]), (3, 1, [0, 1, 2]),
    (2, 5, [0, 1])])
def test_scene_frames(k_frames, every, expected):
    assert scene_frames(k_frames, every).tolist() == expected
