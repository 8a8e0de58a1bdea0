"""The anatomy of the steady state's tail on ``appliance bench`` (issue 8): which pairs are slow, and why.

``appliance bench``'s ROI recognition p99 (300 pairs: about the 3rd slowest) and its loop p99 are a few
pairs. This runs the bench itself (the same scene, chunks, host buffers, cold passes and OpenCV baseline
between the steady passes, the amplifier on its own process; no closed-loop simulation) with the tracker's
steps wrapped, and for every steady pair records:

* its path: ``plain`` (the compiled call's posture), ``objects`` (the call found both views but the frame is
  not plain: the per-view decisions in Python on its blobs and features, with the first of
  :func:`.steady_kernels._finish`'s conditions it fails, or the Python check of
  :meth:`.SteadyPair.plain_posture`), ``per_view`` (the call said a view was not plainly found:
  :meth:`.PostureTracker._search_rois`, with each view's :func:`.roi_search._compiled` result) or ``full``;
* its wall and thread CPU time (us) around ``process``, and the time of the named steps inside it (their
  own clock reads included);
* the garbage collections and numba compilations that ran during it.

Prints the fraction of pairs and the wall/CPU p50, p99 and max per path and reason, the slowest pairs with
what they ran, and the bench's own table; ``--json FILE`` writes the per-pair records. The wrappers add a
few microseconds to the pairs whose steps they time (about 0.3 us per step), so compare paths with each
other, not with ``appliance bench``'s figures. Asserts nothing.

    .venv/bin/python benchmarks/steady_tail.py [--frames 300] [--robot 1] [--json FILE] [--top 12]
"""
from __future__ import annotations

import argparse
import gc
import json
import math
import os
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numba.core.event as numba_event  # noqa: E402

from appliance.commands.bench import measure  # noqa: E402
from appliance.benchmarking import format_table  # noqa: E402
from appliance.recognition import reconstruction_kernels as rk  # noqa: E402
from appliance.recognition import roi_kernels, roi_search, steady_state  # noqa: E402
from appliance.recognition import steady_kernels as sk  # noqa: E402
from appliance.recognition import tracker as tracker_module  # noqa: E402

perf_ns = time.perf_counter_ns
cpu_ns = time.thread_time_ns
#: The record of the ``process`` call running (None outside one).
current: dict[str, Any] | None = None
records: list[dict[str, Any]] = []
#: SteadyPair.objects before it is wrapped.
_UNTIMED_OBJECTS = steady_state.SteadyPair.objects


def _step(name: str, function: Any) -> Any:
    """``function`` timed into the running record's ``steps`` (wall us, summed over calls)."""
    def timed(*args: Any, **kwargs: Any) -> Any:
        record = current
        began = perf_ns()
        try:
            return function(*args, **kwargs)
        finally:
            if record is not None:
                steps = record["steps"]
                steps[name] = steps.get(name, 0.0) + (perf_ns() - began) / 1e3
    return timed


