"""The compiled arithmetic of :func:`.body_prior.place_body`: the body's axial evidence, its combination,
the consistency checks and the placed centroid and tips, in one kernel call (:func:`place`).

The body prior runs on every ok posture, the steady state's plain frames included (issue 8): as Python
(a dozen rays, sigmas and small lists per frame) it cost ~45 us a plain frame, most of a steady pair's
Python. The method and its constants are :mod:`.body_prior`'s (its module docstring says why); this
module holds only the numbers, in the order the Python it replaced computed them (``x ** 2`` as
``x * x``, ``x ** 6`` as libm's ``pow``, Python's ``sum`` as a left-to-right sum). Both the general
path and the plain frames place the body through it, so the two stay identical to the last bit.
:mod:`.body_prior` keeps what needs Python objects: the postures and the reasons given to the operator.
:func:`end_spread` is :func:`.body_prior.end_clutter`'s pixel work on a view over another structure (its
end's neighbourhood off the body and its 5-95 % range: as numpy masks, a dilation and ``np.percentile``
~120 us an end, on every cluttered frame).

Input (``inp``, float64, the ``IN_*`` offsets): the posture's centroid and direction, per view whether it
was observed, its centroid and tips (pixels, the posture's order), :attr:`.Blob.clutter` and its ends'
:func:`.body_prior.end_clutter`, then the measured length (NaN if unknown), the axis sigma (rad),
``settings.max_clutter``, whether the head is identified and how far a view heavier than the body may have
moved the moment centroid along the axis (mm, :func:`.body_mass.centroid_slide_mm`; 0 on the plain frames,
which are not weighed). ``body`` (float64): the body's ``B_*`` numbers.
Output (``out``, the ``OUT_*`` offsets).
"""
from __future__ import annotations

import math

import numpy as np

from appliance.compiled import kernel, register_warm_up
from appliance.geometry_kernels import _K, _SRC, VIEW_SIZE
from appliance.recognition.reconstruction_kernels import _plane_normal, _ray_line_b

# The method's constants (see :mod:`.body_prior`'s docstring for the method).
#: Noise (px along the image axis, on a clean view seen side-on) of the moment centroid and of a flat
#: end's half-height crossing, and of a cone's apex (plus this fraction of the cone's image length: its
#: ramp is extrapolated to the apex). Measured on the accuracy benchmark's clean frames (dev seeds 1-12,
#: robots 1-7): tails 0.1-0.3 px RMS, apexes 0.4-1.2 px with heavy tails, 3D centroids 0.02-0.05 mm.
CENTROID_SIGMA_PX = 0.2
FLAT_END_SIGMA_PX = 0.2
APEX_SIGMA_PX = 0.3
APEX_SIGMA_PER_CONE_PX = 0.01
#: An end face seen obliquely blurs its crossing by the rim: this fraction of the body's image width
#: times cos^6 of the ray-axis angle (negligible until the view is nearly end-on; measured: tails
#: 0.15-0.3 px RMS below cos 0.85, 0.4-1.8 px above).
RIM_FRACTION = 0.1
RIM_POWER = 6
#: Over another structure, a sigma grows by this much per (clutter / max_clutter)^2: the centroid by its
#: frame's worst view, an end by its own view's clutter, and (views over another structure) by this
#: much per end_clutter / max_clutter more. On the dev seeds a cluttered view's tail was 0.2-0.4 mm off
#: where the end's neighbourhood looked clean (the interpolated background slopes along the body), so
#: the view's clutter counts for its ends too.
CENTROID_CLUTTER_GAIN = 4.0
VIEW_CLUTTER_GAIN = 4.0
END_CLUTTER_GAIN = 4.0
#: On a frame over another structure (a view's clutter above max_clutter), a flat tail's inflation above its
#: clean sigma is this fraction of the gains' (the apexes' and the centroid's stay). Measured on dev seeds
#: 1-20 (robots 1, 2, 3, 5, 7, head right): there the gains made the tails' errors 0.18 of their sigma (RMS)
#: and the moment centroid's 0.47, so the centroid, sliding with the background under the whole body
#: (0.15 mm RMS, robot 3 0.2-0.5 mm), outweighed tails that stayed put (0.14 mm RMS).
CLUTTERED_TAIL_INFLATION = 0.3
#: An apex estimate joins only if it lies within this many sigmas of the centroid's and tails' mean: the
#: apex's errors have heavy tails (a faint cone lost to noise or run on into a vessel: 1-3 mm).
APEX_GATE_SIGMAS = 3.0
#: Where the body is placed, the centroid and the tails are inconsistent beyond this many sigmas (per degree
#: of freedom, chi-square) of a clean frame's noise (the sigmas without the clutter terms; with them, a
#: frame just under ``max_clutter`` whose moment centroid slid 0.8 mm passed as clean: dev seed 14, robot
#: 6). On the dev seeds' frames not flagged otherwise it flagged 3 of 611, 2 of them > 0.15 mm off. The
#: measured length is no such sign there: an apex off alone (flagged by it in 1 of 30 frames of robots 1
#: and 5) is not used, and the frame is placed well.
CORE_SIGMAS = 4.0
#: Where the measured tips are kept (head not identified, order undecided), their length is implausible
#: beyond this many sigmas of a clean frame's noise: an end is off (the apex measured as a flat end falls
#: short by ~0.7 of the cone).
LENGTH_SIGMAS = 4.0
#: The ends' order is taken from the body's offset where one order fits the ends better by this much
#: (chi-square), with the head not identified.
ORDER_CHI2 = 25.0
#: With the order undecided, the body is placed where both orders put it where they agree within this many of
#: a clean moment centroid's sigmas (``_E_CORE_C``), and at the moment centroid otherwise.
ORDER_AGREE_SIGMAS = 2.0
#: Noise (px, across the image axis) of where a view's 2D axis line passes its centroid: the moment
#: centroid's (:data:`CENTROID_SIGMA_PX`), which the line goes through.
AXIS_LINE_SIGMA_PX = CENTROID_SIGMA_PX
#: The axis planes move the centroid fully where the 3D axis is known to this (its sigma, rad), and by
#: ``(AXIS_PLANES_FULL_SIGMA_RAD / sigma)^2`` of their shift beyond it: on a far more uncertain axis (a view
#: nearly end-on) a view's plane is as uncertain as its 2D axis, and the planes' line moved such centroids as
#: often away from the truth as towards it (robot 7 seed 14 pose 7, axis 11 deg uncertain: 0.24 -> 0.55 mm
#: moved fully, 0.18 at this weight). Measured on dev seeds 1-20 (all robots, cold and tracked, 4901 frames
#: placed by the general path, ``benchmarks/axis_planes_study.py``): where the sigma was 2.5-4 deg (125
#: frames, over another structure: one view's moment centroid slid along its axis) the planes took the
#: centroid RMS from 0.162 to 0.143 mm; at 4-10 deg (83) 0.126 -> 0.124; above 10 deg (234) moved fully
#: 0.068 -> 0.077, at this weight 0.066. The earlier hard cut-off at 2.5 deg (then
#: ``settings.max_axis_sigma_deg``'s default) left 11 robot-seed runs above 0.1 mm centroid RMS there, this 9.
AXIS_PLANES_FULL_SIGMA_RAD = math.radians(4.0)
#: Each view's axis plane turns about its ray through the moment centroid (its 2D axis line turns about the
#: image centroid) by this times the 3D axis' sigma (one sigma): at a point ``r`` mm from that ray, in the
#: plane, its offset is uncertain by ``r`` times that angle as well as by :data:`AXIS_LINE_SIGMA_PX`. Where
#: the planes nearly coincide (an axis near an epipolar plane) their line lies far from the centroid along
#: their weak direction, and there the turn, not the pixel noise, is what is uncertain (:func:`_planes_shift`).
#: Measured on dev seeds 1-13 (cold, ``benchmarks/axis_planes_study.py``: each plane's normal against the
#: true axis plane's): where the planes meet within 4-8 deg (78-200 frames) the planes turn by 0.04-0.08 of
#: the axis sigma (RMS; 95 % within 0.10-0.14): there the axis sigma is the direction within the planes,
#: which the tips fix, not the planes' own turn (all frames: 0.26-0.97 of it, RMS per sigma bin).
AXIS_PLANE_TURN_PER_AXIS_SIGMA = 0.1

