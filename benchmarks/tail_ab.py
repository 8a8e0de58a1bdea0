"""In-process A/B of the steady state's not-plain frames (issue 8's p99): the tracker as it is against the same
tracker with :mod:`.head_by_body`'s numpy definitions (``axial_rows_reference``, ``chi2_of_reference``) in place
of the compiled :mod:`.head_kernels`, and :mod:`.axis_by_length`'s (``_fit_centroids_reference``) in place of
:mod:`.axis_kernels`' fits (the rays of its measurements are compiled in both), on ``appliance bench``'s scene.

Renders the bench's frames (its scene, robot and speed) once, then runs two trackers over them, alternating which
goes first per frame, each frame copied into the host's buffers before each call (as the bench does: every call
starts on the caches a new frame leaves), and reads the thread CPU time (``time.thread_time_ns``) around each
``process``. Per path (plain / not plain, by whether the steady call's posture was used) it prints the p50, p99
and max of both and the per-frame median of the difference, and checks the two trackers' postures field by
field (exactly: the compiled and numpy rows may differ in the last bits, the decisions made on them must not).
``--cprofile`` instead profiles the new tracker's not-plain frames and prints the functions by own time.

    .venv/bin/python benchmarks/tail_ab.py [--frames 300] [--robot 1] [--cprofile] [--top 30]
"""
from __future__ import annotations

import argparse
import cProfile
import dataclasses
import io
import pstats
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from appliance.commands.bench import RenderedScene  # noqa: E402
from appliance.compiled import warm_up_all  # noqa: E402
from appliance.recognition import axis_by_length, body_corrections, head_by_body, head_kernels  # noqa: E402
from appliance.recognition.tracker import PostureTracker  # noqa: E402

cpu_ns = time.thread_time_ns
COMPILED = (head_by_body.axial_rows, head_by_body.chi2_of, axis_by_length._fit_centroids)
NUMPY = (head_by_body.axial_rows_reference, head_by_body.chi2_of_reference, axis_by_length._fit_centroids_reference)


def _use(functions: tuple[Any, Any, Any]) -> None:
    """Point the tracker's head-by-body correction at these rows and chi-square, the plane scan at these fits."""
    body_corrections.axial_rows, body_corrections.chi2_of, axis_by_length._fit_centroids = functions


def _plain_flags(tracker: PostureTracker) -> list[bool]:
    """A list that gets, per call of the tracker's steady pair's ``plain_posture``, whether it was plain."""
    flags: list[bool] = []
    pair = tracker._pair
    plain_posture = pair.plain_posture

    def recorded(*args: Any, **kwargs: Any) -> Any:
        posture = plain_posture(*args, **kwargs)
        flags.append(posture is not None)
        return posture

    pair.plain_posture = recorded  # type: ignore[method-assign]
    return flags


def _exact(value: Any) -> Any:
    """``value`` with every float and array to the bit (dataclasses and containers recursively)."""
    if isinstance(value, np.ndarray):
        return (value.shape, value.tobytes())
    if isinstance(value, float):
        return value.hex()
    if dataclasses.is_dataclass(value):
        return tuple((f.name, _exact(getattr(value, f.name))) for f in dataclasses.fields(value))
    if isinstance(value, dict):
        return tuple((k, _exact(v)) for k, v in value.items())
    if isinstance(value, (list, tuple)):
        return tuple(_exact(v) for v in value)
    return repr(value)


def _fields(posture: Any) -> Any:
    """What a posture reports (its timings aside), to the bit."""
    return tuple((f.name, _exact(getattr(posture, f.name))) for f in dataclasses.fields(posture)
                 if f.name != "timings_us")


