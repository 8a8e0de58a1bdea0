"""What a loopback device run in a child process needs, on both sides: the pipe link and the frames file.

The renderer (:mod:`drivers.loopback.render_process`) and the whole simulated lab
(:mod:`drivers.loopback.lab_process`) each run as ``python -m MODULE FRAMES_FILE``, so that their numpy and
Python work does not take the appliance's GIL. Both talk the same way, and this module is that way, once:

- :class:`ChildLink` (the parent's side): starts the child with pipes to its stdin and stdout, sends and
  receives length-prefixed pickles, and ends it (end of its input, then terminate, then kill), removing the
  frames file with it. Its ``lock`` is held for one request, its reply and reading the frames the reply
  announces, as the next request overwrites them.
- :class:`FramesFile`: the images of every plane, one after the other as little-endian uint16, in a file in
  shared memory (``/dev/shm`` when there is one) that the child writes and the parent reads, so only the
  small part of a reply crosses the pipe. The parent creates it; the child attaches to it by name.
- :func:`child_main` and :func:`answer_requests` (the child's side): the child ignores Ctrl-C (its parent
  decides when the session ends), replies on a private copy of stdout (anything printed goes to stderr),
  answers every request with ``{"value": ...}`` or ``{"error": "Type: message"}``, and ends at the end of
  its stdin, so it cannot outlive its parent.

What is sent, what a reply means and what a lost child means to its users stay with each module.
"""
from __future__ import annotations

import contextlib
import os
import pickle
import signal
import struct
import subprocess
import sys
import tempfile
import threading
from collections.abc import Callable, Mapping
from typing import Any, BinaryIO

import numpy as np

_LENGTH = struct.Struct("<Q")
_PIXEL = np.dtype("<u2")


def send(stream: BinaryIO, message: Any) -> None:
    """Write ``message`` to ``stream`` as one length-prefixed pickle."""
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(_LENGTH.pack(len(data)) + data)
    stream.flush()


def receive(stream: BinaryIO) -> Any:
    """The next message :func:`send` wrote to the other end of ``stream``; EOFError when that end closed it."""
    head = stream.read(_LENGTH.size)
    if len(head) < _LENGTH.size:
        raise EOFError("the other end closed the pipe")
    (size,) = _LENGTH.unpack(head)
    data = stream.read(size)
    if len(data) < size:
        raise EOFError("the other end closed the pipe mid-message")
    return pickle.loads(data)


def error_reply(err: BaseException) -> dict[str, str]:
    """The reply that carries ``err`` to the parent, which raises it there."""
    return {"error": f"{type(err).__name__}: {err}"}


class FramesFile:
    """One image per plane (``shapes``: name -> (rows, columns)), in that order of names, in the file ``path``.

    Parent and child compute the same offsets from the same shapes, so the shapes are all the child is told."""

    def __init__(self, path: str, shapes: Mapping[str, tuple[int, int]]) -> None:
        self.path = path
        self.shapes = {name: (int(shape[0]), int(shape[1])) for name, shape in shapes.items()}
        self._slices: dict[str, slice] = {}
        size = 0
        for name in sorted(self.shapes):
            count = self.shapes[name][0] * self.shapes[name][1]
            self._slices[name] = slice(size, size + count)      # in pixels
            size += count
        self._pixels = np.memmap(path, dtype=_PIXEL, mode="r+", shape=(size,))

    @classmethod
    def create(cls, views: Mapping[str, Any], prefix: str) -> FramesFile:
        """A new file sized for the images of ``views`` (name -> view with ``image_size`` (width, height))."""
        shapes = {name: (view.image_size[1], view.image_size[0]) for name, view in views.items()}
        size = sum(rows * columns for rows, columns in shapes.values())
        folder = "/dev/shm" if os.path.isdir("/dev/shm") else None
        # Closed once sized: the child and the memmap open it by name.
        with tempfile.NamedTemporaryFile(prefix=prefix, suffix=".u16", dir=folder, delete=False) as handle:
            path = handle.name
        try:
            os.truncate(path, _PIXEL.itemsize * size)
            return cls(path, shapes)
        except BaseException:
            cls.remove(path)
            raise

    def write(self, images: Mapping[str, np.ndarray]) -> None:
        """The child's side: put ``images`` (name -> array of that plane's shape) into the file."""
        for name, image in images.items():
            self._pixels[self._slices[name]] = image.reshape(-1)

    def read(self) -> dict[str, np.ndarray]:
        """The parent's side: a copy of every plane's image (the caller owns the arrays)."""
        return {name: np.array(self._pixels[where].reshape(self.shapes[name])) for name, where in self._slices.items()}

    def unlink(self) -> None:
        """Remove the file (either side may; whoever is first). The mapping stays valid until dropped."""
        self.remove(self.path)

    @staticmethod
    def remove(path: str) -> None:
        """Remove the frames file ``path`` if it is still there."""
        with contextlib.suppress(OSError):
            os.unlink(path)


class ChildLink:
    """``python -m module frames.path`` with pipes to its stdin and stdout; ends with :meth:`close`.

    ``closed`` is set by :meth:`close`; callers check it, and send, receive and read the frames, while
    holding ``lock``. If the child cannot be started the frames file is removed at once."""

    def __init__(self, module: str, frames: FramesFile) -> None:
        self.frames = frames
        self.lock = threading.Lock()
        self.closed = False
        try:
            self.process: subprocess.Popen[bytes] = subprocess.Popen(
                [sys.executable, "-m", module, frames.path], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        except BaseException:
            frames.unlink()
            raise
        assert self.process.stdin is not None and self.process.stdout is not None
        self._to_child: BinaryIO = self.process.stdin
        self._from_child: BinaryIO = self.process.stdout

    def send(self, message: Any) -> None:
        send(self._to_child, message)

    def receive(self) -> Any:
        return receive(self._from_child)

    def close(self, timeout_s: float = 5.0) -> None:
        """End the child (end of its input, then terminate/kill if it does not go) and remove the frames file.
        Idempotent."""
        with self.lock:
            if self.closed:
                return
            self.closed = True
        process = self.process
        with contextlib.suppress(OSError):
            self._to_child.close()
        try:
            process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            process.terminate()
            try:
                process.wait(timeout_s)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        with contextlib.suppress(OSError):
            self._from_child.close()
        self.frames.unlink()


# -- the child's side ----------------------------------------------------------------------------------
def answer_requests(requests: BinaryIO, replies: BinaryIO, answer: Callable[[Any], Any]) -> int:
    """Reply to every request with ``{"value": answer(request)}`` (or the error it raised) until the end of
    ``requests`` (the parent closed the pipe or died); then 0, the child's exit status."""
    while True:
        try:
            request = receive(requests)
        except EOFError:
            return 0
        try:
            reply = {"value": answer(request)}
        except Exception as err:  # noqa: BLE001 - reported to the parent, which raises it there
            reply = error_reply(err)
        send(replies, reply)


def child_main(serve: Callable[[str, BinaryIO, BinaryIO], int], argv: list[str] | None = None) -> int:
    """The child's ``main``: ``serve(frames_path, requests, replies)`` on stdin and a private copy of stdout."""
    args = sys.argv[1:] if argv is None else argv
    # Ctrl-C reaches the whole process group: the parent shuts the session down and then closes our input.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # The replies get stdout's pipe to themselves; anything printed goes to stderr instead.
    replies = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    return serve(args[0], sys.stdin.buffer, replies)
