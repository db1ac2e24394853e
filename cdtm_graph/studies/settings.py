"""The studies' settings the command line shows, in a module that imports no numerics
(``cdtm study --help`` and ``cdtm navsim --help`` without loading the simulator or the
smoothers): :class:`StudyParameter`, the swept parameter of ``cdtm study`` (what each
sweeps: :data:`cdtm_graph.studies.sweeps.SWEEPS`), and the cases of the paper's
navigation simulation (Tables 1-2) that :class:`~cdtm_graph.studies.navsim.NavsimSettings`
defaults to. Re-exported by :mod:`~cdtm_graph.studies.sweeps` and
:mod:`~cdtm_graph.studies.navsim`.
"""

from __future__ import annotations

import enum

#: Table 1's columns: flight altitudes above the terrain's mean (m).
TABLE1_ALTITUDES_M = (700.0, 1000.0, 3000.0)
#: Table 2's columns: sides of the square image (px).
TABLE2_RESOLUTIONS_PX = (500, 1000, 4000)
#: The altitude of every Table 2 case (m).
TABLE2_ALTITUDE_M = 1000.0
#: Flight time of every case (s).
NAVSIM_DURATION_S = 300.0
#: Flight duration of ``cdtm navsim --quick`` (s): a minute, enough for Free to drift
#: tens of metres; seconds of computing per case.
QUICK_DURATION_S = 60.0
#: Distance flown between frames over the altitude.
BASELINE_PER_ALTITUDE = 0.2


def frame_interval_s(altitude_m: float, baseline_per_altitude: float,
                     speed_mps: float) -> float:
    """Time between frames at ``altitude_m`` (s): the baseline scales with altitude."""
    return baseline_per_altitude * altitude_m / speed_mps


class StudyParameter(enum.Enum):
    """The swept parameter (one paper figure each)."""

    FEATURES = "features"
    RESOLUTION = "resolution"
    GRID = "grid"
    RELIEF = "relief"
    BASELINE = "baseline"
    FOV = "fov"
