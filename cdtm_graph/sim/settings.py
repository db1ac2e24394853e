"""Settings of the simulation harness that the command line shows, in a module that imports
no numerics (``cdtm simulate --help`` shows their defaults without loading the simulator):
:class:`NavMode`, :class:`RenderSettings`, and the numbers of the paper's nominal flight
(section VI.A) that :class:`~cdtm_graph.sim.simulate.SimulationSettings` defaults to (its
other defaults and its checks stay with it: they need the camera and the IMU models).
Re-exported by :mod:`~cdtm_graph.sim.simulate` and :mod:`~cdtm_graph.sim.render`.
"""

from __future__ import annotations

import enum
import math
import numbers
from dataclasses import dataclass
from typing import TYPE_CHECKING

from cdtm_graph.errors import SimulationError

if TYPE_CHECKING:
    import numpy as np

#: The nominal flight: altitude above the terrain's mean height (m), the paper's 1000 m.
NOMINAL_ALTITUDE_M = 1000.0
#: Ground speed (m/s), the paper's 200.
NOMINAL_SPEED_MPS = 200.0
#: Camera frames of a simulated log, and their rate (Hz).
NOMINAL_FRAMES = 60
NOMINAL_FPS = 1.0
#: Image (width, height), pixels.
NOMINAL_RESOLUTION_PX = (400, 400)
#: Features per consecutive frame pair (the paper: 100-170).
NOMINAL_FEATURES = 170
#: Grid spacing of the log's DTM (m), the paper's 30 m.
NOMINAL_DTM_SPACING_M = 30.0
#: Relief (max - min) of the fractal terrain cell (m), the paper's 300 m.
NOMINAL_RELIEF_M = 300.0
#: The one seed of a simulation's random draws unless one is given.
DEFAULT_SEED = 0


class NavMode(enum.Enum):
    """Whether and how the simulated log gets a nav.csv (an external navigation solution)."""

    NONE = "none"                    # no nav.csv
    DEAD_RECKONING = "deadreckoning"  # IMU-only propagation from the initial-state prior
    NOISY_TRUTH = "noisy_truth"      # the true state plus white noise per frame


@dataclass(frozen=True)
class RenderSettings:
    """How images are made (module docstring).

    Attributes:
        sun_azimuth_deg: compass direction the sunlight comes from (0 = north, 90 = east).
        sun_elevation_deg: sun elevation above the horizon (deg), in (0, 90].
        ambient: share of the light that does not depend on the normal, in [0, 1].
        exposure: digital numbers per unit radiance divided by 255 (1: an albedo-1 surface
            facing the sun saturates exactly).
        exposure_jitter: relative exposure change per frame, drawn uniformly in
            ``[-jitter, +jitter]`` (0.1: +-10 %).
        motion_blur_px: length of a linear motion blur along each frame's image motion (px).
        noise_sigma_dn: Gaussian sensor noise (8-bit digital numbers).
        seed: seeds the sensor noise and the exposure draws.
    """

    sun_azimuth_deg: float = 135.0
    sun_elevation_deg: float = 45.0
    ambient: float = 0.3
    exposure: float = 1.0
    exposure_jitter: float = 0.0
    motion_blur_px: float = 0.0
    noise_sigma_dn: float = 1.0
    seed: int = 0

    def __post_init__(self) -> None:
        checks = {
            "sun_elevation_deg": 0 < self.sun_elevation_deg <= 90,
            "ambient": 0 <= self.ambient <= 1,
            "exposure": 0 < self.exposure < math.inf,
            "exposure_jitter": 0 <= self.exposure_jitter < 1,
            "motion_blur_px": 0 <= self.motion_blur_px < 64,
            "noise_sigma_dn": 0 <= self.noise_sigma_dn < math.inf,
            "sun_azimuth_deg": math.isfinite(self.sun_azimuth_deg),
        }
        expected = {"sun_elevation_deg": "in (0, 90]", "ambient": "in [0, 1]",
                    "exposure": "> 0", "exposure_jitter": "in [0, 1)",
                    "motion_blur_px": "in [0, 64)", "noise_sigma_dn": ">= 0",
                    "sun_azimuth_deg": "finite"}
        for name, ok in checks.items():
            if not ok:
                raise SimulationError(f"render {name} = {getattr(self, name)!r}, "
                                      f"expected {expected[name]}")
        if not (isinstance(self.seed, numbers.Integral) and self.seed >= 0):
            raise SimulationError(f"render seed = {self.seed!r}, expected an integer >= 0")

    @property
    def sun_world(self) -> np.ndarray:
        """(3,) unit vector toward the sun in world ENU."""
        import numpy as np

        az, el = math.radians(self.sun_azimuth_deg), math.radians(self.sun_elevation_deg)
        return np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)])