# ``inp``: centroid (3), direction (3), then per view IN_VIEW_SIZE numbers from IN_VIEW, then the tail.
IN_CENTROID = 0
IN_DIRECTION = 3
IN_VIEW = 6
V_PRESENT, V_CENTROID, V_TIPS, V_CLUTTER, V_ENDS = 0, 1, 3, 7, 8
IN_VIEW_SIZE = 10
IN_MEASURED = IN_VIEW + 2 * IN_VIEW_SIZE
IN_AXIS_SIGMA = IN_MEASURED + 1
IN_MAX_CLUTTER = IN_MEASURED + 2
IN_HEAD_IDENTIFIED = IN_MEASURED + 3
#: How far (mm, one sigma) a view's merged structure may have moved the moment centroid along the axis (0: no
#: view heavier than the body; :func:`.body_mass.centroid_slide_mm`), added to its sigmas in quadrature.
IN_CENTROID_SLIDE = IN_MEASURED + 4
IN_SIZE = IN_MEASURED + 5

# ``body``: the robot's length, centroid from the tail face, cone length, diameter.
B_LENGTH, B_CENTROID_FROM_TAIL, B_CONE, B_DIAMETER = 0, 1, 2, 3
B_SIZE = 4

# ``out``: the placed centroid and tips (head first under the posture's order; valid where OUT_PLACED is
# 1: otherwise the measured ones are kept), the flag (FLAG_*), for the disagreement the estimate at odds
# (-1: the moment centroid, 0 / 1: view p's / q's tail) and how far it puts the body from the rest (mm),
# for the length check the ends' noise (mm).
OUT_CENTROID = 0
OUT_TIPS = 3
OUT_PLACED = 9
OUT_FLAG = 10
OUT_WHAT = 11
OUT_OFF = 12
OUT_NOISE = 13
OUT_SIZE = 14
FLAG_NONE, FLAG_DISAGREEMENT, FLAG_LENGTH = 0, 1, 2

# One hypothesis' evidence (scratch rows of :func:`place`): counts, the ends' clean sigmas, then the core
# estimates (the moment centroid, then each view's tail: b, sigma, clean sigma, which) and the apexes.
_E_CORE_N, _E_APEX_N, _E_SIGMA_HEAD, _E_SIGMA_TAIL = 0, 1, 2, 3
_E_CORE_B, _E_CORE_S, _E_CORE_C, _E_CORE_WHAT = 4, 7, 10, 13
_E_APEX_B, _E_APEX_S = 16, 18
_E_SIZE = 20


