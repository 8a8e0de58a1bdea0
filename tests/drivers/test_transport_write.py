"""open_serial's device ports: one ``os.write`` when the bytes fit, pyserial's write (timeout, errors)
for the rest, on a real pseudo-terminal."""
from __future__ import annotations

import os
import time
import tty

import pytest
import serial

from drivers.transport import DirectWriteSerial, open_serial

pytestmark = pytest.mark.skipif(os.name != "posix", reason="pseudo-terminals are POSIX")


@pytest.fixture
def pty_pair():
    controller, device = os.openpty()
    tty.setraw(controller)
    path = os.ttyname(device)
    yield controller, path
    os.close(controller)
    os.close(device)


def _read_all(fd: int, size: int, timeout_s: float = 2.0) -> bytes:
    out = bytearray()
    deadline = time.monotonic() + timeout_s
    while len(out) < size and time.monotonic() < deadline:
        out += os.read(fd, size - len(out))
    return bytes(out)


def test_a_device_path_opens_as_a_direct_write_port_and_the_bytes_arrive_whole(pty_pair) -> None:
    controller, path = pty_pair
    port = open_serial(path, timeout=0.05)
    try:
        assert isinstance(port, DirectWriteSerial)
        frame = bytes(range(1, 42)) + b"\x00"
        assert port.write(frame) == len(frame)
        assert port.write(bytearray(b"\x01\x02")) == 2   # other buffer types: pyserial's write
        assert _read_all(controller, len(frame) + 2) == frame + b"\x01\x02"
    finally:
        port.close()
    with pytest.raises(serial.PortNotOpenError):
        port.write(b"\x01")


def test_a_full_buffer_goes_through_pyserials_write_and_its_timeout(pty_pair) -> None:
    """Nobody reads the other end: the kernel's buffer fills, the first os.write is partial (or
    refused), and the rest waits in pyserial's write until its write timeout."""
    _, path = pty_pair
    port = open_serial(path, timeout=0.05)
    try:
        port.write_timeout = 0.2
        began = time.monotonic()
        with pytest.raises(serial.SerialTimeoutException):
            port.write(b"\x55" * (1 << 20))
        assert time.monotonic() - began >= 0.15
    finally:
        port.close()


def test_urls_that_are_not_device_paths_keep_pyserials_classes() -> None:
    port = open_serial("loop://", timeout=0.05)
    try:
        assert not isinstance(port, DirectWriteSerial)
        port.write(b"\x01\x02")
        assert port.read(2) == b"\x01\x02"
    finally:
        port.close()
