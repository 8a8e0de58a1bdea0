"""Where a steady-state pair's thread CPU goes around its one compiled call (issue 8).

The tracker's steady pair is one compiled call (:func:`.steady_kernels.search_pair`) and some Python around
it: the call's input and dispatch, the posture built from its output, the track remembered. At the issue's
scale (tens of microseconds) cProfile's ~1 us per call is most of what it measures, so this times pieces
with the thread's CPU clock (``time.thread_time_ns``) instead, on the frames and in the regime ``appliance
bench`` uses: 1024x1024 pairs rendered first, untimed; before each measured pair it arrives in two host
buffers by ``np.copyto`` (the caches a new frame leaves).

Each repetition runs the rendered pairs through a fresh tracker given the robot's body, as the bench's
(the body prior places every ok posture; the first pair is its cold start, not measured). Three passes, so no piece's clock reads sit inside another's figure:

* ``pair``: :meth:`PostureTracker.process` alone, one clock read either side;
* ``kernel``: the same with the compiled call also timed: ``python`` is ``pair`` minus ``kernel``, for all
  the steady pairs and split into plain ones (the posture built from the call's numbers) and the others
  (blobs, features and the reconstruction's decisions in Python: :meth:`.SteadyPair.objects` was called);
* pieces: each named method timed on its own pass (its clock reads subtracted, as measured back to back);
  a method the code does not have (the base it is compared with) is left out.

Prints the medians, p99, p10 and minimum (us) per row (under load the low ones say most), the clock's own
cost and the load; asserts nothing.

    .venv/bin/python benchmarks/steady_python.py [--pairs 40] [--repeat 8] [--size 1024] [--robot 1]
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from appliance.commands.bench import RenderedScene
from appliance.compiled import warm_up_all
from appliance.recognition import PostureTracker, RecognitionSettings
from appliance.recognition import steady_kernels, steady_state
from appliance.recognition import tracker as tracker_module

#: The pieces timed in the third pass: (owner, attribute, row name). Any the code does not have is skipped.
PIECES = (
    (tracker_module.PostureTracker, "_search_pair", "_search_pair (input, call, sigmas)"),
    (steady_state.SteadyPair, "search", "  SteadyPair.search"),
    (steady_state.SteadyPair, "plain_posture", "plain_posture (the Posture)"),
    (tracker_module.PostureTracker, "_remember", "_remember (the track)"),
    (tracker_module.PostureTracker, "_remember_plain", "_remember_plain (the track)"),
    (tracker_module, "place_plain_body", "place_plain_body (the body prior)"),
)


def _clock_cost_ns(clock) -> float:
    """The median cost of one pair of back-to-back reads of ``clock`` (subtracted from a timed piece)."""
    samples = []
    for _ in range(2000):
        a = clock()
        b = clock()
        samples.append(b - a)
    return float(np.median(samples))


class _Timed:
    """``owner.name`` replaced by a wrapper that adds its thread CPU time (minus the clock's) to ``samples``."""

    def __init__(self, owner: object, name: str, samples: list[float], clock_ns: float) -> None:
        self.owner, self.name, self.real = owner, name, getattr(owner, name)
        real, clock = self.real, time.thread_time_ns
        current = [0.0]

        def timed(*args, **kwargs):  # type: ignore[no-untyped-def]
            began = clock()
            try:
                return real(*args, **kwargs)
            finally:
                current[0] += clock() - began - clock_ns

        self.current = current
        self.samples = samples
        setattr(owner, name, timed)

    def flush(self) -> None:
        self.samples.append(self.current[0] / 1e3)
        self.current[0] = 0.0

    def restore(self) -> None:
        setattr(self.owner, self.name, self.real)


def _run(chunk, calibration, settings, body, repeat, timed: list[_Timed], host, clock_ns,
         plain: list[bool] | None = None) -> list[float]:
    """``repeat`` passes of ``chunk`` through fresh trackers given the robot's ``body`` (as ``appliance bench``
    builds them: the body prior places every ok posture); per steady ROI pair, process()'s thread CPU (us)
    (and, into ``plain``, whether the pair was plain: :meth:`.SteadyPair.objects` not called)."""
    clock = time.thread_time_ns
    totals = []
    objects = steady_state.SteadyPair.objects
    called = [False]

    def spy(self):  # type: ignore[no-untyped-def]
        called[0] = True
        return objects(self)

    steady_state.SteadyPair.objects = spy
    for _ in range(repeat):
        tracker = PostureTracker(calibration, settings, body=body)
        for n, (p, q) in enumerate(chunk):
            np.copyto(host[0], p)
            np.copyto(host[1], q)
            called[0] = False
            began = clock()
            tracker.process(host[0], host[1], frame=n, t=n / 30.0)
            spent = (clock() - began - clock_ns) / 1e3
            keep = n > 0 and tracker.last_search == "roi"
            for t in timed:
                if keep:
                    t.flush()
                else:
                    t.current[0] = 0.0
            if keep:
                totals.append(spent)
                if plain is not None:
                    plain.append(not called[0])
    steady_state.SteadyPair.objects = objects
    return totals


def _row(name: str, values: list[float]) -> str:
    a = np.asarray(values)
    return (f"{name:<40} {np.median(a):8.1f} {np.percentile(a, 99):8.1f} {np.percentile(a, 10):8.1f} {a.min():8.1f} "
            f"{a.size:6d}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--pairs", type=int, default=40)
    parser.add_argument("--repeat", type=int, default=8)
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--robot", type=int, default=1)
    args = parser.parse_args()
    warm_up_all()
    scene = RenderedScene(args.size, args.robot)
    pairs = scene.pairs()
    chunk = [tuple(np.array(image) for image in next(pairs)) for _ in range(args.pairs)]
    settings = RecognitionSettings(dark_level=scene.dark_level)
    host = (np.empty_like(chunk[0][0]), np.empty_like(chunk[0][1]))
    clock_ns = _clock_cost_ns(time.thread_time_ns)
    _run(chunk[:4], scene.calibration, settings, scene.robot, 1, [], host, clock_ns)  # any signature not yet compiled
    rows = []
    rows.append(("pair: process() (thread CPU)", _run(chunk, scene.calibration, settings, scene.robot, args.repeat,
                                                       [], host, clock_ns)))
    kernel_samples: list[float] = []
    kernel = _Timed(steady_kernels, "search_pair", kernel_samples, clock_ns)
    plain: list[bool] = []
    try:
        totals = _run(chunk, scene.calibration, settings, scene.robot, args.repeat, [kernel], host, clock_ns, plain)
    finally:
        kernel.restore()
    python = [t - k for t, k in zip(totals, kernel_samples)]
    rows.append(("  with the call timed: process()", totals))
    rows.append(("  the compiled call (search_pair)", kernel_samples))
    rows.append(("  python = process() - the call", python))
    rows.append(("    of plain pairs", [v for v, p in zip(python, plain) if p]))
    rows.append(("    of the other pairs", [v for v, p in zip(python, plain) if not p]))
    for owner, name, label in PIECES:
        if not hasattr(owner, name):
            continue
        samples: list[float] = []
        piece = _Timed(owner, name, samples, clock_ns)
        try:
            _run(chunk, scene.calibration, settings, scene.robot, args.repeat, [piece], host, clock_ns)
        finally:
            piece.restore()
        rows.append((label, samples))
    print(f"steady pairs of {args.size}x{args.size}, robot {args.robot}, {args.pairs} pairs x {args.repeat}; "
          f"thread CPU, us; a clock read pair costs {clock_ns / 1e3:.2f} us (subtracted); "
          f"load {os.getloadavg()[0]:.2f}")
    print(f"{'':<40} {'p50':>8} {'p99':>8} {'p10':>8} {'min':>8} {'n':>6}")
    for name, values in rows:
        if values and max(values) > 0.0:  # a method the steady path does not call is left out
            print(_row(name, values))


if __name__ == "__main__":
    main()
