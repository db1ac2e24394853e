"""The principal point as a considered parameter: what its declared uncertainty does to
the poses, added to their covariances.

No run estimates the principal point (``cx``, ``cy``): a flight tells it too weakly (the
calibration check's step reads it to 0.4-1 px on the 90-frame flight, docs/verdict.md),
and a shift of it reads as the camera moved by ``height * d / f`` in body axes (1 px at
1800 m: ~3.3 m). So the estimate is made at flight.yaml's value and inherits its error one
for one. When flight.yaml declares how well the calibration knows it
(``camera.principal_point_sigma_px``, 1-sigma of each), the run's pose covariances get
that error's part, as a Schmidt "consider" parameter: ``P + S C S^T``, with ``C`` the
declared covariance and ``S = dx / dc`` the estimate's first-order response to the
principal point, the other calibration held.

``S`` comes from the calibration check's first solve (the run's graph at its optimum,
flight.yaml's calibration pinned: :class:`~cdtm_graph.calibration.check.PinnedSolve`)
with the principal point's columns added to every C-DTM pair factor's rows
(:func:`~cdtm_graph.calibration.extra_parts.with_part`): ``S = -H_xx^-1 H_xc``, the
graph's solution with the principal point pinned at 1 px less the one pinned at 0.
Frames a long log's thinned solve leaves out take ``S`` interpolated in time between the
nearest kept frames (in body axes, where the shift is nearly constant).
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from cdtm_graph.calibration.check import PinnedSolve
from cdtm_graph.calibration.extra_parts import WITH_PART_KEY, with_part
from cdtm_graph.calibration.online import CALIBRATION_KEY
from cdtm_graph.calibration.principal_point import principal_point_part
from cdtm_graph.camera import PinholeCamera
from cdtm_graph.dtm import Dtm
from cdtm_graph.flightlog import CameraConfig
from cdtm_graph.optimizer import step_and_marginals
from cdtm_graph.results import ConsideredPrincipalPoint, StateCovariances

logger = logging.getLogger(__name__)

#: The principal point's pin in the solves that give ``S`` (px): tight against what a
#: flight tells of it (0.4-1 px: its share of ``S`` ~1e-8), loose against round-off.
PIN_PX = 1e-4


def principal_point_sensitivity(pinned: PinnedSolve, camera: PinholeCamera
                                ) -> np.ndarray | None:
    """(F, 6, 2) each solved frame's pose response to the principal point (its tangent:
    rotation, then translation in body axes, per px of ``cx``, ``cy``), the rest of the
    calibration held; None when the solve holds no C-DTM pair factor.

    The graph's solution with the principal point pinned at 1 px in ``cx``, then ``cy``,
    less the solution with it pinned at 0: three eliminations of the side solve's graph
    (a joint marginal per frame, ``Sigma_xc Sigma_cc^-1``, gives the same to 1e-6 at ten
    times the cost: tests/calibration/test_considered.py)."""
    part = principal_point_part(camera)
    built = with_part(pinned.linear, pinned.values, pinned.factors, part) if pinned.factors \
        else None
    if built is None:
        return None
    augmented, _ = built
    m, d = pinned.values.atVector(CALIBRATION_KEY).size, part.dim
    keys = [X(j) for j in range(pinned.kept.size)]

    def solution(cx_cy: np.ndarray) -> np.ndarray:
        graph = gtsam.GaussianFactorGraph()
        graph.push_back(augmented)
        graph.add(WITH_PART_KEY, np.eye(m + d) / PIN_PX, np.r_[np.zeros(m), cx_cy] / PIN_PX,
                  gtsam.noiseModel.Unit.Create(m + d))
        delta, _ = step_and_marginals(graph, [])
        return np.stack([delta.at(k) for k in keys])

    at_zero = solution(np.zeros(d))
    return np.stack([solution(unit) - at_zero for unit in np.eye(d)], axis=2)


#: How far a fixed lag's own response to the principal point strays from ``S`` (the whole
#: flight's), as a fraction of it: its frames keep the estimate they left the window with,
#: made without the later attitude changes. Fitted 2026-11-28 on the 90-frame flight,
#: seed 1, cx and cy moved (8, -6) px: the misfit's rms over the frames 0.090 of ``|S d|``,
#: spread over the three axes alike (per axis 0.0065-0.0096 of ``|S d|^2 / 3``); checked
#: on (0, 10) px (0.094) and seed 2 (0.108): the largest taken, as the live path's.
#: Batch and iSAM2 follow ``S`` to 1-2%.
FIXED_LAG_RESPONSE_MISFIT = 0.11


def misfit_spread(S: np.ndarray, sigma_px: float, misfit: float) -> np.ndarray:
    """(..., 3, 3) the expected square of a response that strays from ``S`` ((..., 6, 2)) by
    ``misfit`` of its size, spread over the three position axes alike:
    ``(misfit sigma |S_pos|_F)^2 / 3`` each (``E|S d|^2 = sigma^2 |S|_F^2`` for ``d`` of
    1-sigma ``sigma`` per axis)."""
    size2 = sigma_px**2 * np.sum(S[..., 3:, :] ** 2, axis=(-2, -1))
    return (misfit**2 * size2 / 3)[..., None, None] * np.eye(3)


def considered(covariances: StateCovariances, t_ns: np.ndarray, pinned: PinnedSolve,
               camera: PinholeCamera, sigma_px: float, response_misfit: float = 0.0
               ) -> tuple[StateCovariances, ConsideredPrincipalPoint | None]:
    """``covariances`` (of the frames at ``t_ns``) with the principal point's declared
    1-sigma ``sigma_px`` considered, and what that added; as they are (and None) when the
    solve holds no C-DTM factor or nothing is declared.

    ``response_misfit``: how far the run's own response may stray from ``S``, as a
    fraction of it (:data:`FIXED_LAG_RESPONSE_MISFIT`); its expected square is added to
    the positions in every direction alike, ``(misfit sigma |S|_F)^2 / 3`` per axis (it
    grows with the declared sigma as the response does: at 10 px a fixed lag without it
    read ANEES 4.6)."""
    start = time.perf_counter()
    if sigma_px <= 0:
        return covariances, None
    solved = principal_point_sensitivity(pinned, camera)
    if solved is None:
        logger.warning("camera.principal_point_sigma_px %g px not considered: the side "
                       "solve holds no C-DTM factor to take its share from", sigma_px)
        return covariances, None
    kept_t = t_ns[pinned.kept].astype(float)
    flat = solved.reshape(solved.shape[0], -1)
    # (each entry in time; the frames outside the solved span take its nearest)
    S = np.stack([np.interp(t_ns.astype(float), kept_t, flat[:, i])
                  for i in range(flat.shape[1])], axis=1).reshape(t_ns.size, 6, -1)
    added = sigma_px**2 * S @ np.swapaxes(S, 1, 2)
    added[:, 3:, 3:] += misfit_spread(S, sigma_px, response_misfit)
    return (replace(covariances, pose=covariances.pose + added),
            ConsideredPrincipalPoint(float(sigma_px), added, int(pinned.kept.size),
                                     time.perf_counter() - start))


#: How far the live path's own response strays from the geometric form, as a fraction of
#: it (the same role as :data:`FIXED_LAG_RESPONSE_MISFIT`): measured 2026-11-28 on the
#: fixed lag's live updates, the 90-frame flight, frames 10-89, rms over the frames 0.192
#: (seed 1, cx, cy moved (8, -6) px), 0.193 (seed 2) and 0.245 ((0, 10) px, seed 1; x and
#: z strayed more than y): the largest taken. (A nadir camera: off nadir,
#: :func:`live_pose_covariance` adds the optical axis's share.)
LIVE_RESPONSE_MISFIT = 0.25


def live_pose_covariance(world_T_body: np.ndarray, body_T_cam: np.ndarray,
                         camera: PinholeCamera, range_m: float, sigma_px: float
                         ) -> np.ndarray:
    """(6, 6) the live path's share of a declared principal point in one frame's pose
    covariance (body frame): the after-run ``S`` needs the side solve, so an update takes
    its geometric approximation, a shift ``d`` of the principal point read as the camera
    moved by ``range * d / f`` along its own x, y axes (``range_m``: along the optical
    axis to the ground; :func:`optical_axis_range_m`). Within 16% of the solved ``S``'s
    position sigma on the 90-frame flight (measured, seeds 1-2: -13% to +16%; the test
    holds 30 frames to 13%). What it leaves out is spread over it: the live response
    strays from it by ~20% (:data:`LIVE_RESPONSE_MISFIT`), in every direction; and a
    camera off nadir by ``theta`` moves along its optical axis too (at 30 deg the solved
    ``S`` had 1.55 m/px there, 0.46 of its size, where this form has none), taken as
    ``tan(theta)`` of a column's size along that axis (0.58 at 30 deg; nothing at
    nadir)."""
    S = np.zeros((6, 2))
    S[3:, 0] = body_T_cam[:3, 0] * range_m / camera.fx
    S[3:, 1] = body_T_cam[:3, 1] * range_m / camera.fy
    added = sigma_px**2 * S @ S.T
    size2 = sigma_px**2 * np.sum(S**2)  # (the share's expected squared length)
    added[3:, 3:] += misfit_spread(S, sigma_px, LIVE_RESPONSE_MISFIT)
    axis = body_T_cam[:3, 2]  # (body axes)
    down = -world_T_body[2, :3]  # world's down in body axes
    cos_theta = float(np.clip(axis @ down, 1e-3, 1.0))
    # (tan(theta) of a column's length: the two columns' mean square)
    added[3:, 3:] += (1 - cos_theta**2) / cos_theta**2 * size2 / 2 * np.outer(axis, axis)
    return added


def optical_axis_range_m(world_T_body: np.ndarray, body_T_cam: np.ndarray, dtm: Dtm
                         ) -> float:
    """The distance along the camera's optical axis to the DTM (m); NaN where it misses."""
    world_T_cam = world_T_body @ body_T_cam
    hits = dtm.raycast(world_T_cam[:3, 3], world_T_cam[:3, 2])
    return float(hits.t[0]) if hits.hit[0] else float("nan")


