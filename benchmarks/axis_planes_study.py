"""What the axis-planes correction (:func:`.body_kernels._onto_axis_planes`) does to the centroid, frame by
frame, at every axis sigma (a diagnostic; asserts nothing, changes no production code).

The accuracy benchmark's frames (its poses, noise and, with ``--tracked``, its history frame) are recognised
by the weighted estimator with the body prior, :func:`.body_kernels.place` wrapped: on each call the planes'
shift ``delta`` (across the axis) is also computed with the sigma cut-off lifted. The final centroid at a
planes weight ``w`` is then ``placed + (w - w_now) * delta`` (``w_now`` the weight the production rule gave it; the shift is across the axis, so the body's placement along it is unchanged
to first order). Frames whose placement runs in the steady-state kernel (tracked plain frames) are not seen
by the wrapper: they have no row (``placed`` is none).

Per frame it writes (``--out``, JSON lines) the axis sigma, the centroid error vector (production), the
shift, the truth's axis, the error along / across the true axis, each view's image-centroid error along and
across its image axis (px), the axis error, and the flags; ``--summary`` prints bins of sigma over such files.

Round 11 rows also hold ``turned`` (the shift at each planes' turn factor of :data:`TURNS`,
:data:`.body_kernels.AXIS_PLANE_TURN_PER_AXIS_SIGMA`), the planes' angle and each plane's turn from the true
axis plane; ``--turns`` summarises them.

Usage: ``python benchmarks/axis_planes_study.py --seeds 1-20 [--robots 1,...] [--tracked] [--poses-only SEED:ROBOT:POSE,...]
--out FILE`` and ``python benchmarks/axis_planes_study.py --summary FILE...`` or ``--turns FILE...``.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import benchmarks.accuracy as acc  # noqa: E402
from appliance.compiled import warm_up_all  # noqa: E402
from appliance.geometry_kernels import _SRC, VIEW_SIZE  # noqa: E402
from appliance.recognition import PostureTracker, RecognitionSettings  # noqa: E402
from appliance.recognition import body_kernels as bk  # noqa: E402
from appliance.recognition.reconstruction_kernels import _plane_normal  # noqa: E402
from appliance.robots import load_robots  # noqa: E402
from drivers.loopback.scene_builders import S_BEND_CENTRELINE_MM, smooth_centreline  # noqa: E402
from drivers.loopback.xray_render import BiplaneRenderer, ImagingSettings, RobotBody, RobotPose, VesselPhantom, biplane_views  # noqa: E402

_last: dict = {}
_place = bk.place


def _wrapped_place(G, inp, body, out):
    _place(G, inp, body, out)
    free = inp.copy()
    free[bk.IN_AXIS_SIGMA] = 0.0   # (the cut-off only: the shift itself does not use the sigma)
    rows = np.empty((2, bk._E_SIZE))
    bk._evidence(G, free, body, 0, rows[0])
    c = np.empty(3)
    sigma_c = rows[0, bk._E_CORE_S] if rows[0, bk._E_CORE_N] > 0 else 0.0
    bk._onto_axis_planes(G, free, sigma_c, c)
    # (round 11) the shift at each turn factor, at the production share (the sigma cut-off as in production)
    c_now = np.empty(3)
    bk._onto_axis_planes(G, inp, sigma_c, c_now)
    turned = {}
    for k in TURNS:
        ck = np.empty(3)
        bk._onto_planes_turned(G, inp, sigma_c, k, ck)
        turned[str(k)] = (ck - inp[:3]).tolist()
    turned[str(float(bk.AXIS_PLANE_TURN_PER_AXIS_SIGMA))] = (c_now - inp[:3]).tolist()
    _last.update(turned=turned, turn_now=str(float(bk.AXIS_PLANE_TURN_PER_AXIS_SIGMA)), normals=_plane_normals(G, inp),
                 centroid_in=inp[:3].tolist())
    _last.update(sigma=float(inp[bk.IN_AXIS_SIGMA]), delta=(c - inp[:3]).tolist(),
                 share=_weight("now", math.degrees(float(inp[bk.IN_AXIS_SIGMA]))),
                 placed=out[bk.OUT_CENTROID:bk.OUT_CENTROID + 3].tolist() if out[bk.OUT_PLACED] else None,
                 centroid_sigma_mm=float(sigma_c))


#: The planes' turn factors (:data:`.body_kernels.AXIS_PLANE_TURN_PER_AXIS_SIGMA`) whose shifts are recorded.
TURNS = (0.0, 0.1, 0.25, 0.5, 1.0, 2.0, 4.0)


def _plane_normals(G, inp) -> list:
    """Each view's axis plane normal as :func:`.body_kernels._onto_planes_turned` builds it (none if absent)."""
    normals = []
    for view in range(2):
        i = bk.IN_VIEW + view * bk.IN_VIEW_SIZE
        tips = inp[i + bk.V_TIPS:i + bk.V_TIPS + 4]
        d = np.array([tips[0] - tips[2], tips[1] - tips[3]])
        n = np.empty(3)
        span = float(np.linalg.norm(d))
        ok = inp[i + bk.V_PRESENT] != 0.0 and span > 0 and _plane_normal(
            G, view * VIEW_SIZE, inp[i + bk.V_CENTROID:i + bk.V_CENTROID + 2].copy(), d / span, 0.25 * span * span, 0.0, n)
        normals.append(n.tolist() if ok else None)
    return normals


