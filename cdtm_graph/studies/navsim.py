"""The paper's navigation simulation (section VI.A, Tables 1 and 2): Free vs Compensated.

The paper flies a ground trajectory at 200 m/s over a DTM made by cloning a basic cell
(Figs. 10-12), with an IMU error model, a 60 degree FOV and 100-120 features per frame
pair, and reports the **maximum** absolute position error per axis of IMU-only navigation
("Free") and of navigation corrected by C-DTM in a Kalman filter ("Compensated"):

* Table 1: altitudes 700, 1000 and 3000 m (resolution not stated; 1000x1000 assumed,
  because Table 2's 1000x1000 column repeats Table 1's 1000 m numbers);
* Table 2: resolutions 500x500, 1000x1000, 4000x4000 (altitude not stated; 1000 m
  assumed, for the same reason).

:func:`run_navsim` flies each case with :func:`cdtm_graph.sim.simulate.simulate` and reports
three estimates of the same flight:

* **Free**: IMU dead reckoning from the initial state (:func:`~cdtm_graph.verdict.evaluation.
  dead_reckoning`);
* **Compensated (smoothed)**: batch Levenberg-Marquardt over the whole flight
  (:func:`~cdtm_graph.run.smooth_and_evaluate`), which uses future frames for past ones;
* **Compensated (as arrived)**: iSAM2 fed frame by frame
  (:class:`~cdtm_graph.smoother.IncrementalSmoother`), keeping for each frame the estimate
  it had right after its own update: what a filter would have output in flight. Frame 0
  has no image pair yet (its estimate is the initial-state prior), so the first
  ``as_arrived_skip_frames`` frames are left out of this row.

Choices the paper leaves open (documented in docs/navsim.md):

* **IMU**: :data:`TACTICAL_IMU`, a tactical-grade unit (0.15 deg/sqrt(h) angle random
  walk, 10 deg/h gyro and 1 mg accelerometer turn-on bias), so Free drifts 0.2-3 km
  horizontally and 65-430 m vertically over the 5-minute flight (seeds 0-2): the paper's
  Free rows span 130-4000 m and 180-250 m. The example IMU of docs/flightlog.md (an
  ADIS16448-class MEMS, EuRoC's numbers) drifts 4-11 km horizontally over the same flight.
* **Initial state**: the aircraft has just lost GNSS: position 5 m, velocity 0.2 m/s,
  attitude 0.1 deg (1 sigma), the biases at their turn-on sigmas.
* **Frame interval**: the paper's 5-30 s intervals with 30-200 m baselines cannot both
  hold at 200 m/s, and at 5 s (1 km) consecutive 60 degree frames at 700 m would not
  overlap. We keep the baseline a fixed fraction of the altitude (``baseline_per_altitude``
  0.2: 1 s and 200 m at 1000 m), so every altitude sees the same image overlap (~83%)
  and the same 110 features per pair; every case flies the same duration.
* **One seed** for every case (common random numbers): the terrain cell, the IMU noise
  and the initial-state draw are the same, so the columns differ by the camera only.

Pure: no file I/O and no printing. ``cdtm navsim`` writes the tables.
"""

from __future__ import annotations

import csv
import dataclasses
import enum
import io
import logging
import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np

from cdtm_graph.constants import STANDARD_GRAVITY_MPS2
from cdtm_graph.dtm import Dtm
from cdtm_graph.errors import SimulationError
from cdtm_graph.flightlog import FlightLog
from cdtm_graph.imu import ImuNoise
from cdtm_graph.replay import replay
from cdtm_graph.results import TrajectoryEstimate
from cdtm_graph.run import smooth_and_evaluate
from cdtm_graph.sim.settings import DEFAULT_SEED, NOMINAL_SPEED_MPS
from cdtm_graph.sim.simulate import SimulationSettings, simulate
from cdtm_graph.smoother import IncrementalSmoother, SmootherMode, SmootherSettings
from cdtm_graph.studies.settings import (  # noqa: F401  (QUICK_DURATION_S re-exported)
    BASELINE_PER_ALTITUDE,
    NAVSIM_DURATION_S,
    QUICK_DURATION_S,
    TABLE1_ALTITUDES_M,
    TABLE2_ALTITUDE_M,
    TABLE2_RESOLUTIONS_PX,
    frame_interval_s,
)
from cdtm_graph.verdict.evaluation import AXES, ErrorReport, trajectory_errors

