"""C-DTM refinement of a candidate fix: the factors themselves on the window's frames.

Every pair of sightings of every track becomes a C-DTM feature (:class:`factors.
CdtmPairFactor`, planes re-intersected); the fix's rotation, translation and velocity are
fitted by Levenberg-Marquardt on the truncated quadratic, under the search prior.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cdtm_graph.geometry import skew, so3_exp, so3_log
from cdtm_graph.robust.acquisition.window import Correction, Problem, Window
from factors import CdtmPairFactor, FeatureNoise, PairFeatures, PlaneMode


@dataclass(frozen=True)
class Features:
    """Every pair of sightings of every track (not only consecutive ones: a pair's
    residual grows with its baseline, and the terrain is what is sought), grouped by
    frame pair."""

    groups: list[tuple[int, int, np.ndarray]]  # (frame a, frame b, feature indices)
    q_a: np.ndarray
    q_b: np.ndarray
    track: np.ndarray  # (F,) track of each feature

    @property
    def n(self) -> int:
        return self.track.size


def pair_features(window: Window) -> Features:
    """The window's :class:`Features`: ``m (m - 1) / 2`` per track of ``m`` sightings."""
    counts = np.diff(window.starts)
    rows_a, rows_b = [], []
    for m in np.unique(counts):  # all pairs k < l, vectorized per track length
        k, l = np.triu_indices(int(m), 1)
        first = window.starts[:-1][counts == m]
        rows_a.append((first[:, None] + k[None, :]).ravel())
        rows_b.append((first[:, None] + l[None, :]).ravel())
    a, b = np.concatenate(rows_a), np.concatenate(rows_b)
    fa, fb = window.frame[a], window.frame[b]
    order = np.lexsort((fb, fa))
    a, b, fa, fb = a[order], b[order], fa[order], fb[order]
    change = np.flatnonzero((np.diff(fa) != 0) | (np.diff(fb) != 0)) + 1
    bounds = np.r_[0, change, a.size]
    groups = [(int(fa[s]), int(fb[s]), np.arange(s, e)) for s, e in zip(bounds[:-1], bounds[1:])]
    return Features(groups, window.q[a], window.q[b], window.track_of[a])


@dataclass(frozen=True)
class Refined:
    """A refined fix and its robust cost (the sum of ``feature_costs``)."""

    correction: Correction
    feature_costs: np.ndarray  # (F,) truncated whitened squared residuals
    cost: float


