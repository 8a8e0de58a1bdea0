"""``appliance bench``: real-time performance of the frame step, per stage, against a plain OpenCV
pipeline and the memory floor (issue 8). Prints one table; ``--json FILE`` writes every figure.

The frame pairs come from the simulated fluoroscope (``drivers/loopback/xray_render.py``): the robot
moves along the operator's path (``config/vessel.yaml``) at ``--speed`` mm/s inside a contrast-filled
vessel, seen by the two planes of ``config/sim.yaml``'s geometry (plane q 15 deg elevated, both
turned -45 deg), with quantum noise, blur and a non-uniform field. The pairs are rendered a chunk at a
time, untimed, then each arrives in host buffers and is measured (see :mod:`appliance.benchmarking`); the amplifier command goes to the loopback amplifier
served on a pseudo-terminal by a separate process, as a real amplifier is a separate device: served
from a thread of this process instead (``--amplifier-in-process``), its polling competes with the loop
for the GIL and a write can wait milliseconds for it to be handed back. This module builds the fakes
(commands may import the loopback package; :mod:`appliance.benchmarking` does not).

    appliance bench [--json FILE] [--frames N] [--size 1024] [--sim-seconds S] [--profile [N]]
"""
from __future__ import annotations

import argparse
import contextlib
import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from appliance.commands._common import integer_at_least, non_negative_float

NAME = "bench"
HELP = "measure recognition, control and the amplifier command per stage against an OpenCV baseline and the memory floor"

#: Geometry of config/sim.yaml's simulated fluoroscope (plane q raised, both C-arms turned).
ELEVATION_DEG = 15.0
AZIMUTH_DEG = -45.0
VESSEL_RADIUS_MM = 2.5
VESSEL_ATTENUATION_PER_MM = 0.06
FPS = 30.0





def _size(text: str) -> int:
    value = integer_at_least(2)(text)
    if not 64 <= value <= 4096:
        raise argparse.ArgumentTypeError(f"image size must be 64..4096 px, got {value}")
    return value





def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", metavar="FILE", type=Path, help="also write every figure of the table as JSON")
    parser.add_argument("--frames", metavar="N", type=integer_at_least(2), default=300,
                        help="biplane pairs to measure (default 300: p99 is then the 3rd slowest)")
    parser.add_argument("--size", metavar="PX", type=_size, default=1024,
                        help="square detector size in pixels (default 1024)")
    parser.add_argument("--robot", metavar="ID", type=int, default=1, help="robot of Table 1 (default 1)")
    parser.add_argument("--speed", metavar="MM_S", type=non_negative_float, default=8.0,
                        help="robot speed along the path, mm/s (default 8)")
    parser.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    parser.add_argument("--sim-seconds", metavar="S", type=non_negative_float, default=10.0,
                        help="simulated seconds of the closed loop of config/sim.yaml (0: skip; default 10: ~300 "
                             "pairs, so that p99 is the 3rd-4th slowest, not the session's first pairs)")
    parser.add_argument("--no-amplifier", action="store_true",
                        help="leave out the amplifier command (the loop then ends at the allocation)")
    parser.add_argument("--amplifier-in-process", action="store_true",
                        help="serve the loopback amplifier from a thread of this process (default: its own process)")
    parser.add_argument("--profile", metavar="N", type=integer_at_least(1), nargs="?", const=30, default=0,
                        help="after the measured pairs, profile N more (default 30) steady-state steps and print "
                             "where the time goes")
    parser.add_argument("--lean-steady-state", action=argparse.BooleanOptionalAction, default=True,
                        help="track with the lean steady-state pass (RecognitionSettings.lean_steady_state, on by "
                             "default; --no-lean-steady-state: the full ROI search every frame)")


