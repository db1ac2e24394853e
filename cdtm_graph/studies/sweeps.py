"""Sensitivity studies of the paper's section VI (Figs. 2-9): one parameter swept at a time.

For each value of the swept parameter (all others nominal, :class:`PairScenario`),
``trials`` random frame pairs are drawn (:func:`sample_pair`) and solved
(:func:`solve_two_frame`). Per trial we keep

* the **predicted** covariance: the weighted closed form (eq. 13 with ``W =
  blockdiag(Sigma_f^+)``, the covariance of the estimator GTSAM solves; equal to GTSAM's
  marginal), linearized at the estimate, mapped to the camera-2 pose (eqs. 27-31,
  ``Sigma_C2``) and read off for the ego-motion (the ``p12`` and ``alpha12`` blocks of
  ``Sigma_theta``);
* the **achieved** error of the estimate against the truth, in the same parameters
  (camera-2 centre and Euler angles eqs. 29-31, ``p12``, ``alpha12``).

A value's row reports RMS predictions ``sqrt(mean(trace of the 3x3 block))`` and RMS error
norms ``sqrt(mean |error|^2)`` over the trials that did not fail, in metres and degrees:
for a consistent estimator the two agree.

A trial **fails** (and is counted, not averaged) when the solver flags the geometry as
degenerate (section V.B), when it does not converge, or when its error is wildly beyond its
own covariance: NEES over the twelve parameters above :data:`NEES_FAILURE_THRESHOLD`,
which a consistent estimate exceeds once in a million trials. The last is counted as a
failure to converge (a wrong local minimum); section V warns of both.

Randomness: trial ``t`` of value ``v`` draws from ``SeedSequence(seed, (TRIAL_STREAM, v,
t))`` and its terrain from ``SeedSequence(seed, (TERRAIN_STREAM, t // trials_per_terrain))``,
never from the worker that runs it, so the same seed gives the same numbers on one core,
many, or a Dask cluster. Terrains are shared across values (the relief sweep scales the
same landscapes, the grid sweep resamples them, as the paper's Figs. 4 and 7 do) and
cached per process.

This module does no file I/O; the ``cdtm study`` command writes CSVs and figures.
"""

from __future__ import annotations

import enum
import functools
import logging
import math
from dataclasses import dataclass, field, replace

import numpy as np

from cdtm_graph.analysis.closed_form import euler_from_rotation, theta_from_cameras
from cdtm_graph.analysis.two_frame import TwoFrameSettings, solve_two_frame
from cdtm_graph.errors import CdtmError, DegenerateGeometryError, SolverError
from cdtm_graph.parallel import ParallelSettings, map_tasks
from cdtm_graph.sim.scenario import (
    PairScenario,
    ScenarioTerrain,
    dtm_ray_caster,
    make_terrain,
    sample_pair,
)
from cdtm_graph.studies.settings import StudyParameter

log = logging.getLogger(__name__)

#: Chi-square quantile of 12 degrees of freedom at probability 1 - 1e-6
#: (``scipy.stats.chi2.ppf(1 - 1e-6, 12)``, checked by the tests). A consistent estimate's
#: NEES exceeds it once in a million trials; beyond it the solve found a wrong minimum.
#: (The 99.9 % quantile is 32.9: this bound is "far outside" it, so that at most a few in
#: ten thousand good trials of a slightly non-Gaussian case are lost from the averages.)
NEES_FAILURE_THRESHOLD = 50.825

#: Spawn-key streams of the study's random numbers (trial draws vs terrains).
TRIAL_STREAM = 0
TERRAIN_STREAM = 1

#: Terrains kept per worker process (a sweep touches a few per value).
_TERRAIN_CACHE_SIZE = 16

#: The :class:`PairScenario` fields :func:`make_terrain` reads: the terrain cache key.
_TERRAIN_FIELDS = ("terrain_size_m", "relief_m", "correlation_length_m", "fine_spacing_m",
                   "grid_spacing_m", "sigma_h_m")

#: Columns of a study table, in order (the CSV header).
STUDY_COLUMNS = ("value", "trials", "failures",
                 "pred_sigma_pos2_m", "rms_err_pos2_m",
                 "pred_sigma_att2_deg", "rms_err_att2_deg",
                 "pred_sigma_t12_m", "rms_err_t12_m",
                 "pred_sigma_r12_deg", "rms_err_r12_deg")

