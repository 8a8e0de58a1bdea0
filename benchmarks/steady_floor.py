"""What a steady-state (ROI) frame pair could cost at best, against what it costs (issue 8).

Issue 8 asks for a steady-state recognition of p50 <= 60 us per pair. This measures the floor under any
algorithm that looks at the tracker's regions of interest, on the frames ``appliance bench`` uses and in
its regime (each pair arrives in host buffers by ``np.copyto`` before it is measured, so the caches are
the ones a new frame leaves):

* ``read``: one compiled pass that reads every 16-bit pixel of both views' ROIs (their sum): the memory
  traffic of the ROIs, no arithmetic;
* ``attenuation``: the ROIs turned into attenuation against the coarse background (the kernel the
  recognition runs first): the log of every pixel and the background's interpolation;
* ``attenuation + moments``: the same, then the attenuation-weighted moments of each ROI: the
  smallest complete estimator (a centroid and an axis, no segmentation) any steady state would run;
* ``recognition``: :meth:`PostureTracker.process` on the same pairs (what we ship).

The ROIs are the ones the tracker searched, frame by frame (recorded in a first pass). Prints p50 / p99
(us) per row; asserts nothing.

    .venv/bin/python benchmarks/steady_floor.py [--frames 200] [--size 1024] [--robot 1]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from appliance.commands.bench import RenderedScene
from appliance.compiled import kernel, warm_up_all
from appliance.recognition import (
    PostureTracker,
    RecognitionSettings,
    segmentation,
    view_kernels,
)
from appliance.recognition import tracker as tracker_module


@kernel
def _window_sum(image, y0, y1, x0, x1):  # pragma: no cover - compiled
    """Sum of a window's pixels: reads each once."""
    total = 0
    for y in range(y0, y1):
        row = image[y]
        for x in range(x0, x1):
            total += row[x]
    return total


@kernel
def _attenuation_computed_log(image, y0, y1, x0, x1, coarse, fy, fx, dark):  # pragma: no cover - compiled
    """:func:`view_kernels.attenuation_from_coarse` with the log computed instead of looked up in the
    256 KB table: ``log x = e ln 2 + 2 atanh((m - 1) / (m + 1))`` from the float32's exponent ``e`` and
    mantissa ``m`` (series to z^11: ~1e-7 relative), in branch-free passes the compiler vectorises."""
    hs, ws = coarse.shape
    h, w = y1 - y0, x1 - x0
    values = np.empty(w, dtype=np.float32)
    bits = values.view(np.int32)
    mant = np.empty(w, dtype=np.int32)
    mant_f = mant.view(np.float32)
    expo = np.empty(w, dtype=np.float32)
    out = np.empty((h, w), dtype=np.float32)
    row = np.empty(ws, dtype=np.float32)
    one = np.float32(1.0)
    ln2 = np.float32(0.6931471805599453)
    for y in range(h):
        s = min(max((y + y0 + 0.5) / fy - 0.5, 0.0), hs - 1.0)
        i = min(int(s), max(hs - 2, 0))
        j = min(i + 1, hs - 1)
        wy = np.float32(s - i)
        for c in range(ws):
            row[c] = coarse[i, c] * (one - wy) + coarse[j, c] * wy
        src = image[y + y0, x0:x1]
        for x in range(w):
            values[x] = max(np.float32(src[x]) - dark, one)
        for x in range(w):
            expo[x] = np.float32((bits[x] >> 23) - 127)
            mant[x] = (bits[x] & 0x7FFFFF) | 0x3F800000
        o = out[y]
        for x in range(w):
            m = mant_f[x]
            z = (m - one) / (m + one)
            z2 = z * z
            series = z * (np.float32(2.0) + z2 * (np.float32(2.0 / 3.0) + z2 * (np.float32(0.4) + z2 * (
                np.float32(2.0 / 7.0) + z2 * (np.float32(2.0 / 9.0) + z2 * np.float32(2.0 / 11.0))))))
            o[x] = -(expo[x] * ln2 + series)
        for x in range(w):
            s_ = min(max((x + x0 + 0.5) / fx - 0.5, 0.0), ws - 1.0)
            k = min(int(s_), max(ws - 2, 0))
            f = np.float32(s_ - k)
            o[x] += row[k] * (one - f) + row[min(k + 1, ws - 1)] * f
    return out


