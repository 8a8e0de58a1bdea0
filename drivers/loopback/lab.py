"""The simulated lab: the world and the device fakes that act on it, stepped together on one clock.

:class:`LoopbackLab` holds what a bench has outside the appliance: the simulated world (robot, coils,
vessel), the amplifier fake and the NDI tracker fake (each behind its server on a pty or a TCP port),
the robot's recent poses (so an X-ray exposure at ``t`` shows the robot as it was then) and the trace of
the currents the coils really carried. :meth:`LoopbackLab.step` advances world and clock in substeps,
each holding the amplifier fake's MEASURED coil currents, so the coils' L/R lag, slew limits and faults
act on the robot.

It also renders the X-ray exposures (:meth:`LoopbackLab.render_at`: the robot as it was at the exposure's
time) and holds what the validation's simulated hands change: the phantom on the table (another
renderer), the robot clamped at a pose, the tracked pointer's motion (:meth:`LoopbackLab.set_pointer`).

It runs in a child process by default (:mod:`drivers.loopback.lab_process`, as the devices of a bench are
other machines) or in the appliance's process (``open_devices(separate_lab=False)``: tests, comparisons).
The clock is the caller's: the harness's simulated clock in-process, a :class:`LabClock` in the child.
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


class Exposures:
    """The renderer as an X-ray scene (``LoopbackScene``) calls it: ``render(t)`` is the exposure at simulated
    ``t`` (the scene's provider hands the time on), the robot drawn as it was then."""

    def __init__(self, render_at: Any, views: Any, process: Any = None) -> None:
        self.render = render_at
        self.views = views
        self.process = process            # the process that renders, when it is another one


class LoopbackLab:
    """World, amplifier fake, tracker fake (with their servers) and the X-ray renderer on one clock; see the
    module docstring. The tracker fake is attached with :meth:`attach_tracker` (its poses come from
    :meth:`tool_poses`)."""

    def __init__(self, clock: Any, world: SimWorld, amplifier_fake: Any, amplifier_server: Any, substep_s: float,
                 *, renderer: Any = None) -> None:
        self.clock = clock
        self.world = world
        self.amplifier_fake = amplifier_fake
        self.amplifier_server = amplifier_server
        self.ots_fake: Any = None
        self.ots_server: Any = None
        self.substep_s = substep_s
        self.renderer = renderer
        self._renderers: list[Any] = []     # the ones replace_renderer put aside
        self.exposures = Exposures(self.render_at, getattr(renderer, "views", None),
                                   getattr(renderer, "process", None))
        self.history = PoseHistory()
        #: (t, max |measured current|) after every world step: what the coils really carried.
        self.current_trace: list[tuple[float, float]] = []
        self._step_lock = threading.RLock()
        self._pointer: Any = None
        self._pointer_in_use = False
        pose = world.pose
        self.history.append(clock.now(), pose.centroid_mm, pose.direction)

    def attach_tracker(self, ots_fake: Any, ots_server: Any) -> None:
        """The tracker fake (built with :meth:`tool_poses` as its provider) and its server."""
        self.ots_fake, self.ots_server = ots_fake, ots_server

    def tool_poses(self, now: float) -> dict[int, Any]:
        """What the tracker sees: tool 0 the holder rigidly on the robot; tool 1, once :meth:`use_pointer` was
        called, the validation's pointer (None while it is put away)."""
        holder = self.world.tool_pose()
        poses: dict[int, Any] = {0: (holder.rotation, holder.position_mm)}
        if self._pointer_in_use:
            poses[1] = self._pointer(now) if self._pointer is not None else None
        return poses

    # -- the validation's hands (appliance validate in simulation) -------------------------------------------
    def use_pointer(self) -> None:
        """From now on the tracker also sees tool 1, the pointer (its current frame is measured again)."""
        self._pointer_in_use = True
        if self.ots_fake is not None:
            with self.ots_server.lock:
                self.ots_fake.provider = self.tool_poses

    def set_pointer(self, pose: Any) -> None:
        """The pointer's pose from now on: a callable ``pose(now) -> (R, t_mm)`` (picklable when the lab is in
        another process: ``ots_poses.HeldPose``, ``ots_poses.PivotingPose``), or None (put away)."""
        self._pointer = pose

    def pass_time(self, seconds: float) -> None:
        """Let time pass without the world's dynamics (the robot clamped in its holder)."""
        self.clock.advance(seconds)

    def pass_time_to(self, t_s: float) -> None:
        self.clock.advance_to(t_s)

    def place_robot(self, centroid_mm: Any, direction: Any) -> None:
        """Clamp the robot at a new pose now: exposures before now show the old pose, after it the new one."""
        t = self.clock.now()
        old = self.world.pose
        self.history.append(t, old.centroid_mm, old.direction)
        self.world.set_pose(centroid_mm, direction)
        new = self.world.pose
        self.history.append(t + 1e-9, new.centroid_mm, new.direction)

    def replace_renderer(self, renderer: Any) -> None:
        """Render with ``renderer`` (another phantom on the table) until :meth:`restore_renderer`."""
        self._renderers.append(self.renderer)
        self.renderer = renderer

    def restore_renderer(self) -> None:
        self.renderer = self._renderers.pop()

    @property
    def renderer_settings(self) -> Any:
        return self.renderer.settings

    def render_at(self, t_s: float) -> Any:
        """The exposure at simulated ``t_s`` (``RenderedPair``): the robot as it was then, or none when hidden."""
        return self.renderer.render(self.exposure_pose(t_s))

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
