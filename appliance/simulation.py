"""The simulation harness: the closed loop of a session whose devices are all loopback fakes.

The harness owns simulated time. Frame ``n`` of both X-ray planes starts its exposure at ``n / fps`` on
the simulated clock; the harness steps the world (in pieces of ``substep_ms``, each holding the
amplifier fake's MEASURED coil currents, so the coils' L/R lag, slew limits and faults act on the robot)
up to ``n / fps + loop_latency_ms`` and then runs one orchestrator step, which gets pair ``n`` through
the real transports (fake USB grabbers -> pyusb -> USB grabber driver -> biplane pairing), recognises
the robot, and commands the amplifier over its pty. The grabbers see the frames of a world step only
when the loop asks for its pair (as on a bench, where the loop is waiting when a pair comes in), so the
measured latency from a pair on the host to the command written is the appliance's, not the harness's.
Each grabber streams its frame over a modelled USB 3 link (``device_factory``: ~3 ms for 768 x 672 mono16,
in the driver's 64 KiB transfers), so a frame is on the host when its last transfer is in, and its earlier
transfers were checked while the later ones were on the wire, as from a real grabber. Nothing of the lab
runs between the pair's arrival and the command: the world is stepped before the frames are released,
and an exposure is rendered when its grabber reads it out, before its transfers.
The simulated lab - world, amplifier fake, tracker fake and X-ray renderer - runs in one child process
(other machines on a bench; ``separate_lab=False`` keeps it in this one): this process has only the
amplifier's and the tracker's ptys and the grabbers' USB backend, and the harness steps the world and reads
its truth through a proxy over a pipe. If that process ends, the loop stops (the stop reason names the lost
lab, or the amplifier's driver finds its link gone, as with a real device that drops out) and the run's
truth up to then is kept. The frames show the robot as it was at mid-exposure (the world keeps a short
pose history), so the modelled latency between exposure and command acts on the loop as a real one would.
Simulated time does not depend on how long the host takes: the run is faster than real time when a step
takes less than ``1 / fps`` of wall time, slower otherwise (:attr:`SimResult.realtime_factor` says which).

Device start-up and shutdown happen with the world following the wall clock (their handshakes and
ramps wait in real time); after the loop has stopped the world runs ``settle_ms`` more of simulated
time so the coils' decay is observed in the fake's measured currents.

Faults can be scheduled at simulated times: the amplifier link cut, the e-stop pressed, the robot
vanishing from the images (tracking loss), the grabbers going silent.
"""
from __future__ import annotations

import dataclasses
import gc
import logging
import math
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from appliance import compiled
from appliance.control import ActuationModel, CurrentAllocator, PathFollower, SafetySupervisor, load_coils, load_path
from appliance.device_factory import Devices, open_devices
from appliance.errors import ConfigError, DeviceError
from appliance.orchestrator import (
    FrameReport,
    LoopListener,
    LoopSettings,
    Orchestrator,
    collect_and_freeze_session,
    recognition_settings,
)
from appliance.recognition import PostureTracker
from appliance.robots import load_robots, select_robot
from appliance.session_config import Session
from appliance.sim_bench import SimBench
from drivers.biplane_pairing import BiplanePair, BiplaneStream

log = logging.getLogger(__name__)

FAULTS = ("amplifier_link", "estop", "tracking", "grabber")
ZERO_CURRENT_A = 0.05   # what counts as "coils at zero" (the amplifier driver's shutdown threshold)


@dataclass
class TruthSample:
    t_s: float
    centroid_mm: np.ndarray
    cross_track_mm: float     # TRUE centroid to the operator's path


