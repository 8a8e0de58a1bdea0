"""Where the recognition error over the vessel comes from: the accuracy benchmark's frames against the
same poses rendered without the vessel.

For each robot and seed, the frames of ``benchmarks/accuracy.py`` (same poses, same noise, recognised
from scratch by the default pipeline) are recognised again as rendered noise-free and without the
vessel phantom (the body's attenuation lowered by the contrast it displaces where it lies in the
lumen, as the renderer does): that second recognition has everything but the background error and
the noise, so the difference between the two is what the background interpolated under the body
(and the noise) cost. The tables give:

* 3D, per clutter category of the frame (the larger ``Blob.clutter`` of its two views: both <= 0.05,
  <= ``max_clutter``, one view above it, both above it): frames, centroid RMS, its parts along and
  across the true axis, the category's share of the total squared error, and the centroid RMS of
  the same poses rendered without the vessel;
* 2D, per view and clutter category of that view: the image centroid's error along and across the
  true axis against the vessel-free render's (px), the errors along the axis of the head (the cone's
  apex) and the tail (the flat end) against their true projections (RMS and median, px), and the
  blob's weighted centroid along the axis against the vessel-free blob's, as is and with the weights
  kept on the vessel-free blob's support only (the part left is the background error inside the true
  support; the rest is the support's extent);
* the frames with the largest 3D centroid error, with their views' clutter and 2D errors.

Usage: ``python benchmarks/clutter_breakdown.py [--robots 6] [--seeds 1-20] [--poses 30] [--worst 15]``.
It prints tables and asserts nothing; use development seeds, not the standing ones.
"""
from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass, replace
from pathlib import Path
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from accuracy import (  # noqa: E402
    VESSEL_ATTENUATION_PER_MM,
    VESSEL_RADIUS_MM,
    random_poses,
    score,
    true_calibration,
)

from appliance.compiled import warm_up_all  # noqa: E402
from appliance.recognition import Blob, PostureTracker, RecognitionSettings, detect, log_background  # noqa: E402
from appliance.robots import load_robots  # noqa: E402
from drivers.loopback.scene_builders import S_BEND_CENTRELINE_MM, smooth_centreline  # noqa: E402
from drivers.loopback.xray_render import (  # noqa: E402
    BiplaneRenderer,
    ImagingSettings,
    RobotBody,
    VesselPhantom,
    biplane_views,
)

VIEWS = ("p", "q")
CLEAN_CLUTTER = 0.05


@dataclass
class ViewError:
    """One view of one ok frame: its clutter and 2D errors (px) along/across the true image axis."""

    clutter: float
    along: float  # image centroid minus the vessel-free render's
    across: float
    head: float  # recognised minus true apex, along the axis (outward positive)
    tail: float  # recognised minus true flat end, along the axis (outward positive)
    #: The blob's own weighted centroid along the axis against the vessel-free blob's (px), and the same
    #: with the weights kept only where the vessel-free blob has weights: what is left is the background
    #: error inside the body's true support; the rest came from the support's extent (an end run on
    #: into the vessel, or a faint end lost to it).
    moment_along: float = math.nan
    on_true_support: float = math.nan


@dataclass
class FrameError:
    """One ok frame: its 3D centroid error (mm), split along and across the true axis, the same pose's
    error rendered without the vessel, and its views."""

    seed: int
    pose: int
    centroid_mm: float
    along_mm: float
    across_mm: float
    vessel_free_mm: float | None
    views: dict[str, ViewError]
    max_clutter: float

    @property
    def category(self) -> str:
        return _category([v.clutter for v in self.views.values()], self.max_clutter)


def _category(clutters: list[float], max_clutter: float) -> str:
    high = sum(c > max_clutter for c in clutters)
    if high == 2:
        return "both views cluttered"
    if high == 1:
        return "one view cluttered"
    return f"clutter <= {CLEAN_CLUTTER:g}" if max(clutters) <= CLEAN_CLUTTER else f"clutter <= {max_clutter:g}"


def _blob_of(image: np.ndarray, centroid_px: np.ndarray, settings: RecognitionSettings) -> Blob | None:
    """The candidate the recognised image centroid belongs to (the nearest one)."""
    blobs = detect(image, log_background(image, settings.background_scale_px, settings.dark_level), settings)
    if not blobs:
        return None
    return min(blobs, key=lambda b: math.hypot(b.centroid_px[0] - centroid_px[0], b.centroid_px[1] - centroid_px[1]))


