"""The axis within an epipolar plane fixed by the robot's known body, where the triangulated tips put its ends too
far apart or too close.

When the 3D axis lies (nearly) in an epipolar plane, both views' axis planes are that plane and fix nothing
within it: the direction there comes from the triangulated tips of the chosen pairing (:mod:`.reconstruction`).
Every ray of either view then lies in the plane, so each view's ends only say where along its epipolar line
the body's ends project; an end that runs on into another structure (a vessel it lies across: standing seed
1234567, robot 6, pose 6, 55 px too long in view p) moves the triangulated end along that view's ray and turns
the axis in the plane (6.5 deg there) with a measured length far from the body's (40 mm against 30).

The known body says more: its apex, tail and moment centroid lie on one line at known offsets (apex ``L - c``,
tail ``c`` from the centroid). For a direction in the plane, the body's centroid that best puts those three
points on each view's rays (its ends measured as the cone's apex and the flat tail, its moment centroid) is a
small linear least-squares; each measurement's misfit is weighed by its noise (the clean sigma and, over
another structure, ``CLUTTER_FRACTION`` of the clutter times the cone's length, the diameter (a flat end) or
the body's length (the moment centroid, which the structure's mass slides along the axis), as in
:mod:`.head_by_body`) and capped, so that one end run on into a vessel cannot pull the fit. :func:`fit_in_plane`
scans the directions in the plane and returns the best; the tracker takes it where it fits well, and otherwise
reports the frame without an axis rather than with a wrong one.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from appliance.geometry import Calibration
from appliance.recognition import body_kernels as bk
from appliance.recognition.body_prior import BodyModel
from appliance.recognition.features import Features2D
from appliance.recognition.head_by_body import CLUTTER_FRACTION

#: The directions tried in the plane: this far (deg) either side of the reconstruction's, in coarse steps, then
#: refined around the best.
SCAN_HALF_RANGE_DEG = 30.0
SCAN_STEP_DEG = 0.5
REFINE_STEP_DEG = 0.05
#: Rounds of refitting without the measurements the last fit put beyond the cap.
TRIM_ROUNDS = 3


@dataclass(frozen=True)
class PlaneFit:
    """The body's best place with its axis in the plane: its direction (tail to head), its moment centroid (mm),
    the capped chi-square there and at the reconstruction's own direction, and the measurements fitted."""

    direction: np.ndarray
    centroid: np.ndarray
    chi2: float
    chi2_at_start: float
    measurements: int


def _measurements(calibration: Calibration, centroid: np.ndarray, feats: dict[str, Features2D],
                  head_index: dict[str, int], clutter: dict[str, float], body: BodyModel
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per measurement (each view's apex, tail and moment centroid): the ray's origin and unit direction, the
    body point's offset along the axis from the moment centroid (mm), the projector across the ray, and the
    weight (1 / sigma^2, sigma in mm at the body)."""
    to_head = body.length_mm - body.centroid_from_tail_mm
    origins, rays, offsets, sigmas = [], [], [], []
    for name, feat in feats.items():
        view = calibration.views[name]
        head = head_index[name]
        sign_head = 1.0 if head == 0 else -1.0
        apex = feat.centroid + sign_head * feat.tip_distance(head, True) * feat.axis
        tail = feat.centroid - sign_head * feat.tip_distance(1 - head, False) * feat.axis
        o, r = view.rays(np.vstack([apex, tail, feat.centroid]))
        mm_per_px = float(np.linalg.norm(view.source_mm - centroid)) / float(view.K[0, 0])
        level = max(clutter.get(name, 0.0), 0.0)
        clean = (bk.APEX_SIGMA_PX * mm_per_px + bk.APEX_SIGMA_PER_CONE_PX * body.cone_length_mm,
                 bk.FLAT_END_SIGMA_PX * mm_per_px, bk.CENTROID_SIGMA_PX * mm_per_px)
        # (over another structure a moment centroid slides along the axis by a fraction of the body's length)
        near = (body.cone_length_mm, body.diameter_mm, body.length_mm)
        origins.append(o)
        rays.append(r)
        offsets.extend((to_head, -body.centroid_from_tail_mm, 0.0))
        sigmas.extend(math.hypot(c, CLUTTER_FRACTION * level * n) for c, n in zip(clean, near))
    o, r = np.vstack(origins), np.vstack(rays)
    across = np.eye(3)[None, :, :] - r[:, :, None] * r[:, None, :]
    return o, r, np.asarray(offsets), across, 1.0 / np.square(sigmas)


def _fit_centroid(direction: np.ndarray, origins: np.ndarray, offsets: np.ndarray, across: np.ndarray,
                  weights: np.ndarray, cap: float) -> tuple[np.ndarray, float]:
    """The moment centroid that best puts the body's points on their rays with this direction, and the capped
    chi-square there: a weighted least-squares, refitted without the measurements beyond ``cap`` sigma."""
    targets = origins - offsets[:, None] * direction[None, :]
    use = np.ones(len(weights), dtype=bool)
    best: tuple[np.ndarray, float] | None = None
    for _ in range(TRIM_ROUNDS + 1):
        w = weights * use
        A = np.einsum("i,ijk->jk", w, across)
        b = np.einsum("i,ijk,ik->j", w, across, targets)
        try:
            centroid = np.linalg.solve(A, b)
        except np.linalg.LinAlgError:
            break
        residual = np.einsum("ijk,ik->ij", across, centroid[None, :] - targets)
        z2 = weights * np.einsum("ij,ij->i", residual, residual)
        chi2 = float(np.minimum(z2, cap * cap).sum())
        if best is None or chi2 < best[1]:
            best = (centroid, chi2)
        keep = z2 <= cap * cap
        if np.array_equal(keep, use) or keep.sum() < 4:
            break
        use = keep
    assert best is not None
    return best


def fit_in_plane(calibration: Calibration, centroid: np.ndarray, direction: np.ndarray, normal: np.ndarray,
                 feats: dict[str, Features2D], head_index: dict[str, int], clutter: dict[str, float],
                 body: BodyModel, cap: float) -> PlaneFit:
    """The body's best place with its axis turned about ``normal`` (the axis planes' normal) from ``direction``
    (tail to head; ``head_index``: each view's 2D end at the head), within ``SCAN_HALF_RANGE_DEG``."""
    o, _, offsets, across, weights = _measurements(calibration, centroid, feats, head_index, clutter, body)
    d0 = direction - float(direction @ normal) * normal
    d0 = d0 / np.linalg.norm(d0)
    side = np.cross(normal, d0)

    def at(angle_deg: float) -> tuple[np.ndarray, np.ndarray, float]:
        a = math.radians(angle_deg)
        d = math.cos(a) * d0 + math.sin(a) * side
        c, chi2 = _fit_centroid(d, o, offsets, across, weights, cap)
        return d, c, chi2

    start = at(0.0)
    coarse = np.arange(-SCAN_HALF_RANGE_DEG, SCAN_HALF_RANGE_DEG + 1e-9, SCAN_STEP_DEG)
    best_angle = min(coarse, key=lambda a: at(float(a))[2])
    fine = best_angle + np.arange(-SCAN_STEP_DEG, SCAN_STEP_DEG + 1e-9, REFINE_STEP_DEG)
    d, c, chi2 = min((at(float(a)) for a in fine), key=lambda r: r[2])
    return PlaneFit(d, c, chi2, start[2], len(weights))
