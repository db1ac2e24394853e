"""The accuracy map's choices and limits, in a module that imports no numerics (``cdtm
accuracy-map --help`` states them without loading the closed form). Re-exported by
:mod:`~cdtm_graph.analysis.accuracy_map`, which checks its settings against them.
"""

from __future__ import annotations

import enum

#: Most features per pair (each node casts three times as many rays).
MAX_FEATURES = 100_000
#: Most nodes of a map (1000 x 1000; 40 x 40 by default): a finer --step-m is a typo.
MAX_NODES = 1_000_000
#: Image sides (px), as flight.yaml's camera.resolution.
RESOLUTION_RANGE_PX = (2, 100_000)
#: Headings (deg) accepted: one turn either way.
MAX_ABS_HEADING_DEG = 360.0
#: The rotation between a pair's frames (deg): an angle of one rotation, at most a half turn.
MAX_ROTATION_DEG = 180.0


class AltitudeReference(enum.Enum):
    """What ``altitude_m`` is measured from."""

    MEAN_TERRAIN = "mean"  # the DTM's mean height: constant-altitude flight (the paper's)
    GROUND = "ground"  # the DTM height right below the first camera
