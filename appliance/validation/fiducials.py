"""X-ray <-> OTS registration from a fiducial phantom, as a lab does it before a validation session.

1. Pivot calibration of the tracked pointer: the pointer pivots about a divot while the tracker samples
   it; :func:`appliance.registration.pivot_calibration` gives the tip in the pointer's frame.
2. The fiducial phantom (metal beads in divots) is put in the field of view: the beads are detected in
   several biplane pairs (:func:`appliance.xray_calibration.beads.detect_beads`), matched across the two
   views by their pixel distance to each other's epipolar lines (one-to-one, Hungarian), triangulated
   with the appliance's calibration, and averaged over the pairs.
3. Each fiducial is touched with the pointer; its tracker position is the mean pointer tip over a
   number of tracker frames (averaging beats the tracker's 0.19 mm per-frame noise down, as a lab does).
4. The two point sets are put in correspondence by their internal distances - a rigid motion keeps
   them, and a registration phantom's layout is built so that no two fiducials share the same set of
   distances to the others - and registered (:func:`appliance.registration.register_points`).

Reported: pivot RMS, per-fiducial FRE, the FLE estimated from FRE, and Fitzpatrick's expected TRE at
the robots' postures. A correspondence that leaves a large FRE is refused rather than used.
"""
from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from appliance.errors import CalibrationError
from appliance.geometry import (
    Calibration,
    epipolar_distance_px,
    fundamental_matrix,
    reprojection_error_px,
    triangulate,
)
from appliance.registration import (
    PivotCalibration,
    Registration,
    pivot_calibration,
    register_points,
)
from appliance.validation.lab import Lab, PairFeed, ToolFeed
from appliance.xray_calibration.beads import detect_beads

log = logging.getLogger(__name__)

#: A bead seen in both views lies within this many pixels of its partner's epipolar line.
EPIPOLAR_BAND_PX = 3.0
#: A registration whose worst fiducial misses by more than this was built on a wrong correspondence.
MAX_FRE_MM = 2.0


@dataclass(frozen=True)
class FiducialSettings:
    pivot_frames: int = 60
    xray_pairs: int = 5
    frames_per_fiducial: int = 10
    max_bead_radius_px: float = 12.0


@dataclass(frozen=True)
class FiducialRegistration:
    """The X-ray -> OTS registration of a session and how it was obtained."""

    registration: Registration          # X-ray points -> tracker points
    pivot: PivotCalibration
    xray_points_mm: np.ndarray           # (N, 3) triangulated bead centres (X-ray frame), phantom order
    ots_points_mm: np.ndarray            # (N, 3) pointer-measured fiducials (tracker frame)
    bead_reprojection_px: np.ndarray     # (N,) RMS over the views and pairs of the triangulated beads

    def to_dict(self, targets_mm: Any | None = None) -> dict[str, Any]:
        data = self.registration.to_dict(targets_mm)
        data["fre_mm"] = np.round(self.registration.fre_mm, 4).tolist()
        data["pivot"] = {"tip_offset_mm": np.round(self.pivot.tip_offset_mm, 3).tolist(),
                         "rms_mm": round(self.pivot.rms_mm, 4), "poses": len(self.pivot.residual_mm)}
        data["bead_reprojection_px"] = np.round(self.bead_reprojection_px, 3).tolist()
        return data


def match_across_views(calibration: Calibration, uv_p: np.ndarray, uv_q: np.ndarray,
                       band_px: float = EPIPOLAR_BAND_PX) -> list[tuple[int, int]]:
    """One-to-one matches (i in p, j in q) by epipolar distance, each within ``band_px``."""
    if len(uv_p) == 0 or len(uv_q) == 0:
        return []
    F = fundamental_matrix(calibration.p, calibration.q)
    a = calibration.p.undistort_points(uv_p)
    b = calibration.q.undistort_points(uv_q)
    cost = np.array([[float(epipolar_distance_px(F, a[i:i + 1], b[j:j + 1])[0]) for j in range(len(b))]
                     for i in range(len(a))])
    rows, cols = linear_sum_assignment(np.minimum(cost, 1e6))
    return [(int(i), int(j)) for i, j in zip(rows, cols) if cost[i, j] <= band_px]


