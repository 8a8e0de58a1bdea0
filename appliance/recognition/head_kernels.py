"""The compiled arithmetic of :mod:`.head_by_body`: the body's place along the axis as each end measures it, and
the capped chi-square of its best place.

A frame whose head is weighed by the body (one not plain, :mod:`.steady_state`) spent ~0.3-1 ms in numpy calls on
five-row arrays (issue 8: the steady state's p99); here it is one call for the rows and one per hypothesis for
the chi-square. :func:`.head_by_body.axial_rows_reference` keeps the readable numpy definition (the tests
compare the two): the rays are :mod:`appliance.geometry_kernels`' (the same fixed-point undistortion and
``R^T K^-1 x``, summed in another order), so ``b`` may differ from numpy's in the last bits.

Inputs travel as plain float arrays:

* per view a row of ``VIEW_*`` numbers (its offset in the packed calibration, its 2D centroid and unit axis,
  the outward distances (px) of end 0 as the cone's apex and as a flat end, then end 1 likewise, its clutter);
* the body as ``BODY_*``: the distances from the moment centroid to the apex and to the tail, the cone's
  length and the diameter (mm).
"""
from __future__ import annotations

import math

import numpy as np

from appliance.compiled import kernel, register_warm_up
from appliance.geometry_kernels import _SRC, VIEW_SIZE, pack_view, pack_views
from appliance.recognition import body_kernels as bk
from appliance.recognition.reconstruction_kernels import _ray_line_b

# Layout of a view's row.
VIEW_OFFSET = 0
VIEW_CENTROID = 1   # 2
VIEW_AXIS = 3       # 2
VIEW_APEX_0 = 5     # end 0 (+axis) as the cone's apex, as a flat end; then end 1 (-axis) likewise
VIEW_FLAT_0 = 6
VIEW_APEX_1 = 7
VIEW_FLAT_1 = 8
VIEW_CLUTTER = 9
VIEW_ROW = 10

# Layout of the body's numbers.
BODY_TO_HEAD = 0
BODY_TO_TAIL = 1
BODY_CONE = 2
BODY_DIAMETER = 3
BODY_SIZE = 4


@kernel
def axial_rows(G: np.ndarray, views: np.ndarray, centroid: np.ndarray, direction: np.ndarray, body: np.ndarray,
               clutter_fraction: float, rows: np.ndarray, plus: np.ndarray) -> None:
    """:func:`.head_by_body.axial_rows` into ``rows`` (2, 2 * views + 1, 3): per hypothesis (the head at the
    ``+direction`` end, then at the ``-direction`` end) each view's apex and tail, then the moment centroid, as
    ``(b, clean sigma, clutter sigma)``; and into ``plus`` (views,) each view's 2D end at ``+direction``."""
    to_head, to_tail = body[BODY_TO_HEAD], body[BODY_TO_TAIL]
    cone, diameter = body[BODY_CONE], body[BODY_DIAMETER]
    n = views.shape[0]
    b = np.empty(5)
    sin2 = np.empty(5)
    sin2_sum, mm_sum, worst = 0.0, 0.0, 0.0
    for i in range(n):
        view = views[i]
        o = int(view[VIEW_OFFSET])
        cu, cv = view[VIEW_CENTROID], view[VIEW_CENTROID + 1]
        au, av = view[VIEW_AXIS], view[VIEW_AXIS + 1]
        # The centroid, end 0 as the cone's apex and as a flat end, then end 1 likewise (as the numpy pixels).
        b[0], sin2[0] = _ray_line_b(G, o, cu, cv, centroid, direction)
        for k in range(4):
            sign = 1.0 if k < 2 else -1.0
            step = sign * view[VIEW_APEX_0 + k]
            b[k + 1], sin2[k + 1] = _ray_line_b(G, o, cu + step * au, cv + step * av, centroid, direction)
        p = 0 if b[2] >= b[4] else 1
        plus[i] = p
        s0 = G[o + _SRC] - centroid[0]
        s1 = G[o + _SRC + 1] - centroid[1]
        s2 = G[o + _SRC + 2] - centroid[2]
        mm_per_px = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2) / G[o]   # G[o]: K[0, 0]
        level = max(view[VIEW_CLUTTER], 0.0)
        worst = max(worst, level)
        sin2_sum += sin2[0]
        mm_sum += mm_per_px
        for hypothesis in range(2):
            sign = 1.0 if hypothesis == 0 else -1.0
            head = p if hypothesis == 0 else 1 - p
            apex, tail = 1 + 2 * head, 4 - 2 * head   # the head's end as the apex, the other as a flat end
            r = 2 * i
            rows[hypothesis, r, 0] = b[apex] - sign * to_head
            rows[hypothesis, r, 1] = bk._end_sigma_mm(True, cone, diameter, mm_per_px, math.sqrt(sin2[apex]), 1.0)
            rows[hypothesis, r, 2] = clutter_fraction * level * cone
            rows[hypothesis, r + 1, 0] = b[tail] - (-sign * to_tail)
            rows[hypothesis, r + 1, 1] = bk._end_sigma_mm(False, cone, diameter, mm_per_px,
                                                          math.sqrt(sin2[tail]), 1.0)
            rows[hypothesis, r + 1, 2] = clutter_fraction * level * diameter
    clean_c = bk.CENTROID_SIGMA_PX * (mm_sum / max(n, 1)) / math.sqrt(max(sin2_sum, 1e-6))
    for hypothesis in range(2):
        rows[hypothesis, 2 * n, 0] = 0.0
        rows[hypothesis, 2 * n, 1] = clean_c
        rows[hypothesis, 2 * n, 2] = clutter_fraction * worst * diameter


