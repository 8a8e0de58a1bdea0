"""Accuracy of the lean steady-state pass (prototype, ``RecognitionSettings.lean_steady_state``) against the
ROI search it would replace, on the same frames (issue 8).

The lean pass starts from the previous tracked pair's bodies, so it needs two frames of history: for each of
``--poses`` random poses per robot (as ``accuracy.py`` draws them, same seed), the robot is rendered at two
earlier positions one ``accuracy.TRACK_STEP_MM`` step apart along a random direction (constant velocity,
``accuracy.TRACK_FPS``), then at the pose. Two trackers see the same three pairs: the first frame is a
full-frame detection, the second a ROI search, the third (measured) a ROI search for one and, for the other,
the lean pass where its checks hold (the full ROI search where they fail). The table is ``accuracy.py``'s
(weighted estimator), one row per tracker; then how many measured views went through the lean pass and the
largest differences between the two trackers' postures. Asserts nothing.

    .venv/bin/python benchmarks/lean_accuracy.py [--poses 30] [--seed S] [--robots 1,...] [--json FILE]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import accuracy  # noqa: E402

from appliance.compiled import warm_up_all  # noqa: E402
from appliance.recognition import PostureTracker, RecognitionSettings  # noqa: E402
from appliance.robots import load_robots  # noqa: E402
from drivers.loopback.scene_builders import S_BEND_CENTRELINE_MM, smooth_centreline  # noqa: E402
from drivers.loopback.xray_render import (  # noqa: E402
    BiplaneRenderer,
    ImagingSettings,
    RobotBody,
    RobotPose,
    VesselPhantom,
    biplane_views,
)

MODES = ("roi search", "lean pass")


def run_robot(robot_id: int, spec: Any, poses: list[RobotPose], seed: int, calibration: Any, views: dict[str, Any],
              phantom: VesselPhantom, imaging: ImagingSettings) -> dict[str, list[dict[str, Any]]]:
    body = RobotBody(spec.length_mm, spec.diameter_mm, spec.tip_angle_deg, spec.attenuation_per_mm)
    renderer = BiplaneRenderer(views, body, vessel=phantom, settings=imaging, seed=seed + robot_id)
    step_rng = np.random.default_rng([seed, robot_id, 1])
    trackers = {mode: PostureTracker(calibration, RecognitionSettings(dark_level=imaging.dark_level,
                                                                       lean_steady_state=mode == "lean pass"))
                for mode in MODES}
    scores: dict[str, list[dict[str, Any]]] = {mode: [] for mode in MODES}
    dt = 1.0 / accuracy.TRACK_FPS
    for i, pose in enumerate(poses):
        step = step_rng.normal(size=3)
        step *= accuracy.TRACK_STEP_MM / np.linalg.norm(step)
        frames = [renderer.render(RobotPose(pose.centroid_mm - k * step, pose.direction)) for k in (2, 1)]
        pair = renderer.render(pose)
        for mode, tracker in trackers.items():
            tracker.reset()
            for k, before in enumerate(frames):
                tracker.process(before.images["p"], before.images["q"], frame=3 * i + k, t=k * dt)
            posture = tracker.process(pair.images["p"], pair.images["q"], frame=3 * i + 2, t=2 * dt)
            record = posture.to_record()
            scored = accuracy.score(record, pose, pair.head_mm, pair.tail_mm)
            scored["search"] = tracker.last_search
            lean = tracker._pair.lean_views() if tracker._lean_from is not None and tracker.last_search == "roi" \
                else (False, False)
            scored["lean_views"] = int(lean[0]) + int(lean[1])
            scored["record"] = record
            scores[mode].append(scored)
        if sys.stderr.isatty():
            sys.stderr.write(f"\rrobot {robot_id}: pose {i + 1}/{len(poses)}   ")
            sys.stderr.flush()
    return scores


def _difference(a: dict[str, Any], b: dict[str, Any]) -> tuple[float, float] | None:
    """Largest centroid and tip differences (mm) between two ok records."""
    if not (a["ok"] and b["ok"]):
        return None
    dc = float(np.linalg.norm(np.subtract(a["centroid_mm"], b["centroid_mm"])))
    if a["tips_mm"] is None or b["tips_mm"] is None:
        return dc, float("nan")
    ta, tb = np.asarray(a["tips_mm"]), np.asarray(b["tips_mm"])
    dt = min(np.abs(ta - tb).max(), np.abs(ta - tb[::-1]).max())
    return dc, float(dt)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--poses", type=int, default=30)
    parser.add_argument("--seed", type=int, default=20261121)
    parser.add_argument("--robots", default="1,2,3,4,5,6,7")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    warm_up_all()
    robots = load_robots()
    views = biplane_views()
    calibration = accuracy.true_calibration(views)
    phantom = VesselPhantom(smooth_centreline(S_BEND_CENTRELINE_MM), accuracy.VESSEL_RADIUS_MM,
                            accuracy.VESSEL_ATTENUATION_PER_MM)
    imaging = ImagingSettings()
    results: dict[int, dict[str, dict[str, Any]]] = {}
    frames: dict[int, dict[str, list[dict[str, Any]]]] = {}
    for robot_id in (int(r) for r in args.robots.split(",")):
        poses = accuracy.random_poses(np.random.default_rng([args.seed, robot_id]), args.poses)
        scores = run_robot(robot_id, robots[robot_id], poses, args.seed, calibration, views, phantom, imaging)
        results[robot_id] = {mode: accuracy.summarise(s) for mode, s in scores.items()}
        frames[robot_id] = scores
    if sys.stderr.isatty():
        sys.stderr.write("\r" + " " * 40 + "\r")
    print(f"lean pass accuracy: {args.poses} poses per robot, seed {args.seed}, accuracy.py's scene; each measured "
          f"frame the third of a track (full, ROI, measured), weighted estimator; rows: 'roi search' (lean off), "
          f"'lean pass' (on)")
    accuracy.print_table(results)
    for robot_id, by_mode in frames.items():
        lean = by_mode["lean pass"]
        views_lean = sum(s["lean_views"] for s in lean)
        both = sum(s["lean_views"] == 2 for s in lean)
        diffs = [d for d in (_difference(a["record"], b["record"]) for a, b in zip(by_mode["roi search"], lean))
                 if d is not None]
        ok_changed = sum(a["ok"] != b["ok"] for a, b in zip(by_mode["roi search"], lean))
        dc = max((d[0] for d in diffs), default=float("nan"))
        dt = max((d[1] for d in diffs if d[1] == d[1]), default=float("nan"))
        print(f"robot {robot_id}: lean views {views_lean} of {2 * len(lean)} (both views lean in {both} frames); "
              f"ok differs in {ok_changed}; largest difference lean vs ROI search: centroid {dc:.3f} mm, tips "
              f"{dt:.3f} mm")
    if args.json:
        args.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "summary": results,
                                         "frames": frames}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
