"""The first pairs of a simulated session, one row each (issue 8, round 13): why pairs 2-4 are slow.

Runs the closed loop of ``config/sim.yaml`` (recording off) for ``--seconds`` and prints, for the first
``--rows`` pairs, the latency pair on host -> written and the step's stages (us), the tracker's search
mode; then the same figures' p50 over the later pairs.

    .venv/bin/python benchmarks/startup_pairs.py [--seconds 3] [--rows 8]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from appliance.config_io import config_path, read_yaml  # noqa: E402
from appliance.session_config import session_from_mapping  # noqa: E402
from appliance.simulation import Simulation  # noqa: E402

_COLS = ("latency", "recognition", "control", "allocation", "amplifier_write")


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--rows", type=int, default=8)
    args = ap.parse_args()
    source = config_path("sim.yaml")
    data = read_yaml(source)
    data.setdefault("recording", {})["enabled"] = False
    data["simulation"] = {**data.get("simulation", {}), "max_seconds": max(args.seconds, 0.1)}
    session = session_from_mapping(data, source)
    rows: list[tuple[Any, ...]] = []
    holder: dict[str, Any] = {}
    subs: list[dict[str, float]] = []

    def on_step(report: Any, truth: Any) -> None:
        if report.latency_write_s is None:
            return
        s = report.stages_us
        rows.append((1e6 * report.latency_write_s, s.get("recognition", 0.0), s.get("control", 0.0),
                     s.get("allocation", 0.0), s.get("amplifier_write", 0.0),
                     f"{holder['sim'].orchestrator.tracker.last_search} {report.mode} {report.limited_by}"))
        subs.append({k[len("recognition."):]: v for k, v in s.items() if k.startswith("recognition.")})

    with Simulation(session) as sim:
        holder["sim"] = sim
        sim.run(args.seconds, on_step=on_step)
    print(f"{'pair':>4} " + " ".join(f"{c:>15}" for c in _COLS) + "  search mode limited_by")
    for k, row in enumerate(rows[:args.rows]):
        print(f"{k:>4} " + " ".join(f"{v:15.0f}" for v in row[:-1]) + f"  {row[-1]}")
    names = sorted({k for sub in subs for k in sub})
    print("recognition's own stages (us), first rows then the later pairs' p50:")
    print(f"{'pair':>4} " + " ".join(f"{n[:12]:>12}" for n in names))
    for k, sub in enumerate(subs[:args.rows]):
        print(f"{k:>4} " + " ".join(f"{sub.get(n, 0.0):12.0f}" for n in names))
    print(f"{'p50':>4} " + " ".join(f"{np.median([sub.get(n, 0.0) for sub in subs[args.rows:]] or [0]):12.0f}"
                                    for n in names))
    later = np.array([row[:-1] for row in rows[args.rows:]])
    if len(later):
        print(f"{'p50':>4} " + " ".join(f"{v:15.0f}" for v in np.median(later, axis=0))
              + f"  (pairs {args.rows}..{len(rows) - 1})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