def triangulated_beads(calibration: Calibration, images: dict[str, np.ndarray], expected: int,
                       max_radius_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Bead centres (expected, 3) triangulated from one pair, and their reprojection error (px)."""
    found = {name: detect_beads(images[name], max_radius_px=max_radius_px, what=f"fiducial phantom, view {name}")
             for name in ("p", "q")}
    matches = match_across_views(calibration, found["p"].uv, found["q"].uv)
    if len(matches) != expected:
        raise CalibrationError(
            f"fiducial phantom: {expected} fiducials expected, but {len(found['p'])} beads were found in view p, "
            f"{len(found['q'])} in view q, and {len(matches)} matched across the views (a bead hidden or overlapping "
            f"another in one view, or the calibration is off by more than {EPIPOLAR_BAND_PX:g} px)")
    uv_p = found["p"].uv[[i for i, _ in matches]]
    uv_q = found["q"].uv[[j for _, j in matches]]
    points = triangulate(calibration.p, calibration.q, uv_p, uv_q)
    return points, reprojection_error_px(calibration.p, calibration.q, points, uv_p, uv_q)


def _order_like(reference: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Indices that put ``points`` in the order of ``reference`` (nearest; the beads did not move between pairs)."""
    distance = np.linalg.norm(reference[:, None, :] - points[None, :, :], axis=2)
    rows, cols = linear_sum_assignment(distance)
    return cols[np.argsort(rows)]


def match_by_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The permutation ``perm`` with ``a[i]`` <-> ``b[perm[i]]``, from each point's sorted distances to the others.

    Rigid motions keep those distances; each point's signature is compared with every other's and the
    one-to-one assignment of smallest total mismatch is taken.
    """
    if len(a) != len(b):
        raise CalibrationError(f"fiducials: {len(a)} seen in X-ray but {len(b)} measured with the tracker")
    sig_a = np.sort(np.linalg.norm(a[:, None] - a[None], axis=2), axis=1)
    sig_b = np.sort(np.linalg.norm(b[:, None] - b[None], axis=2), axis=1)
    cost = np.linalg.norm(sig_a[:, None, :] - sig_b[None, :, :], axis=2)
    rows, cols = linear_sum_assignment(cost)
    return cols[np.argsort(rows)]


def calibrate_pointer(lab: Lab, tools: ToolFeed, handle: int, frames: int) -> PivotCalibration:
    """Pivot calibration of the pointer on ``handle`` from ``frames`` tracker frames."""
    lab.start_pivoting()
    poses = tools.poses(handle, frames, what="pivot calibration")
    return pivot_calibration([p[:3, :3] for p in poses], [p[:3, 3] for p in poses])


def register_with_fiducials(lab: Lab, calibration: Calibration, pairs: PairFeed, tools: ToolFeed, pointer: int,
                            settings: FiducialSettings = FiducialSettings(),
                            progress: Callable[[str], None] = lambda _: None) -> FiducialRegistration:
    """Steps 1-4 of the module docstring, through the lab, the frame stream and the tracker."""
    progress(f"pivot calibration of the pointer ({settings.pivot_frames} tracker frames)")
    pivot = calibrate_pointer(lab, tools, pointer, settings.pivot_frames)
    progress(f"pointer tip at {np.round(pivot.tip_offset_mm, 2).tolist()} mm in its frame, pivot RMS "
             f"{pivot.rms_mm:.3f} mm")

    count = lab.place_fiducials()
    pairs.settle()
    sets, residuals = [], []
    for _ in range(settings.xray_pairs):
        pair = pairs.next()
        points, residual = triangulated_beads(calibration, {"p": pair.p.image, "q": pair.q.image}, count,
                                              settings.max_bead_radius_px)
        if sets:
            same = _order_like(sets[0], points)
            points, residual = points[same], residual[same]
        sets.append(points)
        residuals.append(residual)
    xray = np.mean(sets, axis=0)
    reprojection = np.sqrt(np.mean(np.square(residuals), axis=0))
    progress(f"{count} fiducials triangulated from {settings.xray_pairs} pairs (reprojection RMS "
             f"{float(np.sqrt(np.mean(reprojection ** 2))):.2f} px)")

    measured = []
    for index in range(count):
        lab.touch_fiducial(index)
        poses = tools.poses(pointer, settings.frames_per_fiducial, what=f"fiducial {index + 1}")
        tips = [p[:3, :3] @ pivot.tip_offset_mm + p[:3, 3] for p in poses]
        measured.append(np.mean(tips, axis=0))
    lab.clear_fiducials()
    pairs.settle()
    ots = np.array(measured)
    order = match_by_distances(ots, xray)          # ots[i] is the bead xray[order[i]]
    xray, reprojection = xray[order], reprojection[order]
    registration = register_points(xray, ots)
    if float(registration.fre_mm.max()) > MAX_FRE_MM:
        raise CalibrationError(
            f"fiducial registration: worst FRE {registration.fre_mm.max():.2f} mm (> {MAX_FRE_MM:g} mm): the X-ray "
            f"beads and the touched fiducials were not put in correspondence; is the phantom's layout asymmetric, and "
            f"were the fiducials touched in its numbering?")
    progress(f"registration: FRE RMS {registration.fre_rms_mm:.3f} mm (max {registration.fre_mm.max():.3f}), "
             f"FLE estimate {registration.fle_estimate_mm:.3f} mm")
    return FiducialRegistration(registration, pivot, xray, ots, reprojection)
