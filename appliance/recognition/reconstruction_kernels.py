"""The compiled arithmetic of :func:`.reconstruction.reconstruct` (default ``weighted`` estimator).

A frame's reconstruction is a few hundred floating-point operations on a dozen points; as numpy calls
it cost milliseconds (issue 8), as two kernel calls it costs microseconds. The method is the one the
docstring of :mod:`.reconstruction` describes; :mod:`.reconstruction` keeps the decisions that need
Python objects (the features' head models, the reasons given to the operator) and calls:

* :func:`weighted_front` - centroid and both pairings' tips triangulated (optimal correction), the A/B
  epipolar test, the two axis planes, the choice of pairing, the axis fused from planes and tips,
  the perspective-corrected centroid, and per view which 2D tip is the ``+d`` end;
* :func:`place_tips` - both ends placed on the 3D axis from the views' (re-estimated) tips, the
  length and the reprojection error. :func:`weighted_front` already does it for the tips as measured,
  which is what a steady-state frame keeps (its features come with the head the views agree on).

Outputs go into a float array whose layout is given by the ``OUT_*`` / ``TIPS_*`` offsets.
"""
from __future__ import annotations

import math

import numpy as np

from appliance.compiled import kernel, register_warm_up
from appliance.geometry_kernels import (
    _K,
    _SRC,
    VIEW_SIZE,
    epipolar_distance,
    ideal_pixel,
    project_point,
    ray_direction,
    symmetric_eigen,
    triangulate_ideal,
)

# Status of weighted_front.
STATUS_OK = 0
STATUS_UNRESOLVED = 1  # mirror ambiguity with nothing to resolve it: no direction
STATUS_TIPS_DEGENERATE = 2  # the chosen pairing's triangulated tips coincide or lie behind a source
STATUS_PLANE_P = 3  # view p's axis pixels coincide: no plane through them
STATUS_PLANE_Q = 4

# Reason codes of weighted_front (the text is written by reconstruction.py).
REASON_NONE = 0
REASON_PAIRING_CONFLICT = 1  # the planes imply one pairing, the tips' epipolar test the other
REASON_DISAGREEMENT = 2  # the axis from the planes and from the tips differ
REASON_BY_HEADS = 3  # epipolar-plane ambiguity resolved by the head seen in both views
REASON_BY_PREVIOUS = 4  # ... by the previous frames' direction
REASON_UNRESOLVED = 5  # ... not at all

# Layout of weighted_front's output.
OUT_CENTROID = 0  # 3: triangulated weighted centroids
OUT_HYP_A = 3  # 6: tips of pairing A (row 0 from p's tip 0)
OUT_HYP_B = 9  # 6: tips of pairing B
OUT_RMS_A = 15
OUT_RMS_B = 16
OUT_PLANE_ANGLE = 17  # degrees between the two axis planes
OUT_CASE = 18  # 0: A, 1: B, -1: unresolved
OUT_REASON = 19
OUT_IMPLIED = 20  # the pairing the planes imply (0/1)
OUT_DISAGREEMENT = 21  # degrees between the planes' axis and the tips' axis
OUT_CENTROID_EPIPOLAR = 22  # symmetric epipolar distance (px) of the two image centroids
OUT_DIRECTION = 23  # 3: unit 3D axis (tips of the chosen pairing's sense)
OUT_SIGMA = 26  # standard deviation (rad) of the fused axis
OUT_CORRECTED = 27  # 3: perspective-corrected centroid
OUT_PLUS = 30  # 2: per view, the 2D tip (0/1) at the +direction end
OUT_SIDE = 32  # 2: per view, |ray x direction| (how side-on the view sees the axis)
OUT_CANDIDATES = 34  # 6: unit directions of pairings A and B
OUT_AMBIGUOUS = 40
OUT_ENDS_IN_DOUBT = 41
OUT_PLACED = 42  # TIPS_SIZE: place_tips' output for the views' tips as measured, +d end first
OUT_SIZE = 50

