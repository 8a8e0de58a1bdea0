"""The per-frame loop: newest biplane pair -> posture -> controller -> current allocation -> amplifier.

One owner (the thread that calls :meth:`Orchestrator.step`) runs every stage in order on an injected
monotonic clock (the real one on a bench, the simulated one in simulation); device reader threads only
hand over their newest data (the biplane stream's newest pair, the optical tracker's newest frame, the
amplifier driver's fault events). Every step's stages are timed on the wall clock, and the latency from
"the later frame of the pair is on the host" to "the current command is written to the amplifier" is
measured, as on a bench. Nothing that can wait runs before the write (safety events, the report, the
listeners, the side channels come after it), and the cyclic garbage collector is held off until the write.

Safety: a recognised posture the robot cannot have reached from the last accepted one at the speed
limit (plus ``JUMP_MARGIN_MM``) is rejected as lost - when the robot leaves the images, recognition
can take the contrast-filled vessel for it, and the loop must not steer toward that. The
:class:`~appliance.control.SafetySupervisor` holds, zeroes or stops according to tracking;
in addition the loop latches a stop (output disabled at once, reason recorded) on an amplifier fault,
a lost amplifier link, a silent imaging chain (no pair for ``frame_timeout_ms``), a frame source error
and an operator stop (:meth:`Orchestrator.request_stop`, safe from any thread). :meth:`shutdown` runs
whatever happened (use the orchestrator as a context manager) and ramps the coils to zero and disables
the output; it is idempotent.

Listeners (the recorder, a live view) see every step; an exception in a listener is not swallowed: it
stops the loop and propagates (wrapped in :class:`ListenerError`), and the shutdown still zeroes the coils.
The optical tracker is never in the control path: its failure is recorded and the loop goes on without it.
"""
from __future__ import annotations

import gc
import logging
import math
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from appliance import compiled
from appliance.control import CurrentAllocator, Mode, PathFollower, SafetySupervisor
from appliance.errors import ApplianceError, DeviceError, DeviceFaultError, DeviceTimeoutError, InputDataError
from appliance.geometry import Calibration, dark_level_of
from appliance.loop_events import FrameReport, ListenerError, LoopListener, LoopStats, RecordingListener
from appliance.recognition import PostureTracker, RecognitionSettings
from appliance.session_config import SessionConfig
from drivers.amplifier import Amplifier, AmplifierEvent, AmplifierFaultError
from drivers.biplane_pairing import BiplanePair, BiplaneStream
from drivers.ndi_tracker import NDITracker, ToolSample

log = logging.getLogger(__name__)

__all__ = ["FrameReport", "ListenerError", "LoopListener", "LoopSettings", "LoopStats", "Orchestrator",
           "RecordingListener", "collect_and_freeze_session", "recognition_settings"]

#: Recognition noise allowed on top of the robot's reach when gating a new posture (mm).
JUMP_MARGIN_MM = 2.0
#: Tracked frames (and control steps) :meth:`Orchestrator._rehearse` runs at start-up.
REHEARSAL_TRACKED_PASSES = compiled.BYTECODE_WARM_CALLS


@dataclass(frozen=True)
class LoopSettings:
    """The loop's timing (seconds); see :class:`appliance.session_config.LoopSection`."""

    fps: float = 30.0
    pair_timeout_s: float = 0.5
    frame_timeout_s: float = 0.25
    startup_timeout_s: float = 3.0
    status_every_frames: int = 30
    stop_at_end: bool = True

    @classmethod
    def from_config(cls, config: SessionConfig) -> LoopSettings:
        loop = config.loop
        return cls(fps=config.imaging.fps, pair_timeout_s=loop.pair_timeout_ms / 1000.0,
                   frame_timeout_s=loop.frame_timeout_ms / 1000.0,
                   startup_timeout_s=config.devices.xray.startup_timeout_ms / 1000.0,
                   status_every_frames=loop.status_every_frames, stop_at_end=loop.stop_at_end)


def recognition_settings(config: SessionConfig, calibration: Calibration) -> RecognitionSettings:
    """The session's recognition settings; the detector's dark level comes from the calibration's metadata
    unless the session sets one (it is a property of the detector, measured with its dark frames)."""

    settings = config.recognition
    if settings.dark_level == 0.0:
        settings = settings.model_copy(update={"dark_level": dark_level_of(calibration)})
    return settings


