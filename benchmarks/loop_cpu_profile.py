"""What the loop thread's own CPU time in ``appliance sim``'s window (frame on host -> command written) is spent on.

Runs the closed loop of ``config/sim.yaml`` (recording off, the lab in its child process) and reads the loop
thread's CPU clock (``time.thread_time_ns``, and ``pthread_getcpuclockid`` from the grabber's reader at the later
frame's stamp, where the window opens) around each piece of the step:

* ``wake-up``: the stamp -> the loop's ``next_pair`` returns (its wake-up, the pairing's hand-over, the
  harness's stream wrapper);
* ``recognition`` (``PostureTracker.process``), ``plausible`` (the jump gate), ``follower`` (``command``),
  ``safety`` (``update``), ``allocation`` (``allocate_aligned``);
* ``set_currents -> write``: the amplifier driver from its call to the port's ``write`` returning;
* ``glue``: the rest of the step inside the window (the orchestrator's own lines).

Prints p50 / p99 / mean of each in microseconds of the loop thread's CPU. With ``--cprofile`` it instead
runs ``cProfile`` over the window only (enabled when ``next_pair`` returns, disabled when the write returns)
and prints the functions by their own time per step (the profiler inflates small calls; read the order).

    .venv/bin/python benchmarks/loop_cpu_profile.py [--seconds 20] [--cprofile] [--top 40]
"""
from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import resource
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from appliance.config_io import config_path, read_yaml  # noqa: E402
from appliance.recognition import steady_kernels  # noqa: E402
from appliance.session_config import session_from_mapping  # noqa: E402
from appliance.simulation import Simulation  # noqa: E402

_PIECES = ("wake-up", "recognition", "plausible", "follower", "safety", "allocation", "set_currents -> write",
           "glue", "window total")


_search_pair = steady_kernels.search_pair


def _stamping(to_frame: Any, stamps: dict[tuple[str, int], int], loop_clock: int) -> Any:
    """A grabber driver's ``_to_frame`` that also keeps the loop thread's CPU clock at the frame's stamp."""

    def stamped(assembled: Any, host_time: float) -> Any:
        frame = to_frame(assembled, host_time)
        stamps[(frame.plane, frame.number)] = time.clock_gettime_ns(loop_clock)
        while len(stamps) > 64:
            del stamps[next(iter(stamps))]
        return frame
    return stamped


def _kernel_probe(current: dict[str, Any]) -> None:
    """The steady kernel wrapped: its loop-thread CPU and minor faults into ``current``, its arguments kept."""

    def probed(*args: Any) -> Any:
        faults = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt
        start = time.thread_time_ns()
        result = _search_pair(*args)
        current["pieces"]["kernel in the loop"] = time.thread_time_ns() - start
        current["kernel_faults"] = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt - faults
        current["kernel_args"] = (args, args[-1].copy())
        return result

    steady_kernels.search_pair = probed


def _not_plain(steady: Any) -> str:
    """Why the last steady call's frame was not plain (the first of plain_posture's conditions that failed)."""
    from appliance.recognition.steady_state import _PLAIN_READ

    v = _PLAIN_READ.unpack_from(steady.out)
    plain, placed, flag = v[25], v[45], v[46]
    if plain != 1.0:
        return "the kernel's finish: not plain"
    if steady._body and (placed != 1.0 or flag != 0.0):
        return f"the body: placed {placed:g}, flag {flag:g}"
    import math

    from appliance.recognition.features import clutter_axis_sigma_rad

    for view, at in (("p", 0), ("q", 10)):
        peak, strength, clutter, count, _cu, _cv, l1, l2, axis, kernel_axis = v[at:at + 10]
        python_axis = math.hypot(axis, clutter_axis_sigma_rad(clutter, int(count), peak, strength, l1, l2)
                                 if clutter > 0.0 else 0.0)
        if kernel_axis != python_axis:
            return f"view {view}'s compiled axis uncertainty is not Python's (clutter {clutter > 0.0})"
    rms_a, rms_b, _angle, epipolar, sigma = v[20:25]
    if math.degrees(sigma) > steady._max_axis_sigma_deg:
        return "axis sigma over the limit"
    if epipolar > steady._epipolar_band_px:
        return "centroids' epipolar band"
    return "tips' epipolar band"


