"""Acquisition: find the fix before refining it, when the prior is wider than the pull-in.

The smoothers linearize the C-DTM factors locally. A few DTM cells off, a feature's ray
meets other terrain, and iterating from a prior hundreds of metres wide can settle on
the wrong hill with a small covariance: the paper's analysis (section V.C) assumes an
initial fix within the linear range. :func:`acquire` searches first, on the first frames
of a flight (or the frames after a long gap in constraints):

1. **A point cloud per heading.** The frames' relative poses come from the IMU and are
   accurate; their absolute pose is off by the prior. Under each heading hypothesis the
   frames are re-propagated from a turned first state (:class:`Correction`) and every
   track is triangulated robustly (the pair of sightings most others agree with, then
   its inliers). The triangulation residuals score the heading: the rays' motion must
   match the baseline the IMU velocity gives (epipolar consistency).
2. **Terrain correlation** (TERCOM-like). For the headings the rays do not reject, the
   cloud is moved over a grid of horizontal offsets covering ``n_sigma`` of the prior; at
   each offset its vertical offset and tilt are fitted in closed form (robust IRLS) and
   its heights scored against the DTM with a truncated quadratic.
3. **Modes.** Local minima at least ``merge_radius_m`` apart; the best few are refined
   with the C-DTM factors themselves (every pair of sightings of every track; rotation,
   translation and velocity of the first state; truncated Levenberg-Marquardt under the
   prior, kept within half a merge radius of its mode).
4. **Decision** (:func:`separation_z`): per track, the difference of the robust costs
   of two fixes, tested by Vuong's test for non-nested models (the gain must be
   consistent across tracks) and by its likelihood ratio (the gain must be large).
   ACQUIRED when the best fix beats every other mode by ``separation_z`` standard
   errors; AMBIGUOUS when some tie (they are listed); NO_INFORMATION when too few tracks
   triangulate, or when the best offset does not beat a typical one by
   ``information_z`` (flat terrain, terrain unlike the DTM); AT_EDGE when the best fix
   refines out of the searched region (the truth may lie outside the prior).

Pure: no I/O, no smoother. The smoother calls :func:`needs_acquisition` on its prior (or
its covariance after a gap) and, when true, :func:`acquire` on the dead-reckoned frames,
then applies :attr:`AcquisitionResult.correction` to its first state.
"""

from cdtm_graph.robust.acquisition.search import (
    AcquisitionResult,
    FixVerdict,
    Hypothesis,
    SearchRegion,
    acquire,
    needs_acquisition,
    separation_z,
)
from cdtm_graph.robust.acquisition.settings import AcquisitionSettings
from cdtm_graph.robust.acquisition.window import (
    AcquisitionFrame,
    Correction,
    SearchPrior,
    dead_reckoned_window,
)

__all__ = [
    "AcquisitionFrame",
    "AcquisitionResult",
    "AcquisitionSettings",
    "Correction",
    "Hypothesis",
    "SearchPrior",
    "SearchRegion",
    "FixVerdict",
    "acquire",
    "dead_reckoned_window",
    "needs_acquisition",
    "separation_z",
]
