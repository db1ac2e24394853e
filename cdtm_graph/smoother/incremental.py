"""Incremental smoothing: one frame at a time, the current estimate and its covariance.

:class:`IncrementalSmoother` feeds each frame's sightings through the defences' stages
(:mod:`cdtm_graph.robust.stages`: the fix search's hold, pairing with the epipolar check,
tracks kept out, the factors built, the innovation gate, the track tests) and solves with
a :class:`~cdtm_graph.smoother.window.SolverWindow` (full-history iSAM2 or a fixed lag).
The IMU feed (:class:`~cdtm_graph.imu.ImuFeed`) preintegrates samples as they arrive. Its
pass over a log is also the batch smoother's initializer when the log has no ``nav.csv``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np

from cdtm_graph.calibration.considered import LiveShare
from cdtm_graph.codes import Code
from cdtm_graph.dtm import Dtm
from cdtm_graph.errors import CdtmError, FlightLogError
from cdtm_graph.flightlog import FlightConfig, FlightLog
from cdtm_graph.graph import (
    GraphSettings,
    feature_noise,
    imu_factor,
    insert_state,
    prior_factors,
)
from cdtm_graph.imu import ImuArrays, ImuFeed, initial_bias, navstate_predict
from cdtm_graph.replay import replay
from cdtm_graph.results import (
    GraphCounts,
    MapOffset,
    Rejection,
    Rejections,
    SmootherResult,
    Solver,
    SolverStats,
    StateCovariances,
    TrajectoryEstimate,
)
from cdtm_graph.robust.acquisition import Correction
from cdtm_graph.robust.fix_search import FixSearch
from cdtm_graph.robust.gating import InnovationGate
from cdtm_graph.robust.map_error import BroadMapWatch, MapErrorWatch
from cdtm_graph.robust.observations import TieredObservations
from cdtm_graph.robust.stages import (
    BUILD,
    BuildFactors,
    FrameWork,
    HoldForFix,
    PairSightings,
    incremental_stages,
)
from cdtm_graph.robust.track_judge import TrackJudge
from cdtm_graph.smoother.assembly import ClutterOutcome, assemble_result
from cdtm_graph.smoother.backends import frame_keys
from cdtm_graph.smoother.frame_flags import FrameFlags
from cdtm_graph.smoother.map_growth import MapGrowth
from cdtm_graph.smoother.settings import Progress, SmootherSettings
from cdtm_graph.smoother.settling import Settling
from cdtm_graph.smoother.track_rounds import TrackRounds
from cdtm_graph.smoother.window import SolverWindow
from cdtm_graph.tracks import SightingPairs, checked_sightings
from factors import CdtmPairFactor


@dataclass(frozen=True)
class FrameUpdate:
    """What the incremental smoother knows right after a frame.

    Attributes:
        frame: index of the newest frame. t_ns: its time.
        world_T_body: (4, 4) its current estimate. velocity_mps: (3,).
        pose_covariance: (6, 6) its marginal, GTSAM tangent order [rot, trans], body frame,
            with an offset of the whole map added (flight.yaml's ``dtm.*_offset_sigma_m``,
            :class:`~cdtm_graph.results.MapOffset`) and a declared principal point's share
            (``camera.principal_point_sigma_px``, :class:`~cdtm_graph.calibration.
            considered.LiveShare`).
        n_features: C-DTM features that arrived with it. update_time_s: the update's cost.
        imu_time_s: time spent preintegrating this frame's interval as its IMU samples
            arrived (``add_imu``), before this update.
        converged: whether the estimate had settled under the C-DTM factors (a
            relinearizing step moved the frame by less than its 1-sigma). While it has not
            (from the prior, an acquired fix, an IMU gap), ``pose_covariance`` is the last
            settled covariance (at first the prior's) carried to this frame by the IMU
            alone, not the marginal at a linearization point the estimate is still leaving.
        map_sigma_h_m: the DTM height 1-sigma its factors hold: flight.yaml's, until the
            tracks show the map worse (:class:`~cdtm_graph.robust.map_error.MapErrorWatch`;
            :attr:`IncrementalSmoother.map_grown`).
        flags: why the frame's fix is weak or not to be trusted, as known now
            (:class:`~cdtm_graph.codes.Code` members: ``map_mismatch``, ``few_features``,
            ``no_fix``, ``clutter``...; :class:`~cdtm_graph.smoother.frame_flags.
            FrameFlags`): the run's verdict flags the frame again from its whole window.
    """

    frame: int
    t_ns: int
    world_T_body: np.ndarray
    velocity_mps: np.ndarray
    pose_covariance: np.ndarray
    n_features: int
    update_time_s: float
    imu_time_s: float = 0.0
    converged: bool = True
    map_sigma_h_m: float = float("nan")
    flags: tuple[str, ...] = ()


class IncrementalSmoother:
    """Feed one frame at a time; get the current estimate and the newest covariance.

    Example::

        smoother = IncrementalSmoother(flight.config, dtm)
        smoother.add_imu(imu_samples)                  # as they arrive
        update = smoother.add_frame(t_ns, track_ids, uv_px, closing_imu_samples)

    Args:
        config: the log's flight.yaml (camera, IMU noise, initial state). dtm: the terrain.
        settings: the run's settings; the incremental smoother uses ``graph``, ``lag_s``
            (a fixed lag instead of the full history), ``keep_exit_covariances``,
            ``innovation_gate``, ``acquisition`` and ``final_iterations``.
        imu: IMU samples known up front (a log); otherwise feed them with ``add_imu``.
        frame_interval_s: expected time between frames; with a lag, it lets the smoother
            relinearize less often than every update (still four times per window).

    It is the :class:`~cdtm_graph.robust.stages.SolverView` its stages ask.
    """

    #: finalize(): a settled error within this relative spread of the lowest one is converged.
    CONVERGED_SPREAD = 1e-4
    #: finalize(): rounds of "judge every track, take out the ones off the map, relinearize".
    MISMATCH_ROUNDS = 8
    #: While the estimate moves to an acquired fix, the first window frame is held there by
    #: a temporary prior this tight (rad, m, m/s).
    ANCHOR_SIGMAS = (np.radians(0.2), 2.0, 0.2)

    def __init__(self, config: FlightConfig, dtm: Dtm, settings: SmootherSettings | None = None,
                 imu: ImuArrays | None = None, frame_interval_s: float | None = None):
        self.config, self.dtm = config, dtm
        self.settings = settings = settings or SmootherSettings()
        graph = settings.graph
        noise = feature_noise(config, dtm, graph)
        self._imu = ImuFeed(config, graph.imu_hold, imu, graph.earth_physics, graph.imu_gap_noise)
        self.rejections = Rejections()  # features left out, by reason and frame
        camera = config.camera
        self._pairing = SightingPairs(camera.camera, camera.body_T_cam, dtm,
                                      camera.pixel_sigma_px, graph.epipolar, self.rejections)
        self._gate = InnovationGate(settings.innovation_gate, max(abs(dtm.dx), abs(dtm.dy)),
                                    self.rejections)
        # terrain the DTM lacks, clutter, wrong matches: tracks judged and left out
        self._judge = (None if graph.mismatch is None else TrackJudge(  # (a full history's
            graph.mismatch, graph.clutter, dtm, noise, camera.body_T_cam, self.rejections,
            TieredObservations() if settings.lag_s is None else None))  # record: tiered)
        # fix acquisition: while the pose is too uncertain for the C-DTM linearization,
        # sightings are held back until a search over the newest frames finds the fix
        self._search = (None if settings.acquisition is None else
                        FixSearch(settings.acquisition, config, dtm, self.rejections))
        self._frame_interval_s, search = frame_interval_s, self._search
        self._window = w = SolverWindow(settings.lag_s, frame_interval_s,
                                        settings.keep_exit_covariances)
        self._build = BuildFactors(camera.body_T_cam, dtm, noise, graph, self.rejections)
        hold = None if search is None else HoldForFix(
            search, lambda k: w.needs_fix(search, k),
            lambda: w.holds_search(search, self._frame_interval_s))
        self.stages = incremental_stages(self._pairing, self._build, hold, self._gate,
                                         settings.innovation_gate, self._judge)
        watch = (BroadMapWatch(graph.broad_map_error, graph.mismatch)  # a fixed lag's map
                 if settings.lag_s is not None and graph.broad_map_error is not None  # shape
                 and graph.map_error is not None else None)  # as it goes (batch's: both)
        self._map = _map_growth(graph, noise.sigma_h_m, dtm, self._build, self._judge, w)
        self._rounds = None if self._judge is None else TrackRounds(
            self._judge, watch, w, self.stages, self.forget_tracks, self._map)
        if frame_interval_s is not None:
            check_lag(settings.lag_s, frame_interval_s)
        if frame_interval_s is not None and search is not None \
                and search.needed_at_start() and not w.holds_search(search, frame_interval_s):
            raise _lag_too_short(settings, frame_interval_s)
        self._flags = FrameFlags(clutter=graph.clutter if self._judge is not None else None)
        self._map_offset = MapOffset.of(config.dtm)  # in what it reports, not what it uses
        self._principal_point = LiveShare(config.camera, dtm)  # likewise, a declared one's
        self._pair_prior_of: Callable[[], Callable[[int], np.ndarray]] | None = None
        # Warm-up: from a loose prior (or an acquired fix) every update moves its frame far
        # from the prediction, until one does not; nothing is judged meanwhile. Not a test
        # per update: outliers that moved one would switch off the tests that stop them.
        self.converging = True
        self._settling = Settling(w, settings.final_iterations)  # the live covariance honest
        self.n_features = self.n_cdtm_factors = 0
        self.update_times_s: list[float] = []
        self.imu_times_s: list[float] = []
        self.final_error, self.converged = float("nan"), False

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
            FlightLogError: inconsistent input (time order, shapes, repeated ids, ids that
                are not integers, pixels that are not finite); nothing changes.
                SolverError: the IMU does not cover the interval yet (feed the
                missing samples and retry the frame) or the system is unsolvable.
        """
        start = time.perf_counter()
        w, k = self._window, len(self._window.t_ns)
        if k and t_ns <= w.t_ns[-1]:
            raise FlightLogError(f"frame {k}: time {t_ns} ns is not after the previous frame")
        seen = _sightings(k, track_id, uv_px)  # before anything changes
        if imu is not None:
            self._imu.hold(imu)
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        pim = None  # the IMU's preintegration from the previous frame
        if k == 0:
            init = self.config.initial_state
            graph.push_back(prior_factors(init, 0))
            predicted, bias = init.world_T_body, initial_bias(init)
            velocity = np.asarray(init.velocity_mps, float)
        else:
            bias = w.biases[k - 1]  # the IMU feed's linearization point too
            pim = self._imu.finish(int(t_ns), (w.poses[k - 1], w.velocities[k - 1]))
            if pim.spans_gap:  # predicted across an IMU gap: a guess, judge nothing by it
                self.converging = self._settling.active = True
            link = imu_factor(k - 1, pim)
            graph.add(link)
            predicted, velocity = navstate_predict(pim, w.poses[k - 1], w.velocities[k - 1],
                                                   bias)
        insert_state(values, k, predicted, velocity, bias)
        if k:
            self._settling.carry(k, link, values)
        w.t_ns.append(int(t_ns))
        w.poses[k], w.velocities[k], w.biases[k] = predicted, velocity, bias
        if k:
            w.leave_window(k, self.converging, self.settings.final_iterations)
        self._pair_prior_of = (None if pim is None else
                               lambda: w.pair_prior(k, link, values))
        work = self.stages.run(FrameWork(k, *(seen or (None, None))), self)
        self._pair_prior_of = None  # (this frame's: no later stage run may use it)
        self._flags.add(k, work.flags)
        new = work.factors
        for f in new:
            graph.add(f.factor)
        slots = w.update(graph, values, k)
        self._commit(k, new, work.track_ids, slots[len(slots) - len(new):] if slots else [])
        if self._judge is not None and self._judge.due(k):
            self._mismatch_round(k, self._judge.window_start(k))
        if new:
            w.refresh_newest_noise(k, predicted, len(new))
            # (a frame without factors cannot move: it says nothing of convergence)
            self.converging = self.converging and w.moved_far(k, predicted)
        if pim is not None and pim.spans_gap:  # predicted across an IMU gap: a poor
            w.iterate(self.settings.final_iterations)  # linearization point, iterate
            w.fetch(k)
        w.state_cov = w.backend.joint_marginal(list(frame_keys(k)))
        if self._search is not None and self._search.active:
            with self.stages.charged(HoldForFix.name, HoldForFix.rejects):
                self._try_acquisition(k)
        converged, reported = self._settling.reported(k, self.n_cdtm_factors > 0)
        flags = self._flags.newest(w.t_ns, self.rejections, pim, self._judge, work.track_ids)
        self._imu.start(int(t_ns), w.biases[k])
        pose_cov = self._principal_point.added_to_pose(
            self._map_offset.added_to_pose(reported[:6, :6], w.poses[k]), w.poses[k])
        elapsed = time.perf_counter() - start
        self.update_times_s.append(elapsed)
        self.imu_times_s.append(self._imu.take_time_s())
        return FrameUpdate(k, int(t_ns), w.poses[k], w.velocities[k], pose_cov, work.n_features,
                           elapsed, self.imu_times_s[-1], converged, self._build.noise.sigma_h_m,
                           flags)

    # -- what the stages ask (robust.stages.SolverView) --------------------------------

    @property
    def settled(self) -> int:
        return self._window.settled

    @property
    def lagged(self) -> bool:
        return self.settings.lag_s is not None

    @property
    def poses(self) -> dict[int, np.ndarray]:
        return self._window.poses

    def pose_guess(self, j: int) -> np.ndarray:
        return self._window.pose_guess(j)

    def pair_prior(self) -> Callable[[int], np.ndarray] | None:
        return None if self._pair_prior_of is None else self._pair_prior_of()

    def position_sigma_m(self) -> float:
        return self._window.position_sigma_m()

    def forget_tracks(self, track_ids: np.ndarray, reason: Rejection) -> None:
        """Keep these tracks out from now on, and take their features that entered
        earlier out of the solver (those still in it), counted for ``reason``."""
        assert self._judge is not None
        self._judge.leave_out(track_ids)
        first = self._judge.first_recorded(track_ids)
        self._window.take_out(track_ids, reason, self.rejections, first)

    # -- the solver side of the defences ---------------------------------------------------

    def _try_acquisition(self, k: int) -> None:
        """Search the held frames for the fix if a search is due (:class:`FixSearch`); on
        success, move the estimate there and let the held sightings in."""
        assert self._search is not None
        w = self._window
        # Held frames the lag let go cannot be moved to a fix: their sightings are lost
        # (no_fix). Only when the lag is shorter than the search's window (a live smoother
        # not told its frame interval, or frames that came slower than expected).
        self._search.forget_before(w.settled)
        correction = self._search.search(
            k, w.t_ns.__getitem__, w.pose_guess,
            lambda j: w.search_prior(j, self.config.gravity_mps2))
        if correction is None:
            return
        self._apply_fix(correction, self._search.held, k)
        for j, _, _ in self._search.found():  # their sightings are in now
            self._flags.clear(j, Code.NO_FIX)

    def _apply_fix(self, correction: Correction,
                   held: list[tuple[int, np.ndarray, np.ndarray]], k: int) -> None:
        """Move the estimate to the acquired fix (:meth:`SolverWindow.anchor`), then add
        the held sightings, their factors built at the corrected poses (the stages up to
        the factors: the fix is what they were held for), and release the anchor."""
        w = self._window
        self._settling.restart()  # from frame k's covariance without the fix
        j0 = held[0][0]
        pose, velocity = correction.apply_to_state(w.poses[j0], w.velocities[j0])
        anchor = w.anchor(j0, pose, velocity, k, self.ANCHOR_SIGMAS,
                          2 * self.settings.final_iterations)
        graph = gtsam.NonlinearFactorGraph()
        committed = []
        for j, ids, uv in held:
            work = self.stages.run(FrameWork(j, ids, uv), self, start=PairSightings.name,
                                   stop=BUILD)
            for f in work.factors:
                graph.add(f.factor)
            committed.append((j, work.factors, work.track_ids))
        new_slots = w.backend.update(graph, gtsam.Values(), {})
        at = 0
        for j, factors, track_ids in committed:
            self._commit(j, factors, track_ids, new_slots[at:at + len(factors)])
            at += len(factors)
        w.release(anchor, k, self.settings.final_iterations)
        self.converging = True  # judge nothing until the estimate has settled

    def _mismatch_round(self, k: int, since_frame: int) -> int:
        """A round over the tracks seen since ``since_frame`` (:class:`TrackRounds`): how
        many it left out, one more if the map grew."""
        return 0 if self._rounds is None else self._rounds.run(k, since_frame)

    def _commit(self, k: int, factors: list[CdtmPairFactor], track_ids: list[np.ndarray],
                slots: list[int]) -> None:
        self._window.commit(k, factors, track_ids, slots)
        if self._judge is not None:
            self._judge.record(k, factors, track_ids)
        n_features = sum(f.features.n for f in factors)
        self.n_features += n_features
        self.n_cdtm_factors += len(factors)
        self._flags.features[k] = n_features

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
        w = self._window
        steps = self.settings.final_iterations if iterations is None else iterations
        previous, done, best = w.iterate(steps, relative_tol)
        if w.t_ns and self._judge is not None:
            # the tracks in the solver, judged at the converged estimate, until none is off
            k = len(w.t_ns) - 1
            for _ in range(self.MISMATCH_ROUNDS):
                if not self._mismatch_round(k, w.settled):
                    break
                previous, done, best = w.iterate(steps, relative_tol)
        w.refresh(w.backend.estimate())
        if w.t_ns:  # more frames may follow: the next interval at the new bias estimate
            k = len(w.t_ns) - 1
            self._imu.start(w.t_ns[k], w.biases[k])
            self._imu.advance()
        self.final_error = previous
        self.converged = done and previous <= best * (1.0 + self.CONVERGED_SPREAD)
        return self.converged

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
    def map_grown(self) -> tuple[tuple[int, float], ...]:
        """(frame, sigma_h from there) where the map's error grew (:class:`MapGrowth`)."""
        return () if self._map is None else tuple(self._map.grown)

    @property
    def mismatched_tracks(self) -> np.ndarray:
        """Tracks left out as off the map or holding a wrong match (sorted)."""
        return np.zeros(0, np.int64) if self._judge is None else self._judge.left_out

    @property
    def unfixed_frames(self) -> np.ndarray:
        """Frames whose sightings were held back for a fix that was not found (sorted)."""
        return self._flags.frames_with(Code.NO_FIX)

    def values(self) -> gtsam.Values:
        """Latest estimate of every frame so far (frames out of a lag window keep the
        estimate they had when they left it)."""
        return self._window.values()

    def estimate(self) -> TrajectoryEstimate:
        """Latest estimate of every frame so far."""
        return self._window.estimate()

    def covariances(self) -> StateCovariances:
        """Marginals of every frame (full-history iSAM2), or of the frames still in the
        window (fixed lag; older frames keep the covariances they left the window with
        if ``keep_exit_covariances``, else NaN)."""
        return self._window.covariances()

    def feed(self, flight: FlightLog, progress: Progress | None = None) -> None:
        """Feed a log frame by frame as it would arrive live (:func:`~cdtm_graph.replay.replay`;
        the IMU through :meth:`add_imu` unless given up front) and finalize: no result."""
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
            with self.stages.charged(HoldForFix.name, HoldForFix.rejects):
                self._search.give_up()

    def run(self, flight: FlightLog, progress: Progress | None = None) -> SmootherResult:
        """:meth:`feed` a log; the result like :func:`~cdtm_graph.smoother.smooth`'s."""
        start = time.perf_counter()
        K = len(flight.frames)
        self.feed(flight, progress)
        elapsed = time.perf_counter() - start
        t0 = time.perf_counter()
        covariances = self.covariances()
        estimate = self.estimate()
        counts = GraphCounts(
            K, self._pairing.table.n_tracks, self._pairing.n_observations,
            self._pairing.n_pairs, self.n_features, self.n_cdtm_factors, K - 1,
            np.array([self._flags.features.get(k, 0) for k in range(K)]),
            rejected_per_frame=self.rejections.per_frame(K))
        nis = self.innovation_nis
        stats = SolverStats(
            Solver.ISAM2 if self.settings.lag_s is None else Solver.FIXED_LAG, K,
            float("nan"), self.final_error, self.converged, elapsed,
            time.perf_counter() - t0, tuple(self.update_times_s), tuple(self.imu_times_s),
            float(np.median(nis)) if nis.size else float("nan"),
            float(np.mean(nis)) if nis.size else float("nan"))
        settings = {**self.settings.to_dict(), "acquisitions": self.acquisitions}
        clutter_settings = self.settings.graph.clutter
        clutter = None if self._judge is None or clutter_settings is None else ClutterOutcome(
            self._judge.clutter, self._judge.considered(K), clutter_settings)
        return assemble_result(self.config, estimate, covariances, stats, counts, settings,
                               self._flags.own, self._window.live_factors(), clutter,
                               stages=self.stages.summary(), broad_map_error=None
                               if self._rounds is None or self._rounds.watch is None
                               else self._rounds.watch.result(self._window.t_ns))


def _map_growth(graph: GraphSettings, sigma_h_m: float, dtm: Dtm, build: BuildFactors,
                judge: TrackJudge | None, window: SolverWindow) -> MapGrowth | None:
    """The map's error read and grown as the flight goes, unless the settings hold it
    (``MapErrorSettings.live_every_rounds`` None: a run made again with a grown map)."""
    map_error = graph.map_error
    if map_error is None or not map_error.live_every_rounds or judge is None:
        return None
    return MapGrowth(MapErrorWatch(sigma_h_m, map_error, graph.mismatch), dtm, map_error,
                     build, judge, window)


def _sightings(k: int, track_id: np.ndarray | None, uv_px: np.ndarray | None
               ) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`~cdtm_graph.tracks.checked_sightings`, and ids that are integers (not cut to
    one: 1.5 is not track 1) and finite pixels (a lost track is left out, not given NaN),
    as tracks.csv's reader asks."""
    if track_id is not None and len(track_id):
        given = np.asarray(track_id)
        whole = (np.isfinite(given) & (given == np.round(given)) & (np.abs(given) < 2.0**63)
                 if given.dtype.kind == "f" else None)
        if whole is not None and not whole.all():
            bad = given[~whole][0]
            raise FlightLogError(f"frame {k}: track id {float(bad)!r} is not an integer; expected "
                                 "integer track ids")
    seen = checked_sightings(k, track_id, uv_px)
    if seen is not None and not np.isfinite(seen[1]).all():
        row = int(np.flatnonzero(~np.isfinite(seen[1]).all(axis=1))[0])
        raise FlightLogError(f"frame {k}: track {int(seen[0][row])} has pixel "
                             f"{seen[1][row].tolist()}; expected finite pixels (leave a lost "
                             "track out)")
    return seen


def check_lag(lag_s: float | None, frame_interval_s: float) -> None:
    """Refuse a fixed lag that cannot hold two frames: no C-DTM pair would ever be in the
    window (the run would end ``failed`` on IMU alone, naming another cause).

    Raises:
        CdtmError: ``lag_s`` under two frame intervals (None: full history, fine)."""
    if lag_s is not None and lag_s < 2 * frame_interval_s:
        raise CdtmError(
            f"a fixed lag of {lag_s:g} s holds fewer than two frames ({frame_interval_s:g} s "
            "apart; a frame leaves the window one interval before the lag): expected a lag "
            f"of at least {2 * frame_interval_s:g} s")


def _lag_too_short(settings: SmootherSettings, frame_interval_s: float) -> CdtmError:
    assert settings.acquisition is not None and settings.lag_s is not None
    frames = settings.acquisition.window_frames
    need_s = frames * frame_interval_s
    return CdtmError(
        f"a fixed lag of {settings.lag_s:g} s is shorter than the fix search's window "
        f"({frames} frames, {need_s:g} s at {1 / frame_interval_s:.3g} frames/s): expected "
        f"a lag of at least {need_s:g} s, or no fix search (SmootherSettings.acquisition="
        "None)")
