"""Two-frame scenarios of the paper's section VI: terrain, camera pair, matched features.

The nominal scenario: 400x400 px, FOV 60 degrees, 500 m above a 3x3 km terrain of
300 m relief, 30 m DTM grid (sigma_h about 2.4 m), about 170 features, |p12| = 40 m,
10 degrees of rotation between the frames, half-pixel registration error.

The DTM error follows one of two models (:class:`DtmErrorModel`):

* MODEL (default): the paper's error model (eqs. 23-26). The DTM is the solver's
  terrain; each feature's true ground point sits on the DTM's tangent plane raised
  by its own ``N(0, sigma_h)`` height error, i.e. shifted along the camera-1 ray by
  ``dh R1 q1 / N.R1 q1``. Errors are independent between features, as eq. 13 assumes.
* RESAMPLED: the true terrain is the fine fractal surface; the solver gets it
  resampled to the DTM grid spacing, so the error is the real interpolation error
  (spatially correlated; sigma_h from the Fig. 6 model).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, replace

import numpy as np

from cdtm_graph.camera import DOWNWARD_BODY_T_CAM, PinholeCamera
from cdtm_graph.dtm import OCCLUSION_TOLERANCE_M, Dtm, sigma_h_from_grid_spacing, visible_from
from cdtm_graph.geometry import make_pose, so3_exp
from cdtm_graph.graph import dtm_ray_caster  # noqa: F401  (re-exported for scenario users
from cdtm_graph.sim.terrain import fractal_terrain
from factors import FeatureNoise


class DtmErrorModel(enum.Enum):
    MODEL = "model"
    RESAMPLED = "resampled"


@dataclass(frozen=True)
class PairScenario:
    """A two-frame scenario; the defaults are the paper's nominal one (section VI).

    Attributes:
        resolution_px: image width = height in pixels.
        fov_deg: horizontal field of view.
        altitude_m: height of camera 1 above the terrain's mean height.
        terrain_size_m, relief_m, correlation_length_m: the fractal terrain.
        fine_spacing_m: spacing of the true (fine) terrain.
        grid_spacing_m: DTM grid spacing.
        n_features: features requested (those visible in both frames are kept).
        baseline_m: ``|p12|``, mostly along track.
        rotation_deg: ``|(phi12, theta12, psi12)|``.
        pixel_sigma_px: registration error (1 sigma, pixels) on the second frame's points.
        sigma_h_m: DTM height error; ``None`` uses the Fig. 6 model of the grid spacing.
        dtm_error: how the DTM error is simulated.
        initial_position_error_m, initial_attitude_error_deg: 1-sigma of the initial guess.
        noiseless: draw no pixel or DTM error (the estimator still assumes the noise above).
    """

    resolution_px: int = 400
    fov_deg: float = 60.0
    altitude_m: float = 500.0
    terrain_size_m: float = 3000.0
    relief_m: float = 300.0
    correlation_length_m: float | None = None
    fine_spacing_m: float = 5.0
    grid_spacing_m: float = 30.0
    n_features: int = 170
    baseline_m: float = 40.0
    rotation_deg: float = 10.0
    pixel_sigma_px: float = 0.5
    sigma_h_m: float | None = None
    dtm_error: DtmErrorModel = DtmErrorModel.MODEL
    initial_position_error_m: float = 5.0
    initial_attitude_error_deg: float = 0.5
    noiseless: bool = False

    def with_(self, **changes) -> PairScenario:
        return replace(self, **changes)

    @property
    def camera(self) -> PinholeCamera:
        return PinholeCamera.from_fov(self.resolution_px, self.resolution_px, self.fov_deg)

    @property
    def sigma_h(self) -> float:
        return (sigma_h_from_grid_spacing(self.grid_spacing_m) if self.sigma_h_m is None
                else self.sigma_h_m)

    @property
    def noise(self) -> FeatureNoise:
        """The data noise the estimator assumes (``q_a`` exact, as the paper)."""
        return FeatureNoise(self.camera.sigma_normalized(self.pixel_sigma_px), self.sigma_h)


@dataclass(frozen=True)
class ScenarioTerrain:
    """The true terrain and the DTM the solver uses."""

    truth: Dtm
    dtm: Dtm


def make_terrain(scenario: PairScenario, seed: int) -> ScenarioTerrain:
    """Fractal terrain of the scenario and its DTM (resampled to the grid spacing)."""
    kwargs = {}
    if scenario.correlation_length_m is not None:
        kwargs["correlation_length_m"] = scenario.correlation_length_m
    half = scenario.terrain_size_m / 2
    fine = fractal_terrain(size_m=scenario.terrain_size_m, spacing_m=scenario.fine_spacing_m,
                           relief_m=scenario.relief_m, seed=seed, origin_xy=(-half, -half),
                           **kwargs)
    dtm = fine.resample(scenario.grid_spacing_m)
    dtm = Dtm(dtm.elevation, dtm.x0, dtm.y0, dtm.dx, dtm.dy, sigma_h_m=scenario.sigma_h)
    return ScenarioTerrain(truth=fine, dtm=dtm)


@dataclass(frozen=True)
class PairSample:
    """One random trial of a scenario: truth, measurements and initial guess.

    Attributes:
        world_T_body_a, world_T_body_b: (4, 4) true body poses.
        initial_a, initial_b: (4, 4) initial guess.
        body_T_cam: (4, 4) mounting.
        q_a, q_b: (n, 3) measured normalized rays (q_b noisy).
        G_true: (n, 3) true ground points.
    """

    world_T_body_a: np.ndarray
    world_T_body_b: np.ndarray
    initial_a: np.ndarray
    initial_b: np.ndarray
    body_T_cam: np.ndarray
    q_a: np.ndarray
    q_b: np.ndarray
    G_true: np.ndarray

    @property
    def n_features(self) -> int:
        return self.q_a.shape[0]


def _random_unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def sample_pair(scenario: PairScenario, terrain: ScenarioTerrain,
                rng: np.random.Generator) -> PairSample:
    """Draw one trial: a random camera pair over the terrain and its matched features."""
    camera = scenario.camera
    dtm = terrain.dtm
    xmin, xmax, ymin, ymax = dtm.bounds
    # Keep the footprint inside the map: half-width of the footprint + baseline.
    reach = (scenario.altitude_m + scenario.relief_m) * math.tan(
        math.radians(min(scenario.fov_deg, 120) / 2)) * 1.5 + scenario.baseline_m
    margin_x = min(reach, 0.45 * (xmax - xmin))
    margin_y = min(reach, 0.45 * (ymax - ymin))
    x = rng.uniform(xmin + margin_x, xmax - margin_x)
    y = rng.uniform(ymin + margin_y, ymax - margin_y)
    mean_h = float(np.nanmean(dtm.elevation))
    heading = rng.uniform(0, 2 * np.pi)
    R_a = so3_exp(np.array([0.0, 0.0, heading])) @ so3_exp(rng.normal(0, np.radians(3), 3))
    Ta = make_pose(R_a, np.array([x, y, mean_h + scenario.altitude_m]))
    # Ego-motion: along track (mostly), rotation of the requested magnitude.
    step = np.array([1.0, 0.0, 0.0]) + rng.normal(0, 0.15, 3)
    step *= scenario.baseline_m / np.linalg.norm(step)
    dR = so3_exp(_random_unit(rng) * math.radians(scenario.rotation_deg))
    Tb = Ta @ make_pose(dR, step)
    body_T_cam = DOWNWARD_BODY_T_CAM
    wTc_a, wTc_b = Ta @ body_T_cam, Tb @ body_T_cam

    # Oversample pixels in frame a, keep those seen (unoccluded, inside) in frame b.
    n_try = int(scenario.n_features * 3 + 20)
    uv_a = np.c_[rng.uniform(-0.5, camera.width - 0.5, n_try),
                 rng.uniform(-0.5, camera.height - 0.5, n_try)]
    q_a = camera.pixels_to_rays(uv_a)
    ray_a = q_a @ wTc_a[:3, :3].T
    if scenario.dtm_error is DtmErrorModel.MODEL:
        hits = dtm.raycast(np.broadcast_to(wTc_a[:3, 3], ray_a.shape), ray_a)
        ok = hits.hit
        dh = rng.normal(0, scenario.sigma_h, n_try) * (not scenario.noiseless)
        Nr = np.einsum("ni,ni->n", hits.normal, ray_a)
        G = hits.point + (dh / Nr)[:, None] * ray_a  # eq. 25: the plane raised by dh
        occluder = dtm
    else:
        hits = terrain.truth.raycast(np.broadcast_to(wTc_a[:3, 3], ray_a.shape), ray_a)
        ok = hits.hit
        G = hits.point
        occluder = terrain.truth
    # Off-surface points (the modelled DTM error) may sit a few sigma_h behind the surface.
    tolerance = OCCLUSION_TOLERANCE_M + 3 * abs(scenario.sigma_h) * (
        scenario.dtm_error is DtmErrorModel.MODEL)
    ok, g_b = visible_from(occluder, wTc_b, G, ok, tolerance)
    uv_b = camera.rays_to_pixels(np.where(ok[:, None], g_b, [0.0, 0.0, 1.0]))
    uv_b = uv_b + rng.normal(0, scenario.pixel_sigma_px, uv_b.shape) * (not scenario.noiseless)
    ok &= camera.in_image(uv_b)
    idx = np.flatnonzero(ok)[: scenario.n_features]
    q_b = camera.pixels_to_rays(uv_b[idx])

    def perturb(T):
        dR0 = so3_exp(rng.normal(0, math.radians(scenario.initial_attitude_error_deg), 3))
        return make_pose(T[:3, :3] @ dR0, T[:3, 3] + rng.normal(
            0, scenario.initial_position_error_m, 3))

    return PairSample(Ta, Tb, perturb(Ta), perturb(Tb), body_T_cam, q_a[idx], q_b, G[idx])
