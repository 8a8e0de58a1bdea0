"""The appliance's error root and the errors raised while talking to devices.

The root lives in the lowest layer that raises it so that layers point one way; the appliance adds
its own phases (config, calibration, tracking) in ``appliance.errors`` and re-exports these.
"""
from __future__ import annotations


class ApplianceError(Exception):
    """Root of every error the appliance raises on purpose."""


class DeviceError(ApplianceError):
    """A device could not be opened, initialised or operated."""


class DeviceNotFoundError(DeviceError, FileNotFoundError):
    """The named port, address or USB device does not exist."""


class DeviceBusyError(DeviceError):
    """The device exists but another process holds it."""


class DevicePermissionError(DeviceError, PermissionError):
    """The operating system refused access to the device (udev rules, group membership)."""


class DeviceFaultError(DeviceError):
    """The device reports a fault (over-temperature, over-current, e-stop, watchdog...)."""


class LinkLostError(DeviceError, ConnectionError):
    """An established link stopped working (cable pulled, peer closed)."""


class DeviceTimeoutError(DeviceError, TimeoutError):
    """A device did not answer within its deadline."""


class ProtocolError(DeviceError):
    """Bytes on a link that break the protocol: framing, CRC, or an unexpected reply."""


class InputDataError(ApplianceError, ValueError):
    """Recorded input such as a frame folder or an image file is missing, unreadable or inconsistent."""
