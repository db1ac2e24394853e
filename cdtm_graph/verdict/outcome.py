"""The verdict on a run, as data: its status, its reasons, its self-checks
(:func:`cdtm_graph.verdict.rules.assess` makes one; report.json and the CLI read it)."""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import Any

import numpy as np


def _finite(value: float) -> float | None:
    value = float(value)
    return value if math.isfinite(value) else None


class Status(enum.Enum):
    """How far a run's outputs can be trusted."""

    TRUSTED = "trusted"    # no weak stretch, every self-check inside its bounds
    DEGRADED = "degraded"  # outputs usable where not flagged; read the reasons
    FAILED = "failed"      # outputs written but not a navigation result

    @property
    def exit_code(self) -> int:
        """The CLI's: 0 trusted, 3 outputs written but degraded or failed."""
        return 0 if self is Status.TRUSTED else 3


@dataclass(frozen=True)
class Reason:
    """One reason a run is not trusted.

    Attributes:
        code: machine-readable (a frame flag, or a run-wide check such as
            ``residual_chi2``).
        message: what was seen and what it means, in words.
        first_frame, last_frame: frame indices of frames.csv the reason covers (the whole
            run for run-wide checks).
        status: what it makes the run (DEGRADED or FAILED).
        t_first_s, t_last_s: the same frames' times since the first frame (s).
    """

    code: str
    message: str
    first_frame: int
    last_frame: int
    status: Status
    t_first_s: float = 0.0
    t_last_s: float = 0.0

    def line(self) -> str:
        """One line for a terminal: ``degraded: flat_terrain, frames 31-56 (31.0-56.0
        s): ...``."""
        frames = (f"frame {self.first_frame}" if self.first_frame == self.last_frame else
                  f"frames {self.first_frame}-{self.last_frame}")
        return (f"{self.status.value}: {self.code}, {frames} ({self.t_first_s:.1f}-"
                f"{self.t_last_s:.1f} s): {self.message}")

    def to_dict(self) -> dict[str, Any]:
        return {"code": self.code, "message": self.message, "first_frame": self.first_frame,
                "last_frame": self.last_frame, "status": self.status.value,
                "t_first_s": self.t_first_s, "t_last_s": self.t_last_s}


@dataclass(frozen=True)
class SelfChecks:
    """Checks of the solution against its own noise model (no ground truth needed).

    Attributes:
        residual_chi2: residual chi-square of the features within the test over its
            expectation, whole run (~1 expected); NaN without features.
        residual_chi2_per_window: (K,) the same over each frame's window.
        outlier_fraction: share of features beyond the chi-square(2) 99.9% test.
        innovation_nis_median, innovation_nis_mean: of the innovations the incremental
            gate tested (NaN in batch runs).
        passed: every check inside its bounds.
    """

    residual_chi2: float
    residual_chi2_per_window: np.ndarray
    outlier_fraction: float
    innovation_nis_median: float
    innovation_nis_mean: float
    passed: bool

    def to_dict(self) -> dict[str, Any]:
        return {"residual_chi2": _finite(self.residual_chi2),
                "residual_chi2_per_window": [_finite(v) for v in self.residual_chi2_per_window],
                "outlier_fraction": _finite(self.outlier_fraction),
                "innovation_nis_median": _finite(self.innovation_nis_median),
                "innovation_nis_mean": _finite(self.innovation_nis_mean),
                "passed": self.passed}


@dataclass(frozen=True)
class Verdict:
    """The verdict on a run.

    Attributes:
        status: TRUSTED, DEGRADED or FAILED (the worst of the reasons').
        reasons: why it is not trusted, in frame order, run-wide checks first.
        flags: frame index -> the flags of that frame (every flagged frame, also on
            stretches too short to be a reason).
        self_checks: the checks without ground truth.
        notes: what the user should hear that is no reason to distrust the run (a noise
            model larger than the data's scatter).
    """

    status: Status
    reasons: tuple[Reason, ...]
    flags: dict[int, list[str]]
    self_checks: SelfChecks
    notes: tuple[str, ...] = ()

    def lines(self) -> list[str]:
        """One line per reason, then per note (what the CLI prints on stderr)."""
        return [r.line() for r in self.reasons] + [f"note: {n}" for n in self.notes]

    def to_dict(self) -> dict[str, Any]:
        return {"verdict": self.status.value,
                "reasons": [r.to_dict() for r in self.reasons],
                "notes": list(self.notes),
                "flags": {int(k): list(v) for k, v in self.flags.items()},
                "self_checks": self.self_checks.to_dict()}
