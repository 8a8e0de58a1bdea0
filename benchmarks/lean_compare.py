"""Per frame, the lean pass against the ROI search over ``lean_accuracy.py``'s JSON files (issue 8).

Pooled over the files given, per robot: centroid RMS (all ok frames), tips RMS, median axis error (ok,
not ambiguous) of the ``roi`` and ``lean`` trackers; the frames one tracker has ok and the other not; the
frames whose flags (ambiguous, head identified, head correct) differ; silent failures (axis > 5 deg, ok
and not flagged ambiguous) of each; and the largest per-frame centroid and tip error change. Asserts
nothing.

    .venv/bin/python benchmarks/lean_compare.py lt_777.json lt_4242.json ...
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

SILENT_AXIS_DEG = 5.0


def _rms(values: list[float]) -> float:
    return float(np.sqrt(np.mean(np.square(values)))) if values else float("nan")


def main(argv: list[str] | None = None) -> int:
    paths = [Path(p) for p in (argv if argv is not None else sys.argv[1:])]
    pooled: dict[str, dict[str, list]] = {}
    for path in paths:
        data = json.loads(path.read_text())
        for robot, by_mode in data["frames"].items():
            entry = pooled.setdefault(robot, {"roi": [], "lean": [], "where": []})
            entry["roi"] += by_mode["roi"]
            entry["lean"] += by_mode["lean"]
            entry["where"] += [f"{path.stem}#{i}" for i in range(len(by_mode["roi"]))]
    print(f"lean vs ROI search, pooled over {len(paths)} files")
    print("robot | centroid RMS roi / lean | tips RMS roi / lean | axis med roi / lean | ok lost / won | flags differ"
          " | silent roi / lean | max |d centroid err| | max |d tip err|")
    for robot, e in sorted(pooled.items(), key=lambda kv: int(kv[0])):
        stats = {}
        for mode in ("roi", "lean"):
            ok = [s for s in e[mode] if s["ok"]]
            axes = [s["axis_deg"] for s in ok if not s["ambiguous"] and s["axis_deg"] is not None]
            stats[mode] = (_rms([s["centroid_mm"] for s in ok]),
                           _rms([t for s in ok if s["tips_mm"] is not None for t in s["tips_mm"]]),
                           float(np.median(axes)) if axes else float("nan"),
                           sum(1 for s in ok if not s["ambiguous"] and s["axis_deg"] is not None
                               and s["axis_deg"] > SILENT_AXIS_DEG))
        lost = [w for a, b, w in zip(e["roi"], e["lean"], e["where"]) if a["ok"] and not b["ok"]]
        won = [w for a, b, w in zip(e["roi"], e["lean"], e["where"]) if b["ok"] and not a["ok"]]
        flags = [w for a, b, w in zip(e["roi"], e["lean"], e["where"])
                 if (a["ambiguous"], a["head_identified"], a["head_correct"])
                 != (b["ambiguous"], b["head_identified"], b["head_correct"])]
        both = [(a, b) for a, b in zip(e["roi"], e["lean"]) if a["ok"] and b["ok"]]
        dc = max((abs(a["centroid_mm"] - b["centroid_mm"]) for a, b in both), default=float("nan"))
        dt = max((max(abs(x - y) for x, y in zip(a["tips_mm"], b["tips_mm"])) for a, b in both
                  if a["tips_mm"] is not None and b["tips_mm"] is not None), default=float("nan"))
        r, lean = stats["roi"], stats["lean"]
        print(f"{robot:>5} | {r[0]:.4f} / {lean[0]:.4f} | {r[1]:.4f} / {lean[1]:.4f} | {r[2]:.3f} / {lean[2]:.3f} | "
              f"{len(lost)} / {len(won)} | {len(flags)} | {r[3]} / {lean[3]} | {dc:.4f} | {dt:.4f}")
        for label, frames in (("ok lost", lost), ("ok won", won), ("flags differ", flags)):
            if frames:
                print(f"      {label}: {', '.join(frames)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