def collect_and_freeze_session() -> None:
    """Collect now and freeze what is left (``gc.freeze``): the devices, kernels, calibration and tracker live
    as long as the session. Otherwise the cyclic collector's first full collection during the loop scans them
    all, inside a frame (57 ms measured in a recognition step of ``appliance sim`` at 768 x 672, load ~6, about
    once per 20 s run); later full collections scan only what the loop made. :meth:`Orchestrator.start` calls
    it last before the output goes on, for a bench and a simulation alike (:meth:`Orchestrator.shutdown`
    unfreezes); the simulation also calls it once its kernels are warm, so that the start's own collection
    is short."""
    gc.collect()
    gc.freeze()


#: The allocation's position before the first tracked frame.
_ORIGIN = (0.0, 0.0, 0.0)


def _xyz(vector: np.ndarray) -> tuple[float, float, float]:
    """A 3-vector as a tuple of Python floats (one numpy call)."""
    x, y, z = vector.tolist()
    return x, y, z


def _sample_record(sample: ToolSample) -> dict[str, Any]:
    return {"handle": sample.handle, "rom": sample.rom, "frame": sample.frame, "missing": sample.missing,
            "position_mm": list(sample.position_mm) if sample.position_mm is not None else None,
            "quaternion": list(sample.quaternion) if sample.quaternion is not None else None,
            "rms_mm": sample.rms_mm}


