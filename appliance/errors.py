"""Every error the appliance raises on purpose, by phase, under one root: :class:`ApplianceError`.

Device-phase errors are defined in ``drivers.errors`` (the layer that raises them) and re-exported.
"""
from __future__ import annotations

from drivers.errors import (  # noqa: F401  (re-exported)
    ApplianceError,
    DeviceBusyError,
    DeviceError,
    DeviceFaultError,
    DeviceNotFoundError,
    DevicePermissionError,
    DeviceTimeoutError,
    InputDataError,
    LinkLostError,
    ProtocolError,
)


class ConfigError(ApplianceError, ValueError):
    """A config file is missing, unreadable or invalid; the message names the file and key path."""


class CalibrationError(ApplianceError, ValueError):
    """A calibration file or a calibration computation is invalid or degenerate."""


class TrackingError(ApplianceError):
    """The robot could not be recognised (used where a caller needs an exception, not a record)."""
