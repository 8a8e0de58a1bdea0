"""Latency of ``Amplifier.set_currents`` against the loopback amplifier: until the command is written (the
port's ``write`` returned) and until its acknowledgement is read, over a real pseudo-terminal served by a
thread of this process, a pty served by its own process (as a real amplifier is a separate device, with
no GIL shared), and a loopback TCP socket.

Prints a table (written p50/p99 in us; round trip p50, p90, p99, max in ms; retransmissions); asserts nothing. The loopback server
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

from appliance.benchmarking import _TimedPort  # noqa: E402
from appliance.commands.bench import served_amplifier  # noqa: E402
from drivers.amplifier import Amplifier  # noqa: E402
from drivers.loopback.amplifier_fake import FakeAmplifier, FakeAmplifierConfig  # noqa: E402
from drivers.loopback.serve import TcpServer  # noqa: E402
from drivers.transport import open_serial  # noqa: E402


def measure(url: str, n: int, channels: int, rate_hz: float) -> tuple[np.ndarray, np.ndarray, int]:
    """(written s, round trip s, retransmissions) of ``n`` commands."""
    port = _TimedPort(open_serial(url))
    amp = Amplifier(port, ack_timeout_s=0.1, retries=2)
    try:
        amp.enable()
        written = np.empty(n)
        round_trips = np.empty(n)
        period = 1.0 / rate_hz if rate_hz > 0 else 0.0
        for k in range(n):
            # A slowly rotating field: small steps, as a control loop would command.
            phase = k * 2 * np.pi / 500
            target = 2.0 * np.cos(phase + np.arange(channels) * 2 * np.pi / channels)
            started = time.perf_counter()
            amp.set_currents(target)
            round_trips[k] = time.perf_counter() - started
            written[k] = port.written_at - started
            if period:
                time.sleep(max(0.0, period - (time.perf_counter() - started)))
        return written, round_trips, amp.retransmissions
    finally:
        amp.shutdown()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=2000, help="commands per transport (default 2000)")
    parser.add_argument("--channels", type=int, default=8, help="amplifier channels (default 8)")
    parser.add_argument("--rate-hz", type=float, default=0.0,
                        help="command rate; 0 sends back to back (default)")
    args = parser.parse_args()
    print(f"set_currents: written and acknowledged, {args.n} commands, {args.channels} channels, "
          f"{'back to back' if args.rate_hz <= 0 else f'{args.rate_hz:g} Hz'}")
    print(f"{'transport':<16} {'wr p50 us':>9} {'wr p99 us':>9} {'p50 ms':>8} {'p90 ms':>8} {'p99 ms':>8} "
          f"{'max ms':>8} {'retx':>6}")
    config = FakeAmplifierConfig(channels=args.channels, watchdog_ms=1000)
    for name in ("pty (thread)", "pty (process)", "tcp (thread)"):
        if name == "tcp (thread)":
            with TcpServer(FakeAmplifier(config)) as server:
                wr, rt, retx = measure(server.address, args.n, args.channels, args.rate_hz)
        else:
            with served_amplifier(args.channels, config.watchdog_ms, in_process=name == "pty (thread)") as path:
                wr, rt, retx = measure(path, args.n, args.channels, args.rate_hz)
        w50, w99 = np.percentile(wr, [50, 99]) * 1e6
        p50, p90, p99 = np.percentile(rt, [50, 90, 99]) * 1000
        print(f"{name:<16} {w50:9.0f} {w99:9.0f} {p50:8.3f} {p90:8.3f} {p99:8.3f} {rt.max() * 1000:8.3f} {retx:6d}",
              flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
