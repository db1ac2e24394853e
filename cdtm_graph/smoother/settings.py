"""Settings of a smoothing run: one object, one set of defaults, for batch and incremental."""

from __future__ import annotations

import enum
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

from cdtm_graph.graph import GraphSettings
from cdtm_graph.robust.acquisition import AcquisitionSettings
from cdtm_graph.smoother.modes import SmootherMode

#: ``progress(done, total)``: called once per frame on long runs.
Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class SmootherSettings:
    """Settings of a smoothing run.

    Attributes:
        graph: how factors are built (plane mode, robust kernel, IMU hold).
        mode: BATCH (LM over the whole log) or INCREMENTAL (iSAM2, one update per frame).
        max_iterations: LM iterations (batch).
        relative_error_tol: LM stops when the error decreases less than this, relatively.
        lag_s: incremental only: a fixed-lag smoother of this lag (seconds); ``None``
            keeps the full history in iSAM2.
        final_iterations: incremental only: relinearizing updates after the last frame
            (``IncrementalSmoother.finalize``) so the final estimate reaches the optimum;
            also the most a frame makes while the estimate settles from the prior (an
            acquired fix, an IMU gap) before its marginal is reported (0: it never
            settles, and every frame reports the prior's covariance carried by the IMU).
        marginals: compute per-frame marginal covariances (batch).
        keep_exit_covariances: fixed lag: keep each frame's pose, velocity and bias
            covariances as it leaves the window (about 1 ms per frame; an offline run
            wants them, a live system needs only the newest: set False); otherwise NaN
            for frames older than the lag.
        acquisition: when the prior (or the covariance after a long gap without camera
            constraints) is wider than the smoothers pull in, the fix is searched for
            first (:mod:`cdtm_graph.robust.acquisition`) on the newest frames, their features
            held back until it is found; ``None``: never search.
        innovation_gate: incremental modes (and the batch's incremental first pass): drop
            each C-DTM feature whose innovation, against the prior covariance of its two
            poses, fails the chi-square(2) gate of this probability; ``None`` gates
            nothing. At 0.999 a clean log loses ~0.1% of its features.
    """

    graph: GraphSettings = field(default_factory=GraphSettings)
    mode: SmootherMode = SmootherMode.BATCH
    max_iterations: int = 30
    relative_error_tol: float = 1e-6
    lag_s: float | None = None
    final_iterations: int = 5
    marginals: bool = True
    keep_exit_covariances: bool = True
    innovation_gate: float | None = 0.999
    acquisition: AcquisitionSettings | None = field(default_factory=AcquisitionSettings)

    def __post_init__(self) -> None:
        if self.lag_s is not None and not (math.isfinite(self.lag_s) and self.lag_s > 0):
            raise ValueError(f"SmootherSettings.lag_s = {self.lag_s!r}: expected a finite lag "
                             "> 0 seconds, or None for the full history")

    def to_dict(self) -> dict:
        """Plain values for report.json (enums as their values)."""
        d = asdict(self)
        d["mode"] = self.mode.value
        d["graph"] = {k: (v.value if isinstance(v, enum.Enum) else v)
                      for k, v in asdict(self.graph).items()}
        return d
