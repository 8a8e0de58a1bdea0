"""Each view's blob "mass" against the robot's, per frame of the accuracy benchmark (a study; asserts nothing).

A blob's mass is its integrated attenuation times the pixel's area at the object (mm^2,
:func:`appliance.recognition.body_prior.view_masses_mm2`); a clean view of the robot gives its attenuation
times its volume (:attr:`.BodyModel.mass_mm2`). Per robot, cold and ``--tracked`` (as
``benchmarks/accuracy.py`` renders them: same poses, same noise), this prints the spread of
measured / expected over the views, the frames whose ratio is off the robot's clean spread, and with
``--json`` writes every frame's ratios, the centroid error and each view's centroid error along its axis.

Usage: ``python benchmarks/mass_study.py --seeds 1,2,3 [--robots 6] [--tracked] [--poses N] [--json F]
[--max-mass-excess X]`` (X large: the tracker without the mass check).
Every frame takes the tracker's general path (the steady pair's plain posture is declined: the same
posture to the last bit, with its blobs at hand).
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

import benchmarks.accuracy as acc  # noqa: E402
from appliance.recognition import PostureTracker, RecognitionSettings  # noqa: E402
from appliance.recognition.body_mass import view_masses_mm2  # noqa: E402
from appliance.recognition.body_prior import BodyModel  # noqa: E402
from appliance.recognition.steady_state import SteadyPair  # noqa: E402
from appliance.robots import load_robots  # noqa: E402
from drivers.loopback.scene_builders import S_BEND_CENTRELINE_MM, smooth_centreline  # noqa: E402
from drivers.loopback.xray_render import BiplaneRenderer, ImagingSettings, RobotBody, RobotPose, VesselPhantom, biplane_views  # noqa: E402,E501


def _along_px(feat_centroid: np.ndarray, axis: np.ndarray, true_px: np.ndarray) -> float:
    return float((np.asarray(feat_centroid) - true_px) @ np.asarray(axis))


def study(seed: int, robot_id: int, spec: Any, tracked: bool, poses_n: int, max_mass_excess: float
          ) -> list[dict[str, Any]]:
    views = biplane_views()
    cal = acc.true_calibration(views)
    phantom = VesselPhantom(smooth_centreline(S_BEND_CENTRELINE_MM), acc.VESSEL_RADIUS_MM,
                            acc.VESSEL_ATTENUATION_PER_MM)
    imaging = ImagingSettings()
    poses = acc.random_poses(np.random.default_rng([seed, robot_id]), poses_n)
    body = RobotBody(spec.length_mm, spec.diameter_mm, spec.tip_angle_deg, spec.attenuation_per_mm)
    renderer = BiplaneRenderer(views, body, vessel=phantom, settings=imaging, seed=seed + robot_id)
    step_rng = np.random.default_rng([seed, robot_id, 1])
    # (the rule as it was studied: the heavy view's slide and the flag; settings.mass_rule's default is off)
    tracker = PostureTracker(cal, RecognitionSettings(dark_level=imaging.dark_level, max_mass_excess=max_mass_excess,
                                                      mass_rule="slide"), body=spec)
    expected = BodyModel.of(spec).mass_mm2
    seen: dict[str, Any] = {}
    posture_of = tracker._posture

    def keep(frame, t, rec, blobs):  # the blobs and the reconstruction the posture is made of
        seen["blobs"], seen["rec"] = blobs, rec
        return posture_of(frame, t, rec, blobs)
    tracker._posture = keep
    rows = []
    for i, pose in enumerate(poses):
        before = []
        if tracked:
            step = step_rng.normal(size=3)
            step *= acc.TRACK_STEP_MM / np.linalg.norm(step)
            before = [renderer.render(RobotPose(pose.centroid_mm - step, pose.direction))]
        pair = renderer.render(pose)
        tracker.reset()
        for earlier in before:
            tracker.process(earlier.images["p"], earlier.images["q"], frame=2 * i, t=0.0)
        seen.clear()
        posture = tracker.process(pair.images["p"], pair.images["q"], frame=2 * i + 1, t=len(before) / acc.TRACK_FPS)
        row: dict[str, Any] = {"pose": i, "ok": posture.ok, "ambiguous": posture.ambiguous,
                               "search": tracker.last_search}
        if posture.ok and "blobs" in seen:
            blobs, rec = seen["blobs"], seen["rec"]
            masses = view_masses_mm2(cal, blobs)
            row["centroid_mm"] = float(np.linalg.norm(posture.centroid_mm - pose.centroid_mm))
            row["ratio"] = {name: m / expected for name, m in masses.items()}
            row["clutter"] = {name: b.clutter for name, b in blobs.items()}
            row["along_px"] = {name: _along_px(rec.view_features[name].centroid, rec.view_features[name].axis,
                                               pair.truth[name].centroid_px) for name in blobs}
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="1,2,3")
    parser.add_argument("--robots", default="1,2,3,4,5,6,7")
    parser.add_argument("--tracked", action="store_true")
    parser.add_argument("--poses", type=int, default=30)
    parser.add_argument("--json")
    parser.add_argument("--max-mass-excess", type=float, default=RecognitionSettings().max_mass_excess,
                        help="the tracker's setting (a large value: no view is heavy, the check is off)")
    args = parser.parse_args(argv)
    # Decline every plain posture: the tracker's general path, same numbers, with its blobs.
    SteadyPair.plain_posture = lambda self, frame, t, timings_us=None: None
    robots = load_robots()
    out: dict[str, Any] = {}
    for robot_id in [int(r) for r in args.robots.split(",")]:
        rows = []
        for seed in [int(s) for s in args.seeds.split(",")]:
            rows += [dict(r, seed=seed) for r in study(seed, robot_id, robots[robot_id], args.tracked, args.poses,
                                                               args.max_mass_excess)]
        out[str(robot_id)] = rows
        ratios = np.array([r["ratio"][n] for r in rows if "ratio" in r for n in "pq"])
        clean = np.array([r["ratio"][n] for r in rows if "ratio" in r for n in "pq" if r["clutter"][n] <= 0.05])
        print(f"robot {robot_id}: {len(ratios)} views; ratio median {np.median(ratios):.3f}, 1-99 % "
              f"{np.percentile(ratios, 1):.3f}..{np.percentile(ratios, 99):.3f}, min {ratios.min():.3f} max "
              f"{ratios.max():.3f}; uncluttered views ({len(clean)}) {clean.min():.3f}..{clean.max():.3f}")
        for r in rows:
            if "ratio" in r and (max(r["ratio"].values()) > 1.04 or r["centroid_mm"] > 0.15):
                print(f"   seed {r['seed']} pose {r['pose']:2d} {r['search']:4s} amb {int(r['ambiguous'])} err "
                      f"{r['centroid_mm']:.3f} ratio p {r['ratio']['p']:.3f} q {r['ratio']['q']:.3f} clutter "
                      f"p {r['clutter']['p']:.3f} q {r['clutter']['q']:.3f} along px p {r['along_px']['p']:+.2f} "
                      f"q {r['along_px']['q']:+.2f}")
        sys.stdout.flush()
    if args.json:
        Path(args.json).write_text(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