def _nonplain_reason(pair: steady_state.SteadyPair) -> str:
    """The first of steady_kernels._finish's conditions the last call's frame fails (its order)."""
    out, inp = pair.out, pair._inp
    f = sk.OUT_FRONT
    if out[sk.OUT_FRONT_STATUS] != rk.STATUS_OK:
        return f"front status {int(out[sk.OUT_FRONT_STATUS])}"
    if out[f + rk.OUT_REASON] != rk.REASON_NONE:
        return f"front reason {int(out[f + rk.OUT_REASON])}"
    if out[f + rk.OUT_AMBIGUOUS] != 0.0:
        return "front ambiguous"
    heads, plus = [], []
    for view in range(2):
        o = sk.OUT_VIEW + view * sk.OUT_VIEW_SIZE
        r = roi_kernels.REFINED
        if out[o + r + 11] > inp[sk.IN_FINISH]:
            return f"clutter {'pq'[view]}"
        x0, y0 = out[o + sk.R_ROI], out[o + sk.R_ROI + 1]
        v = sk.IN_VIEW + view * sk.IN_VIEW_SIZE
        h, w = inp[v + sk.V_HEIGHT], inp[v + sk.V_WIDTH]
        if (x0 + out[o + r + 2] <= 0.0 or y0 + out[o + r] <= 0.0 or x0 + out[o + r + 3] >= w
                or y0 + out[o + r + 1] >= h):
            return f"edge {'pq'[view]}"
        heads.append(int(out[o + roi_kernels.HEAD]))
        plus.append(int(out[f + rk.OUT_PLUS + view]))
    votes = [(out[f + rk.OUT_SIDE + view], heads[view] == plus[view]) for view in range(2) if heads[view] >= 0]
    if not votes:
        return "no head vote"
    votes.sort(reverse=True)
    if len(votes) == 2 and votes[0][1] != votes[1][1] and not votes[1][0] < inp[sk.IN_FINISH + 4] * votes[0][0]:
        return "head votes disagree"
    if out[sk.OUT_POSTURE + sk.P_PLAIN] != 1.0:
        return "reprojection or not robot-like"
    # plain_posture's checks in Python, in its order.
    feats = _UNTIMED_OBJECTS(pair)[1]  # (not counted in the pair's steps)
    if any(feat.axis_sigma_rad != out[view * sk.OUT_VIEW_SIZE + sk.R_AXIS_SIGMA] for view, feat in enumerate(feats)):
        return "python: the kernel's axis sigma (numba hypot) is not Python's"
    settings = pair.settings
    if math.degrees(out[sk.OUT_FRONT + rk.OUT_SIGMA]) > settings.max_axis_sigma_deg:
        return "python: the axis uncertain (sigma above max_axis_sigma_deg)"
    if out[sk.OUT_FRONT + rk.OUT_CENTROID_EPIPOLAR] > settings.epipolar_band_px:
        return "python: centroids off the epipolar band"
    return "python: tips off the tips band"


