"""``appliance demo``: render a biplane scene of a robot moving through a vessel, track it, compare with the truth.

The scene comes from the loopback X-ray simulator (the same renderer the simulated frame grabber
uses): the true views of a 90-degree biplane system at 500 mm source-object distance, one robot of
the catalogue (Table 1 of the seed paper), a contrast-filled vessel phantom, a non-uniform field,
quantum noise and detector blur. The robot glides along the vessel's centreline on a smooth
(ease-in/ease-out) trajectory, its axis following the vessel's tangent, head first.

Written to the output folder (a biplane frame folder, architecture.md contract):
``p/``, ``q/`` 16-bit frames, ``calibration.yaml`` (the *true* views, saved with
:meth:`Calibration.save`), ``truth.jsonl`` (the true pose per frame) and ``postures.jsonl`` (what
``appliance track`` makes of it). The calibration's metadata carries the simulated detector's dark
level (``detector.dark_level``), which ``appliance track`` then subtracts by default. The summary compares the two: centroid, axis and tip errors over
the frames the tracker reported, plus how many it flagged ambiguous or lost, and any *silent*
failure (a frame neither ambiguous nor lost whose axis is more than 5 degrees off, the issue's
definition), which makes the exit status 1.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from appliance.commands._common import prepare_frame_folder
from appliance.commands._common import non_negative_float

NAME = "demo"
HELP = "render a biplane scene of a robot moving through a vessel, track it and compare with the truth"

#: A frame is a silent failure if it is neither ambiguous nor lost and its axis is still this wrong.
SILENT_AXIS_DEG = 5.0
#: Centreline of the vessel phantom (mm, world frame, isocentre at 0, z up). It climbs ~30 degrees so
#: that the robot's axis stays out of the epipolar planes of two views that are both level.
VESSEL_CONTROL_MM = ((-34.0, -20.0, -22.0), (-14.0, 3.0, -10.0), (3.0, 11.0, 1.0), (17.0, 3.0, 13.0),
                     (34.0, -14.0, 24.0))
VESSEL_ATTENUATION_PER_MM = 0.06  # diluted iodine contrast: visible, but well below the robot's
#: Default lumen radius: a 5 mm phantom vessel, or wider than the robot's own diameter for robot 6.
DEFAULT_VESSEL_RADIUS_MM = 2.5


def _count(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if not 1 <= value <= 10000:
        raise argparse.ArgumentTypeError(f"must be between 1 and 10000, got {value}")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", metavar="DIR", type=Path,
                        help="folder to write the scene to (must not hold frames yet; default: a new temporary folder)")
    parser.add_argument("--robot", metavar="N", type=int, default=2,
                        help="robot id in config/robots.yaml, Table 1 of the seed paper (default 2: 15 mm x 1.5 mm)")
    parser.add_argument("--frames", metavar="N", type=_count, default=24, help="number of frame pairs (default 24)")
    parser.add_argument("--seed", type=int, default=1, help="noise seed (default 1)")
    parser.add_argument("--vessel-radius", metavar="MM", type=float,
                        help=f"lumen radius of the vessel phantom (default {DEFAULT_VESSEL_RADIUS_MM:g} mm, "
                             "or 0.8 x the robot's diameter if larger)")
    parser.add_argument("--dark-level", type=non_negative_float, metavar="DN",
                        help="detector dark level the tracker subtracts (default: the calibration's "
                             "metadata.detector.dark_level, which the demo writes from its simulated detector)")


@dataclass(frozen=True)
class TrueFrame:
    frame: int
    centroid_mm: np.ndarray
    direction: np.ndarray  # tail -> head
    head_mm: np.ndarray
    tail_mm: np.ndarray

    def to_record(self) -> dict[str, Any]:
        return {"frame": self.frame, "centroid_mm": self.centroid_mm.round(5).tolist(),
                "direction": self.direction.round(7).tolist(), "head_mm": self.head_mm.round(5).tolist(),
                "tail_mm": self.tail_mm.round(5).tolist()}


@dataclass(frozen=True)
class DemoScene:
    truth: list[TrueFrame]
    robot: Any  # appliance.robots.RobotSpec
    vessel_radius_mm: float





def _progress(text: str) -> None:
    if sys.stderr.isatty():
        sys.stderr.write(f"\r{text}   ")
        sys.stderr.flush()


def render_scene(out: Path, robot_id: int, frames: int, seed: int,
                 vessel_radius_mm: float | None = None) -> DemoScene:
    """Render ``frames`` pairs into ``out`` and save the true calibration and the truth."""
    from appliance.geometry import Calibration, View
    from appliance.robots import load_robots, select_robot
    from drivers.biplane_folder import write_frame
    from drivers.loopback.vessel import Vessel
    from drivers.loopback.xray_render import (BiplaneRenderer, ImagingSettings, RobotBody, RobotPose, VesselPhantom,
                                              biplane_views)

    robot = select_robot(load_robots(), robot_id)
    true_views = biplane_views()
    vessel_radius = vessel_radius_mm or max(DEFAULT_VESSEL_RADIUS_MM, 0.8 * robot.diameter_mm)
    if vessel_radius <= robot.radius_mm:
        from appliance.errors import ConfigError
        raise ConfigError(f"--vessel-radius {vessel_radius:g} mm: the robot (radius {robot.radius_mm:g} mm) "
                          "would not fit in the vessel")
    vessel = Vessel(np.array(VESSEL_CONTROL_MM), vessel_radius)
    phantom = VesselPhantom(vessel.sample(1.0), vessel_radius, VESSEL_ATTENUATION_PER_MM)
    body = RobotBody(robot.length_mm, robot.diameter_mm, robot.tip_angle_deg, robot.attenuation_per_mm)
    imaging = ImagingSettings()
    renderer = BiplaneRenderer(true_views, body, vessel=phantom, settings=imaging, seed=seed)

    views = {name: View(name, v.K, v.dist, v.R, v.t, v.image_size) for name, v in true_views.items()}
    Calibration.from_views(views["p"], views["q"], {
        "source": "true views of the simulated biplane system (appliance demo)",
        "robot": robot_id, "seed": seed, "detector": {"dark_level": float(imaging.dark_level)}}).save(out / "calibration.yaml")

    # Stay a robot length away from the vessel's ends so the whole body is inside the phantom.
    margin = min(robot.length_mm, 0.3 * vessel.length_mm)
    s0, s1 = margin, vessel.length_mm - margin
    truth: list[TrueFrame] = []
    for number in range(frames):
        u = number / max(frames - 1, 1)
        s = s0 + (s1 - s0) * (3 * u * u - 2 * u * u * u)  # smoothstep: starts and stops at rest
        pose = RobotPose(vessel.point_at(s), vessel.tangent_at(s))
        pair = renderer.render(pose)
        for plane in ("p", "q"):
            write_frame(out, plane, number, pair.images[plane])
        truth.append(TrueFrame(number, pose.centroid_mm, pose.direction, pair.head_mm, pair.tail_mm))
        _progress(f"demo: rendering frame {number + 1}/{frames}")
    with (out / "truth.jsonl").open("w", encoding="utf-8") as stream:
        for item in truth:
            stream.write(json.dumps(item.to_record()) + "\n")
    return DemoScene(truth, robot, vessel_radius)


def compare(records: list[dict[str, Any]], truth: list[TrueFrame]) -> dict[str, Any]:
    """Errors of the reported postures against the truth (only frames with ok and a pose)."""
    by_frame = {item.frame: item for item in truth}
    centroid, axis, tips, silent = [], [], [], []
    counts = {"ok": 0, "ambiguous": 0, "lost": 0, "head_identified": 0, "head_correct": 0}
    for record in records:
        true = by_frame[record["frame"]]
        if not record["ok"]:
            counts["lost"] += 1
            continue
        counts["ambiguous" if record["ambiguous"] else "ok"] += 1
        if record["centroid_mm"] is None or record["direction"] is None:
            continue
        c_err = float(np.linalg.norm(np.array(record["centroid_mm"]) - true.centroid_mm))
        cos = float(np.dot(record["direction"], true.direction))
        if record["head_identified"]:
            counts["head_identified"] += 1
            counts["head_correct"] += cos > 0
        a_err = math.degrees(math.acos(min(1.0, abs(cos))))  # orientation of the axis, head aside
        centroid.append(c_err)
        axis.append(a_err)
        if record["tips_mm"] is not None and None not in record["tips_mm"]:
            got = np.array(record["tips_mm"])
            want = np.vstack([true.head_mm, true.tail_mm])
            pairings = [want] if record["head_identified"] else [want, want[::-1]]
            tips.append(min(float(np.sqrt(np.mean(np.sum((got - w) ** 2, axis=1)))) for w in pairings))
        if not record["ambiguous"] and a_err > SILENT_AXIS_DEG:
            silent.append(record["frame"])
    return {"counts": counts, "centroid_mm": np.array(centroid), "axis_deg": np.array(axis),
            "tips_mm": np.array(tips), "silent": silent}


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(values ** 2))) if len(values) else float("nan")


def _summary(out: Path, scene: DemoScene, result: dict[str, Any], seconds: dict[str, float]) -> str:
    c, a, t, n = result["centroid_mm"], result["axis_deg"], result["tips_mm"], result["counts"]
    robot, frames = scene.robot, len(scene.truth)
    lines = [
        f"demo: robot {robot.id} (L {robot.length_mm:g} mm, D {robot.diameter_mm:g} mm, tip {robot.tip_angle_deg:g} deg) "
        f"in a {2 * scene.vessel_radius_mm:g} mm vessel, {frames} frame pairs, 90-degree biplane at 500 mm",
        f"  frames        ok {n['ok']}   ambiguous {n['ambiguous']}   lost {n['lost']}",
    ]
    if len(c):
        lines += [
            f"  centroid      rms {_rms(c):.3f} mm   max {c.max():.3f} mm",
            f"  axis          median {np.median(a):.2f} deg   max {a.max():.2f} deg",
            f"  tips          rms {_rms(t):.3f} mm" if len(t) else "  tips          none reported",
            f"  head          identified {n['head_identified']}/{len(c)}, the right end {n['head_correct']}",
        ]
    lines += [
        f"  silent failures (neither ambiguous nor lost, axis > {SILENT_AXIS_DEG:g} deg): "
        + (", ".join(f"frame {f}" for f in result["silent"]) or "none"),
        f"  time          render {seconds['render']:.1f} s, track {seconds['track']:.1f} s "
        f"({1000 * seconds['track'] / max(frames, 1):.0f} ms per pair)",
        f"  written       {out}/{{p,q,calibration.yaml,truth.jsonl,postures.jsonl}}",
        f"  again         appliance track {out}",
    ]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    import time

    from appliance.commands.track import load_inputs, track_folder
    from appliance.geometry import dark_level_of
    from appliance.recognition import PostureTracker, RecognitionSettings
    from appliance.robots import load_robots, select_robot

    robot = select_robot(load_robots(), args.robot)  # a bad --robot fails before any folder is made
    out = Path(tempfile.mkdtemp(prefix="appliance-demo-")) if args.out is None else prepare_frame_folder(args.out)
    started = time.monotonic()
    scene = render_scene(out, args.robot, args.frames, args.seed, args.vessel_radius)
    rendered = time.monotonic()
    frames, calibration = load_inputs(out, None)
    tracker = PostureTracker(calibration, RecognitionSettings(dark_level=dark_level_of(calibration, args.dark_level)),
                             body=robot)
    with (out / "postures.jsonl").open("w", encoding="utf-8") as stream:
        track_folder(frames, tracker, stream, fps=30.0)
    tracked = time.monotonic()  # (track_folder ended the progress line)
    records = [json.loads(line) for line in (out / "postures.jsonl").read_text(encoding="utf-8").splitlines()]
    result = compare(records, scene.truth)
    print(_summary(out, scene, result, {"render": rendered - started, "track": tracked - rendered}))
    return 1 if result["silent"] else 0
