"""The X-ray renderer in a child process: the simulated fluoroscope as a separate device.

On a bench the X-ray generator and detectors are other machines; in simulation the renderer is the
heaviest thing the simulated world does (several ms of numpy per biplane exposure at 768 x 672) and,
run by the grabber threads of the appliance's process, it takes the GIL from the frame loop. Here
it runs in its own interpreter: :class:`RenderProcess` has the renderer's ``render(pose)`` interface
(what :class:`~drivers.loopback.loopback_grabber.LoopbackScene` calls), sends the pose down a pipe,
and reads the images back from a file in shared memory (``/dev/shm`` when there is one) that the
child writes; only the pose and the small truth record cross the pipe.

The child is ``python -m drivers.loopback.render_process SHM_FILE``: it reads the pickled renderer,
then length-prefixed pickled requests, from its stdin and answers on its stdout (the link and the frames
file are :mod:`drivers.loopback.child_process`'s, shared with the lab's process). It ignores Ctrl-C
(the parent decides when the session ends) and exits at the end of its stdin, so it cannot outlive
its parent: when the parent closes the pipe, or dies, the child ends and removes the frames file.
The renderer travels whole (its noise generator's state included), so the images are the ones the
same renderer would have made in-process, in the same order.

Not modelled: nothing changes for the scene; rendering is still one exposure at a time, on request.
"""
from __future__ import annotations

import logging
import sys
from typing import Any, BinaryIO

from drivers.loopback.child_process import ChildLink, FramesFile, answer_requests, child_main, receive, send

log = logging.getLogger(__name__)


class RenderProcessError(RuntimeError):
    """The render process failed or is gone."""


class RenderProcess:
    """``renderer`` (a ``BiplaneRenderer``) moved into a child process; ``render`` is thread-safe."""

    def __init__(self, renderer: Any, *, start_timeout_s: float = 30.0) -> None:
        self.views = renderer.views
        self.body = renderer.body
        self.settings = renderer.settings
        frames = FramesFile.create(renderer.views, prefix="xray-render-")
        self.shm_path = frames.path
        self._link = ChildLink("drivers.loopback.render_process", frames)
        self.process = self._link.process
        try:
            self._link.send({"renderer": renderer, "shapes": frames.shapes})
            reply = self._reply()
            if reply != "ready":
                raise RenderProcessError(f"render process did not start: {reply!r}")
        except BaseException:
            self.close()
            raise
        log.info("renderer in process %d (frames through %s)", self.process.pid, self.shm_path)

    def _reply(self) -> Any:
        try:
            reply = self._link.receive()
        except (EOFError, OSError) as err:
            raise RenderProcessError(f"render process ended (exit status {self.process.poll()}): {err}") from err
        if "error" in reply:
            raise RenderProcessError(f"render process: {reply['error']}")
        return reply["value"]

    def render(self, pose: Any) -> Any:
        """One exposure of every view, as ``BiplaneRenderer.render`` (the images are the caller's own arrays)."""
        from drivers.loopback.xray_render import RenderedPair

        with self._link.lock:
            if self._link.closed:
                raise RenderProcessError("render process is closed")
            try:
                self._link.send(pose)
            except OSError as err:
                raise RenderProcessError(f"render process is gone: {err}") from err
            reply = self._reply()
            images = self._link.frames.read()
        return RenderedPair(images=images, truth=reply["truth"], pose=pose, head_mm=reply["head_mm"],
                            tail_mm=reply["tail_mm"])

    def close(self, timeout_s: float = 5.0) -> None:
        """End the child (end of its input, then terminate/kill if it does not go) and remove the frames file.
        Idempotent."""
        self._link.close(timeout_s)

    def __enter__(self) -> RenderProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _serve(shm_path: str, requests: BinaryIO, replies: BinaryIO) -> int:
    setup = receive(requests)
    renderer = setup["renderer"]
    frames = FramesFile(shm_path, setup["shapes"])
    send(replies, {"value": "ready"})

    def answer(pose: Any) -> dict[str, Any]:
        rendered = renderer.render(pose)
        frames.write(rendered.images)
        return {"truth": rendered.truth, "head_mm": rendered.head_mm, "tail_mm": rendered.tail_mm}

    status = answer_requests(requests, replies, answer)
    # The parent closed the pipe or died: the frames file goes with us (the parent's close removes it too;
    # whoever is first).
    frames.unlink()
    return status


def main(argv: list[str] | None = None) -> int:
    return child_main(_serve, argv)


if __name__ == "__main__":
    sys.exit(main())
