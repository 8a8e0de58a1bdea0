"""The lean steady-state call against another git revision's, in one process, alternating (issue 8, round 13).

``lean_ab.py --base REV`` with each side's buffers (``weights_buf``, ``masks_buf`` and, where the side takes
it, the lean pass's ``work``) one set per side reused by every call, as :class:`.SteadyPair` reuses them (the
recording copies every array argument per call, which would hand each call fresh, cold buffers). The calls
are those a tracker with the lean pass on makes on ``appliance bench``'s frames (robot 1, 1024^2), each after
``np.copyto`` of its pair into the host buffers, thread CPU per call, the sides alternating per call and their
order swapped every repetition. Prints p50 / p99 per side, the paired median difference, how many views
the lean pass found, and how many calls' outputs differ (``steady_chain_ab._same``: status, output numbers,
weights and masks). Asserts nothing.

    .venv/bin/python benchmarks/fused_ab.py --base REV [--frames 120] [--reps 10]
"""
from __future__ import annotations

import argparse
import inspect
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import lean_ab  # noqa: E402
import steady_chain_ab  # noqa: E402

from appliance.compiled import warm_up_all  # noqa: E402
from appliance.recognition import steady_kernels as sk  # noqa: E402

SHARED = ("weights_buf", "masks_buf", "work")


def _shared(side: steady_chain_ab._Side, prepared: list) -> list:
    """The prepared argument lists with the buffers replaced by one set for the side."""
    names = list(inspect.signature(side.kernel.py_func).parameters)[2:]
    first = prepared[0]
    buffers = {names.index(n): np.zeros_like(first[names.index(n)]) for n in SHARED if n in names}
    return [[buffers.get(k, a) for k, a in enumerate(arguments)] for arguments in prepared]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--base", required=True, help="git revision of the base chain")
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--reps", type=int, default=10)
    args = parser.parse_args(argv)
    warm_up_all()
    scene, frames = steady_chain_ab.bench_frames(args.frames)
    calls = lean_ab._lean_calls(frames, scene)
    sides = {"base": steady_chain_ab._Side(steady_chain_ab._load_chain(args.base)), "this": steady_chain_ab._Side(sk)}
    prepared = {name: _shared(side, [side.arguments(a) for _, a in calls]) for name, side in sides.items()}
    names = list(sides)
    host = (np.empty_like(frames[0][0]), np.empty_like(frames[0][1]))
    for name, side in sides.items():
        side.kernel(frames[0][0], frames[0][1], *prepared[name][0])  # compile
    times = {name: np.zeros((args.reps, len(calls))) for name in sides}
    differ = lean_views = 0
    for r in range(args.reps):
        order = names if r % 2 == 0 else names[::-1]
        for i, (n, _) in enumerate(calls):
            results = {}
            for name in order:
                times[name][r, i], results[name] = sides[name].timed(host, frames[n], prepared[name][i])
            differ += not steady_chain_ab._same(results["base"], results["this"])
            if r == 0 and results["this"][0] == sk.PAIR_FOUND:
                out = sides["this"].out
                lean_views += int(out[sk.R_FOUND_BY] == sk.FOUND_BY_LEAN) + int(
                    out[sk.OUT_VIEW_SIZE + sk.R_FOUND_BY] == sk.FOUND_BY_LEAN)
    print(f"search_pair, lean pass asked for: {len(calls)} calls x {args.reps} reps (robot 1, 1024^2), after the "
          f"frame copy, thread CPU us; base {args.base}; lean views {lean_views} of {2 * len(calls)}")
    for name, values in times.items():
        print(f"  {name:<5} p50 {np.percentile(values, 50):7.1f}  p99 {np.percentile(values, 99):7.1f}"
              f"  per-call min over reps, median {np.median(values.min(axis=0)):7.1f}")
    paired = times["this"] - times["base"]
    print(f"  paired difference this - base: median {np.median(paired):+.1f} us"
          f" (IQR {np.percentile(paired, 25):+.1f} .. {np.percentile(paired, 75):+.1f})")
    print(f"  outputs differing (status, numbers, weights, masks): {differ} of {len(calls) * args.reps}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