def _plane_study(G, normals, centroid_in, pose) -> dict:
    """The planes' angle (deg), and each plane's turn from the true axis plane (deg: the angle between its normal
    and the normal of the plane through the source and the true axis)."""
    res = {}
    if all(n is not None for n in normals):
        res["plane_angle_deg"] = math.degrees(math.asin(min(1.0, float(np.linalg.norm(np.cross(normals[0], normals[1]))))))
    turns = []
    for view, n in enumerate(normals):
        if n is None:
            continue
        src = G[view * VIEW_SIZE + _SRC:view * VIEW_SIZE + _SRC + 3]
        true_n = np.cross(pose.centroid_mm - src, pose.direction)
        true_n /= np.linalg.norm(true_n)
        turns.append(math.degrees(math.asin(min(1.0, float(np.linalg.norm(np.cross(n, true_n)))))))
    res["plane_turns_deg"] = turns
    return res


def _views_errors(posture, pair) -> dict:
    res = {}
    for name in "pq":
        obs = posture.views.get(name)
        if obs is None:
            continue
        t = pair.truth[name]
        ax = np.asarray(obs.tips_px[0]) - np.asarray(obs.tips_px[1])
        span = float(np.linalg.norm(ax))
        ax = ax / span if span > 0 else ax
        d = np.asarray(obs.centroid_px) - t.centroid_px
        res[name] = {"along_px": float(d @ ax), "across_px": float(d @ np.array([-ax[1], ax[0]])), "span_px": span}
    return res


def _one_step_back(pose: RobotPose, step_rng: np.random.Generator) -> RobotPose:
    """The benchmark's ``--tracked`` history frame (``--history 1``): the pose one step back along a random direction."""
    step = step_rng.normal(size=3)
    return RobotPose(pose.centroid_mm - step * (acc.TRACK_STEP_MM / np.linalg.norm(step)), pose.direction)


def run(seed: int, robot_ids: list[int], tracked: bool, only: set | None, out) -> None:
    robots = load_robots()
    views = acc.biplane_views() if hasattr(acc, "biplane_views") else biplane_views()
    cal = acc.true_calibration(views)
    phantom = VesselPhantom(smooth_centreline(S_BEND_CENTRELINE_MM), acc.VESSEL_RADIUS_MM, acc.VESSEL_ATTENUATION_PER_MM)
    imaging = ImagingSettings()
    for robot_id in robot_ids:
        if only is not None and not any(s == seed and r == robot_id for s, r, _ in only):
            continue
        spec = robots[robot_id]
        poses = acc.random_poses(np.random.default_rng([seed, robot_id]), 30)
        body = RobotBody(spec.length_mm, spec.diameter_mm, spec.tip_angle_deg, spec.attenuation_per_mm)
        renderer = BiplaneRenderer(views, body, vessel=phantom, settings=imaging, seed=seed + robot_id)
        step_rng = np.random.default_rng([seed, robot_id, 1])
        tracker = PostureTracker(cal, RecognitionSettings(estimator="weighted", dark_level=imaging.dark_level), body=spec)
        for i, pose in enumerate(poses):
            before = [renderer.render(_one_step_back(pose, step_rng))] if tracked else []
            pair = renderer.render(pose)
            # (the benchmark's paper tracker draws no random numbers: skipping it keeps the noise the same)
            if only is not None and (seed, robot_id, i) not in only:
                continue
            tracker.reset()
            for k, earlier in enumerate(before):
                tracker.process(earlier.images["p"], earlier.images["q"], frame=2 * i + k, t=k / acc.TRACK_FPS)
            _last.clear()
            posture = tracker.process(pair.images["p"], pair.images["q"], frame=2 * i + len(before),
                                      t=len(before) / acc.TRACK_FPS)
            s = acc.score(posture.to_record(), pose, pair.head_mm, pair.tail_mm)
            row = {"seed": seed, "robot": robot_id, "pose": i, "tracked": tracked, "ok": s["ok"],
                   "ambiguous": s["ambiguous"], "axis_deg": s["axis_deg"], "centroid_mm": s["centroid_mm"],
                   "tips_mm": s["tips_mm"], "reason": s["reason"], "search": tracker.last_search}
            if posture.ok and posture.centroid_mm is not None:
                err = np.asarray(posture.centroid_mm) - pose.centroid_mm
                u = pose.direction
                row["err"] = err.tolist()
                row["err_along"] = float(err @ u)
                row["err_across"] = float(np.linalg.norm(err - (err @ u) * u))
                row["views"] = _views_errors(posture, pair)
                if posture.direction is not None:
                    row["axis_line_deg"] = acc._angle(np.asarray(posture.direction), u)
                if _last.get("placed") is not None:
                    row.update({k: _last[k] for k in ("sigma", "delta", "share", "centroid_sigma_mm", "turned",
                                                           "turn_now")})
                    row.update(_plane_study(cal.packed, _last["normals"], _last["centroid_in"], pose))
                    row["final_is_placed"] = bool(np.allclose(_last["placed"], posture.centroid_mm, atol=1e-9))
            out.write(json.dumps(row) + "\n")
            out.flush()