@dataclass
class SimResult:
    """What a simulated run did, with the truth to judge it by."""

    start_s: float
    end_s: float
    wall_s: float
    stop_reason: str | None
    reached_end_s: float | None          # simulated seconds from start to the end of the path
    truth: list[TruthSample]
    tracked_mm: list[np.ndarray]
    reports: list[FrameReport]
    current_trace: list[tuple[float, float]]
    fault_times: dict[str, float] = field(default_factory=dict)
    stop_t_s: float | None = None
    shutdown_safe: bool | None = None
    path_mm: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def sim_s(self) -> float:
        return self.end_s - self.start_s

    @property
    def realtime_factor(self) -> float:
        """Simulated seconds per wall second: > 1 faster than real time, < 1 slower."""
        return self.sim_s / self.wall_s if self.wall_s > 0 else math.inf

    def cross_track(self) -> np.ndarray:
        return np.array([s.cross_track_mm for s in self.truth])

    def currents_zero_after(self, t_s: float, threshold_a: float = ZERO_CURRENT_A) -> float | None:
        """The first simulated time after ``t_s`` from which every measured coil current stays below
        ``threshold_a`` to the end of the trace; None if they never settle."""
        settled: float | None = None
        for t, peak in self.current_trace:
            if t < t_s:
                continue
            if peak < threshold_a:
                settled = t if settled is None else settled
            else:
                settled = None
        return settled


def path_distance(points: np.ndarray, point: np.ndarray) -> float:
    """Distance from ``point`` to the polyline ``points`` (full search, independent of the follower)."""
    a = points[:-1]
    seg = np.diff(points, axis=0)
    lengths2 = np.einsum("ij,ij->i", seg, seg)
    t = np.clip(np.einsum("ij,ij->i", point - a, seg) / lengths2, 0.0, 1.0)
    return float(np.min(np.linalg.norm(point - (a + t[:, None] * seg), axis=1)))


class _ReleasingStream:
    """The biplane stream as the harness hands it to the orchestrator.

    Asking for a pair first releases the frames of the world step just done
    (:meth:`SimBench.release_frames`): on a bench the loop is waiting when a pair comes in, and here a
    pair released at the end of the step could otherwise reach the host while the harness is still on
    its way back to the loop, a wait that would count as loop latency. Then it waits for the pair the
    step is for (number ``expect``, the grabbers having started at simulated t = 0): the newest pair
    ready at that moment is the previous one (it arrived while the loop was busy with the one before),
    and taking it would put the loop a whole frame behind the modelled latency, for good.
    """

    def __init__(self, stream: BiplaneStream, bench: SimBench) -> None:
        self._stream = stream
        self._bench = bench
        self.expect: int | None = None
        self.stale = 0           # pairs older than the one the step was for, passed over

    def next_pair(self, timeout_s: float) -> BiplanePair:
        self._bench.release_frames()
        deadline = time.monotonic() + timeout_s
        while True:
            pair = self._stream.next_pair(max(deadline - time.monotonic(), 0.0))
            if self.expect is None or pair.number >= self.expect:
                return pair
            self.stale += 1

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


