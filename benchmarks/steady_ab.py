"""``steady_kernels.search_pair`` against another version of it, in one process, alternating (issue 8).

The other version is a ``steady_kernels.py`` file (``--base``, e.g. a worktree of the round's start), loaded as
its own module on this tree's other kernels (so only that file differs). Both run the calls the tracker makes on
``appliance bench``'s frames (robot 1, 1024^2, recorded in a first pass as ``steady_kernel_profile.py`` records
them), each call after ``np.copyto`` of its pair into the host buffers, A and B alternating per call and their
order swapped every repetition. Thread CPU time per call; prints p50 / p99 over all calls and repetitions and
whether the two outputs are equal. Asserts nothing. The other file must take this tree's arguments
(since 54c38ab the weights' and masks' buffers); against an older chain use ``steady_chain_ab.py``.

    .venv/bin/python benchmarks/steady_ab.py --base /work/wt-base8/appliance/recognition/steady_kernels.py
"""
from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

import numba
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from steady_kernel_profile import _recorded_calls  # noqa: E402

from appliance.commands.bench import RenderedScene  # noqa: E402
from appliance import compiled  # noqa: E402
from appliance.compiled import warm_up_all  # noqa: E402
from appliance.recognition import steady_kernels as sk  # noqa: E402


def _load(path: Path, name: str = "steady_kernels_base"):  # type: ignore[no-untyped-def]
    """The file as module ``name`` whose kernels are compiled here, not cached (its cache entries would clash)."""
    cached = compiled.kernel
    compiled.kernel = lambda function: numba.njit(nogil=True)(function)
    try:
        return _exec(path, name)
    finally:
        compiled.kernel = cached


def _exec(path: Path, name: str):  # type: ignore[no-untyped-def]
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # (numba's cache finds the module by name)
    spec.loader.exec_module(module)
    return module


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--base", type=Path, required=True)
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--reps", type=int, default=10)
    args = parser.parse_args(argv)
    warm_up_all()
    base = _load(args.base)
    scene = RenderedScene(1024, robot_id=1)
    source = scene.pairs()
    frames = [tuple(np.array(image) for image in next(source)) for _ in range(args.frames)]
    calls = _recorded_calls(frames, scene)
    host = (np.empty_like(frames[0][0]), np.empty_like(frames[0][1]))
    kernels = {"base": base.search_pair, "this": sk.search_pair}
    outs = {name: np.empty(sk.OUT_SIZE) for name in kernels}
    for name, kernel in kernels.items():
        kernel(frames[0][0], frames[0][1], *calls[0][1][:-1], outs[name])  # compile
    times = {name: [] for name in kernels}
    differ = 0
    thread = time.thread_time_ns
    for r in range(args.reps):
        order = list(kernels) if r % 2 == 0 else list(kernels)[::-1]
        for n, arguments in calls:
            for name in order:
                np.copyto(host[0], frames[n][0])
                np.copyto(host[1], frames[n][1])
                outs[name][:] = 0.0
                began = thread()
                kernels[name](host[0], host[1], *arguments[:-1], outs[name])
                times[name].append((thread() - began) / 1e3)
            a, b = outs["base"][:sk.OUT_TABLE_WARMED], outs["this"][:sk.OUT_TABLE_WARMED]
            differ += not np.array_equal(a, b, equal_nan=True)
    print(f"search_pair: {len(calls)} calls x {args.reps} reps (robot 1, 1024^2), after the frame copy, thread CPU us")
    for name, values in times.items():
        v = np.asarray(values)
        print(f"  {name:<5} p50 {np.percentile(v, 50):7.1f}  p99 {np.percentile(v, 99):7.1f}  mean {v.mean():7.1f}")
    print(f"  outputs differing (all but the warm sum): {differ} of {len(calls) * args.reps}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
