"""One exception tree for the whole package.

The CLI catches :class:`CdtmError` and prints its message as one line (exit 1);
anything else is a bug and keeps its traceback.
"""

from __future__ import annotations


class CdtmError(Exception):
    """Base of every error a user can cause (bad input, unobservable problem)."""


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
