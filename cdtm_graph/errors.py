"""One exception tree for the whole package.

The CLI catches :class:`CdtmError` and prints its message as one line (exit 1);
anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import os
from pathlib import Path


class CdtmError(Exception):
    """Base of every error a user can cause (bad input, unobservable problem)."""


def why_not_a_file(path: str | os.PathLike) -> str:
    """What stands at ``path`` where a file was expected, for a one-line message.

    Returns:
        ``"is a directory, not a file"``, ``"is not a regular file (...)"`` or
        ``"does not exist"``.
    """
    path = Path(path)
    if path.is_dir():
        return "is a directory, not a file"
    if os.path.lexists(path):
        return "is not a regular file (a broken link, a FIFO, a device)"
    return "does not exist"


def why_not_a_directory(path: str | os.PathLike) -> str:
    """What stands at ``path`` where a directory was expected: ``"is a file, not a
    directory"``, ``"is not a directory"`` or ``"does not exist"``."""
    path = Path(path)
    if path.is_file():
        return "is a file, not a directory"
    if os.path.lexists(path):
        return "is not a directory (a broken link, a FIFO, a device)"
    return "does not exist"


class DtmError(CdtmError):
    """A DTM file or array is malformed or unreadable."""


class FlightLogError(CdtmError):
    """A flight log violates ``cdtm-flightlog/1`` (file, line and expectation in the message)."""


class DegenerateGeometryError(CdtmError):
    """The geometry cannot fix the pose: flat terrain, narrow FOV, few features, tiny baseline.

    Attributes:
        reasons: machine-readable names of every degeneracy detected
            (``"flat_terrain"``, ``"narrow_fov"``, ``"few_features"``, ``"short_baseline"``,
            ``"ill_conditioned"``).
    """

    def __init__(self, message: str, reasons: tuple[str, ...] = ()):
        super().__init__(message)
        self.reasons = tuple(reasons)


class SensorDataError(CdtmError):
    """Sensor recordings (a EuRoC folder, a ROS bag) cannot become a flight log: a topic
    or file is missing, a message is of the wrong type, the initial state is unknown."""


class ImageError(CdtmError):
    """An image cannot be used: unreadable, missing, of the wrong size or type."""


class SolverError(CdtmError):
    """The optimizer failed (indeterminate system, divergence); the message names the variable."""


class SimulationError(CdtmError):
    """The simulation settings or terrain cannot give a valid flight log."""


class OutputError(CdtmError):
    """An output path cannot be written safely: it is the input, a file, someone else's
    folder, or not writable. Nothing was written, deleted or replaced."""


class NoConstraintError(CdtmError):
    """The log gives the smoother no camera or DTM constraint at all (no tracks, no feature
    seen twice, or a DTM that no observed ray meets): the result would be IMU-only."""
