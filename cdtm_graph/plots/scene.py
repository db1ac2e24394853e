"""A 3-D scene of a run for people who would rather look: ``scene.glb`` (glTF 2.0, trimesh).

What it holds (node names, for a viewer's outline):

* ``terrain``: the DTM under the flight (cropped to the track and the camera footprints
  plus a margin, decimated to at most :data:`MAX_TERRAIN_SIDE` samples a side), coloured
  by height and shaded by a hillshade (sun from the north-west, as the 2-D plots);
* ``trajectory_estimated`` (a tube) and ``trajectory_estimated_line`` (the polyline through
  the smoothed positions); ``trajectory_true`` and ``trajectory_true_line`` with ground
  truth, at the frame times;
* ``sigma3_frame_NNNNN``: the 3-sigma position ellipsoid of every N-th frame, true size
  (metres; zoom in: a few metres against kilometres of terrain);
* ``footprint_frame_NNNNN``: the quad the image corners see on the DTM from the smoothed
  camera pose, for the same frames (left out where a corner's ray misses the terrain).

Coordinates: glTF is y-up, so a world point (east, north, up) is stored as
``(east - e0, up - u0, -(north - n0))``, metres, with the offset ``(e0, n0, u0)`` (the first
smoothed position) in the scene's ``extras.world_offset_m``: float32 keeps millimetres
within 10 km of it. Any glTF viewer (Blender, three.js editor, gltf-viewer web pages) opens it.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np
import trimesh
from matplotlib import colormaps
from matplotlib.colors import LightSource, Normalize

from cdtm_graph.dtm import Dtm
from cdtm_graph.flightlog import CameraConfig, States
from cdtm_graph.results import TrajectoryEstimate, pose_covariance_in_world

#: The terrain mesh has at most this many samples along a side (decimated beyond it).
MAX_TERRAIN_SIDE = 400
#: Terrain kept around the track and the footprints, as a fraction of their extent.
TERRAIN_MARGIN = 0.15
N_SIGMA = 3.0
#: Tube radius as a fraction of the scene's horizontal extent (at least 0.5 m).
TUBE_RADIUS_FRACTION = 1.5e-3
#: Footprints float this far above the terrain (m) so that they do not flicker into it.
FOOTPRINT_LIFT_M = 1.0
#: Colours (RGBA, 0-255).
ESTIMATED_RGBA = (31, 119, 180, 255)
TRUE_RGBA = (44, 160, 44, 255)
ELLIPSOID_RGBA = (255, 127, 14, 160)
FOOTPRINT_RGBA = (214, 39, 40, 90)

#: World (east, north, up) -> glTF (x right, y up, z toward the viewer).
WORLD_TO_GLTF = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class SceneSettings:
    """What goes into the scene.

    Attributes:
        every: an ellipsoid and a footprint every this many frames (and the last frame).
        n_sigma: the ellipsoids' size in sigmas.
    """

    every: int = 10
    n_sigma: float = N_SIGMA

    def __post_init__(self) -> None:
        if not (isinstance(self.every, int) and self.every >= 1):
            raise ValueError(f"every = {self.every!r}, expected an integer >= 1")


def scene_frames(k_frames: int, every: int) -> np.ndarray:
    """The frames that get an ellipsoid and a footprint: 0, every, 2 every, ..., and the last."""
    frames = np.arange(0, k_frames, every)
    return frames if frames[-1] == k_frames - 1 else np.append(frames, k_frames - 1)


def build_scene(dtm: Dtm, estimate: TrajectoryEstimate, pose_cov: np.ndarray,
                camera: CameraConfig, groundtruth: States | None = None,
                settings: SceneSettings | None = None) -> trimesh.Scene:
    """The scene of a smoothed run (module docstring).

    Args:
        dtm: the world DTM the run used.
        estimate: the smoothed trajectory, K frames.
        pose_cov: (K, 6, 6) pose covariances, GTSAM tangent order (body frame).
        camera: the camera and its mounting (the footprints).
        groundtruth: true states (interpolated to the frame times inside their span), or None.
        settings: what goes in.

    Returns:
        A trimesh scene in glTF's y-up axes, offset by ``metadata["world_offset_m"]``.
    """
    settings = settings or SceneSettings()
    world_T_body = np.asarray(estimate.world_T_body)
    positions = world_T_body[:, :3, 3]
    _, pos_cov = pose_covariance_in_world(world_T_body, np.asarray(pose_cov))
    frames = scene_frames(len(positions), settings.every)
    world_T_cam = world_T_body[frames] @ camera.body_T_cam
    footprints = {int(k): quad for k, quad in zip(frames, _footprints(dtm, camera,
                                                                        world_T_cam))
                  if quad is not None}
    truth = None
    if groundtruth is not None:
        t = np.asarray(estimate.t_ns)
        inside = (t >= groundtruth.t_ns[0]) & (t <= groundtruth.t_ns[-1])
        if inside.sum() >= 2:
            truth = groundtruth.interpolate(t[inside]).position_m

    seen = [positions] + list(footprints.values()) + ([truth] if truth is not None else [])
    xy = np.concatenate([p[:, :2] for p in seen])
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    extent = float(max(np.max(hi - lo), 10.0 * dtm.grid_spacing_m))
    offset = positions[0].copy()
    radius = max(0.5, TUBE_RADIUS_FRACTION * extent)

    def to_gltf(points: np.ndarray) -> np.ndarray:
        return (np.asarray(points, dtype=float) - offset) @ WORLD_TO_GLTF.T

    scene = trimesh.Scene()
    scene.metadata.update({
        "generator": "cdtm smooth --scene",
        "world_offset_m": offset.tolist(),
        "axes": "glTF y-up: x = east - e0, y = up - u0, z = -(north - n0), metres",
        "ellipsoids": f"{settings.n_sigma:g}-sigma position, true size, every "
                      f"{settings.every} frames",
    })
    terrain = _terrain_mesh(dtm, lo - TERRAIN_MARGIN * extent, hi + TERRAIN_MARGIN * extent)
    if terrain is not None:
        terrain.vertices = to_gltf(terrain.vertices)
        _add(scene, "terrain", terrain)
    for name, points, rgba in (("trajectory_estimated", positions, ESTIMATED_RGBA),
                               ("trajectory_true", truth, TRUE_RGBA)):
        if points is None or len(points) < 2:
            continue
        _add(scene, name, _tube(to_gltf(points), radius, rgba))
        _add(scene, f"{name}_line", trimesh.load_path(to_gltf(points)))
    for k in frames:
        ellipsoid = _ellipsoid(positions[k], pos_cov[k], settings.n_sigma)
        ellipsoid.vertices = to_gltf(ellipsoid.vertices)
        _add(scene, f"sigma3_frame_{k:05d}", ellipsoid)
    for k, quad in footprints.items():
        _add(scene, f"footprint_frame_{k:05d}", _quad(to_gltf(quad)))
    return scene


def write_scene(path: str | os.PathLike, dtm: Dtm, estimate: TrajectoryEstimate,
                pose_cov: np.ndarray, camera: CameraConfig, groundtruth: States | None = None,
                settings: SceneSettings | None = None) -> None:
    """Write :func:`build_scene`'s scene as a binary glTF (``.glb``) file."""
    scene = build_scene(dtm, estimate, pose_cov, camera, groundtruth, settings)
    with open(path, "wb") as f:
        f.write(scene.export(file_type="glb"))


