"""Results of a smoothing run: per-frame states, covariances and statistics (no I/O here).

Covariances of poses are in GTSAM's Pose3 tangent order [rotation, translation], with
perturbations on the right, i.e. in the body frame: ``world_T_body * Exp(xi)``. Writers
that need world-frame blocks rotate them with :func:`pose_covariance_in_world`.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from cdtm_graph.codes import Code

if TYPE_CHECKING:
    from cdtm_graph.calibration.check import CalibrationCheck
    from cdtm_graph.calibration.online import CalibrationEstimate
    from cdtm_graph.flightlog.model import DtmConfig, FlightConfig


@dataclass(frozen=True)
class TrajectoryEstimate:
    """Per-frame body states.

    Attributes:
        t_ns: (K,) int64 frame times.
        world_T_body: (K, 4, 4) body poses.
        velocity_mps: (K, 3) world-frame velocity.
        gyro_bias: (K, 3) rad/s. accel_bias: (K, 3) m/s^2.
    """

    t_ns: np.ndarray
    world_T_body: np.ndarray
    velocity_mps: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    @property
    def position_m(self) -> np.ndarray:
        return self.world_T_body[:, :3, 3]


@dataclass(frozen=True)
class StateCovariances:
    """Marginal covariances per frame.

    Attributes:
        pose: (K, 6, 6) of ``X(k)``, GTSAM tangent order [rot, trans], body frame.
        velocity: (K, 3, 3) of ``V(k)``, world frame.
        bias: (K, 6, 6) of ``B(k)``, GTSAM order [accel, gyro].
    """

    pose: np.ndarray
    velocity: np.ndarray
    bias: np.ndarray

    def with_position_added(self, world_T_body: np.ndarray, position_cov_world: np.ndarray
                            ) -> StateCovariances:
        """These covariances with a world-frame position covariance added
        (:func:`with_position_covariance`)."""
        return StateCovariances(with_position_covariance(self.pose, world_T_body,
                                                         position_cov_world),
                                self.velocity, self.bias)


def with_position_covariance(pose_cov: np.ndarray, world_T_body: np.ndarray,
                             position_cov_world: np.ndarray) -> np.ndarray:
    """(K, 6, 6) body-frame pose covariances with a world-frame position covariance ((3, 3)
    for every pose, or (K, 3, 3)) added: an error the estimate cannot see and so does not
    hold (a considered parameter), e.g. an offset of the whole map. A right perturbation
    moves the position by ``R v``: the body-frame block takes ``R^T C R``."""
    R = world_T_body[:, :3, :3]
    out = pose_cov.copy()
    out[:, 3:, 3:] += np.swapaxes(R, 1, 2) @ position_cov_world @ R
    return out


@dataclass(frozen=True)
class MapOffset:
    """How far the whole map under the flight may be off: its registration and its
    vertical datum (flight.yaml's ``dtm.horizontal_offset_sigma_m`` and
    ``dtm.vertical_offset_sigma_m``, 1-sigma, m; None: not declared, taken as 0).

    The camera and the DTM cannot see such an offset: moving the map and the trajectory
    together changes no measurement, so the estimate takes the offset one for one. Its
    covariance is added to every position covariance, as a considered parameter
    (:meth:`StateCovariances.with_position_added`).
    """

    horizontal_sigma_m: float | None = None
    vertical_sigma_m: float | None = None

    @classmethod
    def of(cls, dtm: DtmConfig) -> MapOffset:
        return cls(dtm.horizontal_offset_sigma_m, dtm.vertical_offset_sigma_m)

    @property
    def undeclared(self) -> tuple[str, ...]:
        """flight.yaml's keys of the sigmas not declared."""
        return tuple(key for key, sigma in (("dtm.horizontal_offset_sigma_m",
                                             self.horizontal_sigma_m),
                                            ("dtm.vertical_offset_sigma_m",
                                             self.vertical_sigma_m)) if sigma is None)

    def covariance_world(self) -> np.ndarray:
        """(3, 3) world (east, north, up), m^2; an undeclared sigma counts as 0."""
        h, v = self.horizontal_sigma_m or 0.0, self.vertical_sigma_m or 0.0
        return np.diag([h**2, h**2, v**2])

    @property
    def declared_zero(self) -> bool:
        """Nothing to add (declared 0, or not declared)."""
        return not (self.horizontal_sigma_m or self.vertical_sigma_m)

    def added_to(self, covariances: StateCovariances, world_T_body: np.ndarray
                 ) -> StateCovariances:
        """``covariances`` (of the poses ``world_T_body``) with the offset's added."""
        if self.declared_zero:
            return covariances
        return covariances.with_position_added(world_T_body, self.covariance_world())

    def added_to_pose(self, pose_cov: np.ndarray, world_T_body: np.ndarray) -> np.ndarray:
        """One (6, 6) pose covariance (of the pose ``world_T_body``) with the offset's added
        (a copy)."""
        if self.declared_zero:
            return pose_cov.copy()
        return with_position_covariance(pose_cov[None], world_T_body[None],
                                        self.covariance_world())[0]


