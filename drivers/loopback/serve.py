"""Serve a byte-stream device fake on a real pseudo-terminal or a loopback TCP socket.

A fake implements :class:`StreamDevice`: it is fed the bytes the host wrote and returns the bytes the
device answers, and it is ticked regularly so that time-driven behaviour (ramps, watchdogs, frame
counters) advances on the injected clock even when the host is silent. The server owns one thread
that does the I/O; the device itself never touches a file descriptor.

What a pty does not carry: a serial break, line speed (accepted, never enforced) and modem lines.
"""
from __future__ import annotations

import errno
import logging
import os
import select
import socket
import threading
import time
import tty
from typing import Callable, Protocol

log = logging.getLogger(__name__)


class StreamDevice(Protocol):
    def feed(self, data: bytes, now: float) -> bytes:
        """Bytes received from the host at time ``now``; returns the bytes to send back."""

    def tick(self, now: float) -> bytes:
        """Advance time-driven state to ``now``; returns unsolicited bytes (usually none)."""


class LinkFilter(Protocol):
    """Optional fault injection on the link: maps bytes in flight to what actually arrives."""

    def __call__(self, data: bytes, direction: str) -> bytes: ...


class _Server:
    def __init__(self, device: StreamDevice, clock: Callable[[], float], tick_s: float,
                 link_filter: LinkFilter | None) -> None:
        self.device = device
        self.clock = clock
        self.tick_s = tick_s
        self.link_filter = link_filter
        self.lock = threading.Lock()          # held while the device is fed or ticked
        self.unplugged = threading.Event()    # fault injection: the link is cut (no bytes pass)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _filtered(self, data: bytes, direction: str) -> bytes:
        if self.unplugged.is_set():
            return b""
        return self.link_filter(data, direction) if self.link_filter and data else data

    def _exchange(self, data: bytes) -> bytes:
        with self.lock:
            reply = self.device.feed(data, self.clock()) if data else b""
            reply += self.device.tick(self.clock())
        return self._filtered(reply, "to_host")

    def start(self, name: str) -> None:
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:  # pragma: no cover - replaced by subclasses
        raise NotImplementedError

    def stop(self) -> None:
        self._stop.set()
        if self._thread and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self.stop()


class PtyServer(_Server):
    """The fake on a pseudo-terminal; ``path`` is the slave device a driver opens like a serial port.

    The server keeps its own handle on the slave open, so hosts may open and close the port again.
    """

    def __init__(self, device: StreamDevice, *, clock: Callable[[], float] = time.monotonic,
                 tick_s: float = 0.002, link_filter: LinkFilter | None = None) -> None:
        super().__init__(device, clock, tick_s, link_filter)
        self.master_fd, self._slave_fd = os.openpty()
        tty.setraw(self._slave_fd)
        tty.setraw(self.master_fd)
        self.path = os.ttyname(self._slave_fd)
        os.set_blocking(self.master_fd, False)
        self.start(f"pty-fake-{self.path}")

    def _write_all(self, data: bytes) -> None:
        view = memoryview(data)
        while view and not self._stop.is_set():
            try:
                sent = os.write(self.master_fd, view)
                view = view[sent:]
            except BlockingIOError:
                select.select([], [self.master_fd], [], 0.01)
            except OSError as err:
                if err.errno == errno.EIO:
                    return
                raise

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master_fd], [], [], self.tick_s)
            data = b""
            if ready:
                try:
                    data = os.read(self.master_fd, 65536)
                except BlockingIOError:
                    data = b""
                except OSError as err:
                    if err.errno == errno.EIO:   # no slave open right now: keep waiting
                        time.sleep(self.tick_s)
                        continue
                    raise
                data = self._filtered(data, "to_device")
            reply = self._exchange(data)
            if reply:
                self._write_all(reply)

    def close(self) -> None:
        self.stop()
        for fd in (self.master_fd, self._slave_fd):
            try:
                os.close(fd)
            except OSError:
                pass


class TcpServer(_Server):
    """The fake on a loopback TCP port (``port=0`` picks a free one); one host connection at a time."""

    def __init__(self, device: StreamDevice, *, host: str = "127.0.0.1", port: int = 0,
                 clock: Callable[[], float] = time.monotonic, tick_s: float = 0.002,
                 link_filter: LinkFilter | None = None) -> None:
        super().__init__(device, clock, tick_s, link_filter)
        self._listener = socket.create_server((host, port))
        self._listener.settimeout(tick_s)
        self.host, self.port = self._listener.getsockname()[:2]
        self.address = f"{self.host}:{self.port}"
        self.start(f"tcp-fake-{self.address}")

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._listener.accept()
            except (TimeoutError, socket.timeout):
                self._exchange(b"")
                continue
            except OSError:
                return
            with conn:
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                conn.setblocking(False)
                self._serve(conn)

    def _serve(self, conn: socket.socket) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([conn], [], [], self.tick_s)
            data = b""
            if ready:
                try:
                    data = conn.recv(65536)
                except BlockingIOError:
                    data = b""
                except OSError:
                    return
                if not data:
                    return  # the host closed the connection
                data = self._filtered(data, "to_device")
            reply = self._exchange(data)
            if reply:
                try:
                    conn.setblocking(True)
                    conn.sendall(reply)
                    conn.setblocking(False)
                except OSError:
                    return

    def close(self) -> None:
        self.stop()
        try:
            self._listener.close()
        except OSError:
            pass
