"""Where the steady-state compiled call's time goes, stage by stage, in the bench's regime (issue 8).

``steady_kernels.search_pair`` (both views' ROI search and the reconstruction's front, one call) is run
on the inputs the tracker gives it on ``appliance bench``'s frames (robot 1, 1024^2: recorded in a first
pass), each call after the pair arrives in host buffers by ``np.copyto`` as in the bench. To time its
stages, prefix copies of ``search_pair``, ``roi_kernels.search_view`` and ``view_kernels.refine`` are
compiled from their source with an early return inserted before a line of text (the ``*_ANCHORS`` below:
if a kernel's text changes, the script stops with the anchor it no longer finds); a stage's cost is the
difference between two prefixes. Thread CPU time, per call the minimum over ``--reps`` repetitions, then
the median over calls. The differences carry the noise of two medians (a few us on a loaded machine) and
a prefix's early return lets the compiler drop what follows it, so read them as a breakdown, not to the
microsecond. ``--warm`` runs each call once untimed first (no copy in between): what the caches a frame's
copy evicts cost is the difference between the two tables. Asserts nothing.

    .venv/bin/python benchmarks/steady_kernel_profile.py [--frames 120] [--reps 5] [--warm]

Measured on the steadyk branch (fe6d2a5), load 3-4, us per pair, cold (after the copy) / warm (the same
call twice): the whole call 302 / 198; dispatch, projection, ROIs 21 / 9; attenuation of both ROIs 67 / 17
(cold, a floor: the log table's and the ROIs' lines, see benchmarks/steady_floor.py); candidates (Gaussian,
labelling, order) 30 / 19; refine 158 / 125 (peak and strong mask 15 / 12, core fill 15 / 10, ring values and
median 20 / 15, side baseline and above-level test 23 / 20, body fill 16 / 11, end stops 9 / 9, support 13 / 11,
near 20 / 13, background fill 13 / 15, weights and the rest 14 / 9); weighted features 18 / 28 (about 10 of it
the exp per weighted pixel in axis_sigma_of); front and finish 7 / 8. A third of a cold pair is what the frame's
copy evicted; warming the log table and the ROIs' pixels alone, or the code with a tiny call, does not bring
it back (only the same call does: its own temporaries and code paths).
"""
from __future__ import annotations

import argparse
import inspect
import sys
import textwrap
import time
from pathlib import Path

import numba
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from appliance.commands.bench import RenderedScene  # noqa: E402
from appliance.compiled import warm_up_all  # noqa: E402
from appliance.recognition import PostureTracker, RecognitionSettings  # noqa: E402
from appliance.recognition import roi_kernels as rk  # noqa: E402
from appliance.recognition import steady_kernels as sk  # noqa: E402
from appliance.recognition import view_kernels as vk  # noqa: E402

#: Stages of refine: (name, the line before which its prefix returns).
REFINE_ANCHORS = [
    ("peak, strong mask", "    seen = np.zeros((bh, bw), dtype=np.uint8)\n"),
    ("core fill, scatter", "    s_min, s_max, t_max = np.inf, -np.inf, 0.0\n"),
    ("window", "    ring_vals, nr = _ring_values("),
    ("ring values", "    baseline = float(median_f32"),
    ("ring median", "    height = peak - baseline\n"),
    ("side baseline, above", "    mask = np.zeros((hh, ww), dtype=np.uint8)\n"),
    ("body fill", "    tolerance = 3.0 * sigma_s * math.sqrt(2.0)\n"),
    ("end stops", "    # The support: a rectangle around the body"),
    ("support", "    # Weigh only near the body"),
    ("near", "    # (Along the structure:)"),
    ("background fill", "    any_near = ky1 >= 0\n"),
    ("weights", "    body = mask[ky0:ky1, kx0:kx1].copy()\n"),
]
SEARCH_ANCHORS = [
    ("attenuation", "    sigma, smooth, labels, stats, order = view_kernels.candidates("),
    ("candidates", "    out[SIGMA] = sigma\n"),
    ("refine loop", "    if borderline:\n"),
]
PAIR_ANCHORS = [("views", "    fp = OUT_VIEW\n"), ("front", "    out[OUT_FRONT_STATUS] = status\n")]


def _prefix(function, name, extra, replacements, anchors, early, scope):  # type: ignore[no-untyped-def]
    """``function``'s source compiled as ``name(*extra, ...)`` with ``early.format(k=k)`` before anchor k."""
    source = textwrap.dedent(inspect.getsource(function.py_func)).replace("@kernel\n", "", 1)
    source = source.replace(f"def {function.py_func.__name__}(", f"def {name}({extra}", 1)
    for old, new in replacements:
        if old not in source:
            raise SystemExit(f"{function.py_func.__name__}: no longer holds {old!r}")
        source = source.replace(old, new)
    for k, (_, anchor) in enumerate(anchors):
        if anchor not in source:
            raise SystemExit(f"{function.py_func.__name__}: no longer holds the anchor {anchor!r}")
        i = source.index(anchor)
        source = source[:i] + early.format(k=k) + source[i:]
    namespace = dict(function.py_func.__globals__)
    namespace.update(scope)
    exec(compile(source, f"<{name}>", "exec"), namespace)  # noqa: S102 - the kernels' own source
    return numba.njit(nogil=True)(namespace[name])


