"""Custom GTSAM factors of cdtm-graph: pure math on numpy + gtsam.

This package never imports ``cdtm_graph``: the DTM enters only as arrays (tangent
planes) or as a ray-casting callable.
"""

from factors.cdtm_factor import (
    CdtmPairFactor,
    FeatureNoise,
    PairFeatures,
    PlaneMode,
    RayCaster,
    RobustKernel,
    make_feature_factors,
)

__all__ = [
    "CdtmPairFactor",
    "FeatureNoise",
    "PairFeatures",
    "PlaneMode",
    "RayCaster",
    "RobustKernel",
    "make_feature_factors",
]
