"""In-process A/B of the driver's command path to the write (issue 8, round 14): the host limiter and the
SET_CURRENTS frame's encoding as of round 13 (rebuilt here) against this tree's
(``limit_current_list(..., milliamps=True)`` and ``encode_set_currents`` through ``frame_short_body``),
alternating on the same vectors, each call after a cache sweep (4 MiB read) as after a frame's recognition.

    .venv/bin/python benchmarks/command_path_ab.py [--rounds 6] [--calls 300]
Prints thread CPU per call (us), median per round: an empty call (the measurement's floor), old, new; and
checks that both put the same bytes on the wire for every vector (over and under the limits).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.amplifier_types import AmplifierLimits, limit_current_list  # noqa: E402
from firmware_protocol.amplifier import (  # noqa: E402
    _SET_CURRENTS_PACKETS,
    _SET_CURRENTS_TYPE,
    HEADER_SIZE,
    PROTOCOL_VERSION,
    encode_set_currents,
)
from firmware_protocol.amplifier_framing import DELIMITER, _CRC, cobs_encode, crc16_ccitt_false  # noqa: E402


def _old_limit(requested_a: list[float], previous_a: list[float], dt_s: float,
               limits: AmplifierLimits) -> tuple[list[float], float, float]:
    """Round 13's limit_current_list."""
    max_a, slew = limits.max_current_a, limits.slew_a_per_s
    current_scale = 1.0
    for value, limit in zip(requested_a, max_a):
        if value > limit or -value > limit:
            current_scale = min(current_scale, limit / abs(value))
    target = [value * current_scale for value in requested_a] if current_scale < 1.0 else requested_a
    step = [t - p for t, p in zip(target, previous_a)]
    dt = 0.0 if 0.0 > dt_s else dt_s
    slew_scale = 1.0
    for delta, rate in zip(step, slew):
        allowed = rate * dt
        if delta > allowed or -delta > allowed:
            slew_scale = min(slew_scale, allowed / abs(delta))
    commanded = []
    for p, d, m in zip(previous_a, step, max_a):
        value = p + d * slew_scale
        value = -m if -m > value else value
        commanded.append(m if m < value else value)
    return commanded, current_scale, slew_scale


def _old_encode(currents_ma: list[int], seq: int) -> bytes:
    """Round 13's encode_set_currents."""
    n = len(currents_ma)
    layout = _SET_CURRENTS_PACKETS.get(n)
    if layout is None:
        raise ValueError(n)
    body = layout.pack(PROTOCOL_VERSION, _SET_CURRENTS_TYPE, seq, layout.size - HEADER_SIZE, n, *currents_ma)
    return DELIMITER + cobs_encode(body + _CRC.pack(crc16_ccitt_false(body))) + DELIMITER


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--calls", type=int, default=300)
    args = ap.parse_args()
    limits = AmplifierLimits.uniform(8, max_current_a=12.0, slew_a_per_s=120.0, watchdog_ms=200)
    rng = np.random.default_rng(0)
    requests = [(rng.normal(0, 3, 8) * rng.choice([0.3, 1.0, 6.0])).tolist() for _ in range(64)]
    previous = [rng.normal(0, 3, 8).clip(-12, 12).tolist() for _ in range(64)]
    dt = 0.02

    def old(i: int) -> bytes:
        commanded, _, _ = _old_limit(requests[i], previous[i], dt, limits)
        return _old_encode([int(v * 1000.0) for v in commanded], i)

    def new(i: int) -> bytes:
        command_ma, _, _ = limit_current_list(requests[i], previous[i], dt, limits, milliamps=True)
        return encode_set_currents(command_ma, i)

    def floor(i: int) -> None:
        return None

    same = sum(old(i) == new(i) for i in range(64))
    print(f"load {os.getloadavg()[0]:.1f}; same bytes on the wire {same}/64")
    junk = np.random.default_rng(1).random(512 * 1024)
    rows: dict[str, list[float]] = {"empty call": [], "round 13": [], "this tree": []}
    for _ in range(args.rounds):
        for name, fn in zip(rows, (floor, old, new)):
            times = []
            for i in range(args.calls):
                junk.sum()
                t0 = time.thread_time_ns()
                fn(i & 63)
                times.append(time.thread_time_ns() - t0)
            rows[name].append(float(np.median(times)) / 1e3)
    for name, values in rows.items():
        print(f"{name:<11} p50 per round {' '.join(f'{v:5.1f}' for v in values)}  (median {np.median(values):5.1f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
