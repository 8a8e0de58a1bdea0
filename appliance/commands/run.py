"""``appliance run --config config/bench.yaml``: the closed loop on the real bench.

The same loop as ``appliance sim`` (recognition -> path follower -> safety -> allocation -> amplifier),
on the devices the session names: the amplifier on its serial port or TCP address, the two X-ray
grabbers by URL, the optical tracker for reference. Start-up checks every device and stops with a
clear message if one is missing, busy, faulted or delivering the wrong image size. Ctrl-C is an
operator stop: the coils are ramped to zero and the output disabled before the program exits, as on
any other way out. The session is recorded (MCAP) and a summary printed at the end.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

NAME = "run"
HELP = "run the closed loop on the real bench described by a session file (config/bench.yaml)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="FILE", type=Path, required=True,
                        help="session file with real devices (see config/bench.yaml)")
    parser.add_argument("--seconds", metavar="S", type=float,
                        help="stop after the loop has run this many seconds (default: when the robot reaches the end of the path)")
    parser.add_argument("--out", metavar="DIR", type=Path,
                        help="folder for the recording (default: run-YYYYmmdd-HHMMSS/ under the session's folder)")


def run(args: argparse.Namespace) -> int:
    from appliance.commands.sim import ProgressLine, progress_text
    from appliance.control import (
        ActuationModel,
        CurrentAllocator,
        PathFollower,
        SafetySupervisor,
        load_coils,
        load_path,
    )
    from appliance.device_factory import open_devices
    from appliance.errors import ConfigError
    from appliance.operator_stop import ctrl_c_requests_stop
    from appliance.orchestrator import LoopSettings, Orchestrator, RecordingListener, recognition_settings
    from appliance.recognition import PostureTracker
    from appliance.recording import Recorder
    from appliance.robots import load_robots, select_robot
    from appliance.session_config import load_session
    from appliance.simulation import latency_line

    session = load_session(args.config)
    config = session.config
    if config.is_simulation:
        raise ConfigError(f"{session.source}: every device is loopback; run it with `appliance sim --config "
                          f"{args.config}`")
    if args.seconds is not None and args.seconds <= 0:
        raise ConfigError(f"--seconds must be positive, got {args.seconds:g}")
    robot = select_robot(load_robots(session.robots_path), config.robot.id)
    coils = load_coils(session.coils_path)
    follower = PathFollower(load_path(session.vessel_path), config.control)
    out = args.out if args.out is not None else Path(config.recording.folder) / f"run-{time.strftime('%Y%m%d-%H%M%S')}"
    progress = ProgressLine()
    recorder = None
    print(f"appliance run: {session.source}: opening devices...", file=sys.stderr, flush=True)
    with open_devices(session, robot, coils) as devices:
        orchestrator = Orchestrator(
            frames=devices.frames, amplifier=devices.amplifier, tracker=PostureTracker(devices.calibration, recognition_settings(config, devices.calibration), body=robot),
            follower=follower, safety=SafetySupervisor(config.safety), allocator=CurrentAllocator(ActuationModel(coils)),
            moment_am2=robot.magnetic_moment_am2, settings=LoopSettings.from_config(config), ots=devices.ots,
            names=devices.names)
        if config.recording.enabled:
            recorder = Recorder.create(out / "session.mcap",
                                       config={"source": str(session.source), **config.model_dump(mode="json")},
                                       calibration=devices.calibration.to_dict(),
                                       frames_every=config.recording.frames_every)
            orchestrator.listeners.append(RecordingListener(recorder))
        try:
            with ctrl_c_requests_stop(orchestrator.request_stop, "appliance run"), orchestrator:
                print("appliance run: loop running; Ctrl-C stops (coils ramp to zero)", file=sys.stderr, flush=True)
                # --seconds counts the loop's time: the start-up's checks and kernel warm-up (seconds on a cold
                # cache or a loaded machine) are not taken from it.
                started = time.monotonic()
                while orchestrator.running:
                    report = orchestrator.step()
                    progress.show(progress_text(report))
                    if args.seconds is not None and time.monotonic() - started >= args.seconds:
                        orchestrator.request_stop(f"time limit of {args.seconds:g} s")
        finally:
            progress.end()
            if recorder is not None:
                recorder.close()
    stats = orchestrator.stats
    print("\n".join([
        f"appliance run: stopped: {orchestrator.stop_reason or 'end'}",
        (f"  frames        {stats.pairs} pairs: {stats.tracked} tracked, {stats.lost} lost; "
        f"{stats.no_pair} steps without a new pair"),
        latency_line(stats, acknowledged=False),
        f"  coils         {'ramped to zero and disabled' if orchestrator.shutdown_safe else 'NOT confirmed at zero'}",
        f"  written       {recorder.path}" if recorder is not None else "  written       (recording disabled)",
    ]))
    return 0 if orchestrator.shutdown_safe else 1
