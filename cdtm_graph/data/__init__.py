"""Files the commands need, shipped inside the package (read through importlib.resources).

- ``sample_flight/``: the simulated flight log of ``cdtm demo`` and the README's library
  example (``scripts/make_sample_log.py`` regenerates it);
- ``sample_images/``: a tiny rendered flight, 4 frames with images
  (``scripts/make_sample_images.py``);
- ``geoid/egm96_15.tif``: the EGM96 15' geoid grid PROJ reads offline (``geoid/README.md``).

The functions return real filesystem paths wherever the package is installed (a wheel,
an editable install, the checkout): the readers, PROJ and GDAL take paths, not streams.
"""

from __future__ import annotations

import atexit
import contextlib
from importlib import resources
from pathlib import Path

__all__ = ["egm96_grid_file", "sample_flight_path", "sample_images_path"]

#: Holds the resources :func:`importlib.resources.as_file` had to extract (a zipped
#: install) until the interpreter exits; a package on disk is used where it lies.
_EXTRACTED = contextlib.ExitStack()
atexit.register(_EXTRACTED.close)


def _resource_path(*parts: str) -> Path:
    resource = resources.files(__name__).joinpath(*parts)
    return Path(_EXTRACTED.enter_context(resources.as_file(resource)))


def sample_flight_path() -> Path:
    """The bundled sample flight log (40 frames, 200 Hz IMU, ground truth, a DTM)."""
    return _resource_path("sample_flight")


def sample_images_path() -> Path:
    """The bundled rendered flight (4 frames with images, 200 Hz IMU, ground truth)."""
    return _resource_path("sample_images")


def egm96_grid_file() -> Path:
    """The bundled EGM96 15' geoid grid (GeoTIFF)."""
    return _resource_path("geoid", "egm96_15.tif")