#: The four reported quantities, in the order of :attr:`TrialOutcomes.pred_var`.
QUANTITIES = ("pos2", "att2", "t12", "r12")
_ANGULAR = np.array([False, True, False, True])  # reported in degrees


@dataclass(frozen=True)
class Sweep:
    """What a study sweeps and how the paper reports it.

    Attributes:
        scenario_field: the :class:`PairScenario` attribute set to each value.
        label: axis label, with units.
        default_values: values swept when none are given (the paper's range).
        integer: the values are counts (features, pixels).
        min_value, max_value: open/closed bounds of a meaningful value (see ``validate``).
        paper_figure: where the paper reports it.
        paper_trend: what the paper reports.
    """

    scenario_field: str
    label: str
    default_values: tuple[float, ...]
    integer: bool
    min_value: float
    max_value: float
    paper_figure: str
    paper_trend: str

    def validate(self, value: float) -> float | int:
        """The value as the scenario takes it; CdtmError if it makes no sense."""
        value_f = float(value)
        if not math.isfinite(value_f) or not self.min_value <= value_f <= self.max_value:
            raise CdtmError(f"{self.scenario_field} = {value!r} is out of range, expected "
                            f"{self.min_value:g} <= value <= {self.max_value:g}")
        if self.integer:
            if value_f != round(value_f):
                raise CdtmError(f"{self.scenario_field} = {value!r}, expected an integer")
            return int(round(value_f))
        return value_f


SWEEPS: dict[StudyParameter, Sweep] = {
    StudyParameter.FEATURES: Sweep(
        "n_features", "number of features", (10, 20, 40, 70, 100, 150, 200, 300), True,
        1, 5000, "Fig. 2", "accuracy improves with the number of features and saturates "
        "at about 150"),
    StudyParameter.RESOLUTION: Sweep(
        "resolution_px", "image resolution [px] (0.5 px registration error)",
        (100, 200, 400, 800, 1200, 1600), True, 10, 20000, "Fig. 3",
        "accuracy improves with image resolution"),
    StudyParameter.GRID: Sweep(
        "grid_spacing_m", "DTM grid spacing [m]", (10, 30, 50, 70, 100, 130, 160, 190), False,
        1e-3, 1000, "Figs. 4-6", "accuracy degrades about linearly with grid spacing "
        "(sigma_h grows linearly with it, Fig. 6)"),
    StudyParameter.RELIEF: Sweep(
        "relief_m", "terrain relief (max - min) [m]",
        (50, 100, 150, 200, 250, 300, 350, 400, 450), False, 0, 5000, "Figs. 7-8",
        "camera pose and translation improve with relief; the ego-motion rotation hardly "
        "depends on it"),
    StudyParameter.BASELINE: Sweep(
        "baseline_m", "baseline |p12| [m]", (5, 10, 20, 30, 40, 50, 70, 95), False, 0,
        1000, "Fig. 9", "accuracy improves with the baseline (critical, as in all "
        "structure-from-motion)"),
    StudyParameter.FOV: Sweep(
        "fov_deg", "field of view [deg]", (2, 4, 6, 8, 10, 15, 20, 30, 45, 60, 90), False,
        0.1, 150, "section V.B", "the estimate breaks down (degenerate) below a FOV of "
        "about 8 degrees"),
}


@dataclass(frozen=True)
class StudySettings:
    """One sensitivity study.

    Attributes:
        parameter: what is swept.
        values: the swept values; ``None`` uses the parameter's defaults.
        trials: random trials per value (the paper uses 150).
        seed: master seed of every random draw (terrains and trials).
        base: the scenario the other parameters come from (nominal by default).
        trials_per_terrain: consecutive trials sharing one random terrain; with 150 trials
            and 50 per terrain, each value averages over three landscapes. It defines the
            experiment (changing it changes the numbers), not the parallel split.
        two_frame: solver settings (``raise_on_degenerate`` is forced off: degenerate
            trials are counted, not raised).
        nees_failure_threshold: NEES (12 dof) beyond which a trial counts as failed.
    """

    parameter: StudyParameter
    values: tuple[float, ...] | None = None
    trials: int = 150
    seed: int = 0
    base: PairScenario = field(default_factory=PairScenario)
    trials_per_terrain: int = 50
    two_frame: TwoFrameSettings = field(
        default_factory=lambda: TwoFrameSettings(raise_on_degenerate=False))
    nees_failure_threshold: float = NEES_FAILURE_THRESHOLD

    def resolved_values(self) -> tuple[float | int, ...]:
        """The swept values, validated and typed as the scenario takes them."""
        sweep = SWEEPS[self.parameter]
        raw = sweep.default_values if self.values is None else tuple(self.values)
        if not raw:
            raise CdtmError(f"study {self.parameter.value}: no values to sweep")
        return tuple(sweep.validate(v) for v in raw)

    def scenario(self, value: float | int) -> PairScenario:
        """The base scenario with the swept parameter set to ``value``."""
        return self.base.with_(**{SWEEPS[self.parameter].scenario_field: value})

    def check(self) -> None:
        """Raise CdtmError on settings that cannot run."""
        if self.trials < 1:
            raise CdtmError(f"trials = {self.trials}, expected >= 1")
        if self.trials_per_terrain < 1:
            raise CdtmError(f"trials_per_terrain = {self.trials_per_terrain}, expected >= 1")
        if self.seed < 0:
            raise CdtmError(f"seed = {self.seed}, expected >= 0")
        self.resolved_values()


