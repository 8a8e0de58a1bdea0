"""The X-ray renderer in a child process: the simulated fluoroscope as a separate device.

On a bench the X-ray generator and detectors are other machines; in simulation the renderer is the
heaviest thing the simulated world does (several ms of numpy per biplane exposure at 768 x 672) and,
run by the grabber threads of the appliance's process, it takes the GIL from the frame loop. Here
it runs in its own interpreter: :class:`RenderProcess` has the renderer's ``render(pose)`` interface
(what :class:`~drivers.loopback.loopback_grabber.LoopbackScene` calls), sends the pose down a pipe,
and reads the images back from a file in shared memory (``/dev/shm`` when there is one) that the
child writes; only the pose and the small truth record cross the pipe.

The child is ``python -m drivers.loopback.render_process SHM_FILE``: it reads the pickled renderer,
then length-prefixed pickled requests, from its stdin and answers on its stdout. It ignores Ctrl-C
(the parent decides when the session ends) and exits at the end of its stdin, so it cannot outlive
its parent: when the parent closes the pipe, or dies, the child ends and removes the frames file.
The renderer travels whole (its noise generator's state included), so the images are the ones the
same renderer would have made in-process, in the same order.

Not modelled: nothing changes for the scene; rendering is still one exposure at a time, on request.
"""
from __future__ import annotations

import contextlib
import logging
import os
import pickle
import signal
import struct
import subprocess
import sys
import tempfile
import threading
from typing import Any, BinaryIO

import numpy as np

log = logging.getLogger(__name__)

_LENGTH = struct.Struct("<Q")


def _send(stream: BinaryIO, message: Any) -> None:
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(_LENGTH.pack(len(data)) + data)
    stream.flush()


def _receive(stream: BinaryIO) -> Any:
    head = stream.read(_LENGTH.size)
    if len(head) < _LENGTH.size:
        raise EOFError("the other end closed the pipe")
    (size,) = _LENGTH.unpack(head)
    data = stream.read(size)
    if len(data) < size:
        raise EOFError("the other end closed the pipe mid-message")
    return pickle.loads(data)


class RenderProcessError(RuntimeError):
    """The render process failed or is gone."""


class RenderProcess:
    """``renderer`` (a ``BiplaneRenderer``) moved into a child process; ``render`` is thread-safe."""

    def __init__(self, renderer: Any, *, start_timeout_s: float = 30.0) -> None:
        self.views = renderer.views
        self.body = renderer.body
        self.settings = renderer.settings
        self._planes = sorted(renderer.views)
        self._shapes = {name: (view.image_size[1], view.image_size[0]) for name, view in renderer.views.items()}
        self._offsets: dict[str, int] = {}
        size = 0
        for name in self._planes:
            self._offsets[name] = size                       # in pixels
            size += int(np.prod(self._shapes[name]))
        folder = "/dev/shm" if os.path.isdir("/dev/shm") else None
        # Closed below once sized: the child and the memmap open it by name.
        handle = tempfile.NamedTemporaryFile(prefix="xray-render-", suffix=".u16", dir=folder, delete=False)  # noqa: SIM115
        self.shm_path = handle.name
        self._lock = threading.Lock()
        self._closed = False
        self.process: subprocess.Popen[bytes] | None = None
        try:
            handle.truncate(2 * size)
            handle.close()
            self._frames = np.memmap(self.shm_path, dtype="<u2", mode="r+", shape=(size,))
            self.process = subprocess.Popen(
                [sys.executable, "-m", "drivers.loopback.render_process", self.shm_path],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, start_new_session=False)
            assert self.process.stdin is not None and self.process.stdout is not None
            self._to_child, self._from_child = self.process.stdin, self.process.stdout
            _send(self._to_child, {"renderer": renderer, "offsets": self._offsets, "shapes": self._shapes})
            reply = self._reply()
            if reply != "ready":
                raise RenderProcessError(f"render process did not start: {reply!r}")
        except BaseException:
            self.close()
            raise
        log.info("renderer in process %d (frames through %s)", self.process.pid, self.shm_path)

    def _reply(self) -> Any:
        try:
            reply = _receive(self._from_child)
        except (EOFError, OSError) as err:
            code = self.process.poll() if self.process is not None else None
            raise RenderProcessError(f"render process ended (exit status {code}): {err}") from err
        if isinstance(reply, dict) and "error" in reply:
            raise RenderProcessError(f"render process: {reply['error']}")
        return reply

    def render(self, pose: Any) -> Any:
        """One exposure of every view, as ``BiplaneRenderer.render`` (the images are the caller's own arrays)."""
        from drivers.loopback.xray_render import RenderedPair

        with self._lock:
            if self._closed:
                raise RenderProcessError("render process is closed")
            try:
                _send(self._to_child, pose)
            except OSError as err:
                raise RenderProcessError(f"render process is gone: {err}") from err
            reply = self._reply()
            images = {name: np.array(self._frames[self._offsets[name]:self._offsets[name]
                                                  + int(np.prod(self._shapes[name]))].reshape(self._shapes[name]))
                      for name in self._planes}
        return RenderedPair(images=images, truth=reply["truth"], pose=pose, head_mm=reply["head_mm"],
                            tail_mm=reply["tail_mm"])

    def close(self, timeout_s: float = 5.0) -> None:
        """End the child (end of its input, then terminate/kill if it does not go) and remove the frames file.
        Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        process = self.process
        if process is not None:
            with contextlib.suppress(OSError):
                process.stdin.close()   # type: ignore[union-attr]
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
                process.stdout.close()  # type: ignore[union-attr]
        with contextlib.suppress(OSError):
            os.unlink(self.shm_path)

    def __enter__(self) -> RenderProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _serve(shm_path: str, requests: BinaryIO, replies: BinaryIO) -> int:
    setup = _receive(requests)
    renderer, offsets, shapes = setup["renderer"], setup["offsets"], setup["shapes"]
    size = sum(int(np.prod(shape)) for shape in shapes.values())
    frames = np.memmap(shm_path, dtype="<u2", mode="r+", shape=(size,))
    _send(replies, "ready")
    while True:
        try:
            pose = _receive(requests)
        except EOFError:
            # The parent closed the pipe or died: the frames file goes with us (the parent's close removes
            # it too; whoever is first).
            with contextlib.suppress(OSError):
                os.unlink(shm_path)
            return 0
        try:
            rendered = renderer.render(pose)
            for name, image in rendered.images.items():
                count = int(np.prod(shapes[name]))
                frames[offsets[name]:offsets[name] + count] = image.reshape(-1)
            _send(replies, {"truth": rendered.truth, "head_mm": rendered.head_mm, "tail_mm": rendered.tail_mm})
        except Exception as err:  # noqa: BLE001 - reported to the parent, which raises it there
            _send(replies, {"error": f"{type(err).__name__}: {err}"})


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    # Ctrl-C reaches the whole process group: the parent shuts the session down and then closes our input.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # The replies get stdout's pipe to themselves; anything printed goes to stderr instead.
    replies = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    return _serve(args[0], sys.stdin.buffer, replies)


if __name__ == "__main__":
    sys.exit(main())
