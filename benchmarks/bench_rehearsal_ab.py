"""A/B of run_bench's start-up rehearsal (round 13): `old` = one tracked frame and one control step, no driver
rehearsal; `new` = REHEARSAL_FRAMES of each and Amplifier.rehearse_command. In-process bench only (--sim-seconds 0).

    .venv/bin/python benchmarks/bench_rehearsal_ab.py old|new FRAMES
"""
import sys, json
sys.path.insert(0, '.')
arm = sys.argv[1]
import appliance.benchmarking as b
if arm == "old":
    import drivers.amplifier as a
    b.REHEARSAL_FRAMES = 1
    a.Amplifier.rehearse_command = lambda self, passes=0: None
from appliance.commands.bench import measure
r = measure(frames=int(sys.argv[2]), sim_seconds=0)
roi = r.stages["roi"]
print(arm, {k: (round(roi[k]["p50"], 1), round(roi[k]["p99"], 1)) for k in ("control_allocation_cpu", "amplifier_write_cpu", "recognition_cpu")},
      "loop cpu", (round(r.loop_cpu_us["p50"], 1), round(r.loop_cpu_us["p99"], 1)))