class TrialStatus(enum.IntEnum):
    """Outcome of one trial; everything but OK counts as a failure."""

    OK = 0
    DEGENERATE = 1  # the degeneracy verdict (section V.B) or an indeterminate system
    NOT_CONVERGED = 2  # the solver hit its iteration limit or failed
    INCONSISTENT = 3  # NEES beyond the threshold: a wrong minimum, counted as not converged


@dataclass(frozen=True)
class TrialChunk:
    """A task: consecutive trials of one value, all on one terrain.

    Attributes:
        scenario: the scenario of this value.
        two_frame: solver settings.
        seed: the study's master seed.
        value_index: index of the value in the sweep (part of each trial's seed).
        first_trial, n_trials: the trials ``first_trial .. first_trial + n_trials - 1``.
        terrain_index: which random terrain (part of its seed).
        nees_failure_threshold: see :class:`StudySettings`.
    """

    scenario: PairScenario
    two_frame: TwoFrameSettings
    seed: int
    value_index: int
    first_trial: int
    n_trials: int
    terrain_index: int
    nees_failure_threshold: float


@dataclass(frozen=True)
class TrialOutcomes:
    """Per-trial results of a chunk or a whole value (trials in index order).

    Attributes:
        status: (n,) :class:`TrialStatus` codes.
        pred_var: (n, 4) predicted variances (traces of the 3x3 blocks) of
            :data:`QUANTITIES`, in m^2 and rad^2; NaN where the analysis has none.
        sq_err: (n, 4) squared error norms, same units; NaN where the solve failed.
        nees: (n,) NEES over the twelve theta parameters (NaN where undefined).
        n_features: (n,) features used.
        reasons: per trial, the degeneracy reasons (comma separated) or ``""``.
    """

    status: np.ndarray
    pred_var: np.ndarray
    sq_err: np.ndarray
    nees: np.ndarray
    n_features: np.ndarray
    reasons: tuple[str, ...]

    @property
    def failed(self) -> np.ndarray:
        return self.status != TrialStatus.OK

    @classmethod
    def concatenate(cls, parts: list[TrialOutcomes]) -> TrialOutcomes:
        """The trials of consecutive parts, in order."""

        def cat(name: str) -> np.ndarray:
            return np.concatenate([getattr(p, name) for p in parts])

        return cls(cat("status"), cat("pred_var"), cat("sq_err"), cat("nees"),
                   cat("n_features"), tuple(r for p in parts for r in p.reasons))


@dataclass(frozen=True)
class StudyRow:
    """One value of a study: a row of the CSV (:data:`STUDY_COLUMNS`), metres and degrees."""

    value: float
    trials: int
    failures: int
    pred_sigma_pos2_m: float
    rms_err_pos2_m: float
    pred_sigma_att2_deg: float
    rms_err_att2_deg: float
    pred_sigma_t12_m: float
    rms_err_t12_m: float
    pred_sigma_r12_deg: float
    rms_err_r12_deg: float

    def as_tuple(self) -> tuple:
        return tuple(getattr(self, c) for c in STUDY_COLUMNS)