# Layout of place_tips' output.
TIPS_POINTS = 0  # 6: the +d end, then the -d end
TIPS_LENGTH = 6
TIPS_REPROJECTION = 7  # RMS px over centroid and both ends, both views (NaN if not defined)
TIPS_SIZE = 8


@kernel
def _line_angle_deg(a0: float, a1: float, a2: float, b0: float, b1: float, b2: float) -> float:
    """Angle between two lines, degrees (as reconstruction.line_angle_deg, NaN cosines counting as 1)."""
    na = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    nb = math.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
    if na == 0.0 or nb == 0.0:
        return 0.0
    c = abs((a0 / na) * (b0 / nb) + (a1 / na) * (b1 / nb) + (a2 / na) * (b2 / nb))
    if not c < 1.0:
        c = 1.0
    return math.degrees(math.acos(c))


@kernel
def _plane_normal(G: np.ndarray, o: int, c: np.ndarray, axis: np.ndarray, eig0: float, eig1: float,
                  out: np.ndarray) -> bool:
    """Unit normal of the plane through the view's source and the blob's axis, its principal direction
    taken in angles about the source rather than in pixels.

    The image of a rod is mirror-symmetric about its axis in the directions of the rays (a reflection
    through the plane of the source and the axis maps rays to rays), not on the pixel grid: pixels that
    are not square (this calibration's ``fx`` and ``fy`` differ by 1 %), distortion and an oblique ray
    stretch the image unevenly, which turns a stubby blob's principal axis off the axis' image by up to
    ``stretch * l2 / (l1 - l2)`` (robot 4 seen foreshortened: l2 / (l1 - l2) ~ 1-3, tenths of a degree).
    So the blob's second moments ``l1 v v^T + l2 w w^T`` (px^2, ``v`` = ``axis``) are carried by the ray
    directions' derivatives at the centroid onto the plane perpendicular to its ray, and the normal is
    the ray's cross product with their principal direction there (with square pixels and no distortion
    at the image centre, the pixels' own axis)."""
    step = max(2.0, math.sqrt(max(eig0, 0.0)))
    u, v = c[0], c[1]
    iu, iv = ideal_pixel(G, o, u, v)
    r0, r1, r2 = ray_direction(G, o, iu, iv)
    iu, iv = ideal_pixel(G, o, u + step, v)
    px0, px1, px2 = ray_direction(G, o, iu, iv)
    iu, iv = ideal_pixel(G, o, u - step, v)
    mx0, mx1, mx2 = ray_direction(G, o, iu, iv)
    iu, iv = ideal_pixel(G, o, u, v + step)
    py0, py1, py2 = ray_direction(G, o, iu, iv)
    iu, iv = ideal_pixel(G, o, u, v - step)
    my0, my1, my2 = ray_direction(G, o, iu, iv)
    v0, v1 = axis[0], axis[1]
    # The ray's change per pixel along the axis (a) and across it (b).
    a0 = ((px0 - mx0) * v0 + (py0 - my0) * v1) / (2.0 * step)
    a1 = ((px1 - mx1) * v0 + (py1 - my1) * v1) / (2.0 * step)
    a2 = ((px2 - mx2) * v0 + (py2 - my2) * v1) / (2.0 * step)
    b0 = (-(px0 - mx0) * v1 + (py0 - my0) * v0) / (2.0 * step)
    b1 = (-(px1 - mx1) * v1 + (py1 - my1) * v0) / (2.0 * step)
    b2 = (-(px2 - mx2) * v1 + (py2 - my2) * v0) / (2.0 * step)
    na = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    if na < 1e-15:
        return False
    e0, e1, e2 = a0 / na, a1 / na, a2 / na
    bx = b0 * e0 + b1 * e1 + b2 * e2
    f0, f1, f2 = b0 - bx * e0, b1 - bx * e1, b2 - bx * e2
    by = math.sqrt(f0 * f0 + f1 * f1 + f2 * f2)
    if by > 0.0:
        f0, f1, f2 = f0 / by, f1 / by, f2 / by
    # The moments in the orthonormal tangent basis (e, f): l1 (a a^T) + l2 (b b^T); their principal direction.
    l1, l2 = max(eig0, 0.0), max(eig1, 0.0)
    sxx = l1 * na * na + l2 * bx * bx
    sxy = l2 * bx * by
    syy = l2 * by * by
    angle = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
    ca, sa = math.cos(angle), math.sin(angle)
    d0, d1, d2 = ca * e0 + sa * f0, ca * e1 + sa * f1, ca * e2 + sa * f2
    n0, n1, n2 = r1 * d2 - r2 * d1, r2 * d0 - r0 * d2, r0 * d1 - r1 * d0
    norm = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    if norm < 1e-12:
        return False
    out[0], out[1], out[2] = n0 / norm, n1 / norm, n2 / norm
    return True