@kernel
def chi2_of(rows: np.ndarray, cap: float) -> float:
    """:func:`.head_by_body.chi2_of` on rows ``(b, clean sigma, clutter sigma)`` (m, 3), summed in its order."""
    m = rows.shape[0]
    weights = np.empty(m)
    total_w, total_wb = 0.0, 0.0
    for i in range(m):
        clean, near = rows[i, 1], rows[i, 2]
        weights[i] = 1.0 / (clean * clean + near * near)
        total_w += weights[i]
        total_wb += weights[i] * rows[i, 0]
    mean = total_wb / total_w
    cap2 = cap * cap
    best = math.inf
    for j in range(m + 1):
        place = mean if j == 0 else rows[j - 1, 0]
        total = 0.0
        for i in range(m):
            d = rows[i, 0] - place
            total += min(weights[i] * (d * d), cap2)
        if total < best:
            best = total
    return best


def warm_up_calibration() -> np.ndarray:
    """A packed calibration (read-only, as :attr:`appliance.geometry.Calibration.packed`: a read-only array is
    another type to numba) for the warm-ups: two views 500 mm from the origin, without distortion."""
    K = np.array([[1000.0, 0.0, 500.0], [0.0, 1000.0, 500.0], [0.0, 0.0, 1.0]])
    view = pack_view(K, np.linalg.inv(K), np.eye(3), np.array([0.0, 0.0, 500.0]), np.zeros(5))
    return pack_views(view, view, np.zeros((3, 3)), 1.0)


def warm_up() -> None:
    """Compile both kernels for the calls :mod:`.head_by_body` makes (two views, the read-only packed calibration),
    so that the first frame weighing a head by the body compiles nothing inside the loop's window."""
    G = warm_up_calibration()
    views = np.zeros((2, VIEW_ROW))
    views[1, VIEW_OFFSET] = VIEW_SIZE
    views[:, VIEW_AXIS] = 1.0
    views[:, VIEW_APEX_0:VIEW_FLAT_1 + 1] = 10.0
    rows = np.empty((2, 5, 3))
    axial_rows(G, views, np.zeros(3), np.array([1.0, 0.0, 0.0]), np.array([2.0, 1.0, 1.0, 0.5]), 0.5, rows,
               np.empty(2, dtype=np.int64))
    chi2_of(rows[0], 4.0)


register_warm_up(__name__)
