"""The frame loop's own behaviours on the simulated bench: start-up checks, listeners, operator stop.

The devices are the loopback fakes over real transports (small images, a fraction of a second of
simulated time per test); the fault behaviours are in ``test_simulation.py``.
"""
from __future__ import annotations

import copy
import gc
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from appliance.control import Mode
from appliance.config_io import config_path, read_yaml
from appliance.device_factory import perturbed_calibration
from appliance.errors import DeviceFaultError, InputDataError
from appliance.orchestrator import FrameReport, ListenerError, LoopListener, LoopSettings
from appliance.session_config import Session, session_from_mapping
from appliance.simulation import ZERO_CURRENT_A, Simulation
from drivers.loopback.xray_render import biplane_views


def small_session(**sections: dict[str, Any]) -> Session:
    data = copy.deepcopy(read_yaml(config_path("sim.yaml")))
    data["imaging"]["image_size"] = [256, 224]
    data["devices"]["ots"] = {"kind": "none"}
    # Not tests of the link's timing: the simulated lab's process, where the amplifier fake answers, is left
    # without a core for over 3 x 50 ms (sim.yaml's ack time-out) on a loaded 2-core machine (load 12-19).
    data["devices"]["amplifier"] = {**data["devices"]["amplifier"], "ack_timeout_ms": 1000.0}
    data["loop"] = {"pair_timeout_ms": 150, "frame_timeout_ms": 250}
    data["simulation"] = {"seed": 0, "settle_ms": 300}
    for key, value in sections.items():
        data[key] = {**data.get(key, {}), **value}
    return session_from_mapping(data, config_path("sim.yaml"))


def coils_are_off(sim: Simulation) -> bool:
    snapshot = sim.bench.amplifier_fake.snapshot()
    return not snapshot.output_on and float(np.max(np.abs(snapshot.measured_a))) < ZERO_CURRENT_A


class Collector(LoopListener):
    def __init__(self, fail_at: int | None = None) -> None:
        self.frames: list[FrameReport] = []
        self.started: list[dict[str, Any]] = []
        self.stopped: list[dict[str, Any]] = []
        self.status: list[str] = []
        self.fail_at = fail_at

    def on_start(self, t_s: float, info: dict[str, Any]) -> None:
        self.started.append(info)

    def on_frame(self, report: FrameReport) -> None:
        self.frames.append(report)
        if self.fail_at is not None and len(self.frames) == self.fail_at:
            raise OSError("disk full")

    def on_status(self, t_s: float, device: str, status: dict[str, Any]) -> None:
        self.status.append(device)

    def on_stop(self, t_s: float, summary: dict[str, Any]) -> None:
        self.stopped.append(summary)


def test_listeners_see_start_frames_status_and_stop() -> None:
    collector = Collector()
    with Simulation(small_session(), [collector]) as sim:
        result = sim.run(0.5)
        assert coils_are_off(sim)
    assert collector.started and "amplifier" in collector.started[0]["devices"]
    assert len(collector.frames) == len(result.reports) >= 14
    # Listeners see each pair's images; the run's result does not keep them (nor, so, every frame of the run).
    assert all(r.images is not None for r in collector.frames) and all(r.images is None for r in result.reports)
    assert [r.frame for r in collector.frames] == sorted({r.frame for r in collector.frames})
    assert {"amplifier", "xray"} <= set(collector.status)
    assert collector.stopped == [{"reason": None, "safe": True, "steps": len(result.reports),
                                  "pairs": len(result.reports), "tracked": sim.orchestrator.stats.tracked}]
    report = collector.frames[-1]
    assert report.measured_a is not None and report.commanded_a.shape == (8,)
    assert {"wait_pair", "recognition", "control", "allocation", "amplifier", "total"} <= set(report.stages_us)
    assert report.latency_write_s is not None and 0.0 < report.latency_write_s <= report.latency_ack_s


