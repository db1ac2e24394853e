"""A-priori accuracy map: the predicted camera-2 pose 1-sigma over a DTM (closed form).

Before flying, place the paper's nominal frame pair at every node of a grid over the DTM
and evaluate the weighted closed form (eq. 13 with ``W = blockdiag(Sigma_f^+)``, then
``Sigma_C2``, eqs. 27-32) at the true geometry with noiseless features. No solve is
needed: the prediction is the covariance the estimator would reach there. Where the
geometry is degenerate (section V.B: flat terrain, too few features, ...) the map holds
NaN and names the reasons as bit codes (:class:`DegeneracyCode`).

The pair at a node ``(x, y)``: a level body with heading ``heading_deg`` (0 = flying
along +x), camera looking straight down (:data:`DOWNWARD_BODY_T_CAM`), at ``altitude_m``
above the DTM's mean height (constant-altitude flight, as the paper's) or above the
ground below it; the second frame is ``baseline_m`` ahead along the body x axis, rotated
by ``rotation_deg`` about the body axis ``(1, 1, 1)/sqrt(3)`` (equal roll, pitch and yaw).
Features are a regular grid of pixels of the first image, cast into the DTM; those seen
unoccluded in the second image are kept, ``n_features`` of them spread evenly over the list.

Pure: no file I/O (``cdtm accuracy-map`` writes the files).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import numpy as np

from cdtm_graph.analysis.closed_form import ClosedFormAnalysis, DegeneracySettings, analyze_pair
from cdtm_graph.analysis.map_options import (
    MAX_ABS_HEADING_DEG,
    MAX_FEATURES,
    MAX_NODES,
    MAX_ROTATION_DEG,
    RESOLUTION_RANGE_PX,
    AltitudeReference,
)
from cdtm_graph.camera import DOWNWARD_BODY_T_CAM, PinholeCamera
from cdtm_graph.dtm import Dtm, visible_from
from cdtm_graph.errors import CdtmError
from cdtm_graph.flightlog.config import RANGES
from cdtm_graph.geometry import make_pose, so3_exp
from cdtm_graph.parallel import ParallelSettings, map_tasks
from factors import FeatureNoise

#: Candidate feature pixels drawn per requested feature (some leave the second image).
_CANDIDATES_PER_FEATURE = 3
#: Grid nodes along the longer side of the DTM when no step is given.
DEFAULT_NODES_PER_SIDE = 40
#: Highest camera altitude (m) of a map: beyond it the camera is in space.
MAX_ALTITUDE_M = 1e5
#: Body axis of the inter-frame rotation: equal roll, pitch and yaw.
_ROTATION_AXIS_BODY = np.ones(3) / math.sqrt(3.0)


class DegeneracyCode(enum.IntFlag):
    """Bit codes of the degeneracy reasons of :mod:`cdtm_graph.analysis.closed_form` in the map."""

    FEW_FEATURES = 1
    NARROW_FOV = 2
    SHORT_BASELINE = 4
    FLAT_TERRAIN = 8
    ILL_CONDITIONED = 16
    OTHER = 32  # a reason this module does not know yet

    @classmethod
    def from_reasons(cls, reasons: tuple[str, ...]) -> DegeneracyCode:
        code = cls(0)
        for reason in reasons:
            code |= cls.__members__.get(reason.upper(), cls.OTHER)
        return code


#: Names of the :class:`DegeneracyCode` bits, lowest bit first (written beside the codes).
DEGENERACY_CODE_NAMES = tuple(name.lower() for name in DegeneracyCode.__members__)


@dataclass(frozen=True)
class AccuracyMapSettings:
    """The frame pair placed at every node, and the grid.

    Attributes:
        altitude_m: camera-1 height above the reference (``altitude_reference``).
        fov_deg: horizontal field of view (square image).
        resolution_px: image width = height.
        n_features: features per pair.
        baseline_m: ``|p12|``, along the body x axis.
        rotation_deg: ``|(phi12, theta12, psi12)|``.
        pixel_sigma_px: registration error, pixels (1 sigma).
        sigma_h_m: DTM height error; ``None`` uses the DTM's own (its ``sigma_h()``).
        heading_deg: flight direction, degrees counter-clockwise from +x.
        step_m: node spacing; ``None`` puts :data:`DEFAULT_NODES_PER_SIDE` nodes along
            the longer side.
        altitude_reference: what the altitude is measured from.
        degeneracy: thresholds of the degeneracy verdict.
    """

    altitude_m: float
    fov_deg: float
    resolution_px: int = 400
    n_features: int = 170
    baseline_m: float = 40.0
    rotation_deg: float = 10.0
    pixel_sigma_px: float = 0.5
    sigma_h_m: float | None = None
    heading_deg: float = 0.0
    step_m: float | None = None
    altitude_reference: AltitudeReference = AltitudeReference.MEAN_TERRAIN
    degeneracy: DegeneracySettings = field(default_factory=DegeneracySettings)

    def check(self) -> None:
        """Raise CdtmError on settings that make no sense."""
        # integers first: math.isfinite(10**400) raises OverflowError
        if not 1 <= self.n_features <= MAX_FEATURES:
            shown = repr(self.n_features)
            shown = shown if len(shown) <= 20 else shown[:16] + "..."
            raise CdtmError(f"n_features = {shown}, expected 1 to {MAX_FEATURES} "
                            "features per pair")
        lo_px, hi_px = RESOLUTION_RANGE_PX
        if not lo_px <= self.resolution_px <= hi_px:
            shown = repr(self.resolution_px)
            shown = shown if len(shown) <= 20 else shown[:16] + "..."
            raise CdtmError(f"resolution_px = {shown}, expected {lo_px} to "
                            f"{hi_px} px")
        positive = {"altitude_m": self.altitude_m, "pixel_sigma_px": self.pixel_sigma_px}
        for name, value in positive.items():
            if not (math.isfinite(value) and value > 0):
                raise CdtmError(f"{name} = {value!r}, expected > 0")
        if not (math.isfinite(self.heading_deg)
                and abs(self.heading_deg) <= MAX_ABS_HEADING_DEG):
            raise CdtmError(f"heading_deg = {self.heading_deg!r}, expected a finite angle in "
                            f"[-{MAX_ABS_HEADING_DEG:g}, {MAX_ABS_HEADING_DEG:g}] deg")
        sigma = RANGES["camera.pixel_sigma_px"]  # as flight.yaml: 1e-300 px is singular
        if not sigma.lo <= self.pixel_sigma_px <= sigma.hi:
            raise CdtmError(f"pixel_sigma_px = {self.pixel_sigma_px!r}, expected {sigma}")
        if not self.altitude_m <= MAX_ALTITUDE_M:
            raise CdtmError(f"altitude_m = {self.altitude_m!r}, expected at most "
                            f"{MAX_ALTITUDE_M:g} m")
        if not 0 < self.fov_deg < 180:
            raise CdtmError(f"fov_deg = {self.fov_deg!r}, expected 0 < fov < 180")
        for name in ("baseline_m", "rotation_deg"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise CdtmError(f"{name} = {value!r}, expected >= 0")
        if not self.rotation_deg <= MAX_ROTATION_DEG:
            raise CdtmError(f"rotation_deg = {self.rotation_deg!r}, expected at most "
                            f"{MAX_ROTATION_DEG:g} deg (the angle of one rotation)")
        if self.sigma_h_m is not None and not (math.isfinite(self.sigma_h_m)
                                               and self.sigma_h_m >= 0):
            raise CdtmError(f"sigma_h_m = {self.sigma_h_m!r}, expected >= 0")
        if self.step_m is not None and not (math.isfinite(self.step_m) and self.step_m > 0):
            raise CdtmError(f"step_m = {self.step_m!r}, expected > 0")

    @property
    def camera(self) -> PinholeCamera:
        return PinholeCamera.from_fov(self.resolution_px, self.resolution_px, self.fov_deg)

    def noise(self, dtm: Dtm) -> FeatureNoise:
        sigma_h = dtm.sigma_h() if self.sigma_h_m is None else self.sigma_h_m
        return FeatureNoise(self.camera.sigma_normalized(self.pixel_sigma_px), sigma_h)


@dataclass(frozen=True)
class LocationAccuracy:
    """The frame pair at one node and its closed-form analysis.

    Attributes:
        world_T_cam_a, world_T_cam_b: (4, 4) true camera poses.
        q_a, q_b: (n, 3) noiseless normalized rays of the features (z = 1).
        G_E, N: (n, 3) DTM hits of the ``q_a`` rays and upward normals there.
        noise: the data noise assumed.
        analysis: :func:`analyze_pair` at this geometry; ``None`` if no feature is seen.
    """

    world_T_cam_a: np.ndarray
    world_T_cam_b: np.ndarray
    q_a: np.ndarray
    q_b: np.ndarray
    G_E: np.ndarray
    N: np.ndarray
    noise: FeatureNoise
    analysis: ClosedFormAnalysis | None

    @property
    def reasons(self) -> tuple[str, ...]:
        return ("few_features",) if self.analysis is None else self.analysis.degeneracy.reasons

    @property
    def sigma_pos2_m(self) -> float:
        """``sqrt(trace)`` of the camera-2 position block of the weighted ``Sigma_C2``."""
        a = self.analysis
        if a is None or a.degeneracy.degenerate:
            return math.nan
        return math.sqrt(np.trace(a.sigma_c2_weighted[:3, :3]))

    @property
    def sigma_att2_deg(self) -> float:
        """``sqrt(trace)`` of the camera-2 Euler-angle block (eqs. 29-31), degrees."""
        a = self.analysis
        if a is None or a.degeneracy.degenerate:
            return math.nan
        return math.degrees(math.sqrt(np.trace(a.sigma_c2_weighted[3:, 3:])))


@dataclass(frozen=True)
class AccuracyMap:
    """Predicted accuracy over a grid of nodes, rows along y and columns along x.

    Attributes:
        x_m: (nx,) node x coordinates (world, m).
        y_m: (ny,) node y coordinates.
        sigma_pos2_m: (ny, nx) camera-2 position 1-sigma (norm over x, y, z); NaN where
            degenerate.
        sigma_att2_deg: (ny, nx) camera-2 attitude 1-sigma (norm over the Euler angles).
        reason_codes: (ny, nx) :class:`DegeneracyCode` bits, 0 where the geometry is good.
        n_features: (ny, nx) features seen in both frames.
        settings: what was computed.
    """

    x_m: np.ndarray
    y_m: np.ndarray
    sigma_pos2_m: np.ndarray
    sigma_att2_deg: np.ndarray
    reason_codes: np.ndarray
    n_features: np.ndarray
    settings: AccuracyMapSettings

    @property
    def degenerate(self) -> np.ndarray:
        """(ny, nx) bool: the geometry at the node cannot fix the pose."""
        return self.reason_codes != 0


def pair_at(dtm: Dtm, x_m: float, y_m: float, settings: AccuracyMapSettings
            ) -> tuple[np.ndarray, np.ndarray]:
    """The true body poses ``(world_T_body_a, world_T_body_b)`` of the pair at a node, (4, 4)."""
    if settings.altitude_reference is AltitudeReference.GROUND:
        ground = float(dtm.height(np.array(x_m), np.array(y_m)))
    else:
        ground = float(np.nanmean(dtm.elevation))
    heading = math.radians(settings.heading_deg)
    Ta = make_pose(so3_exp(np.array([0.0, 0.0, heading])),
                   np.array([x_m, y_m, ground + settings.altitude_m]))
    dR = so3_exp(_ROTATION_AXIS_BODY * math.radians(settings.rotation_deg))
    Tb = Ta @ make_pose(dR, np.array([settings.baseline_m, 0.0, 0.0]))
    return Ta, Tb


def accuracy_at(dtm: Dtm, x_m: float, y_m: float,
                settings: AccuracyMapSettings) -> LocationAccuracy:
    """Noiseless features and the closed-form analysis of the pair at one node.

    Args:
        dtm: the terrain (the truth and the map coincide: the prediction is a-priori).
        x_m, y_m: node position (world, m).
        settings: the pair.

    Returns:
        The geometry, the features and :func:`analyze_pair` there.
    """
    camera = settings.camera
    noise = settings.noise(dtm)
    Ta, Tb = pair_at(dtm, x_m, y_m, settings)
    wTc_a, wTc_b = Ta @ DOWNWARD_BODY_T_CAM, Tb @ DOWNWARD_BODY_T_CAM
    side = math.ceil(math.sqrt(_CANDIDATES_PER_FEATURE * settings.n_features))
    # Pixel-cell centres of a side x side grid over the image.
    u = (np.arange(side) + 0.5) * camera.width / side - 0.5
    v = (np.arange(side) + 0.5) * camera.height / side - 0.5
    uv = np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)
    q_a = camera.pixels_to_rays(uv)
    ray = q_a @ wTc_a[:3, :3].T
    hits = dtm.raycast(np.broadcast_to(wTc_a[:3, 3], ray.shape), ray)
    ok = hits.hit
    G = np.where(ok[:, None], hits.point, 0.0)
    ok, g_b = visible_from(dtm, wTc_b, G, ok)
    ok &= camera.in_image(camera.rays_to_pixels(np.where(ok[:, None], g_b, [0.0, 0.0, 1.0])))
    visible = np.flatnonzero(ok)
    if visible.size > settings.n_features:  # spread the kept ones over the whole overlap
        visible = visible[np.linspace(0, visible.size - 1, settings.n_features).round()
                          .astype(int)]
    q_a, G, N = q_a[visible], hits.point[visible], hits.normal[visible]
    q_b = g_b[visible] / g_b[visible, 2:3]
    analysis = None
    if visible.size > 0:
        analysis = analyze_pair(wTc_a, wTc_b, q_a, q_b, G, N, noise, settings.degeneracy)
    return LocationAccuracy(wTc_a, wTc_b, q_a, q_b, G, N, noise, analysis)


def map_nodes(dtm: Dtm, step_m: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Node coordinates ``(x_m (nx,), y_m (ny,))``: cell centres of a ``step_m`` grid.

    The grid covers the DTM's extent, centred on it, half a step in from the edges.

    Raises:
        CdtmError: the grid would have more than :data:`MAX_NODES` nodes.
    """
    xmin, xmax, ymin, ymax = dtm.bounds
    if step_m is None:
        step_m = max(xmax - xmin, ymax - ymin) / DEFAULT_NODES_PER_SIDE
    step = step_m
    # (capped before floor: a step of 1e-320 m makes the ratio infinite)
    nx, ny = (max(1, math.floor(min((hi - lo) / step, 1e18))) for lo, hi in ((xmin, xmax),
                                                                             (ymin, ymax)))
    if nx * ny > MAX_NODES:
        raise CdtmError(f"step_m = {step:g} m makes about {(xmax - xmin) / step:.3g} x "
                        f"{(ymax - ymin) / step:.3g} nodes over the DTM's {xmax - xmin:.6g} x "
                        f"{ymax - ymin:.6g} m; expected at most {MAX_NODES:.3g} nodes: a "
                        "larger step")

    def axis(lo: float, hi: float, n: int) -> np.ndarray:
        return (lo + hi) / 2 + (np.arange(n) - (n - 1) / 2) * step

    return axis(xmin, xmax, nx), axis(ymin, ymax, ny)