def _weight(rule: str, sigma_deg: float) -> float:
    if rule == "now":   # the production rule
        return _weight(f"tail:{math.degrees(bk.AXIS_PLANES_FULL_SIGMA_RAD)}", sigma_deg)
    if rule == "base":   # the rule at 3f0ba5c: a hard cut-off at 2.5 deg
        return 1.0 if sigma_deg <= 2.5 else 0.0
    if rule == "always":
        return 1.0
    if rule == "never":
        return 0.0
    kind, value = rule.split(":")
    value = float(value)
    if kind == "cut":
        return 1.0 if sigma_deg <= value else 0.0
    if kind == "inv":   # 1 / (1 + (sigma / s0)^2): a weight halved at s0
        return 1.0 / (1.0 + (sigma_deg / value) ** 2)
    if kind == "tail":   # 1 up to value, then (value / sigma)^2
        return min(1.0, (value / sigma_deg) ** 2) if sigma_deg > 0 else 1.0
    if kind == "quart":   # 1 / (1 + (sigma / s0)^4): flat below s0, halved at it
        return 1.0 / (1.0 + (sigma_deg / value) ** 4)
    raise ValueError(rule)


RULES = ("base", "now", "never", "always", "cut:4", "cut:6", "inv:8", "tail:3", "tail:4", "tail:6", "quart:6", "quart:8",
         "quart:10")
BINS = (0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 6.0, 10.0, 90.0)


def _moved(r: dict, rule: str) -> float | None:
    """The frame's centroid error (mm) under a weight rule (unchanged where the wrapper did not see it)."""
    if not r["ok"] or r["centroid_mm"] is None:
        return None
    if "sigma" not in r or not r["final_is_placed"]:
        return r["centroid_mm"]
    w_now = r["share"] if "share" in r else (1.0 if r["applied"] else 0.0)   # (rows written at 3f0ba5c: applied)
    return float(np.linalg.norm(np.asarray(r["err"]) + (_weight(rule, math.degrees(r["sigma"])) - w_now)
                                * np.asarray(r["delta"])))


def summary(paths: list[Path]) -> None:
    every = [json.loads(line) for p in paths for line in p.read_text().splitlines() if line.strip()]
    groups: dict = {}
    for r in every:
        groups.setdefault((r["seed"], r["robot"], r["tracked"]), []).append(r)
    print(f"{len(groups)} robot-seed runs; per rule: runs with centroid RMS > 0.1 mm, and per robot the pooled RMS (mm)")
    for rule in RULES:
        misses, pooled = 0, {}
        for (seed, robot, tracked), rs in groups.items():
            errs = [e for e in (_moved(r, rule) for r in rs) if e is not None]
            misses += bool(errs) and math.sqrt(np.mean(np.square(errs))) > 0.1
            pooled.setdefault(robot, []).extend(errs)
        print(f"{rule:>8}: {misses:3d} misses; " + " ".join(
            f"r{k} {math.sqrt(np.mean(np.square(v))):.4f}" for k, v in sorted(pooled.items())))
    rows = [r for r in every if "sigma" in r and r["final_is_placed"]]
    print(f"{len(rows)} frames placed by the Python path (all of sigma; tracked plain frames are not here)")
    header = f"{'sigma deg':>10} {'n':>5} " + " ".join(f"{r:>8}" for r in RULES) + "   (centroid RMS mm; max)"
    print(header)
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        sel = [r for r in rows if lo <= math.degrees(r["sigma"]) < hi]
        if not sel:
            continue
        cells, maxes = [], []
        for rule in RULES:
            errs = []
            for r in sel:
                sd = math.degrees(r["sigma"])
                w_now = r["share"] if "share" in r else (1.0 if r["applied"] else 0.0)
                e = np.asarray(r["err"]) + (_weight(rule, sd) - w_now) * np.asarray(r["delta"])
                errs.append(float(np.linalg.norm(e)))
            cells.append(f"{math.sqrt(np.mean(np.square(errs))):8.3f}")
            maxes.append(f"{max(errs):8.3f}")
        print(f"{lo:4.1f}-{hi:<5.1f} {len(sel):5d} " + " ".join(cells))
        print(f"{'max':>10} {'':5} " + " ".join(maxes))