@kernel
def _end_sigma_mm(head: bool, cone: float, diameter: float, mm_per_px: float, sine: float,
                  inflation: float) -> float:
    """One view's end: its crossing's noise (px), the rim's, along the 3D axis (/ sine), inflated."""
    cosine = math.sqrt(max(1.0 - sine * sine, 0.0))
    rim = RIM_FRACTION * (diameter / mm_per_px) * math.pow(cosine, float(RIM_POWER))
    if head and cone > 0:
        base = APEX_SIGMA_PX + APEX_SIGMA_PER_CONE_PX * cone / mm_per_px
    else:
        base = FLAT_END_SIGMA_PX
    return (base + rim) * mm_per_px / max(sine, 1e-3) * inflation


@kernel
def flat_tail_of(body: np.ndarray) -> bool:
    """Whether the body's tail is a flat end whose crossing places it: a cylinder at least as long as the
    diameter (robot 4's, 0.6 mm on a 1.5 mm diameter, is not: its measured ends are kept unless their length is
    off the body's, :func:`place`)."""
    return body[B_LENGTH] - body[B_CONE] >= body[B_DIAMETER]


@kernel
def _evidence(G: np.ndarray, inp: np.ndarray, body: np.ndarray, head_end: int, e: np.ndarray) -> None:
    """The axial evidence under ``head_end`` (which of the posture's tips is the head) into the row ``e``
    (:func:`.body_prior.axial_evidence` of the method's description)."""
    c = inp[IN_CENTROID:IN_CENTROID + 3]
    u = inp[IN_DIRECTION:IN_DIRECTION + 3]
    length, cft = body[B_LENGTH], body[B_CENTROID_FROM_TAIL]
    cone, diameter, max_clutter = body[B_CONE], body[B_DIAMETER], inp[IN_MAX_CLUTTER]
    axis_sigma = inp[IN_AXIS_SIGMA]
    to_head = length - cft
    sign = 1.0 if head_end == 0 else -1.0   # +1: the posture's direction points from the tail to the head
    flat_tail = length - cone >= diameter
    weight_head = 0.0
    weight_tail = 0.0
    sin2_sum, mm_sum, views = 0.0, 0.0, 0
    worst = 0.0
    # (a frame over another structure: the tails' inflation is scaled, CLUTTERED_TAIL_INFLATION)
    cluttered = False
    for view in range(2):
        i = IN_VIEW + view * IN_VIEW_SIZE
        if inp[i + V_PRESENT] != 0.0 and inp[i + V_CLUTTER] > max_clutter:
            cluttered = True
    n_core, n_apex = 1, 0   # the moment centroid's slot first
    for view in range(2):
        i = IN_VIEW + view * IN_VIEW_SIZE
        if inp[i + V_PRESENT] == 0.0:
            continue
        o = view * VIEW_SIZE
        _, sin2 = _ray_line_b(G, o, inp[i + V_CENTROID], inp[i + V_CENTROID + 1], c, u)
        sine_c = math.sqrt(sin2)
        w0, w1, w2 = G[o + _SRC] - c[0], G[o + _SRC + 1] - c[1], G[o + _SRC + 2] - c[2]
        mm_per_px = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2) / G[o + _K]
        sin2_sum += sine_c * sine_c
        mm_sum += mm_per_px
        views += 1
        level = inp[i + V_CLUTTER]
        worst = max(worst, level)
        ratio = level / max_clutter
        view_gain = 1.0 + VIEW_CLUTTER_GAIN * (ratio * ratio)
        for end in range(2):
            b, sin2 = _ray_line_b(G, o, inp[i + V_TIPS + 2 * end], inp[i + V_TIPS + 2 * end + 1], c, u)
            sine = math.sqrt(sin2)
            head = end == head_end
            local = inp[i + V_ENDS + end]
            inflation = view_gain + (END_CLUTTER_GAIN * local / max_clutter if math.isfinite(local) else 1e6)
            if cluttered and not head:
                inflation = 1.0 + CLUTTERED_TAIL_INFLATION * (inflation - 1.0)
            tilt = abs(b) * axis_sigma * math.sqrt(max(1.0 - sine * sine, 0.0)) / max(sine, 1e-3)
            sigma = math.hypot(_end_sigma_mm(head, cone, diameter, mm_per_px, sine, inflation), tilt)
            clean = math.hypot(_end_sigma_mm(head, cone, diameter, mm_per_px, sine, 1.0), tilt)
            if head:
                weight_head += 1.0 / (clean * clean)
                e[_E_APEX_B + n_apex] = b - sign * to_head
                e[_E_APEX_S + n_apex] = sigma
                n_apex += 1
            else:
                weight_tail += 1.0 / (clean * clean)
                if flat_tail:
                    e[_E_CORE_B + n_core] = b + sign * cft
                    e[_E_CORE_S + n_core] = sigma
                    e[_E_CORE_C + n_core] = clean
                    e[_E_CORE_WHAT + n_core] = view
                    n_core += 1
    if views:
        clean_c = CENTROID_SIGMA_PX * (mm_sum / views) / math.sqrt(max(sin2_sum, 1e-6))
        ratio = worst / max_clutter
        e[_E_CORE_B] = 0.0
        e[_E_CORE_S] = clean_c * (1.0 + CENTROID_CLUTTER_GAIN * (ratio * ratio))
        e[_E_CORE_C] = clean_c
        slide = inp[IN_CENTROID_SLIDE]
        if slide > 0.0:
            # (known, the slide is part of a clean frame's noise too: the tails' disagreement with it is expected)
            e[_E_CORE_S] = math.hypot(e[_E_CORE_S], slide)
            e[_E_CORE_C] = math.hypot(clean_c, slide)
        e[_E_CORE_WHAT] = -1.0
    else:
        n_core = 0   # no view, no estimate (and no tail either)
    e[_E_CORE_N] = n_core
    e[_E_APEX_N] = n_apex
    e[_E_SIGMA_HEAD] = 1.0 / math.sqrt(weight_head) if weight_head > 0 else math.inf
    e[_E_SIGMA_TAIL] = 1.0 / math.sqrt(weight_tail) if weight_tail > 0 else math.inf