def _stats(values: list[float]) -> str:
    a = np.asarray(values)
    return f"{np.percentile(a, 50):7.0f} {np.percentile(a, 99):7.0f} {a.max():7.0f}" if len(a) else "-"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--robot", type=int, default=1)
    parser.add_argument("--cprofile", action="store_true")
    parser.add_argument("--top", type=int, default=30)
    args = parser.parse_args()
    warm_up_all()
    compiled_after_warm_up = (len(head_kernels.axial_rows.signatures), len(head_kernels.chi2_of.signatures))
    scene = RenderedScene(1024, args.robot)
    frames = []
    for _, (p, q) in zip(range(args.frames), scene.pairs()):
        frames.append((p.copy(), q.copy()))
    host = (np.empty_like(frames[0][0]), np.empty_like(frames[0][1]))
    body = scene.robot
    trackers = {"numpy": PostureTracker(scene.calibration, body=body),
                "compiled": PostureTracker(scene.calibration, body=body)}
    functions = {"numpy": NUMPY, "compiled": COMPILED}
    flags = {name: _plain_flags(tracker) for name, tracker in trackers.items()}
    cpu: dict[str, dict[int, float]] = {name: {} for name in trackers}
    differ = []
    profile = cProfile.Profile() if args.cprofile else None
    stats = None
    for n, (p, q) in enumerate(frames):
        order = ("numpy", "compiled") if n % 2 == 0 else ("compiled", "numpy")
        postures = {}
        for name in order:
            tracker = trackers[name]
            _use(functions[name])
            np.copyto(host[0], p)
            np.copyto(host[1], q)
            calls = len(flags[name])
            if profile is not None and name == "compiled":
                single = cProfile.Profile()
                single.enable()
            began = cpu_ns()
            postures[name] = tracker.process(host[0], host[1], frame=n, t=n / scene.fps)
            spent = (cpu_ns() - began) / 1e3
            if profile is not None and name == "compiled":
                single.disable()
                if len(flags[name]) > calls and not flags[name][-1]:
                    stats = pstats.Stats(single) if stats is None else stats.add(single)
            if n > 0 and tracker.last_search == "roi" and len(flags[name]) > calls:
                cpu[name][n] = spent if not flags[name][-1] else -spent   # (negative: a plain frame)
        if _fields(postures["numpy"]) != _fields(postures["compiled"]):
            differ.append(n)
            a, b = postures["numpy"], postures["compiled"]
            gaps = {key: float(np.max(np.abs(np.subtract(getattr(a, key), getattr(b, key)))))
                    for key in ("centroid_mm", "direction", "tips_mm", "length_mm")
                    if getattr(a, key) is not None and getattr(b, key) is not None}
            print(f"frame {n}: the postures differ; largest differences {gaps}; ok {a.ok}/{b.ok}, ambiguous "
                  f"{a.ambiguous}/{b.ambiguous}, head {a.head_identified}/{b.head_identified}")
    _use(COMPILED)
    print(f"{len(frames)} frames of appliance bench's scene (robot {args.robot}); postures that differ between "
          f"the two: {len(differ)} {differ[:20]}; head_kernels' signatures after the warm-up "
          f"{compiled_after_warm_up}, at the end "
          f"{(len(head_kernels.axial_rows.signatures), len(head_kernels.chi2_of.signatures))}")
    if stats is not None:
        out = io.StringIO()
        stats.stream = out  # type: ignore[attr-defined]
        stats.sort_stats("tottime").print_stats(args.top)
        print(out.getvalue())
        return 0
    common = sorted(set(cpu["numpy"]) & set(cpu["compiled"]))
    for label, keep in (("plain", lambda v: v < 0), ("not plain", lambda v: v > 0)):
        frames_here = [n for n in common if keep(cpu["compiled"][n]) and keep(cpu["numpy"][n])]
        a = [abs(cpu["numpy"][n]) for n in frames_here]
        b = [abs(cpu["compiled"][n]) for n in frames_here]
        diff = [x - y for x, y in zip(a, b)]
        print(f"{label:>10}: {len(frames_here):3d} frames; thread CPU us p50 p99 max: numpy {_stats(a)}  "
              f"compiled {_stats(b)}; per-frame saving p50 {np.median(diff) if diff else float('nan'):.0f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