logger = logging.getLogger(__name__)

__all__ = [
    "PAPER_TABLE1_M",
    "PAPER_TABLE2_M",
    "QUICK_DURATION_S",
    "TACTICAL_IMU",
    "CaseResult",
    "Estimator",
    "NavsimResult",
    "NavsimSettings",
    "NavsimTable",
    "TableKind",
    "TableRow",
    "as_arrived_estimate",
    "run_case",
    "run_navsim",
    "table_csv",
    "table_markdown",
]

_RAD_PER_DEG = math.pi / 180.0
_S_PER_H = 3600.0

#: Tactical-grade IMU (Kalibr densities). Gyro: angle random walk 0.15 deg/sqrt(h)
#: (= 0.15 deg/sqrt(h) / 60 sqrt(s/min) in rad/s/sqrt(Hz)), bias random walk 1e-6
#: rad/s^2/sqrt(Hz) (the bias wanders ~1 deg/h in 5 min). Accelerometer: 100 ug/sqrt(Hz)
#: noise, bias random walk 3e-4 m/s^3/sqrt(Hz) (~0.5 mg in 5 min). The turn-on biases
#: (:attr:`NavsimSettings.sigma_gyro_bias`, ``sigma_accel_bias``) dominate the drift.
TACTICAL_IMU = ImuNoise(
    gyroscope_noise_density=0.15 * _RAD_PER_DEG / math.sqrt(_S_PER_H),
    accelerometer_noise_density=100e-6 * STANDARD_GRAVITY_MPS2,
    gyroscope_random_walk=1.0e-6,
    accelerometer_random_walk=3.0e-4,
)


#: Paper, Table 1 (maximum |error|, m): altitude (m) -> ("Free" | "Compensated", axis).
#: The paper labels its first row "Free"; it is Free-x (the rows go x, y, z in pairs).
PAPER_TABLE1_M: dict[float, dict[tuple[str, str], float]] = {
    700.0: {("Free", "x"): 900.0, ("Compensated", "x"): 25.0,
            ("Free", "y"): 1000.0, ("Compensated", "y"): 25.0,
            ("Free", "z"): 250.0, ("Compensated", "z"): 25.0},
    1000.0: {("Free", "x"): 130.0, ("Compensated", "x"): 20.0,
             ("Free", "y"): 2000.0, ("Compensated", "y"): 20.0,
             ("Free", "z"): 180.0, ("Compensated", "z"): 20.0},
    3000.0: {("Free", "x"): 1300.0, ("Compensated", "x"): 100.0,
             ("Free", "y"): 4000.0, ("Compensated", "y"): 100.0,
             ("Free", "z"): 250.0, ("Compensated", "z"): 150.0},
}

#: Paper, Table 2 (maximum |error| of the compensated solution, m): image side (px) ->
#: axis. The paper gives no Free rows here.
PAPER_TABLE2_M: dict[float, dict[tuple[str, str], float]] = {
    500: {("Compensated", "x"): 50.0, ("Compensated", "y"): 50.0, ("Compensated", "z"): 35.0},
    1000: {("Compensated", "x"): 20.0, ("Compensated", "y"): 20.0, ("Compensated", "z"): 20.0},
    4000: {("Compensated", "x"): 10.0, ("Compensated", "y"): 10.0, ("Compensated", "z"): 10.0},
}

# A duration that is a whole number of frame intervals must not lose its last frame to
# round-off in duration / interval.
_FRAME_COUNT_SLACK = 1e-9


class Estimator(enum.Enum):
    """The three navigation solutions of a case; the value is the row label's stem."""

    FREE = "Free"
    SMOOTHED = "Compensated (smoothed)"
    AS_ARRIVED = "Compensated (as arrived)"

    @property
    def paper_row(self) -> str:
        """The paper's row the estimate compares with: both compensated ones with the
        paper's filter (its only compensated solution)."""
        return "Free" if self is Estimator.FREE else "Compensated"

    def label(self, axis: str) -> str:
        """Row label in the paper's style: ``Free-x``, ``Compensated-x (smoothed)``."""
        if self is Estimator.FREE:
            return f"Free-{axis}"
        qualifier = self.value.removeprefix("Compensated ")
        return f"Compensated-{axis} {qualifier}"


