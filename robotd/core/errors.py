"""One exception root for robotd, with a subclass per concern.

Messages carry the numbers and the URL, path or key that failed, so a log line is enough to act on.
"""

from __future__ import annotations

import math
from typing import Any


class RobotdError(Exception):
    """Root of every error robotd raises on purpose."""


class ConfigError(RobotdError):
    """A configuration file or value is wrong (unknown key, wrong type, out of range)."""


class CalibrationError(RobotdError):
    """A calibration is missing, malformed or could not be computed."""


class InputError(RobotdError):
    """A message crossing a border (frame, odometry, observation) is malformed: shape, dtype, NaN."""


class DriverError(RobotdError):
    """A hardware or replay driver failed: unknown URL scheme, device missing, link lost."""


class ProtocolError(DriverError):
    """A wire frame (serial, MAVLink, recording) could not be decoded."""


class EstimatorError(RobotdError):
    """A filter reached a state it cannot continue from (non-finite covariance, no particles)."""


class SingularityError(EstimatorError):
    """A 3-D pose at pitch ±90° (the ZYX Euler singularity): the motion model cannot propagate it.
    No ground vehicle gets there; the pipeline resets the attitude (docs/reliability.md)."""


class PersistenceError(RobotdError):
    """A saved map or recording is corrupt, foreign or could not be written."""


class DatasetError(RobotdError):
    """A dataset folder or file does not have the expected layout."""


class MapMismatchError(PersistenceError):
    """A saved map that is valid but made for another configuration (filter, dimension, detector):
    it is kept, not moved aside as corrupt."""


def show_value(v: Any) -> str:
    """A value for an error message: its repr, shortened; a huge integer by its size (an error
    stays one readable line, and Python refuses to print integers of more than 4300 digits)."""
    if isinstance(v, int) and not isinstance(v, bool) and abs(v) >= 10**30:
        return f"an integer of {int(abs(v).bit_length() * math.log10(2)) + 1} digits"
    r = repr(v)
    return r if len(r) <= 80 else r[:77] + "..."
