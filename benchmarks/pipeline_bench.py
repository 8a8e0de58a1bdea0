"""Real-time performance of the frame step (issue 8): the same table as ``appliance bench``.

Per stage p50/p99 (us) for steady-state ROI tracking and cold full-frame detection, the plain OpenCV
baseline and the memory floor with their ratios, the in-process loop (frame available -> amplifier
command written) and the closed loop in simulation. Asserts nothing; the figures depend on the machine
and its load, which the table's first line states.

    .venv/bin/python benchmarks/pipeline_bench.py [--json FILE] [--frames N] [--size 1024] [--sim-seconds S]
                                                  [--profile [N]]
    .venv/bin/python benchmarks/pipeline_bench.py --numba [--size 1024]
    .venv/bin/python benchmarks/pipeline_bench.py --profile-recognition roi|full [--frames N] [--size 1024]

``--profile [N]`` (the bench's own) adds the top functions of N more steady-state steps (recognition,
control, allocation, command) to the table. ``--profile-recognition`` runs only the steady-state
(``roi``) or cold (``full``) recognition under cProfile and prints where its time goes: per recognition
function, the share of the total and the time per frame pair.

``--numba`` measures instead what a compiled kernel would give: the per-pixel work of one view's ROI step (attenuation
from the raw 16-bit ROI through a log table, the core threshold, weighted moments, principal axis and
axial profile) as one numba kernel, against the same arithmetic in numpy and against our
``segment`` + ``features`` on the same region of interest of a rendered frame.

The measuring code lives in ``appliance/benchmarking.py`` (and the scene in ``appliance/commands/bench.py``)
so that the installed CLI has it; this script is the same command for those who run benchmarks/.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from appliance.commands import bench  # noqa: E402


def _roi_kernel_numpy(raw: np.ndarray, bg: np.ndarray, lut: np.ndarray, fraction: float) -> tuple[Any, ...]:
    """The reference arithmetic of the kernel, in numpy (what our stages do, minus their refinements)."""
    a = bg - lut[raw]
    ys, xs = np.nonzero(a > fraction * a.max())
    w = a[ys, xs].astype(np.float64)
    m00 = w.sum()
    cx, cy = (w * xs).sum() / m00, (w * ys).sum() / m00
    dx, dy = xs - cx, ys - cy
    cov = np.array([[(w * dx * dx).sum(), (w * dx * dy).sum()], [(w * dx * dy).sum(), (w * dy * dy).sum()]]) / m00
    ev, vec = np.linalg.eigh(cov)
    v = vec[:, 1]
    s = dx * v[0] + dy * v[1]
    u = s - np.floor(s.min())
    i = u.astype(np.int64)
    f = u - i
    n = int(i.max()) + 3
    return cx, cy, ev[1], v, np.bincount(i, w * (1 - f), n) + np.bincount(i + 1, w * f, n)


def _compile_roi_kernel() -> Callable[..., tuple[Any, ...]]:
    import numba

    @numba.njit(cache=False)
    def roi_kernel(raw, bg, lut, fraction):  # type: ignore[no-untyped-def]
        ny, nx = raw.shape
        a = np.empty((ny, nx), np.float32)
        peak = -1e30
        for y in range(ny):
            for x in range(nx):
                v = bg[y, x] - lut[raw[y, x]]
                a[y, x] = v
                peak = max(peak, v)
        threshold = fraction * peak
        m00 = m10 = m01 = 0.0
        for y in range(ny):
            for x in range(nx):
                w = a[y, x]
                if w > threshold:
                    m00 += w
                    m10 += w * x
                    m01 += w * y
        cx, cy = m10 / m00, m01 / m00
        s20 = s02 = s11 = 0.0
        for y in range(ny):
            for x in range(nx):
                w = a[y, x]
                if w > threshold:
                    s20 += w * (x - cx) * (x - cx)
                    s02 += w * (y - cy) * (y - cy)
                    s11 += w * (x - cx) * (y - cy)
        s20, s02, s11 = s20 / m00, s02 / m00, s11 / m00
        l1 = 0.5 * (s20 + s02 + np.sqrt((s20 - s02) ** 2 + 4.0 * s11 * s11))
        vx, vy = s11, l1 - s20
        norm = np.sqrt(vx * vx + vy * vy)
        if norm < 1e-12:
            vx, vy, norm = (1.0, 0.0, 1.0) if s20 >= s02 else (0.0, 1.0, 1.0)
        vx, vy = vx / norm, vy / norm
        offset = nx + ny + 2
        profile = np.zeros(2 * offset + 2)
        for y in range(ny):
            for x in range(nx):
                w = a[y, x]
                if w > threshold:
                    s = (x - cx) * vx + (y - cy) * vy + offset
                    i = int(s)
                    f = s - i
                    profile[i] += w * (1.0 - f)
                    profile[i + 1] += w * f
        return cx, cy, l1, (vx, vy), profile

    return roi_kernel  # type: ignore[no-any-return]


def _percentiles_us(fn: Callable[[], Any], n: int) -> tuple[float, float]:
    times = np.empty(n)
    for k in range(n):
        began = time.perf_counter_ns()
        fn()
        times[k] = (time.perf_counter_ns() - began) / 1e3
    p50, p99 = np.percentile(times, [50, 99])
    return float(p50), float(p99)


def numba_option(size: int, repeats: int = 2000) -> int:
    """Time one view's ROI step: our stages, the same arithmetic in numpy, and a compiled (numba) kernel."""
    try:
        kernel = _compile_roi_kernel()
    except ImportError:
        print("numba is not installed: .venv/bin/python -m pip install numba (not a project dependency)")
        return 1
    from appliance.recognition import PostureTracker, RecognitionSettings, features, segment

    scene = bench.RenderedScene(size)
    settings = RecognitionSettings(dark_level=scene.dark_level)
    tracker = PostureTracker(scene.calibration, settings)
    pairs = scene.pairs()
    for n in range(3):
        image_p, image_q = next(pairs)
        tracker.process(image_p, image_q, frame=n, t=n / scene.fps)
    # View p's ROI as the tracker searches it (around the last posture), on the last frame.
    roi = _roi_of(tracker, image_p)
    blob = segment(image_p, tracker._log_bg["p"], roi, settings)[0]
    raw = np.ascontiguousarray(image_p[roi.slices])
    bg = np.ascontiguousarray(np.asarray(tracker._log_bg["p"][roi.slices], dtype=np.float32))
    lut = np.log(np.maximum(np.arange(65536, dtype=np.float32) - np.float32(scene.dark_level), 1.0)).astype(np.float32)
    kernel(raw, bg, lut, settings.core_fraction)  # compile
    ours = _percentiles_us(lambda: features(segment(image_p, tracker._log_bg["p"], roi, settings)[0], settings), repeats)
    plain = _percentiles_us(lambda: _roi_kernel_numpy(raw, bg, lut, settings.core_fraction), repeats)
    compiled = _percentiles_us(lambda: kernel(raw, bg, lut, settings.core_fraction), repeats)
    k_cx, k_cy = kernel(raw, bg, lut, settings.core_fraction)[:2]
    print(f"one view's ROI step, {raw.shape[1]}x{raw.shape[0]} px ROI of a {size}x{size} frame, {repeats} repeats "
          f"(blob {blob.pixel_count} px)")
    print(f"{'implementation':<38} {'p50 us':>8} {'p99 us':>8}")
    print(f"{'ours: segment + features':<38} {ours[0]:8.1f} {ours[1]:8.1f}")
    print(f"{'same arithmetic as the kernel, numpy':<38} {plain[0]:8.1f} {plain[1]:8.1f}")
    print(f"{'numba kernel (attenuation..profile)':<38} {compiled[0]:8.1f} {compiled[1]:8.1f}")
    print(f"(kernel centroid {roi.x0 + k_cx:.2f}, {roi.y0 + k_cy:.2f} px; ours {blob.centroid_px[0]:.2f}, "
          f"{blob.centroid_px[1]:.2f} px: the kernel leaves out the ring baseline, the capsule and the fill)")
    return 0