class TableKind(enum.Enum):
    """Which parameter a table's columns sweep."""

    ALTITUDE = "altitude"      # Table 1
    RESOLUTION = "resolution"  # Table 2


@dataclass(frozen=True)
class NavsimSettings:
    """The section VI.A flights. Defaults: the paper's cases as docs/navsim.md reports them.

    Attributes:
        altitudes_m: Table 1's columns, flight altitude above the terrain's mean (m).
        resolutions_px: Table 2's columns, the side of the square image (px).
        table1_resolution_px: image side of every Table 1 case (px).
        table2_altitude_m: altitude of every Table 2 case (m).
        duration_s: flight time of every case (s); the last frame is the last whole frame
            interval inside it.
        baseline_per_altitude: distance flown between frames over the altitude: the
            frame interval is ``baseline_per_altitude * altitude / speed_mps``.
        speed_mps: ground speed (m/s), the paper's 200.
        fov_deg: horizontal field of view (deg), the paper's 60.
        n_features: features per consecutive frame pair (the paper: 100-120).
        pixel_sigma_px: 1-sigma registration error (the paper assumes half a pixel).
        dtm_spacing_m: grid spacing of the DTM the navigation uses (m), the paper's 30 m
            (sigma_h from its Fig. 6 model).
        relief_m: max - min height of the cloned terrain cell (m), the paper's 300 m.
        imu_noise: IMU noise densities (simulated and told to the smoother).
        sigma_position_m, sigma_velocity_mps, sigma_attitude_deg: initial-state prior;
            its mean is the truth moved by one draw of these.
        sigma_gyro_bias: turn-on gyro bias, 1 sigma (rad/s); 10 deg/h.
        sigma_accel_bias: turn-on accelerometer bias, 1 sigma (m/s^2); 1 mg.
        smoother: settings of the batch run (its ``mode`` is forced to BATCH; its
            ``graph`` is also the incremental run's).
        as_arrived_skip_frames: leading frames left out of the as-arrived evaluation
            (frame 0's estimate is the prior: no image pair has arrived).
        seed: the one seed of every case (>= 0).
    """

    altitudes_m: tuple[float, ...] = TABLE1_ALTITUDES_M
    resolutions_px: tuple[int, ...] = TABLE2_RESOLUTIONS_PX
    table1_resolution_px: int = 1000
    table2_altitude_m: float = TABLE2_ALTITUDE_M
    duration_s: float = NAVSIM_DURATION_S
    baseline_per_altitude: float = BASELINE_PER_ALTITUDE
    speed_mps: float = NOMINAL_SPEED_MPS
    fov_deg: float = 60.0
    n_features: int = 110
    pixel_sigma_px: float = 0.5
    dtm_spacing_m: float = 30.0
    relief_m: float = 300.0
    imu_noise: ImuNoise = TACTICAL_IMU
    sigma_position_m: float = 5.0
    sigma_velocity_mps: float = 0.2
    sigma_attitude_deg: float = 0.1
    sigma_gyro_bias: float = 10.0 * _RAD_PER_DEG / _S_PER_H
    sigma_accel_bias: float = 1.0e-3 * STANDARD_GRAVITY_MPS2
    smoother: SmootherSettings = field(default_factory=SmootherSettings)
    as_arrived_skip_frames: int = 1
    seed: int = DEFAULT_SEED

    def __post_init__(self) -> None:
        object.__setattr__(self, "altitudes_m", _positive_tuple(
            "altitudes_m", self.altitudes_m, float))
        object.__setattr__(self, "resolutions_px", _positive_tuple(
            "resolutions_px", self.resolutions_px, int))
        for name in ("table1_resolution_px", "n_features"):
            if not _is_int(getattr(self, name)) or getattr(self, name) < 1:
                raise SimulationError(f"{name} = {getattr(self, name)!r}, expected an integer >= 1")
        for name in ("table2_altitude_m", "duration_s", "baseline_per_altitude", "speed_mps"):
            value = getattr(self, name)
            if not (_is_number(value) and math.isfinite(value) and value > 0):
                raise SimulationError(f"{name} = {value!r}, expected a finite number > 0")
        if not _is_int(self.seed) or self.seed < 0:
            raise SimulationError(f"seed = {self.seed!r}, expected an integer >= 0")
        if not _is_int(self.as_arrived_skip_frames) or self.as_arrived_skip_frames < 0:
            raise SimulationError(f"as_arrived_skip_frames = {self.as_arrived_skip_frames!r}, "
                                  "expected an integer >= 0")
        for alt in {*self.altitudes_m, self.table2_altitude_m}:
            frames = self.frames(alt)
            if frames < 2 or frames <= self.as_arrived_skip_frames:
                raise SimulationError(
                    f"duration_s = {self.duration_s:g} holds {frames} frame(s) at {alt:g} m "
                    f"(frame interval {self.frame_interval_s(alt):g} s); expected at least 2 "
                    f"and more than as_arrived_skip_frames = {self.as_arrived_skip_frames}")

    def frame_interval_s(self, altitude_m: float) -> float:
        """Time between frames at ``altitude_m`` (s): the baseline scales with altitude."""
        return frame_interval_s(altitude_m, self.baseline_per_altitude, self.speed_mps)

    def frames(self, altitude_m: float) -> int:
        """Frames of the flight at ``altitude_m``: every whole interval of ``duration_s``."""
        return int(math.floor(self.duration_s / self.frame_interval_s(altitude_m)
                              + _FRAME_COUNT_SLACK)) + 1

    def simulation(self, altitude_m: float, resolution_px: int) -> SimulationSettings:
        """The simulator's settings of one case (the rest at the simulator's defaults)."""
        return SimulationSettings(
            relief_m=self.relief_m, dtm_spacing_m=self.dtm_spacing_m, altitude_m=altitude_m,
            speed_mps=self.speed_mps, frames=self.frames(altitude_m),
            fps=1.0 / self.frame_interval_s(altitude_m), n_features=self.n_features,
            resolution_px=(resolution_px, resolution_px), fov_deg=self.fov_deg,
            pixel_sigma_px=self.pixel_sigma_px, imu_noise=self.imu_noise,
            sigma_position_m=self.sigma_position_m, sigma_attitude_deg=self.sigma_attitude_deg,
            sigma_velocity_mps=self.sigma_velocity_mps, sigma_gyro_bias=self.sigma_gyro_bias,
            sigma_accel_bias=self.sigma_accel_bias, seed=self.seed)

    @property
    def cases(self) -> list[tuple[float, int]]:
        """Distinct (altitude m, resolution px) cases of both tables, Table 1's first."""
        keys = [(alt, self.table1_resolution_px) for alt in self.altitudes_m]
        keys += [(self.table2_altitude_m, res) for res in self.resolutions_px]
        return list(dict.fromkeys(keys))


