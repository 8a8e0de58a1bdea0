"""The loopback server carries bytes both ways over a real pty and a real TCP socket."""
from __future__ import annotations

import serial

from drivers.loopback.serve import PtyServer, TcpServer
from drivers.transport import open_serial


class _Echo:
    """Upper-cases what it is fed; counts ticks."""

    def __init__(self) -> None:
        self.ticks = 0

    def feed(self, data: bytes, now: float) -> bytes:
        return data.upper()

    def tick(self, now: float) -> bytes:
        self.ticks += 1
        return b""


def _round_trip(port: serial.SerialBase, payload: bytes) -> bytes:
    port.write(payload)
    got = b""
    while len(got) < len(payload):
        chunk = port.read(len(payload) - len(got))
        assert chunk, "fake did not answer"
        got += chunk
    return got


def test_pty_server_round_trip_and_reopen() -> None:
    device = _Echo()
    with PtyServer(device) as server:
        for _ in range(2):  # hosts open and close the port more than once
            port = open_serial(server.path, timeout=1.0)
            assert _round_trip(port, b"hello\r") == b"HELLO\r"
            port.close()
    assert device.ticks > 0


def test_tcp_server_round_trip() -> None:
    with TcpServer(_Echo()) as server:
        port = open_serial(server.address, timeout=1.0)
        assert _round_trip(port, b"abc" * 100) == b"ABC" * 100
        port.close()


def test_unplugged_link_passes_nothing() -> None:
    with PtyServer(_Echo()) as server:
        server.unplugged.set()
        port = open_serial(server.path, timeout=0.2)
        port.write(b"x")
        assert port.read(1) == b""
        port.close()
