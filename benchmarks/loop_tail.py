"""Thread CPU time of the loop's tail after recognition: control + allocation, and the amplifier command
until the port's ``write`` returns (issue 8), warm and after the caches were cycled.

Each repetition runs the path follower, the safety supervisor and the current allocator on a posture
moving along the shipped path (as ``appliance bench``'s ``_control_step``), then
``Amplifier.set_currents`` to the loopback amplifier served on a pty by its own process. Two regimes:

* ``warm``: repetitions back to back (everything in the caches);
* ``cold``: a sweep over 48 MB between repetitions, as a frame's recognition does to the caches
  (the ``appliance bench`` figures are taken in this regime).

``--aligned`` runs the control step with ``CurrentAllocator.allocate_aligned`` (the moment along the
field normalised inside the kernel) instead of ``_control_step``'s numpy glue, for comparison.

Prints min / p50 / p99 of the thread CPU time (us) per stage; asserts nothing.

    .venv/bin/python benchmarks/loop_tail.py [--n 2000] [--no-amplifier] [--aligned]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import appliance.control.actuation as _actuation  # noqa: E402
import appliance.control.allocation as _allocation  # noqa: E402
import appliance.control.path_follower as _path_follower  # noqa: E402
from appliance.benchmarking import _control_chain, _control_step, _TimedPort  # noqa: E402
from appliance.commands.bench import served_amplifier  # noqa: E402
from drivers.amplifier import Amplifier  # noqa: E402
from drivers.transport import open_serial  # noqa: E402


class _Posture:
    """The fields of a recognised posture that the control step reads."""

    def __init__(self, centroid_mm: np.ndarray, direction: np.ndarray) -> None:
        self.ok = True
        self.centroid_mm = centroid_mm
        self.direction = direction


def _stats(values: list[float]) -> str:
    a = np.asarray(values)
    return f"min {a.min():7.1f}  p50 {np.percentile(a, 50):7.1f}  p99 {np.percentile(a, 99):7.1f}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=2000, help="repetitions per regime (default 2000)")
    parser.add_argument("--no-amplifier", action="store_true", help="control + allocation only")
    parser.add_argument("--aligned", action="store_true", help="control step with allocate_aligned")
    args = parser.parse_args()
    for module in (_actuation, _allocation, _path_follower):   # the control kernels only
        module.warm_up()
    chain = _control_chain()
    follower = chain[0]
    path = follower.points
    sweep = np.ones(6 * 1024 * 1024)   # 48 MB: more than the L3
    dt = 1.0 / 30.0
    cpu = time.thread_time_ns

    def aligned_step(posture: _Posture, t: float, commanded: np.ndarray) -> object:
        follower, safety, allocator = chain
        command = follower.command(posture.centroid_mm, posture.direction, t)
        decision = safety.update(t, True, command.field_T, command.force_N, None)
        return allocator.allocate_aligned(posture.centroid_mm, decision.field_T, decision.force_N, 1e-3, commanded, dt)

    step = ((lambda posture, t, commanded: aligned_step(posture, t, commanded)) if args.aligned
            else (lambda posture, t, commanded: _control_step(chain, posture, t, commanded, dt, 1e-3)))

    def run(amplifier: Amplifier | None, port: _TimedPort | None) -> None:
        commanded = np.zeros(chain[2].model.n)
        for regime in ("warm", "cold"):
            control_us: list[float] = []
            written_us: list[float] = []
            for k in range(args.n):
                i = (k // 3) % (len(path) - 1)
                posture = _Posture(path[i] + np.array([0.05, -0.03, 0.02]), path[i + 1] - path[i])
                if regime == "cold":
                    sweep.sum()
                t = k * dt
                began = cpu()
                allocation = step(posture, t, commanded)
                allocated = cpu()
                control_us.append((allocated - began) / 1e3)
                if amplifier is not None and port is not None:
                    commanded = amplifier.set_currents(allocation.currents_a).commanded_a
                    written_us.append((port.written_cpu_ns - allocated) / 1e3)
                else:
                    commanded = allocation.currents_a
            print(f"{regime:<5} control + allocation  {_stats(control_us)}", flush=True)
            if written_us:
                print(f"{regime:<5} amplifier written     {_stats(written_us)}", flush=True)

    if args.no_amplifier:
        run(None, None)
        return 0
    with served_amplifier(chain[2].model.n, 1000) as url:
        port = _TimedPort(open_serial(url, timeout=0.05))
        amplifier = Amplifier(port)
        try:
            amplifier.enable()
            run(amplifier, port)
        finally:
            amplifier.shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
