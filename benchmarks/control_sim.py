"""Closed-loop path following in pure simulation (no devices): world -> pose -> controller -> currents.

Each control period (default 30 Hz) the controller reads the robot's posture (the world's truth,
optionally with Gaussian noise on the centroid and the axis, as a stand-in for recognition), runs
PathFollower -> SafetySupervisor -> CurrentAllocator with the CONFIGURED coils, and the world applies
the currents during the next period (one frame of latency: the image of frame k is processed while
frame k+1 is exposed). The world's coils are the config perturbed as in vessel.yaml (0.5 mm, 1 %)
unless ``--exact-coils``. Cross-track error is measured from the TRUE centroid to the operator path.

    .venv/bin/python benchmarks/control_sim.py            # the standard table
    .venv/bin/python benchmarks/control_sim.py --noise-mm 0 0.1 0.3 --flow 0 5

Prints a table; asserts nothing (speed and accuracy are reported, not tested).
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from appliance.config_io import config_path, read_yaml  # noqa: E402
from appliance.control import (  # noqa: E402
    ActuationModel, CurrentAllocator, FollowerSettings, PathFollower, SafetySupervisor, load_coils, load_path,
)
from drivers.loopback.world import SimWorld  # noqa: E402


@dataclass
class Result:
    label: str
    rms_mm: float
    max_mm: float
    time_to_end_s: float | None
    frames: int
    limited_frames: int
    min_scale: float
    max_current_a: float
    wall_contacts: int
    wall_s: float


def run(noise_mm: float, noise_deg: float, perturbed: bool, flow_mm_s: float, seconds: float, rate_hz: float,
        latency_frames: int, seed: int, settings: FollowerSettings) -> Result:
    coils_data = read_yaml(config_path("coils.yaml"))
    vessel_data = read_yaml(config_path("vessel.yaml"))
    world_section = dict(vessel_data["world"])
    if not perturbed:
        world_section.pop("coil_perturbation", None)
    vessel_section = dict(vessel_data["vessel"], flow_mean_mm_s=flow_mm_s)
    world = SimWorld.from_config(coils_data, vessel_section, robot=None, world=world_section, seed=seed)
    path = load_path()
    follower = PathFollower(path, settings)
    safety = SafetySupervisor()
    allocator = CurrentAllocator(ActuationModel(load_coils()))
    moment = world.robot.moment_am2   # the appliance's estimate from the robot's datasheet values
    rng = np.random.default_rng(seed + 1)
    dt = 1.0 / rate_hz
    pending = [np.zeros(allocator.model.n)] * latency_frames
    currents = np.zeros(allocator.model.n)
    errors: list[float] = []
    limited, min_scale, max_current, end_time = 0, 1.0, 0.0, None
    frames = int(seconds * rate_hz)
    started = time.perf_counter()
    for frame in range(frames):
        truth = world.pose
        seen = truth.centroid_mm + rng.normal(0.0, noise_mm, 3)
        axis = truth.direction + rng.normal(0.0, np.radians(noise_deg), 3)
        axis /= np.linalg.norm(axis)
        errors.append(follower_distance(follower, truth.centroid_mm))
        command = follower.command(seen, axis, truth.t_s)
        decision = safety.update(truth.t_s, True, command.field_T, command.force_N)
        allocation = allocator.allocate(seen, decision.field_T, decision.force_N, moment * command.moment_direction,
                                        currents, dt)
        currents = allocation.currents_a
        if allocation.limited_by:
            limited += 1
        min_scale = min(min_scale, allocation.scale)
        max_current = max(max_current, float(np.max(np.abs(currents))))
        pending.append(currents)
        world.step(dt, pending.pop(0))
        if command.done:
            end_time = truth.t_s
            break
        if frame % int(5 * rate_hz) == 0:
            print(f"  t={truth.t_s:5.1f}s  progress {command.progress:5.1%}  cross-track {errors[-1]:.3f} mm",
                  file=sys.stderr, flush=True)
    e = np.asarray(errors)
    label = (f"noise {noise_mm:.2f} mm/{noise_deg:.1f} deg, {'perturbed' if perturbed else 'exact'} coils, "
             f"flow {flow_mm_s:g} mm/s")
    return Result(label, float(np.sqrt(np.mean(e**2))), float(e.max()), end_time, len(e), limited, min_scale,
                  max_current, world.wall_contacts, time.perf_counter() - started)


def follower_distance(follower: PathFollower, point: np.ndarray) -> float:
    """Distance from a point to the follower's path (full search; independent of the follower's hint)."""
    seg_a = follower.points[:-1]
    seg = np.diff(follower.points, axis=0)
    lengths = np.linalg.norm(seg, axis=1)
    t = np.clip(np.einsum("ij,ij->i", point - seg_a, seg) / lengths**2, 0.0, 1.0)
    return float(np.min(np.linalg.norm(point - (seg_a + t[:, None] * seg), axis=1)))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--noise-mm", type=float, nargs="+", default=[0.0, 0.1], help="centroid noise sd per axis")
    parser.add_argument("--noise-deg", type=float, default=1.0, help="axis noise sd when centroid noise > 0")
    parser.add_argument("--flow", type=float, nargs="+", default=[0.0], help="mean flow speeds (mm/s)")
    parser.add_argument("--exact-coils", action="store_true", help="also run with the world's coils exactly as configured")
    parser.add_argument("--seconds", type=float, default=90.0, help="simulated time limit per run")
    parser.add_argument("--rate-hz", type=float, default=30.0)
    parser.add_argument("--latency-frames", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    settings = FollowerSettings()
    runs = []
    for perturbed in ([False, True] if args.exact_coils else [True]):
        for flow in args.flow:
            for noise in args.noise_mm:
                runs.append((noise, args.noise_deg if noise > 0 else 0.0, perturbed, flow))
    results = []
    for noise, noise_deg, perturbed, flow in runs:
        print(f"running: noise {noise} mm, {'perturbed' if perturbed else 'exact'} coils, flow {flow} mm/s",
              file=sys.stderr)
        results.append(run(noise, noise_deg, perturbed, flow, args.seconds, args.rate_hz, args.latency_frames,
                           args.seed, settings))
    print(f"\nclosed loop at {args.rate_hz:g} Hz, latency {args.latency_frames} frame(s), "
          f"cruise {settings.speed_mm_s:g} mm/s, field {settings.field_t * 1e3:g} mT, seed {args.seed}")
    header = (f"{'scenario':58s} {'RMS mm':>7s} {'max mm':>7s} {'t_end s':>8s} {'frames':>6s} "
              f"{'limited':>7s} {'min scale':>9s} {'max |I| A':>9s} {'wall':>5s} {'x realtime':>10s}")
    print(header)
    print("-" * len(header))
    for r in results:
        t_end = f"{r.time_to_end_s:8.1f}" if r.time_to_end_s is not None else f"{'not end':>8s}"
        sim_s = r.frames / args.rate_hz
        print(f"{r.label:58s} {r.rms_mm:7.3f} {r.max_mm:7.3f} {t_end} {r.frames:6d} {r.limited_frames:7d} "
              f"{r.min_scale:9.3f} {r.max_current_a:9.2f} {r.wall_contacts:5d} {sim_s / r.wall_s:10.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
