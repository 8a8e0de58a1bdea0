"""The simulated side of a session: the simulated clock, the world's recent poses, and the bench of fakes.

:class:`SimClock` is the time the world, the device fakes and (in simulation) the frame loop run on;
only the harness advances it. :class:`SimBench` holds what the device factory built - the simulated
world, the amplifier fake and its server, the X-ray scene and grabbers, the tracker fake - and steps
the world with the amplifier fake's MEASURED currents, follows the wall clock on demand (device
start-up and shutdown), and injects faults. Nothing here imports the fakes: the factory hands them in.
"""
from __future__ import annotations

import contextlib
import itertools
import threading
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from drivers.frame_source import FrameSource


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


@dataclass
class _Sample:
    t_s: float
    centroid_mm: np.ndarray
    direction: np.ndarray


class PoseHistory:
    """The world's true pose over the last second, so a frame exposed at ``t`` shows the robot as it was then
    (the harness runs the world ahead of the frame by the modelled loop latency)."""

    def __init__(self, keep_s: float = 1.0) -> None:
        self._samples: deque[_Sample] = deque()
        self._keep_s = keep_s
        self._lock = threading.Lock()
        self.visible = True          # fault injection: False renders frames without the robot

    def append(self, t_s: float, centroid_mm: np.ndarray, direction: np.ndarray) -> None:
        with self._lock:
            self._samples.append(_Sample(t_s, centroid_mm.copy(), direction.copy()))
            while len(self._samples) > 2 and self._samples[1].t_s < t_s - self._keep_s:
                self._samples.popleft()

    def at(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(centroid, unit direction) at ``t_s``, interpolated; held at the ends of the history."""
        with self._lock:
            samples = list(self._samples)
        if not samples:
            raise RuntimeError("pose history is empty")
        if t_s <= samples[0].t_s:
            return samples[0].centroid_mm, samples[0].direction
        for before, after in itertools.pairwise(samples):
            if before.t_s <= t_s <= after.t_s:
                span = after.t_s - before.t_s
                w = 0.0 if span <= 0.0 else (t_s - before.t_s) / span
                direction = (1.0 - w) * before.direction + w * after.direction
                return ((1.0 - w) * before.centroid_mm + w * after.centroid_mm,
                        direction / np.linalg.norm(direction))
        return samples[-1].centroid_mm, samples[-1].direction


class SimBench:
    """The simulated side of a session: world, fakes, their servers, the clock, and fault injection."""

    def __init__(self, clock: SimClock, world: Any, amplifier_fake: Any, amplifier_server: Any,
                 scene: Any, true_views: dict[str, Any], substep_s: float) -> None:
        self.clock = clock
        self.world = world
        self.amplifier_fake = amplifier_fake
        self.amplifier_server = amplifier_server
        self.scene = scene
        self.true_views = true_views
        self.substep_s = substep_s
        self.history = PoseHistory()
        self.grabber_devices: dict[str, Any] = {}
        self.frame_sources: dict[str, FrameSource] = {}
        self.ots_fake: Any = None
        self.ots_server: Any = None
        #: (t, max |measured current|) after every world step: what the coils really carried.
        self.current_trace: list[tuple[float, float]] = []
        self._step_lock = threading.Lock()
        self._frames_held = False
        pose = world.pose
        self.history.append(clock.now(), pose.centroid_mm, pose.direction)

    # -- time ------------------------------------------------------------------------------------
    def measured_currents_a(self) -> np.ndarray:
        """The amplifier fake's coil currents now (brought up to the simulated clock first)."""
        with self.amplifier_server.lock:
            self.amplifier_fake.tick(self.clock.now())
            return self.amplifier_fake.measured_currents_a()

    def step(self, dt_s: float) -> None:
        """Advance world and clock by ``dt_s``, in substeps each holding the amplifier's MEASURED currents."""
        with self._step_lock, self.clock.hold():
            remaining = dt_s
            while remaining > 1e-12:
                h = min(self.substep_s, remaining)
                currents = self.measured_currents_a()
                self.world.step(h, currents)
                t = self.clock.advance(h)
                pose = self.world.pose
                self.history.append(t, pose.centroid_mm, pose.direction)
                self.current_trace.append((t, float(np.max(np.abs(currents)))))
                remaining -= h
            # The fake reflects the end of the step for whoever reads it next.
            self.current_trace.append((self.clock.now(), float(np.max(np.abs(self.measured_currents_a())))))

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
        and shut down: their handshakes wait in real time, and the coils must keep evolving meanwhile)."""
        stop = threading.Event()

        def run() -> None:
            last = time.monotonic()
            while not stop.wait(period_s):
                now = time.monotonic()
                self.step(now - last)
                last = now

        thread = threading.Thread(target=run, name="sim-real-time", daemon=True)
        thread.start()
        try:
            yield
        finally:
            stop.set()
            thread.join(timeout=2.0)

    # -- fault injection -------------------------------------------------------------------------
    def cut_amplifier_link(self) -> None:
        """The amplifier's cable is pulled: no byte passes either way from now on."""
        self.amplifier_server.unplugged.set()

    def press_estop(self) -> None:
        with self.amplifier_server.lock:
            self.amplifier_fake.press_estop()

    def hide_robot(self, hidden: bool = True) -> None:
        """Frames show no robot (it left the field of view, or the images are unusable): tracking is lost."""
        self.history.visible = not hidden

    def stop_grabbers(self) -> None:
        """The imaging chain goes silent (generator off, grabbers stop streaming) without any error."""
        for device in self.grabber_devices.values():
            with device._lock:       # the fake's own lock: a silent stop has no protocol request
                device.streaming = False
        for source in self.frame_sources.values():
            if hasattr(source, "scene"):
                source.scene.rate_hz = 1e-6   # loopback grabber: next frame in 11 days

    def close(self) -> None:
        for server in (self.ots_server, self.amplifier_server):
            if server is not None:
                server.close()