class Simulation:
    """A whole simulated session: devices (fakes on real transports), appliance stack and harness."""

    def __init__(self, session: Session, listeners: Iterable[LoopListener] = (), *, separate_lab: bool = True) -> None:
        config = session.config
        if not config.is_simulation:
            raise ConfigError(f"{session.source}: not a simulation session (devices must be kind: loopback); "
                              f"use `appliance run` for real devices")
        self.session = session
        self.robot = select_robot(load_robots(session.robots_path), config.robot.id)
        self.coils = load_coils(session.coils_path)
        self.path = load_path(session.vessel_path)
        self.devices: Devices = open_devices(session, self.robot, self.coils, separate_lab=separate_lab)
        try:
            assert self.devices.sim is not None
            self.bench: SimBench = self.devices.sim
            self.follower = PathFollower(self.path, config.control)
            self.frames = _ReleasingStream(self.devices.frames, self.bench)
            self.orchestrator = Orchestrator(
                frames=self.frames, amplifier=self.devices.amplifier,
                tracker=PostureTracker(self.devices.calibration,
                                       recognition_settings(config, self.devices.calibration), body=self.robot),
                follower=self.follower,
                safety=SafetySupervisor(config.safety), allocator=CurrentAllocator(ActuationModel(self.coils)),
                moment_am2=self.robot.magnetic_moment_am2, settings=LoopSettings.from_config(config),
                clock=self.bench.clock, ots=self.devices.ots, listeners=listeners, names=self.devices.names)
            # Compile the kernels now, while simulated time stands still: the orchestrator's start()
            # (which would do it otherwise) runs with the world following the wall clock, and after a
            # cold compile (minutes on a loaded machine) the world's catch-up would outlast the start
            # and hold the amplifier fake's lock while the loop waits for its replies.
            compiled.warm_up_all()
            # While simulated time stands still; the orchestrator's start does it again (only what was made
            # since to scan) before the output goes on.
            collect_and_freeze_session()
        except BaseException:
            self.devices.close()
            raise

    def __enter__(self) -> Simulation:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        gc.unfreeze()
        self.devices.close()

    def inject(self, fault: str) -> None:
        """Inject one of :data:`FAULTS` now."""
        bench = self.bench
        actions: dict[str, Callable[[], None]] = {
            "amplifier_link": bench.cut_amplifier_link, "estop": bench.press_estop,
            "tracking": bench.hide_robot, "grabber": bench.stop_grabbers}
        if fault not in actions:
            raise ValueError(f"unknown fault {fault!r}; known: {', '.join(FAULTS)}")
        log.warning("simulation: injecting %s at t = %.3f s", fault, bench.clock.now())
        actions[fault]()

    def run(self, seconds: float | None = None, faults: Mapping[str, float] | None = None,
            on_step: Callable[[FrameReport, TruthSample], None] | None = None) -> SimResult:
        """Run the loop for at most ``seconds`` of simulated time (default: the session's ``max_seconds``),
        with ``faults`` injected at the given simulated seconds after the start."""
        config = self.session.config
        seconds = config.simulation.max_seconds if seconds is None else seconds
        pending = sorted((t, name) for name, t in (faults or {}).items())
        for _, name in pending:
            if name not in FAULTS:
                raise ValueError(f"unknown fault {name!r}; known: {', '.join(FAULTS)}")
        bench, orchestrator = self.bench, self.orchestrator
        fps = config.imaging.fps
        latency = config.simulation.loop_latency_ms / 1000.0
        truth: list[TruthSample] = []
        tracked: list[np.ndarray] = []
        reports: list[FrameReport] = []
        fault_times: dict[str, float] = {}
        reached: float | None = None
        stop_t: float | None = None

        with bench.real_time():
            orchestrator.start()
        start = bench.clock.now()
        wall_start = time.perf_counter()
        frame = math.floor(start * fps) + 1
        lab_lost: DeviceError | None = None
        try:
            while orchestrator.running and bench.clock.now() - start < seconds:
                target = frame / fps + latency
                try:
                    while pending and start + pending[0][0] <= target:
                        at, name = pending.pop(0)
                        bench.advance_to(start + at, release=False)
                        self.inject(name)
                        fault_times[name] = bench.clock.now()
                    bench.advance_to(target, release=False)
                except DeviceError as err:
                    # The simulated lab dropped out (its process ended): stop the loop as an operator would
                    # when the bench's devices go; the amplifier's driver sees its link lost as well.
                    lab_lost = err
                    log.error("simulation: %s", err)
                    orchestrator.request_stop(f"simulated lab lost: {err}")
                self.frames.expect = frame
                report = orchestrator.step()
                if lab_lost is not None:
                    reports.append(_kept(report))
                    stop_t = report.t_s if report.stopped else stop_t
                    break
                pose = bench.pose()
                sample = TruthSample(bench.clock.now(), pose.centroid_mm,
                                     path_distance(self.follower.points, pose.centroid_mm))
                truth.append(sample)
                reports.append(_kept(report))
                if report.tracked and report.posture is not None:
                    tracked.append(np.asarray(report.posture["centroid_mm"], float))
                if report.done and reached is None:
                    reached = report.t_s - start
                if report.stopped:
                    stop_t = report.t_s
                if on_step is not None:
                    on_step(report, sample)
                frame = max(frame + 1, (report.frame or 0) + 1)
        finally:
            self.frames.expect = None
            bench.release_frames()
            wall = time.perf_counter() - wall_start
            end = bench.clock.now()
            with bench.real_time():
                safe = orchestrator.shutdown()
            try:
                bench.step(config.simulation.settle_ms / 1000.0)
            except DeviceError as err:   # the lab dropped out: there is no world left to settle
                log.error("simulation: the coils' decay after the stop was not simulated: %s", err)
        return SimResult(start_s=start, end_s=end, wall_s=wall, stop_reason=orchestrator.stop_reason,
                         reached_end_s=reached, truth=truth, tracked_mm=tracked, reports=reports,
                         current_trace=list(bench.current_trace), fault_times=fault_times, stop_t_s=stop_t,
                         shutdown_safe=safe, path_mm=self.follower.points.copy())


