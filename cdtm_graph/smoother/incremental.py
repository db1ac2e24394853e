"""Incremental smoothing: one frame at a time, the current estimate and its covariance.

:class:`IncrementalSmoother` is a small front over a solver backend (full-history iSAM2
or a fixed lag, :mod:`cdtm_graph.smoother.backends`) with three collaborators: the IMU
feed (:class:`~cdtm_graph.imu.ImuFeed`: samples preintegrated as they arrive), the
pairing of track sightings (:class:`~cdtm_graph.tracks.TrackTable`), the innovation gate
(:class:`~cdtm_graph.gating.InnovationGate`) and the judge of tracks against the DTM
(:class:`~cdtm_graph.smoother.track_judge.TrackJudge`: terrain the map lacks, clutter,
wrong matches). Its pass over a log is also the batch smoother's initializer when the
log has no ``nav.csv``.
"""

from __future__ import annotations

import bisect
import time
from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import V, X

from cdtm_graph.acquisition import Correction, SearchPrior
from cdtm_graph.clutter import clutter_flags, findings, with_vertical_bias
from cdtm_graph.dtm import Dtm
from cdtm_graph.errors import CdtmError, FlightLogError
from cdtm_graph.flightlog import FlightConfig, FlightLog
from cdtm_graph.gating import InnovationGate, residual_test
from cdtm_graph.geometry import largest_eigenvalue_sym3
from cdtm_graph.graph import (
    cdtm_factors,
    cdtm_information,
    feature_noise,
    imu_factor,
    insert_state,
    prior_factors,
)
from cdtm_graph.imu import (
    ImuArrays,
    ImuFeed,
    initial_bias,
    navstate_predict,
    propagate_covariance,
)
from cdtm_graph.replay import replay
from cdtm_graph.results import (
    BiasPrior,
    GraphCounts,
    MapOffset,
    Rejection,
    Rejections,
    SmootherResult,
    Solver,
    SolverStats,
    StateCovariances,
    TrajectoryEstimate,
    frame_flags,
)
from cdtm_graph.smoother.backends import Backend, FixedLag, FullHistory, frame_keys
from cdtm_graph.smoother.fix_search import FixSearch
from cdtm_graph.smoother.settings import Progress, SmootherSettings
from cdtm_graph.smoother.track_judge import TrackJudge
from cdtm_graph.tracks import SightingPairs, check_unique
from factors import CdtmPairFactor


@dataclass(frozen=True)
class FrameUpdate:
    """What the incremental smoother knows right after a frame.

    Attributes:
        frame: index of the newest frame. t_ns: its time.
        world_T_body: (4, 4) its current estimate. velocity_mps: (3,).
        pose_covariance: (6, 6) its marginal, GTSAM tangent order [rot, trans], body frame,
            with an offset of the whole map added (flight.yaml's ``dtm.*_offset_sigma_m``,
            :class:`~cdtm_graph.results.MapOffset`).
        n_features: C-DTM features that arrived with it. update_time_s: the update's cost.
        imu_time_s: time spent preintegrating this frame's interval as its IMU samples
            arrived (``add_imu``), before this update.
    """

    frame: int
    t_ns: int
    world_T_body: np.ndarray
    velocity_mps: np.ndarray
    pose_covariance: np.ndarray
    n_features: int
    update_time_s: float
    imu_time_s: float = 0.0