@dataclass(frozen=True)
class _RowTask:
    dtm: Dtm
    y_m: float
    x_m: np.ndarray
    settings: AccuracyMapSettings


def _map_row(task: _RowTask) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    n = task.x_m.size
    sigma_pos, sigma_att = np.full(n, np.nan), np.full(n, np.nan)
    codes, n_features = np.zeros(n, dtype=np.int32), np.zeros(n, dtype=np.int32)
    for j, x in enumerate(task.x_m):
        loc = accuracy_at(task.dtm, float(x), task.y_m, task.settings)
        codes[j] = int(DegeneracyCode.from_reasons(loc.reasons))
        n_features[j] = loc.q_a.shape[0]
        sigma_pos[j], sigma_att[j] = loc.sigma_pos2_m, loc.sigma_att2_deg
    return sigma_pos, sigma_att, codes, n_features


def accuracy_map(dtm: Dtm, settings: AccuracyMapSettings,
                 parallel: ParallelSettings | None = None) -> AccuracyMap:
    """Predicted camera-2 accuracy at every node of a grid over the DTM.

    Args:
        dtm: the terrain.
        settings: the frame pair and the grid.
        parallel: where to run the rows (default: this process only; the map is
            deterministic, so any backend gives the same numbers).

    Returns:
        The map; nodes whose footprint leaves the DTM see fewer features (``n_features``)
        and may be flagged ``few_features``.
    """
    settings.check()
    x_m, y_m = map_nodes(dtm, settings.step_m)
    tasks = [_RowTask(dtm, float(y), x_m, settings) for y in y_m]
    rows = map_tasks(_map_row, tasks, parallel or ParallelSettings(workers=1))
    sigma_pos, sigma_att, codes, n_features = (np.stack(a) for a in zip(*rows, strict=True))
    return AccuracyMap(x_m, y_m, sigma_pos, sigma_att, codes, n_features, settings)