def _kept(report: FrameReport) -> FrameReport:
    """The report as the run's result keeps it: without the pair's images (the listeners have seen them). Kept,
    they would hold every frame of the run in memory (2 x 1 MB a step at 768 x 672) and, with them, every
    buffer the grabbers' drivers would otherwise reuse."""
    return dataclasses.replace(report, images=None)


def percentile_ms(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values) * 1e3, q)) if values else math.nan


def latency_line(stats: Any, acknowledged: bool = True) -> str:
    """The summary's loop-latency line (``appliance sim`` and ``appliance run``): frame on host -> command
    written, and -> acknowledged, p50 and p99 to 10 us (a p99 moves by tenths of a millisecond)."""
    line = (f"  loop latency  frame on host -> command written: p50 {percentile_ms(stats.latency_write_s, 50):.2f} ms, "
            f"p99 {percentile_ms(stats.latency_write_s, 99):.2f} ms")
    if acknowledged:
        line += (f"; -> acknowledged: p50 {percentile_ms(stats.latency_ack_s, 50):.2f} ms, "
                 f"p99 {percentile_ms(stats.latency_ack_s, 99):.2f} ms")
    return line


def summary_lines(result: SimResult, stats: object) -> list[str]:
    """The end-of-run summary (``appliance sim``): accuracy against the truth, frames, latency, speed."""
    from appliance.orchestrator import LoopStats

    assert isinstance(stats, LoopStats)
    cross = result.cross_track()
    rms = float(np.sqrt(np.mean(cross ** 2))) if len(cross) else math.nan
    peak = float(cross.max()) if len(cross) else math.nan
    end = (f"{result.reached_end_s:.2f} s" if result.reached_end_s is not None
           else f"not reached in {result.sim_s:.1f} s")
    speed = "faster" if result.realtime_factor >= 1.0 else "slower"
    return [
        f"  stop          {result.stop_reason or 'time limit'}",
        f"  cross-track   RMS {rms:.3f} mm   max {peak:.3f} mm   (true centroid to the path, {len(cross)} frames)",
        f"  path end      {end}",
        (f"  frames        {stats.pairs} pairs: {stats.tracked} tracked, {stats.lost} lost; "
        f"{stats.no_pair} steps without a new pair"),
        latency_line(stats),
        (f"  time          {result.sim_s:.2f} s simulated in {result.wall_s:.2f} s wall: "
        f"{speed} than real time (x{result.realtime_factor:.2f})"),
        f"  coils         {'ramped to zero and disabled' if result.shutdown_safe else 'NOT confirmed at zero by the amplifier'}",
    ]
