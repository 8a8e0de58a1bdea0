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
cone lands near the tail, where the apex should be ``L - 2c`` further out (4.8 mm on robot 3, 1.8 mm on
robot 7, times the view's foreshortening). Each measurement's noise is :mod:`.body_kernels`' for a clean
view (the crossing's, the rim's where the view sees the end obliquely, along the axis by the ray-axis
angle), and over another structure ``CLUTTER_FRACTION`` of the view's clutter times the cone's length (an
apex) or the diameter (a tail, the centroid) on top: a cluttered view's ends count for less, a clean
side-on view's decide.

:func:`axial_rows` gives the measurements under each hypothesis and :func:`chi2_of` the chi-square of the
body's best place (robust: a measurement far off counts no more than a cap); the tracker claims
the head only where one fits decisively better and fits well itself, and otherwise leaves it unidentified.
"""
from __future__ import annotations

import math

import numpy as np

from appliance.compiled import register_warm_up
from appliance.geometry import Calibration
from appliance.geometry_kernels import VIEW_SIZE
from appliance.recognition import body_kernels as bk
from appliance.recognition import head_kernels as hk
from appliance.recognition.body_prior import BodyModel
from appliance.recognition.features import Features2D
from appliance.recognition.reconstruction import ray_line_parameters

#: How far (as a fraction of the view's clutter times the cone's length, or the diameter for a flat end and
#: the centroid) a measurement moves over another structure, as a standard deviation (dev seeds 1-20).
CLUTTER_FRACTION = 0.5
#: Each view's offset in the packed calibration (:mod:`appliance.geometry_kernels`).
VIEW_OFFSETS = {"p": 0, "q": VIEW_SIZE}


def _end_px(feat: Features2D, end: int, conical: bool) -> np.ndarray:
    """The pixel of a 2D end measured by the cone's (apex) or the flat end's model."""
    sign = 1.0 if end == 0 else -1.0
    return feat.centroid + sign * feat.tip_distance(end, conical) * feat.axis


def axial_rows(calibration: Calibration, centroid: np.ndarray, direction: np.ndarray,
               feats: dict[str, Features2D], clutter: dict[str, float], body: BodyModel
               ) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """The body's place along the axis ``centroid + b direction`` as each measurement gives it, with its head
    at the ``+direction`` end, then at the ``-direction`` end: per measurement a row ``(b, clean sigma, clutter
    sigma)`` (mm), each view's apex and tail, then the moment centroid (``b`` 0); and per view which of its
    2D ends (0: +axis, 1: -axis) is the ``+direction`` end. One compiled call (:func:`.head_kernels.axial_rows`;
    :func:`axial_rows_reference` is its numpy definition)."""
    views = np.empty((len(feats), hk.VIEW_ROW))
    for i, (name, feat) in enumerate(feats.items()):
        views[i] = (VIEW_OFFSETS[name], feat.centroid[0], feat.centroid[1], feat.axis[0], feat.axis[1],
                    feat.tip_distance(0, True), feat.tip_distance(0, False), feat.tip_distance(1, True),
                    feat.tip_distance(1, False), clutter.get(name, 0.0))
    to_tail = body.centroid_from_tail_mm
    shape = np.array([body.length_mm - to_tail, to_tail, body.cone_length_mm, body.diameter_mm])
    rows = np.empty((2, 2 * len(feats) + 1, 3))
    plus = np.empty(len(feats), dtype=np.int64)
    hk.axial_rows(calibration.packed, views, np.ascontiguousarray(centroid, dtype=np.float64),
                  np.ascontiguousarray(direction, dtype=np.float64), shape, CLUTTER_FRACTION, rows, plus)
    return rows[0], rows[1], {name: int(plus[i]) for i, name in enumerate(feats)}


def axial_rows_reference(calibration: Calibration, centroid: np.ndarray, direction: np.ndarray,
                         feats: dict[str, Features2D], clutter: dict[str, float], body: BodyModel
                         ) -> tuple[list[tuple[float, float, float]], list[tuple[float, float, float]],
                                    dict[str, int]]:
    """:func:`axial_rows` in numpy (its readable definition; the tests compare the two). One ray-axis call per
    view for all its ends."""
    to_head = body.length_mm - body.centroid_from_tail_mm
    to_tail = body.centroid_from_tail_mm
    rows: tuple[list[tuple[float, float, float]], list[tuple[float, float, float]]] = ([], [])
    plus_index: dict[str, int] = {}
    sin2_sum, mm_sum, worst = 0.0, 0.0, 0.0
    for name, feat in feats.items():
        view = calibration.views[name]
        # The 2D end 0 as the cone's apex and as a flat end, then the end 1 likewise; the +direction end is
        # the one whose rays meet the axis further along it.
        pixels = np.vstack([feat.centroid, _end_px(feat, 0, True), _end_px(feat, 0, False),
                            _end_px(feat, 1, True), _end_px(feat, 1, False)])
        b, sin2 = ray_line_parameters(view, pixels, centroid, direction)
        plus = plus_index[name] = 0 if b[2] >= b[4] else 1
        mm_per_px = float(np.linalg.norm(view.source_mm - centroid)) / float(view.K[0, 0])
        level = max(clutter.get(name, 0.0), 0.0)
        worst = max(worst, level)
        sin2_sum += float(sin2[0])
        mm_sum += mm_per_px
        for hypothesis, sign in enumerate((1.0, -1.0)):
            head = plus if sign > 0 else 1 - plus
            apex, tail = 1 + 2 * head, 4 - 2 * head   # the head's end as the apex, the other as a flat end
            for k, is_head, offset in ((apex, True, sign * to_head), (tail, False, -sign * to_tail)):
                clean = bk._end_sigma_mm(is_head, body.cone_length_mm, body.diameter_mm, mm_per_px,
                                         math.sqrt(float(sin2[k])), 1.0)
                # Over another structure the background under the body slopes by about ``level`` of its
                # contrast, and a crossing on the cone's ramp moves by a fraction of the cone that grows with
                # it (a flat end's, of its blurred rim): half of ``level`` on the dev seeds.
                scale = body.cone_length_mm if is_head else body.diameter_mm
                rows[hypothesis].append((float(b[k]) - offset, clean, CLUTTER_FRACTION * level * scale))
    clean_c = bk.CENTROID_SIGMA_PX * (mm_sum / max(len(feats), 1)) / math.sqrt(max(sin2_sum, 1e-6))
    for hypothesis in rows:
        hypothesis.append((0.0, clean_c, CLUTTER_FRACTION * worst * body.diameter_mm))
    return rows[0], rows[1], plus_index


def chi2_of(rows: np.ndarray | list[tuple[float, float, float]], cap: float) -> float:
    """:func:`chi2_of_reference` compiled (:func:`.head_kernels.chi2_of`), on :func:`axial_rows`' rows."""
    return float(hk.chi2_of(np.asarray(rows, dtype=np.float64), float(cap)))


def chi2_of_reference(rows: list[tuple[float, float, float]], cap: float) -> float:
    """The chi-square of the body's best place along the axis, each measurement's term capped at ``cap``
    squared: an end lost to or run on into another structure is an outlier, not a Gaussian error, and
    must neither decide alone nor pull the place. The best place is the inverse-variance mean of the
    measurements, or one of them, whichever gives the least capped sum."""
    weights = [1.0 / (clean * clean + near * near) for _, clean, near in rows]
    mean = sum(w * b for w, (b, _, _) in zip(weights, rows)) / sum(weights)
    return min(sum(min(w * (b - place) ** 2, cap * cap) for w, (b, _, _) in zip(weights, rows))
               for place in [mean] + [b for b, _, _ in rows])


def warm_up() -> None:
    """Compile :func:`.body_kernels._end_sigma_mm` for the call :func:`axial_rows_reference` makes from Python (a
    head flag, five floats). The kernels that call it inline it, so their warm-ups leave it without a Python signature,
    and the first frame that weighs a head by the body would load it (~10 ms from the cache, seconds cold)
    inside the loop's window."""
    for is_head in (True, False):
        bk._end_sigma_mm(is_head, 1.0, 0.5, 0.05, math.sqrt(0.5), 1.0)


register_warm_up(__name__)