class RenderedScene:
    """Frame pairs of a robot moving along the operator's path, rendered by the simulated fluoroscope."""

    def __init__(self, size: int, robot_id: int = 1, speed_mm_s: float = 8.0, seed: int = 0,
                 fps: float = FPS) -> None:
        from appliance.control import load_path
        from appliance.device_factory import turned_views
        from appliance.geometry import Calibration, View
        from appliance.robots import load_robots, select_robot
        from drivers.loopback.xray_render import BiplaneRenderer, ImagingSettings, RobotBody, VesselPhantom, biplane_views

        self.robot = select_robot(load_robots(), robot_id)
        self.fps = fps
        self.speed_mm_s = speed_mm_s
        self.path = load_path()
        steps = np.linalg.norm(np.diff(self.path, axis=0), axis=1)
        self._s = np.concatenate([[0.0], np.cumsum(steps)])
        views = turned_views(biplane_views(image_size=(size, size), elevation_deg=ELEVATION_DEG), AZIMUTH_DEG)
        self.calibration = Calibration.from_views(*(View(n, v.K, v.dist, v.R, v.t, v.image_size)
                                                    for n, v in (("p", views["p"]), ("q", views["q"]))))
        imaging = ImagingSettings()
        self.dark_level = float(imaging.dark_level)
        r = self.robot
        body = RobotBody(r.length_mm, r.diameter_mm, r.tip_angle_deg, r.attenuation_per_mm)
        self.renderer = BiplaneRenderer(views, body, vessel=VesselPhantom(self.path, VESSEL_RADIUS_MM,
                                                                          VESSEL_ATTENUATION_PER_MM),
                                        settings=imaging, seed=seed)

    def pose_at(self, t_s: float) -> Any:
        """The robot on the path at ``t_s`` (back and forth along it), axis along the path's tangent."""
        from drivers.loopback.xray_render import RobotPose

        total = float(self._s[-1])
        # Start 20 % in so the robot is whole in both views; turn round at the ends.
        s = (0.2 * total + self.speed_mm_s * t_s) % (2 * total)
        s = s if s <= total else 2 * total - s
        k = int(np.clip(np.searchsorted(self._s, s) - 1, 0, len(self.path) - 2))
        f = (s - self._s[k]) / max(self._s[k + 1] - self._s[k], 1e-9)
        centroid = self.path[k] + f * (self.path[k + 1] - self.path[k])
        return RobotPose(centroid, self.path[k + 1] - self.path[k])

    def pairs(self) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        n = 0
        while True:
            pair = self.renderer.render(self.pose_at(n / self.fps))
            yield pair.images["p"], pair.images["q"]
            n += 1


#: What the amplifier's own process runs: the loopback amplifier on a pty, path on the first line,
#: until its standard input closes.
_SERVE_AMPLIFIER = """
import sys
from drivers.loopback.amplifier_fake import FakeAmplifier, FakeAmplifierConfig
from drivers.loopback.serve import PtyServer
config = FakeAmplifierConfig(channels=int(sys.argv[1]), watchdog_ms=int(sys.argv[2]))
with PtyServer(FakeAmplifier(config)) as server:
    print(server.path, flush=True)
    sys.stdin.read()
"""


