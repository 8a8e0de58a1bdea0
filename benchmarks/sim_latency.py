"""Where the wall time of ``appliance sim``'s "frame on host -> command written" goes (issue 8).

Runs the closed loop of ``config/sim.yaml`` (recording off) and, for every step, reads the CPU clock of
every thread of this process (``pthread_getcpuclockid``, ~1 us a thread) at three moments:

* ``host``: when the later frame of the step's pair is handed on by its grabber's driver (the pair's
  "frame on host" time is stamped when its last transfer is in, before the driver checks the payload's
  CRC: the line "stamp -> driver hands it on");
* ``got``: when the loop's ``next_pair`` returns the pair;
* ``written``: when the loop's ``write`` of the current command to the amplifier's port returns.

It prints the latency and its two parts (host -> got: pairing and the loop's wake-up; got -> written:
recognition, control, allocation, the command), the loop thread's CPU time in got -> written against the
wall time (the difference is time the loop could not run: another thread held the GIL, or the core was
taken; the loop thread's run-queue wait from ``/proc/self/task/TID/schedstat`` says how much was the
core), and the CPU time other threads of the process used inside each window, by thread (their sum is
an upper bound of the GIL time they took from the loop). Also each thread's CPU per step over the whole
run, the harness's world step (``advance_to``, in the loop's thread, between steps) and, when the
simulated lab runs in a child process, the child processes' CPU per step.

With ``--stages`` it takes only wall-clock stamps inside the window (no thread-CPU snapshots, which cost
~10-30 us each there) and prints the window stage by stage, p50 and p99 of each: stamp -> the driver hands the
frame on (the payload CRC of what came after the stamp, assembly) -> ``read`` returns (the source's checks and
counters) -> the pair formed in the pairer -> the loop's ``next_pair`` returns (its wake-up) -> recognition ->
control -> allocation -> the rest of the loop before the write -> the write; then the worst 2 % of steps one
by one with what they had in common: a collection of the garbage collector inside the window, the lab child's
CPU inside the window (its world step, render or the fakes' servers on the other core), which plane came
last, the loop thread's wait on a run queue (its core taken by another task; read outside the window, from
the frames' release to the write), the time since the harness released the frames, and the busiest other
thread of this process from the pair formed to the write (the readings inside the window: the other threads'
CPU clocks, ~1 us each, by the reader that forms the pair before it wakes the loop, and the lab child's CPU
clock at the hand-over; ``--record DIR`` records the session as ``appliance sim`` does).

    .venv/bin/python benchmarks/sim_latency.py [--seconds 20] [--in-process] [--scheduler-placement] [--stages [--record DIR]]

``--scheduler-placement`` leaves the lab's process and this one where the scheduler puts them
(``simulation.lab_own_core`` false; by default the lab has a core of its own, :mod:`appliance.core_placement`).
``--in-process`` keeps the simulated lab (world, amplifier fake, tracker fake) in this process, as
before issue 8's split (where the build has that option). Quote the load (``uptime``) beside the figures.
"""
from __future__ import annotations

import argparse
import ctypes
import gc
import inspect
import math
import os
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from appliance.config_io import config_path, read_yaml  # noqa: E402
from appliance.session_config import session_from_mapping  # noqa: E402
from appliance.simulation import Simulation, summary_lines  # noqa: E402

_TICKS = os.sysconf("SC_CLK_TCK")


def _threads() -> dict[int, str]:
    return {t.ident: t.name for t in threading.enumerate() if t.ident is not None}


def _cpu_ns(ident: int) -> int | None:
    try:
        return time.clock_gettime_ns(time.pthread_getcpuclockid(ident))
    except (OSError, ProcessLookupError):
        return None


_MAIN_TID = threading.get_native_id()


def _queued_ns() -> int:
    """Nanoseconds the loop's thread has waited on a run queue (runnable, its core taken by another task)."""
    try:
        with open(f"/proc/self/task/{_MAIN_TID}/schedstat") as handle:
            return int(handle.read().split()[1])
    except (OSError, IndexError, ValueError):
        return 0


