"""One vocabulary: every code a run's flags, reasons and notes carry, with what it means.

A code is a :class:`Code` member everywhere in the package (the smoothers that set a
frame's flag, the verdict's rules, the reports); being a ``str`` enum, it is written to
report.json and printed as its plain string (``"no_fix"``), so reports keep their
strings. ``Code.NO_FIX.text`` says what it means in words.

The features left out of the graph have their own enum,
:class:`~cdtm_graph.results.Rejection` (why one feature went); a frame flag says why a
frame is weak, a reason why a run is not trusted, a note what a user should hear that is
no reason to distrust it.
"""

from __future__ import annotations

import enum


class Kind(enum.Enum):
    """Where a code appears."""

    FRAME = "frame"  # a per-frame flag (a stretch of them may become a reason)
    RUN = "run"      # a run-wide reason
    NOTE = "note"    # a note: no reason to distrust the run
    FINDING = "finding"  # what the IMU check found in the samples (report.json imu_findings)


class Code(enum.StrEnum):
    """A flag, reason or note code, with its kind and its meaning."""

    kind: Kind
    text: str

    def __new__(cls, value: str, kind: Kind, text: str) -> Code:
        member = str.__new__(cls, value)
        member._value_ = value
        member.kind = kind
        member.text = text
        return member

    # -- per-frame flags: why a frame's fix is weak or missing -----------------------
    NO_FEATURES = ("no_features", Kind.FRAME,
                   "no C-DTM feature ends at the frame (tracks lost): the IMU alone")
    OFF_DTM = ("off_dtm", Kind.FRAME,
               "most of the frame's rays miss the DTM (the flight left the map)")
    FEW_FEATURES = ("few_features", Kind.FRAME, "few features per frame in the window")
    FLAT_TERRAIN = ("flat_terrain", Kind.FRAME,
                    "flat terrain: the horizontal position gets little information")
    NARROW_FOV = ("narrow_fov", Kind.FRAME,
                  "a narrow footprint: the horizontal position can barely be told from a tilt")
    MAP_MISMATCH = ("map_mismatch", Kind.FRAME,
                    "the ground points are not where the DTM says (terrain the map lacks)")
    HEAVY_REJECTION = ("heavy_rejection", Kind.FRAME,
                       "many features left out: the tracker's matches, the DTM or the IMU "
                       "disagree")
    IMU_GAP = ("imu_gap", Kind.FRAME, "IMU samples missing inside the frame's interval")
    RESIDUAL_MISFIT = ("residual_misfit", Kind.FRAME,
                       "the window's residual chi-square outside its band")
    BROAD_MAP_ERROR = ("broad_map_error", Kind.FRAME,
                       "the map's heights are off by a smooth surface over kilometres under "
                       "the footprint (a hill the DTM lacks): the altitude takes part of it, "
                       "which the covariance does not hold")
    CLUTTER = ("clutter", Kind.FRAME,
               "clutter the DTM lacks (forest, town) may bias the frame's height")
    NO_FIX = ("no_fix", Kind.FRAME,
              "the fix was not acquired: the prior is wider than the smoothers pull in, and "
              "the frame's sightings were held back")
    SEARCH_BEYOND_LAG = ("search_beyond_lag", Kind.FRAME,
                         "the covariance outgrew what the smoothers pull in (a long stretch "
                         "without camera constraints), but the fixed lag is shorter than the "
                         "fix search's window: the frames went on without a search for the "
                         "fix (a longer --lag-s searches)")
    # -- IMU findings (the samples themselves; an imu_gap also flags its frames) -------
    IMU_RATE_MISMATCH = ("imu_rate_mismatch", Kind.FINDING,
                         "the samples' median spacing is not 1 / imu.rate_hz")
    IMU_STUCK = ("imu_stuck", Kind.FINDING, "all six values repeated: a frozen sensor")
    IMU_SATURATED = ("imu_saturated", Kind.FINDING, "a channel held at its extreme value")
    IMU_TIME_ORDER = ("imu_time_order", Kind.FINDING, "a sample not after the one before")
    # -- run-wide reasons ---------------------------------------------------------------
    NOT_CONVERGED = ("not_converged", Kind.RUN, "the solver did not converge")
    MISFIT = ("misfit", Kind.RUN, "the solution does not fit its data")
    WRONG_FIX = ("wrong_fix", Kind.RUN,
                 "most of the terrain seen is not where the DTM says: the fix is wrong")
    RESIDUAL_CHI2 = ("residual_chi2", Kind.RUN,
                     "the features' residual chi-square is off its expectation")
    OUTLIERS = ("outliers", Kind.RUN, "too many features fail the chi-square test")
    INNOVATION_NIS = ("innovation_nis", Kind.RUN,
                      "the innovations' squared Mahalanobis distances are off chi-square(2)")
    CONFIDENTLY_WRONG = ("confidently_wrong", Kind.RUN,
                         "against ground truth, most errors lie beyond the 99.9% bound of "
                         "their covariance")
    OVERCONFIDENT = ("overconfident", Kind.RUN,
                     "against ground truth, the covariances are too small")
    MAP_ERROR = ("map_error", Kind.RUN,
                 "the tracks show the DTM's heights off by more than the run may grow its "
                 "stated sigma_h to")
    INITIAL_POSITION = ("initial_position", Kind.RUN,
                        "flight.yaml's initial position contradicts the data, and the first "
                        "frames lean on it")
    IMU_BIAS = ("imu_bias", Kind.RUN,
                "an IMU bias the run estimates lies beyond flight.yaml's prior")
    IMU_NOISE = ("imu_noise", Kind.RUN,
                 "the IMU samples scatter more than flight.yaml's noise densities")
    IMU_RANDOM_WALK = ("imu_random_walk", Kind.RUN,
                       "the IMU biases wander beyond flight.yaml's random walks, more than "
                       "the run may grow them")
    CALIBRATION_SUSPECT = ("calibration_suspect", Kind.RUN,
                           "the flight contradicts flight.yaml's camera calibration")
    # -- notes ----------------------------------------------------------------------------
    MAP_OFFSET_UNDECLARED = ("map_offset_undeclared", Kind.NOTE,
                             "flight.yaml does not say how far the whole map may be off")
    PRINCIPAL_POINT_CONSIDERED = ("principal_point_considered", Kind.NOTE,
                                  "flight.yaml's principal-point uncertainty is in the "
                                  "covariances: its share of them")
    CALIBRATION_UNOBSERVABLE = ("calibration_unobservable", Kind.NOTE,
                                "a calibration part this flight cannot tell")
    CALIBRATION_UNRESOLVED = ("calibration_unresolved", Kind.NOTE,
                              "the side solve tells the calibration poorly: the flight "
                              "cannot check it")
    CALIBRATION_HELD = ("calibration_held", Kind.NOTE,
                        "a significant correction the positions do not feel")
    CALIBRATION_CONFOUNDED = ("calibration_confounded", Kind.NOTE,
                              "a correction that another fault explains as well: the map's "
                              "shared error, the residuals' scatter, or a fault the verdict "
                              "names")
    INITIAL_POSITION_NOT_HELD = ("initial_position_not_held", Kind.NOTE,
                                 "flight.yaml's initial position contradicts the data, which "
                                 "hold the first frame without it")
    INITIAL_POSITION_CONFOUNDED = ("initial_position_confounded", Kind.NOTE,
                                   "flight.yaml's initial position contradicts the data, "
                                   "whose own fault the verdict names")
    MAP_ERROR_GROWN = ("map_error_grown", Kind.NOTE,
                       "the tracks show the DTM's heights worse than its stated sigma_h: "
                       "the run used theirs")
    IMU_RANDOM_WALK_GROWN = ("imu_random_walk_grown", Kind.NOTE,
                             "the bias steps show the IMU biases wandering beyond "
                             "flight.yaml's random walks: the run used grown ones")

    @classmethod
    def of(cls, value: str) -> Code | None:
        """The member whose string ``value`` is, or None (a code from elsewhere)."""
        return cls._value2member_map_.get(value)  # type: ignore[return-value]

    @property
    def fails(self) -> bool:
        """Whether this reason makes a run FAILED (the others make it DEGRADED)."""
        return self in FAILING


#: The reasons that make a run FAILED: an estimate that is not a navigation result.
FAILING = frozenset({Code.NOT_CONVERGED, Code.NO_FIX, Code.MISFIT, Code.WRONG_FIX,
                     Code.CONFIDENTLY_WRONG})