@dataclass(frozen=True)
class StudyResult:
    """A finished study.

    Attributes:
        settings: what was run.
        values: the swept values.
        rows: one summary per value.
        outcomes: the per-trial results of each value.
    """

    settings: StudySettings
    values: tuple[float | int, ...]
    rows: tuple[StudyRow, ...]
    outcomes: tuple[TrialOutcomes, ...]

    @property
    def parameter(self) -> StudyParameter:
        return self.settings.parameter

    def column(self, name: str) -> np.ndarray:
        """(n_values,) one CSV column."""
        return np.array([getattr(r, name) for r in self.rows], dtype=float)

    def failure_counts(self) -> list[dict[TrialStatus, int]]:
        """Per value, how many trials ended in each failure status."""
        return [{s: int(np.sum(o.status == s)) for s in TrialStatus if s is not TrialStatus.OK}
                for o in self.outcomes]


# -- worker side ---------------------------------------------------------------------


def _seed_sequence(seed: int, *key: int) -> np.random.SeedSequence:
    return np.random.SeedSequence(seed, spawn_key=key)


def terrain_seed(seed: int, terrain_index: int) -> int:
    """Seed of the ``terrain_index``-th random terrain of a study."""
    return int(_seed_sequence(seed, TERRAIN_STREAM, terrain_index).generate_state(1)[0])


def trial_rng(seed: int, value_index: int, trial_index: int) -> np.random.Generator:
    """The random generator of one trial: a function of these three numbers only."""
    return np.random.default_rng(_seed_sequence(seed, TRIAL_STREAM, value_index, trial_index))


@functools.lru_cache(maxsize=_TERRAIN_CACHE_SIZE)
def _cached_terrain(terrain_key: tuple, seed: int) -> ScenarioTerrain:
    return make_terrain(PairScenario().with_(**dict(zip(_TERRAIN_FIELDS, terrain_key,
                                                        strict=True))), seed)


def study_terrain(scenario: PairScenario, seed: int) -> ScenarioTerrain:
    """:func:`make_terrain`, cached per process on the fields that define the terrain."""
    return _cached_terrain(tuple(getattr(scenario, f) for f in _TERRAIN_FIELDS), seed)


