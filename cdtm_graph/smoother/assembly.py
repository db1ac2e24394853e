"""One result assembly for both smoothers: what every run reports beside its estimate.

The batch and the incremental smoothers differ in how they solve; what they report is
assembled here alike: the residual test at the solution, the clutter the features may
still hold (a considered vertical bias of the covariances, and its flags), an offset of
the whole map in every position covariance, the C-DTM fix information per frame, and the
frame flags.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from cdtm_graph.calibration.online import CalibrationEstimate
from cdtm_graph.flightlog import FlightConfig
from cdtm_graph.graph import cdtm_information
from cdtm_graph.results import (
    BiasPrior,
    BroadMapError,
    GraphCounts,
    MapOffset,
    PositionPrior,
    SmootherResult,
    SolverStats,
    StateCovariances,
    TrajectoryEstimate,
    frame_flags,
)
from cdtm_graph.robust.clutter import (
    Clutter,
    ClutterSettings,
    clutter_flags,
    findings,
    with_vertical_bias,
)
from cdtm_graph.robust.gating import residual_test
from factors import CdtmPairFactor


@dataclass(frozen=True)
class ClutterOutcome:
    """What the track tests' clutter view leaves a run: the latest fit, each frame's
    considered vertical offset (m, (K,)) and the settings that flag a frame."""

    clutter: Clutter
    offsets_m: np.ndarray
    settings: ClutterSettings


def assemble_result(config: FlightConfig, estimate: TrajectoryEstimate,
                    covariances: StateCovariances, stats: SolverStats, counts: GraphCounts,
                    settings: dict, flags: dict[int, list[str]],
                    factors: Sequence[CdtmPairFactor], clutter: ClutterOutcome | None,
                    calibration: CalibrationEstimate | None = None,
                    stages: Sequence[dict] = (),
                    broad_map_error: BroadMapError | None = None) -> SmootherResult:
    """A run's result from its estimate and what it solved with.

    Args:
        config: the log's flight.yaml (the map's offset, the IMU bias prior).
        estimate, covariances: the solution and its marginals (as solved).
        stats: the solver's. counts: what went into the graph (the residual test's fields
            are filled here). settings: the run's, for report.json.
        flags: the smoother's own frame flags (``no_fix``...).
        factors: the live C-DTM factors, as the poses alone see them (held at an estimated
            calibration).
        clutter: the clutter view's outcome, or None (no clutter view).
        calibration: the online calibration's estimate, when it was estimated.
        stages: what each defence left out, and its time (``Stages.summary``).
        broad_map_error: the map's shape across the footprints, when the run took it as it
            went (a fixed lag: :class:`~cdtm_graph.robust.map_error.BroadMapWatch`).
    """
    K = len(estimate)
    residuals = residual_test(factors, estimate.world_T_body, K)
    counts = replace(counts, n_outliers=residuals.n_outliers,
                     outliers_per_frame=residuals.outliers_per_frame,
                     residual_chi2_per_frame=residuals.chi2_within_per_frame)
    flags = {k: list(v) for k, v in flags.items()}
    terrain = None
    if clutter is not None:
        covariances = with_vertical_bias(covariances, estimate.world_T_body, clutter.offsets_m)
        terrain = findings(clutter.clutter, clutter.offsets_m)
        for k, v in clutter_flags(clutter.offsets_m, clutter.settings).items():
            flags.setdefault(k, []).extend(v)
    map_offset = MapOffset.of(config.dtm)
    return SmootherResult(estimate, map_offset.added_to(covariances, estimate.world_T_body),
                          stats, counts, settings, frame_flags(counts, flags),
                          cdtm_information(factors, estimate.world_T_body.__getitem__, K),
                          terrain, calibration, map_offset=map_offset,
                          bias_prior=BiasPrior.of(config),
                          position_prior=PositionPrior.of(config), stages=tuple(stages),
                          broad_map_error=broad_map_error)
