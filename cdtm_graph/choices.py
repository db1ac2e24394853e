"""Named choices of flight.yaml and the command line that the root modules use, in a module
that imports no numerics: ``cdtm simulate --distortion-model`` and ``cdtm import
--vertical-datum`` offer them without loading OpenCV or numpy. Re-exported where they are
used: :class:`DistortionModel` from :mod:`cdtm_graph.camera`, :class:`VerticalDatum` from
:mod:`cdtm_graph.geodesy` (which converts heights between datums:
:func:`~cdtm_graph.geodesy.ellipsoidal_height_m`).
"""

from __future__ import annotations

import enum


class DistortionModel(enum.Enum):
    """The lens distortion model (flight.yaml ``camera.distortion_model``, Kalibr's names)."""

    NONE = "none"
    RADTAN = "radtan"            # OpenCV k1 k2 p1 p2 [k3]
    EQUIDISTANT = "equidistant"  # OpenCV fisheye (Kannala-Brandt) k1 k2 k3 k4


class VerticalDatum(enum.Enum):
    """What a DEM's heights are measured from (``dtm.vertical_datum`` in flight.yaml).

    ELLIPSOID: WGS84 ellipsoidal heights (GNSS heights).
    EGM96: heights above the EGM96 geoid ("MSL"), as SRTM and Copernicus GLO-30 give them.
    """

    ELLIPSOID = "ellipsoid"
    EGM96 = "egm96"
