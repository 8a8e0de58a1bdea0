"""The lean steady-state pass's cost, in one process, alternating (issue 8).

The calls a tracker with ``RecognitionSettings.lean_steady_state`` on makes on ``appliance bench``'s frames
(robot 1, 1024^2; recorded as ``steady_kernel_profile.py`` records them, with the lean setting), each after
``np.copyto`` of its pair into the host buffers, thread CPU per call, the two sides alternating per call and
their order swapped every repetition:

* without ``--base``: this tree's ``search_pair`` with the lean pass asked for (as recorded) against the same
  kernel with it not asked for (``V_LEAN`` 0 in both views: the tight ROI / ROI search, the default path);
* with ``--base REV``: the chain (``steady_chain_ab.py``'s three files) at ``REV`` against this tree's, both
  with the lean pass asked for; and whether their outputs are equal (``steady_chain_ab.py``'s comparison).

Each side's buffers (``weights_buf``, ``masks_buf`` and, where the side takes it, the lean pass's ``work``)
are one set per side, reused by every call, as :class:`.SteadyPair` reuses them (the recording copies every
array argument per call, which would hand each call fresh, cold buffers; round 13 measured with both).

Prints p50 / p99 of both sides, the paired median difference and how many views the lean pass found.
Asserts nothing.

    .venv/bin/python benchmarks/lean_ab.py [--base REV] [--frames 120] [--reps 10]
"""
from __future__ import annotations

import argparse
import inspect
import functools
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import steady_chain_ab  # noqa: E402
import steady_kernel_profile  # noqa: E402

from appliance.commands.bench import RenderedScene  # noqa: E402
from appliance.compiled import warm_up_all  # noqa: E402
from appliance.recognition import RecognitionSettings  # noqa: E402
from appliance.recognition import steady_kernels as sk  # noqa: E402


def _lean_calls(frames: list, scene: RenderedScene) -> list:
    """The calls of a tracker with the lean pass on (steady_kernel_profile's recording, that setting added)."""
    plain = steady_kernel_profile.RecognitionSettings
    steady_kernel_profile.RecognitionSettings = functools.partial(RecognitionSettings, lean_steady_state=True)
    try:
        return steady_kernel_profile._recorded_calls(frames, scene)
    finally:
        steady_kernel_profile.RecognitionSettings = plain


def _without_lean(arguments: list) -> list:
    """The recorded arguments with the lean pass not asked for in either view."""
    names = list(inspect.signature(sk.search_pair.py_func).parameters)[2:]
    changed = list(arguments)
    k = names.index("inp")
    inp = changed[k].copy()
    inp[sk.IN_VIEW + sk.V_LEAN] = inp[sk.IN_VIEW + sk.IN_VIEW_SIZE + sk.V_LEAN] = 0.0
    changed[k] = inp
    return changed


#: The buffer arguments of ``search_pair`` that a SteadyPair owns and reuses every frame.
SHARED = ("weights_buf", "masks_buf", "work")


def _shared(side: steady_chain_ab._Side, prepared: list) -> list:
    """The prepared argument lists with the buffers replaced by one set for the side."""
    names = list(inspect.signature(side.kernel.py_func).parameters)[2:]
    first = prepared[0]
    buffers = {names.index(n): np.zeros_like(first[names.index(n)]) for n in SHARED if n in names}
    return [[buffers.get(k, a) for k, a in enumerate(arguments)] for arguments in prepared]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--base", help="git revision of the base chain (else: lean off against lean on)")
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--reps", type=int, default=10)
    args = parser.parse_args(argv)
    warm_up_all()
    scene, frames = steady_chain_ab.bench_frames(args.frames)
    calls = _lean_calls(frames, scene)
    this = steady_chain_ab._Side(sk)
    if args.base:
        sides = {"base": steady_chain_ab._Side(steady_chain_ab._load_chain(args.base)), "this": this}
        prepared = {name: [side.arguments(a) for _, a in calls] for name, side in sides.items()}
    else:
        other = steady_chain_ab._Side(sk)
        sides = {"lean off": other, "lean on": this}
        prepared = {"lean off": [other.arguments(_without_lean(a)) for _, a in calls],
                    "lean on": [this.arguments(a) for _, a in calls]}
    prepared = {name: _shared(sides[name], lists) for name, lists in prepared.items()}
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
            if args.base:
                differ += not steady_chain_ab._same(results["base"], results["this"])
            if r == 0 and results[names[1]][0] == sk.PAIR_FOUND:
                out = this.out
                lean_views += int(out[sk.R_FOUND_BY] == sk.FOUND_BY_LEAN) + int(
                    out[sk.OUT_VIEW_SIZE + sk.R_FOUND_BY] == sk.FOUND_BY_LEAN)
    print(f"search_pair, lean pass asked for: {len(calls)} calls x {args.reps} reps (robot 1, 1024^2), after the "
          f"frame copy, thread CPU us; lean views {lean_views} of {2 * len(calls)}")
    for name, values in times.items():
        print(f"  {name:<8} p50 {np.percentile(values, 50):7.1f}  p99 {np.percentile(values, 99):7.1f}"
              f"  per-call min over reps, median {np.median(values.min(axis=0)):7.1f}")
    paired = times[names[1]] - times[names[0]]
    print(f"  paired difference {names[1]} - {names[0]}: median {np.median(paired):+.1f} us"
          f" (IQR {np.percentile(paired, 25):+.1f} .. {np.percentile(paired, 75):+.1f})")
    if args.base:
        print(f"  outputs differing (status, numbers, weights, masks): {differ} of {len(calls) * args.reps}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
