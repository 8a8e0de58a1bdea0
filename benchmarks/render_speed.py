"""How long the synthetic X-ray renderer takes per view, per stage, at two detector sizes.

Run: ``.venv/bin/python benchmarks/render_speed.py [--frames N] [--robots 1,6]``. Prints a table of
median milliseconds over N frames of random poses within +-30 mm of the isocentre, in a vessel
phantom: wall-clock time, and CPU time of this process (steadier on a shared machine; OpenCV's blur
may use a second thread, which CPU time adds). Nothing is asserted: the figures depend on the
machine and its load, which is printed with them.
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np

from appliance.robots import load_robots
from drivers.loopback.xray_render import (
    BiplaneRenderer,
    ImagingSettings,
    RobotBody,
    RobotPose,
    VesselPhantom,
    biplane_views,
)

SIZES = {"768x672": ((768, 672), (150.0, 130.0)), "1024x1024": ((1024, 1024), (150.0, 150.0))}


def vessel() -> VesselPhantom:
    t = np.linspace(-1.0, 1.0, 40)
    return VesselPhantom(np.stack([60 * t, 20 * np.sin(3 * t), 25 * t * t - 10], axis=1), 2.5, 0.04)


def median_ms(fn, n: int) -> tuple[float, float]:
    """Median wall and CPU milliseconds of ``fn()`` over ``n`` calls."""
    wall, cpu = [], []
    for _ in range(n):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append((time.perf_counter() - w0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
    return statistics.median(wall), statistics.median(cpu)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--robots", default="1,6,7", help="robot ids from config/robots.yaml")
    args = parser.parse_args()
    catalogue = load_robots()
    rng = np.random.default_rng(0)
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs; median ms over "
          f"{args.frames} frames")
    header = (f"{'detector':>10} {'robot':>5} {'setup s':>8} {'pair wall':>9} {'pair cpu':>9} "
              f"{'view cpu':>9} {'trace cpu':>9} {'expose cpu':>10} {'no-noise view':>13}")
    print(header)
    print("-" * len(header))
    for label, (size, fov) in SIZES.items():
        views = biplane_views(image_size=size, fov_mm=fov)
        for rid in (int(r) for r in args.robots.split(",")):
            spec = catalogue[rid]
            body = RobotBody(spec.length_mm, spec.diameter_mm, spec.tip_angle_deg,
                             spec.attenuation_per_mm)
            start = time.perf_counter()
            renderer = BiplaneRenderer(views, body, vessel=vessel(), seed=1)
            setup_s = time.perf_counter() - start
            quiet = BiplaneRenderer(views, body, vessel=vessel(),
                                    settings=ImagingSettings(noise=False))
            poses = [RobotPose(rng.uniform(-30, 30, 3), rng.normal(size=3)) for _ in range(args.frames)]
            it = iter(poses * 4)
            pair_wall, pair_cpu = median_ms(lambda: renderer.render(next(it)), args.frames)
            state = renderer._states["p"]  # stage timings reach into the renderer on purpose
            _, trace_cpu = median_ms(lambda: renderer._robot_in_view(state, next(it)), args.frames)
            _, expose_cpu = median_ms(lambda: renderer._expose(state, None), args.frames)
            _, quiet_cpu = median_ms(lambda: quiet.render(next(it)), args.frames)
            print(f"{label:>10} {rid:>5} {setup_s:>8.2f} {pair_wall:>9.1f} {pair_cpu:>9.1f} "
                  f"{pair_cpu / 2:>9.1f} {trace_cpu:>9.2f} {expose_cpu:>10.2f} {quiet_cpu / 2:>13.2f}")


if __name__ == "__main__":
    main()