class Refiner:
    """C-DTM refinement of a fix: rotation, translation and velocity of the first state.

    Levenberg-Marquardt on the truncated quadratic (features past the truncation weigh
    nothing in a step) plus the search prior on all nine, planes re-intersected at every
    evaluation.
    """

    #: Converged when a step moves the fix less than this (m, rad).
    STEP_M = 0.01
    STEP_RAD = 1e-5

    def __init__(self, problem: Problem, features: Features):
        self.problem = problem
        self.f = features
        self.noise = FeatureNoise(problem.sigma_q, problem.dtm.sigma_h())
        # L^-1 of the prior's position covariance: |L^-1 x|^2 = x^T P^-1 x.
        self._position_whitening = np.linalg.inv(np.linalg.cholesky(
            np.asarray(problem.prior.position_covariance_world, dtype=float)))
        self.tau2 = problem.tau ** 2

    def _build(self, poses: np.ndarray) -> list[tuple[int, int, np.ndarray, CdtmPairFactor | None,
                                                      np.ndarray]]:
        body_T_cam = self.problem.camera.body_T_cam
        raycast = self.problem.dtm.tangent_planes
        out = []
        for a, b, idx in self.f.groups:
            wTc_a, wTc_b = poses[a] @ body_T_cam, poses[b] @ body_T_cam
            q_a, q_b = self.f.q_a[idx], self.f.q_b[idx]
            G, N, hit = raycast(wTc_a[:3, 3], q_a @ wTc_a[:3, :3].T)
            factor = None
            if hit.any():
                features = PairFeatures.build(wTc_a, wTc_b, q_a[hit], q_b[hit], G[hit], N[hit],
                                              self.noise)
                factor = CdtmPairFactor(0, 1, features, body_T_cam, PlaneMode.REINTERSECT,
                                        raycast)
            out.append((a, b, idx, factor, hit))
        return out

    def _evaluate(self, built, c: Correction, jacobians: bool):
        """Truncated costs (F,), and with ``jacobians`` residuals (F, 2) and Jacobians
        (F, 2, 9) w.r.t. [rotation (left, world), translation, velocity] of the fix."""
        s = self.problem
        poses = s.poses(c)
        F = self.f.n
        costs = np.full(F, self.tau2)  # a ray off the DTM fits nothing
        e_all = np.zeros((F, 2))
        H_all = np.zeros((F, 2, 9) if jacobians else (0, 2, 9))
        pose_jacobians = self._pose_jacobians(poses, c) if jacobians else None
        for a, b, idx, factor, hit in built:
            if factor is None:
                continue
            if jacobians:
                e, Ha, Hb = factor.innovations(poses[a], poses[b])
            else:
                e = factor.whitened_residuals(poses[a], poses[b])
            rows = idx[hit]
            costs[rows] = np.minimum((e ** 2).sum(axis=1), self.tau2)
            if pose_jacobians is not None:
                e_all[rows] = e
                H_all[rows] = Ha @ pose_jacobians[a] + Hb @ pose_jacobians[b]
        return costs, e_all, H_all

    def _pose_jacobians(self, poses: np.ndarray, c: Correction) -> np.ndarray:
        """(K, 6, 9): each pose's change (GTSAM's right perturbation [rotation,
        translation], body) per change of the fix [rotation (left, world), translation,
        velocity] (:class:`Correction`)."""
        s = self.problem
        turned = s.drift() @ c.rotation_world.T
        Rt = np.swapaxes(poses[:, :3, :3], 1, 2)
        J = np.zeros((poses.shape[0], 6, 9))
        J[:, :3, :3] = Rt
        J[:, 3:, :3] = -Rt @ skew(turned)
        J[:, 3:, 3:6] = Rt
        J[:, 3:, 6:] = Rt * s.window.dt_s[:, None, None]
        return J

    def _prior(self, c: Correction) -> np.ndarray:
        """(9,) the whitened prior residual of the fix [rotation, translation, velocity]:
        the search prior, so that directions the terrain leaves free stay put."""
        p = self.problem.prior
        rotation = so3_log(c.rotation_world) / np.array(
            [p.tilt_sigma_rad, p.tilt_sigma_rad, p.heading_sigma_rad])
        return np.r_[rotation, self._position_whitening @ c.translation_world_m,
                     c.velocity_world_mps / p.velocity_sigma_mps]

    @staticmethod
    def _step(c: Correction, delta: np.ndarray) -> Correction:
        return Correction(so3_exp(delta[:3]) @ c.rotation_world,
                          c.translation_world_m + delta[3:6], c.velocity_world_mps + delta[6:])

    def refine(self, c: Correction) -> Refined:
        """Levenberg-Marquardt from ``c`` (damping on the diagonal); the planes and noise
        are built at the start and again at the first solution.

        A trust region keeps the fix within ``merge_radius_m / 2`` (horizontally) of
        ``c``: the refinement polishes a mode of the search, it does not wander to
        another (over flat ground the prior alone would pull every mode to its mean).
        """
        p = self.problem.prior
        start_xy = c.translation_world_m[:2].copy()
        reach = 0.5 * self.problem.settings.merge_radius_m
        # The prior's Jacobian, with d log(Exp(w) R) / dw ~ I (turns of a few degrees).
        J_prior = np.zeros((9, 9))
        J_prior[:3, :3] = np.diag(1.0 / np.array(
            [p.tilt_sigma_rad, p.tilt_sigma_rad, p.heading_sigma_rad]))
        J_prior[3:6, 3:6] = self._position_whitening
        J_prior[6:, 6:] = np.eye(3) / p.velocity_sigma_mps
        for rebuild in range(2):
            built = self._build(self.problem.poses(c))
            costs, e, H = self._evaluate(built, c, True)
            r_prior = self._prior(c)
            total = costs.sum() + r_prior @ r_prior
            lam = 1e-4
            for _ in range(self.problem.settings.refine_iterations if rebuild == 0 else 5):
                w = costs < self.tau2  # past the truncation a feature weighs nothing
                Hw = H[w].reshape(-1, 9)
                A = Hw.T @ Hw + J_prior.T @ J_prior
                g = Hw.T @ e[w].reshape(-1) + J_prior.T @ r_prior
                accepted = False
                while lam < 1e8:
                    delta = -np.linalg.solve(A + lam * np.diag(np.diag(A)), g)
                    trial = self._step(c, delta)
                    if np.linalg.norm(trial.translation_world_m[:2] - start_xy) > reach:
                        lam *= 10.0
                        continue
                    t_costs, t_e, t_H = self._evaluate(built, trial, True)
                    t_prior = self._prior(trial)
                    t_total = t_costs.sum() + t_prior @ t_prior
                    if t_total < total:
                        c, costs, e, H, r_prior, total = trial, t_costs, t_e, t_H, t_prior, t_total
                        lam = max(lam * 0.1, 1e-9)
                        accepted = True
                        break
                    lam *= 10.0
                if not accepted or (np.linalg.norm(delta[3:6]) < self.STEP_M
                                    and np.linalg.norm(delta[:3]) < self.STEP_RAD):
                    break
        costs, _, _ = self._evaluate(self._build(self.problem.poses(c)), c, False)
        return Refined(c, costs, float(costs.sum()))
