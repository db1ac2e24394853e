"""Ground detail the DTM lacks, correlated over tens to hundreds of metres.

The simulator's own map error is the fractal remainder of resampling the true terrain to
the DTM's spacing: the very model the DTM's ``sigma_h`` is fitted to (the paper's Fig. 6).
A real DTM is wrong in other ways: detail between its posts that is not fractal, and
errors that hold over many posts, so that neighbouring features share them. A
:class:`MapDetail` adds such detail to the *true* ground only (made before features are
cast on it; the log's DTM does not know it), in one of three shapes:

* ``WAVES``: a sum of plane waves, wavelengths log-uniform in a band, random directions
  and phases; heights near-Gaussian.
* ``RIDGES``: the same waves folded (``|sin|``): rounded crests between sharp troughs,
  the variance at half the wavelengths (dunes, ploughed ridges, terraces).
* ``BUMPS``: round smooth bumps of random sizes in the band, random signs, overlapping
  (knolls and hollows, tree clumps); heavy-tailed.

Each is scaled to its ``rms_m`` over the grid it is added to.
"""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass

import numpy as np

from cdtm_graph.dtm import Dtm


class DetailShape(enum.Enum):
    WAVES = "waves"
    RIDGES = "ridges"
    BUMPS = "bumps"


@dataclass(frozen=True)
class MapDetail:
    """Detail the true ground has and the DTM lacks.

    Attributes:
        shape: the detail's shape (module docstring).
        rms_m: its root mean square height over the grid (m).
        wavelength_m: (shortest, longest) wavelength of the waves; for bumps, twice their
            radius (m).
        n_waves: waves summed, or bumps per square kilometre for ``BUMPS``.
        seed: the detail's own random layout.
    """

    shape: DetailShape = DetailShape.WAVES
    rms_m: float = 3.0
    wavelength_m: tuple[float, float] = (40.0, 300.0)
    n_waves: int = 24
    seed: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "shape", DetailShape(self.shape))
        short, long = self.wavelength_m
        if not (0.0 < short <= long) or self.rms_m < 0.0 or self.n_waves < 1:
            raise ValueError(f"map detail {self}: expected 0 < shortest <= longest "
                             "wavelength, rms_m >= 0 and n_waves >= 1")

    def to_dict(self) -> dict:
        out = dataclasses.asdict(self)
        out["shape"] = self.shape.value
        out["wavelength_m"] = list(self.wavelength_m)
        return out

    def heights(self, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
        """The detail's heights (m) on the grid of columns ``x_m`` (C,) and rows ``y_m``
        (R,): (R, C), scaled to ``rms_m`` over it."""
        rng = np.random.default_rng(self.seed)
        xx, yy = np.meshgrid(np.asarray(x_m, float), np.asarray(y_m, float))
        short, long = self.wavelength_m
        out = np.zeros(xx.shape)
        if self.shape is DetailShape.BUMPS:
            area_km2 = max(np.ptp(xx) * np.ptp(yy), 1.0) * 1e-6
            n = max(int(round(self.n_waves * area_km2)), 1)
            centres = np.column_stack([rng.uniform(xx.min(), xx.max(), n),
                                       rng.uniform(yy.min(), yy.max(), n)])
            radii = 0.5 * np.exp(rng.uniform(np.log(short), np.log(long), n))
            signs = rng.choice([-1.0, 1.0], n)
            for (cx, cy), r, s in zip(centres, radii, signs):
                box = (np.abs(xx[0] - cx) < 4 * r), (np.abs(yy[:, 0] - cy) < 4 * r)
                sub = np.ix_(box[1], box[0])
                d2 = (xx[sub] - cx) ** 2 + (yy[sub] - cy) ** 2
                out[sub] += s * np.exp(-0.5 * d2 / r**2)
        else:
            wavelengths = np.exp(rng.uniform(np.log(short), np.log(long), self.n_waves))
            azimuths = rng.uniform(0.0, np.pi, self.n_waves)
            phases = rng.uniform(0.0, 2.0 * np.pi, self.n_waves)
            for lam, az, ph in zip(wavelengths, azimuths, phases):
                wave = np.sin(2.0 * np.pi * (xx * np.cos(az) + yy * np.sin(az)) / lam + ph)
                out += np.abs(wave) if self.shape is DetailShape.RIDGES else wave
        out -= out.mean()
        rms = float(np.sqrt(np.mean(out**2)))
        return out * (self.rms_m / rms) if rms > 0.0 else out


def apply_map_detail(truth: Dtm, detail: MapDetail) -> Dtm:
    """The true terrain with the detail added (a new grid; ``truth`` is unchanged)."""
    rows, cols = truth.shape
    x = truth.x0 + np.arange(cols) * truth.dx
    y = truth.y0 + np.arange(rows) * truth.dy
    return Dtm(truth.elevation + detail.heights(x, y), truth.x0, truth.y0, truth.dx,
               truth.dy, sigma_h_m=truth.sigma_h_m)
