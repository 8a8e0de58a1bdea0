"""Where a cold (full-frame, no history) frame pair's time goes, stage by stage (issue 8).

Issue 8 asks for a cold detection of a 1024x1024 pair in at most 4x the memory floor (``np.copyto`` of
both frames). On the frames ``appliance bench`` uses and in its regime (each pair arrives in host
buffers by ``np.copyto`` before it is measured), this runs the full-frame detection's stages one by one,
as :meth:`PostureTracker._search_full` calls them, and times each in thread CPU (what the stage costs
when other processes share the cores):

* per view: ``log_background`` (the block mean, OpenCV's closing and blur on the coarse grid, back onto
  the detection grid), ``coarse_windows`` (the coarse search, one kernel), ``window_attenuation``
  (each window's attenuation and noise, one kernel) and ``segment`` on the windows;
* ``whole cold pair``: :meth:`PostureTracker.process` after a ``reset`` (after another arrival), and
  ``rest``: its p50 less the p50 of the detection stages above together (pairing, features,
  reconstruction, plausibility; the two are separate runs, so only their medians are compared);
* ``floor``: the arrival itself, ``np.copyto`` of both frames.

Prints min and p50 (us) per row over ``--frames`` pairs times ``--repeat``; asserts nothing.

    .venv/bin/python benchmarks/cold_profile.py [--frames 40] [--repeat 3] [--size 1024] [--robot 1]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from appliance.commands.bench import RenderedScene
from appliance.compiled import warm_up_all
from appliance.recognition import PostureTracker, RecognitionSettings, background_kernels, segmentation
from appliance.recognition.background import log_background
from appliance.recognition.detection import coarse_windows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--robot", type=int, default=1)
    args = parser.parse_args(argv)
    warm_up_all()
    scene = RenderedScene(args.size, robot_id=args.robot)
    settings = RecognitionSettings(dark_level=scene.dark_level)
    source = scene.pairs()
    frames = [tuple(np.array(image) for image in next(source)) for _ in range(args.frames)]
    host = (np.empty_like(frames[0][0]), np.empty_like(frames[0][1]))
    table = segmentation._log_table(settings.dark_level)
    tracker = PostureTracker(scene.calibration, settings)
    tracker.process(*frames[0])   # any signature the warm-ups missed
    cpu = time.thread_time_ns
    rows: dict[str, list[float]] = {}

    def add(name: str, ns: int) -> None:
        rows.setdefault(name, []).append(ns / 1e3)

    def arrive(pair: tuple) -> int:
        began = cpu()
        np.copyto(host[0], pair[0])
        np.copyto(host[1], pair[1])
        return cpu() - began

    windows = []
    for _ in range(args.repeat):
        for pair in frames:
            add("floor (copyto, pair)", arrive(pair))
            detection = 0
            for name, image in zip(("p", "q"), host):
                t0 = cpu()
                background = log_background(image, settings.background_scale_px, settings.dark_level)
                t1 = cpu()
                rois = coarse_windows(background, settings)
                t2 = cpu()
                measured = [background_kernels.window_attenuation(image, roi.y0, roi.y1, roi.x0, roi.x1,
                                                                  background.coarse, background.fy, background.fx,
                                                                  table) for roi in rois]
                t3 = cpu()
                for roi, (a, sigma) in zip(rois, measured):
                    segmentation.segment(image, background, roi, settings, sigma=sigma if sigma > 0 else None,
                                         region_attenuation=a)
                t4 = cpu()
                add(f"{name}: log_background", t1 - t0)
                add(f"{name}: coarse_windows", t2 - t1)
                add(f"{name}: window_attenuation", t3 - t2)
                add(f"{name}: segment", t4 - t3)
                detection += t4 - t0
                windows.extend(roi.shape[0] * roi.shape[1] for roi in rois)
            arrive(pair)
            tracker.reset()
            began = cpu()
            tracker.process(*host)
            whole = cpu() - began
            add("whole cold pair", whole)
            add("detection (both views)", detection)
    per_view = len(windows) / (2 * len(rows["whole cold pair"]))
    print(f"cold pair profile: {args.frames} pairs x {args.repeat} of {args.size}x{args.size}, robot {args.robot}, "
          f"detection windows {np.mean(windows):.0f} px on average ({per_view:.2f} per view); thread CPU")
    print(f"{'stage (us)':<32} {'min':>8} {'p50':>8}")
    for name, values in rows.items():
        print(f"{name:<32} {min(values):8.1f} {float(np.median(values)):8.1f}")
    rest = float(np.median(rows["whole cold pair"]) - np.median(rows["detection (both views)"]))
    print(f"{'rest (p50 difference)':<32} {'':>8} {rest:8.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