class Orchestrator:
    """The closed loop over ready devices; context manager: ``start`` on enter, ``shutdown`` on exit."""

    def __init__(self, *, frames: BiplaneStream, amplifier: Amplifier, tracker: PostureTracker,
                 follower: PathFollower, safety: SafetySupervisor, allocator: CurrentAllocator, moment_am2: float,
                 settings: LoopSettings = LoopSettings(), clock: Callable[[], float] = time.monotonic,
                 ots: NDITracker | None = None, listeners: Iterable[LoopListener] = (),
                 names: dict[str, str] | None = None) -> None:
        self.frames, self.amplifier, self.tracker = frames, amplifier, tracker
        self.follower, self.safety, self.allocator = follower, safety, allocator
        self.moment_am2 = moment_am2
        self.settings = settings
        self.clock = clock
        self.ots = ots
        self.listeners = list(listeners)
        self.names = dict(names or {})
        self.stats = LoopStats()
        self.running = False
        self.stop_reason: str | None = None
        self.shutdown_safe: bool | None = None
        self._n = allocator.model.n
        self._commanded = np.zeros(self._n)
        self._position: tuple[float, float, float] | None = None   # the last accepted centroid (mm)
        self._moment_dir: tuple[float, float, float] | None = None
        self._last_tracked: tuple[float, tuple[float, float, float]] | None = None
        self._last_pair_t = 0.0
        self._ots_frame = -1
        self._stop_request: str | None = None
        self._amp_events: list[AmplifierEvent] = []
        self._events_lock = threading.Lock()
        self._shut = False
        self._safety_seen = 0
        self._collector_held = False

    # -- lifecycle ----------------------------------------------------------------------------------
    def __enter__(self) -> Orchestrator:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    def start(self) -> None:
        """Check every device, fail clearly if one is not ready, then enable the amplifier output."""
        status = self.amplifier.status()
        where = self.names.get("amplifier", "the amplifier")
        if status.faults.latched:
            raise DeviceFaultError(f"{where} reports latched faults {status.faults!r}: find the cause, then clear "
                                   f"them (`appliance amp clear`) before a session")
        if self.amplifier.info.channels != self._n:
            raise DeviceError(f"{where} has {self.amplifier.info.channels} channels, the coils file {self._n}")
        try:
            pair = self.frames.next_pair(self.settings.startup_timeout_s)
        except DeviceTimeoutError as err:
            raise DeviceTimeoutError(
                f"no biplane pair from {self.names.get('xray_p', 'plane p')} and {self.names.get('xray_q', 'plane q')} "
                f"within {self.settings.startup_timeout_s:g} s: is the X-ray on and are both grabbers streaming?") from err
        for plane, frame in pair.frames.items():
            size = self.tracker.calibration.views[plane].image_size
            if (frame.width, frame.height) != size:
                raise InputDataError(f"plane {plane} delivers {frame.width}x{frame.height} px images but the "
                                     f"calibration is for {size[0]}x{size[1]}: wrong calibration or grabber mode")
        if self.ots is not None:
            try:
                self.ots.wait_for_frame(timeout_s=self.settings.startup_timeout_s)
            except DeviceError as err:
                raise DeviceTimeoutError(f"optical tracker {self.names.get('ots', '')}: {err}") from err
        # Every compiled kernel (recognition, control) now, while the output is still off: no frame
        # pays for compilation (a first call can take seconds; from the on-disk cache, milliseconds).
        compiled.warm_up_all()
        self._rehearse(pair)
        collect_and_freeze_session()
        # A pair that came in during the start-up (or the collection) is stale now: the first step waits for a fresh one
        # (latest-pair mode only; a replay in all-frames mode keeps every pair).
        if self.frames.pairer.mode == "latest" and self.frames.pairer.ready:
            self.frames.next_pair(0.0)
        self.amplifier.add_listener(self._on_amplifier_event)
        self.amplifier.enable()
        self._commanded = np.zeros(self._n)
        self._last_pair_t = self.clock()
        self.running = True
        self._notify("on_start", self.clock(), {"devices": dict(self.names), "channels": self._n,
                                                "fps": self.settings.fps})
        log.info("loop started: %s", ", ".join(f"{k} = {v}" for k, v in self.names.items()))

    def request_stop(self, reason: str = "operator stop") -> None:
        """Operator stop from any thread: the next step latches STOP and switches the output off."""
        self._stop_request = reason

    def run(self, until: Callable[[FrameReport], bool] | None = None) -> str | None:
        """Step until the loop stops (end of path, a latched stop) or ``until(report)`` is true."""
        while self.running:
            report = self.step()
            if until is not None and until(report):
                break
        return self.stop_reason

    def shutdown(self) -> bool:
        """Ramp the coils to zero and disable the output (whatever happened before); True when the amplifier
        confirmed it. Idempotent."""
        if self._shut:
            return bool(self.shutdown_safe)
        self._shut = True
        self.running = False
        try:
            self.shutdown_safe = self.amplifier.shutdown()
        finally:
            if not self.shutdown_safe:
                log.error("shutdown: the amplifier did not confirm zero current (its watchdog takes over)")
            summary = {"reason": self.stop_reason, "safe": bool(self.shutdown_safe), "steps": self.stats.steps,
                       "pairs": self.stats.pairs, "tracked": self.stats.tracked}
            try:
                self._notify("on_stop", self.clock(), summary)
            finally:
                gc.unfreeze()   # what start froze is collectable again (sessions end; processes may go on)
        return bool(self.shutdown_safe)

    # -- the step -----------------------------------------------------------------------------------
    def step(self) -> FrameReport:
        """One frame: wait for the newest pair, recognise, decide, allocate, command; listeners see the result.

        The cyclic garbage collector is held off from the start of the step to the command's write (or, on
        a latched stop, to the output switched off): a collection falls due at an allocation of whichever
        thread, and between the pair's arrival and the write it would be paid inside the loop's latency.
        Held, it runs at the first allocation after the write instead (the report, the listeners), with
        what it would have collected. A collector the caller switched off stays off."""
        if not self.running:
            raise DeviceError(f"the loop is not running ({self.stop_reason or 'not started'})")
        self._collector_held = gc.isenabled()
        if self._collector_held:
            gc.disable()
        try:
            return self._step()
        finally:
            self._resume_collector()

    def _resume_collector(self) -> None:
        """Let the collector run again if the step held it off (idempotent)."""
        if self._collector_held:
            self._collector_held = False
            gc.enable()

    def _step(self) -> FrameReport:
        stages: dict[str, float] = {}
        began = time.perf_counter()
        self.stats.steps += 1
        fault = self._pending_fault()
        if fault is not None:
            return self._latch(*fault, stages=stages)
        pair, error = self._next_pair()
        stages["wait_pair"] = (time.perf_counter() - began) * 1e6
        now = self.clock()
        if error is not None:
            return self._latch("xray", error, stages=stages)
        if pair is not None:
            self._last_pair_t = now
            self.stats.pairs += 1
        elif now - self._last_pair_t > self.settings.frame_timeout_s:
            return self._latch("xray", f"no biplane pair for {(now - self._last_pair_t) * 1000:.0f} ms "
                                       f"(limit {self.settings.frame_timeout_s * 1000:.0f} ms): the imaging chain stopped",
                               stages=stages)
        else:
            self.stats.no_pair += 1

        mark = time.perf_counter()
        posture = None
        tracked = False
        xyz: tuple[float, float, float] | None = None
        jump: float | None = None
        if pair is not None:
            posture = self.tracker.process(pair.p.image, pair.q.image, frame=pair.number, t=now)
            tracked = posture.ok and posture.centroid_mm is not None
            if tracked:
                # The centroid as plain floats, once: the gate, the speed and the allocation's position take
                # them without a numpy call (each costs the loop 10-20 us after recognition, issue 8).
                xyz = _xyz(posture.centroid_mm)
                jump = self._jump_mm(xyz)
                if not self._plausible(jump, now):
                    # A robot cannot jump: a far-off "robot" is something else (a contrast-filled vessel
                    # when the real one left the images). Treated as lost, so the supervisor holds and zeroes.
                    tracked = False
                    self.stats.rejected += 1
            self.stats.tracked += tracked
            self.stats.lost += not tracked
        stages["recognition"] = (time.perf_counter() - mark) * 1e6

        mark = time.perf_counter()
        command, speed = None, None
        if tracked:
            assert posture is not None and posture.centroid_mm is not None and xyz is not None
            centroid = posture.centroid_mm
            axis = posture.direction if posture.direction is not None else self._moment_dir
            if axis is None:
                axis = self.follower.tangent_at(self.follower.nearest(centroid)[0])
            if jump is not None and self._last_tracked is not None and now > self._last_tracked[0]:
                speed = jump / (now - self._last_tracked[0])
            self._last_tracked = (now, xyz)
            self._position = xyz
            command = self.follower.command(centroid, axis, now)
        decision = self.safety.update(now, tracked, command.field_T if command else None,
                                      command.force_N if command else None, speed)
        stages["control"] = (time.perf_counter() - mark) * 1e6
        if decision.mode is Mode.STOP:
            self._notify_safety_events()
            return self._latch("safety", decision.reason or "safety stop", stages=stages)

        mark = time.perf_counter()
        # The robot's moment lies along the requested field (it aligns within microseconds); with no
        # field, along the last one. Plain floats here, the normalisation inside the allocation kernel.
        field = fx, fy, fz = decision.field_T.tolist()
        field_norm = math.sqrt(fx * fx + fy * fy + fz * fz)
        if field_norm > 0.0:
            self._moment_dir = (fx / field_norm, fy / field_norm, fz / field_norm)
        allocation = self.allocator.allocate_aligned(
            self._position if self._position is not None else _ORIGIN, field, decision.force_N.tolist(),
            self.moment_am2, self._commanded, 1.0 / self.settings.fps,
            zero_field_direction=self._moment_dir if self._moment_dir is not None else (0.0, 0.0, 1.0))
        stages["allocation"] = (time.perf_counter() - mark) * 1e6

        # The command goes out now; everything that can wait (safety events, the report, listeners such
        # as the recorder, the side channels) comes after it.
        sent = time.monotonic()
        try:
            result = self.amplifier.set_currents(allocation.currents_a)
        except AmplifierFaultError as err:
            return self._latch("amplifier", f"amplifier fault: {err}", stages=stages)
        except DeviceError as err:
            return self._latch("amplifier", f"amplifier link: {err}", stages=stages, link_lost=True)
        acked = time.monotonic()
        self._resume_collector()   # what fell due since the step began is collected from here on, after the command
        # The driver's clock is time.monotonic (the frames' host clock) unless a test injected another.
        written = result.written_at_s if sent <= result.written_at_s <= acked else sent
        stages["amplifier"] = (acked - sent) * 1e6
        stages["amplifier_write"] = (written - sent) * 1e6
        self._commanded = result.commanded_a
        self._notify_safety_events()
        if posture is not None:
            for name, us in posture.timings_us.items():
                stages[f"recognition.{name}"] = us
        latency_write = latency_ack = available = None
        if pair is not None:
            available = max(pair.p.host_time_s, pair.q.host_time_s)
            latency_write = written - available
            latency_ack = acked - available
            self.stats.latency_write_s.append(latency_write)
            self.stats.latency_ack_s.append(latency_ack)

        report = FrameReport(
            index=self.stats.steps, t_s=now, frame=pair.number if pair else None,
            posture=posture.to_record() if posture is not None else None, tracked=tracked,
            mode=decision.mode.value, reason=decision.reason,
            cross_track_mm=command.cross_track_mm if command else None,
            progress=command.progress if command else None, done=bool(command and command.done),
            field_T=np.asarray(decision.field_T, float), force_N=np.asarray(decision.force_N, float),
            commanded_a=result.commanded_a, measured_a=result.measured_a, scale=allocation.scale,
            limited_by=allocation.limited_by, stages_us=stages, latency_write_s=latency_write,
            latency_ack_s=latency_ack, images=(pair.p.image, pair.q.image) if pair is not None else None,
            available_s=available, written_s=written)
        self._side_channels(now)
        stages["total"] = (time.perf_counter() - began) * 1e6
        self.stats.step_s.append(stages["total"] / 1e6)
        self._notify("on_frame", report)
        if report.done and self.settings.stop_at_end:
            self.running = False
            self.stop_reason = "the robot reached the end of the path"
            log.info("loop: %s at t = %.2f s", self.stop_reason, now)
        return report

    # -- helpers ------------------------------------------------------------------------------------
    def _rehearse(self, pair: BiplanePair) -> None:
        """Run the step's work on the start-up pair and forget it, before the loop's clock starts.

        Recognition: a detection, then :data:`REHEARSAL_TRACKED_PASSES` tracked frames. A kernel called with
        argument types its warm-up did not cover (read-only frames from a grabber, a view of an array) is
        compiled at its first call, holding the GIL for up to seconds: the amplifier's heartbeat and the
        grabbers' readers would stall with the loop. And CPython runs a function's bytecode unspecialised
        for its first calls (3.11 quickens a code object after 8): the tracked path's Python, the control
        chain's and the amplifier driver's would run so for the session's first pairs (issue 8: pairs 2-4
        slower than the rest). Control: the follower (reset after), a scratch supervisor of the same
        settings (the session's keeps no trace), the allocation (no state), and the driver's command path
        up to the write (nothing is sent: :meth:`~drivers.amplifier.Amplifier.rehearse_command`)."""
        began = time.perf_counter()
        t = self.clock()
        dt = 1.0 / self.settings.fps
        posture = None
        for k in range(1 + REHEARSAL_TRACKED_PASSES):
            posture = self.tracker.process(pair.p.image, pair.q.image, frame=pair.number, t=t + k * dt)
        self.tracker.reset()
        centroid = posture.centroid_mm if posture is not None and posture.centroid_mm is not None else None
        if centroid is None:
            centroid = self.follower.points[0]
        axis = posture.direction if posture is not None and posture.direction is not None else None
        if axis is None:
            axis = self.follower.tangent_at(0.0)
        xyz = _xyz(centroid)
        safety = SafetySupervisor(self.safety.settings)
        commanded = np.zeros(self._n)
        for k in range(REHEARSAL_TRACKED_PASSES):
            command = self.follower.command(centroid, axis, t + k * dt)
            decision = safety.update(t + k * dt, True, command.field_T, command.force_N, 0.0)
            self.allocator.allocate_aligned(xyz, decision.field_T.tolist(), decision.force_N.tolist(),
                                            self.moment_am2, commanded, dt, zero_field_direction=(0.0, 0.0, 1.0))
        self.follower.reset()
        self.amplifier.rehearse_command()
        log.debug("start-up pair rehearsed in %.3f s (compilation of what the warm-ups missed, bytecode "
                  "specialisation)", time.perf_counter() - began)

    def _notify_safety_events(self) -> None:
        """The supervisor's changes of mode since the last call, to the listeners."""
        for event in self.safety.events[self._safety_seen:]:
            self._notify("on_fault", event.t_s, {"device": "safety", "reason": event.reason, "mode": event.mode.value,
                                                 "previous": event.previous.value, "step": self.stats.steps})
        self._safety_seen = len(self.safety.events)

    def _next_pair(self) -> tuple[BiplanePair | None, str | None]:
        try:
            return self.frames.next_pair(self.settings.pair_timeout_s), None
        except DeviceTimeoutError:
            return None, None
        except ApplianceError as err:   # a grabber vanished, a link broke, a source ended
            return None, f"X-ray frames: {err}"

    def _jump_mm(self, xyz: tuple[float, float, float]) -> float | None:
        """The distance (mm) from the last accepted centroid to ``xyz``; None before the first."""
        if self._last_tracked is None:
            return None
        x, y, z = self._last_tracked[1]
        dx, dy, dz = xyz[0] - x, xyz[1] - y, xyz[2] - z
        return math.sqrt(dx * dx + dy * dy + dz * dz)

    def _plausible(self, jump: float | None, now: float) -> bool:
        """Whether a centroid ``jump`` mm from the last accepted one (:meth:`_jump_mm`; None: there is none)
        is reachable at the supervisor's speed limit (plus ``JUMP_MARGIN_MM`` for recognition noise); the gate
        widens the longer the robot was not seen. A NaN jump (a non-finite centroid) is not."""
        if jump is None:
            return True
        t_last = self._last_tracked[0] if self._last_tracked is not None else now
        reach = self.safety.settings.max_robot_speed_mm_s * max(now - t_last, 0.0) + JUMP_MARGIN_MM
        if jump <= reach:
            return True
        log.info("posture rejected: %.1f mm from the last one in %.3f s (reach %.1f mm)", jump, now - t_last, reach)
        return False

    def _on_amplifier_event(self, event: AmplifierEvent) -> None:
        # Called on the driver's heartbeat thread: only hand the event over.
        if event.kind in ("fault", "link_lost"):
            with self._events_lock:
                self._amp_events.append(event)

    def _pending_fault(self) -> tuple[str, str] | None:
        if self._stop_request is not None:
            return "operator", self._stop_request
        with self._events_lock:
            events, self._amp_events = self._amp_events, []
        for event in events:
            return "amplifier", f"amplifier {event.kind.replace('_', ' ')}: {event.message}"
        return None

    def _latch(self, device: str, reason: str, *, stages: dict[str, float], link_lost: bool = False) -> FrameReport:
        """Latched stop: output off at once (unless the link is gone), the reason recorded, the loop ended."""
        now = self.clock()
        decision = self.safety.fault(reason, now)
        self._safety_seen = len(self.safety.events)
        if not link_lost:
            try:
                self.amplifier.disable()
            except ApplianceError as err:
                log.error("stop: could not disable the amplifier output: %s", err)
        self._resume_collector()
        self.running = False
        self.stop_reason = reason
        log.warning("loop stopped at t = %.3f s: %s", now, reason)
        self._notify("on_fault", now, {"device": device, "reason": reason, "mode": decision.mode.value,
                                       "step": self.stats.steps})
        report = FrameReport(
            index=self.stats.steps, t_s=now, frame=None, posture=None, tracked=False, mode=decision.mode.value,
            reason=reason, cross_track_mm=None, progress=None, done=False, field_T=np.zeros(3),
            force_N=np.zeros(3), commanded_a=np.zeros(self._n), measured_a=None, scale=0.0, limited_by=None,
            stages_us=stages, stopped=True)
        self._notify("on_frame", report)
        return report

    def _side_channels(self, now: float) -> None:
        """OTS samples and device status, recorded beside the loop (never steering it)."""
        if self.ots is not None:
            try:
                samples = self.ots.latest()
            except ApplianceError as err:
                log.error("optical tracker lost (%s); the loop goes on without it", err)
                self._notify("on_fault", now, {"device": "ots", "reason": f"optical tracker: {err}",
                                               "mode": "continue", "step": self.stats.steps})
                self.ots = None
                samples = None
            if samples and samples[0].frame != self._ots_frame:
                self._ots_frame = samples[0].frame
                self._notify("on_ots", now, [_sample_record(s) for s in samples])
        if self.stats.steps % self.settings.status_every_frames == 1:
            status = self.amplifier.status()
            self._notify("on_status", now, "amplifier", {
                "state": status.state.name, "faults": repr(status.faults), "uptime_s": status.uptime_s,
                "measured_a": status.measured_a.tolist(), "setpoint_a": status.setpoint_a.tolist(),
                "temperature_c": status.temperature_c.tolist(), "retransmissions": self.amplifier.retransmissions})
            counters = self.frames.pairer.counters
            self._notify("on_status", now, "xray", {
                "pairs": counters.pairs, "superseded": counters.superseded, "unpaired_p": counters.unpaired_p,
                "unpaired_q": counters.unpaired_q,
                **{f"{plane}_{k}": v for plane, source in self.frames.sources.items()
                   for k, v in vars(source.counters).items()}})

    def _notify(self, method: str, *args: Any) -> None:
        for listener in self.listeners:
            try:
                getattr(listener, method)(*args)
            except Exception as err:
                self.running = False
                self.stop_reason = f"listener {type(listener).__name__} failed in {method}: {err}"
                log.error("loop: %s", self.stop_reason)
                raise ListenerError(self.stop_reason) from err
