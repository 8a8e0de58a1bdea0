"""Sustained throughput of the USB grabber path: the real driver (pyusb, FrameAssembler, CRC checks,
numpy frames) reading 1024x1024 16-bit frames from the fake pyusb backend as fast as it delivers them.

    .venv/bin/python benchmarks/usb_throughput.py [--frames 300] [--size 1024x1024]

Prints a table per bulk transfer size (and one run with injected faults), then an integrity table: many
small frames with every kind of fault injected at random, what the device injected against what the
driver counted, and how many delivered frames differ from what the device sent (must be 0). The fake device's side is
included in the time (it slices its pre-encoded frame into transfers and copies each into pyusb's
buffer, as libusb copies from the kernel), so the figures are a lower bound for the host path alone;
real hardware is further limited by the bus (USB 2.0 high speed carries about 40 MB/s of payload,
i.e. ~19 frames/s at 1024x1024x2 bytes; USB 3 about 400 MB/s).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.frame_source import open_source  # noqa: E402
from drivers.loopback.usb_backend import FakeGrabberBackend, FakeGrabberDevice, Fault, PatternFeed  # noqa: E402


def run(width: int, height: int, frames: int, transfer_kib: int, faults: dict[Fault, float] | None) -> dict[str, float]:
    feed = PatternFeed("p", width, height, pool=4, seed=1)
    device = FakeGrabberDevice(feed, serial="BENCH", realtime=False, fault_rates=faults, seed=3)
    source = open_source(f"usb://1209:0001?transfer_kib={transfer_kib}", backend=FakeGrabberBackend([device]))
    with source:
        source.read(5.0)                     # warm-up: first frame encoded, buffers allocated
        start = time.perf_counter()
        for _ in range(frames):
            source.read(5.0)
        elapsed = time.perf_counter() - start
        stats = source.link_stats
        counters = source.counters
    payload_mb = frames * width * height * 2 / 1e6
    return {"fps": frames / elapsed, "mbps": payload_mb / elapsed, "ms": 1000 * elapsed / frames,
            "transfers": stats.transfers / (frames + 1), "corrupt": counters.corrupt, "dropped": counters.dropped,
            "stalls": stats.stalls}


def integrity(frames: int, transfer_kib: int = 3) -> None:
    import numpy as np

    rates = {Fault.CORRUPT_HEADER: 0.02, Fault.BAD_CRC: 0.02, Fault.TRUNCATE: 0.02, Fault.STALL: 0.01,
             Fault.TIMEOUT: 0.02, Fault.SHORT_TRANSFERS: 0.03, Fault.GARBAGE: 0.02}
    feed = PatternFeed("p", 256, 256, pool=8, seed=2)
    device = FakeGrabberDevice(feed, serial="CHECK", realtime=False, fault_rates=rates, seed=5)
    with open_source(f"usb://1209:0001?transfer_kib={transfer_kib}", backend=FakeGrabberBackend([device])) as source:
        got = [source.read(5.0) for _ in range(frames)]
        stats, counters = source.link_stats, source.counters
    last = got[-1].number
    injected = {kind: sum(1 for n, f in device.faults_injected.items() if f is kind and n <= last) for kind in Fault}
    bad = sum(not np.array_equal(f.image, feed.frame(f.number).image) for f in got)
    print(f"\nintegrity: {frames} frames delivered of {last + 1} sent (256x256 mono16, {transfer_kib} KiB transfers)")
    print(f"  injected: " + ", ".join(f"{kind.value} {count}" for kind, count in injected.items()))
    print(f"  counted:  corrupt_header {stats.corrupt_headers}, bad_crc {stats.bad_crc}, truncated {stats.truncated}, "
          f"stalls {stats.stalls}, usb_timeouts {stats.usb_timeouts}; source corrupt {counters.corrupt}, "
          f"dropped {counters.dropped}")
    print(f"  delivered frames that differ from what the device sent: {bad}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--size", default="1024x1024")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    print(f"USB grabber path, {width}x{height} mono16 ({width * height * 2 / 1e6:.2f} MB/frame), "
          f"{args.frames} frames per row, fake backend unpaced")
    print(f"{'transfer':>9} {'faults':>7} {'frames/s':>9} {'MB/s':>8} {'ms/frame':>9} {'xfers/frame':>11} "
          f"{'corrupt':>7} {'dropped':>7} {'stalls':>6}")
    faults = {Fault.BAD_CRC: 0.02, Fault.TRUNCATE: 0.02, Fault.CORRUPT_HEADER: 0.02, Fault.STALL: 0.01,
              Fault.TIMEOUT: 0.02}
    for kib, injected in ((64, None), (256, None), (1024, None), (4096, None), (1024, faults)):
        r = run(width, height, args.frames, kib, injected)
        print(f"{kib:>6}KiB {'yes' if injected else 'no':>7} {r['fps']:>9.1f} {r['mbps']:>8.0f} {r['ms']:>9.2f} "
              f"{r['transfers']:>11.1f} {r['corrupt']:>7d} {r['dropped']:>7d} {r['stalls']:>6d}")
    integrity(2000)


if __name__ == "__main__":
    import logging

    logging.disable(logging.WARNING)   # the driver warns on every injected fault; the table says it all
    main()