@kernel
def _ray_line_b(G: np.ndarray, o: int, u: float, v: float, c: np.ndarray, d: np.ndarray) -> tuple[float, float]:
    """For an observed pixel's ray, the parameter ``b`` of its point nearest the line ``c + b d``, and ``sin^2``
    of the ray-line angle (as reconstruction.ray_line_parameters)."""
    iu, iv = ideal_pixel(G, o, u, v)
    r0, r1, r2 = ray_direction(G, o, iu, iv)
    k = r0 * d[0] + r1 * d[1] + r2 * d[2]
    w0 = G[o + _SRC] - c[0]
    w1 = G[o + _SRC + 1] - c[1]
    w2 = G[o + _SRC + 2] - c[2]
    sin2 = max(1.0 - k * k, 1e-12)
    b = (w0 * d[0] + w1 * d[1] + w2 * d[2] - k * (w0 * r0 + w1 * r1 + w2 * r2)) / sin2
    return b, sin2


@kernel
def weighted_front(G: np.ndarray, cp: np.ndarray, axp: np.ndarray, tp: np.ndarray, cq: np.ndarray,
                   axq: np.ndarray, tq: np.ndarray, eig_p0: float, eig_p1: float, sigma_p: float, head_p: int,
                   eig_q0: float, eig_q1: float, sigma_q: float, head_q: int, prev0: float, prev1: float,
                   prev2: float, has_previous: bool, ambiguity_px: float, min_plane_angle_deg: float,
                   max_axis_disagreement_deg: float, min_view_elongation: float, axis_floor_rad: float,
                   tip_sigma_px: float, tip_rim_fraction: float, out: np.ndarray) -> int:
    """Everything of the weighted reconstruction up to the head decision (see the module docstring).

    ``sigma_*``: the view's axis-angle noise (rad), NaN if unknown; ``head_*``: the head's 2D index or -1.
    """
    out[:] = math.nan
    q = VIEW_SIZE
    # Centroid and the tips of both pairings (row 0 of each from p's tip 0).
    ucp, vcp = ideal_pixel(G, 0, cp[0], cp[1])
    ucq, vcq = ideal_pixel(G, q, cq[0], cq[1])
    out[OUT_CENTROID], out[OUT_CENTROID + 1], out[OUT_CENTROID + 2] = triangulate_ideal(G, ucp, vcp, ucq, vcq, True)
    ip = np.empty((2, 2))
    iq = np.empty((2, 2))
    for k in range(2):
        ip[k, 0], ip[k, 1] = ideal_pixel(G, 0, tp[k, 0], tp[k, 1])
        iq[k, 0], iq[k, 1] = ideal_pixel(G, q, tq[k, 0], tq[k, 1])
    for k in range(2):
        a = OUT_HYP_A + 3 * k
        out[a], out[a + 1], out[a + 2] = triangulate_ideal(G, ip[k, 0], ip[k, 1], iq[k, 0], iq[k, 1], True)
        b = OUT_HYP_B + 3 * k
        out[b], out[b + 1], out[b + 2] = triangulate_ideal(G, ip[k, 0], ip[k, 1], iq[1 - k, 0], iq[1 - k, 1], True)
    # Pairing A/B by the RMS symmetric epipolar distance of the ideal tips.
    da0 = epipolar_distance(G, ip[0, 0], ip[0, 1], iq[0, 0], iq[0, 1])
    da1 = epipolar_distance(G, ip[1, 0], ip[1, 1], iq[1, 0], iq[1, 1])
    db0 = epipolar_distance(G, ip[0, 0], ip[0, 1], iq[1, 0], iq[1, 1])
    db1 = epipolar_distance(G, ip[1, 0], ip[1, 1], iq[0, 0], iq[0, 1])
    rms_a = math.sqrt((da0 * da0 + da1 * da1) / 2.0)
    rms_b = math.sqrt((db0 * db0 + db1 * db1) / 2.0)
    out[OUT_RMS_A], out[OUT_RMS_B] = rms_a, rms_b
    pairing_case = 0 if rms_a <= rms_b else 1
    separated = abs(rms_a - rms_b) >= ambiguity_px
    out[OUT_CENTROID_EPIPOLAR] = epipolar_distance(G, ucp, vcp, ucq, vcq)
    # Unit directions of both pairings (the mirror candidates).
    for k in range(2):
        h = OUT_HYP_A if k == 0 else OUT_HYP_B
        e0, e1, e2 = out[h] - out[h + 3], out[h + 1] - out[h + 4], out[h + 2] - out[h + 5]
        norm = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        if norm > 0.0:  # else NaN, as left by the initialisation
            c = OUT_CANDIDATES + 3 * k
            out[c], out[c + 1], out[c + 2] = e0 / norm, e1 / norm, e2 / norm
    # The two axis planes.
    n_p = np.empty(3)
    n_q = np.empty(3)
    if not _plane_normal(G, 0, cp, axp, eig_p0, eig_p1, n_p):
        return STATUS_PLANE_P
    if not _plane_normal(G, q, cq, axq, eig_q0, eig_q1, n_q):
        return STATUS_PLANE_Q
    x0 = n_p[1] * n_q[2] - n_p[2] * n_q[1]
    x1 = n_p[2] * n_q[0] - n_p[0] * n_q[2]
    x2 = n_p[0] * n_q[1] - n_p[1] * n_q[0]
    cross_norm = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
    plane_angle = math.degrees(math.asin(min(1.0, cross_norm)))
    out[OUT_PLANE_ANGLE] = plane_angle
    ambiguous = False
    ends_in_doubt = False
    reason = REASON_NONE
    case = pairing_case
    if plane_angle >= min_plane_angle_deg:
        # The planes fix the line; the pairing is the one whose tips run along it.
        angles = np.empty(2)
        for k in range(2):
            h = OUT_HYP_A if k == 0 else OUT_HYP_B
            e0, e1, e2 = out[h] - out[h + 3], out[h + 1] - out[h + 4], out[h + 2] - out[h + 5]
            finite = True
            for i in range(6):
                finite = finite and math.isfinite(out[h + i])
            angles[k] = _line_angle_deg(e0, e1, e2, x0, x1, x2) if finite else 180.0
        implied = 0 if angles[0] <= angles[1] else 1
        out[OUT_IMPLIED] = implied
        case = implied
        h = OUT_HYP_A if implied == 0 else OUT_HYP_B
        e0, e1, e2 = out[h] - out[h + 3], out[h + 1] - out[h + 4], out[h + 2] - out[h + 5]
        if math.isfinite(e0) and math.isfinite(e1) and math.isfinite(e2):
            disagreement = _line_angle_deg(e0, e1, e2, x0, x1, x2)
        else:
            disagreement = 90.0
        out[OUT_DISAGREEMENT] = disagreement
        if separated and implied != pairing_case:
            ambiguous = ends_in_doubt = True
            reason = REASON_PAIRING_CONFLICT
        elif disagreement > max_axis_disagreement_deg:
            ambiguous = ends_in_doubt = True
            reason = REASON_DISAGREEMENT
    elif not separated:
        ambiguous = True
        if head_p >= 0 and head_q >= 0:
            case = 0 if head_p == head_q else 1
            reason = REASON_BY_HEADS
        elif has_previous:
            best = -1.0
            case = -1
            for k in range(2):
                h = OUT_HYP_A if k == 0 else OUT_HYP_B
                finite = True
                for i in range(6):
                    finite = finite and math.isfinite(out[h + i])
                if finite:
                    c = OUT_CANDIDATES + 3 * k
                    score = abs(out[c] * prev0 + out[c + 1] * prev1 + out[c + 2] * prev2)
                    if score > best:
                        best = score
                        case = k
            reason = REASON_BY_PREVIOUS if case >= 0 else REASON_UNRESOLVED
        else:
            case = -1
            reason = REASON_UNRESOLVED
    out[OUT_CASE] = case
    out[OUT_REASON] = reason
    out[OUT_AMBIGUOUS] = 1.0 if ambiguous else 0.0
    out[OUT_ENDS_IN_DOUBT] = 1.0 if ends_in_doubt else 0.0
    if case < 0:
        return STATUS_UNRESOLVED
    # The axis fused from both planes and the chosen pairing's tips, each by its precision.
    h = OUT_HYP_A if case == 0 else OUT_HYP_B
    e0, e1, e2 = out[h] - out[h + 3], out[h + 1] - out[h + 4], out[h + 2] - out[h + 5]
    norm = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    if not (math.isfinite(norm) and norm > 1e-9):
        return STATUS_TIPS_DEGENERATE
    t0, t1, t2 = e0 / norm, e1 / norm, e2 / norm
    c = out[OUT_CENTROID:OUT_CENTROID + 3]
    M = np.zeros((3, 3))
    sigma_tips = 0.0
    for view in range(2):
        o = view * VIEW_SIZE
        n = n_p if view == 0 else n_q
        s0, s1, s2 = c[0] - G[o + _SRC], c[1] - G[o + _SRC + 1], c[2] - G[o + _SRC + 2]
        z = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
        s0, s1, s2 = s0 / z, s1 / z, s2 / z
        y0, y1, y2 = s1 * t2 - s2 * t1, s2 * t0 - s0 * t2, s0 * t1 - s1 * t0
        sin_a = max(math.sqrt(y0 * y0 + y1 * y1 + y2 * y2), 0.05)
        sigma_view = sigma_p if view == 0 else sigma_q
        angle_sigma = sigma_view if math.isfinite(sigma_view) else 0.01
        eig0, eig1 = (eig_p0, eig_p1) if view == 0 else (eig_q0, eig_q1)
        if eig0 < min_view_elongation * eig1:
            angle_sigma = 1.0  # nearly round image (seen end-on): its principal axis means nothing
        sigma = math.hypot(angle_sigma * sin_a, axis_floor_rad)
        for i in range(3):
            for j in range(3):
                M[i, j] += n[i] * n[j] / sigma ** 2
        tips = tp if view == 0 else tq
        image_length = max(math.hypot(tips[0, 0] - tips[1, 0], tips[0, 1] - tips[1, 1]), 1.0)
        width_px = 4.0 * math.sqrt(max(eig1, 0.0))
        cos_a = abs(s0 * t0 + s1 * t1 + s2 * t2)
        tip_sigma = math.hypot(tip_sigma_px, tip_rim_fraction * width_px * cos_a)
        sigma_tips = max(sigma_tips, tip_sigma * math.sqrt(2.0) / image_length)
    t = (t0, t1, t2)
    for i in range(3):
        for j in range(3):
            M[i, j] += ((1.0 if i == j else 0.0) - t[i] * t[j]) / sigma_tips ** 2
    values = np.empty(3)
    vectors = np.empty((3, 3))
    symmetric_eigen(M, values, vectors)
    d = np.empty(3)
    sign = 1.0 if vectors[0, 0] * t0 + vectors[1, 0] * t1 + vectors[2, 0] * t2 >= 0 else -1.0
    norm = math.sqrt(vectors[0, 0] ** 2 + vectors[1, 0] ** 2 + vectors[2, 0] ** 2)
    for i in range(3):
        d[i] = sign * vectors[i, 0] / norm
    out[OUT_SIGMA] = 1.0 / math.sqrt(max(values[1] - values[0], 1e-12))
    out[OUT_DIRECTION], out[OUT_DIRECTION + 1], out[OUT_DIRECTION + 2] = d[0], d[1], d[2]
    # Perspective-corrected centroid: each view's weighted centroid is the projection of
    # C - 3 k Var / z d (Var: the body's variance along its axis, from the most side-on view).
    best_sin2 = -1.0
    variance = 0.0
    for view in range(2):
        o = view * VIEW_SIZE
        r0, r1, r2 = c[0] - G[o + _SRC], c[1] - G[o + _SRC + 1], c[2] - G[o + _SRC + 2]
        z = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
        k = (r0 * d[0] + r1 * d[1] + r2 * d[2]) / z
        sin2 = 1.0 - k * k
        mm_per_px = z / G[o + _K]
        if sin2 > best_sin2:
            best_sin2 = sin2
            variance = (eig_p0 if view == 0 else eig_q0) * mm_per_px ** 2 / max(sin2, 1e-6)
    corrected = np.empty(4)
    for view in range(2):
        o = view * VIEW_SIZE
        r0, r1, r2 = c[0] - G[o + _SRC], c[1] - G[o + _SRC + 1], c[2] - G[o + _SRC + 2]
        z = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
        shift = -3.0 * ((r0 * d[0] + r1 * d[1] + r2 * d[2]) / z) * variance / z
        su, sv = project_point(G, o, c[0] + shift * d[0], c[1] + shift * d[1], c[2] + shift * d[2])
        tu, tv = project_point(G, o, c[0], c[1], c[2])
        cv = cp if view == 0 else cq
        iu, iv = ideal_pixel(G, o, cv[0] + (tu - su), cv[1] + (tv - sv))
        corrected[2 * view], corrected[2 * view + 1] = iu, iv
    X0, X1, X2 = triangulate_ideal(G, corrected[0], corrected[1], corrected[2], corrected[3], True)
    out[OUT_CORRECTED], out[OUT_CORRECTED + 1], out[OUT_CORRECTED + 2] = X0, X1, X2
    centre = out[OUT_CORRECTED:OUT_CORRECTED + 3]
    # Which 2D tip of each view is the +d end, and how side-on each view sees the axis.
    for view in range(2):
        o = view * VIEW_SIZE
        tips = tp if view == 0 else tq
        b0, _ = _ray_line_b(G, o, tips[0, 0], tips[0, 1], centre, d)
        b1, _ = _ray_line_b(G, o, tips[1, 0], tips[1, 1], centre, d)
        out[OUT_PLUS + view] = 0.0 if b0 >= b1 else 1.0
        r0, r1, r2 = centre[0] - G[o + _SRC], centre[1] - G[o + _SRC + 1], centre[2] - G[o + _SRC + 2]
        z = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
        r0, r1, r2 = r0 / z, r1 / z, r2 / z
        y0, y1, y2 = r1 * d[2] - r2 * d[1], r2 * d[0] - r0 * d[2], r0 * d[1] - r1 * d[0]
        out[OUT_SIDE + view] = math.sqrt(y0 * y0 + y1 * y1 + y2 * y2)
    _place(G, centre, d, tp, int(out[OUT_PLUS]), tq, int(out[OUT_PLUS + 1]), cp, cq, out, OUT_PLACED)
    return STATUS_OK