def _recorded_rois(scene: RenderedScene, frames: list, settings: RecognitionSettings) -> list:
    """Per frame, the (view index, Roi, LogBackground) the tracker searched (None for a full-frame frame)."""
    searched: list = []
    original = tracker_module.find_in_roi

    def spy(image, log_bg, roi, settings, predicted_px, **kwargs):  # type: ignore[no-untyped-def]
        searched.append((image, roi, log_bg))
        return original(image, log_bg, roi, settings, predicted_px, **kwargs)

    tracker = PostureTracker(scene.calibration, settings)
    # The ROIs as the per-view path searches them (the one call per pair computes the same ROIs inside).
    tracker._pair.usable = lambda *args: False  # type: ignore[method-assign]
    per_frame = []
    tracker_module.find_in_roi = spy
    try:
        for n, (p, q) in enumerate(frames):
            searched.clear()
            tracker.process(p, q, frame=n, t=n / scene.fps)
            rois = [(0 if image is p else 1, roi, log_bg) for image, roi, log_bg in searched if roi is not None]
            per_frame.append(rois if tracker.last_search == "roi" and len(rois) == 2 else None)
    finally:
        tracker_module.find_in_roi = original
    return per_frame


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--robot", type=int, default=1)
    args = parser.parse_args(argv)
    warm_up_all()
    scene = RenderedScene(args.size, robot_id=args.robot)
    settings = RecognitionSettings(dark_level=scene.dark_level)
    source = scene.pairs()
    frames = [tuple(np.array(image) for image in next(source)) for _ in range(args.frames)]
    rois = _recorded_rois(scene, frames, settings)
    host = (np.empty_like(frames[0][0]), np.empty_like(frames[0][1]))
    table = segmentation._log_table(settings.dark_level)
    perf = time.perf_counter_ns
    rows: dict[str, list[float]] = {"read": [], "attenuation": [], "attenuation, computed log": [],
                                    "attenuation + moments": [], "recognition": []}
    dark = np.float32(settings.dark_level)
    _attenuation_computed_log(frames[0][0], 0, 8, 0, 8, np.zeros((2, 2), np.float32), 8.0, 8.0, dark)  # compile
    _window_sum(frames[0][0], 0, 8, 0, 8)
    worst = 0.0
    pixels = []

    def arrive(pair: tuple) -> None:
        np.copyto(host[0], pair[0])
        np.copyto(host[1], pair[1])

    for n, pair in enumerate(frames):
        if rois[n] is None:
            continue
        pixels.append(sum(roi.shape[0] * roi.shape[1] for _, roi, _ in rois[n]))
        arrive(pair)
        began = perf()
        for view, roi, _ in rois[n]:
            _window_sum(host[view], roi.y0, roi.y1, roi.x0, roi.x1)
        rows["read"].append((perf() - began) / 1e3)
        arrive(pair)
        began = perf()
        for view, roi, bg in rois[n]:
            view_kernels.attenuation_from_coarse(host[view], roi.y0, roi.y1, roi.x0, roi.x1, bg.coarse, bg.fy,
                                                 bg.fx, table)
        rows["attenuation"].append((perf() - began) / 1e3)
        arrive(pair)
        began = perf()
        for view, roi, bg in rois[n]:
            _attenuation_computed_log(host[view], roi.y0, roi.y1, roi.x0, roi.x1, bg.coarse, bg.fy, bg.fx, dark)
        rows["attenuation, computed log"].append((perf() - began) / 1e3)
        for view, roi, bg in rois[n]:
            looked_up = view_kernels.attenuation_from_coarse(host[view], roi.y0, roi.y1, roi.x0, roi.x1, bg.coarse,
                                                             bg.fy, bg.fx, table)
            computed = _attenuation_computed_log(host[view], roi.y0, roi.y1, roi.x0, roi.x1, bg.coarse, bg.fy, bg.fx,
                                                 dark)
            worst = max(worst, float(np.abs(computed - looked_up).max()))
        arrive(pair)
        began = perf()
        for view, roi, bg in rois[n]:
            a = view_kernels.attenuation_from_coarse(host[view], roi.y0, roi.y1, roi.x0, roi.x1, bg.coarse, bg.fy,
                                                     bg.fx, table)
            view_kernels.moments(a)
        rows["attenuation + moments"].append((perf() - began) / 1e3)
    tracker = PostureTracker(scene.calibration, settings)
    for n, pair in enumerate(frames):
        arrive(pair)
        began = perf()
        tracker.process(host[0], host[1], frame=n, t=n / scene.fps)
        if n > 0 and tracker.last_search == "roi":
            rows["recognition"].append((perf() - began) / 1e3)
    print(f"steady-state floor: {len(pixels)} tracked pairs of {args.size}x{args.size}, robot {args.robot}, "
          f"ROI pixels per pair p50 {np.median(pixels):.0f}")
    print(f"computed log: largest attenuation difference from the table's {worst:.1e}")
    print(f"{'per pair (us)':<24} {'p50':>8} {'p99':>8}")
    for name, values in rows.items():
        v = np.asarray(values)
        print(f"{name:<24} {np.percentile(v, 50):8.1f} {np.percentile(v, 99):8.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
