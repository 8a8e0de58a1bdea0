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
:mod:`.head_by_body`) and capped, so that one end run on into a vessel cannot pull the fit. :class:`PlaneScan`
scans the directions in the plane for the best; the tracker takes it where it fits well, and otherwise
reports the frame without an axis rather than with a wrong one.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from appliance.geometry import Calibration
from appliance.recognition import axis_kernels as ak
from appliance.recognition import body_kernels as bk
from appliance.recognition.body_prior import BodyModel
from appliance.recognition.features import Features2D
from appliance.recognition.head_by_body import VIEW_OFFSETS, CLUTTER_FRACTION

#: The directions tried in the plane: this far (deg) either side of the reconstruction's, in coarse steps, then
#: refined around the best.
SCAN_HALF_RANGE_DEG = 30.0
SCAN_STEP_DEG = 0.5
REFINE_STEP_DEG = 0.05
CURVATURE_STEP_DEG = 1.0
#: Rounds of refitting without the measurements the last fit put beyond the cap.
TRIM_ROUNDS = 3


@dataclass(frozen=True)
class PlaneFit:
    """The body's best place with its axis in the plane: its direction (tail to head), its moment centroid (mm),
    the capped chi-square there and at the reconstruction's own direction, the measurements fitted, and how
    well the fit pins the direction in the plane (deg: where the chi-square rises by one, from its curvature
    over ``CURVATURE_STEP_DEG`` either side)."""

    direction: np.ndarray
    centroid: np.ndarray
    chi2: float
    chi2_at_start: float
    measurements: int
    sigma_deg: float


