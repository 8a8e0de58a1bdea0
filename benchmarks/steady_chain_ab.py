"""The steady-state call against its kernels at another git revision, in one process, alternating (issue 8).

``steady_ab.py`` swaps ``steady_kernels.py`` alone; a change to the pixel kernels under it (``view_kernels``,
``roi_kernels``) needs the whole chain swapped. Here the three files are read from ``--base`` (a git revision
of this tree) and loaded as their own modules, each bound to the other two of the same revision (compiled
here, not cached), the rest of the tree shared. Both run the calls the tracker makes on ``appliance bench``'s
frames (robot 1, 1024^2, recorded in a first pass with this tree's tracker), each call after ``np.copyto`` of
its pair into the host buffers, A and B alternating per call and their order swapped every repetition.
Thread CPU per call: p50 / p99 over all calls and repetitions, the paired median difference, and whether
the outputs are equal: the output array (all but the log table's warm sum and, where this tree's layout
adds numbers after it, those) and each view's weights and mask, returned (older revisions) or written into
the caller's buffers. Asserts nothing.

    .venv/bin/python benchmarks/steady_chain_ab.py --base 3f0ba5c [--frames 120] [--reps 10]
"""
from __future__ import annotations

import argparse
import inspect
import subprocess
import sys
import time
import types
from pathlib import Path

import numba
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from appliance import compiled  # noqa: E402
from appliance.commands.bench import RenderedScene  # noqa: E402
from appliance.compiled import warm_up_all  # noqa: E402
from appliance.recognition import steady_kernels as sk  # noqa: E402
from steady_kernel_profile import _recorded_calls  # noqa: E402

#: The chain's files, each loaded after those it uses.
CHAIN = ("view_kernels", "roi_kernels", "steady_kernels")


def _load_chain(revision: str) -> types.ModuleType:
    """The chain at ``revision`` as modules bound to each other; returns its steady_kernels."""
    cached = compiled.kernel
    compiled.kernel = lambda function: numba.njit(nogil=True)(function)
    loaded: dict[str, types.ModuleType] = {}
    try:
        for name in CHAIN:
            source = subprocess.run(["git", "-C", str(ROOT), "show", f"{revision}:appliance/recognition/{name}.py"],
                                    check=True, capture_output=True, text=True).stdout
            module = types.ModuleType(f"base_{name}")
            module.__file__ = f"<{revision}:{name}.py>"
            sys.modules[module.__name__] = module
            exec(compile(source, module.__file__, "exec"), module.__dict__)  # noqa: S102 - this tree's history
            for other, bound in loaded.items():  # numba reads the module globals at the first call
                if other in module.__dict__:
                    module.__dict__[other] = bound
            loaded[name] = module
    finally:
        compiled.kernel = cached
    return loaded["steady_kernels"]


class _Side:
    """One revision's search_pair, called with this tree's recorded arguments, its results normalised."""

    def __init__(self, module: types.ModuleType) -> None:
        self.module = module
        self.kernel = module.search_pair
        self.buffered = "weights_buf" in inspect.signature(self.kernel.py_func).parameters
        self.out = np.empty(module.OUT_SIZE)

    def arguments(self, recorded: list) -> list:
        """The recorded arguments (this tree's signature) as this side takes them, its own output last."""
        names = list(inspect.signature(sk.search_pair.py_func).parameters)[2:]
        mine = list(inspect.signature(self.kernel.py_func).parameters)[2:]
        by_name = dict(zip(names, recorded))
        if self.buffered:
            by_name.setdefault("weights_buf", np.zeros((2, sk.WINDOW_CAPACITY), dtype=np.float32))
            by_name.setdefault("masks_buf", np.zeros((2, sk.WINDOW_CAPACITY), dtype=np.uint8))
        by_name["out"] = self.out
        return [by_name[name] for name in mine]

    def timed(self, host: tuple, frame: tuple, arguments: list) -> tuple:
        """The call on ``frame`` after its copy into the ``host`` buffers: (thread CPU us, :meth:`results`)."""
        np.copyto(host[0], frame[0])
        np.copyto(host[1], frame[1])
        self.out[:] = 0.0
        began = time.thread_time_ns()
        returned = self.kernel(host[0], host[1], *arguments)
        elapsed = (time.thread_time_ns() - began) / 1e3
        return elapsed, self.results(returned, arguments)

    def results(self, returned, arguments: list):  # type: ignore[no-untyped-def]
        """(status, output numbers, [weights_p, mask_p, weights_q, mask_q]) of the last call."""
        module = self.module
        if not self.buffered:
            status, *arrays = returned
            return status, self.out[:module.OUT_TABLE_WARMED].copy(), [np.array(a) for a in arrays]
        status = returned
        names = list(inspect.signature(self.kernel.py_func).parameters)[2:]
        w_buf, m_buf = arguments[names.index("weights_buf")], arguments[names.index("masks_buf")]
        arrays = []
        for view in range(2):
            h, w = (int(x) for x in self.out[module.OUT_WINDOW_SHAPES + 2 * view:module.OUT_WINDOW_SHAPES + 2 * view + 2])
            arrays += [w_buf[view, :h * w].reshape(h, w).copy(), m_buf[view, :h * w].reshape(h, w).copy()]
        return status, self.out[:module.OUT_TABLE_WARMED].copy(), arrays


def bench_frames(count: int) -> tuple[RenderedScene, list]:
    """``appliance bench``'s scene (robot 1, 1024^2) and its first ``count`` pairs, rendered."""
    scene = RenderedScene(1024, robot_id=1)
    source = scene.pairs()
    return scene, [tuple(np.array(image) for image in next(source)) for _ in range(count)]


def _same(a, b) -> bool:  # type: ignore[no-untyped-def]
    if a[0] != b[0] or not np.array_equal(a[1], b[1], equal_nan=True):
        return False
    if a[0] != sk.PAIR_FOUND:
        return True  # (the weights of a pair not found are not read)
    return all(x.shape == y.shape and np.array_equal(x, y) for x, y in zip(a[2], b[2]))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--base", required=True, help="git revision of the base chain")
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--reps", type=int, default=10)
    args = parser.parse_args(argv)
    warm_up_all()
    sides = {"base": _Side(_load_chain(args.base)), "this": _Side(sk)}
    scene, frames = bench_frames(args.frames)
    calls = _recorded_calls(frames, scene)
    host = (np.empty_like(frames[0][0]), np.empty_like(frames[0][1]))
    prepared = {name: [side.arguments(arguments) for _, arguments in calls] for name, side in sides.items()}
    for name, side in sides.items():
        side.kernel(frames[0][0], frames[0][1], *prepared[name][0])  # compile
    times = {name: np.zeros((args.reps, len(calls))) for name in sides}
    differ = 0
    for r in range(args.reps):
        order = list(sides) if r % 2 == 0 else list(sides)[::-1]
        for i, (n, _) in enumerate(calls):
            results = {}
            for name in order:
                times[name][r, i], results[name] = sides[name].timed(host, frames[n], prepared[name][i])
            differ += not _same(results["base"], results["this"])
    print(f"search_pair: {len(calls)} calls x {args.reps} reps (robot 1, 1024^2), after the frame copy, thread CPU us;"
          f" base {args.base}")
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
