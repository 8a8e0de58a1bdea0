"""The simulated lab in a child process: world, amplifier fake, tracker fake and renderer outside the appliance.

On a bench the coil amplifier, the optical tracker and the fluoroscope are other machines; in simulation
the world's dynamics (magpylib field and gradient every substep), the amplifier fake's coil physics, the
tracker fake's poses and the X-ray rendering are several ms of Python and numpy per frame, and run in the
appliance's process they take its GIL from the frame loop. Here they run in their own interpreter:
``python -m drivers.loopback.lab_process SHM_FILE`` builds a :class:`~drivers.loopback.lab.LoopbackLab`
from the pickled world and fake configurations it reads from its stdin, serves the amplifier fake and the
tracker fake on their own pseudo-terminals (or loopback TCP ports) and answers length-prefixed pickled
requests on its stdout (the link and the frames file are :mod:`drivers.loopback.child_process`'s, shared
with the renderer's process): step the world to a simulated time, render the exposure at a time into the
frames file in shared memory (``/dev/shm`` when there is one), and small calls on the world and the
fakes (truth, measured currents, snapshots, fault injection) for the harness and the tests.

:class:`LabProcess` is the parent's side, with the methods of ``LoopbackLab`` the simulation bench uses;
``world`` and ``amplifier_fake`` are proxies whose attributes and methods are read and called in the
child. The appliance talks to the fakes only through their real transports, as on a bench: the pty paths
(:attr:`LabProcess.amplifier_url`, :attr:`LabProcess.ots_url`) and, for the X-ray frames, the fake pyusb
backend in its own process reading :attr:`LabProcess.exposures`.

Lifetime: the child ignores Ctrl-C (the parent shuts the session down through it, ramping the coils to
zero) and exits at the end of its stdin, so it cannot outlive its parent: when the parent closes the
pipe, or dies, the child ends, its ptys close and it removes the frames file. When the child dies, the
parent's next request raises :class:`LabProcessError` (a :class:`~drivers.errors.LinkLostError`: every
device of the lab dropped out at once), and the amplifier's and the tracker's ptys report a lost link
to their drivers, as a real device that drops out does. Everything the parent got before (the current
trace, the truth of every step) stays in the parent.
"""
from __future__ import annotations

import contextlib
import logging
import subprocess
import sys
from typing import Any, BinaryIO

import numpy as np

from drivers.errors import LinkLostError
from drivers.loopback.child_process import (
    ChildLink,
    FramesFile,
    answer_requests,
    child_main,
    error_reply,
    receive,
    send,
)

log = logging.getLogger(__name__)

_CALLABLE = "<callable>"
_OWN = ""          # the lab itself, in requests that name an object


class LabProcessError(LinkLostError):
    """The simulated lab's process failed a request, or is gone."""