def _instrument() -> None:
    """Wrap the tracker's steps (see the module docstring)."""
    T = tracker_module.PostureTracker
    process = T.process

    def recorded(self: Any, image_p: np.ndarray, image_q: np.ndarray, *, frame: int = 0, t: float = 0.0) -> Any:
        global current
        record = {"frame": frame, "tracking": self._track is not None, "steps": {}, "path": None, "why": None,
                  "views": [], "gc": [], "compiles": 0, "tracker": id(self)}
        current = record
        began, cpu = perf_ns(), cpu_ns()
        try:
            posture = process(self, image_p, image_q, frame=frame, t=t)
        finally:
            record["wall_us"], record["cpu_us"] = (perf_ns() - began) / 1e3, (cpu_ns() - cpu) / 1e3
            current = None
        record["search"] = self.last_search
        record["ok"], record["ambiguous"], record["reason"] = posture.ok, posture.ambiguous, posture.reason
        if record["path"] is None:
            record["path"] = "full" if self.last_search == "full" else "other"
        records.append(record)
        return posture

    T.process = recorded
    search = steady_state.SteadyPair.search

    def searched(self: Any, *args: Any, **kwargs: Any) -> bool:
        found = search(self, *args, **kwargs)
        if current is not None and not found:
            current["path"] = "per_view"
        return found

    steady_state.SteadyPair.search = _step("pair.search", searched)
    plain_posture = steady_state.SteadyPair.plain_posture

    def plain(self: Any, *args: Any, **kwargs: Any) -> Any:
        posture = plain_posture(self, *args, **kwargs)
        if current is not None:
            current["path"] = "plain" if posture is not None else "objects"
            if posture is None:
                current["why"] = _nonplain_reason(self)
        return posture

    steady_state.SteadyPair.plain_posture = _step("pair.plain_posture", plain)
    compiled = roi_search._compiled

    def view(*args: Any, **kwargs: Any) -> Any:
        found = compiled(*args, **kwargs)
        if current is not None:
            current["views"].append("borderline" if found is False else "not found" if found is None else "found")
        return found

    roi_search._compiled = view
    for name in ("objects", "body_inputs", "sigmas"):
        if not hasattr(steady_state.SteadyPair, name):
            continue   # (a step a later round folded away)
        setattr(steady_state.SteadyPair, name, _step(f"pair.{name}", getattr(steady_state.SteadyPair, name)))
    for name in ("_search_rois", "_search_full", "_head_by_clean_view", "_head_in_doubt", "_posture", "_placed",
                 "_remember", "_remember_plain", "_centroid_mismatch_px", "_head_by_body", "_mirror_by_body",
                 "_axis_by_length", "_rejection"):
        if not hasattr(T, name):
            continue
        setattr(T, name, _step(name, getattr(T, name)))
    for name in ("reconstruct", "reconstruct_from_front", "not_robot_like", "cut_by_edge", "off_its_images",
                 "at_odds_with_track", "declutter", "place_body", "place_plain_body", "end_clutter", "ends_used"):
        if not hasattr(tracker_module, name):
            continue
        setattr(tracker_module, name, _step(name, getattr(tracker_module, name)))

    collecting: dict[str, int] = {}

    def on_gc(phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            collecting["began"] = perf_ns()
        elif current is not None and "began" in collecting:
            current["gc"].append((info["generation"], (perf_ns() - collecting["began"]) / 1e3))

    gc.callbacks.append(on_gc)

    class Compiles(numba_event.Listener):
        def on_start(self, event: Any) -> None:
            if current is not None:
                current["compiles"] += 1

        def on_end(self, event: Any) -> None:
            pass

    numba_event.register("numba:compile", Compiles())


def _stats(values: list[float]) -> str:
    if not values:
        return "-"
    a = np.asarray(values)
    return f"{np.percentile(a, 50):6.0f} {np.percentile(a, 99):6.0f} {a.max():6.0f}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--robot", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--top", type=int, default=12, help="slowest steady pairs listed (default 12)")
    parser.add_argument("--json", type=Path, help="write the per-pair records")
    args = parser.parse_args()
    _instrument()
    result = measure(args.frames, 1024, args.robot, 8.0, args.seed, sim_seconds=0.0)
    # The steady tracker is the one whose second call was tracking (the scratch tracker's calls come first).
    trackers = [r["tracker"] for r in records if r["tracking"] and r["frame"] > 0]
    steady_id = max(set(trackers), key=trackers.count)
    steady = [r for r in records if r["tracker"] == steady_id and r["frame"] > 0 and r["search"] == "roi"]
    print(format_table(result))
    print(f"\nload {os.getloadavg()[0]:.2f}; {len(steady)} steady pairs (ROI); wall / CPU us: p50 p99 max")
    groups: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for r in steady:
        key = r["path"] + (f": {r['why']}" if r["why"] else "") + (f" ({', '.join(r['views'])})" if r["views"] else "")
        groups[key].append(r)
        groups["(all)"].append(r)
    print(f"{'path':<70} {'n':>4} {'%':>6}   {'wall p50 p99 max':>20}   {'cpu p50 p99 max':>20}")
    for key, rs in sorted(groups.items(), key=lambda kv: -len(kv[1])):
        print(f"{key[:70]:<70} {len(rs):4d} {100 * len(rs) / len(steady):6.1f}   "
              f"{_stats([r['wall_us'] for r in rs]):>20}   {_stats([r['cpu_us'] for r in rs]):>20}")
    gcs = [r for r in steady if r["gc"]]
    print(f"\npairs with a GC inside: {len(gcs)} ({[(r['frame'], r['gc']) for r in gcs][:10]})")
    print(f"pairs with a numba compile inside: {sum(r['compiles'] > 0 for r in steady)}")
    print(f"\nslowest {args.top} steady pairs (wall us, cpu us, path, reason, steps over 5 us):")
    for r in sorted(steady, key=lambda r: -r["wall_us"])[:args.top]:
        steps = ", ".join(f"{k} {v:.0f}" for k, v in sorted(r["steps"].items(), key=lambda kv: -kv[1]) if v >= 5)
        print(f"  frame {r['frame']:4d} {r['wall_us']:7.0f} {r['cpu_us']:7.0f}  {r['path']} {r['why'] or ''} "
              f"{r['views'] or ''} gc={r['gc'] or ''}  | {steps}")
    nonplain = [r for r in steady if r["path"] != "plain"]
    if nonplain:
        totals: dict[str, list[float]] = defaultdict(list)
        for r in nonplain:
            for k, v in r["steps"].items():
                totals[k].append(v)
        print(f"\nnot-plain pairs' steps (us, p50 / max over the {len(nonplain)} pairs that ran them):")
        for k, v in sorted(totals.items(), key=lambda kv: -float(np.median(kv[1]))):
            print(f"  {k:<28} n {len(v):3d}  p50 {np.median(v):6.1f}  max {max(v):6.1f}")
    if args.json:
        args.json.write_text(json.dumps(steady, indent=0, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
