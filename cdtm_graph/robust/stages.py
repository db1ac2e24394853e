"""The per-frame stages: what a frame's sightings pass through before they enter a graph.

Both smoothers run an ordered :class:`Stages` list over each frame: the sightings (track
ids and pixels) become pairs with their tracks' earlier sightings, the pairs become C-DTM
factors, the factors lose the features that fail a test. Each stage has its settings,
names the :class:`~cdtm_graph.results.Rejection` reasons it counts (into
``counts.rejected_per_frame`` of report.json) and is timed. What the defences leave out
outside a frame's pass (the fix search's late verdicts, the track tests' rounds over many
frames) is charged to its own entry (:meth:`Stages.charged`), so that report.json's
``stages`` (:meth:`Stages.summary`) adds up to ``counts.rejected_per_frame``.

The order (:func:`incremental_stages`; the batch, :func:`batch_stages`, runs the stages
that need no running solver, with what the incremental pass learned):

1. :class:`HoldForFix` (``no_fix``): while the fix is not acquired, the sightings wait.
2. :class:`PairSightings` (``wrong_match``, ``too_old``): sightings paired with their
   tracks' last good ones, each pair checked against the epipolar geometry.
3. :class:`KeepOutTracks` (``map_mismatch``): tracks already found off the map stay out.
4. :class:`BuildFactors` (``missed_dtm``, ``grazing``): one C-DTM factor per frame pair,
   rays that miss the DTM or graze a ridge out.
5. :class:`GateInnovations` (``gated``): each feature's innovation against the prior of
   its poses scales its kernel and, once the solution settled, is gated.
6. :class:`JudgeNewTracks` (``map_mismatch``, ``wrong_match``): the frame's tracks
   triangulated against the DTM; the ones off it leave the solver.

Adding a defence: docs/design.md, "Adding a stage".
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from cdtm_graph.codes import Code
from cdtm_graph.dtm import Dtm
from cdtm_graph.graph.builders import GraphSettings, cdtm_factors
from cdtm_graph.results import Rejection, Rejections
from cdtm_graph.robust.fix_search import FixSearch
from cdtm_graph.robust.gating import InnovationGate
from cdtm_graph.robust.track_judge import TrackJudge
from cdtm_graph.tracks import FramePairObservations, SightingPairs, pairs_without
from factors import CdtmPairFactor, FeatureNoise


@dataclass
class FrameWork:
    """One frame's sightings on their way into the graph (each stage takes its part).

    Attributes:
        k: the frame. track_id, uv_px: its sightings, (m,) and (m, 2); None once held
            back or when there are none.
        pairs: the pairs the sightings close. factors: their C-DTM factors; track_ids:
            each factor's features' track ids.
        flags: the frame's flags the stages set.
    """

    k: int
    track_id: np.ndarray | None = None
    uv_px: np.ndarray | None = None
    pairs: list[FramePairObservations] = field(default_factory=list)
    factors: list[CdtmPairFactor] = field(default_factory=list)
    track_ids: list[np.ndarray] = field(default_factory=list)
    flags: list[Code] = field(default_factory=list)

    @property
    def n_features(self) -> int:
        return sum(f.features.n for f in self.factors)


class SolverView(Protocol):
    """What a stage may ask of the smoother running it (the incremental smoother; the
    batch's graph builder, which has an initial guess and no solver yet)."""

    @property
    def settled(self) -> int:
        """Frames before this one have left the solver (a fixed lag's window)."""

    @property
    def lagged(self) -> bool:
        """A fixed lag: tables of old sightings may be forgotten."""

    @property
    def converging(self) -> bool:
        """The solution still converges from a loose prior: judge nothing."""

    @property
    def poses(self) -> Mapping[int, np.ndarray] | Sequence[np.ndarray]:
        """Frame -> the (4, 4) pose guess the factors are built at."""

    def pose_guess(self, j: int) -> np.ndarray:
        """Frame j's pose as the epipolar check and the tests see it: the solver's now
        (the newest frame: its prediction); the batch's initial guess (its rotations
        chained from the IMU when the guess is a nav.csv)."""

    def pair_prior(self) -> Callable[[int], np.ndarray] | None:
        """Earlier frame a -> the (12, 12) prior covariance of ``(X(a), X(k))`` before
        this frame's factors; None without one (the first frame, the batch)."""

    def position_sigma_m(self) -> float:
        """The newest estimated frame's largest position 1-sigma (m)."""

    def forget_tracks(self, track_ids: np.ndarray, reason: Rejection) -> None:
        """Keep these tracks out from now on, their earlier features out of the solver."""


class Stage(Protocol):
    """One defence over a frame's sightings."""

    name: str
    rejects: tuple[Rejection, ...]
    settings: Any

    def run(self, work: FrameWork, solver: SolverView) -> None:
        """Take this stage's part of ``work`` (in place), counting what it leaves out."""


class Stages:
    """An ordered list of stages, each timed (seconds over the run) and its features left
    out counted (by reason, in the run's ``rejections``)."""

    def __init__(self, stages: Sequence[Stage], rejections: Rejections):
        self.stages = tuple(stages)
        self.rejections = rejections
        self.names = frozenset(s.name for s in self.stages)
        self.time_s = dict.fromkeys((s.name for s in self.stages), 0.0)
        self.rejected: dict[str, dict[Rejection, int]] = {
            s.name: dict.fromkeys(s.rejects, 0) for s in self.stages}

    def run(self, work: FrameWork, solver: SolverView, start: str | None = None,
            stop: str | None = None) -> FrameWork:
        """Every stage in order over ``work`` (from the one named ``start``, through the
        one named ``stop``)."""
        if not {start, stop} - {None} <= self.names:
            raise ValueError(f"stages {start!r}..{stop!r}: expected names of "
                             f"{[s.name for s in self.stages]}")
        total = self.rejections.total
        started = start is None
        for stage in self.stages:  # (a frame's hot path: no context manager per stage)
            started = started or stage.name == start
            if not started:
                continue
            before = [total(r) for r in stage.rejects]
            t0 = time.perf_counter()
            stage.run(work, solver)
            self.time_s[stage.name] += time.perf_counter() - t0
            counts = self.rejected[stage.name]
            for r, n in zip(stage.rejects, before):
                counts[r] += total(r) - n
            if stage.name == stop:
                break
        return work

    @contextlib.contextmanager
    def charged(self, name: str, rejects: tuple[Rejection, ...]) -> Iterator[None]:
        """Charge what is left out (for ``rejects``) and the time spent inside the block to
        the entry ``name``: a stage, or a defence's work outside a frame's pass (the track
        tests' rounds, the fix search's verdict on held frames)."""
        before = [self.rejections.total(r) for r in rejects]
        t0 = time.perf_counter()
        try:
            yield
        finally:
            counts = self.rejected.setdefault(name, {})
            for r, n in zip(rejects, before):
                counts[r] = counts.get(r, 0) + self.rejections.total(r) - n
            self.time_s[name] = self.time_s.get(name, 0.0) + time.perf_counter() - t0

    def summary(self) -> list[dict]:
        """Each entry (the stages in order, then the work charged apart): its name, the
        features it left out by reason, its time (report.json's ``stages``)."""
        return [{"name": name, "rejected": {r.value: n for r, n in counts.items()},
                 "time_s": self.time_s[name]} for name, counts in self.rejected.items()]


class HoldForFix:
    """While the fix is not acquired, the frame's sightings wait (``no_fix``) for a search
    over the newest frames (:class:`~cdtm_graph.robust.fix_search.FixSearch`).

    Args:
        search: the held sightings and the searches over them.
        needs_fix: frame k -> whether it starts a search (the prior, or the covariance
            after a long gap, reaches farther than the smoothers pull in).
        lag_holds_search: whether the solver's window holds the frames a search needs.
    """

    name: str = "hold_for_fix"
    rejects: tuple[Rejection, ...] = (Rejection.NO_FIX,)

    def __init__(self, search: FixSearch, needs_fix: Callable[[int], bool],
                 lag_holds_search: Callable[[], bool]):
        self.search = search
        self.settings = search.settings
        self.needs_fix, self.lag_holds_search = needs_fix, lag_holds_search

    def run(self, work: FrameWork, solver: SolverView) -> None:
        k = work.k
        if not (self.search.active or self.needs_fix(k)):
            return
        if not self.search.active and k and not self.lag_holds_search():
            # the covariance outgrew what the smoothers pull in (a long gap), but the
            # lag cannot hold the frames a search needs: on unsearched, and said so
            work.flags.append(Code.SEARCH_BEYOND_LAG)
            return
        seen = None
        if work.track_id is not None and work.uv_px is not None:
            seen = (work.track_id, work.uv_px)
        self.search.hold(k, seen)
        work.track_id = work.uv_px = None  # held back: no C-DTM factor until the fix
        work.flags.append(Code.NO_FIX)


class HoldUnfixed:
    """The batch's: frames whose sightings waited for a fix the incremental pass never
    found stay out (``no_fix``): their linearization would be a guess."""

    name: str = "hold_for_fix"
    rejects: tuple[Rejection, ...] = (Rejection.NO_FIX,)
    settings = None

    def __init__(self, unfixed_frames: np.ndarray | None, rejections: Rejections):
        self.unfixed = set() if unfixed_frames is None else set(unfixed_frames.tolist())
        self.rejections = rejections

    def run(self, work: FrameWork, solver: SolverView) -> None:
        if work.k in self.unfixed and work.track_id is not None:
            self.rejections.add(Rejection.NO_FIX, work.k, len(work.track_id))
            work.track_id = work.uv_px = None


class PairSightings:
    """Sightings paired with their tracks' last good ones; each pair checked against the
    epipolar geometry of the current relative pose (wrong matches out, the track pairs
    across them: :class:`~cdtm_graph.tracks.SightingPairs`). With a fixed lag, pairs with
    a frame that left the window are dropped (``too_old``) and old sightings forgotten."""

    name: str = "pair_sightings"
    rejects: tuple[Rejection, ...] = (Rejection.WRONG_MATCH, Rejection.TOO_OLD)

    def __init__(self, pairing: SightingPairs,
                 on_forget: Sequence[Callable[[int], None]] = ()):
        self.pairing = pairing
        self.settings = pairing.settings
        self.on_forget = tuple(on_forget)  # others that keep sightings by frame

    def run(self, work: FrameWork, solver: SolverView) -> None:
        if work.track_id is None or work.uv_px is None or not len(work.track_id):
            return
        work.pairs = self.pairing.add_frame(work.k, work.track_id, work.uv_px,
                                            solver.pose_guess, solver.settled)
        table = self.pairing.table
        if solver.lagged and len(table) > 4 * len(work.track_id):
            table.forget_before(solver.settled)
            for forget in self.on_forget:
                forget(solver.settled)


class KeepOutTracks:
    """Tracks already found off the map (by the track tests, or the batch's incremental
    pass) stay out of new pairs (``map_mismatch``)."""

    name: str = "keep_out_tracks"
    rejects: tuple[Rejection, ...] = (Rejection.MAP_MISMATCH,)
    settings = None

    def __init__(self, left_out: Callable[[], np.ndarray], rejections: Rejections):
        self.left_out = left_out
        self.rejections = rejections

    def run(self, work: FrameWork, solver: SolverView) -> None:
        if work.pairs:
            work.pairs = pairs_without(work.pairs, self.left_out(), work.k,
                                       Rejection.MAP_MISMATCH, self.rejections)


class BuildFactors:
    """One C-DTM factor per frame pair at the current pose guesses; rays that miss the DTM
    (``missed_dtm``) or graze a ridge (``grazing``) out (:func:`~cdtm_graph.graph.
    builders.cdtm_factors`)."""

    name: str = "build_factors"
    rejects: tuple[Rejection, ...] = (Rejection.MISSED_DTM, Rejection.GRAZING)

    def __init__(self, body_T_cam: np.ndarray, dtm: Dtm, noise: FeatureNoise,
                 settings: GraphSettings, rejections: Rejections,
                 calibration: tuple[int, np.ndarray] | None = None):
        self.body_T_cam, self.dtm, self.noise = body_T_cam, dtm, noise
        self.graph_settings, self.rejections, self.calibration = settings, rejections, calibration
        self.settings = {"grazing_turn_cells": settings.grazing_turn_cells}

    def run(self, work: FrameWork, solver: SolverView) -> None:
        if not work.pairs:
            return
        build = cdtm_factors(work.pairs, solver.poses, self.body_T_cam, self.dtm, self.noise,
                             self.graph_settings, self.rejections, self.calibration)
        work.factors, work.track_ids = build.factors, build.track_ids


class GateInnovations:
    """Each feature's innovation against the IMU's prediction (the prior of its two
    poses): the robust kernel's scale, and, once the solution no longer converges from a
    loose prior, the chi-square(2) gate (``gated``;
    :class:`~cdtm_graph.robust.gating.InnovationGate`)."""

    name: str = "gate_innovations"
    rejects: tuple[Rejection, ...] = (Rejection.GATED,)

    def __init__(self, gate: InnovationGate, probability: float | None):
        self.gate = gate
        self.settings = {"innovation_gate": probability}

    def run(self, work: FrameWork, solver: SolverView) -> None:
        if not work.factors:
            return
        prior = solver.pair_prior()
        if prior is None:
            return
        work.factors, work.track_ids = self.gate.apply(
            work.k, work.factors, work.track_ids, solver.pose_guess, prior,
            test=not solver.converging)


class JudgeNewTracks:
    """The frame's tracks triangulated, with everything seen of them, against the DTM:
    the ones off the map (``map_mismatch``) or holding a wrong match (``wrong_match``) lose
    this frame's features and leave the solver (:class:`~cdtm_graph.robust.track_judge.
    TrackJudge`; its periodic rounds are the smoother's)."""

    name: str = "judge_new_tracks"
    rejects: tuple[Rejection, ...] = (Rejection.MAP_MISMATCH, Rejection.WRONG_MATCH)

    def __init__(self, judge: TrackJudge):
        self.judge = judge
        self.settings = judge.mismatch

    def run(self, work: FrameWork, solver: SolverView) -> None:
        if not work.factors or solver.converging:
            return
        sigma_m = solver.position_sigma_m()
        if not self.judge.settle(work.k, sigma_m):
            return
        work.factors, work.track_ids, off_map, wrong = self.judge.judge_new(
            work.k, work.factors, work.track_ids, solver.pose_guess, sigma_m)
        if off_map.size:
            solver.forget_tracks(off_map, Rejection.MAP_MISMATCH)
        if wrong.size:
            solver.forget_tracks(wrong, Rejection.WRONG_MATCH)


#: The stage that ends the part of the list a frame whose sightings were held runs when
#: the fix is found (its factors are built at the corrected poses; no gate, no judging).
BUILD = BuildFactors.name


def incremental_stages(pairing: SightingPairs, build: BuildFactors,
                       hold: HoldForFix | None, gate: InnovationGate, gate_probability:
                       float | None, judge: TrackJudge | None) -> Stages:
    """The incremental smoothers' list (the defences switched off in the settings are
    left out)."""
    stages: list[Stage] = []
    if hold is not None:
        stages.append(hold)
    forget = () if judge is None else (judge.observations.forget_before,)
    stages.append(PairSightings(pairing, forget))
    if judge is not None:
        stages.append(KeepOutTracks(lambda: judge.left_out, judge.rejections))
    stages += [build, GateInnovations(gate, gate_probability)]
    if judge is not None:
        stages.append(JudgeNewTracks(judge))
    return Stages(stages, build.rejections)


def batch_stages(pairing: SightingPairs, build: BuildFactors, unfixed_frames: np.ndarray |
                 None, off_map: np.ndarray | None, rejections: Rejections) -> Stages:
    """The batch's list: the stages that need no running solver, with the frames and
    tracks the incremental pass (its robust start) found without a fix or off the map."""
    left_out = np.zeros(0, np.int64) if off_map is None else off_map
    return Stages([HoldUnfixed(unfixed_frames, rejections), PairSightings(pairing),
                   KeepOutTracks(lambda: left_out, rejections), build], rejections)
