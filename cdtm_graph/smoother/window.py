"""The incremental smoother's solver side: a backend, the estimates fetched from it, and
the C-DTM factors it holds.

:class:`SolverWindow` is what :class:`~cdtm_graph.smoother.incremental.IncrementalSmoother`
solves with: the backend (full-history iSAM2 or a fixed lag,
:mod:`~cdtm_graph.smoother.backends`), each frame's latest estimate (frames that left a
fixed lag's window keep the one they left with, and, offline, their covariances), and the
ledger of C-DTM factors in the solver (their slots, track ids and later frames), so that
tracks found off the map can be taken out and the newest factors relinearized.
"""

from __future__ import annotations

import bisect
from collections.abc import Callable

import gtsam
import numpy as np
from gtsam.symbol_shorthand import V, X

from cdtm_graph.constants import NS_PER_S
from cdtm_graph.geometry import largest_eigenvalue_sym3
from cdtm_graph.graph import insert_state
from cdtm_graph.imu import propagate_covariance
from cdtm_graph.results import Rejection, Rejections, StateCovariances, TrajectoryEstimate
from cdtm_graph.robust.acquisition import SearchPrior
from cdtm_graph.robust.fix_search import FixSearch
from cdtm_graph.smoother.backends import Backend, FixedLag, FullHistory, frame_keys
from factors import CdtmPairFactor, FeatureNoise, RayCaster


def _frame(key: int) -> int:
    return int(gtsam.Symbol(key).index())


