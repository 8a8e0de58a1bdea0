"""2D features of the robot's image by principal component analysis: centroid, axes, eigenvalues, tips.

Two estimators:

* :func:`paper_features` is the seed paper's eq. 2-3 verbatim: the binary pixel cloud's mean, its
  covariance with ``1/(n-1)``, the closed-form eigenvalues and major eigenvector, tips at
  ``c +- 2 sqrt(lambda1) v``. (For a uniform rod the half-length is ``sqrt(3 lambda1)``, so those tips
  overshoot; see architecture.md, known traps.)
* :func:`weighted_features` uses attenuation-weighted moments: with weights proportional to the path
  length through the body, the weighted centroid is the projection of the body's volume centroid (a
  binary silhouette's is not, for a cone-tipped body), and the axis is the symmetry line of the image.
  The weights lose a cone's faint tip (the segmentation keeps contrast above a fifth of the peak); the
  centroid counts it from the end's own profile (:func:`.view_kernels.missing_cone_shift`).
  The tips come from the axial profile (the weights summed across the axis, proportional to the body's
  cross-section area): a flat end is a blurred step, located at its half-height; a conical end's
  profile falls as the square of the distance to the apex, so ``sqrt(profile)`` is a straight line whose
  zero is the apex. The longer ramp of a conical end also identifies the head of a bullet-shaped robot.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from appliance.recognition import view_kernels
from appliance.recognition.segmentation import Blob
from appliance.recognition.settings import RecognitionSettings

#: Profile levels (fractions of the plateau) measured at each end; 0.25 and 0.64 are where
#: sqrt(profile) is 0.5 and 0.8 of the plateau's, the two points of the apex extrapolation.
_LEVELS = (0.2, 0.25, 0.5, 0.64, 0.8)
_LEVELS_ARRAY = np.array(_LEVELS)


@dataclass(frozen=True)
class Features2D:
    """Features of one view's robot image, in observed image pixels.

    ``tips[0]`` is the end along ``+axis``, ``tips[1]`` along ``-axis``. ``reach`` holds, per end, the
    outward distance (px from the centroid along the axis) at which the profile falls to each level of
    ``_LEVELS``; None for the paper's estimator.
    """

    centroid: np.ndarray
    axis: np.ndarray
    eigenvalues: tuple[float, float]
    tips: np.ndarray
    pixel_count: int
    head_index: int | None = None
    ramp_px: tuple[float, float] | None = None
    reach: tuple[dict[float, float], dict[float, float]] | None = None
    #: Standard deviation (radians) of the axis direction expected from the image noise, the mixed
    #: moment's sampling error on the pixel grid (:data:`.view_kernels.MOMENT_BIAS_PX2`) and, over
    #: another structure, the background under the body (:func:`clutter_axis_sigma_rad`); None if unknown.
    axis_sigma_rad: float | None = None

    def tip_distance(self, end: int, conical: bool) -> float:
        """Outward distance (px) of end ``end`` (0: +axis, 1: -axis) from the centroid."""
        if self.reach is None:
            return float(np.dot(self.tips[end] - self.centroid, self.axis) * (1 if end == 0 else -1))
        r = self.reach[end]
        if conical:
            # sqrt(P) = (e_apex - e) / Lc: two levels give Lc and the apex.
            cone = (r[0.25] - r[0.64]) / (0.8 - 0.5)
            return r[0.25] + 0.5 * cone
        return r[0.5]

    def with_head(self, head_index: int | None) -> Features2D:
        """The same features with the tips re-estimated for a known (or unknown) head end."""
        tips = np.array([self.centroid + self.axis * self.tip_distance(0, head_index == 0),
                         self.centroid - self.axis * self.tip_distance(1, head_index == 1)])
        return Features2D(self.centroid, self.axis, self.eigenvalues, tips, self.pixel_count,
                          head_index, self.ramp_px, self.reach, self.axis_sigma_rad)


def _eig2(s11: float, s22: float, s12: float) -> tuple[float, float, np.ndarray]:
    """Eigenvalues (l1 >= l2) and the major unit eigenvector of a 2x2 covariance (paper eq. 3)."""
    root = np.sqrt((s11 - s22) ** 2 + 4.0 * s12 * s12)
    l1, l2 = 0.5 * (s11 + s22 + root), 0.5 * (s11 + s22 - root)
    norm = np.hypot(l1 - s11, s12)
    if norm < 1e-12:  # axis-aligned: the formula's 0/0; the major axis is x when s11 >= s22
        v = np.array([1.0, 0.0]) if s11 >= s22 else np.array([0.0, 1.0])
    else:
        v = np.array([s12, l1 - s11]) / norm
    return float(l1), float(l2), v


def paper_features_from_points(points: np.ndarray) -> Features2D:
    """Eq. 2-3 of the seed paper on a point cloud (N,2) of ``[x, y]`` pixels."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    n = len(pts)
    if n < 2:
        raise ValueError(f"PCA needs at least 2 points, got {n}")
    c = pts.mean(axis=0)
    d = pts - c
    s11, s22, s12 = (float(np.dot(d[:, 0], d[:, 0])) / (n - 1), float(np.dot(d[:, 1], d[:, 1])) / (n - 1),
                     float(np.dot(d[:, 0], d[:, 1])) / (n - 1))
    l1, l2, v = _eig2(s11, s22, s12)
    half = 2.0 * np.sqrt(max(l1, 0.0))
    return Features2D(c, v, (l1, l2), np.array([c + half * v, c - half * v]), n)


