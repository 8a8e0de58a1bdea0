"""Round-trip latency of ``Amplifier.set_currents`` (write SET_CURRENTS, read its acknowledgement)
against the loopback amplifier over a real pseudo-terminal and a loopback TCP socket.

Prints a table (p50, p90, p99, max in ms, retransmissions); asserts nothing. The loopback server
polls with a 2 ms select timeout but wakes on data, so figures are dominated by thread wake-ups and
the Python codec on both sides, not by a line rate (a pty has none; at 115200 baud a 41-byte
8-channel SET_CURRENTS frame alone would take 3.6 ms on the wire).

    .venv/bin/python benchmarks/amplifier_latency.py [--n 2000] [--channels 8] [--rate-hz 0]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.amplifier import Amplifier  # noqa: E402
from drivers.loopback.amplifier_fake import FakeAmplifier, FakeAmplifierConfig  # noqa: E402
from drivers.loopback.serve import PtyServer, TcpServer  # noqa: E402
from drivers.transport import open_serial  # noqa: E402


def measure(url: str, n: int, channels: int, rate_hz: float) -> tuple[np.ndarray, int]:
    amp = Amplifier(open_serial(url), ack_timeout_s=0.1, retries=2)
    try:
        amp.enable()
        round_trips = np.empty(n)
        period = 1.0 / rate_hz if rate_hz > 0 else 0.0
        for k in range(n):
            # A slowly rotating field: small steps, as a control loop would command.
            phase = k * 2 * np.pi / 500
            target = 2.0 * np.cos(phase + np.arange(channels) * 2 * np.pi / channels)
            started = time.perf_counter()
            amp.set_currents(target)
            round_trips[k] = time.perf_counter() - started
            if period:
                time.sleep(max(0.0, period - (time.perf_counter() - started)))
        return round_trips, amp.retransmissions
    finally:
        amp.shutdown()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=2000, help="commands per transport (default 2000)")
    parser.add_argument("--channels", type=int, default=8, help="amplifier channels (default 8)")
    parser.add_argument("--rate-hz", type=float, default=0.0,
                        help="command rate; 0 sends back to back (default)")
    args = parser.parse_args()
    print(f"set_currents -> ack round trip, {args.n} commands, {args.channels} channels, "
          f"{'back to back' if args.rate_hz <= 0 else f'{args.rate_hz:g} Hz'}")
    print(f"{'transport':<10} {'p50 ms':>8} {'p90 ms':>8} {'p99 ms':>8} {'max ms':>8} {'retx':>6}")
    config = FakeAmplifierConfig(channels=args.channels, watchdog_ms=1000)
    for name, server_cls in (("pty", PtyServer), ("tcp", TcpServer)):
        with server_cls(FakeAmplifier(config)) as server:
            url = server.path if name == "pty" else server.address
            rt, retx = measure(url, args.n, args.channels, args.rate_hz)
        p50, p90, p99 = np.percentile(rt, [50, 90, 99]) * 1000
        print(f"{name:<10} {p50:8.3f} {p90:8.3f} {p99:8.3f} {rt.max() * 1000:8.3f} {retx:6d}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