class SolverWindow:
    """A backend and what the smoother keeps of it.

    Args:
        lag_s: a fixed lag of this many seconds; None: the full history.
        frame_interval_s: the expected frame interval (a fixed lag relinearizes less often).
        keep_exit_covariances: keep each frame's covariances as it leaves a fixed lag.
    """

    #: The newest C-DTM factors are rebuilt once when the update moved their frame this
    #: far from the prediction their noise was linearized at (metres, radians).
    NOISE_REFRESH_POSITION_M = 2.0
    NOISE_REFRESH_ROTATION_RAD = np.radians(0.2)

    def __init__(self, lag_s: float | None, frame_interval_s: float | None,
                 keep_exit_covariances: bool):
        self.lag_s = lag_s
        self.backend: Backend = (FullHistory() if lag_s is None
                                 else FixedLag(lag_s, frame_interval_s))
        self.keep_exit_covariances = keep_exit_covariances
        self.t_ns: list[int] = []
        # latest estimate of every frame (frames out of a lag window keep their last)
        self.poses: dict[int, np.ndarray] = {}
        self.velocities: dict[int, np.ndarray] = {}
        self.biases: dict[int, gtsam.imuBias.ConstantBias] = {}
        self.settled = 0  # fixed lag: frames before this one have left the window
        self.exit_cov: dict[int, tuple[np.ndarray, ...]] = {}  # ... their (X, V, B) then
        self.state_cov = np.zeros((15, 15))  # newest frame's [X, V, B] covariance
        # every C-DTM factor (outliers, refresh); None where its features all went
        self.cdtm: list[CdtmPairFactor | None] = []
        self.slots: list[int] = []  # ... their solver slots
        self.ids: list[np.ndarray] = []  # ... their features' track ids
        self.frame_b: list[int] = []  # ... their later frames (non-decreasing)

    # -- the estimate ---------------------------------------------------------------

    def update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, k: int,
               relinearize: bool = False) -> list[int]:
        """One solver update with frame k's new factors and states; fetches frame k."""
        t_s = self.t_ns[k] * 1e-9  # (as the backends time every key: not / NS_PER_S, 1 ulp off)
        slots = self.backend.update(graph, values, {key: t_s for key in frame_keys(k)},
                                    relinearize)
        self.fetch(k)  # only the newest state: a full estimate grows with the flight
        return slots

    def fetch(self, k: int) -> None:
        """Current estimate of frame k's states."""
        self.poses[k] = self.backend.pose(k)
        self.velocities[k] = self.backend.velocity(k)
        self.biases[k] = self.backend.bias(k)

    def pose_guess(self, j: int) -> np.ndarray:
        """Frame j's pose as the solver has it now (the newest frame: its prediction)."""
        # fetch only the poses asked for; frames out of a lag window keep their last
        if self.settled <= j != len(self.t_ns) - 1:
            self.poses[j] = self.backend.pose(j)
        return self.poses[j]

    def iterate(self, steps: int, relative_tol: float = 1e-6) -> tuple[float, bool, float]:
        """Relinearizing updates with no new data until one gains less than
        ``relative_tol`` (at most ``steps``): the final error, whether it stopped by
        itself, and the lowest error seen."""
        previous = best = self.backend.error()
        done = False
        for _ in range(steps):
            self.backend.step()
            error = self.backend.error()
            best = min(best, error)
            done = error >= previous * (1.0 - relative_tol)  # no gain left (or a loss)
            previous = error
            if done:
                break
        return previous, done, best

    def leave_window(self, k: int, converging: bool, final_iterations: int) -> None:
        """Fixed lag: fetch, for the last time, the frames that frame k's update may
        marginalize (older than the lag, with one frame interval of margin so float
        timestamps cannot race the smoother); they keep that estimate (and, offline,
        their covariances)."""
        if self.lag_s is None:
            return
        margin_ns = self.t_ns[k] - self.t_ns[k - 1]
        horizon = self.t_ns[k] - self.lag_s * NS_PER_S + margin_ns
        if converging and self.settled < k and self.t_ns[self.settled] < horizon:
            # A state is marginalized at its linearization point: not while the solution
            # still converges (from a loose prior), or that point is frozen where it was.
            self.iterate(final_iterations)
        while self.settled < k and self.t_ns[self.settled] < horizon:
            j = self.settled
            self.fetch(j)
            if self.keep_exit_covariances:  # ~1 ms: marginals deep in the tree
                self.exit_cov[j] = tuple(self.backend.marginal(key) for key in frame_keys(j))
            self.settled += 1

    def moved_far(self, k: int, predicted: np.ndarray) -> bool:
        """Whether frame k's estimate is past the refresh thresholds from ``predicted``."""
        pose = self.poses[k]
        # the motion predicted^-1 pose: its translation's length (a rotation keeps it) and
        # its angle from the trace of predicted^T pose
        moved_m = float(np.linalg.norm(pose[:3, 3] - predicted[:3, 3]))
        cos_angle = 0.5 * (float(np.sum(predicted[:3, :3] * pose[:3, :3])) - 1.0)
        return bool(moved_m >= self.NOISE_REFRESH_POSITION_M
                    or cos_angle <= np.cos(self.NOISE_REFRESH_ROTATION_RAD))

    def position_sigma_m(self) -> float:
        """The newest estimated frame's largest position 1-sigma (m)."""
        return largest_position_sigma_m(self.state_cov)

    def frame_position_sigma_m(self, j: int) -> float:
        """Frame j's largest position 1-sigma (m) now (as it left the window, if it has;
        the newest frame's where it left without one)."""
        cov = self.frame_pose_covariance(j)
        return largest_position_sigma_m(self.state_cov if cov is None else cov)

    def frame_pose_covariance(self, j: int) -> np.ndarray | None:
        """Frame j's (6, 6) pose covariance now; as it left the window, if it has (None
        where it was not kept)."""
        if j < self.settled:
            return self.exit_cov[j][0] if j in self.exit_cov else None
        return self.backend.marginal(X(j))

    def refresh(self, estimate: gtsam.Values) -> None:
        """Every frame's states from ``estimate``."""
        for key in estimate.keys():
            symbol = gtsam.Symbol(key)
            i, c = int(symbol.index()), chr(symbol.chr())
            if c == "x":
                self.poses[i] = estimate.atPose3(key).matrix()
            elif c == "v":
                self.velocities[i] = np.asarray(estimate.atVector(key))
            elif c == "b":
                self.biases[i] = estimate.atConstantBias(key)

    def values(self) -> gtsam.Values:
        """Latest estimate of every frame so far."""
        values = gtsam.Values()
        for k in range(len(self.t_ns)):
            insert_state(values, k, self.poses[k], self.velocities[k], self.biases[k])
        return values

    def estimate(self) -> TrajectoryEstimate:
        """Latest estimate of every frame so far."""
        K = len(self.t_ns)
        biases = [self.biases[k] for k in range(K)]
        return TrajectoryEstimate(
            t_ns=np.asarray(self.t_ns, dtype=np.int64),
            world_T_body=np.stack([self.poses[k] for k in range(K)]),
            velocity_mps=np.stack([self.velocities[k] for k in range(K)]),
            gyro_bias=np.stack([b.gyroscope() for b in biases]),
            accel_bias=np.stack([b.accelerometer() for b in biases]))

    def covariances(self) -> StateCovariances:
        """Marginals of every frame in the solver; older frames keep the covariances they
        left the window with (if kept), else NaN."""
        K = len(self.t_ns)
        pose, vel, bias = np.full((K, 6, 6), np.nan), np.full((K, 3, 3), np.nan), \
            np.full((K, 6, 6), np.nan)
        current = self.backend.estimate()
        for k in range(K):
            if current.exists(X(k)):
                pose[k], vel[k], bias[k] = (self.backend.marginal(key) for key in frame_keys(k))
            elif k in self.exit_cov:  # as it left the window
                pose[k], vel[k], bias[k] = self.exit_cov[k]
        return StateCovariances(pose, vel, bias)

    def pair_prior(self, k: int, imu: gtsam.CombinedImuFactor, predicted: gtsam.Values
                   ) -> Callable[[int], np.ndarray]:
        """Earlier frame a -> the (12, 12) prior covariance of ``(X(a), X(k))``: frame
        k-1's state covariance carried through the IMU factor (a Kalman prediction, no
        solver update); an older frame a gets its joint covariance with frame k-1."""
        values = gtsam.Values(predicted)
        insert_state(values, k - 1, self.poses[k - 1], self.velocities[k - 1],
                     self.biases[k - 1])
        later, M = propagate_covariance(imu, values, self.state_cov)
        P_k = later[:6, :6]
        cache: dict[int, np.ndarray] = {}

        def prior(a: int) -> np.ndarray:
            if a not in cache:
                if a == k - 1:
                    P_a, cross = self.state_cov[:6, :6], M[:6] @ self.state_cov[:, :6]
                else:
                    J = self.backend.joint_marginal([X(a), *frame_keys(k - 1)])
                    P_a, cross = J[:6, :6], M[:6] @ J[6:, :6]
                P = cache[a] = np.empty((12, 12))
                P[:6, :6], P[:6, 6:], P[6:, :6], P[6:, 6:] = P_a, cross.T, cross, P_k
            return cache[a]

        return prior

    def needs_fix(self, search: FixSearch, k: int) -> bool:
        """Whether frame k starts a search for the fix: the prior (frame 0) or, after a
        long stretch without camera constraints, the newest covariance reaches farther than
        the smoothers pull in."""
        if k == 0:
            return search.needed_at_start()
        return search.needed(self.poses[k - 1], self.state_cov)

    def holds_search(self, search: FixSearch, frame_interval_s: float | None) -> bool:
        """Whether the fixed lag holds the fix search's frames (at the given interval, or
        the frames' median): the fix is applied to the oldest of them, and a frame that left
        the window cannot be moved (frames leave one interval before the lag)."""
        if self.lag_s is None:
            return True
        dt_s = frame_interval_s or float(np.median(np.diff(self.t_ns))) * 1e-9
        return self.lag_s >= search.settings.window_frames * dt_s

    def search_prior(self, j: int, gravity_mps2: float) -> SearchPrior:
        """Where frame j may be, for a fix search: its marginals now."""
        velocity_cov = self.backend.marginal(V(j))
        return SearchPrior.from_pose_covariance(
            self.poses[j], self.backend.marginal(X(j)), self.backend.velocity(j),
            float(np.sqrt(np.linalg.eigvalsh(velocity_cov).max())), gravity_mps2)

    def anchor(self, j0: int, world_T_body: np.ndarray, velocity_mps: np.ndarray, k: int,
               sigmas: tuple[float, float, float], iterations: int) -> list[int]:
        """Move the estimate to a corrected state of frame j0: iSAM2 cannot be told new
        linearization points, so a temporary prior (``sigmas``: rad, m, m/s) holds frame j0
        there while relinearizing steps carry the IMU chain along; frames j0..k fetched.
        Returns the prior's slots, for :meth:`release`."""
        rot, pos, vel = sigmas
        prior = gtsam.NonlinearFactorGraph()
        prior.add(gtsam.PriorFactorPose3(X(j0), gtsam.Pose3(world_T_body),
                                         gtsam.noiseModel.Diagonal.Sigmas(
                                             np.r_[[rot] * 3, [pos] * 3])))
        prior.add(gtsam.PriorFactorVector(V(j0), velocity_mps,
                                          gtsam.noiseModel.Isotropic.Sigma(3, vel)))
        slots = self.backend.update(prior, gtsam.Values(), {})
        self.iterate(iterations)
        for j in range(j0, k + 1):
            self.fetch(j)
        return slots

    def release(self, slots: list[int], k: int, iterations: int) -> None:
        """Take the temporary prior of :meth:`anchor` out (iterating before and after);
        frame k fetched, its covariance anew."""
        self.iterate(iterations)
        self.backend.replace(gtsam.NonlinearFactorGraph(), slots)
        self.iterate(iterations)
        self.fetch(k)
        self.state_cov = self.backend.joint_marginal(list(frame_keys(k)))

    # -- the C-DTM factors in the solver ---------------------------------------------

    def commit(self, k: int, factors: list[CdtmPairFactor], track_ids: list[np.ndarray],
               slots: list[int]) -> None:
        """Frame k's factors entered the solver at ``slots``."""
        self.cdtm.extend(factors)
        self.ids.extend(track_ids)
        # in frame order: the window's factors are found by bisection
        assert not self.frame_b or k >= self.frame_b[-1]
        self.frame_b.extend([k] * len(factors))
        self.slots.extend(slots)

    def live_factors(self) -> list[CdtmPairFactor]:
        return [f for f in self.cdtm if f is not None]

    def since(self, frame: int) -> int:
        """Index of the first factor whose later frame is ``frame`` or after (a round's
        cost must not grow with the flight)."""
        return bisect.bisect_left(self.frame_b, frame)

    def take_out(self, track_ids: np.ndarray, reason: Rejection, rejections: Rejections,
                 first_frame: int = 0) -> None:
        """Take the features of these tracks that are still in the solver out (counted for
        ``reason`` by each factor's later frame). ``first_frame``: the earliest frame any
        of them entered the solver at (the factors ending before it hold none of them:
        full history, the scan would otherwise grow with the flight)."""
        graph = gtsam.NonlinearFactorGraph()
        slots, changed = [], []
        # a factor whose later frame has left the window has left the solver
        for i in range(self.since(max(self.settled, first_frame)), len(self.cdtm)):
            f, ids = self.cdtm[i], self.ids[i]
            if f is None or _frame(f.key_a) < self.settled:
                continue
            hit = np.isin(ids, track_ids)
            if not hit.any():
                continue
            rejections.add(reason, _frame(f.key_b), int(hit.sum()))
            slots.append(self.slots[i])
            replacement = f.with_features(~hit) if not hit.all() else None
            if replacement is not None:
                graph.add(replacement.factor)
            changed.append((i, replacement, ids[~hit]))
        if not slots:
            return
        new_slots = self.backend.replace(graph, slots)
        at = 0
        for i, replacement, ids in changed:
            self.cdtm[i], self.ids[i] = replacement, ids
            if replacement is not None:
                self.slots[i] = new_slots[at]
                at += 1
            else:
                self.slots[i] = -1

    def on_map(self, noise: FeatureNoise, raycast: RayCaster, k: int) -> None:
        """Every C-DTM factor still in the solver on another reading of the map (a grown
        sigma_h, regional slopes: :meth:`~factors.CdtmPairFactor.refreshed`) at the poses
        held now, its kernel's scale kept (a gate's innovation spread); frame k fetched."""
        pose = self.backend.pose
        self._swapped(  # (a factor whose earlier frame has left the window left the solver)
            [i for i in range(self.since(self.settled), len(self.cdtm))
             if (f := self.cdtm[i]) is not None and _frame(f.key_a) >= self.settled],
            lambda f: f.refreshed(pose(_frame(f.key_a)), pose(_frame(f.key_b)), noise,
                                  raycast).with_robust_scale(f.features.robust_scale), k)

    def refresh_newest_noise(self, k: int, predicted: np.ndarray, n: int) -> None:
        """When frame k's update moved it far from its IMU prediction (early frames under a
        loose prior), swap its ``n`` new C-DTM factors for ones whose planes and noise
        (eqs. 19-26) are linearized at the updated estimate, as the batch smoother does at
        its solution. Only the newest factors change: a local re-elimination."""
        if not self.moved_far(k, predicted):
            return
        # (a mismatch round since the commit may have taken some of them out)
        self._swapped(
            [i for i in range(len(self.cdtm) - n, len(self.cdtm)) if self.cdtm[i] is not None],
            lambda f: f.refreshed(self.backend.pose(_frame(f.key_a)), self.poses[k]
                                  ).with_robust_scale(f.features.robust_scale), k)

    def _swapped(self, live: list[int], remade: Callable[[CdtmPairFactor], CdtmPairFactor],
                 k: int) -> None:
        """The factors at ``live`` (in the solver) swapped for ``remade`` ones, in one
        solver update; frame k fetched (nothing if none)."""
        if not live:
            return
        made = []
        graph = gtsam.NonlinearFactorGraph()
        for i in live:
            f = self.cdtm[i]
            assert f is not None
            made.append(remade(f))
            graph.add(made[-1].factor)
        new_slots = self.backend.replace(graph, [self.slots[i] for i in live])
        for i, r, slot in zip(live, made, new_slots):
            self.cdtm[i], self.slots[i] = r, slot
        self.fetch(k)


def largest_position_sigma_m(pose_cov: np.ndarray) -> float:
    """The largest position 1-sigma (m) of a pose covariance (GTSAM's [rot, trans])."""
    return float(np.sqrt(max(largest_eigenvalue_sym3(pose_cov[3:6, 3:6]), 0.0)))