def _plain_probe(current: dict[str, Any], steady: Any) -> None:
    """``steady.plain_posture`` wrapped: whether the step's frame was plain (its posture built from the call)."""
    plain_posture = steady.plain_posture

    def probed(*args: Any) -> Any:
        posture = plain_posture(*args)
        current["plain"] = posture is not None
        if posture is None:
            current["why"] = _not_plain(steady)
        return posture

    steady.plain_posture = probed


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--cprofile", action="store_true", help="cProfile over the window instead of the pieces")
    parser.add_argument("--top", type=int, default=40)
    parser.add_argument("--commands", type=Path, default=None,
                        help="the steps' commanded currents and fields into this .npz (to compare two builds' outputs)")
    parser.add_argument("--dump", type=Path, default=None, help="with --cprofile: the profile's stats into this file")
    parser.add_argument("--kernel", action="store_true",
                        help="also the steady kernel's own CPU in the loop, its minor page faults, and the same call "
                             "repeated at once after the step (hot caches), for the cause of the tail")
    args = parser.parse_args()
    data = read_yaml(config_path("sim.yaml"))
    data["recording"]["enabled"] = False
    session = session_from_mapping(data, config_path("sim.yaml"))
    main_ident = threading.get_ident()
    loop_clock = time.pthread_getcpuclockid(main_ident)
    stamps: dict[tuple[str, int], int] = {}
    current: dict[str, Any] = {}
    rows: list[dict[str, int]] = []
    # On the thread's CPU clock: a call that waits (the write, a lock) counts what it ran, not its wait.
    profiler = cProfile.Profile(time.thread_time_ns, 1e-9) if args.cprofile else None
    scratch: list[np.ndarray] = []

    with Simulation(session) as sim:
        orchestrator = sim.orchestrator
        for source in sim.devices.frames.sources.values():
            source._to_frame = _stamping(source._to_frame, stamps, loop_clock)
        frames = sim.frames
        next_pair = frames.next_pair

        def timed_next_pair(timeout_s: float) -> Any:
            pair = next_pair(timeout_s)
            got = time.thread_time_ns()
            faults = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt if args.kernel else 0
            current.clear()
            current.update(pair=pair, got=got, pieces={}, faults_got=faults)
            if profiler is not None:
                profiler.enable()
            return pair

        frames.next_pair = timed_next_pair
        pieces: dict[str, int] = {}

        def fresh() -> dict[str, int]:
            return current.get("pieces", pieces)

        for key, owner, name in (("recognition", orchestrator.tracker, "process"),
                                 ("plausible", orchestrator, "_plausible"),
                                 ("follower", orchestrator.follower, "command"),
                                 ("safety", orchestrator.safety, "update"),
                                 ("allocation", orchestrator.allocator, "allocate_aligned")):
            if profiler is None:
                function = getattr(owner, name)

                def wrapper(*a: Any, _f: Any = function, _k: str = key, **kw: Any) -> Any:
                    start = time.thread_time_ns()
                    try:
                        return _f(*a, **kw)
                    finally:
                        record = fresh()
                        record[_k] = record.get(_k, 0) + time.thread_time_ns() - start
                setattr(owner, name, wrapper)
        amplifier = sim.devices.amplifier
        set_currents = amplifier.set_currents

        def timed_set_currents(values: Any) -> Any:
            current["set_start"] = time.thread_time_ns()
            return set_currents(values)

        if profiler is None:
            amplifier.set_currents = timed_set_currents
        port = amplifier._port
        write = port.write

        def timed_write(data: bytes) -> Any:
            n = write(data)
            if threading.get_ident() == main_ident and "pair" in current and "written" not in current:
                current["written"] = time.thread_time_ns()
                if args.kernel:
                    current["faults_written"] = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt
                if profiler is not None:
                    profiler.disable()
            return n

        port.write = timed_write

        def on_step(report: Any, truth: Any) -> None:
            if report.latency_write_s is None or "written" not in current:
                return
            pair = current["pair"]
            later = max(pair.frames.values(), key=lambda f: f.host_time_s)
            stamp = stamps.get((later.plane, later.number))
            if stamp is None:
                return
            row = dict(current["pieces"])
            row["wake-up"] = current["got"] - stamp
            if "set_start" in current:
                row["set_currents -> write"] = current["written"] - current["set_start"]
            row["window total"] = current["written"] - stamp
            row["glue"] = row["window total"] - sum(row.get(k, 0) for k in _PIECES[:-2])
            if "kernel_args" in current:
                args_, out = current.pop("kernel_args")
                for _ in range(2):   # the second call is on the caches the first left
                    spare = out.copy()
                    start = time.thread_time_ns()
                    _search_pair(*args_[:-1], spare)
                    hot = time.thread_time_ns() - start
                row["kernel repeated hot"] = hot
                # Again after a copy of both frames (as their arrival writes them into host memory), and after
                # the same copy into buffers of their own on the other side of the caches' footprint.
                images = args_[:2]
                if len(scratch) != 2:
                    scratch[:] = [np.empty_like(image) for image in images]
                for image, buffer in zip(images, scratch):
                    np.copyto(buffer, image)
                spare = out.copy()
                start = time.thread_time_ns()
                _search_pair(*args_[:-1], spare)
                row["kernel repeated after a pair's copy"] = time.thread_time_ns() - start
                row["kernel minor faults"] = current["kernel_faults"] * 1000   # printed / 1e3
                row["window minor faults"] = (current["faults_written"] - current["faults_got"]) * 1000
                row["plain"] = current.pop("plain", False)
                row["why"] = current.pop("why", "no steady call")
            rows.append(row)

        if args.kernel:
            _kernel_probe(current)
            _plain_probe(current, orchestrator.tracker._pair)
        result = sim.run(args.seconds, on_step=on_step)
    if args.commands is not None:
        kept = [r for r in result.reports if r.frame is not None]
        np.savez(args.commands, frame=np.array([r.frame for r in kept]),
                 commanded_a=np.array([r.commanded_a for r in kept]), field_T=np.array([r.field_T for r in kept]),
                 force_N=np.array([r.force_N for r in kept]), mode=np.array([r.mode for r in kept]))
    print(f"appliance sim, {args.seconds:g} s simulated, {len(result.reports)} steps, {len(rows)} measured; "
          f"load {os.getloadavg()[0]:.2f}")
    if profiler is not None:
        stats = pstats.Stats(profiler)
        if args.dump is not None:
            stats.dump_stats(args.dump)
        n = max(len(rows), 1)
        entries = sorted(stats.stats.items(), key=lambda kv: -kv[1][2])  # type: ignore[attr-defined]
        print(f"cProfile over the window, per step: own us, cumulative us, calls  ({n} steps)")
        for (file, line, name), (_cc, calls, own, cum, _callers) in entries[:args.top]:
            where = f"{Path(file).name}:{line}" if line else file
            print(f"  {own / n * 1e6:8.1f} {cum / n * 1e6:8.1f} {calls / n:6.1f}  {name} ({where})")
        return 0
    print("the loop thread's CPU in the window, us: p50 / p99 / mean")
    for key in _PIECES + (("kernel in the loop", "kernel repeated hot",
                                          "kernel repeated after a pair's copy", "kernel minor faults", "window minor faults")
                          if args.kernel else ()):
        values = [row.get(key, 0) / 1e3 for row in rows]
        print(f"  {key:<24} {np.percentile(values, 50):8.1f} {np.percentile(values, 99):8.1f} {np.mean(values):8.1f}")
    if args.kernel:
        for plain in (True, False):
            chosen = [row for row in rows if row.get("plain") is plain]
            if chosen:
                print(f"{len(chosen)} steps {'with' if plain else 'without'} a plain frame (the posture from the "
                      f"steady call): p50 / p99 / mean")
                if not plain:
                    reasons: dict[str, int] = {}
                    for row in chosen:
                        reasons[row["why"]] = reasons.get(row["why"], 0) + 1
                    print("  " + "; ".join(f"{why}: {count}" for why, count in sorted(reasons.items())))
                for key in ("recognition", "kernel in the loop", "window total"):
                    values = [row.get(key, 0) / 1e3 for row in chosen]
                    print(f"  {key:<24} {np.percentile(values, 50):8.1f} {np.percentile(values, 99):8.1f} "
                          f"{np.mean(values):8.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
