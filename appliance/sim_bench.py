"""The simulated side of a session: the simulated clock and the bench of fakes.

:class:`SimClock` is the time the world, the device fakes and (in simulation) the frame loop run on;
only the harness advances it. :class:`SimBench` holds what the device factory built - the simulated lab
(world, amplifier fake, tracker fake: in a child process by default, as a bench's devices are other
machines), the X-ray scene and grabbers - steps the world with the amplifier fake's MEASURED currents,
follows the wall clock on demand (device start-up and shutdown), and injects faults. Nothing here
imports the fakes: the factory hands them in.
"""
from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Iterator
from typing import Any

import numpy as np

from drivers.errors import DeviceError
from drivers.frame_source import FrameSource

log = logging.getLogger(__name__)


class SimClock:
    """Simulated time (s), shared by the world, the fakes and the frame loop; advanced by the harness.

    ``sleep`` lets a fake that polls for "time to pass" (a grabber waiting for its next exposure) wake as
    soon as the harness advances the clock, instead of sleeping the simulated interval in real time.

    The X-ray grabbers see the clock through :attr:`released` (:meth:`released_now`, :meth:`sleep`): while
    the harness steps the world inside :meth:`hold`, that reading stands still and moves to the end of the
    step only when the step is done. On a bench the world moves on its own, in parallel with the host; here
    it moves in the host's process, between frames, so a frame put on the host in the middle of a step
    would wait for the rest of the step (up to ``loop_latency_ms`` of simulated time, tens of ms of wall
    time) and that wait would be counted as the appliance's loop latency.
    """

    def __init__(self, start_s: float = 0.0) -> None:
        self._t = float(start_s)
        self._released = self._t
        self._holds = 0
        self._cond = threading.Condition()
        self.released = _ReleasedClock(self)

    def __call__(self) -> float:
        return self._t

    def now(self) -> float:
        return self._t

    def released_now(self) -> float:
        """The time the grabbers see: ``now()``, except that it stands still inside :meth:`hold`."""
        return self._released

    def advance(self, dt_s: float) -> float:
        if not dt_s >= 0.0:
            raise ValueError(f"simulated time only moves forward, got dt {dt_s}")
        with self._cond:
            self._t += dt_s
            if not self._holds:
                self._released = self._t
                self._cond.notify_all()
            return self._t

    def advance_to(self, t_s: float) -> float:
        """Move to ``t_s`` exactly (never backwards): the clock of a lab in another process ends its steps there."""
        with self._cond:
            self._t = max(self._t, float(t_s))
            if not self._holds:
                self._released = self._t
                self._cond.notify_all()
            return self._t

    def pause(self) -> None:
        """From now on :attr:`released` stands still, until as many :meth:`resume` calls as pauses."""
        with self._cond:
            self._holds += 1

    def resume(self) -> None:
        with self._cond:
            if self._holds <= 0:
                raise RuntimeError("SimClock.resume without a pause")
            self._holds -= 1
            if not self._holds:
                self._released = self._t
                self._cond.notify_all()

    @contextlib.contextmanager
    def hold(self) -> Iterator[None]:
        """While inside, :attr:`released` does not move; on leaving it jumps to ``now()`` and wakes sleepers."""
        self.pause()
        try:
            yield
        finally:
            self.resume()

    def sleep(self, seconds: float) -> None:
        """Wait until the released clock has advanced ``seconds``, or at most ``seconds`` of real time."""
        with self._cond:
            target = self._released + seconds
            self._cond.wait_for(lambda: self._released >= target, timeout=max(seconds, 0.0))


class _ReleasedClock:
    """The clock as the X-ray grabbers see it (see :class:`SimClock`): callable, with ``sleep``."""

    def __init__(self, clock: SimClock) -> None:
        self._clock = clock
        self.sleep = clock.sleep

    def __call__(self) -> float:
        return self._clock.released_now()