class LabProcess:
    """The simulated lab (see the module docstring) in a child process; thread-safe.

    ``clock`` is the harness's simulated clock (``now()``, ``advance_to(t)``): :meth:`step` moves the child's
    clock and then this one to the same time. ``ots`` is None (no tracker fake) or ``{"link": "pty" | "tcp",
    "seed": int}``."""

    def __init__(self, *, clock: Any, world: Any, amplifier_config: Any, amplifier_link: str, renderer: Any,
                 substep_s: float, ots: dict[str, Any] | None = None) -> None:
        self.clock = clock
        self.views = renderer.views
        self._pose: Any = None                 # the world's pose after the last step (None: ask the child)
        #: (t, max |measured current|) after every world step, as the child reported it with each step.
        self.current_trace: list[tuple[float, float]] = []
        self.world = _Remote(self, "world")
        self.amplifier_fake = _Remote(self, "amplifier_fake")
        self.renderer_settings = renderer.settings
        #: The amplifier fake's last snapshot, taken as the child is closed (its state when the session ended).
        self.final_amplifier_state: Any = None
        from drivers.loopback.lab import Exposures

        frames = FramesFile.create(renderer.views, prefix="sim-lab-")
        self.shm_path = frames.path
        self._link = ChildLink("drivers.loopback.lab_process", frames)
        self.process = self._link.process
        self.exposures = Exposures(self.render_at, self.views, self.process)
        try:
            ready = self._request({
                "world": world, "amplifier_config": amplifier_config, "amplifier_link": amplifier_link,
                "ots": ots, "renderer": renderer, "substep_s": substep_s, "start_s": clock.now(),
                "shapes": frames.shapes})
            self.amplifier_url: str = ready["amplifier"]
            self.ots_url: str | None = ready["ots"]
        except BaseException:
            self.close()
            raise
        log.info("simulated lab in process %d: amplifier on %s, tracker on %s, frames through %s",
                 self.process.pid, self.amplifier_url, self.ots_url, self.shm_path)

    # -- the link ----------------------------------------------------------------------------------
    def _request(self, message: Any) -> Any:
        return self._exchange(message, rendering=False)[0]

    def _exchange(self, message: Any, *, rendering: bool) -> tuple[Any, dict[str, np.ndarray] | None]:
        """The reply's value and, ``rendering``, the images the child wrote for it (read before the next
        request can overwrite them)."""
        with self._link.lock:
            if self._link.closed:
                raise LabProcessError("the simulated lab's process is closed")
            try:
                self._link.send(message)
                reply = self._link.receive()
            except (EOFError, OSError, ValueError) as err:
                if rendering:
                    raise LabProcessError(f"the simulated lab's process ended ({self._exit_status()}) while "
                                          f"rendering: {err}") from err
                raise LabProcessError(f"the simulated lab's process ended ({self._exit_status()}): world, "
                                      f"amplifier and tracker fakes are gone ({err})") from err
            if "error" in reply:
                raise LabProcessError(f"simulated lab: {reply['error']}")
            images = self._link.frames.read() if rendering else None
        return reply["value"], images

    def _exit_status(self) -> str:
        process = self.process
        try:
            code = process.wait(0.5)
        except subprocess.TimeoutExpired:
            return "still running, its pipe broken"
        return f"killed by signal {-code}" if code < 0 else f"exit status {code}"

    def call(self, target: str, name: str, *args: Any, **kwargs: Any) -> Any:
        """``getattr(lab.<target>, name)(*args, **kwargs)`` in the child (``target`` "" is the lab itself)."""
        self._pose = None          # the call may move the world (set_pose)
        return self._request(("call", target, name, args, kwargs))

    # -- what the simulation bench uses (LoopbackLab's methods) --------------------------------------
    def step(self, dt_s: float) -> Any:
        target = self.clock.now() + dt_s
        pose, trace = self._request(("step_to", target))
        self.current_trace.extend(trace)
        self._pose = pose
        self.clock.advance_to(target)
        return pose

    def pose(self) -> Any:
        pose = self._pose
        if pose is None:
            pose = self._pose = self.call(_OWN, "pose")
        return pose

    def measured_currents_a(self) -> np.ndarray:
        return self.call(_OWN, "measured_currents_a")

    def cut_amplifier_link(self) -> None:
        self.call(_OWN, "cut_amplifier_link")

    def press_estop(self) -> None:
        self.call(_OWN, "press_estop")

    def hide_robot(self, hidden: bool = True) -> None:
        self.call(_OWN, "hide_robot", hidden)

    # -- the validation's hands (see LoopbackLab) ---------------------------------------------------------
    def use_pointer(self) -> None:
        self.call(_OWN, "use_pointer")

    def set_pointer(self, pose: Any) -> None:
        self.call(_OWN, "set_pointer", pose)

    def pass_time(self, seconds: float) -> None:
        target = self.clock.now() + seconds
        self.call(_OWN, "pass_time_to", target)
        self.clock.advance_to(target)

    def place_robot(self, centroid_mm: Any, direction: Any) -> None:
        self.call(_OWN, "place_robot", centroid_mm, direction)

    def replace_renderer(self, renderer: Any) -> None:
        self.call(_OWN, "replace_renderer", renderer)

    def restore_renderer(self) -> None:
        self.call(_OWN, "restore_renderer")

    def render_at(self, t_s: float) -> Any:
        """The exposure at simulated ``t_s`` (``RenderedPair``; the images are the caller's own arrays)."""
        from drivers.loopback.xray_render import RenderedPair

        value, images = self._exchange(("render", t_s), rendering=True)
        return RenderedPair(images=images, truth=value["truth"], pose=value["pose"], head_mm=value["head_mm"],
                            tail_mm=value["tail_mm"])

    # -- lifetime ------------------------------------------------------------------------------------
    @property
    def alive(self) -> bool:
        return self.process.poll() is None and not self._link.closed

    def close(self, timeout_s: float = 5.0) -> None:
        """End the child (end of its input, then terminate/kill if it does not go) and remove the frames file.
        Idempotent."""
        if self.alive:
            with contextlib.suppress(LabProcessError):
                self.final_amplifier_state = self.call("amplifier_fake", "snapshot")
        self._link.close(timeout_s)

    def __enter__(self) -> LabProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _Remote:
    """An object of the child's lab: attributes are read there, methods called there (pickled both ways)."""

    def __init__(self, lab: LabProcess, target: str) -> None:
        self._lab = lab
        self._target = target

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        value = self._lab._request(("get", self._target, name))
        if isinstance(value, str) and value == _CALLABLE:
            return lambda *args, **kwargs: self._lab.call(self._target, name, *args, **kwargs)
        return value


