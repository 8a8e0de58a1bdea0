"""``appliance sim``: the whole bench simulated, closed loop along the default path (the README's main command).

Starts the simulated world and every loopback device over real transports (the amplifier and the
optical tracker on pseudo-terminals, both X-ray planes through the USB grabber driver on a fake pyusb
backend), runs the frame loop (recognition -> path follower -> safety -> allocation -> amplifier) on
simulated time, shows a live progress line on a terminal, and ends with a summary (cross-track error
against the TRUE robot position, time to the end of the path, frames, loop latency, simulated vs wall
time), a PNG of the path followed against the target, and the MCAP recording of the session.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from appliance.commands._common import positive_float

NAME = "sim"
HELP = "run the closed loop on the simulated bench (every device a loopback fake) and report how well it followed the path"





def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="FILE", type=Path,
                        help="session file (default: config/sim.yaml, every device loopback)")
    parser.add_argument("--seconds", metavar="S", type=positive_float,
                        help="simulated time limit (default: the session's simulation.max_seconds); "
                             "the run also ends when the robot reaches the end of the path")
    parser.add_argument("--out", metavar="DIR", type=Path,
                        help="folder for the plot and the recording (default: sim-YYYYmmdd-HHMMSS/ "
                             "under the session's recording folder)")
    parser.add_argument("--no-recording", action="store_true", help="do not write the MCAP recording")


class ProgressLine:
    """A one-line live view on a terminal (stderr), refreshed a few times per second of wall time."""

    def __init__(self, stream: Any = None, period_s: float = 0.25) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = bool(getattr(self.stream, "isatty", lambda: False)())
        self.period_s = period_s
        self._last = 0.0

    def show(self, text: str) -> None:
        now = time.monotonic()
        if not self.enabled or now - self._last < self.period_s:
            return
        self._last = now
        self.stream.write(f"\r{text[:150]:<150s}")
        self.stream.flush()

    def end(self) -> None:
        if self.enabled:
            self.stream.write("\r" + " " * 150 + "\r")
            self.stream.flush()


def progress_text(report: Any, cross_track_mm: float | None = None, position_mm: Any = None) -> str:
    """``frame 312  t 10.40 s  run  pos (-12.1, -8.3, 3.0) mm  xt 0.18 mm  52%  |I| max 4.9 A``."""
    pos = report.posture.get("centroid_mm") if report.posture else None
    pos = pos if pos is not None else position_mm
    where = "(" + ", ".join(f"{v:.1f}" for v in pos) + ") mm" if pos is not None else "(not tracked)"
    xt = cross_track_mm if cross_track_mm is not None else report.cross_track_mm
    progress = f"{100 * report.progress:4.0f}%" if report.progress is not None else "   -"
    currents = report.measured_a if report.measured_a is not None else report.commanded_a
    return (f"frame {report.frame if report.frame is not None else '-':>5}  t {report.t_s:6.2f} s  {report.mode:4s}  "
            f"pos {where}  xt {xt if xt is not None else float('nan'):.2f} mm  {progress}  "
            f"|I| max {float(abs(currents).max()):.1f} A")


def run(args: argparse.Namespace) -> int:
    from appliance.operator_stop import ctrl_c_requests_stop
    from appliance.orchestrator import RecordingListener
    from appliance.plots import plot_path
    from appliance.recording import Recorder
    from appliance.session_config import load_session
    from appliance.simulation import Simulation, summary_lines

    session = load_session(args.config)
    config = session.config
    stamp = time.strftime("%Y%m%d-%H%M%S")
    out = args.out if args.out is not None else Path(config.recording.folder) / f"sim-{stamp}"
    out.mkdir(parents=True, exist_ok=True)
    progress = ProgressLine()
    print(f"appliance sim: {session.source}: robot {config.robot.id}, {config.imaging.fps:g} fps "
          f"{config.imaging.image_size[0]}x{config.imaging.image_size[1]}, starting the simulated bench...",
          file=sys.stderr, flush=True)
    from appliance.compiled import cache_is_warm

    if not cache_is_warm():
        print("appliance sim: compiling the recognition and control kernels (first run after an install or a "
              "change; about a minute, cached afterwards)...", file=sys.stderr, flush=True)
    recorder = None
    try:
        with Simulation(session) as sim:
            if config.recording.enabled and not args.no_recording:
                # Created once the bench is built: the calibration the loop uses (nominal, perturbed) is known then.
                recorder = Recorder.create(out / "session.mcap",
                                           config={"source": str(session.source), **config.model_dump(mode="json")},
                                           calibration=sim.devices.calibration.to_dict(),
                                           frames_every=config.recording.frames_every)
                sim.orchestrator.listeners.append(RecordingListener(recorder))
            with ctrl_c_requests_stop(sim.orchestrator.request_stop, "appliance sim"):
                result = sim.run(args.seconds, on_step=lambda report, truth: progress.show(
                    progress_text(report, truth.cross_track_mm)))
            stats = sim.orchestrator.stats
            robot = sim.robot
            length_mm = sim.follower.length_mm
    finally:
        progress.end()
        if recorder is not None:
            recorder.close()
    events = [(t, name) for name, t in result.fault_times.items()]
    if result.stop_t_s is not None and result.stop_reason:
        events.append((result.stop_t_s, "stop"))
    plot = plot_path(out / "path.png", result.path_mm, [s.centroid_mm for s in result.truth],
                     [s.t_s for s in result.truth], result.cross_track(), tracked_mm=result.tracked_mm,
                     events=events, title=f"appliance sim: robot {robot.id} along {session.vessel_path.name}'s path")
    lines = [(f"appliance sim: robot {robot.id} (L {robot.length_mm:g} mm, D {robot.diameter_mm:g} mm), "
             f"{config.imaging.fps:g} fps biplane, {len(result.path_mm)} path points "
             f"({length_mm:.1f} mm)")]
    lines += summary_lines(result, stats)
    lines.append(f"  written       {plot}" + (f", {recorder.path}" if recorder is not None else ""))
    print("\n".join(lines))
    return 0