def _wrap_angle(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def _camera2_params(world_T_cam_b: np.ndarray) -> np.ndarray:
    """(6,) the camera-2 pose as Sigma_C2 orders it: centre, then Euler angles eqs. 29-31."""
    return np.concatenate([world_T_cam_b[:3, 3], euler_from_rotation(world_T_cam_b[:3, :3])])


class _DropDegenerateWarnings(logging.Filter):
    """Drops the solver's per-trial "degenerate geometry" warnings: a study counts them."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("degenerate geometry")


def run_trial_chunk(task: TrialChunk) -> TrialOutcomes:
    """Run the trials of one task (the unit of parallel work; pure given the task)."""
    solver_log = logging.getLogger(solve_two_frame.__module__)
    quiet = _DropDegenerateWarnings()
    solver_log.addFilter(quiet)
    try:
        return _run_trials(task)
    finally:
        solver_log.removeFilter(quiet)


def _run_trials(task: TrialChunk) -> TrialOutcomes:
    scenario = task.scenario
    terrain = study_terrain(scenario, terrain_seed(task.seed, task.terrain_index))
    raycast = dtm_ray_caster(terrain.dtm)
    noise = scenario.noise
    n = task.n_trials
    status = np.full(n, TrialStatus.OK, dtype=np.int8)
    pred_var = np.full((n, 4), np.nan)
    sq_err = np.full((n, 4), np.nan)
    nees = np.full(n, np.nan)
    n_features = np.zeros(n, dtype=np.int32)
    reasons = [""] * n
    for k in range(n):
        rng = trial_rng(task.seed, task.value_index, task.first_trial + k)
        s = sample_pair(scenario, terrain, rng)
        n_features[k] = s.n_features
        try:
            r = solve_two_frame(s.q_a, s.q_b, raycast, s.initial_a, s.initial_b, s.body_T_cam,
                                noise, task.two_frame)
        except DegenerateGeometryError as exc:
            status[k], reasons[k] = TrialStatus.DEGENERATE, ",".join(exc.reasons)
            continue
        except SolverError:
            status[k] = TrialStatus.NOT_CONVERGED
            continue
        a = r.analysis
        n_features[k] = r.n_features
        S, S_c2 = a.sigma_theta_weighted, a.sigma_c2_weighted
        pred_var[k] = [np.trace(S_c2[:3, :3]), np.trace(S_c2[3:, 3:]),
                       np.trace(S[6:9, 6:9]), np.trace(S[9:12, 9:12])]
        if r.degenerate:
            status[k], reasons[k] = TrialStatus.DEGENERATE, ",".join(r.degeneracy.reasons)
            continue
        if not r.converged:
            status[k] = TrialStatus.NOT_CONVERGED
            continue
        wTc_a_true = s.world_T_body_a @ s.body_T_cam
        wTc_b_true = s.world_T_body_b @ s.body_T_cam
        d_theta = a.theta - theta_from_cameras(wTc_a_true, wTc_b_true)
        d_theta[3:6], d_theta[9:12] = _wrap_angle(d_theta[3:6]), _wrap_angle(d_theta[9:12])
        d_c2 = _camera2_params(r.world_T_body_b @ s.body_T_cam) - _camera2_params(wTc_b_true)
        d_c2[3:] = _wrap_angle(d_c2[3:])
        sq_err[k] = [d_c2[:3] @ d_c2[:3], d_c2[3:] @ d_c2[3:],
                     d_theta[6:9] @ d_theta[6:9], d_theta[9:12] @ d_theta[9:12]]
        try:
            nees[k] = float(d_theta @ np.linalg.solve(S, d_theta))
        except np.linalg.LinAlgError:
            nees[k] = np.inf
        if not nees[k] <= task.nees_failure_threshold:  # NaN/inf fail too
            status[k] = TrialStatus.INCONSISTENT
    return TrialOutcomes(status, pred_var, sq_err, nees, n_features, tuple(reasons))


# -- driver side ---------------------------------------------------------------------


def study_tasks(settings: StudySettings) -> list[TrialChunk]:
    """The tasks of a study: per value, one chunk per terrain block of trials."""
    settings.check()
    tasks = []
    two_frame = settings.two_frame
    if two_frame.raise_on_degenerate:  # degenerate trials are counted, not raised
        two_frame = replace(two_frame, raise_on_degenerate=False)
    block = settings.trials_per_terrain
    for v, value in enumerate(settings.resolved_values()):
        scenario = settings.scenario(value)
        for first in range(0, settings.trials, block):
            tasks.append(TrialChunk(scenario, two_frame, settings.seed, v, first,
                                    min(block, settings.trials - first), first // block,
                                    settings.nees_failure_threshold))
    return tasks


def summarize(value: float | int, outcomes: TrialOutcomes) -> StudyRow:
    """One CSV row: RMS predictions and RMS errors over the trials that did not fail."""
    ok = ~outcomes.failed
    scale = np.where(_ANGULAR, math.degrees(1.0), 1.0)
    if ok.any():
        pred = np.sqrt(np.mean(outcomes.pred_var[ok], axis=0)) * scale
        err = np.sqrt(np.mean(outcomes.sq_err[ok], axis=0)) * scale
    else:
        pred = err = np.full(4, np.nan)
    stats = [x for pair in zip(pred, err, strict=True) for x in pair]
    return StudyRow(value, int(outcomes.status.size), int((~ok).sum()),
                    *(float(x) for x in stats))


def run_studies(studies: list[StudySettings],
                parallel: ParallelSettings | None = None) -> list[StudyResult]:
    """Run several studies as one batch of tasks (one pool, balanced across studies).

    Args:
        studies: the studies.
        parallel: where to run (default: all local cores).

    Returns:
        One result per study, in order; identical for any backend or worker count.
    """
    per_study = [study_tasks(s) for s in studies]
    flat = [t for tasks in per_study for t in tasks]
    log.info("%d studies, %d tasks, %d trials", len(studies), len(flat),
             sum(t.n_trials for t in flat))
    outcomes = iter(map_tasks(run_trial_chunk, flat, parallel))
    results = []
    for settings, tasks in zip(studies, per_study, strict=True):
        values = settings.resolved_values()
        chunks: list[list[TrialOutcomes]] = [[] for _ in values]
        for task in tasks:  # tasks are in (value, trial) order, and so are the outcomes
            chunks[task.value_index].append(next(outcomes))
        per_value = tuple(TrialOutcomes.concatenate(c) for c in chunks)
        rows = tuple(summarize(v, o) for v, o in zip(values, per_value, strict=True))
        results.append(StudyResult(settings, values, rows, per_value))
    return results


def run_study(settings: StudySettings,
              parallel: ParallelSettings | None = None) -> StudyResult:
    """Run one study (see :func:`run_studies`)."""
    return run_studies([settings], parallel)[0]