def _add(scene: trimesh.Scene, name: str, geometry) -> None:
    scene.add_geometry(geometry, node_name=name, geom_name=name)


def _terrain_mesh(dtm: Dtm, lo: np.ndarray, hi: np.ndarray) -> trimesh.Trimesh | None:
    """The DTM inside [lo, hi] (x, y), decimated, with hillshaded height colours."""
    rows, cols = dtm.shape
    x = dtm.x0 + dtm.dx * np.arange(cols)
    y = dtm.y0 + dtm.dy * np.arange(rows)
    c = np.flatnonzero((x >= lo[0] - abs(dtm.dx)) & (x <= hi[0] + abs(dtm.dx)))
    r = np.flatnonzero((y >= lo[1] - abs(dtm.dy)) & (y <= hi[1] + abs(dtm.dy)))
    if c.size < 2 or r.size < 2:
        return None
    step = max(1, math.ceil(max(c.size, r.size) / MAX_TERRAIN_SIDE))
    c, r = c[::step], r[::step]
    z = np.asarray(dtm.elevation)[np.ix_(r, c)]
    if np.count_nonzero(np.isfinite(z)) < 4:
        return None
    sub = Dtm(z, float(x[c[0]]), float(y[r[0]]), dtm.dx * step, dtm.dy * step)
    mesh = sub.to_trimesh()
    if len(mesh.faces) == 0:
        return None
    # LightSource wants rows north to south; the colours go back to the grid's order.
    flip_rows = sub.dy > 0
    grid = z[::-1] if flip_rows else z
    filled = np.where(np.isfinite(grid), grid, np.nanmean(grid))
    finite = filled[np.isfinite(filled)]
    norm = Normalize(float(finite.min()), float(max(finite.max(), finite.min() + 1.0)))
    rgb = LightSource(azdeg=315, altdeg=45).shade(
        filled, cmap=colormaps["gist_earth"], norm=norm, blend_mode="soft",
        dx=abs(sub.dx), dy=abs(sub.dy))[..., :3]
    if flip_rows:
        rgb = rgb[::-1]
    if sub.dx < 0:  # (LightSource assumes columns west to east)
        rgb = rgb[:, ::-1]
    rr, cc = np.nonzero(np.isfinite(z))  # to_trimesh's vertex order
    colours = np.column_stack([np.round(rgb[rr, cc] * 255), np.full(rr.size, 255)])
    return _mesh(mesh.vertices, mesh.faces, colours.astype(np.uint8))