@contextlib.contextmanager
def served_amplifier(channels: int, watchdog_ms: int = 1000, in_process: bool = False) -> Iterator[str]:
    """The loopback amplifier served on a pty (its path), by its own process unless ``in_process``."""
    if in_process:
        from drivers.loopback.amplifier_fake import FakeAmplifier, FakeAmplifierConfig
        from drivers.loopback.serve import PtyServer

        with PtyServer(FakeAmplifier(FakeAmplifierConfig(channels=channels, watchdog_ms=watchdog_ms))) as server:
            yield server.path
        return
    process = subprocess.Popen([sys.executable, "-c", _SERVE_AMPLIFIER, str(channels), str(watchdog_ms)],
                               stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert process.stdout is not None
        path = process.stdout.readline().strip()
        if not path:
            raise RuntimeError(f"the loopback amplifier process did not start (exit status {process.wait(5)})")
        yield path
    finally:
        if process.stdin is not None:
            process.stdin.close()   # the server's read returns: it closes the pty and exits
        try:
            process.wait(timeout=5)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


class _Progress:
    """Progress on stderr: a rewritten line on a terminal, a line every 10 % otherwise."""

    def __init__(self, total: int) -> None:
        self.tty = sys.stderr.isatty()
        self.total = total
        self.shown = -1

    def __call__(self, text: str) -> None:
        if self.tty:
            sys.stderr.write(f"\r{text[:100]:<100s}")
            sys.stderr.flush()
            return
        try:
            done = int(text.split()[1].split("/")[0])
        except (IndexError, ValueError):
            return
        tenth = 10 * done // self.total
        if tenth != self.shown:
            self.shown = tenth
            print(f"appliance bench: {text}", file=sys.stderr, flush=True)

    def end(self) -> None:
        if self.tty:
            sys.stderr.write("\r" + " " * 100 + "\r")
            sys.stderr.flush()


def measure(frames: int = 300, size: int = 1024, robot_id: int = 1, speed_mm_s: float = 8.0, seed: int = 0,
            sim_seconds: float = 10.0, amplifier: bool = True, progress: Any = None, profile_pairs: int = 0,
            amplifier_in_process: bool = False, lean_steady_state: bool = True) -> Any:
    """The whole benchmark: returns an :class:`appliance.benchmarking.BenchResult` (used by the CLI and
    ``benchmarks/pipeline_bench.py``)."""
    from appliance.benchmarking import run_bench, run_simulation
    from appliance.control import load_coils
    from appliance.recognition import RecognitionSettings

    scene = RenderedScene(size, robot_id, speed_mm_s, seed)
    moment = scene.robot.magnetic_moment_am2
    settings = RecognitionSettings(dark_level=scene.dark_level, lean_steady_state=lean_steady_state)
    if amplifier:
        with served_amplifier(len(load_coils().coils), in_process=amplifier_in_process) as path:
            result = run_bench(scene, frames, amplifier_url=path, moment_am2=moment, progress=progress,
                               profile_pairs=profile_pairs, settings=settings, robot=scene.robot)
    else:
        result = run_bench(scene, frames, moment_am2=moment, progress=progress, profile_pairs=profile_pairs,
                           settings=settings, robot=scene.robot)
    result.config.update({"robot": robot_id, "speed_mm_s": speed_mm_s, "seed": seed,
                          "amplifier_served_by": None if not amplifier else
                          "a thread of this process" if amplifier_in_process else "its own process"})
    if not amplifier:
        result.notes.append("no amplifier: the loop is recognition + control + allocation")
    else:
        result.notes.append("amplifier: the loopback amplifier on a pty, served by "
                            + ("a thread of this process (shares the GIL with the loop)" if amplifier_in_process
                               else "its own process, as a real amplifier is a separate device"))
    result.notes.append("frames: rendered ahead, untimed; before each measured pair, the pair arrives in the host's "
                        "frame buffers by np.copyto (the memory floor, 8 MB of cache traffic per 1024^2 pair, as a "
                        "grabber's DMA), so every stage starts on the caches a new frame leaves")
    result.notes.append("ROI: the steady-state pair is one compiled call (both views' attenuation, candidates, "
                        "refinement, gate and weighted features, and the reconstruction's front), timed as "
                        "segmentation; its features row is 0, triangulation is the reconstruction's Python rest"
                        + ("" if lean_steady_state else "; lean steady-state pass OFF"))
    result.notes.append("loop = frame available -> SET_CURRENTS written to the pty (ROI recognition, control, "
                        "allocation, the driver's limit check and encoding, the write call); the line's transfer "
                        "and the acknowledgement are not in it ('amplifier: acked' is the round trip)")
    if sim_seconds > 0:
        result.simulation = run_simulation(sim_seconds, progress=progress)
    else:
        result.notes.append("closed loop in simulation skipped (--sim-seconds 0)")
    return result


def run(args: argparse.Namespace) -> int:
    from appliance.benchmarking import format_table

    progress = _Progress(args.frames)
    print(f"appliance bench: rendering and measuring {args.frames} pairs of {args.size}x{args.size} px...",
          file=sys.stderr, flush=True)
    try:
        result = measure(args.frames, args.size, args.robot, args.speed, args.seed, args.sim_seconds,
                         not args.no_amplifier, progress, profile_pairs=args.profile,
                         amplifier_in_process=args.amplifier_in_process, lean_steady_state=args.lean_steady_state)
    finally:
        progress.end()
    print(format_table(result))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result.to_json(), indent=1))
        print(f"written {args.json}", file=sys.stderr)
    return 0