@dataclass(frozen=True)
class CaseResult:
    """One flight and its three navigation solutions.

    Attributes:
        altitude_m: flight altitude (m). resolution_px: image side (px).
        frame_interval_s: time between frames (s). frames: K.
        features_per_pair_min, features_per_pair_mean: features seen in both frames of a
            consecutive pair (simulated).
        free: errors of IMU-only dead reckoning, K frames.
        smoothed: errors of the batch-smoothed trajectory, K frames (with ANEES).
        as_arrived: errors of each frame's estimate right after its own incremental
            update, frames ``as_arrived_skip_frames`` .. K-1.
        timings_s: wall time of "simulate", "batch" (batch smoothing + Free) and
            "incremental" (s).
    """

    altitude_m: float
    resolution_px: int
    frame_interval_s: float
    frames: int
    features_per_pair_min: int
    features_per_pair_mean: float
    free: ErrorReport
    smoothed: ErrorReport
    as_arrived: ErrorReport
    timings_s: dict[str, float]

    def report(self, estimator: Estimator) -> ErrorReport:
        """The error report of one solution."""
        return {Estimator.FREE: self.free, Estimator.SMOOTHED: self.smoothed,
                Estimator.AS_ARRIVED: self.as_arrived}[estimator]

    def max_error_m(self, estimator: Estimator) -> np.ndarray:
        """(3,) maximum |error| per world axis (x east, y north, z up), m."""
        return np.asarray(self.report(estimator).max_abs_position_error_m, dtype=float)