@kernel
def _core_mean(e: np.ndarray, n: int, sigmas: int) -> tuple[float, float]:
    """The inverse-variance mean of the ``n`` core estimates (``e[_E_CORE_B:]``) with the sigmas at
    ``e[sigmas:]`` (the frame's, or a clean frame's): ``(mean, sum of the weights)``."""
    total = 0.0
    for i in range(n):
        s = e[sigmas + i]
        total += 1.0 / (s * s)
    num = 0.0
    for i in range(n):
        s = e[sigmas + i]
        num += 1.0 / (s * s) * e[_E_CORE_B + i]
    return num / total, total


@kernel
def _combine(e: np.ndarray) -> tuple[float, float]:
    """The inverse-variance mean of the core estimates and the apexes consistent with it (within
    ``APEX_GATE_SIGMAS``): ``(b, chi-square)``.

    Independent Gaussian measurements of one number: their inverse-variance mean is the
    maximum-likelihood one, and its variance the smallest of any linear combination. The apexes are
    gated because their errors are not Gaussian (a cone's faint apex lost or run on into a vessel)."""
    n_core, n_apex = int(e[_E_CORE_N]), int(e[_E_APEX_N])
    b, total = _core_mean(e, n_core, _E_CORE_S)
    gated = np.zeros(2, dtype=np.bool_)
    for j in range(n_apex):
        s = e[_E_APEX_S + j]
        gated[j] = abs(e[_E_APEX_B + j] - b) <= APEX_GATE_SIGMAS * math.sqrt(s * s + 1.0 / total)
    total = 0.0
    num = 0.0
    for i in range(n_core):
        s = e[_E_CORE_S + i]
        total += 1.0 / (s * s)
    for j in range(n_apex):
        if gated[j]:
            s = e[_E_APEX_S + j]
            total += 1.0 / (s * s)
    for i in range(n_core):
        s = e[_E_CORE_S + i]
        num += 1.0 / (s * s) * e[_E_CORE_B + i]
    for j in range(n_apex):
        if gated[j]:
            s = e[_E_APEX_S + j]
            num += 1.0 / (s * s) * e[_E_APEX_B + j]
    b = num / total
    chi2 = 0.0
    for i in range(n_core):
        s = e[_E_CORE_S + i]
        d = e[_E_CORE_B + i] - b
        chi2 += 1.0 / (s * s) * (d * d)
    for j in range(n_apex):
        if gated[j]:
            s = e[_E_APEX_S + j]
            d = e[_E_APEX_B + j] - b
            chi2 += 1.0 / (s * s) * (d * d)
    return b, chi2


@kernel
def _disagreement(e: np.ndarray) -> tuple[float, int, int, float]:
    """How far the core estimates disagree by a clean frame's noise: the chi-square of their inverse-variance
    mean with the clean sigmas, its degrees of freedom, which estimate is most at odds with it (``OUT_WHAT``'s
    code) and how far (mm) it puts the body from where the others do."""
    n = int(e[_E_CORE_N])
    b, total = _core_mean(e, n, _E_CORE_C)
    chi2 = 0.0
    k, worst = 0, -math.inf
    for i in range(n):
        s = e[_E_CORE_C + i]
        d = e[_E_CORE_B + i] - b
        term = 1.0 / (s * s) * (d * d)
        chi2 += term
        if term > worst:   # the first of equal terms, as Python's max
            k, worst = i, term
    s = e[_E_CORE_C + k]
    wk = 1.0 / (s * s)
    others = total - wk
    rest = (b * total - wk * e[_E_CORE_B + k]) / others if others > 0 else b
    return chi2, n - 1, int(e[_E_CORE_WHAT + k]), e[_E_CORE_B + k] - rest


@kernel
def _onto_axis_planes(G: np.ndarray, inp: np.ndarray, centroid_sigma: float, c: np.ndarray) -> None:
    """:func:`_onto_planes_turned` with the planes' turn :data:`AXIS_PLANE_TURN_PER_AXIS_SIGMA` of the axis sigma."""
    _onto_planes_turned(G, inp, centroid_sigma, AXIS_PLANE_TURN_PER_AXIS_SIGMA, c)