def paper_features(blob: Blob) -> Features2D:
    """The paper's estimator on the blob's binary pixel cloud."""
    ys, xs = np.nonzero(blob.mask)
    points = np.column_stack([xs + blob.window.x0, ys + blob.window.y0]).astype(np.float64)
    return paper_features_from_points(points)


def _as_weights(weights: np.ndarray) -> np.ndarray:
    """Weights as the kernels take them: float32 (as :func:`.segment` makes them), C-contiguous."""
    return np.ascontiguousarray(weights, dtype=np.float32)


def weighted_moments(weights: np.ndarray) -> tuple[np.ndarray, float, float, float, float]:
    """Weighted centroid (local px) and central second moments ``s11, s22, s12`` and total weight."""
    m00, m10, m01, mu20, mu02, mu11 = view_kernels.moments(_as_weights(weights))
    if not m00 > 0:
        raise ValueError("weights sum to zero or less")
    return np.array([m10 / m00, m01 / m00]), mu20 / m00, mu02 / m00, mu11 / m00, m00


def axial_profile(weights: np.ndarray, centroid: np.ndarray, axis: np.ndarray) -> tuple[np.ndarray, float]:
    """Weights summed in 1-px bins of the axial coordinate ``s`` (linear interpolation between bins),
    then a [1 2 1]/4 smoothing: symmetric, so it moves no crossing of a symmetric edge.

    Returns the profile and ``s`` of its bin 0; bin ``i`` is at ``s0 + i``.
    """
    return view_kernels.axial_profile_of(_as_weights(weights), float(centroid[0]), float(centroid[1]),
                                         float(axis[0]), float(axis[1]))


def axis_sigma_rad(weights: np.ndarray, centroid: np.ndarray, axis: np.ndarray, spread: float,
                   pixel_sigma: float) -> float:
    """Standard deviation of the principal axis' angle caused by pixel noise ``pixel_sigma``.

    The axis turns by ``mu_st / (l1 - l2)`` for a mixed moment ``mu_st`` in the principal frame, which
    noise of independent pixels makes ``sqrt(sum sigma_i^2 s^2 t^2) / W``. A linear estimate: when it
    comes out large (a nearly round blob: the robot seen end-on) the axis is simply unknown. Quantum
    noise of -log(I) grows as exp(A / 2) behind the body (fewer photons), so each pixel's variance is
    scaled by ``exp(weight)``: a dense robot's own pixels are much noisier than the background
    ``pixel_sigma`` was measured on.
    """
    return float(view_kernels.axis_sigma_of(_as_weights(weights), float(centroid[0]), float(centroid[1]),
                                            float(axis[0]), float(axis[1]), float(spread), float(pixel_sigma)))


def _reach(profile: np.ndarray, s0: float, level: float, direction: int) -> float:
    """Outward distance from s = 0 where the profile last exceeds ``level`` on one side (sub-bin): the
    definition in numpy, which the compiled :func:`.view_kernels.reach_at` computes for every frame."""
    above = np.flatnonzero(profile >= level)
    if direction > 0:
        j = int(above.max())
        if j + 1 >= len(profile):
            return s0 + j
        step = profile[j] - profile[j + 1]
        return s0 + j + ((profile[j] - level) / step if step > 0 else 0.0)
    j = int(above.min())
    if j == 0:
        return -(s0 + j)
    step = profile[j] - profile[j - 1]
    return -(s0 + j - ((profile[j] - level) / step if step > 0 else 0.0))