@dataclass(frozen=True)
class TableRow:
    """One row of a table: our maximum errors per column beside the paper's.

    Attributes:
        label: e.g. ``Compensated-x (smoothed)``.
        estimator: which solution. axis: "x", "y" or "z".
        ours_m: (C,) our maximum |error| per column (m).
        paper_m: (C,) the paper's number for the row and column, or None where it has none.
    """

    label: str
    estimator: Estimator
    axis: str
    ours_m: tuple[float, ...]
    paper_m: tuple[float | None, ...]


@dataclass(frozen=True)
class NavsimTable:
    """Table 1 (columns: altitudes) or Table 2 (columns: resolutions).

    Attributes:
        kind: which parameter the columns sweep.
        columns: (C,) altitudes (m) or image sides (px).
        cases: (C,) the case of each column.
    """

    kind: TableKind
    columns: tuple[float, ...] | tuple[int, ...]
    cases: tuple[CaseResult, ...]

    @property
    def title(self) -> str:
        if self.kind is TableKind.ALTITUDE:
            return "Table 1. Maximum errors vs. height"
        return "Table 2. Effect of resolution on max. error"

    @property
    def corner(self) -> str:
        """Header of the label column, as the paper's."""
        return "Flight height" if self.kind is TableKind.ALTITUDE else "Resolution"

    def column_label(self, value: float | int) -> str:
        """``700 m`` or ``500x500``, as the paper heads its columns."""
        if self.kind is TableKind.ALTITUDE:
            return f"{value:g} m"
        return f"{value}x{value}"

    def paper_value(self, column: float | int, estimator: Estimator,
                    axis: str) -> float | None:
        """The paper's number for a row and column, or None (not in the paper)."""
        paper = PAPER_TABLE1_M if self.kind is TableKind.ALTITUDE else PAPER_TABLE2_M
        return paper.get(column, {}).get((estimator.paper_row, axis))

    def rows(self) -> list[TableRow]:
        """Rows in the paper's order (x, y, z; Free then Compensated), with our extra
        as-arrived row after each smoothed one."""
        out = []
        for a, axis in enumerate(AXES):
            for estimator in Estimator:
                out.append(TableRow(
                    label=estimator.label(axis), estimator=estimator, axis=axis,
                    ours_m=tuple(float(c.max_error_m(estimator)[a]) for c in self.cases),
                    paper_m=tuple(self.paper_value(col, estimator, axis)
                                  for col in self.columns)))
        return out


@dataclass(frozen=True)
class NavsimResult:
    """Both tables and how they were made.

    Attributes:
        settings: the settings of the run.
        table1: columns ``settings.altitudes_m``.
        table2: columns ``settings.resolutions_px``.
        time_s: wall time of the whole run (s).
    """

    settings: NavsimSettings
    table1: NavsimTable
    table2: NavsimTable
    time_s: float


# --------------------------------------------------------------------------- running


def as_arrived_estimate(flight: FlightLog, dtm: Dtm,
                        settings: SmootherSettings | None = None) -> TrajectoryEstimate:
    """Each frame's estimate right after its own incremental update (filter-like).

    The flight is fed to :class:`IncrementalSmoother` (full-history iSAM2, or fixed lag
    with ``settings.lag_s``) frame by frame; frame k's pose and velocity are those of the
    :class:`~cdtm_graph.smoother.FrameUpdate` of ``add_frame(k)``, never revised by later
    frames.

    Args:
        flight: the log. dtm: its terrain.
        settings: the ``graph`` and ``lag_s`` to use (default: the defaults).

    Returns:
        K frames; biases are the smoother's final estimate (not evaluated here).
    """
    settings = settings or SmootherSettings()
    smoother = IncrementalSmoother(flight.config, dtm, settings, imu=flight.imu)
    t_ns = np.asarray(flight.frames.t_ns, dtype=np.int64)
    poses = np.empty((t_ns.shape[0], 4, 4))
    velocities = np.empty((t_ns.shape[0], 3))
    for frame in replay(flight):
        update = smoother.add_frame(frame.t_ns, frame.track_id, frame.uv_px)
        poses[frame.k], velocities[frame.k] = update.world_T_body, update.velocity_mps
    final = smoother.estimate()
    return TrajectoryEstimate(t_ns=t_ns, world_T_body=poses, velocity_mps=velocities,
                              gyro_bias=final.gyro_bias, accel_bias=final.accel_bias)


