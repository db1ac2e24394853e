"""Which solver a run uses, in a module that imports no numerics (``cdtm smooth --mode``
reads it without loading GTSAM)."""

from __future__ import annotations

import enum


class SmootherMode(enum.Enum):
    """Which solver a run uses."""

    BATCH = "batch"              # Levenberg-Marquardt over the whole log
    INCREMENTAL = "incremental"  # iSAM2, one update per frame (fixed lag with ``lag_s``)
