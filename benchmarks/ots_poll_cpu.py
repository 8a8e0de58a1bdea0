"""The NDI reader's CPU per poll, part by part (issue 8: the reader thread shares the loop's GIL).

Against the loopback tracker over a real pseudo-terminal (the fake served by a thread of this process,
as ``PtyServer`` does), with N tools loaded, in TX or BX mode. Every figure is thread CPU time
(``time.thread_time_ns``), median and p90 over many repetitions, in microseconds:

* ``poll``: one ``NDITracker.read_frame`` (what the background reader calls each period);
* ``exchange``: its command and reply (flush, encode, write, the reads, the BX header CRC or the text
  reply's CRC), i.e. ``command``;
* ``decode``: the reply bytes -> records (``decode_bx`` / ``decode_tx_text``), on one recorded reply;
* ``crc``: ``crc16`` of that reply's body alone (a part of ``decode`` for BX);
* ``samples``: records -> ``ToolSample`` objects (the 4x4 transforms);
* ``hand-off``: the reader's store of the newest frame and its ``notify_all``;
* ``reader``: the background reader's own CPU clock (``pthread_getcpuclockid``) from one hand-off to
  the next while it streams at 60 Hz for ``--stream-s`` seconds: a whole period of its loop (the wait,
  the poll, the hand-off), read by this thread when the hand-off wakes it. Its kernel time (the pty's
  system calls, the GIL released) is included: it is an upper bound of the GIL time it takes. It varies
  run to run with the machine's load by up to 2x: compare trees alternately, several runs each.

Runs against whichever tree is first on ``PYTHONPATH`` (it appends its own tree only as a fallback), so
the same script measures a baseline worktree. Asserts nothing; quote the load (``uptime``).

    PYTHONPATH=. .venv/bin/python benchmarks/ots_poll_cpu.py [--n 2000] [--tools 1] [--modes bx tx]
"""
from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.append(str(Path(__file__).resolve().parents[1]))

from drivers.loopback.ots_fake import FixedPose, NdiTrackerFake, NoiseModel, synthetic_rom  # noqa: E402
from drivers.loopback.serve import PtyServer  # noqa: E402
from drivers.ndi_tracker import NDITracker  # noqa: E402
from drivers.transport import open_serial  # noqa: E402
from firmware_protocol.ndi import crc16  # noqa: E402
from firmware_protocol.ndi_replies import BX_HEADER_BYTES, decode_bx, decode_tx_text  # noqa: E402

POSITION = np.array([10.0, -20.0, -1500.0])


def cpu_us(fn, n: int) -> np.ndarray:
    """Thread CPU of ``fn()`` n times, microseconds each."""
    out = np.empty(n)
    clock = time.thread_time_ns
    for k in range(n):
        start = clock()
        fn()
        out[k] = (clock() - start) / 1e3
    return out


def measure(mode: str, n: int, tools: int, stream_s: float) -> dict[str, np.ndarray | float]:
    fake = NdiTrackerFake(FixedPose(np.eye(3), POSITION), noise=NoiseModel(seed=1))
    with PtyServer(fake) as server, NDITracker(open_serial(server.path, baudrate=9600, timeout=0.05)) as ndi:
        ndi.connect()
        for k in range(tools):
            ndi.load_tool(synthetic_rom(f"BENCH-{k}"))
        ndi.start()
        for _ in range(50):
            ndi.read_frame(mode)
        figures: dict[str, np.ndarray | float] = {}
        figures["poll"] = cpu_us(lambda: ndi.read_frame(mode), n)
        figures["exchange"] = cpu_us(lambda: ndi.command(mode.upper(), "0001", binary=mode == "bx"), n)
        raw = ndi.command(mode.upper(), "0001", binary=mode == "bx")
        if mode == "bx":
            assert isinstance(raw, bytes)
            body = raw[BX_HEADER_BYTES:-2]
            figures["decode"] = cpu_us(lambda: decode_bx(raw), n)
            figures["crc"] = cpu_us(lambda: crc16(body), n)
            reply = decode_bx(raw)
        else:
            assert isinstance(raw, str)
            figures["decode"] = cpu_us(lambda: decode_tx_text(raw), n)
            framed = raw.encode("ascii")   # the text reply's CRC, checked inside the exchange
            figures["crc"] = cpu_us(lambda: crc16(framed), n)
            reply = decode_tx_text(raw)
        figures["samples"] = cpu_us(lambda: ndi._samples(reply, 0.0), n)
        samples = ndi._samples(reply, 0.0)

        def hand_off() -> None:
            with ndi._latest_changed:
                ndi._latest = samples
                ndi._latest_changed.notify_all()

        figures["hand-off"] = cpu_us(hand_off, n)

        ndi.start_streaming(mode)
        ndi.wait_for_frame(timeout_s=2.0)
        assert ndi._reader is not None and ndi._reader.ident is not None
        clock_id = time.pthread_getcpuclockid(ndi._reader.ident)
        per_poll, seen = [], ndi._latest
        before = time.clock_gettime_ns(clock_id)
        end = time.monotonic() + stream_s
        while time.monotonic() < end:
            with ndi._latest_changed:       # woken by each poll's hand-off (a new list every poll)
                while ndi._latest is seen:
                    ndi._latest_changed.wait(1.0)
                seen = ndi._latest
            now = time.clock_gettime_ns(clock_id)
            per_poll.append((now - before) / 1e3)
            before = now
        ndi.stop_streaming()
        figures["reader"] = np.array(per_poll[1:])
        figures["reader polls/s"] = len(per_poll) / stream_s
    return figures


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=2000, help="repetitions of each part")
    parser.add_argument("--tools", type=int, default=1, help="tools loaded (the sim loads one)")
    parser.add_argument("--modes", nargs="+", default=["bx", "tx"], choices=["bx", "tx"])
    parser.add_argument("--stream-s", type=float, default=3.0, help="seconds of background reading")
    args = parser.parse_args()
    import drivers
    print(f"tree {Path(drivers.__file__).resolve().parents[1]}, load {os.getloadavg()[0]:.2f}, "
          f"{args.tools} tool(s), thread CPU us: median / p90")
    for mode in args.modes:
        figures = measure(mode, args.n, args.tools, args.stream_s)
        parts = []
        for name in ("poll", "exchange", "decode", "crc", "samples", "hand-off", "reader"):
            values = figures[name]
            assert isinstance(values, np.ndarray)
            parts.append(f"{name} {np.median(values):.1f}/{np.percentile(values, 90):.1f}")
        print(f"{mode}: " + ", ".join(parts) + f" ({figures['reader polls/s']:.1f} polls/s)", flush=True)
    print(f"load after {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
