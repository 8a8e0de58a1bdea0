"""The tight ROI's cost against the ROI's (issue 8), in one process: ``RecognitionSettings.tight_roi`` on and off.

Two trackers follow the same frames of ``appliance bench``'s scene (robot 1 unless ``--robot``, 1024^2), each
pair arriving in host buffers by ``np.copyto`` before each tracker's ``process`` (as in the bench), the order of
the two alternating from frame to frame; thread CPU time per pair, over the pairs both trackers searched in
ROIs (from the fourth). Per round: each side's p50 and p99 and the median of the paired differences; then
the medians over rounds and their range. On a shared machine compare the two sides within a round only.
Asserts nothing.

    .venv/bin/python benchmarks/tight_roi_ab.py [--frames 200] [--rounds 6] [--robot 1]

Measured on the roi branch (load ~5 on 2 cores), two runs of 6 rounds of 197 pairs: p50 175 / 189 us on against
186 / 202 off, paired median -19 us (rounds -6 .. -24) / -12 us (-15 .. +2); p99 254-369 against 311-433 in the
first run, 5 of 6 rounds lower on; in the second about even.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from appliance.commands.bench import RenderedScene  # noqa: E402
from appliance.compiled import warm_up_all  # noqa: E402
from appliance.recognition import PostureTracker, RecognitionSettings  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--rounds", type=int, default=6)
    parser.add_argument("--robot", type=int, default=1)
    args = parser.parse_args(argv)
    warm_up_all()
    scene = RenderedScene(1024, robot_id=args.robot)
    source = scene.pairs()
    frames = [tuple(np.array(image) for image in next(source)) for _ in range(args.frames)]
    host = (np.empty_like(frames[0][0]), np.empty_like(frames[0][1]))
    thread = time.thread_time_ns
    rounds: dict[str, list[float]] = {"on": [], "off": [], "on - off": []}
    for r in range(args.rounds):
        trackers = {side: PostureTracker(scene.calibration, RecognitionSettings(
            dark_level=scene.dark_level, tight_roi=side == "on"), body=scene.robot) for side in ("on", "off")}
        times: dict[str, list[float]] = {"on": [], "off": []}
        for i, (p, q) in enumerate(frames):
            took = {}
            for side in (("on", "off") if (i + r) % 2 == 0 else ("off", "on")):
                np.copyto(host[0], p)
                np.copyto(host[1], q)
                began = thread()
                trackers[side].process(host[0], host[1], frame=i, t=i / scene.fps)
                took[side] = (thread() - began) / 1e3
            if i >= 3 and all(tracker.last_search == "roi" for tracker in trackers.values()):
                for side, us in took.items():
                    times[side].append(us)
        on, off = np.array(times["on"]), np.array(times["off"])
        print(f"round {r}: {on.size} pairs; tight ROI on p50 {np.median(on):.0f} p99 {np.percentile(on, 99):.0f}, "
              f"off p50 {np.median(off):.0f} p99 {np.percentile(off, 99):.0f}; paired on - off median "
              f"{np.median(on - off):+.1f} us")
        rounds["on"].append(float(np.median(on)))
        rounds["off"].append(float(np.median(off)))
        rounds["on - off"].append(float(np.median(on - off)))
    for name, values in rounds.items():
        print(f"{name}: median over rounds {np.median(values):.1f} us (range {min(values):.1f} .. {max(values):.1f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