class IncrementalSmoother:
    """Feed one frame at a time; get the current estimate and the newest covariance.

    Example::

        smoother = IncrementalSmoother(flight.config, dtm)
        smoother.add_imu(imu_samples)                  # as they arrive
        update = smoother.add_frame(t_ns, track_ids, uv_px, closing_imu_samples)

    Args:
        config: the log's flight.yaml (camera, IMU noise, initial state).
        dtm: the terrain.
        settings: the run's settings; the incremental smoother uses ``graph``, ``lag_s``
            (a fixed lag instead of the full history), ``keep_exit_covariances``,
            ``innovation_gate`` and ``final_iterations``.
        imu: IMU samples known up front (a log); otherwise feed them with ``add_imu``.
        frame_interval_s: expected time between frames; with a lag, it lets the smoother
            relinearize less often than every update (still four times per window).
    """

    def __init__(self, config: FlightConfig, dtm: Dtm, settings: SmootherSettings | None = None,
                 imu: ImuArrays | None = None, frame_interval_s: float | None = None):
        self.config = config
        self.dtm = dtm
        self.settings = settings = settings or SmootherSettings()
        graph = settings.graph
        self._noise = feature_noise(config, dtm, graph)
        self._imu = ImuFeed(config, graph.imu_hold, imu, graph.earth_physics, graph.imu_gap_noise)
        self.rejections = Rejections()  # features left out, by reason and frame
        self._pairing = SightingPairs(config.camera.camera, config.camera.body_T_cam, dtm,
                                      config.camera.pixel_sigma_px, graph.epipolar,
                                      self.rejections)
        self._gate = InnovationGate(settings.innovation_gate, max(abs(dtm.dx), abs(dtm.dy)),
                                    self.rejections)
        # terrain the DTM lacks, clutter, wrong matches: tracks judged and left out
        self._judge = (None if graph.mismatch is None else TrackJudge(
            graph.mismatch, graph.clutter, dtm, self._noise, config.camera.body_T_cam,
            self.rejections))
        # fix acquisition: while the pose is too uncertain for the C-DTM linearization,
        # sightings are held back until a search over the newest frames finds the fix
        self._search = (None if settings.acquisition is None else
                        FixSearch(settings.acquisition, config, dtm, self.rejections))
        self._frame_interval_s = frame_interval_s
        if frame_interval_s is not None and self._search is not None \
                and self._search.needed_at_start() and not self._lag_holds_search(frame_interval_s):
            raise self._lag_too_short(frame_interval_s)
        self._frame_flags: dict[int, list[str]] = {}
        self._backend: Backend = (
            FullHistory() if settings.lag_s is None
            else FixedLag(settings.lag_s, frame_interval_s))
        self._state_cov = np.zeros((15, 15))  # newest frame's [X, V, B] covariance
        self._map_offset = MapOffset.of(config.dtm)  # in what it reports, not what it uses
        self._camera = config.camera.camera
        self._body_T_cam = config.camera.body_T_cam
        self._t_ns: list[int] = []
        # latest estimate of every frame (frames out of a lag window keep their last)
        self._poses: dict[int, np.ndarray] = {}
        self._velocities: dict[int, np.ndarray] = {}
        self._biases: dict[int, gtsam.imuBias.ConstantBias] = {}
        self._settled = 0  # fixed lag: frames before this one have left the window
        self._exit_cov: dict[int, tuple[np.ndarray, ...]] = {}  # ... their (X, V, B) then
        # every C-DTM factor (outliers, refresh); None where its features all went
        self._cdtm: list[CdtmPairFactor | None] = []
        self._cdtm_slots: list[int] = []  # ... their solver slots
        self._cdtm_ids: list[np.ndarray] = []  # ... their features' track ids
        self._cdtm_frame_b: list[int] = []  # ... their later frames (non-decreasing)
        # Warm-up: from a loose prior (or an acquired fix) every update moves its frame far
        # from the prediction, until one does not; nothing is judged meanwhile. Not a test
        # per update: outliers that moved one would switch off the tests that stop them.
        self._converging = True
        self._features_per_frame: dict[int, int] = {}
        self.n_features = self.n_cdtm_factors = 0
        self.update_times_s: list[float] = []
        self.imu_times_s: list[float] = []
        self.final_error = float("nan")
        self.converged = False

    #: finalize(): a settled error within this relative spread of the lowest one is converged.
    CONVERGED_SPREAD = 1e-4

    #: The newest C-DTM factors are rebuilt once when the update moved their frame this
    #: far from the prediction their noise was linearized at (metres, radians).
    NOISE_REFRESH_POSITION_M = 2.0
    NOISE_REFRESH_ROTATION_RAD = np.radians(0.2)

    # -- input ------------------------------------------------------------------------

    def add_imu(self, imu: ImuArrays) -> None:
        """Append IMU samples (times after the ones already held) as they arrive.

        They are preintegrated at once, as far as they fix the hold pieces, so a frame
        update is left with the last piece or two of its interval. The time this takes
        is kept per frame interval (``imu_times_s``).
        """
        self._imu.add(imu)

    def add_frame(self, t_ns: int, track_id: np.ndarray | None = None,
                  uv_px: np.ndarray | None = None, imu: ImuArrays | None = None) -> FrameUpdate:
        """Add the next frame: its time, its tracked features, and new IMU samples.

        Args:
            t_ns: frame time (after the previous frame's).
            track_id: (m,) ids of the features seen in this frame.
            uv_px: (m, 2) their pixels.
            imu: IMU samples since the last call (optional if given at construction);
                they may run past the frame (held, not yet integrated).

        Returns:
            The newest frame's estimate and covariance.

        Raises:
            FlightLogError: inconsistent input (time order, shapes, repeated ids); nothing
                changes. SolverError: the IMU does not cover the interval yet (feed the
                missing samples and retry the frame) or the system is unsolvable.
        """
        start = time.perf_counter()
        k = len(self._t_ns)
        if k and t_ns <= self._t_ns[-1]:
            raise FlightLogError(f"frame {k}: time {t_ns} ns is not after the previous frame")
        seen = self._checked_sightings(k, track_id, uv_px)  # before anything changes
        if imu is not None:
            self._imu.hold(imu)
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        link = None  # the IMU factor from the previous frame
        if k == 0:
            init = self.config.initial_state
            graph.push_back(prior_factors(init, 0))
            predicted, bias = init.world_T_body, initial_bias(init)
            velocity = np.asarray(init.velocity_mps, float)
        else:
            bias = self._biases[k - 1]  # the IMU feed's linearization point too
            pim = self._imu.finish(int(t_ns), (self._poses[k - 1], self._velocities[k - 1]))
            if pim.spans_gap:  # predicted across an IMU gap: a guess, judge nothing by it
                self._converging = True
            link = imu_factor(k - 1, pim)
            graph.add(link)
            predicted, velocity = navstate_predict(pim, self._poses[k - 1],
                                                   self._velocities[k - 1], bias)
        insert_state(values, k, predicted, velocity, bias)
        self._t_ns.append(int(t_ns))
        self._poses[k], self._velocities[k], self._biases[k] = predicted, velocity, bias
        if k:
            self._leave_window(k)
        if self._search is not None and (self._search.active or self._should_acquire(k)):
            if not self._search.active and k and not self._lag_holds_search(
                    self._frame_interval_s or float(np.median(np.diff(self._t_ns))) * 1e-9):
                # the covariance outgrew what the smoothers pull in (a long gap), but the
                # lag cannot hold the frames a search needs: on unsearched, and said so
                self._frame_flags.setdefault(k, []).append("search_beyond_lag")
            else:
                self._search.hold(k, seen)
                seen = None  # held back: no C-DTM factor until the fix is found
                self._frame_flags.setdefault(k, []).append("no_fix")
        new, new_ids = self._new_cdtm(k, *seen) if seen is not None else ([], [])
        if new and link is not None:
            # Each feature's innovation against the IMU's prediction: the kernel's scale
            # and the gate (not while the solution still converges from a loose prior: the
            # linearized test would misjudge good features).
            new, new_ids = self._gate.apply(
                k, new, new_ids, self._pose_guess, self._pair_prior(k, link, values),
                test=not self._converging)
        if new and self._judge is not None and not self._converging \
                and self._judge.settle(k, sigma_m := self._position_sigma_m()):
            new, new_ids, off_map, wrong = self._judge.judge_new(
                k, new, new_ids, self._pose_guess, sigma_m)
            if off_map.size:
                self._forget_tracks(off_map, Rejection.MAP_MISMATCH)
            if wrong.size:
                self._forget_tracks(wrong, Rejection.WRONG_MATCH)
        n_new = sum(f.features.n for f in new)
        for f in new:
            graph.add(f.factor)
        slots = self._update(graph, values, k)
        self._commit(k, new, new_ids, slots[len(slots) - len(new):] if slots else [])
        if self._judge is not None and self._judge.due(k):
            self._mismatch_round(k, self._judge.window_start(k))
        if new:
            self._refresh_newest_noise(k, predicted, len(new))
            # (a frame without factors cannot move: it says nothing of convergence)
            self._converging = self._converging and self._moved_far(k, predicted)
        if link is not None and pim.spans_gap:  # predicted across an IMU gap: a poor
            self._iterate(self.settings.final_iterations)  # linearization point, iterate
            self._fetch(k)
        self._state_cov = self._backend.joint_marginal(list(frame_keys(k)))
        if self._search is not None and self._search.active:
            self._try_acquisition(k)
        self._imu.start(int(t_ns), self._biases[k])
        pose_cov = self._map_offset.added_to_pose(self._state_cov[:6, :6], self._poses[k])
        elapsed = time.perf_counter() - start
        self.update_times_s.append(elapsed)
        self.imu_times_s.append(self._imu.take_time_s())
        return FrameUpdate(k, int(t_ns), self._poses[k], self._velocities[k], pose_cov, n_new,
                           elapsed, self.imu_times_s[-1])

    def _pair_prior(self, k: int, imu: gtsam.CombinedImuFactor, predicted: gtsam.Values
                    ) -> Callable[[int], np.ndarray]:
        """Earlier frame a -> the (12, 12) prior covariance of ``(X(a), X(k))``: frame
        k-1's state covariance carried through the IMU factor (a Kalman prediction, no
        solver update); an older frame a gets its joint covariance with frame k-1."""
        values = gtsam.Values(predicted)
        insert_state(values, k - 1, self._poses[k - 1], self._velocities[k - 1],
                     self._biases[k - 1])
        later, M = propagate_covariance(imu, values, self._state_cov)
        P_k = later[:6, :6]
        cache: dict[int, np.ndarray] = {}

        def prior(a: int) -> np.ndarray:
            if a not in cache:
                if a == k - 1:
                    P_a, cross = self._state_cov[:6, :6], M[:6] @ self._state_cov[:, :6]
                else:
                    J = self._backend.joint_marginal([X(a), *frame_keys(k - 1)])
                    P_a, cross = J[:6, :6], M[:6] @ J[6:, :6]
                P = cache[a] = np.empty((12, 12))
                P[:6, :6], P[:6, 6:], P[6:, :6], P[6:, 6:] = P_a, cross.T, cross, P_k
            return cache[a]

        return prior

    def _should_acquire(self, k: int) -> bool:
        """Whether frame k starts a search for the fix: the prior (frame 0) or, after a
        long stretch without camera constraints, the newest covariance reaches farther than
        the smoothers pull in."""
        assert self._search is not None
        if k == 0:
            return self._search.needed_at_start()
        return self._search.needed(self._poses[k - 1], self._state_cov)

    def _lag_holds_search(self, frame_interval_s: float) -> bool:
        """Whether the fixed lag holds the fix search's frames: the fix is applied to the
        oldest of them, and a frame that left the window cannot be moved (frames leave
        one interval before the lag, :meth:`_leave_window`)."""
        assert self._search is not None
        return (self.settings.lag_s is None
                or self.settings.lag_s >= self._search.settings.window_frames * frame_interval_s)

    def _lag_too_short(self, frame_interval_s: float) -> CdtmError:
        assert self._search is not None and self.settings.lag_s is not None
        frames = self._search.settings.window_frames
        need_s = frames * frame_interval_s
        return CdtmError(
            f"a fixed lag of {self.settings.lag_s:g} s is shorter than the fix search's window "
            f"({frames} frames, {need_s:g} s at {1 / frame_interval_s:.3g} frames/s): expected "
            f"a lag of at least {need_s:g} s, or no fix search (SmootherSettings.acquisition="
            "None)")

    def _try_acquisition(self, k: int) -> None:
        """Search the held frames for the fix if a search is due (:class:`FixSearch`); on
        success, move the estimate there and let the held sightings in."""
        assert self._search is not None
        # Held frames the lag let go cannot be moved to a fix: their sightings are lost
        # (no_fix). Only when the lag is shorter than the search's window (a live smoother
        # not told its frame interval, or frames that came slower than expected).
        self._search.forget_before(self._settled)
        correction = self._search.search(k, self._t_ns.__getitem__, self._pose_guess,
                                         self._search_prior)
        if correction is None:
            return
        self._apply_fix(correction, self._search.held, k)
        for j, _, _ in self._search.found():  # their sightings are in now
            self._frame_flags[j].remove("no_fix")
            if not self._frame_flags[j]:
                del self._frame_flags[j]

    def _search_prior(self, j: int) -> SearchPrior:
        """Where frame j may be, for a search: its marginals now."""
        velocity_cov = self._backend.marginal(V(j))
        return SearchPrior.from_pose_covariance(
            self._poses[j], self._backend.marginal(X(j)), self._backend.velocity(j),
            float(np.sqrt(np.linalg.eigvalsh(velocity_cov).max())), self.config.gravity_mps2)

    #: While the estimate moves to an acquired fix, the first window frame is held there by
    #: a temporary prior this tight (rad, m, m/s).
    ANCHOR_SIGMAS = (np.radians(0.2), 2.0, 0.2)

    def _apply_fix(self, correction: Correction,
                   held: list[tuple[int, np.ndarray, np.ndarray]], k: int) -> None:
        """Move the estimate to the acquired fix, then add the held sightings.

        iSAM2 cannot be told new linearization points: a temporary prior holds the first
        window frame at the corrected state while relinearizing steps carry the IMU chain
        there; then the held frames' C-DTM factors (built at the corrected poses) go in and
        the temporary prior comes out.
        """
        j0 = held[0][0]
        pose, velocity = correction.apply_to_state(self._poses[j0], self._velocities[j0])
        rot, pos, vel = self.ANCHOR_SIGMAS
        anchor = gtsam.NonlinearFactorGraph()
        anchor.add(gtsam.PriorFactorPose3(X(j0), gtsam.Pose3(pose),
                                          gtsam.noiseModel.Diagonal.Sigmas(
                                              np.r_[[rot] * 3, [pos] * 3])))
        anchor.add(gtsam.PriorFactorVector(V(j0), velocity,
                                           gtsam.noiseModel.Isotropic.Sigma(3, vel)))
        slots = self._backend.update(anchor, gtsam.Values(), {})
        self._iterate(2 * self.settings.final_iterations)
        for j in range(j0, k + 1):
            self._fetch(j)
        graph = gtsam.NonlinearFactorGraph()
        committed = []
        for j, ids, uv in held:
            factors, track_ids = self._new_cdtm(j, ids, uv)
            for f in factors:
                graph.add(f.factor)
            committed.append((j, factors, track_ids))
        new_slots = self._backend.update(graph, gtsam.Values(), {})
        at = 0
        for j, factors, track_ids in committed:
            self._commit(j, factors, track_ids, new_slots[at:at + len(factors)])
            at += len(factors)
        self._iterate(self.settings.final_iterations)
        self._backend.replace(gtsam.NonlinearFactorGraph(), slots)
        self._iterate(self.settings.final_iterations)
        self._fetch(k)
        self._state_cov = self._backend.joint_marginal(list(frame_keys(k)))
        self._converging = True  # judge nothing until the estimate has settled

    def _checked_sightings(self, k: int, track_id: np.ndarray | None, uv_px: np.ndarray | None
                           ) -> tuple[np.ndarray, np.ndarray] | None:
        if track_id is None or not len(track_id):
            return None
        ids = np.asarray(track_id, dtype=np.int64)
        uv = np.asarray(uv_px, dtype=float)
        if ids.ndim != 1 or uv.shape != (ids.size, 2):
            raise FlightLogError(f"frame {k}: {ids.shape} track ids with pixels of "
                                 f"shape {uv.shape}; expected (m,) and (m, 2)")
        check_unique(k, ids)
        return ids, uv

    def _new_cdtm(self, k: int, track_id: np.ndarray, uv_px: np.ndarray
                  ) -> tuple[list[CdtmPairFactor], list[np.ndarray]]:
        """The C-DTM factors frame k's sightings close (counted, not yet in the graph).

        A fixed lag has let go of frames before the window: their pairs are dropped
        (counted), and tracks last seen there can never pair again.
        """
        pairs = self._pairing.add_frame(k, track_id, uv_px, self._pose_guess, self._settled)
        table = self._pairing.table
        if self.settings.lag_s is not None and len(table) > 4 * len(track_id):
            table.forget_before(self._settled)
            if self._judge is not None:
                self._judge.observations.forget_before(self._settled)
        if self._judge is not None:  # tracks found off the map stay out
            pairs = self._judge.keep_out(k, pairs)
        build = cdtm_factors(pairs, self._poses, self._body_T_cam, self.dtm, self._noise,
                             self.settings.graph, self.rejections)
        return build.factors, build.track_ids

    def _pose_guess(self, j: int) -> np.ndarray:
        """Frame j's pose as the solver has it now (the newest frame: its prediction)."""
        # fetch only the poses asked for; frames out of a lag window keep their last
        if self._settled <= j != len(self._t_ns) - 1:
            self._poses[j] = self._backend.pose(j)
        return self._poses[j]

    def _position_sigma_m(self) -> float:
        """The newest estimated frame's largest position 1-sigma (m)."""
        return _largest_position_sigma_m(self._state_cov)

    def _frame_position_sigma_m(self, j: int) -> float:
        """Frame j's largest position 1-sigma (m) now (as it left the window, if it has)."""
        if j < self._settled:
            cov = self._exit_cov[j][0] if j in self._exit_cov else None
        else:
            cov = self._backend.marginal(X(j))
        return _largest_position_sigma_m(self._state_cov if cov is None else cov)

    #: finalize(): rounds of "judge every track, take out the ones off the map, relinearize".
    MISMATCH_ROUNDS = 8

    def _mismatch_round(self, k: int, since_frame: int) -> int:
        """Judge the tracks seen since ``since_frame`` at the current estimate
        (:meth:`TrackJudge.round`); take the ones it leaves out of the solver. Returns how
        many."""
        if self._judge is None:
            return 0
        off, wrong = self._judge.round(since_frame, self._pose_guess,
                                       self._frame_position_sigma_m)
        if off.size:
            self._forget_tracks(off, Rejection.MAP_MISMATCH)
        if wrong.size:
            self._forget_tracks(wrong, Rejection.WRONG_MATCH)
        if off.size or wrong.size:
            self._fetch(k)
        recent = bisect.bisect_left(self._cdtm_frame_b, since_frame)  # (a round's cost
        # must not grow with the flight)
        self._judge.consider(since_frame, k, self._cdtm[recent:], self._cdtm_ids[recent:])
        return int(off.size + wrong.size)

    def _forget_tracks(self, track_ids: np.ndarray, reason: Rejection) -> None:
        """Keep these tracks out from now on, and take their features that entered
        earlier out of the solver (those still in it), counted for ``reason``."""
        assert self._judge is not None
        self._judge.left_out = np.union1d(self._judge.left_out, track_ids)
        graph = gtsam.NonlinearFactorGraph()
        slots, changed = [], []
        # a factor whose later frame has left the window has left the solver
        for i in range(bisect.bisect_left(self._cdtm_frame_b, self._settled), len(self._cdtm)):
            f, ids = self._cdtm[i], self._cdtm_ids[i]
            if f is None or int(gtsam.Symbol(f.key_a).index()) < self._settled:
                continue
            hit = np.isin(ids, track_ids)
            if not hit.any():
                continue
            self.rejections.add(reason, int(gtsam.Symbol(f.key_b).index()), int(hit.sum()))
            slots.append(self._cdtm_slots[i])
            replacement = f.with_features(~hit) if not hit.all() else None
            if replacement is not None:
                graph.add(replacement.factor)
            changed.append((i, replacement, ids[~hit]))
        if not slots:
            return
        new_slots = self._backend.replace(graph, slots)
        at = 0
        for i, replacement, ids in changed:
            self._cdtm[i], self._cdtm_ids[i] = replacement, ids
            if replacement is not None:
                self._cdtm_slots[i] = new_slots[at]
                at += 1
            else:
                self._cdtm_slots[i] = -1

    def _commit(self, k: int, factors: list[CdtmPairFactor], track_ids: list[np.ndarray],
                slots: list[int]) -> None:
        n_features = sum(f.features.n for f in factors)
        self._cdtm.extend(factors)
        self._cdtm_ids.extend(track_ids)
        # in frame order: the window's factors are found by bisection
        assert not self._cdtm_frame_b or k >= self._cdtm_frame_b[-1]
        self._cdtm_frame_b.extend([k] * len(factors))
        self._cdtm_slots.extend(slots)
        if self._judge is not None:
            self._judge.record(k, factors, track_ids)
        self.n_features += n_features
        self.n_cdtm_factors += len(factors)
        self._features_per_frame[k] = n_features

    def _update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, k: int,
                relinearize: bool = False) -> list[int]:
        """One solver update with frame k's new factors and states; fetches frame k."""
        t_s = self._t_ns[k] * 1e-9
        slots = self._backend.update(graph, values, {key: t_s for key in frame_keys(k)},
                                     relinearize)
        self._fetch(k)  # only the newest state: a full estimate grows with the flight
        return slots

    def _leave_window(self, k: int) -> None:
        """Fixed lag: fetch, for the last time, the frames that frame k's update may
        marginalize (older than the lag, with one frame interval of margin so float
        timestamps cannot race the smoother); they keep that estimate (and, offline,
        their covariances)."""
        lag_s = self.settings.lag_s
        if lag_s is None:
            return
        margin_ns = self._t_ns[k] - self._t_ns[k - 1]
        horizon = self._t_ns[k] - lag_s * 1e9 + margin_ns
        if self._converging and self._settled < k and self._t_ns[self._settled] < horizon:
            # A state is marginalized at its linearization point: not while the solution
            # still converges (from a loose prior), or that point is frozen where it was.
            self._iterate(self.settings.final_iterations)
        while self._settled < k and self._t_ns[self._settled] < horizon:
            j = self._settled
            self._fetch(j)
            if self.settings.keep_exit_covariances:  # ~1 ms: marginals deep in the tree
                self._exit_cov[j] = tuple(self._backend.marginal(key) for key in frame_keys(j))
            self._settled += 1

    def _fetch(self, k: int) -> None:
        """Current estimate of frame k's states."""
        self._poses[k] = self._backend.pose(k)
        self._velocities[k] = self._backend.velocity(k)
        self._biases[k] = self._backend.bias(k)

    def _moved_far(self, k: int, predicted: np.ndarray) -> bool:
        """Whether frame k's estimate is past the refresh thresholds from ``predicted``."""
        pose = self._poses[k]
        # the motion predicted^-1 pose: its translation's length (a rotation keeps it) and
        # its angle from the trace of predicted^T pose
        moved_m = float(np.linalg.norm(pose[:3, 3] - predicted[:3, 3]))
        cos_angle = 0.5 * (float(np.sum(predicted[:3, :3] * pose[:3, :3])) - 1.0)
        return bool(moved_m >= self.NOISE_REFRESH_POSITION_M
                    or cos_angle <= np.cos(self.NOISE_REFRESH_ROTATION_RAD))

    def _refresh_newest_noise(self, k: int, predicted: np.ndarray, n: int) -> None:
        """When frame k's update moved it far from its IMU prediction (early frames under a
        loose prior), swap its ``n`` new C-DTM factors for ones whose planes and noise
        (eqs. 19-26) are linearized at the updated estimate, as the batch smoother does at
        its solution. Only the newest factors change: a local re-elimination."""
        if not self._moved_far(k, predicted):
            return
        # (a mismatch round since the commit may have taken some of them out)
        live = [i for i in range(len(self._cdtm) - n, len(self._cdtm))
                if self._cdtm[i] is not None]
        if not live:
            return
        refreshed = []
        graph = gtsam.NonlinearFactorGraph()
        for i in live:
            f = self._cdtm[i]
            assert f is not None
            r = f.refreshed(self._backend.pose(int(gtsam.Symbol(f.key_a).index())),
                            self._poses[k]).with_robust_scale(f.features.robust_scale)
            refreshed.append(r)
            graph.add(r.factor)
        new_slots = self._backend.replace(graph, [self._cdtm_slots[i] for i in live])
        for i, r, slot in zip(live, refreshed, new_slots):
            self._cdtm[i], self._cdtm_slots[i] = r, slot
        self._fetch(k)

    # -- results ----------------------------------------------------------------------

    def finalize(self, iterations: int | None = None, relative_tol: float = 1e-6) -> bool:
        """Relinearize everything and iterate with no new data, so the estimate reaches the
        optimum (``relinearizeSkip`` otherwise leaves it one step from a stale point).

        Args:
            iterations: at most this many relinearizing steps (default:
                ``settings.final_iterations``).
            relative_tol: a step that lowers the error by less than this, relatively, ends.

        Returns:
            Whether it settled: the error stopped decreasing within ``CONVERGED_SPREAD``
            of the lowest error seen. Near the optimum, relinearizing only the states past
            their thresholds makes the error wander by ~1e-5 relative: it stops at the
            first step that does not gain.
        """
        steps = self.settings.final_iterations if iterations is None else iterations
        previous, done, best = self._iterate(steps, relative_tol)
        if self._t_ns and self._judge is not None:
            # the tracks in the solver, judged at the converged estimate, until none is off
            k = len(self._t_ns) - 1
            for _ in range(self.MISMATCH_ROUNDS):
                if not self._mismatch_round(k, self._settled):
                    break
                previous, done, best = self._iterate(steps, relative_tol)
        self._refresh(self._backend.estimate())
        if self._t_ns:  # more frames may follow: the next interval at the new bias estimate
            k = len(self._t_ns) - 1
            self._imu.start(self._t_ns[k], self._biases[k])
            self._imu.advance()
        self.final_error = previous
        self.converged = done and previous <= best * (1.0 + self.CONVERGED_SPREAD)
        return self.converged

    def _iterate(self, steps: int, relative_tol: float = 1e-6) -> tuple[float, bool, float]:
        """Relinearizing updates with no new data until one gains less than
        ``relative_tol`` (at most ``steps``): the final error, whether it stopped by
        itself, and the lowest error seen."""
        previous = best = self._backend.error()
        done = False
        for _ in range(steps):
            self._backend.step()
            error = self._backend.error()
            best = min(best, error)
            done = error >= previous * (1.0 - relative_tol)  # no gain left (or a loss)
            previous = error
            if done:
                break
        return previous, done, best

    def _refresh(self, estimate: gtsam.Values) -> None:
        for key in estimate.keys():
            symbol = gtsam.Symbol(key)
            i, c = int(symbol.index()), chr(symbol.chr())
            if c == "x":
                self._poses[i] = estimate.atPose3(key).matrix()
            elif c == "v":
                self._velocities[i] = np.asarray(estimate.atVector(key))
            elif c == "b":
                self._biases[i] = estimate.atConstantBias(key)

    @property
    def innovation_nis(self) -> np.ndarray:
        """Squared Mahalanobis distance of every innovation the gate tested, (n,):
        chi-square(2) (median 1.39, mean 2) when the noise model and the prior are honest."""
        return self._gate.all_nis

    @property
    def acquisitions(self) -> list[dict]:
        """Each search for the fix: frame, window, verdict, reason."""
        return [] if self._search is None else self._search.searches

    @property
    def mismatched_tracks(self) -> np.ndarray:
        """Tracks left out as off the map or holding a wrong match (sorted)."""
        return np.zeros(0, np.int64) if self._judge is None else self._judge.left_out

    @property
    def unfixed_frames(self) -> np.ndarray:
        """Frames whose sightings were held back for a fix that was not found (sorted)."""
        return np.array(sorted(k for k, flags in self._frame_flags.items()
                               if "no_fix" in flags), dtype=np.int64)

    def values(self) -> gtsam.Values:
        """Latest estimate of every frame so far (frames out of a lag window keep the
        estimate they had when they left it)."""
        values = gtsam.Values()
        for k in range(len(self._t_ns)):
            insert_state(values, k, self._poses[k], self._velocities[k], self._biases[k])
        return values

    def estimate(self) -> TrajectoryEstimate:
        """Latest estimate of every frame so far."""
        K = len(self._t_ns)
        biases = [self._biases[k] for k in range(K)]
        return TrajectoryEstimate(
            t_ns=np.asarray(self._t_ns, dtype=np.int64),
            world_T_body=np.stack([self._poses[k] for k in range(K)]),
            velocity_mps=np.stack([self._velocities[k] for k in range(K)]),
            gyro_bias=np.stack([b.gyroscope() for b in biases]),
            accel_bias=np.stack([b.accelerometer() for b in biases]))

    def covariances(self) -> StateCovariances:
        """Marginals of every frame (full-history iSAM2), or of the frames still in the
        window (fixed lag; older frames keep the covariances they left the window with
        if ``keep_exit_covariances``, else NaN)."""
        K = len(self._t_ns)
        pose, vel, bias = np.full((K, 6, 6), np.nan), np.full((K, 3, 3), np.nan), \
            np.full((K, 6, 6), np.nan)
        current = self._backend.estimate()
        for k in range(K):
            if current.exists(X(k)):
                pose[k], vel[k], bias[k] = (self._backend.marginal(key) for key in frame_keys(k))
            elif k in self._exit_cov:  # as it left the window
                pose[k], vel[k], bias[k] = self._exit_cov[k]
        return StateCovariances(pose, vel, bias)

    def run(self, flight: FlightLog, progress: Progress | None = None) -> SmootherResult:
        """Feed a whole log frame by frame (:func:`~cdtm_graph.replay.replay`), finalize,
        and return the result like :func:`~cdtm_graph.smoother.smooth`.

        Unless the smoother was given the IMU up front, the log's samples are fed as they
        would arrive live: those before each frame through :meth:`add_imu`, then the
        frame with the sample that closes its interval.
        """
        start = time.perf_counter()
        K = len(flight.frames)
        live_imu = not self._imu.given_up_front
        for frame in replay(flight):
            if live_imu and len(frame.imu_before):
                self.add_imu(frame.imu_before)
            self.add_frame(frame.t_ns, frame.track_id, frame.uv_px,
                           frame.imu_closing if live_imu else None)
            if progress is not None:
                progress(frame.k + 1, K)
        self.finalize()
        if self._search is not None:  # the log ended before a fix was found
            self._search.give_up()
        elapsed = time.perf_counter() - start
        t0 = time.perf_counter()
        covariances = self.covariances()
        estimate = self.estimate()
        residuals = residual_test([f for f in self._cdtm if f is not None],
                                  estimate.world_T_body, K)
        counts = GraphCounts(
            K, self._pairing.table.n_tracks, self._pairing.n_observations,
            self._pairing.n_pairs, self.n_features,
            self.n_cdtm_factors, K - 1,
            np.array([self._features_per_frame.get(k, 0) for k in range(K)]),
            residuals.n_outliers, residuals.outliers_per_frame, self.rejections.per_frame(K),
            residuals.chi2_within_per_frame)
        nis = self.innovation_nis
        stats = SolverStats(
            Solver.ISAM2 if self.settings.lag_s is None else Solver.FIXED_LAG, K,
            float("nan"), self.final_error, self.converged, elapsed,
            time.perf_counter() - t0, tuple(self.update_times_s), tuple(self.imu_times_s),
            float(np.median(nis)) if nis.size else float("nan"),
            float(np.mean(nis)) if nis.size else float("nan"))
        information = cdtm_information([f for f in self._cdtm if f is not None],
                                       estimate.world_T_body.__getitem__, K)
        settings = self.settings.to_dict()
        settings["acquisitions"] = self.acquisitions
        flags = {k: list(v) for k, v in self._frame_flags.items()}
        terrain = None
        clutter_settings = self.settings.graph.clutter
        if self._judge is not None and clutter_settings is not None:
            offsets = self._judge.considered(K)
            covariances = with_vertical_bias(covariances, estimate.world_T_body, offsets)
            terrain = findings(self._judge.clutter, offsets)
            for k, v in clutter_flags(offsets, clutter_settings).items():
                flags.setdefault(k, []).extend(v)
        return SmootherResult(estimate, self._map_offset.added_to(covariances,
                                                                  estimate.world_T_body),
                              stats, counts, settings, frame_flags(counts, flags), information,
                              terrain, map_offset=self._map_offset,
                              bias_prior=BiasPrior.of(self.config))


def _largest_position_sigma_m(pose_cov: np.ndarray) -> float:
    """The largest position 1-sigma (m) of a pose covariance (GTSAM's [rot, trans])."""
    return float(np.sqrt(max(largest_eigenvalue_sym3(pose_cov[3:6, 3:6]), 0.0)))