def _prefixes():  # type: ignore[no-untyped-def]
    refine = _prefix(vk.refine, "refine_upto", "rstop, ", [], REFINE_ANCHORS,
                     "    if rstop == {k}:\n        return _not_refined()\n", {})
    search = _prefix(rk.search_view, "search_upto", "svstop, rstop, ",
                     [("view_kernels.refine(a,", "refine_upto(rstop, a,")], SEARCH_ANCHORS,
                     "    if svstop == {k}:\n        return NOT_FOUND, np.zeros((0, 0), dtype=np.float32), "
                     "np.zeros((0, 0), dtype=np.uint8)\n", {"refine_upto": refine})
    return _prefix(sk.search_pair, "pair_upto", "stop, svstop, rstop, ",
                   [("roi_kernels.search_view(", "search_upto(svstop, rstop, "),
                    ("            if status != roi_kernels.FOUND:\n",
                     "            if svstop < 99:\n                continue\n"
                     "            if status != roi_kernels.FOUND:\n"),
                    ("        if not ok:\n", "        if stop < 0:\n            continue\n        if not ok:\n"),
                    # A tight ROI's prefix finds nothing: not the ROI's search after it too (it would count twice).
                    ("        found, via = lean, ", "        tried = False\n        found, via = lean, "),
                    ("                if ok:\n                    status, weights, mask = search_upto(",
                     "                if ok:\n                    tried = True\n"
                     "                    status, weights, mask = search_upto("),
                    ("        if not found:\n            status, weights, mask = search_upto(",
                     "        if not found and not (tried and (svstop < 99 or rstop < 99)):\n"
                     "            status, weights, mask = search_upto(")],
                   PAIR_ANCHORS, "    if stop == {k}:\n        return PAIR_PER_VIEW\n",
                   {"search_upto": search})


def _recorded_calls(frames: list, scene: RenderedScene) -> list:
    """(frame index, search_pair's arguments after the two images) of every call the tracker makes."""
    calls: list = []
    original = sk.search_pair
    current = [0]

    def spy(image_p, image_q, *args):  # type: ignore[no-untyped-def]
        calls.append((current[0], [a.copy() if isinstance(a, np.ndarray) else a for a in args]))
        return original(image_p, image_q, *args)

    tracker = PostureTracker(scene.calibration, RecognitionSettings(dark_level=scene.dark_level))
    sk.search_pair = spy
    try:
        for n, (p, q) in enumerate(frames):
            current[0] = n
            tracker.process(p, q, frame=n, t=n / scene.fps)
    finally:
        sk.search_pair = original
    return calls


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--reps", type=int, default=5)
    parser.add_argument("--warm", action="store_true", help="run each call once untimed first (no copy between)")
    args = parser.parse_args(argv)
    warm_up_all()
    scene = RenderedScene(1024, robot_id=1)
    source = scene.pairs()
    frames = [tuple(np.array(image) for image in next(source)) for _ in range(args.frames)]
    calls = _recorded_calls(frames, scene)
    pair_upto = _prefixes()
    host = (np.empty_like(frames[0][0]), np.empty_like(frames[0][1]))
    out = np.empty(sk.OUT_SIZE)
    # (row, stop, svstop, rstop): the first row stops before any view's search (dispatch, projection, ROIs,
    # and the front and finish on the last output).
    configs = [("dispatch, projection", -1, 0, 0), ("attenuation", 0, 0, 0), ("candidates", 0, 1, 0)]
    configs += [(f"refine: {name}", 0, 2, k) for k, (name, _) in enumerate(REFINE_ANCHORS)]
    configs += [("refine: rest", 0, 2, 99), ("features, axis sigma", 0, 99, 99), ("front", 1, 99, 99),
                ("finish (the whole copy)", 99, 99, 99)]
    for _, stop, svstop, rstop in configs:
        pair_upto(stop, svstop, rstop, frames[0][0], frames[0][1], *calls[0][1][:-1], out)  # compile
    thread = time.thread_time_ns
    times = {name: np.zeros((args.reps, len(calls))) for name, *_ in configs}
    times["search_pair itself"] = np.zeros((args.reps, len(calls)))
    for r in range(args.reps):
        for name, stop, svstop, rstop in [*configs, ("search_pair itself", None, 0, 0)]:
            for i, (n, arguments) in enumerate(calls):
                np.copyto(host[0], frames[n][0])
                np.copyto(host[1], frames[n][1])
                rest = arguments[:-1]
                if stop is None:
                    if args.warm:
                        sk.search_pair(host[0], host[1], *rest, out)
                    began = thread()
                    sk.search_pair(host[0], host[1], *rest, out)
                else:
                    if args.warm:
                        pair_upto(stop, svstop, rstop, host[0], host[1], *rest, out)
                    began = thread()
                    pair_upto(stop, svstop, rstop, host[0], host[1], *rest, out)
                times[name][r, i] = (thread() - began) / 1e3
    print(f"steady_kernels.search_pair: {len(calls)} calls (robot 1, 1024^2), {args.reps} reps, "
          f"{'warm' if args.warm else 'after the frame copy'}; thread CPU us per pair, per call the min over reps")
    print(f"{'prefix up to and with':<34} {'median':>8} {'stage':>8}")
    previous = 0.0
    for name, values in times.items():
        median = float(np.median(values.min(axis=0)))
        print(f"{name:<34} {median:8.1f} {median - previous if name != 'search_pair itself' else float('nan'):8.1f}")
        previous = median
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
