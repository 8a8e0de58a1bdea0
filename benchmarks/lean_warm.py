"""The lean pair's warm and after-copy cost per call, one tree per process, from a saved recording (issue 8).

``lean_ab.py`` compiles the base chain afresh every run (minutes on a loaded machine). Here the lean calls
(``lean_ab._lean_calls`` on ``appliance bench``'s frames) are recorded once into ``--calls`` (a pickle; made
if missing) and replayed on the tree this script runs from (its root first on ``sys.path``; copy the script
into an exported base tree to time that): per call, ``--reps`` calls after ``np.copyto`` of the frame pair
("cold"), each followed by ``--warm`` calls without the copy ("warm"), thread CPU. Prints the medians over
calls of the per-call minimum and median, and writes the outputs (status, numbers, each view's weights and
mask) to ``--outputs`` for a bit-for-bit comparison of two trees (``--compare FILE``). Timings of two
processes on a loaded machine are less comparable than lean_ab's alternation; the warm minimum is the
steadiest figure. Asserts nothing.

    .venv/bin/python benchmarks/lean_warm.py --calls /tmp/calls.pkl [--outputs F] [--compare F]
"""
from __future__ import annotations

import argparse
import pickle
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import lean_ab  # noqa: E402
import steady_chain_ab  # noqa: E402

from appliance.compiled import warm_up_all  # noqa: E402
from appliance.recognition import steady_kernels as sk  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--calls", required=True, help="pickle of the recorded frames and calls (made if missing)")
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--reps", type=int, default=5)
    parser.add_argument("--warm", type=int, default=5)
    parser.add_argument("--outputs", help="write the outputs here (pickle)")
    parser.add_argument("--compare", help="compare the outputs with this file's")
    args = parser.parse_args(argv)
    path = Path(args.calls)
    if path.exists():
        frames, calls = pickle.loads(path.read_bytes())
    else:
        scene, frames = steady_chain_ab.bench_frames(args.frames)
        calls = lean_ab._lean_calls(frames, scene)
        used = sorted({n for n, _ in calls})
        frames = {n: frames[n] for n in used}
        path.write_bytes(pickle.dumps((frames, calls)))
    warm_up_all()
    side = steady_chain_ab._Side(sk)
    prepared = lean_ab._shared(side, [side.arguments(a) for _, a in calls])
    first = next(iter(frames.values()))
    host = (np.empty_like(first[0]), np.empty_like(first[1]))
    side.kernel(host[0], host[1], *prepared[0])
    cold = np.zeros((args.reps, len(calls)))
    warm = np.zeros((args.reps * args.warm, len(calls)))
    outputs = []
    for r in range(args.reps):
        for i, (n, _) in enumerate(calls):
            cold[r, i], result = side.timed(host, frames[n], prepared[i])
            if r == 0:
                outputs.append(result)
            for k in range(args.warm):
                began = time.thread_time_ns()
                side.kernel(host[0], host[1], *prepared[i])
                warm[r * args.warm + k, i] = (time.thread_time_ns() - began) / 1e3
    lean_views = sum(int(o[1][sk.R_FOUND_BY] == sk.FOUND_BY_LEAN)
                     + int(o[1][sk.OUT_VIEW_SIZE + sk.R_FOUND_BY] == sk.FOUND_BY_LEAN) for o in outputs)
    print(f"{ROOT.name}: {len(calls)} calls, lean views {lean_views} of {2 * len(calls)}; thread CPU us")
    for name, values in (("after copy", cold), ("warm", warm)):
        print(f"  {name:<10} median of per-call min {np.median(values.min(axis=0)):6.1f}"
              f"  median {np.median(values):6.1f}  p99 {np.percentile(values, 99):6.1f}")
    if args.outputs:
        Path(args.outputs).write_bytes(pickle.dumps(outputs))
    if args.compare:
        theirs = pickle.loads(Path(args.compare).read_bytes())
        differ = sum(not steady_chain_ab._same(a, b) for a, b in zip(outputs, theirs))
        print(f"  outputs differing from {args.compare}: {differ} of {len(outputs)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