def _roi_of(tracker: Any, image: np.ndarray) -> Any:
    from appliance.recognition import Roi

    track = tracker._track
    centre = track.centroid
    half = 0.5 * (track.length_mm or 0.0) + 1.0
    direction = track.direction if track.direction is not None else np.zeros(3)
    points = np.array([centre, centre + half * direction, centre - half * direction])
    return Roi.around(tracker.calibration.p.project(points), tracker.settings.roi_margin_px, image.shape)


def profile(mode: str, frames: int, size: int, top: int = 25) -> int:
    """cProfile of ``frames`` pairs of ROI tracking or cold detection; the table lists cumulative time per
    function of the recognition (and the library calls that cost most of their own time)."""
    import cProfile
    import pstats

    from appliance.recognition import PostureTracker, RecognitionSettings

    scene = bench.RenderedScene(size)
    tracker = PostureTracker(scene.calibration, RecognitionSettings(dark_level=scene.dark_level))
    pairs = scene.pairs()
    profiler = cProfile.Profile()
    for n in range(frames + 1):
        image_p, image_q = next(pairs)
        if mode == "full":
            tracker.reset()
        if n == 0:  # the first frame starts the track (and warms the caches)
            tracker.process(image_p, image_q, frame=n, t=0.0)
            continue
        profiler.enable()
        tracker.process(image_p, image_q, frame=n, t=n / scene.fps)
        profiler.disable()
    stats = pstats.Stats(profiler)
    raw = stats.stats  # type: ignore[attr-defined]
    total = sum(tt for (_, _, _), (_, _, tt, _, _) in raw.items())
    rows = []
    for (path, line, name), (_, calls, tottime, cumtime, _) in raw.items():
        own = "appliance/" in path
        if own or tottime / max(total, 1e-12) > 0.02:
            where = path.split("appliance/")[-1] if own else Path(path).name
            rows.append((cumtime if own else tottime, own, f"{where}:{line}({name})", calls))
    rows.sort(reverse=True)
    print(f"cProfile, {mode}: {frames} pairs of {size}x{size}; total {1e3 * total / frames:.2f} ms per pair "
          f"(profiled: slower than the bench)")
    print(f"{'function':<64} {'calls/pair':>10} {'ms/pair':>8} {'share':>6}")
    for seconds, own, label, calls in rows[:top]:
        kind = "" if own else " (own time)"
        print(f"{(label + kind)[:64]:<64} {calls / frames:10.1f} {1e3 * seconds / frames:8.3f} {seconds / total:6.1%}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    bench.add_arguments(parser)
    parser.add_argument("--numba", action="store_true", help="measure the compiled-kernel option instead (see above)")
    parser.add_argument("--profile-recognition", choices=("roi", "full"),
                        help="profile the recognition alone instead (see above)")
    args = parser.parse_args(argv)
    if args.numba:
        return numba_option(args.size)
    if args.profile_recognition:
        return profile(args.profile_recognition, min(args.frames, 100), args.size)
    return bench.run(args)


if __name__ == "__main__":
    raise SystemExit(main())