def _frames_from(estimate: TrajectoryEstimate, first: int) -> TrajectoryEstimate:
    return TrajectoryEstimate(estimate.t_ns[first:], estimate.world_T_body[first:],
                              estimate.velocity_mps[first:], estimate.gyro_bias[first:],
                              estimate.accel_bias[first:])


def run_case(settings: NavsimSettings, altitude_m: float, resolution_px: int) -> CaseResult:
    """Simulate one flight and evaluate Free, smoothed and as-arrived navigation.

    Args:
        settings: the navsim settings.
        altitude_m: flight altitude (m). resolution_px: image side (px).

    Returns:
        The case's errors.

    Raises:
        SimulationError: the case cannot be simulated (e.g. the altitude does not clear
            the terrain, or frames share no feature).
        SolverError: the smoother found the system indeterminant.
    """
    timings: dict[str, float] = {}
    start = time.perf_counter()
    sim = simulate(settings.simulation(altitude_m, resolution_px))
    flight, dtm = sim.log, sim.dtm
    timings["simulate"] = time.perf_counter() - start

    start = time.perf_counter()
    batch = dataclasses.replace(settings.smoother, mode=SmootherMode.BATCH)
    run = smooth_and_evaluate(flight, dtm, batch)
    timings["batch"] = time.perf_counter() - start
    truth = flight.groundtruth
    if run.errors is None or run.free_errors is None or truth is None:
        # (simulate always writes ground truth)
        raise SimulationError("the simulated flight has no ground truth to evaluate")

    start = time.perf_counter()
    arrived = as_arrived_estimate(flight, dtm, settings.smoother)
    as_arrived = trajectory_errors(_frames_from(arrived, settings.as_arrived_skip_frames),
                                   None, truth)
    timings["incremental"] = time.perf_counter() - start

    pairs = sim.stats.pairs_per_frame
    case = CaseResult(
        altitude_m=float(altitude_m), resolution_px=int(resolution_px),
        frame_interval_s=settings.frame_interval_s(altitude_m), frames=len(flight.frames),
        features_per_pair_min=int(pairs.min()), features_per_pair_mean=float(pairs.mean()),
        free=run.free_errors, smoothed=run.errors, as_arrived=as_arrived, timings_s=timings)
    logger.info("navsim %g m, %dx%d px, %d frames: max |error| free %s, smoothed %s, "
                "as arrived %s m (%.1f s)", altitude_m, resolution_px, resolution_px,
                case.frames, *(np.round(case.max_error_m(e), 1) for e in Estimator),
                sum(timings.values()))
    return case


def run_navsim(settings: NavsimSettings | None = None,
               progress: Callable[[int, int, tuple[float, int]], None] | None = None
               ) -> NavsimResult:
    """Fly every case of Tables 1 and 2 (a case both tables share is flown once).

    Args:
        settings: what to fly (default: the paper's cases, :class:`NavsimSettings`).
        progress: called as ``progress(done, total, (altitude_m, resolution_px))``
            before each case and once at the end (``done == total``).

    Returns:
        Both tables.
    """
    settings = settings or NavsimSettings()
    start = time.perf_counter()
    keys = settings.cases
    results: dict[tuple[float, int], CaseResult] = {}
    for i, key in enumerate(keys):
        if progress is not None:
            progress(i, len(keys), key)
        results[key] = run_case(settings, *key)
    if progress is not None:
        progress(len(keys), len(keys), keys[-1])
    res1 = settings.table1_resolution_px
    table1 = NavsimTable(TableKind.ALTITUDE, settings.altitudes_m,
                         tuple(results[(alt, res1)] for alt in settings.altitudes_m))
    alt2 = settings.table2_altitude_m
    table2 = NavsimTable(TableKind.RESOLUTION, settings.resolutions_px,
                         tuple(results[(alt2, res)] for res in settings.resolutions_px))
    return NavsimResult(settings, table1, table2, time.perf_counter() - start)