def clutter_axis_sigma_rad(clutter: float, pixel_count: int, peak: float, strength: float, l1: float,
                           l2: float) -> float:
    """Standard deviation (rad) of the 2D axis from the background interpolated under the body.

    Where the robot overlaps another structure, the background under it is known only to about
    ``clutter x peak`` (:attr:`.Blob.clutter`). An error field of that size that changes sign across
    the axis from one end to the other (the worst case: it follows ``s t``) adds a mixed moment of up
    to ``clutter peak sum|s t|`` over the body's ``N`` pixels, about ``clutter peak N 0.75 sqrt(l1 l2)``,
    and turns the axis by that over ``W (l1 - l2)``. The worst case is taken as three standard
    deviations. It matters for short, stubby bodies: robot 4 (3 x 1.5 mm, elongation ~1.5) over the
    vessel had a 2D axis 3 deg off where the pixel noise explained 0.08 deg, while a long robot over
    the same clutter moves a few tenths of a degree. Zero on a clean background.
    """
    spread = l1 - l2
    if not clutter > 0.0 or not strength > 0.0 or not spread > 0.0:
        return 0.0
    worst = clutter * peak * pixel_count * 0.75 * math.sqrt(max(l1 * l2, 0.0)) / (strength * spread)
    return worst / 3.0


def _reach_scalar(profile: list[float] | np.ndarray, s0: float, level: float, direction: int) -> float:
    """:func:`_reach` as every frame computes it (the compiled kernel); kept under this name for the tests
    that compare the two."""
    return float(view_kernels.reach_at(np.asarray(profile, dtype=np.float64), float(s0), float(level), int(direction)))


def weighted_features(blob: Blob, settings: RecognitionSettings | None = None) -> Features2D:
    """Attenuation-weighted PCA, sub-pixel tips from the axial profile, and the head end if it shows.

    With ``settings.axis_saturation`` < 1 the orientation comes from the weights capped at that
    fraction of the peak: still symmetric about the projected axis, but the silhouette's edges weigh
    as much as its thick middle, which keeps short, cone-heavy bodies (whose mass sits in a round
    lump) from having an ill-defined principal axis. The numbers come from one kernel
    (:func:`.view_kernels.weighted_view_features`); the head is the end whose ramp (profile from 0.8
    down to 0.2 of the plateau) is clearly longer. The centroid includes the cone tip the weights lost
    beyond their end (:func:`.view_kernels.missing_cone_shift`: ~0.2 px along the axis on robot 6), and
    the reaches are measured from it; the moments and the axis are the weights' own. The axis' sigma
    is the kernel's (pixel noise and the mixed moment's sampling error) with the clutter term added.
    """
    settings = settings or RecognitionSettings()
    cap = settings.axis_saturation * blob.peak if settings.axis_saturation < 1.0 else math.inf
    status, out = view_kernels.weighted_view_features(_as_weights(blob.weights), cap, float(blob.sigma),
                                                      _LEVELS_ARRAY)
    if not status:
        raise ValueError("weights sum to zero or less")
    numbers = out.tolist()
    cx, cy, l1, l2, vx, vy, axis_sigma = numbers[:7]
    plus, minus = numbers[7:7 + len(_LEVELS)], numbers[7 + len(_LEVELS):]
    reach = (dict(zip(_LEVELS, plus)), dict(zip(_LEVELS, minus)))
    ramps = (reach[0][0.2] - reach[0][0.8], reach[1][0.2] - reach[1][0.8])
    head: int | None = None
    for end in (0, 1):
        long_, short = ramps[end], ramps[1 - end]
        if long_ >= settings.head_ramp_ratio * max(short, 1e-6) and long_ - short >= settings.head_min_ramp_px:
            head = end
    x0, y0 = cx + blob.window.x0, cy + blob.window.y0
    # The tips as Features2D.with_head places them, in scalars (one dataclass per view and frame).
    d0, d1 = (_tip_distance(plus, head == 0), _tip_distance(minus, head == 1))
    tips = np.array([[x0 + vx * d0, y0 + vy * d0], [x0 - vx * d1, y0 - vy * d1]])
    axis_sigma = math.hypot(axis_sigma, clutter_axis_sigma_rad(blob.clutter, blob.pixel_count, blob.peak,
                                                               blob.strength, l1, l2))
    return Features2D(np.array([x0, y0]), np.array([vx, vy]), (l1, l2), tips, blob.pixel_count, head,
                      ramps, reach, axis_sigma)


def _tip_distance(reach_px: list[float], conical: bool) -> float:
    """:meth:`Features2D.tip_distance` on one end's reaches listed in the order of ``_LEVELS``."""
    if conical:
        cone = (reach_px[1] - reach_px[3]) / (0.8 - 0.5)   # levels 0.25 and 0.64
        return reach_px[1] + 0.5 * cone
    return reach_px[2]                                       # level 0.5


def features(blob: Blob, settings: RecognitionSettings | None = None) -> Features2D:
    """The features of the configured estimator (``settings.estimator``)."""
    settings = settings or RecognitionSettings()
    if settings.estimator == "paper":
        return paper_features(blob)
    return weighted_features(blob, settings)