def _switches() -> tuple[int, int]:
    """The loop thread's (voluntary, involuntary) context switches so far (``/proc/self/task/TID/status``)."""
    counts = [0, 0]
    try:
        with open(f"/proc/self/task/{_MAIN_TID}/status") as handle:
            for line in handle:
                if line.startswith("voluntary_ctxt_switches"):
                    counts[0] = int(line.split()[1])
                elif line.startswith("nonvoluntary_ctxt_switches"):
                    counts[1] = int(line.split()[1])
    except (OSError, ValueError):
        pass
    return counts[0], counts[1]


def _snapshot() -> dict[int, int]:
    out = {}
    for ident in list(_threads()):
        value = _cpu_ns(ident)
        if value is not None:
            out[ident] = value
    out[-1] = _queued_ns()
    return out


def _children_cpu_s() -> float:
    """CPU seconds (user + system) of this process's live child processes."""
    total = 0.0
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == os.getpid():          # ppid
            total += (int(fields[11]) + int(fields[12])) / _TICKS
    return total


def _label(name: str, names: dict[str, str]) -> str:
    for device, where in names.items():
        path = where.rsplit(" on ", 1)[-1]
        if path and name.endswith(path):
            return f"{name.split('-')[0]}({device})"
    return name


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def _session(args: argparse.Namespace) -> tuple[Any, dict[str, Any]]:
    """``config/sim.yaml`` with recording off (and the scheduler's placement with ``--scheduler-placement``), and
    the :class:`Simulation` options ``--in-process`` asks for (where the build has them)."""
    data = read_yaml(config_path("sim.yaml"))
    data["recording"]["enabled"] = False
    if args.scheduler_placement:
        data["simulation"]["lab_own_core"] = False
    options: dict[str, Any] = {}
    if "separate_lab" in inspect.signature(Simulation.__init__).parameters:
        options["separate_lab"] = not args.in_process
    return session_from_mapping(data, config_path("sim.yaml")), options


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--in-process", action="store_true", help="the simulated lab in this process")
    parser.add_argument("--stages", action="store_true", help="wall stamps only; the window stage by stage")
    parser.add_argument("--switch-interval", metavar="S", type=float, default=None,
                        help="with --stages: the interpreter's thread switch interval (sys.setswitchinterval) to run with")
    parser.add_argument("--record", metavar="DIR", type=Path, default=None,
                        help="with --stages: record the session into DIR/session.mcap, as appliance sim does")
    parser.add_argument("--scheduler-placement", action="store_true",
                        help="leave the lab's process and this one where the scheduler puts them (simulation."
                             "lab_own_core false; by default the lab has a core of its own)")
    args = parser.parse_args()
    if args.stages:
        return stages(args)
    session, options = _session(args)
    if args.in_process and not options:
        print("(this build has the lab in the loop's process only)")
    main_ident = threading.get_ident()
    host_snaps: dict[tuple[str, int], tuple[float, dict[int, int]]] = {}
    steps: list[dict[str, Any]] = []
    current: dict[str, Any] = {}
    world_cpu: list[float] = []
    world_wall: list[float] = []

    with Simulation(session, **options) as sim:
        names = dict(sim.devices.names)
        for source in sim.devices.frames.sources.values():
            original = source._to_frame

            def to_frame(assembled: Any, host_time: float, original: Any = original) -> Any:
                frame = original(assembled, host_time)
                host_snaps[(frame.plane, frame.number)] = (host_time, _snapshot(), time.monotonic())
                if len(host_snaps) > 64:
                    host_snaps.pop(next(iter(host_snaps)))
                return frame

            source._to_frame = to_frame
        frames = sim.frames
        next_pair = frames.next_pair

        def timed_next_pair(timeout_s: float) -> Any:
            pair = next_pair(timeout_s)
            current.clear()
            current.update(pair=pair, got=(time.monotonic(), _snapshot()))
            return pair

        frames.next_pair = timed_next_pair
        port = sim.devices.amplifier._port
        write = port.write

        def timed_write(data: bytes) -> Any:
            n = write(data)
            if threading.get_ident() == main_ident and "pair" in current and "written" not in current:
                current["written"] = (time.monotonic(), _snapshot())
            return n

        port.write = timed_write
        advance_to = sim.bench.advance_to

        def timed_advance_to(t_s: float, **kw: Any) -> None:
            c, w = time.thread_time_ns(), time.perf_counter()
            advance_to(t_s, **kw)
            world_cpu.append((time.thread_time_ns() - c) / 1e6)
            world_wall.append((time.perf_counter() - w) * 1e3)

        sim.bench.advance_to = timed_advance_to

        def on_step(report: Any, truth: Any) -> None:
            if report.latency_write_s is None or "written" not in current or "pair" not in current:
                return
            pair = current["pair"]
            later = max(pair.frames.values(), key=lambda f: f.host_time_s)
            host = host_snaps.get((later.plane, later.number))
            steps.append({"latency": report.latency_write_s * 1e3, "host": host, "got": current["got"],
                          "written": current["written"], "index": report.index,
                          "recognition_ms": report.stages_us.get("recognition", 0.0) / 1e3})

        cpu_start = _snapshot()
        children_start = _children_cpu_s()
        wall_start = time.perf_counter()
        result = sim.run(args.seconds, on_step=on_step)
        wall = time.perf_counter() - wall_start
        cpu_end = _snapshot()
        children_cpu = _children_cpu_s() - children_start
        thread_names = _threads()
        stats = sim.orchestrator.stats

    print(f"appliance sim, {args.seconds:g} s simulated, lab {'in process' if args.in_process else 'default'}; "
          f"load {os.getloadavg()[0]:.2f}")
    print("\n".join(summary_lines(result, stats)))
    n = max(len(result.reports), 1)
    lat = [s["latency"] for s in steps]
    a_wall = [(s["got"][0] - s["host"][0]) * 1e3 for s in steps if s["host"]]
    b_wall = [(s["written"][0] - s["got"][0]) * 1e3 for s in steps]
    b_loop = [(s["written"][1][main_ident] - s["got"][1][main_ident]) / 1e6 for s in steps]
    stamp = [(s["host"][2] - s["host"][0]) * 1e3 for s in steps if s["host"]]
    b_queue = [(s["written"][1][-1] - s["got"][1][-1]) / 1e6 for s in steps]
    ab_queue = [(s["written"][1][-1] - s["host"][1][-1]) / 1e6 for s in steps if s["host"]]
    print(f"\nsteps measured {len(steps)}; ms: p50 / p99 / max")
    for label, values in (("frame on host -> written", lat), ("  host -> got (pairing, wake-up)", a_wall),
                          ("    of which stamp -> driver hands it on", stamp),
                          ("  got -> written", b_wall), ("    loop thread CPU in it", b_loop),
                          ("    not running (wall - CPU)", [w - c for w, c in zip(b_wall, b_loop)]),
                          ("    of which on a run queue", b_queue),
                          ("  loop on a run queue, host -> written", ab_queue)):
        print(f"  {label:<34} {_pct(values, 50):7.2f} {_pct(values, 99):7.2f} {max(values, default=float('nan')):7.2f}")
    worst = sorted(range(len(steps)), key=lambda i: lat[i])[-max(1, len(steps) // 100):]
    print("  worst steps (index: latency, recognition ms): " + ", ".join(
        f"{steps[i]['index']}: {lat[i]:.1f}, {steps[i]['recognition_ms']:.1f}" for i in reversed(worst)))
    others: dict[str, list[float]] = defaultdict(list)
    others_worst: dict[str, float] = defaultdict(float)
    for i, s in enumerate(steps):
        start = s["host"][1] if s["host"] else s["got"][1]
        end = s["written"][1]
        for ident, value in end.items():
            if ident in (main_ident, -1) or ident not in start:
                continue
            label = _label(thread_names.get(ident, str(ident)), names)
            others[label].append((value - start[ident]) / 1e6)
            if i in worst:
                others_worst[label] += (value - start[ident]) / 1e6 / len(worst)
    print("\nother threads' CPU inside host -> written (ms per step): mean, p99, mean over the worst 1 % of steps")
    for label, values in sorted(others.items(), key=lambda kv: -float(np.mean(kv[1]))):
        print(f"  {label:<44} {np.mean(values):7.3f} {_pct(values, 99):7.3f} {others_worst[label]:7.3f}")
    print(f"\nwhole run, CPU per step (ms), {n} steps, {wall:.1f} s wall:")
    for ident, value in sorted(cpu_end.items(), key=lambda kv: -(kv[1] - cpu_start.get(kv[0], kv[1]))):
        if ident not in cpu_start or ident == -1:
            continue
        used = (value - cpu_start[ident]) / 1e6 / n
        if used >= 0.01:
            print(f"  {_label(thread_names.get(ident, str(ident)), names):<44} {used:7.3f}")
    print(f"  {'child processes':<44} {children_cpu * 1e3 / n:7.3f}")
    print(f"  harness world step (advance_to, loop thread) CPU {np.median(world_cpu):.2f} ms p50, "
          f"wall {np.median(world_wall):.2f} ms p50 / {_pct(world_wall, 99):.2f} p99")
    return 0


_LIBC = ctypes.CDLL(None, use_errno=True)


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


def _process_cpu_clock(pid: int) -> int | None:
    """The CPU-time clock id of process ``pid`` (clock_getcpuclockid), or None."""
    clock = ctypes.c_int()
    return clock.value if _LIBC.clock_getcpuclockid(pid, ctypes.byref(clock)) == 0 else None


def _clock_ns(clock: int | None) -> int:
    if clock is None:
        return 0
    ts = _Timespec()
    return ts.tv_sec * 1_000_000_000 + ts.tv_nsec if _LIBC.clock_gettime(clock, ctypes.byref(ts)) == 0 else 0


_STAGES = (("stamp -> driver hands it on", "handed"), ("  -> read returns", "read"),
           ("  -> pair formed", "paired"), ("  -> loop's next_pair returns", "got"),
           ("recognition", "recognition"), ("control", "control"), ("allocation", "allocation"),
           ("loop's rest before the write", "glue"), ("write (sent -> written)", "write"))


def stages(args: argparse.Namespace) -> int:
    """``--stages``: wall stamps only inside the window; the window stage by stage and its worst steps."""
    session, options = _session(args)
    mono = time.monotonic
    frame_marks: dict[tuple[str, int], dict[str, float]] = {}
    pair_marks: dict[int, float] = {}
    pair_threads: dict[int, dict[int, int]] = {}
    thread_names: dict[int, str] = {}
    current: dict[str, Any] = {}
    collections: list[tuple[float, float, int]] = []
    gc_started: list[float] = []
    released: list[float] = [0.0]
    queued: list[int] = [0]
    switches: list[tuple[int, int]] = [(0, 0)]
    rows: list[dict[str, Any]] = []

    def on_gc(phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            gc_started[:] = [mono()]
        elif gc_started:
            collections.append((gc_started[0], mono(), int(info.get("generation", -1))))

    recorder = None
    if args.switch_interval is not None:
        sys.setswitchinterval(args.switch_interval)
    with Simulation(session, **options) as sim:
        if args.record is not None:
            from appliance.orchestrator import RecordingListener
            from appliance.recording import Recorder

            recorder = Recorder.create(args.record / "session.mcap", config=session.config.model_dump(mode="json"),
                                       calibration=sim.devices.calibration.to_dict(),
                                       frames_every=session.config.recording.frames_every)
            sim.orchestrator.listeners.append(RecordingListener(recorder))
        main_ident = threading.get_ident()
        lab = getattr(sim.bench.lab, "process", None)
        child_clock = _process_cpu_clock(lab.pid) if lab is not None else None
        stream = sim.devices.frames
        for source in stream.sources.values():
            original_to_frame, original_read = source._to_frame, source.read

            def to_frame(assembled: Any, host_time: float, original: Any = original_to_frame) -> Any:
                frame = original(assembled, host_time)
                # The loop thread's CPU clock (~1 us, read from this reader): where the window opens.
                frame_marks[(frame.plane, frame.number)] = {"stamp": host_time, "handed": mono(),
                                                            "loop_cpu": _cpu_ns(main_ident) or 0,
                                                            "queued": _queued_ns(), "switches": _switches()}
                return frame

            def read(timeout_s: float, original: Any = original_read) -> Any:
                frame = original(timeout_s)
                marks = frame_marks.get((frame.plane, frame.number))
                if marks is not None:
                    marks["read"] = mono()
                if len(frame_marks) > 64:
                    frame_marks.pop(next(iter(frame_marks)))
                return frame

            if hasattr(source, "_to_frame"):
                source._to_frame = to_frame
            source.read = read
        pairer = stream.pairer
        push = pairer.push

        def timed_push(frame: Any) -> None:
            before = pairer.counters.pairs
            push(frame)
            if pairer.counters.pairs > before:
                pair_marks[frame.number] = mono()
                pair_threads[frame.number] = _others()
                if len(pair_marks) > 64:
                    pair_threads.pop(next(iter(pair_threads)))
                    pair_marks.pop(next(iter(pair_marks)))

        pairer.push = timed_push
        bench = sim.bench
        release = bench.release_frames

        def timed_release() -> None:
            # The loop thread's run-queue wait so far: read before the window opens (the frames are not out).
            queued[0] = _queued_ns()
            switches[0] = _switches()
            release()
            released[0] = mono()

        bench.release_frames = timed_release
        frames = sim.frames
        next_pair = frames.next_pair

        def timed_next_pair(timeout_s: float) -> Any:
            pair = next_pair(timeout_s)
            current.clear()
            current.update(pair=pair, got=mono(), child_got=_clock_ns(child_clock), released=released[0],
                           switches_released=switches[0])
            return pair

        def _others() -> dict[int, int]:
            # The other threads' CPU clocks (~1 us each), read by the reader that formed the pair, before it
            # wakes the loop: with the lab child's clock at the hand-over, the only readings inside the window.
            out = {}
            for ident, name in _threads().items():
                if ident != main_ident and (ns := _cpu_ns(ident)) is not None:
                    out[ident] = ns
                    thread_names.setdefault(ident, name)
            return out

        frames.next_pair = timed_next_pair
        port = sim.devices.amplifier._port
        write = port.write

        def timed_write(data: bytes) -> Any:
            n = write(data)
            if threading.get_ident() == main_ident and "pair" in current and "written" not in current:
                current["written"] = mono()
            return n

        read_port = port.read

        def timed_read(size: int = 1) -> Any:
            # The first read after the command's write (for its reply): the window has closed and the driver has
            # taken its "written" time, so these readings are not in the latency.
            if threading.get_ident() == main_ident and "written" in current and "queued" not in current:
                current["loop_cpu_written"] = time.thread_time_ns()
                current["switches_written"] = _switches()
                current["child_written"] = _clock_ns(child_clock)
                current["queued_written"] = _queued_ns()
                current["queued"] = current["queued_written"] - queued[0]
                current["threads_written"] = _others()
            return read_port(size)

        port.write = timed_write
        port.read = timed_read

        def on_step(report: Any, truth: Any) -> None:
            if report.latency_write_s is None or "queued" not in current:
                return
            pair = current["pair"]
            marks = {plane: frame_marks.get((plane, frame.number)) for plane, frame in pair.frames.items()}
            if any(m is None or "read" not in m for m in marks.values()):
                return
            last = max(marks, key=lambda plane: marks[plane]["stamp"])
            m = marks[last]
            st = report.stages_us
            paired = pair_marks.get(pair.number, m["read"])
            sent_to_written = st.get("amplifier_write", 0.0) / 1e3
            got_to_written = (current["written"] - current["got"]) * 1e3
            work = (st.get("recognition", 0.0) + st.get("control", 0.0) + st.get("allocation", 0.0)) / 1e3
            start_threads = pair_threads.get(pair.number, {})
            row = {"index": report.index, "latency": report.latency_write_s * 1e3, "last": last,
                   "handed": (m["handed"] - m["stamp"]) * 1e3, "read": (m["read"] - m["handed"]) * 1e3,
                   "paired": (paired - m["read"]) * 1e3, "got": (current["got"] - paired) * 1e3,
                   "recognition": st.get("recognition", 0.0) / 1e3, "control": st.get("control", 0.0) / 1e3,
                   "allocation": st.get("allocation", 0.0) / 1e3,
                   "glue": got_to_written - work - sent_to_written, "write": sent_to_written,
                   "skew": abs(marks["p"]["stamp"] - marks["q"]["stamp"]) * 1e3,
                   "since_release": (m["stamp"] - current["released"]) * 1e3,
                   "child_cpu": (current["child_written"] - current["child_got"]) / 1e6,
                   "runq": current["queued"] / 1e6,
                   "loop_cpu": (current["loop_cpu_written"] - m["loop_cpu"]) / 1e6,
                   "runq_window": (current["queued_written"] - m["queued"]) / 1e6,
                   "voluntary": current["switches_written"][0] - m["switches"][0],
                   "preempted": current["switches_written"][1] - m["switches"][1],
                   "threads": {ident: (ns - start_threads[ident]) / 1e6
                               for ident, ns in current["threads_written"].items() if ident in start_threads},
                   "window": (m["stamp"], current["written"])}
            row["asleep"] = row["latency"] - row["loop_cpu"] - row["runq_window"]
            rows.append(row)

        gc.callbacks.append(on_gc)
        try:
            result = sim.run(args.seconds, on_step=on_step)
        finally:
            gc.callbacks.remove(on_gc)
            if recorder is not None:
                recorder.close()
        stats = sim.orchestrator.stats
        names = dict(sim.devices.names)

    print(f"appliance sim, {args.seconds:g} s simulated, lab {'in process' if args.in_process else 'default'}, "
          f"recording {'on' if recorder is not None else 'off'}, switch interval {sys.getswitchinterval() * 1e3:g} ms, "
          f"wall stamps only; load {os.getloadavg()[0]:.2f}")
    print("\n".join(summary_lines(result, stats)))
    for row in rows:
        start, end = row["window"]
        row["gc"] = sum((min(b, end) - max(a, start)) * 1e3 for a, b, _ in collections if a < end and b > start)
    print(f"\nsteps measured {len(rows)}; frame on host (the later plane's stamp: its last bulk transfer returned) "
          f"-> command written, ms: p50 / p99 / max")
    print(f"  {'frame on host -> written':<36} {_pct([r['latency'] for r in rows], 50):7.3f} "
          f"{_pct([r['latency'] for r in rows], 99):7.3f} {max((r['latency'] for r in rows), default=math.nan):7.3f}")
    for label, key in _STAGES:
        values = [r[key] for r in rows]
        print(f"  {label:<36} {_pct(values, 50):7.3f} {_pct(values, 99):7.3f} {max(values, default=math.nan):7.3f}")
    for label, key in (("p/q stamps apart", "skew"), ("lab child CPU, got -> written", "child_cpu"),
                       ("loop thread on a run queue", "runq"), ("loop thread CPU in the window", "loop_cpu"),
                       ("loop thread on a run queue in it", "runq_window"),
                       ("loop thread asleep (window-CPU-runq)", "asleep"),
                       ("loop's voluntary switches", "voluntary"), ("loop's preemptions", "preempted"),
                       ("gc inside the window", "gc")):
        values = [r[key] for r in rows]
        print(f"  ({label:<34} {_pct(values, 50):7.3f} {_pct(values, 99):7.3f} {max(values, default=math.nan):7.3f})")
    worst = sorted(rows, key=lambda r: r["latency"])[-max(1, len(rows) // 50):]
    label = {ident: _label(name, names) for ident, name in thread_names.items()}
    by_thread: dict[str, list[float]] = defaultdict(list)
    for r in rows:
        for ident, ms in r["threads"].items():
            by_thread[label.get(ident, str(ident))].append(ms)
    print("\nthis process's other threads' CPU, pair formed -> written (ms): mean, p99, mean over the worst steps")
    for name, values in sorted(by_thread.items(), key=lambda kv: -float(np.mean(kv[1]))):
        tail = [r["threads"].get(ident, 0.0) for r in worst for ident in r["threads"]
                if label.get(ident, str(ident)) == name]
        print(f"  {name:<44} {np.mean(values):7.3f} {_pct(values, 99):7.3f} "
              f"{(sum(tail) / len(worst)) if worst else math.nan:7.3f}")
    for r in rows:
        busiest = max(r["threads"].items(), key=lambda kv: kv[1], default=(None, 0.0))
        r["busiest"] = (label.get(busiest[0], "-") if busiest[0] is not None else "-", busiest[1])
    print(f"\nworst {len(worst)} steps (ms): " + " ".join(f"{k[:6]:>6}" for _, k in _STAGES)
          + "  last   gc  child   runq loopcpu  inwin asleep vol/inv  since-release  busiest other thread")
    for r in reversed(worst):
        print(f"  #{r['index']:<5} {r['latency']:6.2f} " + " ".join(f"{r[k]:6.2f}" for _, k in _STAGES)
              + f"  {r['last']:>4} {r['gc']:5.2f} {r['child_cpu']:6.2f} {r['runq']:6.2f} {r['loop_cpu']:7.2f}"
              + f" {r['runq_window']:6.2f} {r['asleep']:6.2f} {r['voluntary']:3d}/{r['preempted']:<3d} {r['since_release']:6.2f}"
              + f"         {r['busiest'][0]} {r['busiest'][1]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