def turn_summary(paths: list[Path]) -> None:
    """Round 11: the planes' turn model (rows with ``turned``): per turn factor the centroid RMS (all frames and
    per robot, and by the planes' angle) and the frames it moves by > 1 um against no turn; each plane's measured
    turn (from the true axis plane) against the axis sigma, by the planes' angle. A row's error at factor ``k``
    is its production error plus ``turned[k] - turned[now]`` (now: the production factor)."""
    rows = [json.loads(line) for p in paths for line in p.read_text().splitlines() if line.strip()]
    rows = [r for r in rows if r["ok"] and r["centroid_mm"] is not None]
    ks = [str(k) for k in TURNS if all(str(k) in r["turned"] for r in rows if "turned" in r)]   # (in every file)

    def shifted(r: dict) -> bool:
        return "turned" in r and bool(r.get("final_is_placed"))

    def err(r: dict, k: str | None) -> float:
        """The row's centroid error at turn factor ``k`` (None: no planes at all)."""
        if not shifted(r):
            return r["centroid_mm"]
        now = np.asarray(r["turned"][r.get("turn_now", "1.0")])   # (rows of the first round-11 runs: at 1.0)
        new = np.asarray(r["turned"][k]) if k is not None else np.zeros(3)
        return float(np.linalg.norm(np.asarray(r["err"]) + new - now))

    def rms(v: list) -> float:
        return math.sqrt(np.mean(np.square(v))) if len(v) else math.nan

    print(f"{len(rows)} ok frames; centroid RMS (mm) per turn factor, all frames and per robot")
    for k in (None, *ks):
        per: dict = {}
        for r in rows:
            per.setdefault(r["robot"], []).append(err(r, k))
        every = [x for v in per.values() for x in v]
        moved = "" if k in (None, ks[0]) else " (vs no turn: %d better, %d worse by > 1 um)" % (
            sum(err(r, k) < err(r, ks[0]) - 1e-3 for r in rows), sum(err(r, k) > err(r, ks[0]) + 1e-3 for r in rows))
        print(f"{k or 'none':>6}: all {rms(every):.5f} " + " ".join(f"r{rb} {rms(v):.5f}" for rb, v in sorted(per.items()))
              + moved)
    placed = [r for r in rows if "plane_angle_deg" in r and shifted(r)]
    print("by the planes' angle (deg): frames, centroid RMS without the planes and per turn factor (" + ", ".join(ks) + "); each plane's turn (deg) RMS and its ratio to the axis sigma")
    for lo, hi in ((0, 2), (2, 4), (4, 8), (8, 15), (15, 90)):
        sel = [r for r in placed if lo <= r["plane_angle_deg"] < hi]
        if not sel:
            continue
        turns = [t for r in sel for t in r["plane_turns_deg"]]
        ratio = [t / math.degrees(r["sigma"]) for r in sel for t in r["plane_turns_deg"] if r["sigma"] > 0]
        print(f"{lo:2d}-{hi:<3d} {len(sel):5d} " + " ".join(f"{rms([err(r, k) for r in sel]):.4f}" for k in (None, *ks))
              + f"  turn RMS {rms(turns):.3f} ratio RMS {rms(ratio):.3f} (95 % {np.percentile(ratio, 95):.3f})")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="1-20")
    ap.add_argument("--robots", default="1,2,3,4,5,6,7")
    ap.add_argument("--tracked", action="store_true")
    ap.add_argument("--poses-only", default=None, help="SEED:ROBOT:POSE,... (only these frames)")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--summary", type=Path, nargs="+")
    ap.add_argument("--turns", type=Path, nargs="+", help="round 11: the planes' turn model's summary of such files")
    a = ap.parse_args()
    if a.turns:
        turn_summary(a.turns)
        return 0
    if a.summary:
        summary(a.summary)
        return 0
    only = None
    if a.poses_only:
        only = {tuple(int(x) for x in item.split(":")) for item in a.poses_only.split(",")}
        seeds = sorted({s for s, _, _ in only})
    else:
        lo, _, hi = a.seeds.partition("-")
        seeds = list(range(int(lo), int(hi or lo) + 1))
    warm_up_all()
    bk.place = _wrapped_place
    with open(a.out, "a") as out:
        for seed in seeds:
            run(seed, [int(r) for r in a.robots.split(",")], a.tracked, only, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