class LiveShare:
    """A declared principal point's share in the live path's pose covariances (the
    incremental smoother's ``FrameUpdate``), as :class:`~cdtm_graph.results.MapOffset`
    adds the map's offset there: its geometric form (:func:`live_pose_covariance`), the
    last range kept where the optical axis misses the DTM (none before the first hit).

    Args:
        camera: flight.yaml's camera (its ``principal_point_sigma_px`` declared or not).
        dtm: the map.
    """

    def __init__(self, camera: CameraConfig, dtm: Dtm):
        self.sigma_px = camera.principal_point_sigma_px or 0.0
        self.camera, self.dtm = camera, dtm
        self.range_m = float("nan")

    def added_to_pose(self, pose_cov: np.ndarray, world_T_body: np.ndarray) -> np.ndarray:
        """One (6, 6) pose covariance (of the pose ``world_T_body``) with the share added
        (itself where nothing is declared)."""
        if not self.sigma_px:
            return pose_cov
        range_m = optical_axis_range_m(world_T_body, self.camera.body_T_cam, self.dtm)
        if np.isfinite(range_m):
            self.range_m = range_m
        if not np.isfinite(self.range_m):
            return pose_cov
        return pose_cov + live_pose_covariance(world_T_body, self.camera.body_T_cam,
                                               self.camera.camera, self.range_m,
                                               self.sigma_px)