@kernel
def _place(G: np.ndarray, c: np.ndarray, d: np.ndarray, tp: np.ndarray, plus_p: int, tq: np.ndarray, plus_q: int,
           cp: np.ndarray, cq: np.ndarray, out: np.ndarray, at: int) -> None:
    """:func:`place_tips` with each view's +d tip given by its index (``plus_*``), into ``out[at:]``."""
    sums0 = sums1 = weights0 = weights1 = 0.0
    for view in range(2):
        o = view * VIEW_SIZE
        tips = tp if view == 0 else tq
        plus = plus_p if view == 0 else plus_q
        b, w = _ray_line_b(G, o, tips[plus, 0], tips[plus, 1], c, d)
        sums0 += b * w
        weights0 += w
        b, w = _ray_line_b(G, o, tips[1 - plus, 0], tips[1 - plus, 1], c, d)
        sums1 += b * w
        weights1 += w
    b_plus, b_minus = sums0 / weights0, sums1 / weights1
    for i in range(3):
        out[at + TIPS_POINTS + i] = c[i] + b_plus * d[i]
        out[at + TIPS_POINTS + 3 + i] = c[i] + b_minus * d[i]
    out[at + TIPS_LENGTH] = b_plus - b_minus
    total = 0.0
    for point in range(3):
        if point == 0:
            X0, X1, X2 = c[0], c[1], c[2]
        else:
            a = at + TIPS_POINTS + 3 * (point - 1)
            X0, X1, X2 = out[a], out[a + 1], out[a + 2]
        for view in range(2):
            o = view * VIEW_SIZE
            u, v = project_point(G, o, X0, X1, X2)
            if point == 0:
                mu, mv = (cp[0], cp[1]) if view == 0 else (cq[0], cq[1])
            else:
                tips = tp if view == 0 else tq
                plus = plus_p if view == 0 else plus_q
                row = plus if point == 1 else 1 - plus
                mu, mv = tips[row, 0], tips[row, 1]
            total += ((u - mu) ** 2 + (v - mv) ** 2) / 2.0
    out[at + TIPS_REPROJECTION] = math.sqrt(total / 3.0)