@kernel
def _onto_planes_turned(G: np.ndarray, inp: np.ndarray, centroid_sigma: float, turn_per_sigma: float,
                        c: np.ndarray) -> None:
    """The posture's centroid moved, across its axis, onto the line where the views' axis planes meet, into
    ``c`` (3).

    Each view's 2D axis line goes through its moment centroid and back-projects to a plane holding the 3D
    axis; the triangulated centroid lies on both only where the two image centroids are images of one
    point. Where one of them slid along its image axis (over another structure: the background under the
    body slopes along it), the optimal correction shares that slide between the views and the point
    leaves the axis, across it as well as along it (dev seeds: 0.1-0.25 mm across on robot 3 over the
    vessel, where the planes' line was within 0.01-0.05 mm of the truth). Along the axis the body's
    evidence places it (:func:`place`); across it, the shift ``delta`` (perpendicular to the direction) is
    the least-squares one that puts the point in both planes, each plane's offset weighted by
    :data:`AXIS_LINE_SIGMA_PX` of its view and by how far the planes' turn moves it
    (``turn_per_sigma`` of the axis sigma), with ``|delta|`` held to the moment centroid's own sigma
    (``centroid_sigma``, mm; :func:`_planes_shift`): where the planes nearly coincide (an axis near an
    epipolar plane) the component they leave open stays where the triangulation put it. Less of the shift
    where the axis is uncertain (:data:`AXIS_PLANES_FULL_SIGMA_RAD`)."""
    u = inp[IN_DIRECTION:IN_DIRECTION + 3]
    for i in range(3):
        c[i] = inp[IN_CENTROID + i]
    # An orthonormal basis (a, w) of the plane across the axis.
    if abs(u[0]) < 0.9:
        a0, a1, a2 = 0.0, u[2], -u[1]
    else:
        a0, a1, a2 = -u[2], 0.0, u[0]
    na = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    axis_sigma = inp[IN_AXIS_SIGMA]
    if not na > 0 or not centroid_sigma > 0 or not axis_sigma >= 0.0:
        return
    share = 1.0 if axis_sigma <= AXIS_PLANES_FULL_SIGMA_RAD else (AXIS_PLANES_FULL_SIGMA_RAD / axis_sigma) ** 2
    a0, a1, a2 = a0 / na, a1 / na, a2 / na
    w0, w1, w2 = u[1] * a2 - u[2] * a1, u[2] * a0 - u[0] * a2, u[0] * a1 - u[1] * a0
    prior = 1.0 / (centroid_sigma * centroid_sigma)
    # Per plane: its weight, its normal's and its in-plane lever's components along (a, w).
    planes = np.zeros((2, 5))
    m00, m01, m11, r0, r1 = 0.0, 0.0, 0.0, 0.0, 0.0
    normal = np.empty(2 * 3)
    axis2 = np.empty(2)
    centre2 = np.empty(2)
    for view in range(2):
        i = IN_VIEW + view * IN_VIEW_SIZE
        if inp[i + V_PRESENT] == 0.0:
            continue
        o = view * VIEW_SIZE
        du = inp[i + V_TIPS] - inp[i + V_TIPS + 2]
        dv = inp[i + V_TIPS + 1] - inp[i + V_TIPS + 3]
        span = math.sqrt(du * du + dv * dv)
        if not span > 0:
            continue
        axis2[0], axis2[1] = du / span, dv / span
        centre2[0], centre2[1] = inp[i + V_CENTROID], inp[i + V_CENTROID + 1]
        n = normal[3 * view:3 * view + 3]
        if not _plane_normal(G, o, centre2, axis2, 0.25 * span * span, 0.0, n):
            continue
        s0, s1, s2 = G[o + _SRC], G[o + _SRC + 1], G[o + _SRC + 2]
        offset = n[0] * (s0 - c[0]) + n[1] * (s1 - c[1]) + n[2] * (s2 - c[2])   # the plane's, from the point
        x0, x1, x2 = s0 - c[0], s1 - c[1], s2 - c[2]
        z = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
        sigma = AXIS_LINE_SIGMA_PX * z / G[o + _K]
        weight = 1.0 / (sigma * sigma)
        pa = n[0] * a0 + n[1] * a1 + n[2] * a2
        pw = n[0] * w0 + n[1] * w1 + n[2] * w2
        # The lever's direction: in the plane, across the ray (n x ray; the point is on the ray to its offset).
        l0, l1, l2 = n[1] * x2 - n[2] * x1, n[2] * x0 - n[0] * x2, n[0] * x1 - n[1] * x0
        nl = math.sqrt(l0 * l0 + l1 * l1 + l2 * l2)
        if nl > 0:
            planes[view, 3] = (l0 * a0 + l1 * a1 + l2 * a2) / nl
            planes[view, 4] = (l0 * w0 + l1 * w1 + l2 * w2) / nl
        planes[view, 0], planes[view, 1], planes[view, 2] = weight, pa, pw
        m00 += weight * pa * pa
        m01 += weight * pa * pw
        m11 += weight * pw * pw
        r0 += weight * pa * offset
        r1 += weight * pw * offset
    da, dw = _planes_shift(m00, m01, m11, r0, r1, prior, planes, turn_per_sigma * axis_sigma)
    c[0] += share * (da * a0 + dw * w0)
    c[1] += share * (da * a1 + dw * w1)
    c[2] += share * (da * a2 + dw * w2)


