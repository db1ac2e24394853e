"""The factors' named choices, in a module that imports no numerics.

:class:`PlaneMode` and :class:`RobustKernel` are what ``cdtm smooth --plane/--robust``
offer: the command line reads them here without loading GTSAM or numba (the package's
``__init__`` loads :mod:`factors.cdtm_factor` only when one of its names is asked for).
"""

from __future__ import annotations

import enum
from typing import Any


class PlaneMode(enum.Enum):
    """How a factor holds the DTM tangent plane of each feature."""

    FIXED = "fixed"
    REINTERSECT = "reintersect"


class RobustKernel(enum.Enum):
    """M-estimators applied per feature to the whitened 2-vector residual norm."""

    NONE = "none"
    HUBER = "huber"
    CAUCHY = "cauchy"
    TUKEY = "tukey"

    @property
    def default_threshold(self) -> float:
        """Thresholds of ~98% asymptotic efficiency for a 2-D Gaussian residual (the
        norm of the 2-vector, in units of its spread): Huber 2.0 (98.3%), Cauchy 4.0
        (98.5%), Tukey 6.5 (98.1%). The 1-D "95%" values (1.345, 2.385, 4.685) give 93-94%
        in 2-D and down-weight more inliers than needed."""
        return {"none": 0.0, "huber": 2.0, "cauchy": 4.0, "tukey": 6.5}[self.value]

    @property
    def kernel_id(self) -> int:
        """The numba kernels' code of this estimator (:mod:`factors.kernel`)."""
        from factors.kernel import KERNEL_CAUCHY, KERNEL_HUBER, KERNEL_NONE, KERNEL_TUKEY

        return {"none": KERNEL_NONE, "huber": KERNEL_HUBER, "cauchy": KERNEL_CAUCHY,
                "tukey": KERNEL_TUKEY}[self.value]

    def gtsam_estimator(self, threshold: float):
        """The equivalent ``gtsam.noiseModel.mEstimator`` (``None`` for NONE)."""
        if self is RobustKernel.NONE:
            return None
        import gtsam

        m = gtsam.noiseModel.mEstimator
        estimator: Any = {"huber": m.Huber, "cauchy": m.Cauchy, "tukey": m.Tukey}[self.value]
        return estimator.Create(threshold)