@dataclass(frozen=True)
class BiasPrior:
    """What flight.yaml says of the IMU biases: their value and 1-sigma at the first frame
    (``initial_state``) and how fast they may wander (``imu.*_random_walk``). The run's
    bias estimates are held against it (:meth:`excess`, the verdict's ``imu_bias``).
    """

    accel_mps2: np.ndarray
    gyro_radps: np.ndarray
    sigma_accel_mps2: float
    sigma_gyro_radps: float
    accel_random_walk: float  # m/s^3/sqrt(Hz)
    gyro_random_walk: float  # rad/s^2/sqrt(Hz)

    @classmethod
    def of(cls, config: FlightConfig) -> BiasPrior:
        init, imu = config.initial_state, config.imu
        return cls(np.asarray(init.accel_bias, float), np.asarray(init.gyro_bias, float),
                   float(init.sigma_accel_bias), float(init.sigma_gyro_bias),
                   float(imu.accelerometer_random_walk), float(imu.gyroscope_random_walk))

    def excess(self, t_ns: np.ndarray, accel_bias: np.ndarray, gyro_bias: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
        """(K,) each frame's squared distance of the accelerometer and of the gyro bias
        estimates from the prior's value, in the prior's variance there (its initial
        variance plus the random walk's since the first frame): chi-square(3)-like for
        biases the prior describes (a little less: the estimate shrinks toward it)."""
        t_s = (np.asarray(t_ns) - t_ns[0]) * 1e-9
        out = []
        for bias, value, sigma, walk in ((accel_bias, self.accel_mps2, self.sigma_accel_mps2,
                                          self.accel_random_walk),
                                         (gyro_bias, self.gyro_radps, self.sigma_gyro_radps,
                                          self.gyro_random_walk)):
            variance = sigma**2 + walk**2 * t_s
            out.append(np.sum((bias - value) ** 2, axis=1) / variance)
        return out[0], out[1]


@dataclass(frozen=True)
class PriorConflict:
    """flight.yaml's position prior against the first frame's estimate
    (:meth:`PositionPrior.conflict`).

    Attributes:
        nis: the squared distance of the prior's value from where the rest of the data
            put the first frame, in the covariance the two should differ by
            (chi-square(``dof``) when both are as stated).
        dof: the directions the data tell (those the prior alone holds are left out).
        distance_m: how far the rest of the data put the first frame from the prior.
        pull_m: how far the prior moved the first frame's estimate from there.
        pull_nees: that move in the run's covariance of the frame (its NEES, were the
            prior's value wrong). The distance and the pull are exact where the frame's
            position is the model's only state; its attitude and velocity, correlated with
            it, move them a little (20 m off at 2 m: the pull read 9.9-14.9 m against a
            run without the prior's 10.4-15.0 m), the statistic not at all.
    """

    nis: float
    dof: int
    distance_m: float
    pull_m: float
    pull_nees: float

    def to_dict(self) -> dict:
        return {"nis": self.nis, "dof": self.dof, "distance_m": self.distance_m,
                "pull_m": self.pull_m, "pull_nees": self.pull_nees}


#: A direction the data tell less than this share of (one minus the prior's share of the
#: frame's information) is the prior's alone: it cannot be tested there.
_UNTOLD_SHARE = 1e-3


@dataclass(frozen=True)
class PositionPrior:
    """flight.yaml's prior on the first frame's position (``initial_state.position_m``
    within ``sigma_position_m``, each axis). The verdict holds the first frame's estimate
    against it (:meth:`conflict`, the verdict's ``initial_position``), as it holds the
    bias estimates against theirs (:class:`BiasPrior`)."""

    position_m: np.ndarray
    sigma_m: float

    @classmethod
    def of(cls, config: FlightConfig) -> PositionPrior:
        init = config.initial_state
        return cls(np.asarray(init.position_m, float), float(init.sigma_position_m))

    def conflict(self, world_T_body: np.ndarray, pose_cov: np.ndarray,
                 offset_cov_world: np.ndarray) -> PriorConflict | None:
        """The prior against the first frame's estimate ``world_T_body`` (4, 4), whose
        marginal ``pose_cov`` (6, 6, body frame) holds ``offset_cov_world`` (3, 3): what the
        data's fix carries and the prior does not (the map's offset, as :class:`MapOffset`
        adds it; a declared principal point's share). None when there is
        nothing to test (no sigma, no covariance, or the prior alone holds the frame).

        Why it works without the data's own fix: in the linear-Gaussian model the posterior
        ``x`` of a prior ``N(mu, Sp)`` and data fixing ``x_d`` is ``mu + (I - A)(x_d - mu)``
        with ``A = P Sp^-1`` (P the posterior covariance), so ``r = x - mu`` gives back
        ``x_d - mu = (I - A)^-1 r``; ``r`` has covariance ``Sp - P`` (plus the map's
        offset, which ``x_d`` carries and ``mu`` does not, through ``I - A``), and the
        prior moved the estimate by ``-A (I - A)^-1 r`` from the data's fix. Where the data
        dominate (``A`` ~ 0) a far prior moves nothing; where the prior holds the frame
        (``A`` near 1) the data barely tell it and a small ``r`` is a large conflict.
        """
        sigma = self.sigma_m
        if not (sigma > 0.0 and math.isfinite(sigma)) or not np.all(np.isfinite(pose_cov)):
            return None
        R = world_T_body[:3, :3]
        run_cov = R @ pose_cov[3:, 3:] @ R.T
        run_cov = (run_cov + run_cov.T) / 2
        offset = np.asarray(offset_cov_world, float)
        # the posterior of the frame without the map's offset, in the prior's units (divided
        # by sigma twice: sigma**2 may overflow)
        with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
            scaled = (run_cov - offset) / sigma / sigma
            offset_scaled = offset / sigma / sigma
            y_all = (world_T_body[:3, 3] - self.position_m) / sigma
        if not (np.all(np.isfinite(scaled)) and np.all(np.isfinite(offset_scaled))
                and np.all(np.isfinite(y_all)) and np.linalg.eigvalsh(run_cov)[0] > 0.0):
            return None
        share, V = np.linalg.eigh(scaled)
        share = np.clip(share, 0.0, 1.0)
        told = 1.0 - share > _UNTOLD_SHARE
        if not told.any():
            return None
        V, share = V[:, told], share[told]
        y = V.T @ y_all
        D = np.diag(1.0 - share)
        S = D + D @ V.T @ offset_scaled @ V @ D
        nis = float(y @ np.linalg.solve(S, y))
        pull = -sigma * V @ (share / (1.0 - share) * y)
        return PriorConflict(nis=nis, dof=int(told.sum()),
                             distance_m=float(sigma * np.linalg.norm(y / (1.0 - share))),
                             pull_m=float(np.linalg.norm(pull)),
                             pull_nees=float(pull @ np.linalg.solve(run_cov, pull)))

    def to_dict(self) -> dict:
        return {"position_m": self.position_m.tolist(), "sigma_m": self.sigma_m}


class Solver(enum.Enum):
    """The solver that produced a result."""

    LEVENBERG_MARQUARDT = "batch"  # batch LM over the whole log
    ISAM2 = "incremental"          # full-history iSAM2
    FIXED_LAG = "fixed_lag"        # GTSAM's incremental fixed-lag smoother


@dataclass(frozen=True)
class SolverStats:
    """What the optimizer did.

    Attributes (incremental runs): update_times_s: each frame's update (``add_frame``);
    imu_times_s: the IMU preintegration of each frame interval done as its samples
    arrived (``add_imu``), before that frame's update; innovation_nis_median,
    innovation_nis_mean: of the squared Mahalanobis distances of the innovations the gate
    tested (chi-square(2): 1.39 and 2 when the model is honest; NaN without a gate).
    """

    solver: Solver
    iterations: int
    initial_error: float
    final_error: float
    converged: bool
    time_s: float
    marginals_time_s: float = 0.0
    update_times_s: tuple[float, ...] = ()
    imu_times_s: tuple[float, ...] = ()
    innovation_nis_median: float = float("nan")
    innovation_nis_mean: float = float("nan")


class Rejection(enum.Enum):
    """Why a feature (one consecutive observation pair of a track) was left out."""

    MISSED_DTM = "missed_dtm"      # its ray missed the DTM or hit no data
    WRONG_MATCH = "wrong_match"    # off its epipolar line: the tracker matched something else
    GRAZING = "grazing"            # its ray grazes a ridge: the DTM hit is unstable
    MAP_MISMATCH = "map_mismatch"  # its ground point is not where the DTM says
    GATED = "gated"                # its innovation failed the gate against the prior
    TOO_OLD = "too_old"            # its earlier frame had left the fixed lag's window
    NO_FIX = "no_fix"              # seen while the fix was not acquired (prior too wide)


class Rejections:
    """Features left out, by reason and by frame (the later frame of the pair)."""

    def __init__(self) -> None:
        self._counts: dict[Rejection, dict[int, int]] = {r: {} for r in Rejection}
        self._totals = dict.fromkeys(Rejection, 0)  # (a stage's count: before and after)

    def add(self, reason: Rejection, frame: int, n: int) -> None:
        if n:
            per_frame = self._counts[reason]
            per_frame[frame] = per_frame.get(frame, 0) + int(n)
            self._totals[reason] += int(n)

    def total(self, reason: Rejection | None = None) -> int:
        if reason is not None:
            return self._totals[reason]
        return sum(self._totals.values())

    def in_frames(self, first: int, end: int) -> dict[str, np.ndarray]:
        """Reason value -> counts of frames ``first .. end - 1``, the reasons that left
        any out there (a live update's few frames: looked up, not gathered)."""
        out = {}
        for reason, counts in self._counts.items():
            if counts:
                n = [counts.get(k, 0) for k in range(first, end)]
                if any(n):
                    out[reason.value] = np.array(n, dtype=float)
        return out

    def per_frame(self, n_frames: int) -> dict[str, np.ndarray]:
        """Reason value -> (K,) counts, every reason present."""
        out = {}
        for reason, counts in self._counts.items():
            arr = np.zeros(n_frames, dtype=int)
            for k, n in counts.items():
                arr[k] += n
            out[reason.value] = arr
        return out


@dataclass(frozen=True)
class GraphCounts:
    """What went into the graph.

    Attributes:
        n_frames: frames (pose nodes).
        n_tracks: distinct track ids.
        n_observations: rows of tracks.csv.
        n_feature_pairs: consecutive observation pairs offered to the graph.
        n_cdtm_features: pairs that became C-DTM residuals.
        n_cdtm_factors: batched factors (one per frame pair).
        n_imu_factors: IMU preintegration factors.
        features_per_frame: (K,) C-DTM features ending at each frame.
        n_outliers: features whose residual at the solution fails the chi-square(2)
            99.9% test (flagged; the robust kernel weights them).
        outliers_per_frame: (K,) the same, by the frame the feature pair ends at.
        rejected_per_frame: :class:`Rejection` value -> (K,) features left out for that
            reason, by the frame the pair ends at.
        residual_chi2_per_frame: (K,) sum of the squared Mahalanobis distances (full
            measurement noise) of the features within the chi-square test, by the frame
            the pair ends at (``features_per_frame - outliers_per_frame`` of them): the
            residual self-check of :mod:`cdtm_graph.verdict.rules`. Empty if not computed.
    """

    n_frames: int
    n_tracks: int
    n_observations: int
    n_feature_pairs: int
    n_cdtm_features: int
    n_cdtm_factors: int
    n_imu_factors: int
    features_per_frame: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    n_outliers: int = 0
    outliers_per_frame: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    rejected_per_frame: dict[str, np.ndarray] = field(default_factory=dict)
    residual_chi2_per_frame: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def n_rejected(self, reason: Rejection | None = None) -> int:
        """Features left out for ``reason`` (any reason if None)."""
        if reason is not None:
            return int(np.sum(self.rejected_per_frame.get(reason.value, 0)))
        return int(sum(np.sum(v) for v in self.rejected_per_frame.values()))


@dataclass(frozen=True)
class TerrainFindings:
    """What the smoother found of the ground against the DTM, seen as a population of
    ground and clutter (:mod:`cdtm_graph.robust.clutter`).

    Attributes:
        clutter_found: the tracks' heights show clutter (forest, buildings) the DTM lacks.
        clutter_share: its share of the tracks. clutter_height_m: its height over the
            ground. clutter_spread_m: the spread of that height.
        ground_offset_m: where the ground tracks lie against the DTM at the solution.
        likelihood_ratio: ``2 log`` of the clutter mixture's likelihood over the ground's.
        considered_vertical_m: (K,) the vertical offset each frame's features may still
            carry; its square is in the frame's position covariance (world up).
    """

    clutter_found: bool
    clutter_share: float
    clutter_height_m: float
    clutter_spread_m: float
    ground_offset_m: float
    likelihood_ratio: float
    considered_vertical_m: np.ndarray


def position_move_nees(world_T_body: np.ndarray, pose_cov: np.ndarray,
                       position_m: np.ndarray) -> np.ndarray:
    """Per frame, how far ``position_m`` lies from the run's positions in the run's own
    position covariance: ``d^T P^-1 d``, ``d`` the run's position less ``position_m``.

    Args:
        world_T_body: (F, 4, 4) the run's poses.
        pose_cov: (F, 6, 6) their covariances (body frame, [rot, trans]).
        position_m: (F, 3) the other solution's positions, world axes.

    Returns:
        (F,) the squared Mahalanobis distances; NaN where a frame has no covariance.
    """
    d = world_T_body[:, :3, 3] - position_m
    R = world_T_body[:, :3, :3]
    P = R @ pose_cov[:, 3:, 3:] @ np.swapaxes(R, 1, 2)  # body -> world
    ok = np.isfinite(P).all(axis=(1, 2))
    out = np.full(d.shape[0], np.nan)
    if ok.any():
        out[ok] = np.einsum("ki,ki->k", d[ok], np.linalg.solve(P[ok], d[ok][..., None])[..., 0])
    return out


@dataclass(frozen=True)
class MapErrorEstimate:
    """The DTM's height error the tracks show, beside the stated one
    (:mod:`cdtm_graph.robust.map_error`).

    Attributes:
        stated_m: flight.yaml's (or the spacing model's) sigma_h.
        estimated_m: the tracks' estimate (NaN with too few well-triangulated tracks).
        n_tracks: the well-triangulated tracks it rests on.
        used_m: the sigma_h the run was made with: the stated one, or the estimate when
            it exceeded it beyond chance (the run then made again with it), or the bound.
        bound_m: the most a run is grown to (``MapErrorSettings.max_ratio`` times the
            stated).
        first_estimated_m: the first run's reading, when it lay beyond the bound and the
            run made again at the bound read within it and was kept (``estimated_m`` is
            then that run's); NaN otherwise.
        bound_estimated_m: the reading of the run made again at the bound, when the
            first run's lay beyond it and that run was not kept (beyond again, or NaN:
            too few tracks); NaN otherwise.
        slope_sigma_posts: the run kept took its tangent planes' slopes from the DTM
            smoothed over this many posts (a Gaussian's sigma; a grown run's,
            ``MapErrorSettings.slope_sigma_posts``); 0: the bilinear patches' own.
        grown_at: an incremental pass that grew sigma_h as it went (:class:`~cdtm_graph.
            robust.map_error.MapErrorWatch`): (frame, sigma_h from that frame on), in
            order; ``used_m`` is then the last. Its factors held the stated sigma_h
            before the first. Empty: none (a run made with one sigma_h throughout).
    """

    stated_m: float
    estimated_m: float
    n_tracks: int
    used_m: float
    bound_m: float = float("inf")
    first_estimated_m: float = float("nan")
    bound_estimated_m: float = float("nan")
    slope_sigma_posts: float = 0.0
    grown_at: tuple[tuple[int, float], ...] = ()

    @property
    def grown(self) -> bool:
        return self.used_m > self.stated_m

    @property
    def beyond(self) -> bool:
        """The tracks read the map beyond the bound a run is grown to."""
        return self.estimated_m > self.bound_m

    def to_dict(self) -> dict:
        return {"stated_m": self.stated_m,
                "estimated_m": None if math.isnan(self.estimated_m) else self.estimated_m,
                "n_tracks": self.n_tracks, "used_m": self.used_m, "grown": self.grown,
                "bound_m": self.bound_m,
                "first_estimated_m": (None if math.isnan(self.first_estimated_m)
                                      else self.first_estimated_m),
                "bound_estimated_m": (None if math.isnan(self.bound_estimated_m)
                                      else self.bound_estimated_m),
                "slope_sigma_posts": self.slope_sigma_posts,
                "grown_at": [{"frame": k, "sigma_h_m": m} for k, m in self.grown_at]}


@dataclass(frozen=True)
class RandomWalkEstimate:
    """flight.yaml's IMU bias random walks against the wander the run's bias steps show,
    and the walks the run was made with (:mod:`cdtm_graph.robust.imu_walk`).

    Attributes:
        stated_gyro, stated_accel: flight.yaml's ``imu.gyroscope_random_walk``
            (rad/s^2/sqrt(Hz)) and ``imu.accelerometer_random_walk`` (m/s^3/sqrt(Hz)).
        ratio_gyro, ratio_accel: the bias steps' chi-square over its expectation at the
            stated walks, over the lower half of the flight's segments (the spread: ~1 or
            less when they hold;
            :class:`~cdtm_graph.robust.imu_walk.BiasSteps`).
        chi2, expected: (gyro, accelerometer) that chi-square and its expectation.
        chi2_bound: (gyro, accelerometer) the chi-square's quantile beyond which the walks
            are grown (``RandomWalkSettings.probability``).
        n_steps: the frame intervals counted (those with an IMU gap left out).
        used_gyro, used_accel: the walks the run was made with (the stated ones, or grown).
        final_ratios: (gyro, accelerometer) the ratios over every segment at the walks
            used (what the growth settles).
        bound_scale: the most the walks are grown (times the stated).
        held: the walks used hold the bias steps: no ratio beyond the growth threshold,
            and none still above the settling ratio at the bound (False: the bound
            stopped the growth, not the data: the verdict's ``imu_random_walk``).
        rounds: side solves of the growth. time_s: the check's cost.
        yielded_to: the steps exceeded the walks, but the verdict names these reasons
            of another fault that bends them (``verdict.rules.WALK_CONFOUNDERS``: a bias
            beyond flight.yaml's prior, a calibration the flight contradicts, outliers...):
            not grown; empty when it did not yield.
    """

    stated_gyro: float
    stated_accel: float
    ratio_gyro: float
    ratio_accel: float
    chi2: tuple[float, float]
    expected: tuple[float, float]
    chi2_bound: tuple[float, float]
    n_steps: int
    used_gyro: float
    used_accel: float
    final_ratios: tuple[float, float]
    bound_scale: float
    held: bool
    rounds: int
    time_s: float
    yielded_to: tuple[str, ...] = ()

    @property
    def yielded(self) -> bool:
        """The steps exceeded the walks, but another fault the verdict names may bend
        them (:attr:`yielded_to`): not grown."""
        return bool(self.yielded_to)

    @property
    def grown(self) -> bool:
        return self.used_gyro > self.stated_gyro or self.used_accel > self.stated_accel

    @property
    def scales(self) -> tuple[float, float]:
        """(gyro, accelerometer) the walks used over the stated."""
        return self.used_gyro / self.stated_gyro, self.used_accel / self.stated_accel

    def to_dict(self) -> dict:
        return {"stated_gyro": self.stated_gyro, "stated_accel": self.stated_accel,
                "ratio_gyro": self.ratio_gyro, "ratio_accel": self.ratio_accel,
                "chi2": list(self.chi2), "expected": list(self.expected),
                "chi2_bound": list(self.chi2_bound),
                "n_steps": self.n_steps, "used_gyro": self.used_gyro,
                "used_accel": self.used_accel, "grown": self.grown,
                "final_ratios": list(self.final_ratios), "bound_scale": self.bound_scale,
                "held": self.held, "rounds": self.rounds, "time_s": self.time_s,
                "yielded_to_imu_bias": "imu_bias" in self.yielded_to,
                "yielded_to": [str(code) for code in self.yielded_to]}


@dataclass(frozen=True)
class BroadMapError:
    """How far the map's error tilts and curves across each frame's footprint, over
    kilometres (:func:`cdtm_graph.robust.map_error.broad_map_error`): a hill or a hollow
    the DTM lacks, whose mean the estimate takes as its own height while the map's
    sigma_h, counted per feature, averages it away.

    Attributes:
        shape_chi2: (K,) the Wald statistic (chi-square(3) without such error) of the tilt
            and the isotropic curvature of a smooth surface fitted to the tracks' heights
            above the DTM over their ground points, the tracks of the frame's window
            (scaled by the window's own scatter; the tilt an attitude error gives
            counted); NaN where not judged (a window cut by the flight's ends, too few
            tracks).
        evidence: (K,) its mean over the frames of a few seconds about the frame (NaN
            unless all were judged): what the verdict reads.
        tilt_m: (K,) how far the surface's tilt moves the heights 1 km from the window's
            centre (m).
        bend_m: (K,) the same of its curvature (m).
        n_tracks: (K,) the tracks the window's fit rests on.
    """

    shape_chi2: np.ndarray
    evidence: np.ndarray
    tilt_m: np.ndarray
    bend_m: np.ndarray
    n_tracks: np.ndarray

    def to_dict(self) -> dict:
        judged = np.isfinite(self.evidence)
        if not judged.any():
            return {"n_frames_judged": 0, "max_evidence": None, "max_evidence_frame": None,
                    "tilt_m_there": None, "bend_m_there": None}
        k = int(np.nanargmax(self.evidence))
        return {"n_frames_judged": int(judged.sum()), "max_evidence": float(self.evidence[k]),
                "max_evidence_frame": k, "tilt_m_there": float(self.tilt_m[k]),
                "bend_m_there": float(self.bend_m[k])}


@dataclass(frozen=True)
class ConsideredPrincipalPoint:
    """What the declared principal point's uncertainty added to the run's covariances
    (report.json ``considered_principal_point``;
    :mod:`cdtm_graph.calibration.considered`).

    Attributes:
        sigma_px: flight.yaml's ``camera.principal_point_sigma_px``.
        pose_cov_added: (K, 6, 6) what each frame's pose covariance got (body frame, as
            :class:`StateCovariances`).
        frames_solved: how many frames the solve held (the others interpolated).
        time_s: its cost.
    """

    sigma_px: float
    pose_cov_added: np.ndarray
    frames_solved: int
    time_s: float

    @property
    def position_sigma_m(self) -> np.ndarray:
        """(K,) each frame's largest position 1-sigma the term adds alone (m)."""
        return np.sqrt(np.linalg.eigvalsh(self.pose_cov_added[:, 3:, 3:])[:, -1].clip(0.0))

    def position_cov_world(self, k: int, world_T_body: np.ndarray) -> np.ndarray:
        """(3, 3) what frame k's position covariance got, in world axes, at its pose."""
        R = world_T_body[:3, :3]
        return R @ self.pose_cov_added[k, 3:, 3:] @ R.T

    def to_dict(self) -> dict:
        s = self.position_sigma_m
        ok = s[np.isfinite(s)]
        return {"sigma_px": self.sigma_px, "frames_solved": self.frames_solved,
                "position_sigma_added_m": {
                    "median": float(np.median(ok)) if ok.size else None,
                    "max": float(ok.max()) if ok.size else None},
                "time_s": self.time_s}


@dataclass(frozen=True)
class ConvergenceCheck:
    """One more solve from a run's estimate: how far it moves the positions against the
    run's own covariance (:func:`cdtm_graph.smoother.convergence.check_convergence`; made
    when the run's solver did not report convergence, read by the verdict's
    ``not_converged`` rule).

    Attributes:
        frames: (F,) the frames solved (every n-th of a long log).
        move_m: (F,) how far each frame's position moved (m).
        move_nees: (F,) the move's squared Mahalanobis distance in the run's position
            covariance (:func:`position_move_nees`; NaN without a covariance).
        converged: whether the extra solve itself converged.
        time_s: its cost.
    """

    frames: np.ndarray
    move_m: np.ndarray
    move_nees: np.ndarray
    converged: bool
    time_s: float

    def to_dict(self) -> dict:
        finite = self.move_nees[np.isfinite(self.move_nees)]
        return {"n_frames": int(self.frames.size),
                "max_move_m": float(np.max(self.move_m)) if self.move_m.size else None,
                "median_move_m": float(np.median(self.move_m)) if self.move_m.size else None,
                "max_move_nees": float(np.max(finite)) if finite.size else None,
                "median_move_nees": float(np.median(finite)) if finite.size else None,
                "n_frames_with_covariance": int(finite.size),
                "converged": self.converged, "time_s": self.time_s}


@dataclass(frozen=True)
class SmootherResult:
    """Everything a smoothing run produced (``smooth(...)`` or the incremental smoother).

    Attributes:
        estimate: smoothed per-frame states.
        covariances: marginal covariances per frame.
        stats: solver statistics.
        counts: graph contents.
        settings: the settings used, as a plain dict (for report.json).
        flags: per-frame warnings, e.g. ``{12: [Code.NO_FEATURES]}``.
        cdtm_information: (K, 6, 6) what the C-DTM features ending at each frame say
            about where the aircraft is, at the solution: the information their whitened,
            robustly weighted rows give a rigid motion of the poses they tie (the relative
            motion held, which the IMU knows too), order [rotation, translation], world
            axes, about the frame's body position (:func:`cdtm_graph.graph.
            cdtm_information`). Its eigen-structure over a window of frames names a weak
            geometry (flat terrain, few features, a narrow footprint:
            :mod:`cdtm_graph.verdict.rules`).
        terrain: the ground against the DTM (clutter), when the smoother looked.
        calibration: the camera calibration estimated online
            (:class:`cdtm_graph.calibration.online.CalibrationEstimate`), when it was.
        calibration_check: a run that held flight.yaml's calibration (the default, and
            the incremental modes always): what a batch side solve estimating it found
            (:class:`cdtm_graph.calibration.check.CalibrationCheck`), unless the
            settings hold it unchecked.
        map_offset: flight.yaml's sigmas of an offset of the whole map, in
            ``covariances``.
        bias_prior: flight.yaml's IMU bias prior, which the verdict holds the bias
            estimates against (``None``: not checked).
        position_prior: flight.yaml's prior on the first frame's position, which the
            verdict holds that frame's estimate against (``None``: not checked).
        stages: what each defence left out (features, by reason) and its time: the
            per-frame stages in order, then the work charged apart (the track tests'
            rounds, the fix search's verdicts); they add up to ``counts.rejected_per_frame``
            (:meth:`cdtm_graph.robust.stages.Stages.summary`).
        convergence_check: a run whose solver did not report convergence: how far one
            more batch solve from its estimate moves it (:class:`ConvergenceCheck`).
        map_error: the DTM's height error the tracks showed at the run's estimate, and
            the sigma_h the run was made with (:class:`MapErrorEstimate`); None when not
            estimated.
        imu_random_walk: flight.yaml's IMU bias random walks against the bias steps of a
            side solve, and the walks the run was made with (:class:`RandomWalkEstimate`);
            None when not checked.
        broad_map_error: the map's smooth error across each frame's footprint, from the
            tracks at the run's estimate (:class:`BroadMapError`); None when not looked at.
        broad_map_error_whole: a fixed lag's: the same read at the calibration check's
            batch solve of the whole flight (its own is read at the poses its window held,
            as it goes); the verdict names either. None otherwise.
        considered_principal_point: what flight.yaml's declared principal-point
            uncertainty added to ``covariances`` (:class:`ConsideredPrincipalPoint`); None
            when it declares none.
    """

    estimate: TrajectoryEstimate
    covariances: StateCovariances
    stats: SolverStats
    counts: GraphCounts
    settings: dict = field(default_factory=dict)
    flags: dict = field(default_factory=dict)
    cdtm_information: np.ndarray | None = None
    terrain: TerrainFindings | None = None
    calibration: CalibrationEstimate | None = None
    calibration_check: CalibrationCheck | None = None
    map_offset: MapOffset = field(default_factory=MapOffset)
    bias_prior: BiasPrior | None = None
    position_prior: PositionPrior | None = None
    stages: tuple[dict, ...] = ()
    convergence_check: ConvergenceCheck | None = None
    map_error: MapErrorEstimate | None = None
    imu_random_walk: RandomWalkEstimate | None = None
    broad_map_error: BroadMapError | None = None
    broad_map_error_whole: BroadMapError | None = None
    considered_principal_point: ConsideredPrincipalPoint | None = None

    def initial_position_conflict(self) -> PriorConflict | None:
        """flight.yaml's position prior against the first frame's estimate
        (:meth:`PositionPrior.conflict`; None: nothing to test). A fixed lag's against
        the calibration check's first frame, the whole flight's view of it, when the check
        made one (:attr:`~cdtm_graph.calibration.check.CalibrationCheck.first_frame`): the
        lag's own is the window's it left, where the prior holds most of the frame (20 m
        off at 2 m read 3.2-4.3 sigma there, 1 of 3 named)."""
        if self.position_prior is None or len(self.estimate) == 0:
            return None
        world_T_body, pose_cov = self.estimate.world_T_body[0], self.covariances.pose[0]
        check = self.calibration_check
        considered = self.considered_principal_point
        if check is not None and check.first_frame is not None:
            world_T_body, first_cov = check.first_frame
            pose_cov = self.map_offset.added_to_pose(first_cov, world_T_body)
            if considered is not None:
                pose_cov = pose_cov + considered.pose_cov_added[0]
        # (a declared principal point's share, as the map's offset: the data's fix carries
        # it, the prior does not)
        offset = self.map_offset.covariance_world()
        if considered is not None:
            offset = offset + considered.position_cov_world(0, world_T_body)
        return self.position_prior.conflict(world_T_body, pose_cov, offset)


def frame_flags(counts: GraphCounts, extra: dict[int, list[str]] | None = None
                ) -> dict[int, list[str]]:
    """Per-frame warnings from what went into the graph: ``{k: [Code.NO_FEATURES]}``, with
    the smoother's own (``extra``, e.g. ``no_fix`` while the fix was not acquired)."""
    flags: dict[int, list[str]] = {k: list(v) for k, v in (extra or {}).items()}
    for k in range(1, counts.n_frames):
        if counts.features_per_frame[k] == 0:
            flags.setdefault(k, []).append(Code.NO_FEATURES)
    return dict(sorted(flags.items()))


def pose_covariance_in_world(world_T_body: np.ndarray, pose_cov: np.ndarray
                             ) -> tuple[np.ndarray, np.ndarray]:
    """World-frame orientation and position covariances from body-frame tangent ones.

    A right perturbation ``[omega, v]`` moves the orientation by ``R omega`` and the
    position by ``R v`` (world frame), so each 3x3 block is rotated by ``R``.

    Args:
        world_T_body: (K, 4, 4). pose_cov: (K, 6, 6).

    Returns:
        ``(orientation_cov, position_cov)``, (K, 3, 3) each, rad^2 and m^2.
    """
    R = world_T_body[:, :3, :3]
    Rt = np.swapaxes(R, 1, 2)
    return R @ pose_cov[:, :3, :3] @ Rt, R @ pose_cov[:, 3:, 3:] @ Rt