@kernel
def _planes_shift(m00: float, m01: float, m11: float, r0: float, r1: float, prior: float, planes: np.ndarray,
                  turn_sigma: float) -> tuple[float, float]:
    """The shift ``(da, dw)`` across the axis (:func:`_onto_axis_planes`' basis): the planes' least-squares point
    (normal equations ``m``, ``r``, without the prior) fused with the centroid's prior ``prior`` (1 / mm^2, about
    the triangulated point), in the planes' eigen-directions.

    Each coordinate of the planes' point is as uncertain as its normal equations say (the offsets' pixel noise)
    and, as well, as the planes' turns (``turn_sigma``, rad, each plane about its centroid ray) move it there:
    a plane turned by ``phi`` is off by ``phi`` times the point's lever (``planes[:, 3:5]``, its in-plane
    distance from the ray). Where the planes nearly coincide, their weak direction's coordinate is
    ``offset difference / sin(angle)`` and errs by about its own size times ``turn / angle``: the turns, not the
    pixels, limit it, and it stays with the triangulation. The weak coordinate is taken first, with the
    levers at the planes' point; the strong one then with the levers at the point so placed (the planes pivot
    near the centroid: their common offset there is not made uncertain by how far away they cross).
    ``planes`` rows: weight (1 / mm^2), the normal's and the lever direction's components along (a, w)."""
    trace = m00 + m11
    root = math.hypot(0.5 * (m00 - m11), m01)
    big, small = 0.5 * trace + root, 0.5 * trace - root
    angle = 0.5 * math.atan2(2.0 * m01, m00 - m11)
    e0, e1 = math.cos(angle), math.sin(angle)   # the strong direction; the weak one is (-e1, e0)
    strong = (e0 * r0 + e1 * r1) / big if big > 0 else 0.0
    weak = (e0 * r1 - e1 * r0) / small if small > 1e-9 * big else 0.0
    pa0, pw0 = strong * e0 - weak * e1, strong * e1 + weak * e0   # the planes' point
    var = 0.0
    for k in range(2):
        lever = planes[k, 3] * pa0 + planes[k, 4] * pw0
        g = (e0 * planes[k, 2] - e1 * planes[k, 1]) * planes[k, 0] * lever
        var += g * g
    info = small / (1.0 + var * turn_sigma * turn_sigma / small) if small > 1e-9 * big else 0.0
    weak = info * weak / (info + prior)
    pa1, pw1 = strong * e0 - weak * e1, strong * e1 + weak * e0
    var = 0.0
    for k in range(2):
        lever = planes[k, 3] * pa1 + planes[k, 4] * pw1
        g = (e0 * planes[k, 1] + e1 * planes[k, 2]) * planes[k, 0] * lever
        var += g * g
    info = big / (1.0 + var * turn_sigma * turn_sigma / big) if big > 0 else 0.0
    strong = info * strong / (info + prior)
    return strong * e0 - weak * e1, strong * e1 + weak * e0