def _weighted_centroid(blob: Blob, keep: Blob | None = None) -> np.ndarray:
    """The blob's weighted centroid (image px); with ``keep``, of its weights where ``keep`` has weights."""
    ys, xs = np.nonzero(blob.weights)
    values = blob.weights[ys, xs].astype(np.float64)
    gx, gy = xs + blob.window.x0, ys + blob.window.y0
    if keep is not None:
        kx, ky = gx - keep.window.x0, gy - keep.window.y0
        h, w = keep.weights.shape
        inside = (kx >= 0) & (kx < w) & (ky >= 0) & (ky < h)
        inside[inside] = keep.weights[ky[inside], kx[inside]] != 0
        gx, gy, values = gx[inside], gy[inside], values[inside]
    return np.array([gx @ values, gy @ values]) / values.sum()


def _ends(tips_px: np.ndarray, head_px: np.ndarray, tail_px: np.ndarray, axis: np.ndarray
          ) -> tuple[float, float]:
    """Outward errors along ``axis`` (towards the head) of the recognised ends matched to head and tail."""
    t0, t1 = tips_px
    direct = np.linalg.norm(t0 - head_px) + np.linalg.norm(t1 - tail_px)
    if direct > np.linalg.norm(t1 - head_px) + np.linalg.norm(t0 - tail_px):
        t0, t1 = t1, t0
    return float((t0 - head_px) @ axis), float((tail_px - t1) @ axis)


def run_robot(robot_id: int, seed: int, poses: int, settings: RecognitionSettings) -> list[FrameError]:
    spec = load_robots()[robot_id]
    views = biplane_views()
    calibration = true_calibration(views)
    imaging = ImagingSettings()
    phantom = VesselPhantom(smooth_centreline(S_BEND_CENTRELINE_MM), VESSEL_RADIUS_MM, VESSEL_ATTENUATION_PER_MM)
    body = RobotBody(spec.length_mm, spec.diameter_mm, spec.tip_angle_deg, spec.attenuation_per_mm)
    # As accuracy.run_robot renders them (cold: one render per pose).
    renderer = BiplaneRenderer(views, body, vessel=phantom, settings=imaging, seed=seed + robot_id)
    quiet = replace(imaging, noise=False)
    free = BiplaneRenderer(views, body, vessel=None, settings=quiet)
    displaced = replace(body, attenuation_per_mm=body.attenuation_per_mm - VESSEL_ATTENUATION_PER_MM)
    free_in_lumen = BiplaneRenderer(views, displaced, vessel=None, settings=quiet)
    tracker = PostureTracker(calibration, settings)
    out = []
    for i, pose in enumerate(random_poses(np.random.default_rng([seed, robot_id]), poses)):
        pair = renderer.render(pose)
        in_lumen = phantom.distance_mm(pose.centroid_mm[None, :])[0] <= phantom.radius_mm
        reference = (free_in_lumen if in_lumen else free).render(pose)
        tracker.reset()
        posture = tracker.process(pair.images["p"], pair.images["q"], frame=2 * i)
        tracker.reset()
        clean = tracker.process(reference.images["p"], reference.images["q"], frame=2 * i + 1)
        s = score(posture.to_record(), pose, pair.head_mm, pair.tail_mm)
        if not s["ok"]:
            continue
        error = np.asarray(posture.centroid_mm) - pose.centroid_mm
        along = float(error @ pose.direction)
        s_free = score(clean.to_record(), pose, pair.head_mm, pair.tail_mm)
        frame_views: dict[str, ViewError] = {}
        for name in VIEWS:
            truth = pair.truth[name]
            axis = (truth.head_px - truth.tail_px) / np.linalg.norm(truth.head_px - truth.tail_px)
            seen = posture.views[name]
            blob = _blob_of(pair.images[name], seen.centroid_px, settings)
            clutter = float(blob.clutter) if blob is not None else math.nan
            if clean.ok:
                shift = seen.centroid_px - clean.views[name].centroid_px
                d_along, d_across = float(shift @ axis), float(shift @ np.array([-axis[1], axis[0]]))
            else:
                d_along = d_across = math.nan
            head, tail = _ends(seen.tips_px, truth.head_px, truth.tail_px, axis)
            frame_views[name] = ViewError(clutter, d_along, d_across, head, tail)
            free_blob = _blob_of(reference.images[name], clean.views[name].centroid_px, settings) if clean.ok else None
            if blob is not None and free_blob is not None:
                free_centroid = _weighted_centroid(free_blob)
                frame_views[name].moment_along = float((_weighted_centroid(blob) - free_centroid) @ axis)
                frame_views[name].on_true_support = float((_weighted_centroid(blob, free_blob) - free_centroid) @ axis)
        across = float(np.linalg.norm(error - along * pose.direction))
        out.append(FrameError(seed, i, s["centroid_mm"], along, across, s_free["centroid_mm"], frame_views,
                              settings.max_clutter))
    return out


