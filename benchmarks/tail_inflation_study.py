"""How the flat tails' inflation over another structure (:data:`.body_kernels.CLUTTERED_TAIL_INFLATION`) weighs
them against the moment centroid, frame by frame (a diagnostic; asserts nothing, changes no production code).

The accuracy benchmark's cold frames (its poses and noise) are recognised by the weighted estimator with the
body prior, :func:`.body_prior._apply` wrapped to keep each call's ``inp``. Frames with a view over another
structure (clutter above ``max_clutter``), the head identified and correct, are kept: their evidence rows
(:func:`.body_kernels._evidence`, after the axis planes) and the truth's offset along the posture's axis from
the planes' point. ``--replay`` then prints, per estimate class (the moment centroid, the tail of a view over
the structure, the tail of the clean view), its error RMS and its error over its sigma (the present one and
the one without the reduction), and replays the combination (:func:`.body_kernels._combine`'s arithmetic on the
rows' offsets, only the tails' sigmas changed) under three rules: the present one, full inflation for a
cluttered view's own tail (round 11's lead), and the reduction on the view's clutter term only (the end's own
term kept). The ambiguity flag and the unidentified heads are not replayed. Round 12: ``outliers_round12.md``.

Usage: ``python benchmarks/tail_inflation_study.py --seeds 1-12 --robots 1,2,3,5,6,7 --out FILE`` and
``python benchmarks/tail_inflation_study.py --replay FILE...``.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import benchmarks.accuracy as acc  # noqa: E402
from appliance.recognition import PostureTracker, RecognitionSettings  # noqa: E402
from appliance.recognition import body_kernels as bk  # noqa: E402
from appliance.recognition import body_prior as bp  # noqa: E402
from drivers.loopback.xray_render import BiplaneRenderer, RobotBody  # noqa: E402

RULES = {"now": "every tail reduced on a cluttered frame",
         "own-full": "full inflation for a cluttered view's own tail",
         "end-kept": "only the view-clutter term reduced, the end's own term kept"}


def _seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out += list(range(int(lo), int(hi or lo) + 1))
    return out


def collect(seeds: list[int], robot_ids: list[int]) -> list[dict[str, Any]]:
    robots, views, calibration, phantom, imaging = acc.benchmark_scene()
    captured: list[tuple[np.ndarray, list[float], Any]] = []
    original = bp._apply

    def spy(packed: np.ndarray, placed: Any, body: Any, numbers: list[float]) -> Any:
        captured.append((packed, list(numbers), body))
        return original(packed, placed, body, numbers)

    bp._apply = spy
    rows = []
    for seed in seeds:
        for rid in robot_ids:
            spec = robots[rid]
            poses = acc.random_poses(np.random.default_rng([seed, rid]), 30)
            body = RobotBody(spec.length_mm, spec.diameter_mm, spec.tip_angle_deg, spec.attenuation_per_mm)
            renderer = BiplaneRenderer(views, body, vessel=phantom, settings=imaging, seed=seed + rid)
            tracker = PostureTracker(calibration, RecognitionSettings(dark_level=imaging.dark_level), body=spec)
            for k, pose in enumerate(poses):
                pair = renderer.render(pose)
                tracker.reset()
                captured.clear()
                posture = tracker.process(pair.images["p"], pair.images["q"], frame=k, t=0.0)
                if not posture.ok or not captured:
                    continue
                packed, numbers, model = captured[-1]
                inp = np.array(numbers)
                clutter = [float(inp[bk.IN_VIEW + v * bk.IN_VIEW_SIZE + bk.V_CLUTTER]) for v in range(2)]
                u = inp[bk.IN_DIRECTION:bk.IN_DIRECTION + 3]
                if (not max(clutter) > inp[bk.IN_MAX_CLUTTER] or inp[bk.IN_HEAD_IDENTIFIED] == 0.0
                        or np.dot(u, pose.direction) < 0):
                    continue
                row = np.empty(bk._E_SIZE)
                bk._evidence(packed, inp, model.packed, 0, row)
                moved = inp.copy()
                bk._onto_axis_planes(packed, moved, row[bk._E_CORE_S], moved[bk.IN_CENTROID:bk.IN_CENTROID + 3])
                bk._evidence(packed, moved, model.packed, 0, row)
                truth = float(np.dot(pose.centroid_mm - moved[bk.IN_CENTROID:bk.IN_CENTROID + 3], u))
                rows.append({"seed": seed, "robot": rid, "pose": k, "inp": inp.tolist(), "row": row.tolist(),
                             "truth": truth, "centroid_mm": float(np.linalg.norm(posture.centroid_mm - pose.centroid_mm))})
    bp._apply = original
    return rows


def _inflations(inp: list[float], view: int) -> tuple[float, dict[str, float]]:
    """A view's tail: its inflation without the reduction, and under each rule (``_evidence``'s arithmetic)."""
    i = bk.IN_VIEW + view * bk.IN_VIEW_SIZE
    max_clutter = inp[bk.IN_MAX_CLUTTER]
    ratio = inp[i + bk.V_CLUTTER] / max_clutter
    view_gain = 1.0 + bk.VIEW_CLUTTER_GAIN * ratio * ratio
    local = inp[i + bk.V_ENDS + 1]   # the tail is end 1 (head_end 0)
    end_term = bk.END_CLUTTER_GAIN * local / max_clutter if math.isfinite(local) else 1e6
    full = view_gain + end_term
    reduced = 1.0 + bk.CLUTTERED_TAIL_INFLATION * (full - 1.0)
    own = inp[i + bk.V_CLUTTER] > max_clutter
    return full, {"now": reduced, "own-full": full if own else reduced,
                  "end-kept": 1.0 + bk.CLUTTERED_TAIL_INFLATION * (view_gain - 1.0) + end_term}


def _combined(b: np.ndarray, s: np.ndarray, apex_b: list[float], apex_s: list[float]) -> float:
    w = 1.0 / np.square(s)
    total = float(np.sum(w))
    mean = float(np.sum(w * b)) / total
    num, den = float(np.sum(w * b)), total
    for ab, sa in zip(apex_b, apex_s):
        if abs(ab - mean) <= bk.APEX_GATE_SIGMAS * math.sqrt(sa * sa + 1.0 / total):
            num += ab / (sa * sa)
            den += 1.0 / (sa * sa)
    return num / den


def replay(rows: list[dict[str, Any]]) -> None:
    classes: dict[str, list[tuple[float, float, float]]] = {}
    errors: dict[str, list[float]] = {name: [] for name in RULES}
    for r in rows:
        inp, e = r["inp"], r["row"]
        n, n_apex = int(e[bk._E_CORE_N]), int(e[bk._E_APEX_N])
        b = np.array(e[bk._E_CORE_B:bk._E_CORE_B + n])
        sigma = np.array(e[bk._E_CORE_S:bk._E_CORE_S + n])
        clean = np.array(e[bk._E_CORE_C:bk._E_CORE_C + n])
        apex_b, apex_s = e[bk._E_APEX_B:bk._E_APEX_B + n_apex], e[bk._E_APEX_S:bk._E_APEX_S + n_apex]
        by_rule = {name: sigma.copy() for name in RULES}
        for j in range(n):
            what = int(e[bk._E_CORE_WHAT + j])
            err = b[j] - r["truth"]
            if what < 0:
                classes.setdefault("moment centroid", []).append((err, sigma[j], sigma[j]))
                continue
            full, rule = _inflations(inp, what)
            # sigma^2 = clean^2 + end^2 (inflation^2 - 1): the end's own part from the present sigma
            end2 = (sigma[j] ** 2 - clean[j] ** 2) / (rule["now"] ** 2 - 1.0) if rule["now"] > 1.0 + 1e-9 else 0.0
            for name in RULES:
                by_rule[name][j] = math.sqrt(clean[j] ** 2 + end2 * (rule[name] ** 2 - 1.0))
            max_clutter = inp[bk.IN_MAX_CLUTTER]
            clutter = [inp[bk.IN_VIEW + v * bk.IN_VIEW_SIZE + bk.V_CLUTTER] for v in range(2)]
            if clutter[what] > max_clutter:
                key = "tail, its view over it" + (", both views" if clutter[1 - what] > max_clutter else ", other clean")
            else:
                key = "tail of the clean view"
            classes.setdefault(key, []).append((err, sigma[j], math.sqrt(clean[j] ** 2 + end2 * (full ** 2 - 1.0))))
        for name in RULES:
            errors[name].append(_combined(b, by_rule[name], apex_b, apex_s) - r["truth"])
    print(f"{len(rows)} frames over another structure (head identified and correct); error along the axis:")
    for key, values in sorted(classes.items()):
        a = np.array(values)
        print(f"  {key:34s} n {len(a):4d}  RMS {np.sqrt(np.mean(a[:, 0] ** 2)):.3f} mm  max {np.max(abs(a[:, 0])):.3f}"
              f"  / sigma {np.sqrt(np.mean((a[:, 0] / a[:, 1]) ** 2)):.2f}  / unreduced sigma "
              f"{np.sqrt(np.mean((a[:, 0] / a[:, 2]) ** 2)):.2f}  beyond 3 sigma {int(np.sum(abs(a[:, 0] / a[:, 1]) > 3))}")
    print("placed centroid along the axis, per rule:")
    for name, text in RULES.items():
        e = np.array(errors[name])
        print(f"  {name:9s} RMS {np.sqrt(np.mean(e ** 2)):.4f} mm  max {np.max(abs(e)):.3f}  > 0.1 mm {int(np.sum(abs(e) > 0.1))}"
              f"  ({text})")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default="1-12")
    parser.add_argument("--robots", default="1,2,3,5,6,7", help="robots with a flat tail (robot 4 has none)")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--replay", type=Path, nargs="+")
    args = parser.parse_args(argv)
    if args.replay:
        replay([r for path in args.replay for r in json.loads(path.read_text())])
        return 0
    rows = collect(_seeds(args.seeds), [int(r) for r in args.robots.split(",")])
    if args.out:
        args.out.write_text(json.dumps(rows))
    replay(rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