def _measurements(calibration: Calibration, centroid: np.ndarray, feats: dict[str, Features2D],
                  head_index: dict[str, int], clutter: dict[str, float], body: BodyModel
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per measurement (each view's apex, tail and moment centroid): the ray's origin and unit direction (the
    compiled :func:`.axis_kernels.ray_directions`), the body point's offset along the axis from the moment
    centroid (mm), and the weight (1 / sigma^2, sigma in mm at the body)."""
    to_head = body.length_mm - body.centroid_from_tail_mm
    packed = calibration.packed
    origins = np.empty((3 * len(feats), 3))
    rays = np.empty((3 * len(feats), 3))
    offsets, sigmas = [], []
    for i, (name, feat) in enumerate(feats.items()):
        view = calibration.views[name]
        head = head_index[name]
        sign_head = 1.0 if head == 0 else -1.0
        apex = feat.centroid + sign_head * feat.tip_distance(head, True) * feat.axis
        tail = feat.centroid - sign_head * feat.tip_distance(1 - head, False) * feat.axis
        ak.ray_directions(packed, VIEW_OFFSETS[name], np.vstack([apex, tail, feat.centroid]), rays[3 * i:3 * i + 3])
        origins[3 * i:3 * i + 3] = view.source_mm
        mm_per_px = float(np.linalg.norm(view.source_mm - centroid)) / float(view.K[0, 0])
        level = max(clutter.get(name, 0.0), 0.0)
        clean = (bk.APEX_SIGMA_PX * mm_per_px + bk.APEX_SIGMA_PER_CONE_PX * body.cone_length_mm,
                 bk.FLAT_END_SIGMA_PX * mm_per_px, bk.CENTROID_SIGMA_PX * mm_per_px)
        # (over another structure a moment centroid slides along the axis by a fraction of the body's length)
        near = (body.cone_length_mm, body.diameter_mm, body.length_mm)
        offsets.extend((to_head, -body.centroid_from_tail_mm, 0.0))
        sigmas.extend(math.hypot(c, CLUTTER_FRACTION * level * n) for c, n in zip(clean, near))
    return origins, rays, np.asarray(offsets), 1.0 / np.square(sigmas)


def _fit_centroids(directions: np.ndarray, origins: np.ndarray, rays: np.ndarray, offsets: np.ndarray,
                   weights: np.ndarray, cap: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_fit_centroids_reference` compiled (:func:`.axis_kernels.fit_centroids`)."""
    centroids = np.empty((len(directions), 3))
    chi2 = np.empty(len(directions))
    ak.fit_centroids(np.ascontiguousarray(directions), origins, rays, offsets, weights, float(cap), TRIM_ROUNDS,
                     centroids, chi2)
    return centroids, chi2


def _fit_centroids_reference(directions: np.ndarray, origins: np.ndarray, rays: np.ndarray, offsets: np.ndarray,
                             weights: np.ndarray, cap: float) -> tuple[np.ndarray, np.ndarray]:
    """Per direction (rows of ``directions``), the moment centroid that best puts the body's points on their
    rays, and the capped chi-square there: a weighted least-squares, refitted without the measurements beyond
    ``cap`` sigma (all directions at once; the numpy definition of :func:`_fit_centroids`)."""
    across = np.eye(3)[None, :, :] - rays[:, :, None] * rays[:, None, :]
    targets = origins[None, :, :] - offsets[None, :, None] * directions[:, None, :]
    use = np.ones((len(directions), len(weights)))
    best_chi2 = np.full(len(directions), np.inf)
    best_centroid = np.zeros((len(directions), 3))
    for _ in range(TRIM_ROUNDS + 1):
        w = weights[None, :] * use
        A = np.einsum("nm,mjk->njk", w, across)
        b = np.einsum("nm,mjk,nmk->nj", w, across, targets)
        centroid = np.linalg.solve(A, b[:, :, None])[:, :, 0]
        residual = np.einsum("mjk,nmk->nmj", across, centroid[:, None, :] - targets)
        z2 = weights[None, :] * np.einsum("nmj,nmj->nm", residual, residual)
        chi2 = np.minimum(z2, cap * cap).sum(axis=1)
        better = chi2 < best_chi2
        best_chi2[better] = chi2[better]
        best_centroid[better] = centroid[better]
        keep = (z2 <= cap * cap).astype(float)
        # (at least four points on their rays: a direction's centroid stays fixed)
        keep[keep.sum(axis=1) < 4] = use[keep.sum(axis=1) < 4]
        if np.array_equal(keep, use):
            break
        use = keep
    return best_centroid, best_chi2


class PlaneScan:
    """The body fitted with its axis turned about ``normal`` (the axis planes' normal) from ``direction`` (tail
    to head; ``head_index``: each view's 2D end at the head): :attr:`chi2_at_start` at the measured direction
    (one fit: where it is below the gain a refit must bring, the scan need not run), :meth:`best` within
    ``SCAN_HALF_RANGE_DEG``."""

    def __init__(self, calibration: Calibration, centroid: np.ndarray, direction: np.ndarray, normal: np.ndarray,
                 feats: dict[str, Features2D], head_index: dict[str, int], clutter: dict[str, float],
                 body: BodyModel, cap: float) -> None:
        self._measured = _measurements(calibration, centroid, feats, head_index, clutter, body)
        self._cap = cap
        d0 = direction - float(direction @ normal) * normal
        self._d0 = d0 / np.linalg.norm(d0)
        self._side = np.cross(normal, self._d0)
        self.chi2_at_start = float(self._at(np.zeros(1))[2][0])

    def _at(self, angles_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        a = np.radians(angles_deg)
        d = np.cos(a)[:, None] * self._d0[None, :] + np.sin(a)[:, None] * self._side[None, :]
        c, chi2 = _fit_centroids(d, *self._measured, self._cap)
        return d, c, chi2

    def best(self) -> PlaneFit:
        """The best direction in the plane, by a coarse scan refined around its minimum."""
        coarse = np.arange(-SCAN_HALF_RANGE_DEG, SCAN_HALF_RANGE_DEG + 1e-9, SCAN_STEP_DEG)
        _, _, chi2 = self._at(coarse)
        best = float(coarse[int(np.argmin(chi2))])
        fine = best + np.arange(-SCAN_STEP_DEG, SCAN_STEP_DEG + 1e-9, REFINE_STEP_DEG)
        d, c, chi2 = self._at(fine)
        k = int(np.argmin(chi2))
        angle = float(fine[k])
        _, _, beside = self._at(np.array([angle - CURVATURE_STEP_DEG, angle + CURVATURE_STEP_DEG]))
        rise = float(beside.sum()) - 2.0 * float(chi2[k])
        sigma = CURVATURE_STEP_DEG * math.sqrt(2.0 / rise) if rise > 0 else math.inf
        return PlaneFit(d[k], c[k], float(chi2[k]), self.chi2_at_start, len(self._measured[3]), sigma)