# -- the child ---------------------------------------------------------------------------------------
def _build(setup: dict[str, Any]) -> Any:
    from drivers.loopback.amplifier_fake import FakeAmplifier
    from drivers.loopback.lab import LabClock, LoopbackLab
    from drivers.loopback.serve import PtyServer, TcpServer

    clock = LabClock(setup["start_s"])
    fake = FakeAmplifier(setup["amplifier_config"])
    server = TcpServer(fake, clock=clock) if setup["amplifier_link"] == "tcp" else PtyServer(fake, clock=clock)
    lab = LoopbackLab(clock, setup["world"], fake, server, setup["substep_s"], renderer=setup["renderer"])
    if setup["ots"] is not None:
        from drivers.loopback.ots_fake import NdiTrackerFake, NoiseModel

        ots_fake = NdiTrackerFake(lab.tool_poses, noise=NoiseModel(seed=setup["ots"]["seed"]))
        lab.attach_tracker(ots_fake, TcpServer(ots_fake, clock=clock) if setup["ots"]["link"] == "tcp"
                           else PtyServer(ots_fake, clock=clock))
    return lab


def _url(server: Any) -> str | None:
    if server is None:
        return None
    return server.path if hasattr(server, "path") else server.address


def _answer(lab: Any, frames: FramesFile, request: Any) -> Any:
    kind = request[0]
    if kind == "step_to":
        before = len(lab.current_trace)
        pose = lab.step_to(request[1])
        trace = lab.current_trace[before:]
        del lab.current_trace[:]       # the parent keeps the trace
        return pose, trace
    if kind == "render":
        rendered = lab.render_at(request[1])
        frames.write(rendered.images)
        return {"truth": rendered.truth, "head_mm": rendered.head_mm, "tail_mm": rendered.tail_mm,
                "pose": rendered.pose}
    target = lab if request[1] == _OWN else getattr(lab, request[1])
    if kind == "get":
        value = getattr(target, request[2])
        return _CALLABLE if callable(value) else value
    if kind == "call":
        return getattr(target, request[2])(*request[3], **request[4])
    raise ValueError(f"unknown request {kind!r}")


def _serve(shm_path: str, requests: BinaryIO, replies: BinaryIO) -> int:
    try:
        setup = receive(requests)
        lab = _build(setup)
    except EOFError:
        return 0
    except Exception as err:  # noqa: BLE001 - reported to the parent, which raises it there
        send(replies, error_reply(err))
        return 1
    try:
        frames = FramesFile(shm_path, setup["shapes"])
        send(replies, {"value": {"amplifier": _url(lab.amplifier_server), "ots": _url(lab.ots_server)}})
        return answer_requests(requests, replies, lambda request: _answer(lab, frames, request))
    finally:
        lab.close()
        # The frames file goes with us (the parent's close removes it too; whoever is first).
        FramesFile.remove(shm_path)


def main(argv: list[str] | None = None) -> int:
    # Ctrl-C is ignored here: the parent shuts the session down (ramping the coils to zero through the
    # amplifier fake served here) and then closes our input. Logging goes to stderr, as does anything printed.
    logging.basicConfig(level=logging.WARNING, format="simulated lab: %(levelname)s %(name)s: %(message)s")
    return child_main(_serve, argv)


if __name__ == "__main__":
    sys.exit(main())