class SimBench:
    """The simulated side of a session: the lab (world and fakes), the clock, the X-ray scene, fault injection.

    ``lab`` is what the factory built: a ``LabProcess`` proxy to a ``LoopbackLab`` in a child process (the
    default), or a ``LoopbackLab`` in this process; both have ``step``, ``pose``, ``measured_currents_a``,
    ``current_trace``, the fault injections and the validation's hands. ``world`` and ``amplifier_fake``
    are the lab's (proxies when it is in a child); ``history``, ``amplifier_server``, ``ots_fake`` and
    ``ots_server`` exist only for a lab in this process (None otherwise)."""

    def __init__(self, clock: SimClock, lab: Any, true_views: dict[str, Any]) -> None:
        self.clock = clock
        self.lab = lab
        self.true_views = true_views
        self.scene: Any = None
        self.grabber_devices: dict[str, Any] = {}
        self.frame_sources: dict[str, FrameSource] = {}
        self._step_lock = threading.Lock()
        self._frames_held = False

    # -- the lab -----------------------------------------------------------------------------------
    @property
    def world(self) -> Any:
        return self.lab.world

    @property
    def amplifier_fake(self) -> Any:
        return self.lab.amplifier_fake

    @property
    def amplifier_server(self) -> Any:
        return getattr(self.lab, "amplifier_server", None)

    @property
    def ots_fake(self) -> Any:
        return getattr(self.lab, "ots_fake", None)

    @property
    def ots_server(self) -> Any:
        return getattr(self.lab, "ots_server", None)

    @property
    def history(self) -> Any:
        return getattr(self.lab, "history", None)

    @property
    def current_trace(self) -> list[tuple[float, float]]:
        """(t, max |measured current|) after every world step: what the coils really carried."""
        return self.lab.current_trace

    def pose(self) -> Any:
        """The world's true pose now (``RobotState``)."""
        return self.lab.pose()

    # -- time ------------------------------------------------------------------------------------
    def measured_currents_a(self) -> np.ndarray:
        """The amplifier fake's coil currents now (brought up to the simulated clock first)."""
        return self.lab.measured_currents_a()

    def step(self, dt_s: float) -> None:
        """Advance world and clock by ``dt_s``, in substeps each holding the amplifier's MEASURED currents."""
        with self._step_lock, self.clock.hold():
            self.lab.step(dt_s)

    def advance_to(self, t_s: float, *, release: bool = True) -> None:
        """Step the world to ``t_s``. ``release=False`` keeps the frames of the step from the grabbers until
        :meth:`release_frames` (the harness releases them once the frame loop waits for its pair)."""
        if not release and not self._frames_held:
            self.clock.pause()
            self._frames_held = True
        if t_s > self.clock.now():
            self.step(t_s - self.clock.now())
        if release:
            self.release_frames()

    def release_frames(self) -> None:
        """Let the grabbers see the clock again after ``advance_to(..., release=False)`` (idempotent)."""
        if self._frames_held:
            self._frames_held = False
            self.clock.resume()

    @contextlib.contextmanager
    def real_time(self, period_s: float = 0.004) -> Iterator[None]:
        """While inside, a thread advances the world in step with the wall clock (used while devices start
        and shut down: their handshakes wait in real time, and the coils must keep evolving meanwhile).
        If the lab drops out (its process ended) the thread logs it and stops; the devices' drivers see
        their links lost."""
        stop = threading.Event()

        def run() -> None:
            last = time.monotonic()
            while not stop.wait(period_s):
                now = time.monotonic()
                try:
                    self.step(now - last)
                except DeviceError as err:
                    log.error("simulated bench: the world stopped following the wall clock: %s", err)
                    return
                last = now

        thread = threading.Thread(target=run, name="sim-real-time", daemon=True)
        thread.start()
        try:
            yield
        finally:
            stop.set()
            thread.join(timeout=2.0)

    # -- the validation's hands (appliance validate in simulation) -------------------------------------------
    def pass_time(self, seconds: float) -> None:
        """Let time pass without the world's dynamics (the robot clamped in its holder)."""
        self.lab.pass_time(seconds)

    def use_pointer(self) -> None:
        """The tracker sees tool 1, the validation's pointer, from now on."""
        self.lab.use_pointer()

    def set_pointer(self, pose: Any) -> None:
        """The pointer's pose provider (``pose(now) -> (R, t_mm)``, picklable), or None (put away)."""
        self.lab.set_pointer(pose)

    def place_robot(self, centroid_mm: Any, direction: Any) -> None:
        """Clamp the robot at a new pose now (exposures from now on show it there)."""
        self.lab.place_robot(centroid_mm, direction)

    def replace_renderer(self, renderer: Any) -> None:
        """X-ray exposures rendered by ``renderer`` (another phantom) until :meth:`restore_renderer`."""
        self.lab.replace_renderer(renderer)

    def restore_renderer(self) -> None:
        self.lab.restore_renderer()

    @property
    def renderer_settings(self) -> Any:
        """The simulated detector's settings (photons per pixel, dark level)."""
        return self.lab.renderer_settings

    # -- fault injection -------------------------------------------------------------------------
    def cut_amplifier_link(self) -> None:
        """The amplifier's cable is pulled: no byte passes either way from now on."""
        self.lab.cut_amplifier_link()

    def press_estop(self) -> None:
        self.lab.press_estop()

    def hide_robot(self, hidden: bool = True) -> None:
        """Frames show no robot (it left the field of view, or the images are unusable): tracking is lost."""
        self.lab.hide_robot(hidden)

    def stop_grabbers(self) -> None:
        """The imaging chain goes silent (generator off, grabbers stop streaming) without any error."""
        for device in self.grabber_devices.values():
            with device._lock:       # the fake's own lock: a silent stop has no protocol request
                device.streaming = False
        for source in self.frame_sources.values():
            if hasattr(source, "scene"):
                source.scene.rate_hz = 1e-6   # loopback grabber: next frame in 11 days
