"""What recording costs the loop: wall time per frame of the session recorder, and bytes per frame.

One "frame" is what the orchestrator writes per step: a posture record, a command, the currents,
an OTS sample and the timings, plus (when kept) both X-ray images. Images are rendered once by the
loopback X-ray renderer at the sim's size (noise included, so compression is realistic) and reused.
Frames are paced at ``--fps`` as in the loop. Cases: the writer in the caller's thread ("direct") or
on its background thread, images never / every 10th pair (sim.yaml) / every pair (bench.yaml), chunk
compression zstd (and none once); fsync at every frame boundary. The time is what the loop spends in
the recorder's calls per frame; "dropped" counts image pairs the background writer had to drop
because it fell behind. Also the reader's speed over the same files.

Prints a table; asserts nothing. Run: ``.venv/bin/python benchmarks/recording_speed.py [--frames N]
[--dir DIR] [--fps HZ]`` (DIR: where the files go, default a temporary folder; use the disk you record on).
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from appliance.recording import Recorder, RecordingReader
from drivers.loopback.xray_render import BiplaneRenderer, ImagingSettings, RobotBody, RobotPose, biplane_views


def _posture(frame: int, t: float) -> dict:
    return {"frame": frame, "t": t, "ok": True, "ambiguous": False, "centroid_mm": [1.23456, -2.3456, 3.4567],
            "direction": [0.297582, 0.502003, 0.812058], "tips_mm": [[5.0552, -0.5414, 10.589], [2.06, -5.58, 2.42]],
            "head_identified": True, "length_mm": 10.012, "reprojection_px": 0.213,
            "views": {v: {"centroid": [312.125, 290.5], "tips": [[300.0, 280.0], [325.0, 301.0]],
                          "axis": [0.76, 0.65], "pixel_count": 1480} for v in ("p", "q")}, "reason": None}


def _run(path: Path, frames: int, images: tuple[np.ndarray, np.ndarray], every: int | None, compression: str,
         threaded: bool, fps: float) -> tuple[list[float], int, int]:
    times = []
    period = 1.0 / fps
    with Recorder.create(path, config={"bench": True}, calibration={"views": {}}, frames_every=every or 1,
                         compression=compression, fsync=True, threaded=threaded) as rec:
        next_frame = time.perf_counter()
        for frame in range(frames):
            # Paced like the loop (the threaded writer uses the time between frames).
            next_frame += period
            time.sleep(max(0.0, next_frame - time.perf_counter()))
            t = frame / fps
            start = time.perf_counter()
            rec.write_posture(t, _posture(frame, t))
            rec.write_command(t, {"frame": frame, "mode": "run", "field_T": [0.0, 0.01, 0.002],
                                  "force_N": [1e-5, 0.0, 0.0], "commanded_a": [1.0] * 8, "scale": 1.0})
            rec.write_currents(t, [0.99] * 8, [1.0] * 8)
            rec.write_ots(t, {"handle": "01", "position_mm": [1.0, 2.0, 3.0], "quaternion": [1.0, 0, 0, 0]})
            if every is not None:
                rec.write_frames(t, frame, *images)
            rec.write_timing(t, frame, {"segmentation": 900.0, "features": 80.0, "control": 50.0})
            times.append(time.perf_counter() - start)
        dropped = rec.images_dropped
    return times, path.stat().st_size, dropped


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--dir", type=Path, default=None)
    parser.add_argument("--fps", type=float, default=30.0)
    args = parser.parse_args()
    views = biplane_views(image_size=(768, 672))
    pair = BiplaneRenderer(views, RobotBody(10.0, 2.0, 20.0, 1.0), settings=ImagingSettings(), seed=1).render(
        RobotPose(np.array([2.0, 1.0, 0.0]), np.array([0.0, 0.6, 0.8])))
    images = (pair.images["p"], pair.images["q"])
    folder = args.dir or Path(tempfile.mkdtemp(prefix="recording_speed_"))
    print(f"{args.frames} frames, images 768x672 uint16 x 2, files in {folder}")
    print(f"{'writer':>8} {'images kept':>12} {'compr.':>6} | {'p50 ms':>7} {'p99 ms':>7} {'max ms':>7} | "
          f"{'dropped':>7} | {'kB/frame':>8} | {'read MB/s':>9}")
    cases = [(threaded, every, "zstd") for threaded in (False, True) for every in (None, 10, 1)]
    cases.append((True, 1, "none"))
    for case, (threaded, every, compression) in enumerate(cases):
        path = folder / f"case{case}.mcap"
        times, size, dropped = _run(path, args.frames, images, every, compression, threaded, args.fps)
        start = time.perf_counter()
        reader = RecordingReader(path)
        pairs = sum(1 for _ in reader.frames())
        count = sum(1 for _ in reader.messages())
        read_s = time.perf_counter() - start
        ms = sorted(t * 1e3 for t in times)
        kept = "never" if every is None else f"1 in {every}"
        print(f"{('thread' if threaded else 'direct'):>8} {kept:>12} {compression:>6} | {statistics.median(ms):7.3f} "
              f"{ms[int(0.99 * (len(ms) - 1))]:7.3f} {ms[-1]:7.3f} | {dropped:7d} | {size / args.frames / 1e3:8.1f} | "
              f"{size / read_s / 1e6:9.1f}   ({pairs} pairs, {count} messages read back)")
        path.unlink()

if __name__ == "__main__":
    main()
