"""Constants and small formulas every part of the package shares, in one place.

Time units, standard gravity, chi-square quantiles and a fast median. The quantiles come from
``scipy.special`` (``chi2.ppf``'s own formula, bit for bit), not ``scipy.stats``, whose
import alone costs seconds at start-up.
"""

from __future__ import annotations

import math

import numpy as np

#: Nanoseconds per second: every time in the package is an integer ``t_ns``.
NS_PER_S = 1_000_000_000

#: Standard gravity (m/s^2): the default where flight.yaml states none and no geodetic
#: origin gives WGS84 normal gravity.
STANDARD_GRAVITY_MPS2 = 9.80665


def chi2_quantile(probability: float | np.ndarray, dof: float | np.ndarray) -> np.ndarray:
    """The ``probability`` quantile of chi-square with ``dof`` degrees of freedom
    (``scipy.stats.chi2.ppf``, the same formula: ``2 P^-1(dof / 2, p)``); broadcasts."""
    from scipy.special import gammaincinv  # (a numerics import: not at package import)

    return 2.0 * gammaincinv(np.asarray(dof, float) / 2.0, probability)


def chi2_2dof_quantile(p: float) -> float:
    """The p-quantile of chi-square with 2 degrees of freedom: ``-2 ln(1 - p)``."""
    if not 0.0 < p < 1.0:
        raise ValueError(f"gate probability {p}: expected 0 < p < 1")
    return float(-2.0 * math.log1p(-p))


def median(x: np.ndarray) -> float:
    """``np.median`` of a non-empty 1-d array, bit for bit, by one partition (a tenth of
    its cost: the gate's spread per frame, the map error's solve)."""
    lo, hi = (x.size - 1) // 2, x.size // 2
    part = np.partition(x, (lo, hi, x.size - 1))
    if np.isnan(part[-1]):  # NaNs sort last
        return float("nan")
    return float(0.5 * (part[lo] + part[hi]))