def _rms(values: list[float]) -> float:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return math.sqrt(sum(v * v for v in finite) / len(finite)) if finite else math.nan


def _median_abs(values: list[float]) -> float:
    finite = [abs(v) for v in values if v is not None and math.isfinite(v)]
    return float(np.median(finite)) if finite else math.nan


def print_tables(frames: list[FrameError], worst: int, max_clutter: float) -> None:
    total = sum(f.centroid_mm ** 2 for f in frames) or 1.0
    order = [f"clutter <= {CLEAN_CLUTTER:g}", f"clutter <= {max_clutter:g}", "one view cluttered",
             "both views cluttered"]
    print(f"3D centroid error by frame category ({len(frames)} ok frames; mm)")
    print(f"{'category':>22} | {'frames':>6} {'RMS':>6} {'along':>6} {'across':>6} {'share':>6} | {'no vessel':>9}")
    for cat in order + ["all"]:
        sel = [f for f in frames if cat in ("all", f.category)]
        if not sel:
            continue
        share = sum(f.centroid_mm ** 2 for f in sel) / total
        print(f"{cat:>22} | {len(sel):6d} {_rms([f.centroid_mm for f in sel]):6.3f} "
              f"{_rms([f.along_mm for f in sel]):6.3f} {_rms([f.across_mm for f in sel]):6.3f} {share:6.2f} | "
              f"{_rms([f.vessel_free_mm for f in sel]):9.3f}")
    views = [v for f in frames for v in f.views.values()]
    print("\n2D errors by view clutter (px): image centroid against the vessel-free render's, ends against the truth")
    print(f"{'view clutter':>22} | {'views':>5} {'along':>6} {'across':>6} | {'head RMS':>8} {'median':>6} | "
          f"{'tail RMS':>8} {'median':>6} | {'moment':>6} {'on true support':>15}")
    for label, low, high in ((f"<= {CLEAN_CLUTTER:g}", -math.inf, CLEAN_CLUTTER),
                             (f"{CLEAN_CLUTTER:g} - {max_clutter:g}", CLEAN_CLUTTER, max_clutter),
                             (f"> {max_clutter:g}", max_clutter, math.inf)):
        sel = [v for v in views if low < v.clutter <= high]
        if not sel:
            continue
        print(f"{label:>22} | {len(sel):5d} {_rms([v.along for v in sel]):6.2f} {_rms([v.across for v in sel]):6.2f} | "
              f"{_rms([v.head for v in sel]):8.2f} {_median_abs([v.head for v in sel]):6.2f} | "
              f"{_rms([v.tail for v in sel]):8.2f} {_median_abs([v.tail for v in sel]):6.2f} | "
              f"{_rms([v.moment_along for v in sel]):6.2f} {_rms([v.on_true_support for v in sel]):15.2f}")
    print(f"\nworst {worst} frames (3D centroid error, mm; per view: clutter, centroid along/across, head, tail px)")
    for f in sorted(frames, key=lambda f: -f.centroid_mm)[:worst]:
        per_view = "  ".join(f"{n}: {v.clutter:.2f} {v.along:+6.2f}/{v.across:+5.2f} {v.head:+6.1f} {v.tail:+5.1f}"
                             for n, v in f.views.items())
        free = f.vessel_free_mm if f.vessel_free_mm is not None else math.nan
        print(f"  seed {f.seed:>3} pose {f.pose:>2}: {f.centroid_mm:.3f} (along {f.along_mm:+.3f}, across "
              f"{f.across_mm:.3f}; no vessel {free:.3f})  {per_view}")


def _seeds(text: str) -> list[int]:
    seeds: list[int] = []
    for part in text.split(","):
        first, _, last = part.partition("-")
        seeds.extend(range(int(first), int(last or first) + 1))
    return seeds


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", default="6", help="comma-separated robot ids (default 6)")
    parser.add_argument("--seeds", default="1-20", help="seeds, e.g. 1-20 or 1,2,5 (default 1-20)")
    parser.add_argument("--poses", type=int, default=30, help="random poses per robot and seed (default 30)")
    parser.add_argument("--worst", type=int, default=15, help="frames listed with the largest error (default 15)")
    args = parser.parse_args(argv)
    warm_up_all()
    imaging = ImagingSettings()
    settings = RecognitionSettings(dark_level=imaging.dark_level)
    for robot_id in (int(r) for r in args.robots.split(",")):
        frames: list[FrameError] = []
        for seed in _seeds(args.seeds):
            frames.extend(run_robot(robot_id, seed, args.poses, settings))
        print(f"robot {robot_id}, seeds {args.seeds}, {args.poses} poses each (the accuracy benchmark's frames, cold)")
        print_tables(frames, args.worst, settings.max_clutter)
        print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
