"""The simulated lab: the world and the device fakes that act on it, stepped together on one clock.

:class:`LoopbackLab` holds what a bench has outside the appliance: the simulated world (robot, coils,
vessel), the amplifier fake and the NDI tracker fake (each behind its server on a pty or a TCP port),
the robot's recent poses (so an X-ray exposure at ``t`` shows the robot as it was then) and the trace of
the currents the coils really carried. :meth:`LoopbackLab.step` advances world and clock in substeps,
each holding the amplifier fake's MEASURED coil currents, so the coils' L/R lag, slew limits and faults
act on the robot.

It runs either in the appliance's process (the device factory's in-process lab, which the validation's
simulated hands need: they swap the tracker's pose provider and the renderer) or in a child process
(:mod:`drivers.loopback.lab_process`, the default of the simulation harness, as the devices of a bench
are other machines). The clock is the caller's: the harness's simulated clock in-process, a
:class:`LabClock` in the child.
"""
from __future__ import annotations

import itertools
import threading
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from drivers.loopback.world import RobotState, SimWorld


class LabClock:
    """Simulated time (s) in the lab's own process: only the lab's steps move it."""

    def __init__(self, start_s: float = 0.0) -> None:
        self._t = float(start_s)

    def __call__(self) -> float:
        return self._t

    def now(self) -> float:
        return self._t

    def advance(self, dt_s: float) -> float:
        if not dt_s >= 0.0:
            raise ValueError(f"simulated time only moves forward, got dt {dt_s}")
        self._t += dt_s
        return self._t

    def advance_to(self, t_s: float) -> float:
        """Set the clock to ``t_s`` exactly (never backwards): the lab's time equals the harness's."""
        self._t = max(self._t, float(t_s))
        return self._t


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


class LoopbackLab:
    """World, amplifier fake and tracker fake (with their servers) on one clock; see the module docstring."""

    def __init__(self, clock: Any, world: SimWorld, amplifier_fake: Any, amplifier_server: Any, substep_s: float,
                 *, ots_fake: Any = None, ots_server: Any = None) -> None:
        self.clock = clock
        self.world = world
        self.amplifier_fake = amplifier_fake
        self.amplifier_server = amplifier_server
        self.ots_fake = ots_fake
        self.ots_server = ots_server
        self.substep_s = substep_s
        self.history = PoseHistory()
        #: (t, max |measured current|) after every world step: what the coils really carried.
        self.current_trace: list[tuple[float, float]] = []
        self._step_lock = threading.RLock()
        pose = world.pose
        self.history.append(clock.now(), pose.centroid_mm, pose.direction)

    def measured_currents_a(self) -> np.ndarray:
        """The amplifier fake's coil currents now (brought up to the clock first)."""
        with self.amplifier_server.lock:
            self.amplifier_fake.tick(self.clock.now())
            return self.amplifier_fake.measured_currents_a()

    def step(self, dt_s: float) -> RobotState:
        """Advance world and clock by ``dt_s``, in substeps each holding the amplifier's MEASURED currents;
        returns the world's pose at the end."""
        with self._step_lock:
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
            return self.world.pose

    def step_to(self, t_s: float) -> RobotState:
        """Step to ``t_s`` and leave the clock at exactly ``t_s`` (the lab's own :class:`LabClock`)."""
        with self._step_lock:
            pose = self.step(t_s - self.clock.now()) if t_s > self.clock.now() else self.world.pose
            self.clock.advance_to(t_s)
            return pose

    def pose(self) -> RobotState:
        return self.world.pose

    def exposure_pose(self, t_s: float) -> Any:
        """What an exposure at ``t_s`` shows: the robot's pose then (``RobotPose``), or None when hidden."""
        from drivers.loopback.xray_render import RobotPose

        if not self.history.visible:
            return None
        centroid, direction = self.history.at(t_s)
        return RobotPose(centroid, direction)

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

    def close(self) -> None:
        for server in (self.ots_server, self.amplifier_server):
            if server is not None:
                server.close()
