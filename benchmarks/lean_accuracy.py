"""The lean steady-state pass against the full ROI search on ``accuracy.py --tracked``'s frames (issue 8).

``accuracy.run_robot`` with two trackers (weighted estimator, the robot's body known, as ``accuracy.py``'s)
that differ only in ``RecognitionSettings.lean_steady_state``, both seeing the same frames. Each measured
frame is preceded by ``--history`` frames one ``accuracy.TRACK_STEP_MM`` step apart (default 2: the first is a
full-frame detection, the second a ROI search whose output the lean pass starts from; with 1 the lean pass is
never tried). Prints ``accuracy.py``'s table (rows ``roi`` and ``lean``), how many measured views the lean pass
found, and per robot the frames whose records differ; ``--json`` writes both trackers' per-frame scores in
``accuracy.py``'s layout (under ``frames[robot]["roi" | "lean"]``). Asserts nothing.

    .venv/bin/python benchmarks/lean_accuracy.py --seed 1 [--poses 30] [--history 2] [--json FILE]
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
sys.path.insert(0, str(ROOT / "benchmarks"))

import accuracy  # noqa: E402

from appliance.compiled import warm_up_all  # noqa: E402
from appliance.recognition import steady_state  # noqa: E402
from appliance.robots import load_robots  # noqa: E402
from drivers.loopback.scene_builders import S_BEND_CENTRELINE_MM, smooth_centreline  # noqa: E402
from drivers.loopback.xray_render import ImagingSettings, VesselPhantom, biplane_views  # noqa: E402

VARIANTS = {"roi": {"estimator": "weighted", "lean_steady_state": False},
            "lean": {"estimator": "weighted", "lean_steady_state": True}}

#: Views found by the lean pass, per variant (counted by wrapping SteadyPair.search).
LEAN_VIEWS = {name: 0 for name in VARIANTS}
PAIRS = {name: 0 for name in VARIANTS}


def _counting_search():  # type: ignore[no-untyped-def]
    search = steady_state.SteadyPair.search

    def counted(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        found = search(self, *args, **kwargs)
        name = "lean" if self.settings.lean_steady_state else "roi"
        PAIRS[name] += 1
        if found:
            LEAN_VIEWS[name] += sum(self.lean_views())
        return found

    steady_state.SteadyPair.search = counted  # type: ignore[method-assign]


def _key(record: dict[str, Any]) -> tuple:
    return tuple(json.dumps(record.get(k), sort_keys=True) for k in sorted(record) if k != "search")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--poses", type=int, default=30)
    parser.add_argument("--seed", type=int, default=20261121)
    parser.add_argument("--robots", default="1,2,3,4,5,6,7")
    parser.add_argument("--history", type=int, default=2)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    _counting_search()
    warm_up_all()
    robots = load_robots()
    views = biplane_views()
    calibration = accuracy.true_calibration(views)
    phantom = VesselPhantom(smooth_centreline(S_BEND_CENTRELINE_MM), accuracy.VESSEL_RADIUS_MM,
                            accuracy.VESSEL_ATTENUATION_PER_MM)
    imaging = ImagingSettings()
    results: dict[int, dict[str, dict[str, Any]]] = {}
    frames: dict[int, dict[str, list[dict[str, Any]]]] = {}
    lines = []
    for robot_id in (int(r) for r in args.robots.split(",")):
        before = dict(LEAN_VIEWS)
        poses = accuracy.random_poses(np.random.default_rng([args.seed, robot_id]), args.poses)
        scores, _ = accuracy.run_robot(robot_id, robots[robot_id], poses, args.seed, calibration, views, phantom,
                                       imaging, tracked=True, history=args.history, variants=VARIANTS)
        results[robot_id] = {name: accuracy.summarise(s) for name, s in scores.items()}
        frames[robot_id] = scores
        differ = [i for i, (a, b) in enumerate(zip(scores["roi"], scores["lean"])) if _key(a) != _key(b)]
        found = LEAN_VIEWS["lean"] - before["lean"]
        lines.append(f"robot {robot_id}: lean views {found} (of {2 * args.poses} measured + "
                     f"{2 * args.poses * (args.history - 1)} history); records differing {len(differ)}: {differ}")
    if args.json:
        settings = {k: str(v) for k, v in vars(args).items()}
        args.json.write_text(json.dumps({"args": settings, "summary": results, "frames": frames}, indent=1))
    if sys.stderr.isatty():
        sys.stderr.write("\r" + " " * 40 + "\r")
    print(f"lean vs ROI search, accuracy.py --tracked --history {args.history}, {args.poses} poses, seed {args.seed}")
    accuracy.print_table(results)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
