"""Custom GTSAM factors of cdtm-graph: pure math on numpy + gtsam.

This package never imports ``cdtm_graph``: the DTM enters only as arrays (tangent
planes) or as a ray-casting callable.

The named choices (:mod:`factors.modes`) are loaded with the package; the factors
(:mod:`factors.cdtm_factor`, GTSAM and numba) on first use of one of their names, so that
the command line offers ``--plane`` and ``--robust`` without loading the numerics.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from factors.modes import PlaneMode, RobustKernel

if TYPE_CHECKING:
    from factors.cdtm_factor import (
        CdtmPairFactor,
        FeatureNoise,
        PairFeatures,
        RayCaster,
        make_feature_factors,
    )

#: The names loaded on first use, from :mod:`factors.cdtm_factor`.
_LAZY = frozenset({"CdtmPairFactor", "FeatureNoise", "PairFeatures", "RayCaster",
                   "make_feature_factors"})

__all__ = [
    "CdtmPairFactor",
    "FeatureNoise",
    "PairFeatures",
    "PlaneMode",
    "RayCaster",
    "RobustKernel",
    "make_feature_factors",
]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        from factors import cdtm_factor

        return getattr(cdtm_factor, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
