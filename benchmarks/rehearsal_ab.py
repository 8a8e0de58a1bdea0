"""A/B of the start-up rehearsal (issue 8, round 13): the session's first pairs with the old rehearsal
(a detection and one tracked frame; no control, no driver) against the new one
(:data:`appliance.orchestrator.REHEARSAL_TRACKED_PASSES` tracked frames and control steps, the driver's
command path). Runs ``config/sim.yaml`` for ``--seconds`` per run, alternating, in fresh processes.

    .venv/bin/python benchmarks/rehearsal_ab.py [--runs 3] [--seconds 2]
Prints per run and arm the stages (us, wall) of pairs 1-5 (pair 0 is the detection) and the later pairs' p50.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
_CHILD = r"""
import json, sys
sys.path.insert(0, {root!r})
import appliance.orchestrator as o
if {old}:
    import drivers.amplifier as a
    o.REHEARSAL_TRACKED_PASSES = 1
    a.Amplifier.rehearse_command = lambda self, passes=0: None
from appliance.config_io import config_path, read_yaml
from appliance.session_config import session_from_mapping
from appliance.simulation import Simulation
data = read_yaml(config_path("sim.yaml"))
data.setdefault("recording", {{}})["enabled"] = False
data["simulation"] = {{**data.get("simulation", {{}}), "max_seconds": {seconds}}}
rows = []
def on_step(report, truth):
    if report.latency_write_s is None:
        return
    s = report.stages_us
    rows.append([1e6 * report.latency_write_s, s.get("recognition", 0.0),
                 s.get("control", 0.0) + s.get("allocation", 0.0), s.get("amplifier_write", 0.0)])
with Simulation(session_from_mapping(data, config_path("sim.yaml"))) as sim:
    sim.run({seconds}, on_step=on_step)
print("ROWS" + json.dumps(rows))
"""


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=2.0)
    args = ap.parse_args()
    print("columns: latency, recognition, control+allocation, amplifier written (us, wall)")
    summary: dict[str, list[np.ndarray]] = {"old": [], "new": []}
    for run in range(args.runs):
        for arm in ("old", "new") if run % 2 == 0 else ("new", "old"):
            code = _CHILD.format(root=str(ROOT), old=arm == "old", seconds=args.seconds)
            out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                                 env=os.environ.copy(), timeout=600)
            line = next((x for x in out.stdout.splitlines() if x.startswith("ROWS")), None)
            if line is None:
                print(f"run {run} {arm}: failed\n{out.stderr[-800:]}")
                continue
            rows = np.array(json.loads(line[4:]))
            if len(rows) < 10:
                print(f"run {run} {arm}: only {len(rows)} pairs (the session stopped early)\n{out.stderr[-400:]}")
                continue
            load = os.getloadavg()[0]
            first, later = rows[1:6], np.median(rows[6:], axis=0)
            summary[arm].append(np.median(first, axis=0) - later)
            print(f"run {run} {arm} (load {load:.1f}): pairs 1-5 " + "; ".join(
                " ".join(f"{v:.0f}" for v in r) for r in first) + " | later p50 " + " ".join(f"{v:.0f}" for v in later))
    for arm, excess in summary.items():
        if excess:
            print(f"{arm}: pairs 1-5 median minus later p50, median over runs: "
                  + " ".join(f"{v:.0f}" for v in np.median(excess, axis=0)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