def _tube(points: np.ndarray, radius: float, rgba: tuple[int, ...]) -> trimesh.Trimesh:
    """A tube along a polyline: one open cylinder per segment (zero-length ones skipped)."""
    vertices, faces = [], []
    n = 0
    for a, b in zip(points[:-1], points[1:]):
        if np.linalg.norm(b - a) > 1e-9:
            part = trimesh.creation.cylinder(radius=radius, segment=np.array([a, b]),
                                             sections=12)
            vertices.append(part.vertices)
            faces.append(part.faces + n)
            n += len(part.vertices)
    return _mesh(np.concatenate(vertices), np.concatenate(faces), rgba)


def _ellipsoid(centre: np.ndarray, cov: np.ndarray, n_sigma: float) -> trimesh.Trimesh:
    """The n-sigma surface of a 3-D Gaussian: ``centre + n V sqrt(L) u`` for unit u."""
    eigval, eigvec = np.linalg.eigh(0.5 * (cov + cov.T))
    axes = eigvec * (n_sigma * np.sqrt(np.clip(eigval, 0.0, None)))
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    return _mesh(sphere.vertices @ axes.T + centre, sphere.faces.copy(), ELLIPSOID_RGBA)


def _footprints(dtm: Dtm, camera: CameraConfig, world_T_cam: np.ndarray) -> list:
    """(4, 3) terrain points seen by the image corners from each pose, or None."""
    cam = camera.camera
    corners = np.array([[-0.5, -0.5], [cam.width - 0.5, -0.5],
                        [cam.width - 0.5, cam.height - 0.5], [-0.5, cam.height - 0.5]])
    rays = cam.pixels_to_rays(corners)
    if not np.all(np.isfinite(rays)):  # a fisheye's corners beyond 90 degrees: the edge
        centre = np.array([cam.cx, cam.cy])  # midpoints half-way out see the ground
        rays = cam.pixels_to_rays(centre + 0.5 * (corners - centre))
    out: list = []
    for T in world_T_cam:
        directions = rays @ T[:3, :3].T
        hits = dtm.raycast(np.tile(T[:3, 3], (4, 1)), directions)
        ok = np.all(np.isfinite(hits.point))
        out.append(hits.point + [0.0, 0.0, FOOTPRINT_LIFT_M] if ok else None)
    return out


def _quad(corners: np.ndarray) -> trimesh.Trimesh:
    """Two triangles over four corners, seen from both sides (both windings)."""
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 2, 1], [0, 3, 2]])
    return _mesh(corners, faces, FOOTPRINT_RGBA)


def _mesh(vertices: np.ndarray, faces: np.ndarray,
          colours: np.ndarray | tuple[int, ...]) -> trimesh.Trimesh:
    """A mesh with per-vertex RGBA colours: (N, 4) uint8, or one colour for all."""
    rgba = np.asarray(colours, dtype=np.uint8)
    if rgba.ndim == 1:
        rgba = np.tile(rgba, (len(vertices), 1))
    return trimesh.Trimesh(vertices=vertices, faces=faces, vertex_colors=rgba, process=False)
