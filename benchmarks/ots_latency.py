"""NDI tracker driver against the loopback tracker: frame round trip, background-reader rate, noise.

For TX and BX over a real pseudo-terminal and a loopback TCP socket, prints the round trip of
``NDITracker.read_frame`` (p50, p90, p99, max in ms) with N tools, the number of distinct 60 Hz frames
the background reader delivers per second, and the 3D RMS of the reported positions about the pose
set (the fake's default noise is the Polaris Spectra's 0.19 mm). Asserts nothing. A pty carries no
line rate: on a real Polaris at 115200 baud a one-tool TX reply (~80 bytes) alone takes ~7 ms.

    .venv/bin/python benchmarks/ots_latency.py [--n 600] [--tools 2]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.loopback.ots_fake import FixedPose, NdiTrackerFake, NoiseModel, synthetic_rom  # noqa: E402
from drivers.loopback.serve import PtyServer, TcpServer  # noqa: E402
from drivers.ndi_tracker import NDITracker  # noqa: E402
from drivers.transport import open_serial  # noqa: E402

POSITION = np.array([10.0, -20.0, -1500.0])


def measure(url: str, mode: str, n: int, tools: int) -> tuple[np.ndarray, float, float]:
    with NDITracker(open_serial(url, baudrate=9600, timeout=0.05)) as ndi:
        ndi.connect()
        for k in range(tools):
            ndi.load_tool(synthetic_rom(f"BENCH-{k}"))
        ndi.start()
        round_trips = np.empty(n)
        positions: dict[int, np.ndarray] = {}
        for k in range(n):
            started = time.perf_counter()
            samples = ndi.read_frame(mode)
            round_trips[k] = time.perf_counter() - started
            positions[samples[0].frame] = np.asarray(samples[0].position_mm)
        error = np.array(list(positions.values())) - POSITION
        rms = float(np.sqrt(np.mean(np.sum(error ** 2, axis=1))))
        ndi.start_streaming(mode)
        first = ndi.wait_for_frame(timeout_s=2.0)[0].frame
        time.sleep(2.0)
        last = ndi.wait_for_frame(first, timeout_s=2.0)[0].frame
        ndi.stop_streaming()
    return round_trips * 1e3, (last - first) / 2.0, rms


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=600, help="frames read per case")
    parser.add_argument("--tools", type=int, default=2, help="tools loaded")
    args = parser.parse_args()
    print(f"{'link':5} {'mode':4} {'p50 ms':>7} {'p90 ms':>7} {'p99 ms':>7} {'max ms':>7} "
          f"{'reader frames/s':>15} {'RMS mm':>7}")
    for kind in ("pty", "tcp"):
        for mode in ("tx", "bx"):
            fake = NdiTrackerFake(FixedPose(np.eye(3), POSITION), noise=NoiseModel(seed=1))
            server = PtyServer(fake) if kind == "pty" else TcpServer(fake)
            with server:
                url = server.path if isinstance(server, PtyServer) else server.address
                ms, rate, rms = measure(url, mode, args.n, args.tools)
            p50, p90, p99 = np.percentile(ms, [50, 90, 99])
            print(f"{kind:5} {mode:4} {p50:7.2f} {p90:7.2f} {p99:7.2f} {ms.max():7.2f} {rate:15.1f} {rms:7.3f}",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