def test_the_loop_runs_with_the_sessions_objects_frozen_out_of_the_collector() -> None:
    class FreezeCounts(LoopListener):
        def __init__(self) -> None:
            self.at_start: int | None = None
            self.in_loop: list[int] = []

        def on_start(self, t_s: float, info: dict[str, Any]) -> None:
            self.at_start = gc.get_freeze_count()

        def on_frame(self, report: FrameReport) -> None:
            self.in_loop.append(gc.get_freeze_count())

    counts = FreezeCounts()
    with Simulation(small_session(), [counts]) as sim:
        gc.unfreeze()            # whatever the harness froze: the orchestrator's start alone must do it
        assert gc.get_freeze_count() == 0
        sim.run(0.3)
        assert gc.get_freeze_count() == 0                  # the shutdown unfroze
    # The session's objects (~160 thousand), not a handful; frozen objects freed by reference counting
    # leave the count, so it may fall a little during the loop but does not go back to zero.
    assert counts.at_start is not None and counts.at_start > 10_000
    assert counts.in_loop and min(counts.in_loop) > counts.at_start // 2


def test_the_collector_is_held_off_from_the_steps_start_to_the_write_and_not_after() -> None:
    seen: dict[str, list[tuple[int, bool]]] = {"recognition": [], "command": [], "listener": []}

    class Enabled(LoopListener):
        def on_frame(self, report: FrameReport) -> None:
            seen["listener"].append((report.index, gc.isenabled()))

    with Simulation(small_session(), [Enabled()]) as sim:
        orchestrator = sim.orchestrator
        process, set_currents = orchestrator.tracker.process, orchestrator.amplifier.set_currents

        def watched(name: str, call: Any) -> Any:
            def inner(*args: Any, **kwargs: Any) -> Any:
                if orchestrator.running:                   # not the start-up's rehearsal
                    seen[name].append((orchestrator.stats.steps, gc.isenabled()))
                return call(*args, **kwargs)
            return inner

        orchestrator.tracker.process = watched("recognition", process)   # type: ignore[method-assign]
        orchestrator.amplifier.set_currents = watched("command", set_currents)   # type: ignore[method-assign]

        def on_step(report: FrameReport, truth: Any) -> None:
            if report.index == 3:
                gc.disable()                               # a caller's choice is left alone ...
            elif report.index == 4:
                gc.enable()
            elif report.index == 8:
                orchestrator.request_stop("operator stop")

        try:
            sim.run(1.0, on_step=on_step)
        finally:
            gc.enable()
        assert orchestrator.stop_reason == "operator stop"
    assert len(seen["recognition"]) == len(seen["command"]) == 8
    assert not any(enabled for _, enabled in seen["recognition"] + seen["command"])
    # After the write the collector runs again (the listeners see it on), also after the latched stop (step 9) ...
    assert [enabled for index, enabled in seen["listener"] if index != 4] == [True] * 8
    # ... except where the caller had switched it off: then the step does not switch it on.
    assert dict(seen["listener"])[4] is False


def test_a_failing_listener_stops_the_loop_and_the_coils_still_go_to_zero() -> None:
    collector = Collector(fail_at=5)
    with Simulation(small_session(), [collector]) as sim:
        with pytest.raises(ListenerError, match="Collector failed in on_frame: disk full"):
            sim.run(1.0)
        assert not sim.orchestrator.running
        assert coils_are_off(sim)
    assert len(collector.frames) == 5          # no step after the failure


def test_operator_stop_latches_and_switches_the_output_off() -> None:
    with Simulation(small_session()) as sim:
        def stop_after_ten(report: FrameReport, truth: Any) -> None:
            if report.index == 10:
                sim.orchestrator.request_stop("operator pressed stop")
        result = sim.run(1.0, on_step=stop_after_ten)
        assert result.stop_reason == "operator pressed stop"
        assert result.reports[-1].stopped and result.reports[-1].mode == "stop"
        assert len(result.reports) == 11
        assert coils_are_off(sim)
        assert sim.orchestrator.safety.mode.value == "stop"


def test_start_up_refuses_an_amplifier_with_a_latched_fault() -> None:
    with Simulation(small_session()) as sim:
        sim.bench.press_estop()
        with pytest.raises(DeviceFaultError, match=r"loopback amplifier on /dev/pts/\d+ reports latched faults"):
            sim.run(0.2)
        assert not sim.bench.amplifier_fake.snapshot().output_on   # never enabled


