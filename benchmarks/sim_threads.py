"""Every thread of ``appliance sim`` and of its child processes: how often it wakes, what it runs, how long it waits.

Issue 8's loop window (frame on host -> command written, ~1 ms) loses its core when another task is
runnable on it: this machine has two cores, and the simulated lab (world, amplifier and tracker fakes,
renderer) runs in child processes beside the appliance's own threads (grabber readers, the tracker's
reader, the amplifier's heartbeat). A thread that wakes often can preempt the loop inside its window even
if it uses little CPU, so this census counts the wake-ups as well as the CPU.

Runs the closed loop of ``config/sim.yaml`` (recording off) and reads, before and after the run, for every
task of this process and of its descendants: ``/proc/PID/task/TID/schedstat`` (CPU time, time spent
runnable on a run queue, time slices), the voluntary and involuntary context switches of ``status``
(a voluntary switch is the thread going to sleep, so it is about its wake-ups) and its nice value and
scheduling policy from ``stat``. Prints per thread: CPU and run-queue wait per loop step, wake-ups and
preemptions per wall second, nice and policy. Threads of this process are named by their Python name;
child processes by their module.

    .venv/bin/python benchmarks/sim_threads.py [--seconds 20] [--in-process]

Quote the load (``uptime``) beside the figures; asserts nothing.
"""
from __future__ import annotations

import argparse
import inspect
import os
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from appliance.config_io import config_path, read_yaml  # noqa: E402
from appliance.session_config import session_from_mapping  # noqa: E402
from appliance.simulation import Simulation, summary_lines  # noqa: E402

_POLICIES = {0: "other", 1: "fifo", 2: "rr", 3: "batch", 5: "idle", 6: "deadline"}


@dataclass
class TaskReading:
    process: str
    name: str
    cpu_ns: int
    queued_ns: int
    voluntary: int
    involuntary: int
    nice: int
    policy: str


def _descendants(pid: int) -> list[int]:
    """``pid`` and every live process below it."""
    parents: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                parents[int(entry.name)] = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
    found, frontier = [pid], [pid]
    while frontier:
        children = [child for child, parent in parents.items() if parent in frontier]
        found += children
        frontier = children
    return found


def _process_label(pid: int) -> str:
    if pid == os.getpid():
        return "appliance"
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return str(pid)
    module = argv[argv.index(b"-m") + 1].decode() if b"-m" in argv else argv[0].decode()
    return f"{module.rsplit('.', 1)[-1]}[{pid}]"


def census() -> dict[int, TaskReading]:
    """A reading of every task of this process and its descendants, by thread id."""
    python_names = {t.native_id: t.name for t in threading.enumerate() if t.native_id is not None}
    readings: dict[int, TaskReading] = {}
    for pid in _descendants(os.getpid()):
        label = _process_label(pid)
        try:
            tids = [int(name) for name in os.listdir(f"/proc/{pid}/task")]
        except OSError:
            continue
        for tid in tids:
            where = Path(f"/proc/{pid}/task/{tid}")
            try:
                cpu, queued, _ = (int(v) for v in (where / "schedstat").read_text().split())
                status = dict(line.split(":", 1) for line in (where / "status").read_text().splitlines() if ":" in line)
                stat = (where / "stat").read_text().rsplit(")", 1)[1].split()
            except (OSError, ValueError):
                continue
            name = python_names.get(tid, f"tid {tid}") if pid == os.getpid() else (
                "main" if tid == pid else f"tid {tid}")
            readings[tid] = TaskReading(
                process=label, name=name, cpu_ns=cpu, queued_ns=queued,
                voluntary=int(status["voluntary_ctxt_switches"]), involuntary=int(status["nonvoluntary_ctxt_switches"]),
                nice=int(stat[16]), policy=_POLICIES.get(int(stat[38]), stat[38]))
    return readings


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--in-process", action="store_true", help="the simulated lab in this process")
    args = parser.parse_args()
    data = read_yaml(config_path("sim.yaml"))
    data["recording"]["enabled"] = False
    session = session_from_mapping(data, config_path("sim.yaml"))
    options = {"separate_lab": not args.in_process} if "separate_lab" in inspect.signature(
        Simulation.__init__).parameters else {}
    steps: list[int] = [0]
    with Simulation(session, **options) as sim:
        before = census()
        wall = time.perf_counter()
        result = sim.run(args.seconds, on_step=lambda report, truth: steps.__setitem__(0, steps[0] + 1))
        wall = time.perf_counter() - wall
        after = census()
        stats = sim.orchestrator.stats
        # Threads of the loop's process that the run started (the orchestrator's) are in ``after`` only.
        names = {t.native_id: t.name for t in threading.enumerate() if t.native_id is not None}
    print(f"appliance sim, {args.seconds:g} s simulated in {wall:.1f} s wall, lab "
          f"{'in process' if args.in_process else 'default'}; load {os.getloadavg()[0]:.2f}")
    print("\n".join(summary_lines(result, stats)))
    n = max(steps[0], 1)
    print(f"\nevery task, over the run ({n} steps): CPU and run-queue wait in ms per step, wake-ups (voluntary "
          f"switches) and preemptions (involuntary) per wall second")
    print(f"  {'process':<22} {'thread':<34} {'CPU':>7} {'queued':>7} {'wakes/s':>8} {'preempt/s':>9} "
          f"{'nice':>4} policy")
    rows = []
    for tid, end in after.items():
        start = before.get(tid)
        base = start if start is not None else TaskReading(end.process, end.name, 0, 0, 0, 0, end.nice, end.policy)
        name = names.get(tid, end.name) if end.process == "appliance" else end.name
        rows.append((end.process, name, (end.cpu_ns - base.cpu_ns) / 1e6 / n,
                     (end.queued_ns - base.queued_ns) / 1e6 / n, (end.voluntary - base.voluntary) / wall,
                     (end.involuntary - base.involuntary) / wall, end.nice, end.policy))
    for process, name, cpu, queued, wakes, preempted, nice, policy in sorted(rows, key=lambda r: (r[0], -r[2])):
        if cpu < 0.005 and wakes < 1.0:
            continue
        print(f"  {process:<22} {name[:34]:<34} {cpu:7.3f} {queued:7.3f} {wakes:8.1f} {preempted:9.1f} {nice:4d} "
              f"{policy}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