# --------------------------------------------------------------------------- rendering


def _metres(value: float) -> str:
    """One of our maximum errors for a table: 1 decimal below 100 m, whole metres above."""
    if not math.isfinite(value):
        return "nan"
    return f"{value:.1f}" if abs(value) < 100.0 else f"{value:.0f}"


def _paper(value: float | None) -> str:
    """One of the paper's numbers as it prints it; a dash where it has none."""
    return "–" if value is None else f"{value:g}"


def table_markdown(table: NavsimTable) -> str:
    """The table as markdown, laid out as the paper's, with its numbers beside ours.

    Columns: the paper's label column, then per swept value "ours" and "paper"; rows
    Free-x, Compensated-x (smoothed), Compensated-x (as arrived), Free-y, ... Both
    compensated rows sit beside the paper's one (filtered) compensated number. Below the
    table, one line per column says how its flight was flown.

    Args:
        table: Table 1 or 2.

    Returns:
        Markdown text ending in a newline.
    """
    header = [table.corner]
    for col in table.columns:
        header += [table.column_label(col), "paper"]
    lines = [f"**{table.title}** (maximum |position error|, m; ours beside the paper's)", "",
             "| " + " | ".join(header) + " |",
             "|---" + "|---:" * (len(header) - 1) + "|"]
    for row in table.rows():
        cells = [row.label]
        for ours, paper in zip(row.ours_m, row.paper_m):
            cells += [_metres(ours), _paper(paper)]
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    for col, case in zip(table.columns, table.cases):
        fixed = (f"{case.resolution_px}x{case.resolution_px} px"
                 if table.kind is TableKind.ALTITUDE else f"{case.altitude_m:g} m")
        lines.append(
            f"- {table.column_label(col)}: {fixed}, {case.frames} frames every "
            f"{case.frame_interval_s:g} s, "
            f"{case.features_per_pair_min}-{case.features_per_pair_mean:.0f} features per "
            f"pair (min-mean); smoothed RMSE x/y/z "
            + "/".join(f"{v:.1f}" for v in case.smoothed.rmse_position_m) + " m")
    return "\n".join(lines) + "\n"


def table_csv(table: NavsimTable) -> str:
    """The table as CSV: the markdown's layout, numbers unrounded, empty where the paper
    has none.

    Header: ``row`` then, per column, its label and ``<label> paper`` (e.g. ``700 m``,
    ``700 m paper``). One line per :meth:`NavsimTable.rows` row.

    Args:
        table: Table 1 or 2.

    Returns:
        CSV text (``\\n`` line ends).
    """
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    header = ["row"]
    for col in table.columns:
        label = table.column_label(col)
        header += [label, f"{label} paper"]
    writer.writerow(header)
    for row in table.rows():
        cells = [row.label]
        for ours, paper in zip(row.ours_m, row.paper_m):
            cells += [repr(float(ours)), "" if paper is None else f"{paper:g}"]
        writer.writerow(cells)
    return buffer.getvalue()


# --------------------------------------------------------------------------- helpers


def _positive_tuple(name: str, values: object, kind: type) -> tuple:
    """``values`` as a non-empty tuple of distinct finite positive ``kind`` numbers."""
    try:
        items: tuple[Any, ...] = tuple(cast(Iterable[Any], values))
    except TypeError:
        raise SimulationError(f"{name} = {values!r}, expected a sequence of numbers") from None
    check = _is_int if kind is int else _is_number
    if not items or not all(check(v) and math.isfinite(v) and v > 0 for v in items):
        what = "integers" if kind is int else "finite numbers"
        raise SimulationError(f"{name} = {values!r}, expected one or more {what} > 0")
    out = tuple(kind(v) for v in items)
    if len(set(out)) != len(out):
        raise SimulationError(f"{name} = {values!r}, expected distinct values")
    return out


def _is_number(value: object) -> bool:
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(value,
                                                                                       bool)


def _is_int(value: object) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool)
