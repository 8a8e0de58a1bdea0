"""The USB grabber driver's share of "frame on host -> command written" (issue 8): from the return of the
bulk transfer that completes a frame (where the driver stamps the frame's host time) to the frame handed on
by ``read`` (payload CRC checked, assembled, wrapped as a numpy frame), per frame, in thread CPU and wall time.

    .venv/bin/python benchmarks/grabber_handoff.py [--frames 400] [--sizes 1024x1024,768x672] [--transfers 64,1024]

The real driver reads the fake pyusb backend unpaced (``realtime=False``), one frame per ``read``; each row
is a frame size and a bulk transfer size (with 1024 KiB transfers a 768x672 mono16 frame, 1.03 MB, is one
transfer, so its whole payload is checked after the stamp; a 1024x1024 one, 2.1 MB, ends with a 40-byte
transfer). The consumer keeps the last ``--hold`` frames, as the pairer and the tracker do. Also printed: the
grabber thread's CPU per frame over the whole read (all transfers). Quote the load (``uptime``).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.frame_source import open_source  # noqa: E402
from drivers.loopback.usb_backend import FakeGrabberBackend, FakeGrabberDevice, PatternFeed  # noqa: E402


def measure(width: int, height: int, transfer_kib: int, frames: int, hold: int) -> dict[str, list[float]]:
    feed = PatternFeed("p", width, height, pool=4, seed=1)
    device = FakeGrabberDevice(feed, serial="HANDOFF", realtime=False)
    source: Any = open_source(f"usb://1209:0001?transfer_kib={transfer_kib}", backend=FakeGrabberBackend([device]))
    last: list[int] = [0, 0]
    with source:
        read = source.device.read

        def stamped_read(*args: Any, **kwargs: Any) -> Any:
            n = read(*args, **kwargs)
            last[0], last[1] = time.perf_counter_ns(), time.thread_time_ns()
            return n

        source.device.read = stamped_read
        kept: deque[Any] = deque(maxlen=hold)
        for _ in range(8):                       # warm-up: payloads encoded, buffers allocated
            kept.append(source.read(5.0))
        out: dict[str, list[float]] = {"wall": [], "cpu": [], "read_cpu": []}
        for _ in range(frames):
            c0 = time.thread_time_ns()
            frame = source.read(5.0)
            w1, c1 = time.perf_counter_ns(), time.thread_time_ns()
            kept.append(frame)
            out["wall"].append((w1 - last[0]) / 1e3)
            out["cpu"].append((c1 - last[1]) / 1e3)
            out["read_cpu"].append((c1 - c0) / 1e3)
        assert source.counters.corrupt == 0 and source.counters.dropped == 0
        assert np.array_equal(kept[-1].image, feed.frame(kept[-1].number).image)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=400)
    parser.add_argument("--sizes", default="1024x1024,768x672")
    parser.add_argument("--transfers", default="64,1024", help="bulk transfer sizes, KiB (the driver's default: 64)")
    parser.add_argument("--hold", type=int, default=3, help="frames the consumer keeps")
    args = parser.parse_args()
    print(f"grabber hand-off, {args.frames} frames per row, mono16, consumer holds {args.hold}; "
          f"load {os.getloadavg()[0]:.2f}")
    print("last transfer in -> frame handed on (us), and the whole read's thread CPU (all its transfers)")
    print(f"{'size':>10} {'transfer':>9} {'CPU p50':>8} {'p99':>7} {'wall p50':>9} {'p99':>7} {'read CPU p50':>13}")
    for size in args.sizes.split(","):
        width, height = (int(v) for v in size.split("x"))
        for kib in (int(v) for v in args.transfers.split(",")):
            r = measure(width, height, kib, args.frames, args.hold)
            p = {k: np.percentile(v, [50, 99]) for k, v in r.items()}
            print(f"{size:>10} {kib:>6}KiB {p['cpu'][0]:8.0f} {p['cpu'][1]:7.0f} {p['wall'][0]:9.0f} "
                  f"{p['wall'][1]:7.0f} {p['read_cpu'][0]:13.0f}")


if __name__ == "__main__":
    main()
