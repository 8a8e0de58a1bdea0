"""Per-frame comparison of two sets of ``benchmarks/accuracy.py --json`` files (a diagnostic; asserts nothing).

Usage: ``python benchmarks/accuracy_compare.py BASE_DIR NEW_DIR [PREFIX...]``: for each ``PREFIX_SEED.json``
found in both (prefixes default ``acc`` and ``acct``), the weighted estimator's frames whose centroid error
changed by more than 1 um (before -> after, and their flags), then per robot-seed the target misses before
and after (centroid RMS > 0.1 mm, median axis > 0.5 deg, tips RMS > 0.3 mm, silent failures), and per robot
the centroid RMS pooled over every file.
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path


def misses(summary: dict) -> list[str]:
    out = []
    if summary["centroid_rms_mm"] is not None and summary["centroid_rms_mm"] > 0.1:
        out.append(f"centroid {summary['centroid_rms_mm']:.3f}")
    if summary["axis_median_deg"] is not None and summary["axis_median_deg"] > 0.5:
        out.append(f"axis {summary['axis_median_deg']:.2f}")
    if summary["tips_rms_mm"] is not None and summary["tips_rms_mm"] > 0.3:
        out.append(f"tips {summary['tips_rms_mm']:.3f}")
    if summary["silent_failures"]:
        out.append(f"silent {summary['silent_failures']}")
    return out


def main() -> int:
    base, new = Path(sys.argv[1]), Path(sys.argv[2])
    prefixes = sys.argv[3:] or ["acc", "acct"]
    pooled: dict = {}
    total = {"before": 0, "after": 0}
    for prefix in prefixes:
        for path in sorted(new.glob(f"{prefix}_*.json")):
            old_path = base / path.name
            if not old_path.exists():
                continue
            a, b = json.loads(old_path.read_text()), json.loads(path.read_text())
            for robot, by_estimator in b["frames"].items():
                fa, fb = a["frames"][robot]["weighted"], by_estimator["weighted"]
                for i, (x, y) in enumerate(zip(fa, fb)):
                    pooled.setdefault(robot, {"before": [], "after": []})
                    if x["centroid_mm"] is not None:
                        pooled[robot]["before"].append(x["centroid_mm"])
                    if y["centroid_mm"] is not None:
                        pooled[robot]["after"].append(y["centroid_mm"])
                    cx, cy = x["centroid_mm"], y["centroid_mm"]
                    if (cx is None) != (cy is None) or (cx is not None and abs(cx - cy) > 1e-3) \
                            or x["ambiguous"] != y["ambiguous"] or x["ok"] != y["ok"]:
                        print(f"{path.stem} robot {robot} pose {i}: centroid {cx} -> {cy}, ambiguous "
                              f"{x['ambiguous']} -> {y['ambiguous']}, ok {x['ok']} -> {y['ok']}, axis "
                              f"{x['axis_deg']} -> {y['axis_deg']}")
                ma = misses(a["summary"][robot]["weighted"])
                mb = misses(b["summary"][robot]["weighted"])
                total["before"] += len(ma)
                total["after"] += len(mb)
                if ma or mb:
                    print(f"{path.stem} robot {robot}: misses {ma} -> {mb}")
    print(f"target misses: {total['before']} -> {total['after']}")
    for robot, v in sorted(pooled.items()):
        rms = {k: math.sqrt(sum(e * e for e in es) / len(es)) for k, es in v.items()}
        print(f"robot {robot}: pooled centroid RMS {rms['before']:.4f} -> {rms['after']:.4f} mm")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