def test_start_up_refuses_frames_that_do_not_fit_the_calibration(tmp_path: Path) -> None:
    wrong = perturbed_calibration(biplane_views(image_size=(320, 280)), 0.0, 0.0, 0)
    wrong.save(tmp_path / "calibration.yaml")
    session = small_session(calibration={"source": "file", "file": str(tmp_path / "calibration.yaml")})
    with Simulation(session) as sim, pytest.raises(InputDataError, match="256x224 px images but the calibration "
                                                                         "is for 320x280"):
        sim.run(0.2)


def test_loop_settings_come_from_the_session() -> None:
    settings = LoopSettings.from_config(small_session(loop={"frame_timeout_ms": 400}).config)
    assert settings.fps == 30.0 and settings.frame_timeout_s == 0.4 and settings.pair_timeout_s == 0.15


def test_a_posture_out_of_the_robots_reach_is_rejected_as_lost_and_the_speed_is_the_accepted_steps() -> None:
    """The jump gate: a recognised centroid farther from the last accepted one than the robot can go at the
    speed limit (plus the margin) is lost, as is a non-finite one; the supervisor sees the speed between
    accepted centroids (distance over time), and the gate measures from the last accepted centroid."""
    with Simulation(small_session()) as sim:
        orchestrator = sim.orchestrator
        process, update = orchestrator.tracker.process, orchestrator.safety.update
        moved: dict[int, np.ndarray] = {}
        speeds: list[tuple[int, float | None]] = []
        steps = [0]

        def shifted(*args: Any, **kwargs: Any) -> Any:
            posture = process(*args, **kwargs)
            if orchestrator.running:
                steps[0] += 1
                offset = {6: np.array([0.0, 40.0, 0.0]), 9: np.array([np.nan, 0.0, 0.0])}.get(steps[0])
                if offset is not None and posture.centroid_mm is not None:
                    posture.centroid_mm = posture.centroid_mm + offset
                if posture.centroid_mm is not None:
                    moved[steps[0]] = np.array(posture.centroid_mm)
            return posture

        def watched(t_s: float, tracked: bool, *args: Any) -> Any:
            speeds.append((steps[0], args[2] if len(args) > 2 else None))
            return update(t_s, tracked, *args)

        orchestrator.tracker.process, orchestrator.safety.update = shifted, watched
        result = sim.run(0.5)
    by_step = {k + 1: report for k, report in enumerate(result.reports)}
    assert len(by_step) >= 12 and all(by_step[k].posture is not None and by_step[k].posture["ok"] for k in by_step)
    rejected = {k for k, report in by_step.items() if not report.tracked}
    assert rejected == {6, 9}
    assert orchestrator.stats.rejected == 2
    times = {k: report.t_s for k, report in by_step.items()}
    checked = 0
    for k, speed in speeds:
        if k in rejected or k - 1 not in moved or k == 1:
            continue
        last = k - 1 if k - 1 not in rejected else k - 2    # the gate and the speed start at the last accepted
        expected = float(np.linalg.norm(moved[k] - moved[last])) / (times[k] - times[last])
        assert speed == pytest.approx(expected, rel=1e-12)
        checked += 1
    assert checked >= len(by_step) - 5


def test_the_start_up_rehearsal_leaves_the_follower_and_the_supervisor_as_new() -> None:
    """The rehearsal runs the follower, a supervisor and the allocation a dozen times on the start-up pair
    (bytecode specialisation before the loop's clock): the session's follower is reset after it and its
    supervisor never sees it, so the first step is the session's first for both."""
    holder: dict[str, Any] = {}
    seen: dict[str, Any] = {}

    class AtStart(LoopListener):
        def on_start(self, t_s: float, info: dict[str, Any]) -> None:
            orchestrator = holder["sim"].orchestrator
            fresh = type(orchestrator.follower)(orchestrator.follower.points)
            seen["follower_state"] = orchestrator.follower._state.copy()
            seen["fresh_state"] = fresh._state.copy()
            safety = orchestrator.safety
            seen["safety"] = (safety.mode, list(safety.events), safety._lost, safety._reacquired)

    with Simulation(small_session(), [AtStart()]) as sim:
        holder["sim"] = sim
        sim.run(0.2)
    np.testing.assert_array_equal(seen["follower_state"], seen["fresh_state"])   # NaN where a new one has NaN
    assert seen["safety"] == (Mode.RUN, [], 0, 0)