@kernel
def place(G: np.ndarray, inp: np.ndarray, body: np.ndarray, out: np.ndarray) -> None:
    """The body placed on the posture's axis, and the checks' verdict, into ``out`` (see the module
    docstring and :func:`.body_prior.place_body`): the centroid first moved across the axis onto the views'
    axis planes (:func:`_onto_axis_planes`), then along it by the body's evidence."""
    rows = np.empty((2, _E_SIZE))
    _evidence(G, inp, body, 0, rows[0])   # (the moment centroid's sigma)
    inp = inp.copy()
    _onto_axis_planes(G, inp, rows[0, _E_CORE_S] if rows[0, _E_CORE_N] > 0 else 0.0, inp[IN_CENTROID:IN_CENTROID + 3])
    c = inp[IN_CENTROID:IN_CENTROID + 3]
    u = inp[IN_DIRECTION:IN_DIRECTION + 3]
    length, cft = body[B_LENGTH], body[B_CENTROID_FROM_TAIL]
    chosen = 0
    ordered = False   # the order undecided, the tips placed either side of the centroid
    if inp[IN_HEAD_IDENTIFIED] != 0.0:
        _evidence(G, inp, body, 0, rows[0])
        b, _ = _combine(rows[0])
        placed = True
        for i in range(3):
            centroid = c[i] + b * u[i]
            tail = centroid - cft * u[i]
            out[OUT_CENTROID + i] = centroid
            out[OUT_TIPS + i] = tail + length * u[i]
            out[OUT_TIPS + 3 + i] = tail
    else:
        # Each order of the tips is a hypothesis; the ends choose only where one fits decisively better.
        _evidence(G, inp, body, 0, rows[0])
        b0, chi0 = _combine(rows[0])
        _evidence(G, inp, body, 1, rows[1])
        b1, chi1 = _combine(rows[1])
        chosen = 1 if chi1 < chi0 else 0   # a stable sort by chi-square
        b, chi2, other = (b1, chi1, chi0) if chosen == 1 else (b0, chi0, chi1)
        ordered = rows[chosen, _E_CORE_N] > 1
        placed = ordered and other - chi2 >= ORDER_CHI2
        if placed:
            sign = 1.0 if chosen == 0 else -1.0   # +u points to the head under this order
            first = 0 if chosen == 0 else 3   # where the head goes among the tips
            for i in range(3):
                centroid = c[i] + b * u[i]
                tail = centroid - sign * cft * u[i]
                out[OUT_CENTROID + i] = centroid
                out[OUT_TIPS + first + i] = tail + sign * length * u[i]
                out[OUT_TIPS + 3 - first + i] = tail
        elif ordered:
            # Undecided: each tip where it errs least whichever end is the head, the body's half length either
            # side of its place along the axis: within the body's offset asymmetry (L / 2 - centroid_from_tail:
            # robot 7 0.9 mm, robot 3 2.4 mm) of the truth. The measured ends err by 0 and ~0.7 of the cone (an
            # apex measured as a flat end: 2 and 5 mm), or, where the head claim was withheld, by the cone-model
            # tip put at the wrong end as well. The place is where both orders put the body where they agree
            # to a clean moment centroid's noise (:data:`ORDER_AGREE_SIGMAS`: then it does not matter which end
            # is the head; seed 7182818 robot 3 pose 19, the moment centroid over the vessel: 0.71 -> 0.22 mm),
            # otherwise the moment centroid's. (Not the orders weighed by their likelihoods: where a withheld
            # claim left the cone-model tip at one end, its order fits best whether right or not; standing seed
            # 31337 robot 7 pose 6, a wrong claim withheld: 0.03 -> 0.24 mm.)
            along = 0.0
            if abs(b0 - b1) <= ORDER_AGREE_SIGMAS * rows[0, _E_CORE_C]:
                along = 0.5 * (b0 + b1)
            for i in range(3):
                out[OUT_CENTROID + i] = c[i] + along * u[i]
                out[OUT_TIPS + i] = c[i] + (along + 0.5 * length) * u[i]
                out[OUT_TIPS + 3 + i] = c[i] + (along - 0.5 * length) * u[i]
        else:
            out[OUT_CENTROID:OUT_PLACED] = math.nan
    e = rows[chosen]
    out[OUT_PLACED] = 1.0 if placed or ordered else 0.0
    out[OUT_FLAG] = FLAG_NONE
    out[OUT_WHAT] = math.nan
    out[OUT_OFF] = math.nan
    out[OUT_NOISE] = math.nan
    measured = inp[IN_MEASURED]
    if placed:
        # Placed by the centroid and the tails: where they disagree beyond a clean frame's noise, one is off.
        chi2, dof, what, off = _disagreement(e)
        if dof > 0 and chi2 > CORE_SIGMAS ** 2 * dof:
            out[OUT_FLAG] = FLAG_DISAGREEMENT
            out[OUT_WHAT] = what
            out[OUT_OFF] = off
    elif math.isfinite(measured):
        # The order is undecided (the tips placed either side of the centroid, or the measured ones kept): a
        # measured length off the body's beyond the ends' noise means a measured end is off.
        noise = math.hypot(e[_E_SIGMA_HEAD], e[_E_SIGMA_TAIL])
        out[OUT_NOISE] = noise
        if abs(measured - length) > LENGTH_SIGMAS * noise:
            out[OUT_FLAG] = FLAG_LENGTH
            if not ordered and rows[chosen, _E_CORE_N] == 1 and not flat_tail_of(body):
                # A body without a flat tail (robot 4), its measured ends kept and their length off: the apex
                # was measured as a flat end (0.16 and 1.42 mm off, 13 fresh seeds, 9 frames). Its tips go
                # half its length either side of the centroid, as an undecided order's (0.73 mm each); where
                # the length fits, the measured ends stay (0.03-0.16 mm there: the cone model's tip).
                for i in range(3):
                    out[OUT_CENTROID + i] = c[i]
                    out[OUT_TIPS + i] = c[i] + 0.5 * length * u[i]
                    out[OUT_TIPS + 3 + i] = c[i] - 0.5 * length * u[i]
                out[OUT_PLACED] = 1.0


@kernel
def end_spread(a: np.ndarray, ox: int, oy: int, tu: float, tv: float, au: float, av: float, behind: float,
               reach: float, weights: np.ndarray, wx0: int, wy0: int, disk: np.ndarray) -> tuple[float, int]:
    """The pixel work of :func:`.body_prior.end_clutter` for one end: the 5-95 % range of ``a`` (the
    3 x 3-averaged attenuation, its pixel ``[0, 0]`` at image ``(ox, oy)``) over the end's neighbourhood
    off the body, and how many pixels that is.

    The neighbourhood: ``-behind <= gs <= reach`` along the unit axis ``(au, av)`` outward from the tip
    ``(tu, tv)`` and ``|gt| <= reach`` across it, less the body: pixels within the structuring element
    ``disk`` (centred) of a non-zero pixel of ``weights`` (its ``[0, 0]`` at image ``(wx0, wy0)``), which is
    the binary dilation the Python did. The range is ``np.percentile(values, (5, 95))``'s linear method, to
    the bit: ``(n - 1) q`` in float64, the neighbours' float32 difference, the lerp from the nearer side.
    A NaN among the values gives NaN (as numpy's)."""
    rows, cols = a.shape
    h, w = weights.shape
    gy, gx = disk.shape
    ry, rx = gy // 2, gx // 2
    # The element's rows as spans (cv2's ellipse: each row one run of columns, [first, last]).
    first = np.full(gy, gx, dtype=np.int64)
    last = np.full(gy, -1, dtype=np.int64)
    for i in range(gy):
        for j in range(gx):
            if disk[i, j] != 0:
                first[i] = min(first[i], j)
                last[i] = max(last[i], j)
    # Per row of the rectangle grown by the element, the running count of the weights' non-zero pixels
    # (count[r, k]: those left of column k - rx of the rectangle): a span's test is two reads.
    grown_rows, grown_cols = rows + 2 * ry, cols + 2 * rx
    count = np.zeros((grown_rows, grown_cols + 1), dtype=np.int32)
    for r in range(grown_rows):
        wr = oy - ry + r - wy0
        inside_row = 0 <= wr < h
        total = 0
        for k in range(grown_cols):
            wc = ox - rx + k - wx0
            if inside_row and 0 <= wc < w and weights[wr, wc] != 0:
                total += 1
            count[r, k + 1] = total
    values = np.empty(rows * cols, dtype=a.dtype)
    n = 0
    nan = False
    for r in range(rows):
        y = oy + r
        dy = y - tv
        for c in range(cols):
            x = ox + c
            dx = x - tu
            gs = dx * au + dy * av
            gt = abs(-dx * av + dy * au)
            if not (gs >= -behind and gs <= reach and gt <= reach):
                continue
            body = False
            for i in range(gy):
                # image row y + i - ry, columns x + first - rx .. x + last - rx: grown row r + i, columns c + first ..
                if last[i] >= 0 and count[r + i, c + last[i] + 1] - count[r + i, c + first[i]] > 0:
                    body = True
                    break
            if body:
                continue
            v = a[r, c]
            if math.isnan(v):
                nan = True
            values[n] = v
            n += 1
    if n == 0:
        return math.nan, 0
    if nan:
        return math.nan, n
    lo = _linear_quantile(values, n, 0.05)
    hi = _linear_quantile(values, n, 0.95)
    return hi - lo, n


