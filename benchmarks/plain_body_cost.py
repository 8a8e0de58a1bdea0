"""Thread CPU of the body prior on the steady state's plain frames (issue 8), and of process() on them.

A tracker given the robot's body places every ok posture by it (:mod:`appliance.recognition.body_prior`),
the plain frames' included. This times one named function (by default the tracker's plain-frame entry,
``place_plain_body``; ``--name place_body`` for a tree before it) on the plain frames only (those whose
posture is still deferred when the function is called; ``--any``: every call; a tree whose plain frames are placed within the pair's
compiled call has no such function, and then only process() is timed), in the regime ``appliance
bench`` uses: 1024x1024 pairs rendered first, untimed; before each pair it arrives in two host buffers by
``np.copyto`` (the caches a new frame leaves). Thread CPU time (``time.thread_time_ns``) minus a clock read
pair; passes alternate timed and untimed, and the untimed ones give process()'s figure for the plain pairs.
Prints min / p50 / p99 (us) and the load; asserts nothing.

    .venv/bin/python benchmarks/plain_body_cost.py [--robot 1] [--pairs 40] [--repeat 10]
        [--owner appliance.recognition.tracker] [--name place_plain_body] [--any]
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from appliance.commands.bench import RenderedScene  # noqa: E402
from appliance.compiled import warm_up_all  # noqa: E402
from appliance.recognition import PostureTracker, RecognitionSettings  # noqa: E402
from appliance.recognition import steady_state  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pairs", type=int, default=40)
    ap.add_argument("--repeat", type=int, default=10)
    ap.add_argument("--robot", type=int, default=1)
    ap.add_argument("--name", default="place_plain_body")
    ap.add_argument("--owner", default="appliance.recognition.tracker")
    ap.add_argument("--any", action="store_true")
    args = ap.parse_args()
    warm_up_all()
    scene = RenderedScene(1024, args.robot)
    pairs = scene.pairs()
    chunk = [tuple(np.array(i) for i in next(pairs)) for _ in range(args.pairs)]
    settings = RecognitionSettings(dark_level=scene.dark_level)
    host = (np.empty_like(chunk[0][0]), np.empty_like(chunk[0][1]))
    clock = time.thread_time_ns
    c0 = min((lambda a, b: b - a)(clock(), clock()) for _ in range(2000))
    owner = importlib.import_module(args.owner)
    real = getattr(owner, args.name, None)
    place: list[float] = []

    def timed(*a, **k):  # type: ignore[no-untyped-def]
        deferred = args.any or "_rest" in a[1].__dict__
        began = clock()
        try:
            return real(*a, **k)
        finally:
            if deferred:
                place.append((clock() - began - c0) / 1e3)

    objects = steady_state.SteadyPair.objects
    called = [False]

    def spy(self):  # type: ignore[no-untyped-def]
        called[0] = True
        return objects(self)

    steady_state.SteadyPair.objects = spy
    totals = []
    for timing in (False, True, False, True) if real is not None else (False, False):
        if real is not None:
            setattr(owner, args.name, timed if timing else real)
        for _ in range(args.repeat):
            tr = PostureTracker(scene.calibration, settings, body=scene.robot)
            for n, (p, q) in enumerate(chunk):
                np.copyto(host[0], p)
                np.copyto(host[1], q)
                called[0] = False
                # A plain frame: objects() not called (known only afterwards: its sample is dropped then).
                before = len(place)
                b = clock()
                tr.process(host[0], host[1], frame=n, t=n / 30.0)
                spent = (clock() - b - c0) / 1e3
                steady = n > 0 and tr.last_search == "roi" and not called[0]
                if not steady:
                    del place[before:]
                elif not timing:
                    totals.append(spent)
    if real is not None:
        setattr(owner, args.name, real)
    a, t = np.asarray(place), np.asarray(totals)
    print(f"robot {args.robot}; load {os.getloadavg()[0]:.2f}; thread CPU us")
    if real is None:
        print(f"no {args.owner}.{args.name}: the body is placed within the pair's compiled call")
    elif not a.size:
        print("no plain frames (none of the steady pairs was built from the call's numbers)")
        return
    else:
        print(f"{args.name} on plain frames: min {a.min():.1f} p50 {np.median(a):.1f} "
              f"p99 {np.percentile(a, 99):.1f} n {a.size}")
    print(f"process() of plain pairs: min {t.min():.1f} p50 {np.median(t):.1f} p99 {np.percentile(t, 99):.1f} n {t.size}")


if __name__ == "__main__":
    main()