@kernel
def place_tips(G: np.ndarray, c: np.ndarray, d: np.ndarray, tp: np.ndarray, plus_p: int, tq: np.ndarray, plus_q: int,
               cp: np.ndarray, cq: np.ndarray, out: np.ndarray) -> None:
    """Both ends on the 3D line ``c + b d`` from each view's tips (``tips[plus]`` at the +d end), weighted by
    ``sin^2`` of the ray-line angle; the length; the RMS reprojection error of centroid and ends over both
    views. (The +d tip goes by index so that no reversed, non-contiguous view of the tips is passed: a new
    array layout would compile a new variant at the first frame that needs it.)"""
    _place(G, c, d, tp, plus_p, tq, plus_q, cp, cq, out, 0)


def warm_up() -> None:
    """Compile both kernels on a tiny biplane geometry."""
    from appliance.geometry_kernels import pack_view, pack_views

    K = np.array([[1000.0, 0.0, 256.0], [0.0, 1000.0, 256.0], [0.0, 0.0, 1.0]])
    turn = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    views = [pack_view(K, np.linalg.inv(K), R, np.array([0.0, 0.0, 500.0]), np.zeros(5)) for R in (np.eye(3), turn)]
    G = pack_views(views[0], views[1], np.ones((3, 3)) / 3.0, 500.0)
    c = np.array([256.0, 256.0])
    axis = np.array([1.0, 0.0])
    tips = np.array([[266.0, 256.0], [246.0, 256.0]])
    out = np.empty(OUT_SIZE)
    weighted_front(G, c, axis, tips, c, axis, tips, 10.0, 1.0, 0.01, -1, 10.0, 1.0, math.nan, 0, 0.0, 0.0, 1.0, True,
                   3.0, 4.0, 12.0, 1.3, 0.001, 0.7, 0.25, out)
    place_tips(G, np.zeros(3), np.array([1.0, 0.0, 0.0]), tips, 0, tips, 1, c, c, np.empty(TIPS_SIZE))


register_warm_up(__name__)