@kernel
def _select(v: np.ndarray, begin: int, end: int, k: int) -> None:
    """Reorder ``v[begin:end]`` so that ``v[k]`` is the value a sort would put there, none after it
    smaller, none before it larger (quickselect, median-of-three pivot; no NaN)."""
    while end - begin > 1:
        mid = (begin + end) // 2
        a, b, c = v[begin], v[mid], v[end - 1]
        pivot = max(min(a, b), min(max(a, b), c))
        i, j = begin, end - 1
        while i <= j:
            while v[i] < pivot:
                i += 1
            while v[j] > pivot:
                j -= 1
            if i <= j:
                v[i], v[j] = v[j], v[i]
                i += 1
                j -= 1
        # now v[begin:j + 1] <= pivot <= v[i:end], and v[j + 1:i] == pivot
        if k <= j:
            end = j + 1
        elif k >= i:
            begin = i
        else:
            return


@kernel
def _linear_quantile(v: np.ndarray, n: int, q: float) -> float:
    """``np.percentile``'s default (linear) quantile ``q`` of the float32 ``v[:n]`` (no NaN), its arithmetic:
    the virtual index ``(n - 1) q``, its neighbours' float32 difference, the lerp from the nearer side.
    Reorders ``v[:n]`` (selection: only the two order statistics, not a sort)."""
    virtual = (n - 1) * q
    if virtual >= n - 1:
        _select(v, 0, n, n - 1)
        return float(v[n - 1])
    below = math.floor(virtual)
    gamma = virtual - below
    k = int(below)
    _select(v, 0, n, k)
    a = v[k]
    b = v[k + 1]
    for i in range(k + 2, n):   # the next order statistic: the smallest of those after the k-th
        b = min(b, v[i])
    d = b - a   # float32, as numpy's ``b - a``
    if gamma >= 0.5:
        return float(b) - float(d) * (1.0 - gamma)
    return float(a) + float(d) * gamma


def warm_up() -> None:
    """Compile the kernel on a tiny biplane geometry, with the head identified and not."""
    from appliance.geometry_kernels import pack_view, pack_views

    K = np.array([[1000.0, 0.0, 256.0], [0.0, 1000.0, 256.0], [0.0, 0.0, 1.0]])
    turn = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    views = [pack_view(K, np.linalg.inv(K), R, np.array([0.0, 0.0, 500.0]), np.zeros(5)) for R in (np.eye(3), turn)]
    G = pack_views(views[0], views[1], np.ones((3, 3)) / 3.0, 500.0)
    inp = np.zeros(IN_SIZE)
    inp[IN_DIRECTION] = 1.0
    for view in range(2):
        i = IN_VIEW + view * IN_VIEW_SIZE
        inp[i:i + 7] = (1.0, 256.0, 256.0, 266.0, 256.0, 246.0, 256.0)
    inp[IN_MEASURED] = 2.0
    inp[IN_MAX_CLUTTER] = 0.1
    body = np.array([2.0, 0.9, 0.5, 0.5])
    out = np.empty(OUT_SIZE)
    for head_identified in (1.0, 0.0):
        inp[IN_HEAD_IDENTIFIED] = head_identified
        place(G, inp, body, out)
    a = np.linspace(0.0, 1.0, 100, dtype=np.float32).reshape(10, 10)
    weights = np.zeros((4, 4), dtype=np.float32)
    weights[1:3, 1:3] = 1.0
    # ``a`` as end_clutter passes it: an interior view of cv2.blur's output (another layout, another signature).
    end_spread(a[1:-1, 1:-1], 1, 1, 5.0, 5.0, 1.0, 0.0, 9.0, 6.0, weights, 0, 0, np.ones((7, 7), dtype=np.uint8))


register_warm_up(__name__)
