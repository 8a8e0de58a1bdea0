"""Thread CPU of each piece of the loop after recognition (issue 8, round 13): follower, safety, allocation,
the amplifier driver's set_currents up to the write returning, called as the orchestrator calls them, each
step after a cache sweep (2 x 2 MiB copied, as a 1024^2 pair's arrival; 4 MiB read, as recognition's work).

    .venv/bin/python benchmarks/control_pieces.py [--steps 400]
Prints p50 / p90 / p99 (us) per piece; the amplifier is the loopback one on a pty, served by its own process.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from appliance.benchmarking import _TimedPort, _control_chain  # noqa: E402
from appliance.commands.bench import served_amplifier  # noqa: E402
from appliance.compiled import warm_up_all  # noqa: E402
from appliance.control import load_coils  # noqa: E402
from drivers.amplifier import Amplifier  # noqa: E402
from drivers.transport import open_serial  # noqa: E402


class _Port(_TimedPort):
    """:class:`_TimedPort` that also keeps the thread CPU clock just before the owner's write."""

    def write(self, data: bytes) -> int | None:
        object.__setattr__(self, "before_write_cpu_ns", time.thread_time_ns())
        return super().write(data)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--no-sweep", action="store_true")
    args = ap.parse_args()
    warm_up_all()
    follower, safety, allocator = _control_chain()
    src = [np.random.default_rng(0).integers(0, 65535, (1024, 1024), dtype=np.uint16) for _ in range(2)]
    host = [np.empty_like(a) for a in src]
    junk = np.random.default_rng(1).random(512 * 1024)
    clock = time.thread_time_ns
    rows: dict[str, list[float]] = {k: [] for k in ("follower", "safety", "allocation", "set_currents->write", "  of it: write call",
                                                     "total")}
    with served_amplifier(len(load_coils().coils)) as path:
        port = _Port(open_serial(path, timeout=0.05))
        amp = Amplifier(port)
        amp.enable()
        commanded = np.zeros(allocator.model.n)
        dt = 1.0 / 30
        moment_dir = None
        p0 = follower.points[5]
        for n in range(args.steps):
            t = n * dt
            if not args.no_sweep:
                np.copyto(host[0], src[0])
                np.copyto(host[1], src[1])
                junk.sum()
            # a posture's centroid/axis as recognition leaves them (fresh small arrays)
            centroid = p0 + np.array([0.01 * math.sin(n), 0.02, 0.01]) + follower.tangent_at(0.0) * 0.03 * n
            axis = np.array([1.0, 0.1, 0.0])
            xyz = tuple(centroid.tolist())
            c0 = clock()
            command = follower.command(centroid, axis, t)
            c1 = clock()
            decision = safety.update(t, True, command.field_T, command.force_N, 1.0)
            c2 = clock()
            field = fx, fy, fz = decision.field_T.tolist()
            fn = math.sqrt(fx * fx + fy * fy + fz * fz)
            if fn > 0.0:
                moment_dir = (fx / fn, fy / fn, fz / fn)
            allocation = allocator.allocate_aligned(xyz, field, decision.force_N.tolist(), 1e-3, commanded, dt,
                                                    zero_field_direction=moment_dir or (0.0, 0.0, 1.0))
            c3 = clock()
            result = amp.set_currents(allocation.currents_a)
            c4 = port.written_cpu_ns
            cw = port.before_write_cpu_ns
            commanded = result.commanded_a
            if n >= 20:
                for k, v in zip(rows, (c1 - c0, c2 - c1, c3 - c2, c4 - c3, c4 - cw, c4 - c0)):
                    rows[k].append(v / 1e3)
            time.sleep(0.002)
        amp.shutdown()
    for k, v in rows.items():
        a = np.asarray(v)
        p50, p90, p99 = np.percentile(a, [50, 90, 99])
        print(f"{k:<22} p50 {p50:6.1f}  p90 {p90:6.1f}  p99 {p99:6.1f}  mean {a.mean():6.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
