"""In-process A/B of the allocation's field-and-gradient kernel (issue 8, round 14): the 7-point central
difference of the loop fields (the old ``_field_and_gradient``, rebuilt here from ``_coil_fields``) against the
analytic one, on the shipped coils at the follower's path points, alternating old and new on the same points.

    .venv/bin/python benchmarks/gradient_ab.py [--reps 2000] [--rounds 5]
Prints the thread CPU per call (us): warm (tight loop) and after a cache sweep (4 MiB read, as a frame's
recognition leaves the caches), median per round and over the rounds.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numba
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from appliance.control import ActuationModel, load_coils  # noqa: E402
from appliance.control.actuation import _coil_fields, _field_and_gradient  # noqa: E402
from appliance.control.path_follower import PathFollower  # noqa: E402
from appliance.control import load_path  # noqa: E402

_STEP_M = 20e-6


@numba.njit(nogil=True)
def _fd_field_and_gradient(centres, axes, radii, turns, owner, n_coils, point_m):  # type: ignore[no-untyped-def]
    """The round-13 kernel: fields at the point and 6 points 20 um away, central difference."""
    points = np.empty((7, 3))
    for i in range(7):
        for k in range(3):
            points[i, k] = point_m[k]
    for j in range(3):
        points[1 + 2 * j, j] += _STEP_M
        points[2 + 2 * j, j] -= _STEP_M
    fields = _coil_fields(centres, axes, radii, turns, owner, n_coils, points)
    gradient = np.empty((9, n_coils))
    for i in range(3):
        for j in range(3):
            for c in range(n_coils):
                gradient[3 * i + j, c] = (fields[1 + 2 * j, i, c] - fields[2 + 2 * j, i, c]) / (2.0 * _STEP_M)
    return fields[0].copy(), gradient


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--reps", type=int, default=2000)
    ap.add_argument("--swept", type=int, default=200)
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    model = ActuationModel(load_coils())
    loops = (*model.loops[:4], model.loops[4], model.n)
    points = [np.asarray(p, float) * 1e-3 for p in PathFollower(load_path()).points]
    kernels = {"7-point difference": _fd_field_and_gradient, "analytic": _field_and_gradient}
    for k in kernels.values():
        k(*loops, points[0])
    worst = max(np.abs(kernels["analytic"](*loops, p)[1] - _fd_field_and_gradient(*loops, p)[1]).max()
                / np.abs(_fd_field_and_gradient(*loops, p)[1]).max() for p in points)
    print(f"load {os.getloadavg()[0]:.1f}; {len(points)} path points; analytic vs difference: max rel {worst:.1e}")
    junk = np.random.default_rng(1).random(512 * 1024)
    warm: dict[str, list[float]] = {k: [] for k in kernels}
    swept: dict[str, list[float]] = {k: [] for k in kernels}
    for _ in range(args.rounds):
        for name, k in kernels.items():
            t0 = time.thread_time_ns()
            for r in range(args.reps):
                k(*loops, points[r % len(points)])
            warm[name].append((time.thread_time_ns() - t0) / args.reps / 1e3)
            times = []
            for r in range(args.swept):
                junk.sum()
                t0 = time.thread_time_ns()
                k(*loops, points[r % len(points)])
                times.append((time.thread_time_ns() - t0) / 1e3)
            swept[name].append(float(np.median(times)))
    for name in kernels:
        print(f"{name:<20} warm per call {' '.join(f'{v:5.1f}' for v in warm[name])}  (median {np.median(warm[name]):5.1f})"
              f"   after sweep p50 {' '.join(f'{v:5.1f}' for v in swept[name])}  (median {np.median(swept[name]):5.1f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
