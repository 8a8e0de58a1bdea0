"""Open byte-stream transports from a URL, translating OS errors into appliance errors.

Drivers take the object this returns (a ``serial.SerialBase``); they never parse port strings.
Accepted forms are whatever pyserial's ``serial_for_url`` accepts: a device path (``/dev/ttyUSB0``,
a pty path such as ``/dev/pts/5``), ``socket://host:port``, ``loop://``; and the shorthand
``host:port`` / ``tcp://host:port`` for TCP.

A device path on POSIX opens as :class:`DirectWriteSerial`: pyserial's own port, whose ``write`` puts
the bytes out with one ``os.write`` when they all fit in the kernel's buffer. pyserial's ``write``
follows every write, even a complete one, with a ``select`` for writability and its timeout objects:
a second system call and ~20 Python operations on the path from the allocated currents to the coil
amplifier, measured at 4 us (min) to 20 us (p50) of the loop's CPU per command (issue 8). A partial
write, a full buffer or an error goes on through pyserial's ``write`` for the rest, with its write
timeout and its exceptions.
"""
from __future__ import annotations

import errno
import logging
import os
import re

import serial

from drivers.errors import (
    DeviceBusyError,
    DeviceError,
    DeviceNotFoundError,
    DevicePermissionError,
)

log = logging.getLogger(__name__)

_HOST_PORT = re.compile(r"^(?:tcp://)?(?P<host>[A-Za-z0-9_.\-]+|\[[0-9a-fA-F:]+\]):(?P<port>\d{1,5})$")


def normalise_url(url: str) -> str:
    """Map the accepted shorthands onto pyserial URLs (``host:port`` -> ``socket://host:port``)."""
    url = url.strip()
    if not url:
        raise DeviceNotFoundError("empty port name: give a device path, a pty path or host:port")
    if url.startswith("socket://") or url.startswith("loop://") or url.startswith("/"):
        return url
    match = _HOST_PORT.match(url)
    if match:
        return f"socket://{match['host']}:{match['port']}"
    return url


class DirectWriteSerial(serial.Serial):
    """pyserial's POSIX serial port with a one-system-call ``write`` when the bytes fit (module docstring)."""

    def write(self, data: bytes) -> int | None:  # type: ignore[override]
        if type(data) is not bytes or not self.is_open:
            return super().write(data)   # other buffer types, and pyserial's "port not open" error
        try:
            written = os.write(self.fd, data)
        except BlockingIOError:
            written = 0
        except OSError:
            return super().write(data)   # pyserial reports it (SerialException naming the error)
        if written == len(data):
            return written
        rest = super().write(data[written:])
        return written + (rest or 0)


def open_serial(url: str, *, baudrate: int = 115200, timeout: float = 0.1, exclusive: bool = True) -> serial.SerialBase:
    """Open ``url`` and return a ready pyserial object, or raise a DeviceError that names the port."""
    target = normalise_url(url)
    if target.startswith("/") and not os.path.exists(target):
        raise DeviceNotFoundError(f"port {url!r} does not exist (is the device plugged in, or the loopback running?)")
    try:
        if target.startswith("/") and os.name == "posix":
            port = DirectWriteSerial(None, baudrate=baudrate, timeout=timeout, write_timeout=max(timeout, 1.0))
            port.port = target
        else:
            port = serial.serial_for_url(target, baudrate=baudrate, timeout=timeout,
                                         write_timeout=max(timeout, 1.0), do_not_open=True)
        if exclusive and hasattr(port, "exclusive") and target.startswith("/"):
            port.exclusive = True
        port.open()
    except serial.SerialException as err:
        raise _translate(url, err) from err
    except (OSError, ValueError) as err:
        raise _translate(url, err) from err
    log.debug("opened %s", target)
    return port


def _translate(url: str, err: Exception) -> DeviceError:
    code = getattr(err, "errno", None)
    text = str(err)
    if code in (errno.ENOENT, errno.ENODEV, errno.ENXIO) or "No such file" in text:
        return DeviceNotFoundError(f"port {url!r} does not exist: {text}")
    if code in (errno.EACCES, errno.EPERM) or "Permission denied" in text:
        return DevicePermissionError(
            f"no permission to open {url!r}: add your user to the 'dialout' group or install a udev rule ({text})")
    if code in (errno.EBUSY, errno.EAGAIN) or "busy" in text.lower() or "lock" in text.lower():
        return DeviceBusyError(f"port {url!r} is busy: another program holds it ({text})")
    if code in (errno.ECONNREFUSED,) or "refused" in text.lower():
        return DeviceNotFoundError(f"nothing listens at {url!r}: {text}")
    return DeviceError(f"could not open {url!r}: {text}")
