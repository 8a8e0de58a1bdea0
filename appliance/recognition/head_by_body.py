"""The head told by the robot's known body: which end, measured as the cone's apex, puts the body where the rest
of the evidence does.

A view tells the head by its ends' ramps (:mod:`.features`), and that fails in two ways: over another
structure the background interpolated under the body sags, a level crossing at one end collapses inwards
and that end's "ramp" grows longer than any cone can make (dev seeds: a vessel at the tail, a wrong claim);
and seen foreshortened or small, the cone's ramp is squeezed into the blurred end and the view claims
nothing. Left unidentified, both ends are measured as flat, and a cone's half-height crossing falls short of
its apex by about the body's offset asymmetry: both orders of the known body fit those ends about equally
(:mod:`.body_prior`), and the apex stays ~0.7 of the cone short.

The body's shape in 3D, both views together, tells the ends apart where the ramps do not: under the
hypothesis that the head is the ``+d`` end, each view's ``+d`` end, measured as a cone (its apex extrapolated
from the levels 0.25 and 0.64), and its ``-d`` end, measured as a flat end (the half-height crossing), put
the body's apex and tail on the 3D axis; with the moment centroid, these are five measurements of one
number, the body's place along the axis, through the known offsets (apex ``L - c``, tail ``c`` from the
centroid). Under the true hypothesis they agree within their noise; under the other, the tail measured as a
cone lands near the tail, not a body length from the far end's tail: a cone's worth (3.4 mm on robot 3,
1.5 mm on robot 7, times the view's foreshortening) off. Each measurement's noise is
:mod:`.body_kernels`' (the crossing's, the rim's where the view sees the end obliquely, along the axis by
the ray-axis angle, inflated by the view's clutter), so a cluttered view's ends count for little and a
clean side-on view's decide.

:func:`fit_chi2` gives the chi-square of the body's best place under each hypothesis; the tracker claims
the head only where one fits decisively better and fits well itself, and otherwise leaves it unidentified.
"""
from __future__ import annotations

import math

import numpy as np

from appliance.geometry import Calibration
from appliance.recognition import body_kernels as bk
from appliance.recognition.body_prior import BodyModel
from appliance.recognition.features import Features2D
from appliance.recognition.reconstruction import ray_line_parameters

#: How far (as a fraction of the view's clutter times the cone's length, or the diameter for a flat end and
#: the centroid) a measurement moves over another structure, as a standard deviation (dev seeds 1-20).
CLUTTER_FRACTION = 0.5


def plus_end(calibration: Calibration, name: str, centroid: np.ndarray, direction: np.ndarray,
             feat: Features2D) -> int:
    """Which 2D end of ``feat`` (0: +axis, 1: -axis) is the image of the 3D axis' ``+direction`` end."""
    view = calibration.views[name]
    uv = view.project(np.vstack([centroid, centroid + direction]))
    return 0 if float(np.dot(uv[1] - uv[0], feat.axis)) >= 0.0 else 1


def _end_px(feat: Features2D, end: int, conical: bool) -> np.ndarray:
    """The pixel of a 2D end measured by the cone's (apex) or the flat end's model."""
    sign = 1.0 if end == 0 else -1.0
    return feat.centroid + sign * feat.tip_distance(end, conical) * feat.axis


def axial_rows(calibration: Calibration, centroid: np.ndarray, direction: np.ndarray,
               feats: dict[str, Features2D], clutter: dict[str, float], body: BodyModel
               ) -> tuple[list[tuple[float, float, float]], list[tuple[float, float, float]]]:
    """The body's place along the axis ``centroid + b direction`` as each measurement gives it, with its head
    at the ``+direction`` end, then at the ``-direction`` end: per measurement ``(b, clean sigma, clutter
    sigma)`` (mm). The moment centroid comes last (``b`` 0); each view gives its apex and its tail."""
    to_head = body.length_mm - body.centroid_from_tail_mm
    to_tail = body.centroid_from_tail_mm
    out: list[list[tuple[float, float, float]]] = []
    for sign in (1.0, -1.0):
        rows: list[tuple[float, float, float]] = []
        sin2_sum, mm_sum, worst = 0.0, 0.0, 0.0
        for name, feat in feats.items():
            view = calibration.views[name]
            plus = plus_end(calibration, name, centroid, direction, feat)
            head = plus if sign > 0 else 1 - plus
            pixels = np.vstack([feat.centroid, _end_px(feat, head, True), _end_px(feat, 1 - head, False)])
            b, sin2 = ray_line_parameters(view, pixels, centroid, direction)
            mm_per_px = float(np.linalg.norm(view.source_mm - centroid)) / float(view.K[0, 0])
            level = max(clutter.get(name, 0.0), 0.0)
            worst = max(worst, level)
            sin2_sum += float(sin2[0])
            mm_sum += mm_per_px
            for k, is_head, offset in ((1, True, sign * to_head), (2, False, -sign * to_tail)):
                sine = math.sqrt(float(sin2[k]))
                clean = bk._end_sigma_mm(is_head, body.cone_length_mm, body.diameter_mm, mm_per_px, sine, 1.0)
                # Over another structure the background under the body slopes by about ``level`` of its
                # contrast, and a crossing on the cone's ramp moves by a fraction of the cone that grows with
                # it (a flat end's, of its blurred rim): half of ``level`` on the dev seeds.
                scale = body.cone_length_mm if is_head else body.diameter_mm
                rows.append((float(b[k]) - offset, clean, CLUTTER_FRACTION * level * scale))
        views = max(len(rows) // 2, 1)
        clean_c = bk.CENTROID_SIGMA_PX * (mm_sum / views) / math.sqrt(max(sin2_sum, 1e-6))
        rows.append((0.0, clean_c, CLUTTER_FRACTION * worst * body.diameter_mm))
        out.append(rows)
    return out[0], out[1]


def chi2_of(rows: list[tuple[float, float, float]], cap: float) -> float:
    """The chi-square of the body's best place along the axis, each measurement's term capped at ``cap``
    squared: an end lost to or run on into another structure is an outlier, not a Gaussian error, and
    must neither decide alone nor pull the place. The best place is the inverse-variance mean of the
    measurements, or one of them, whichever gives the least capped sum."""
    weights = [1.0 / (clean * clean + near * near) for _, clean, near in rows]
    mean = sum(w * b for w, (b, _, _) in zip(weights, rows)) / sum(weights)
    return min(sum(min(w * (b - place) ** 2, cap * cap) for w, (b, _, _) in zip(weights, rows))
               for place in [mean] + [b for b, _, _ in rows])
