"""The tracker's steady-state frame pair as one compiled call: both views' ROI search and the reconstruction's front.

A tracked pair used to be five kernel calls from Python (the prediction's projection, each view's
:func:`.roi_kernels.search_view`, :func:`.reconstruction_kernels.weighted_front`) with the ROIs, the
gate and the features' axis uncertainty computed in Python between them; the calls' argument
handling (30 arguments a view) and the Python between them cost about as much as the pixel work
around it (issue 8). :func:`search_pair` runs the same chain in one call, with the same arithmetic
in the same order (the tests compare every field with the per-view path):

* the predicted centroid and ends projected into both views (:func:`.geometry_kernels.project_segment`),
  moved with the last frame's 2D outline where there is one, and each view's ROI around them
  (:meth:`.segmentation.Roi.around_coordinates`);
* each view's :func:`.roi_kernels.search_view`, and its axis uncertainty with the clutter term
  (:func:`.features.clutter_axis_sigma_rad`);
* :func:`.reconstruction_kernels.weighted_front` on the two views' features.

Every number goes in through one float array (layout ``IN_*``) and comes out through one (``OUT_*``).
Where a view's search is not plainly found (no ROI, nothing near the prediction, a gate test too
close to call, weights summing to nothing) the call says so and the caller takes the per-view path,
which decides exactly as before.
"""
from __future__ import annotations

import math

import numpy as np

from appliance.compiled import kernel, register_warm_up
from appliance.geometry_kernels import VIEW_SIZE, project_point, project_segment
from appliance.recognition import body_kernels, reconstruction_kernels, roi_kernels, view_kernels

#: Status of :func:`search_pair`.
PAIR_FOUND = 0  # both views found; the front's status is at OUT_FRONT_STATUS
PAIR_PER_VIEW = 1  # a view was not plainly found: take the per-view path

#: Layout of the input array. First what changes from frame to frame (``IN_FRAME_SIZE`` numbers, written
#: in one assignment): the prediction (``IN_CENTRE``, ``IN_DIRECTION`` unit or zero, ``IN_HALF`` the half
#: length + 1 mm), the last frame's 3D centroid (the lean pass moves its 2D bodies by its motion), the
#: previous direction and 1 if there is one, then per view (``IN_VIEW + view * IN_VIEW_SIZE``) the numbers
#: of the layout ``V_*``. Then the margin (px) and the reconstruction's settings.
IN_CENTRE = 0
IN_DIRECTION = 3
IN_HALF = 6
IN_LAST_CENTRE = 7
IN_PREVIOUS = 10
IN_VIEW = 14
V_HAS_OUTLINE = 0  # 1 if the last frame's 2D outline is known
V_OUTLINE = 1  # 7: its centroid u, v, ends u0, v0, u1, v1 and the body's half width
V_KNOWN_SIGMA = 8  # the noise sigma to reuse (0: measure it)
V_LEAN = 9  # 1: try the lean pass from the previous pair's output (see lean_view)
V_FY = 10  # the coarse background's factors
V_FX = 11
V_HEIGHT = 12  # the image's shape
V_WIDTH = 13
IN_VIEW_SIZE = 14
IN_FRAME_SIZE = IN_VIEW + 2 * IN_VIEW_SIZE
IN_MARGIN = IN_FRAME_SIZE
IN_FRONT = IN_MARGIN + 1  # the reconstruction's settings, in weighted_front's order
FRONT_SETTINGS = 7  # ambiguity_px ... tip_rim_fraction
#: The plain frame's checks (see _finish): max_clutter, max_length_over_width, min_path_attenuation_per_mm,
#: max_reprojection_px, head_foreshortening, then per view its source (mm) and focal length (px) as
#: plausibility has them.
IN_FINISH = IN_FRONT + FRONT_SETTINGS
FINISH_SETTINGS = 5
IN_SOURCES = IN_FINISH + FINISH_SETTINGS
#: The robot's body for the body prior on a plain frame (see _place_body): 1 if the tracker knows it, then its
#: numbers in :mod:`.body_kernels`' ``B_*`` layout (:attr:`.BodyModel.packed`).
IN_BODY = IN_SOURCES + 8
#: 1 where the previous pair's output (``prev``) is the last frame's and each view may first be searched in
#: the ROI its prediction error allows (see :data:`TIGHT_MARGIN_PX`), 0: the ROI only (written per frame).
IN_TIGHT = IN_BODY + 1 + body_kernels.B_SIZE
IN_SIZE = IN_TIGHT + 1

#: Layout of the output array: per view (``OUT_VIEW + view * OUT_VIEW_SIZE``) search_view's output
#: (``roi_kernels`` layout, ``SEARCH_SIZE`` numbers), then the view's ROI ``x0, y0, x1, y1`` and its
#: axis uncertainty (rad, with the clutter term); then the front's output and status.
OUT_VIEW = 0
SEARCH_SIZE = roi_kernels.OUT_SIZE + 2 * 5
R_ROI = SEARCH_SIZE
R_AXIS_SIGMA = SEARCH_SIZE + 4
R_FOUND_BY = SEARCH_SIZE + 5  # which search found this view: FOUND_BY_ROI, FOUND_BY_LEAN or FOUND_BY_TIGHT
R_EXTENT = SEARCH_SIZE + 6  # 3: the body's (mask's) s range and largest |t| about the centroid, along the axis
R_RESIDUAL = SEARCH_SIZE + 9  # the prediction's error in this view (px): found centroid - predicted
OUT_VIEW_SIZE = SEARCH_SIZE + 10
#: The values of ``R_FOUND_BY``: the ROI, the lean pass (prototype), the tight ROI.
FOUND_BY_ROI, FOUND_BY_LEAN, FOUND_BY_TIGHT = 0.0, 1.0, 2.0
OUT_FRONT = 2 * OUT_VIEW_SIZE
OUT_FRONT_STATUS = OUT_FRONT + reconstruction_kernels.OUT_SIZE
#: The plain frame's posture (see _finish): 1 if plain, then its centroid, direction, tips (head first),
#: length, reprojection (NaN: none) and per view the 2D tips in the same order.
OUT_POSTURE = OUT_FRONT_STATUS + 1
P_PLAIN = 0
P_CENTROID = 1
P_DIRECTION = 4
P_TIPS = 7
P_LENGTH = 13
P_REPROJECTION = 14
P_VIEW_TIPS = 15
POSTURE_SIZE = 23
#: The plain frame's posture placed by the known body (see _place_body): :func:`.body_kernels.place`'s output
#: (its ``OUT_*`` layout; ``OUT_PLACED`` 0 where the body is not known or the frame is not plain).
OUT_BODY = OUT_POSTURE + POSTURE_SIZE
#: The sum of the log table's entries that :func:`_warm_log_table` read (kept so that the compiler keeps its
#: reads; means nothing).
OUT_TABLE_WARMED = OUT_BODY + body_kernels.OUT_SIZE
#: Per view the shape (rows, columns) of the chosen blob's weights and mask, which :func:`search_pair` writes
#: row-major into the first ``rows x columns`` of that view's row of its ``weights_buf`` and ``masks_buf``.
OUT_WINDOW_SHAPES = OUT_TABLE_WARMED + 1
OUT_SIZE = OUT_WINDOW_SHAPES + 4
#: Pixels of a view's weights (and mask) that the buffers hold: a blob with a larger window takes the per-view
#: path (its weights would not fit). The weights' window lies in the ROI; the bench's is ~30 x 60 px.
WINDOW_CAPACITY = 1 << 18


@kernel
def clutter_axis_sigma(clutter, pixel_count, peak, strength, l1, l2):  # pragma: no cover - compiled
    """features.clutter_axis_sigma_rad, the same operations (Python's ``max`` with a NaN first argument)."""
    spread = l1 - l2
    if not clutter > 0.0 or not strength > 0.0 or not spread > 0.0:
        return 0.0
    product = l1 * l2
    floor = 0.0 if 0.0 > product else product  # noqa: FURB136 - Python's max(product, 0.0), NaN included
    worst = clutter * peak * pixel_count * 0.75 * math.sqrt(floor) / (strength * spread)
    return worst / 3.0


@kernel
def _roi(pu, pv, eu0, ev0, eu1, ev1, margin, h, w):  # pragma: no cover - compiled
    """Roi.around_coordinates on the three points: ``(ok, x0, y0, x1, y1)``."""
    if not (math.isfinite(pu) and math.isfinite(eu0) and math.isfinite(eu1) and math.isfinite(pv)
            and math.isfinite(ev0) and math.isfinite(ev1)):
        return False, 0, 0, 0, 0
    # Python's min / max of three floats (finite here): the first extreme in order.
    lo_u = pu
    if eu0 < lo_u:
        lo_u = eu0
    if eu1 < lo_u:
        lo_u = eu1
    hi_u = pu
    if eu0 > hi_u:
        hi_u = eu0
    if eu1 > hi_u:
        hi_u = eu1
    lo_v = pv
    if ev0 < lo_v:
        lo_v = ev0
    if ev1 < lo_v:
        lo_v = ev1
    hi_v = pv
    if ev0 > hi_v:
        hi_v = ev0
    if ev1 > hi_v:
        hi_v = ev1
    x0 = max(0, math.floor(lo_u - margin))
    y0 = max(0, math.floor(lo_v - margin))
    x1 = min(w, math.ceil(hi_u + margin) + 1)
    y1 = min(h, math.ceil(hi_v + margin) + 1)
    if x1 - x0 < 4 or y1 - y0 < 4:
        return False, 0, 0, 0, 0
    return True, x0, y0, x1, y1


# ------------------------------------------------------------------------------------- the log table
#: Entries of the float32 log table per 64-byte cache line.
_TABLE_LINE = 16


@kernel
def _warm_log_table(image, y0, y1, x0, x1, log_table):  # pragma: no cover - compiled
    """Read one entry per cache line of the log table over the gray levels of the ROI ``y0:y1, x0:x1``, in one
    loop of independent loads; returns their sum (for the caller to keep, so the reads stay).

    The attenuation looks every ROI pixel up in the 256 KB log table, and a new frame's copy (``appliance
    bench``'s ``np.copyto``, a grabber's DMA) evicts the table from the core's caches: each lookup of a line
    not yet fetched waits for it, with few other lookups in flight (each pixel's arithmetic fills the
    out-of-order window). Here the lines of the levels the ROI holds (its minimum to its maximum, a pass the
    compiler vectorises) are fetched together first (issue 8: bench robot 1, ~50 us of a ~230 us pair, thread
    CPU after the frame copy; the ROI's own pixels, touched the same way, gained nothing)."""
    lo, hi = 65535, 0
    for y in range(y0, y1):
        row = image[y, x0:x1]
        for x in range(x1 - x0):
            v = int(row[x])
            lo = min(lo, v)
            hi = max(hi, v)
    total = np.float32(0.0)
    for i in range(lo - lo % _TABLE_LINE, min(hi + _TABLE_LINE, log_table.size), _TABLE_LINE):
        total += log_table[i]
    return float(total)


# ------------------------------------------------------------------------------------- the tight ROI
#: The tight ROI (issue 8): where the last frame was the pair's, a view is first searched in the ROI around
#: the same predicted body with this margin (px beyond the body's half width) plus its allowance for the
#: prediction's error, ``2 x`` the last frame's error in that view ``+ 1`` px, where that is narrower than
#: the ROI's (``roi_margin_px``) and the view's noise sigma is not measured this frame (it is measured on
#: the ROI). The refinement's own edge test keeps a body whose support and fill come within 3 px of the
#: tight ROI's edge out; its side baselines (up to ~8 px beside the core) are clamped into the ROI there,
#: as at the ROI's edge. The ROI's pixels are most of the attenuation's and the candidates' work.
TIGHT_MARGIN_PX = 7.0
#: What the tight ROI's body must be, else the view is searched in the ROI as before: its centroid within
#: the allowance + this many px of the prediction ...
TIGHT_GATE_PX = 2.0
#: ... and its pixel count within this fraction of the last frame's (a body cut by the tight ROI, or
#: another blob, is not the robot where predicted).
TIGHT_COUNT_CHANGE = 0.25


@kernel
def _is_as_predicted(view_out, prev, o, pu, pv, allowance):  # pragma: no cover - compiled
    """Whether the tight ROI's body (``view_out``) is the last frame's (``prev[o:]``) where predicted."""
    c = roi_kernels.CENTROID
    if not math.hypot(view_out[c] - pu, view_out[c + 1] - pv) <= allowance + TIGHT_GATE_PX:
        return False
    count, last = view_out[roi_kernels.REFINED + 12], prev[o + roi_kernels.REFINED + 12]
    return abs(count - last) <= TIGHT_COUNT_CHANGE * last


# ------------------------------------------------------------------------------------- the lean pass
#: The lean pass (prototype, ``RecognitionSettings.lean_steady_state``): margin (px) of its capsule around
#: the last frame's body moved by the predicted motion (motion error and rotation between two frames) ...
LEAN_MARGIN_PX = 4.0
#: ... and how far beyond it the smoothed attenuation is computed, along and across the axis (px): the
#: support is 3 px beyond the body and the background's fill 3 px beyond that; the side baselines lie
#: 4 and 6 px beside the body.
LEAN_GROW_ALONG_PX = 7.0
LEAN_GROW_ACROSS_PX = 5.0
#: Its checks, against the last frame's body (else the full ROI search): the background under the body
#: varies by at most this fraction of its contrast (no vessel under it) ...
LEAN_MAX_CLUTTER = 0.08
#: ... the body's length and width change by at most these many px, its pixels and contrast by this fraction.
LEAN_LENGTH_PX = 3.0
LEAN_WIDTH_PX = 1.5
LEAN_CHANGE = 0.15


@kernel
def _capsule_rows(h, w, ox, oy, ax, ay, s0, s1, tmax, x_lo, x_hi):  # pragma: no cover - compiled
    """Per row ``y`` of an ``h x w`` window, the pixels ``[x_lo[y], x_hi[y])`` whose centres have
    ``s = (x - ox) ax + (y - oy) ay`` in ``[s0, s1]`` and ``|t| = |-(x - ox) ay + (y - oy) ax| <= tmax``
    (``ax, ay`` a unit vector). Each slab's bounds are linear in ``y``: multiplications by the two
    reciprocals computed once, no division per row."""
    use_s, use_t = abs(ax) > 1e-9, abs(ay) > 1e-9
    ia = 1.0 / ax if use_s else 0.0
    ib = 1.0 / ay if use_t else 0.0
    for y in range(h):
        dy = y - oy
        lo, hi = 0.0, w - 1.0
        # s slab: ax (x - ox) in [s0 - dy ay, s1 - dy ay]
        a, b = s0 - dy * ay, s1 - dy * ay
        if use_s:
            u0, u1 = ox + a * ia, ox + b * ia
            if u0 > u1:
                u0, u1 = u1, u0
            lo, hi = max(lo, u0), min(hi, u1)
        elif not (a <= 0.0 <= b):
            hi = -1.0
        # t slab: ay (x - ox) in [dy ax - tmax, dy ax + tmax]
        a, b = dy * ax - tmax, dy * ax + tmax
        if use_t:
            u0, u1 = ox + a * ib, ox + b * ib
            if u0 > u1:
                u0, u1 = u1, u0
            lo, hi = max(lo, u0), min(hi, u1)
        elif not (a <= 0.0 <= b):
            hi = -1.0
        if hi < lo:
            x_lo[y], x_hi[y] = 0, 0
        else:
            x_lo[y], x_hi[y] = max(math.ceil(lo), 0), min(math.floor(hi) + 1, w)


@kernel
def _features_tail(out, weights, cap, sigma, levels, head_ramp_ratio, head_min_ramp_px, wx, wy,
                   sums):  # pragma: no cover - compiled
    """The weighted features of ``weights`` (whose origin is image pixel ``wx, wy``; ``sums`` their
    :func:`.view_kernels.moments_and_capped`, see :func:`.view_kernels.features_of_moments`) into ``out``
    (search_view's layout), as :func:`.roi_kernels.search_view` computes them for its chosen blob; False if
    the weights sum to nothing."""
    status, f = view_kernels.features_of_moments(weights, cap, sigma, levels, sums)
    if not status:
        return False
    n = levels.size
    cx, cy, l1, l2, vx, vy = f[0], f[1], f[2], f[3], f[4], f[5]
    R = roi_kernels.REACH
    for k in range(2 * n):
        out[R + k] = f[7 + k]
    ramp_plus = out[R] - out[R + n - 1]
    ramp_minus = out[R + n] - out[R + 2 * n - 1]
    head = -1
    for end in range(2):
        long_ = ramp_plus if end == 0 else ramp_minus
        short = ramp_minus if end == 0 else ramp_plus
        floor_short = 1e-6 if 1e-6 > short else short  # noqa: FURB136 - Python's max(short, 1e-6)
        if long_ >= head_ramp_ratio * floor_short and long_ - short >= head_min_ramp_px:
            head = end
    px, py = cx + wx, cy + wy
    d0 = roi_kernels._tip_distance(out, R, head == 0)
    d1 = roi_kernels._tip_distance(out, R + n, head == 1)
    out[roi_kernels.CENTROID], out[roi_kernels.CENTROID + 1] = px, py
    out[roi_kernels.AXIS], out[roi_kernels.AXIS + 1] = vx, vy
    t = roi_kernels.TIPS
    out[t], out[t + 1] = px + vx * d0, py + vy * d0
    out[t + 2], out[t + 3] = px - vx * d1, py - vy * d1
    out[roi_kernels.EIGENVALUES], out[roi_kernels.EIGENVALUES + 1] = l1, l2
    out[roi_kernels.AXIS_SIGMA] = f[6]
    out[roi_kernels.HEAD] = head
    out[roi_kernels.RAMPS], out[roi_kernels.RAMPS + 1] = ramp_plus, ramp_minus
    return True


@kernel
def _extent(out, o, mask, mx, my):  # pragma: no cover - compiled
    """The body's (``mask``, origin image pixel ``mx, my``) s range and largest |t| about the features'
    centroid along their axis, into ``out[o + R_EXTENT:]`` (what the next frame's lean pass starts from)."""
    cx, cy = out[o + roi_kernels.CENTROID], out[o + roi_kernels.CENTROID + 1]
    vx, vy = out[o + roi_kernels.AXIS], out[o + roi_kernels.AXIS + 1]
    s_lo, s_hi, t_max = np.inf, -np.inf, 0.0
    h, w = mask.shape
    for y in range(h):
        for x in range(w):
            if mask[y, x]:
                dx, dy = (mx + x) - cx, (my + y) - cy
                s_ = dx * vx + dy * vy
                t_ = abs(-dx * vy + dy * vx)
                s_lo, s_hi, t_max = min(s_lo, s_), max(s_hi, s_), max(t_max, t_)
    out[o + R_EXTENT], out[o + R_EXTENT + 1], out[o + R_EXTENT + 2] = s_lo, s_hi, t_max


#: Bytes of the lean pass's workspace (``work``: its window's attenuation, row pass, smoothed attenuation,
#: background, the body's pixel list, mask and support, the capsule's row tables and the interpolation's
#: columns, carved out of one buffer that :class:`.steady_state.SteadyPair` owns and passes every frame, so
#: that a lean view allocates none of them: issue 8). A window needing more (~130 000 px) takes the ROI search.
LEAN_WORK_BYTES = 1 << 22


@kernel
def _carve(at, nbytes):  # pragma: no cover - compiled
    """The workspace offset after ``nbytes`` bytes from ``at``, rounded up to a cache line."""
    end = at + nbytes
    return (end + 63) // 64 * 64


@kernel
def lean_view(image, coarse, fy, fx, log_table, g, prev, po, qu, qv, sigma, p, near_hw, levels, cap_fraction,
              head_ramp_ratio, head_min_ramp_px, gate_px, out, o, work, weights_flat, body_flat):  # pragma: no cover
    """The lean steady-state pass of one view (prototype): the body found again around where the last
    frame's was, without candidates, labelling, the ring median or flood fills.

    The last frame's body (``prev[po:]``, this module's view layout: its axis, extent about its centroid,
    contrast, pixel count, baseline) moved to ``qu, qv`` (its centroid moved by the predicted motion)
    gives a capsule; the attenuation and its 5x5 smoothing are computed on a capsule grown by
    :data:`LEAN_GROW_ALONG_PX` and :data:`LEAN_GROW_ACROSS_PX` only, row by row in one sweep (each row's
    attenuation, its row pass, and the column pass of the row two above). The body is what stands above
    the attenuation beside it (:func:`.view_kernels._side_baseline`) by the refinement's level, inside the
    capsule; its support, the background interpolated under it (:func:`.view_kernels._fill_values`), the
    weights near it and the features follow as in the refinement and :func:`_features_tail`. The baseline
    (the ring median) is the last frame's. Every window-sized array is a part of ``work`` (uint8,
    :data:`LEAN_WORK_BYTES`); the weights and the body's mask are written row-major into ``weights_flat``
    and ``body_flat`` (the caller's buffers). Returns ``(found, rows, columns, x0, y0)``, the weights' shape;
    not found where a check fails (the body reaches the capsule's end or side, its length, width, pixels or
    contrast changed, the background under it varies: a vessel under the body, a body that changed; the
    window does not fit the workspace), and the caller runs the full ROI search. ``out[o:]`` gets
    search_view's layout with the window relative to ``x0, y0``."""
    A, E, Rf = roi_kernels.AXIS, R_EXTENT, roi_kernels.REFINED
    ax, ay = prev[po + A], prev[po + A + 1]
    s_lo, s_hi, t_max = prev[po + E], prev[po + E + 1], prev[po + E + 2]
    last_height, baseline, last_count = prev[po + Rf + 4], prev[po + Rf + 5], prev[po + Rf + 12]
    if not (math.isfinite(ax) and math.isfinite(ay) and math.isfinite(s_lo) and math.isfinite(s_hi)
            and math.isfinite(qu) and math.isfinite(qv) and last_count > 0 and last_height > 0 and sigma > 0):
        return False, 0, 0, 0, 0
    dilate_px, support_sigma, support_fraction = int(p[6]), p[7], p[8]
    smooth_gain, fill_rows, fill_cols = p[9], int(p[10]), int(p[11])
    pad = dilate_px + 1.0
    bs0, bs1, bt = s_lo - LEAN_MARGIN_PX, s_hi + LEAN_MARGIN_PX, t_max + LEAN_MARGIN_PX
    gs_s, gs_t = LEAN_GROW_ALONG_PX, LEAN_GROW_ACROSS_PX
    ga_s, ga_t = gs_s + 3.0, gs_t + 3.0  # 3 >= 2 sqrt(2): the smoothed capsule's 5x5 neighbourhoods lie in it
    H, W = image.shape
    lo_x, hi_x, lo_y, hi_y = np.inf, -np.inf, np.inf, -np.inf
    for k in range(4):
        s_ = bs0 - ga_s if k < 2 else bs1 + ga_s
        t_ = -(bt + ga_t) if k % 2 == 0 else bt + ga_t
        gx, gy = qu + s_ * ax - t_ * ay, qv + s_ * ay + t_ * ax
        lo_x, hi_x, lo_y, hi_y = min(lo_x, gx), max(hi_x, gx), min(lo_y, gy), max(hi_y, gy)
    x0, y0 = math.floor(lo_x), math.floor(lo_y)
    x1, y1 = math.ceil(hi_x) + 1, math.ceil(hi_y) + 1
    if x0 < 0 or y0 < 0 or x1 > W or y1 > H:
        return False, 0, 0, 0, 0  # near the detector's edge: the ROI search knows what to do
    hh, ww = y1 - y0, x1 - x0
    ws = coarse.shape[1]
    n_px = hh * ww
    # The workspace's parts (byte offsets, each on a cache line).
    at_a = 0
    at_tmp = _carve(at_a, 4 * n_px)
    at_smooth = _carve(at_tmp, 4 * n_px)
    at_ys = _carve(at_smooth, 4 * n_px)
    at_xs = _carve(at_ys, 8 * n_px)
    at_rows = _carve(at_xs, 8 * n_px)
    at_cols = _carve(at_rows, 8 * 6 * hh)
    at_wx = _carve(at_cols, 8 * 2 * ww)
    at_row = _carve(at_wx, 4 * ww)
    at_mask = _carve(at_row, 4 * ws)
    at_support = _carve(at_mask, n_px)
    at_marks = _carve(at_support, n_px)
    at_near = _carve(at_marks, 4 * hh * (ww + 1))
    at_fill = _carve(at_near, n_px)
    if _carve(at_fill, view_kernels.FILL_SCRATCH_PER_LINE * max(hh, ww)) > work.size or n_px > weights_flat.size:
        return False, 0, 0, 0, 0
    a = work[at_a:at_a + 4 * n_px].view(np.float32).reshape((hh, ww))
    tmp = work[at_tmp:at_tmp + 4 * n_px].view(np.float32).reshape((hh, ww))
    smooth = work[at_smooth:at_smooth + 4 * n_px].view(np.float32).reshape((hh, ww))
    mys = work[at_ys:at_ys + 8 * n_px].view(np.int64)
    mxs = work[at_xs:at_xs + 8 * n_px].view(np.int64)
    tables = work[at_rows:at_rows + 8 * 6 * hh].view(np.int64).reshape((6, hh))
    xa0, xa1, xs0, xs1, xb0, xb1 = tables[0], tables[1], tables[2], tables[3], tables[4], tables[5]
    columns = work[at_cols:at_cols + 8 * 2 * ww].view(np.int64).reshape((2, ww))
    ix0, ix1 = columns[0], columns[1]
    ucols = work[at_cols:at_cols + 8 * 2 * ww].view(np.uint64).reshape((2, ww))  # (the same, unsigned)
    wxs = work[at_wx:at_wx + 4 * ww].view(np.float32)
    row = work[at_row:at_row + 4 * ws].view(np.float32)
    mask = work[at_mask:at_mask + n_px].reshape((hh, ww))
    ox, oy = qu - x0, qv - y0
    _capsule_rows(hh, ww, ox, oy, ax, ay, bs0 - ga_s, bs1 + ga_s, bt + ga_t, xa0, xa1)
    _capsule_rows(hh, ww, ox, oy, ax, ay, bs0 - gs_s, bs1 + gs_s, bt + gs_t, xs0, xs1)
    _capsule_rows(hh, ww, ox, oy, ax, ay, bs0, bs1, bt, xb0, xb1)
    # The log table's lines over the gray levels of the grown capsule (as _warm_log_table over the ROI, which
    # search_pair leaves to this pass where it asks for it: fewer pixels, the same lines).
    lo_v, hi_v = 65535, 0
    for y in range(hh):
        src = image[y + y0]
        for x in range(xa0[y], xa1[y]):
            v = int(src[x + x0])
            lo_v = min(lo_v, v)
            hi_v = max(hi_v, v)
    total = np.float32(0.0)
    for i in range(lo_v - lo_v % _TABLE_LINE, min(hi_v + _TABLE_LINE, log_table.size), _TABLE_LINE):
        total += log_table[i]
    out[OUT_TABLE_WARMED] += float(total)
    # bilinear_columns' numbers, into the workspace.
    view_kernels.bilinear_columns_into(ww, x0, fx, ws, ix0, ix1, wxs)
    # One sweep down the window: row y's attenuation on the grown capsule (attenuation_from_coarse's arithmetic,
    # pixel for pixel) and its row pass of the 5x5 Gaussian, then the column pass of row y - 2 on the smoothed
    # capsule (as gaussian5 sums them). (The attenuation and the row pass are not zeroed: every pixel read of
    # them, and of the background below, lies in the capsule or the support where they are written; the
    # smoothed attenuation is read beyond, and zeroed.)
    g0, g1, g2, g3, g4 = g[0], g[1], g[2], g[3], g[4]
    one = np.float32(1.0)
    zero = np.float32(0.0)
    clo, chi = ix0[0], ix1[ww - 1] + 1
    # (The inner loops run on slices with unsigned indices: no negative-index wrap-around per access, which
    # kept the compiler from vectorising them; ~4x faster row and column passes.)
    u1, u2, u3, u4 = np.uint64(1), np.uint64(2), np.uint64(3), np.uint64(4)
    for y in range(hh):
        lo, hi = xa0[y], xa1[y]
        if hi > lo:
            view_kernels.coarse_row_at(coarse, y + y0, fy, clo, chi, row)
            src, arow = image[y + y0, lo + x0:hi + x0], a[y, lo:hi]
            c0s, c1s, wrow = ucols[0, lo:hi], ucols[1, lo:hi], wxs[lo:hi]
            for i in range(np.uint64(hi - lo)):
                bg = row[c0s[i]] * (one - wrow[i]) + row[c1s[i]] * wrow[i]
                arow[i] = bg - log_table[src[i]]
            if hi - lo > 4:
                trow = tmp[y, lo + 2:hi - 2]
                for i in range(np.uint64(hi - lo - 4)):
                    trow[i] = (g0 * arow[i] + g1 * arow[i + u1] + g2 * arow[i + u2] + g3 * arow[i + u3]
                               + g4 * arow[i + u4])
        r = y - 2  # the row whose column pass the rows up to y allow
        if r < 0:
            continue
        srow = smooth[r]
        for x in range(ww):
            srow[x] = zero
        if r < 2 or r >= hh - 2:
            continue
        lo, hi = xs0[r], xs1[r]
        if hi <= lo:
            continue
        r0, r1, r2, r3, r4 = tmp[r - 2, lo:hi], tmp[r - 1, lo:hi], tmp[r, lo:hi], tmp[r + 1, lo:hi], tmp[r + 2, lo:hi]
        srow = smooth[r, lo:hi]
        for i in range(np.uint64(hi - lo)):
            srow[i] = g0 * r0[i] + g1 * r1[i] + g2 * r2[i] + g3 * r3[i] + g4 * r4[i]
    for r in range(max(hh - 2, 0), hh):
        srow = smooth[r]
        for x in range(ww):
            srow[x] = zero
    # The body: above the attenuation beside it by the refinement's level, inside the capsule.
    peak = -np.inf
    for y in range(hh):
        srow = smooth[y]
        for x in range(xb0[y], xb1[y]):
            peak = max(peak, float(srow[x]))
    height = peak - baseline
    if not (abs(height - last_height) <= LEAN_CHANGE * last_height):
        return False, 0, 0, 0, 0
    level = max(support_sigma * sigma * smooth_gain, support_fraction * height)
    lvl32 = np.float32(level)
    nside = math.floor(bs1 - bs0) + 1
    side = view_kernels._side_baseline(smooth, 0, 0, hh, ww, ox, oy, ax, ay, bs0, nside, t_max + pad + 1.0)
    count = 0
    in_lo, in_hi, in_t = np.inf, -np.inf, 0.0
    by0, by1, bx0, bx1 = hh, -1, ww, -1  # the body's bounding box
    for y in range(hh):
        gy = y - oy
        srow, mrow = smooth[y], mask[y]
        for x in range(ww):
            mrow[x] = 0
        for x in range(xb0[y], xb1[y]):
            gx = x - ox
            s_ = gx * ax + gy * ay
            k = min(max(int(s_ - bs0), 0), nside - 1)
            if (srow[x] - side[k]) > lvl32:
                mrow[x] = 1
                mys[count], mxs[count] = y, x
                count += 1
                by0, by1, bx0, bx1 = min(by0, y), max(by1, y), min(bx0, x), max(bx1, x)
                t_ = abs(-gx * ay + gy * ax)
                in_lo, in_hi, in_t = min(in_lo, s_), max(in_hi, s_), max(in_t, t_)
    if count == 0 or abs(count - last_count) > LEAN_CHANGE * last_count:
        return False, 0, 0, 0, 0
    if (in_lo < bs0 + 1.0 or in_hi > bs1 - 1.0 or in_t > bt - 1.0
            or abs((in_hi - in_lo) - (s_hi - s_lo)) > LEAN_LENGTH_PX or abs(in_t - t_max) > LEAN_WIDTH_PX):
        return False, 0, 0, 0, 0
    # The support (a rectangle around the body along its axis) and the background interpolated under it.
    lo_s_, hi_s_, hi_t = in_lo - pad, in_hi + pad, in_t + pad
    gx_lo, gx_hi, gy_lo, gy_hi = np.inf, -np.inf, np.inf, -np.inf
    for k in range(4):
        s_ = lo_s_ if k < 2 else hi_s_
        t_ = -hi_t if k % 2 == 0 else hi_t
        gxk, gyk = s_ * ax - t_ * ay + ox, s_ * ay + t_ * ax + oy
        gx_lo, gx_hi, gy_lo, gy_hi = min(gx_lo, gxk), max(gx_hi, gxk), min(gy_lo, gyk), max(gy_hi, gyk)
    sy0, sy1 = max(math.floor(gy_lo) - 1, 0), min(math.ceil(gy_hi) + 2, hh)
    sx0, sx1 = max(math.floor(gx_lo) - 1, 0), min(math.ceil(gx_hi) + 2, ww)
    sh, sw = max(sy1 - sy0, 0), max(sx1 - sx0, 0)
    support = work[at_support:at_support + sh * sw].reshape((sh, sw))
    # (Branch-free on unsigned indices, the same arithmetic per pixel: the compiler vectorises it.)
    fx0 = float(sx0)
    for y in range(sy0, sy1):
        gy = y - oy
        srow_ = support[y - sy0]
        for i in range(np.uint64(sw)):
            gx = (fx0 + float(i)) - ox
            s_, t_ = gx * ax + gy * ay, -gx * ay + gy * ax
            srow_[i] = np.uint8((s_ >= lo_s_) & (s_ <= hi_s_) & (abs(t_) <= hi_t))
    background = tmp  # (the row pass is done with)
    view_kernels.fill_values_into(smooth, 0, 0, hh, ww, support, sy0, sy1, sx0, sx1, fill_rows, fill_cols,
                                  abs(ax) < abs(ay), background, work[at_fill:])
    # The weights near the body, their window, and how much the background under the body varies.
    # (view_kernels._dilated_box's dilation of the body, from its mask's runs on its bounding box grown by the
    # element's radius, the marks' prefix sums taken in the same pass as the support's test.)
    rad = (near_hw.size - 1) // 2
    ny0, nx0 = max(by0 - rad, 0), max(bx0 - rad, 0)
    nh, nw = min(by1 + rad + 1, hh) - ny0, min(bx1 + rad + 1, ww) - nx0
    marks = work[at_marks:at_marks + 4 * nh * (nw + 1)].view(np.int32).reshape((nh, nw + 1))
    near = work[at_near:at_near + nh * nw].reshape((nh, nw))
    for y in range(nh):
        mrow = marks[y]
        for x in range(nw + 1):
            mrow[x] = 0
    for y in range(nh):
        mrow = mask[ny0 + y]
        x = nx0
        while x < nx0 + nw:
            while x < nx0 + nw and mrow[x] == 0:
                x += 1
            start = x
            while x < nx0 + nw and mrow[x] != 0:
                x += 1
            if start < nx0 + nw:
                view_kernels._mark_run(marks, y, start - nx0, x - nx0, near_hw)
    # Near pixels lie in the support's box: rows outside it are cleared, and in a row the prefix sum up to the
    # box is taken first, then the box's part branch-free (the box's columns on unsigned indices).
    ky0, ky1, kx0, kx1 = hh, -1, ww, -1
    bmin, bmax = np.inf, -np.inf
    qx0, qx1 = max(sx0, nx0), min(sx1, nx0 + nw)  # the near box's columns inside the support's
    for y in range(nh):
        nrow = near[y]
        for x in range(nw):
            nrow[x] = 0
        yy = ny0 + y
        if yy < sy0 or yy >= sy1 or qx1 <= qx0:
            continue
        mrow = marks[y]
        acc = 0
        for x in range(qx0 - nx0):
            acc += mrow[x]
        mseg, nseg = marks[y, qx0 - nx0:qx1 - nx0], near[y, qx0 - nx0:qx1 - nx0]
        sseg, bseg = support[yy - sy0, qx0 - sx0:qx1 - sx0], background[yy, qx0:qx1]
        first, last = -1, -1
        for i in range(np.uint64(qx1 - qx0)):
            acc += mseg[i]
            inside = (acc > 0) & (sseg[i] != 0)
            nseg[i] = np.uint8(inside)
            b = float(bseg[i])
            bmin = min(bmin, b) if inside else bmin
            bmax = max(bmax, b) if inside else bmax
        for i in range(qx1 - qx0 - 1, -1, -1):
            first = i if nseg[i] else first
        for i in range(qx1 - qx0):
            last = i if nseg[i] else last
        if first >= 0:
            ky0, ky1, kx0, kx1 = min(ky0, yy), max(ky1, yy), min(kx0, qx0 + first), max(kx1, qx0 + last)
    if ky1 < 0:
        return False, 0, 0, 0, 0
    clutter = (bmax - bmin) / height
    if not clutter <= LEAN_MAX_CLUTTER:
        return False, 0, 0, 0, 0
    for i in range(count):
        ky0, ky1, kx0, kx1 = min(ky0, mys[i]), max(ky1, mys[i]), min(kx0, mxs[i]), max(kx1, mxs[i])
    ky1 += 1
    kx1 += 1
    wh, wwid = ky1 - ky0, kx1 - kx0
    weights = weights_flat[:wh * wwid].reshape((wh, wwid))
    body = body_flat[:wh * wwid].reshape((wh, wwid))
    # (The weights' window lies in the near box, which holds the body's box and the near pixels: one pass, the
    # weights where near, zero elsewhere.)
    for y in range(wh):
        wrow, brow, mrow = weights[y], body[y], mask[ky0 + y, kx0:kx1]
        nrow = near[ky0 + y - ny0, kx0 - nx0:kx1 - nx0]
        arow, grow = a[ky0 + y, kx0:kx1], background[ky0 + y, kx0:kx1]
        for i in range(np.uint64(wwid)):
            wrow[i] = arow[i] - grow[i] if nrow[i] else zero
            brow[i] = mrow[i]
    cap = cap_fraction * height if cap_fraction < 1.0 else np.inf
    # The weights' moments once, for the refinement's numbers and the features (and the capped ones' with them:
    # moments_and_capped's first six are moments').
    if math.isfinite(cap):
        sums = view_kernels.moments_and_capped(weights, cap)
    else:
        m00, m10, m01, mu20, mu02, mu11 = view_kernels.moments(weights)
        sums = (m00, m10, m01, mu20, mu02, mu11, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    m00, m10, m01, mu20, mu02, mu11 = sums[0], sums[1], sums[2], sums[3], sums[4], sums[5]
    if not m00 > 0.0:
        return False, 0, 0, 0, 0
    _, minor, _, _ = view_kernels._principal(mu20, mu02, mu11, 1)
    sc = (float(ky0), float(ky1), float(kx0), float(kx1), height, baseline, m00, m10 / m00, m01 / m00, 0.0, minor,
          clutter, float(count))
    for i in range(roi_kernels.REFINED_SIZE):
        out[o + Rf + i] = sc[i]
    out[o + roi_kernels.SIGMA] = sigma
    if not _features_tail(out[o:o + SEARCH_SIZE], weights, cap, sigma, levels, head_ramp_ratio, head_min_ramp_px,
                          x0 + kx0, y0 + ky0, sums):
        return False, 0, 0, 0, 0
    if not math.hypot(out[o + roi_kernels.CENTROID] - qu, out[o + roi_kernels.CENTROID + 1] - qv) <= gate_px:
        return False, 0, 0, 0, 0
    return True, wh, wwid, x0, y0


# ------------------------------------------------------------------------------------- the plain frame
@kernel
def _robot_like(out, inp, centre, d, length):  # pragma: no cover - compiled
    """plausibility.not_robot_like finding nothing, in its operations: the length over the mean width, and the
    attenuation per mm of path in the view that sees the axis most side-on."""
    widths = np.empty(2)
    rays = np.empty((2, 4))
    for view in range(2):
        o = OUT_VIEW + view * OUT_VIEW_SIZE
        r = roi_kernels.REFINED
        ratio = out[o + r + 10] / out[o + r + 6]
        width_px = 4.0 * math.sqrt(0.0625 if 0.0625 > ratio else ratio)  # noqa: FURB136 - Python's max(ratio, ...)
        k = IN_SOURCES + 4 * view
        rx, ry, rz = centre[0] - inp[k], centre[1] - inp[k + 1], centre[2] - inp[k + 2]
        distance = math.sqrt(rx * rx + ry * ry + rz * rz)
        rays[view, 0], rays[view, 1], rays[view, 2], rays[view, 3] = rx, ry, rz, distance
        widths[view] = width_px * distance / inp[k + 3]
    width = 0.5 * (widths[0] + widths[1])
    if length > inp[IN_FINISH + 1] * width:
        return False
    side, side_sine = 0, -1.0
    for view in range(2):
        cosine = abs(rays[view, 0] * d[0] + rays[view, 1] * d[1] + rays[view, 2] * d[2]) / rays[view, 3]
        c2 = 1.0 - cosine * cosine
        sine = math.sqrt(c2 if c2 > 0.0 else 0.0)  # Python's max(0.0, c2)
        if sine > side_sine:
            side, side_sine = view, sine
    o = OUT_VIEW + side * OUT_VIEW_SIZE
    sine_floor = 1e-3 if 1e-3 > side_sine else side_sine  # noqa: FURB136 - Python's max(side_sine, 1e-3)
    width_floor = 1e-6 if 1e-6 > widths[side] else widths[side]  # noqa: FURB136
    mu = out[o + roi_kernels.REFINED + 4] * sine_floor / width_floor
    return not mu < inp[IN_FINISH + 2]


@kernel
def _finish(out, inp, G):  # pragma: no cover - compiled
    """The posture of a plain frame into ``out[OUT_POSTURE:]``, as reconstruction.reconstruct_from_front, the
    tracker's checks and plausibility make it, where the frame is plain: the front found no ambiguity and gave
    no reason, neither view's background under the body varies (clutter), no window reaches a detector
    edge, the head is identified by the views' votes, the rod is robot-like and reprojects onto its images.
    Anything else is left to Python (``P_PLAIN`` 0). (The checks that go through Python's ``math.degrees``
    and ``math.hypot``, whose last bits numba's may not match, stay in Python.)"""
    P = OUT_POSTURE
    out[P + P_PLAIN] = 0.0
    f = OUT_FRONT
    R = reconstruction_kernels
    if (out[OUT_FRONT_STATUS] != R.STATUS_OK or out[f + R.OUT_REASON] != R.REASON_NONE
            or out[f + R.OUT_AMBIGUOUS] != 0.0):
        return
    heads = np.empty(2, dtype=np.int64)
    plus = np.empty(2, dtype=np.int64)
    for view in range(2):
        o = OUT_VIEW + view * OUT_VIEW_SIZE
        r = roi_kernels.REFINED
        if out[o + r + 11] > inp[IN_FINISH]:
            return  # cluttered: flagged, declutter and the doubt checks apply
        x0, y0 = out[o + R_ROI], out[o + R_ROI + 1]
        h, w = inp[IN_VIEW + view * IN_VIEW_SIZE + V_HEIGHT], inp[IN_VIEW + view * IN_VIEW_SIZE + V_WIDTH]
        if x0 + out[o + r + 2] <= 0.0 or y0 + out[o + r] <= 0.0 or x0 + out[o + r + 3] >= w or y0 + out[o + r + 1] >= h:
            return  # the window reaches a detector edge: cut_by_edge decides
        heads[view] = int(out[o + roi_kernels.HEAD])
        plus[view] = int(out[f + R.OUT_PLUS + view])
    # The views' votes (how side-on, the head is the +d end), sorted as Python sorts the tuples, reversed.
    n_votes = 0
    sides = np.empty(2)
    says = np.empty(2, dtype=np.bool_)
    for view in range(2):
        if heads[view] >= 0:
            sides[n_votes] = out[f + R.OUT_SIDE + view]
            says[n_votes] = heads[view] == plus[view]
            n_votes += 1
    if n_votes == 0:
        return
    if n_votes == 2 and (sides[1] > sides[0] or (sides[1] == sides[0] and says[1] and not says[0])):
        sides[0], sides[1] = sides[1], sides[0]
        says[0], says[1] = says[1], says[0]
    if n_votes == 2 and says[0] != says[1]:
        if sides[1] < inp[IN_FINISH + 4] * sides[0]:
            n_votes = 1  # the foreshortened view's vote is the weaker evidence
        else:
            return  # the views disagree on the head: a reason
    flipped = not says[0]
    d = np.empty(3)
    for i in range(3):
        d[i] = -out[f + R.OUT_DIRECTION + i] if flipped else out[f + R.OUT_DIRECTION + i]
    if flipped:
        plus[0], plus[1] = 1 - plus[0], 1 - plus[1]
    # Each view's tips with the head at its +d end (Features2D.with_head where the head moves).
    n = 5
    tips = np.empty((2, 2, 2))
    same = True
    for view in range(2):
        o = OUT_VIEW + view * OUT_VIEW_SIZE
        t = roi_kernels.TIPS
        if heads[view] == plus[view]:
            tips[view, 0, 0], tips[view, 0, 1] = out[o + t], out[o + t + 1]
            tips[view, 1, 0], tips[view, 1, 1] = out[o + t + 2], out[o + t + 3]
        else:
            same = False
            c0, c1 = out[o + roi_kernels.CENTROID], out[o + roi_kernels.CENTROID + 1]
            a0, a1 = out[o + roi_kernels.AXIS], out[o + roi_kernels.AXIS + 1]
            d0 = roi_kernels._tip_distance(out, o + roi_kernels.REACH, plus[view] == 0)
            d1 = roi_kernels._tip_distance(out, o + roi_kernels.REACH + n, plus[view] == 1)
            tips[view, 0, 0], tips[view, 0, 1] = c0 + a0 * d0, c1 + a1 * d0
            tips[view, 1, 0], tips[view, 1, 1] = c0 - a0 * d1, c1 - a1 * d1
    centre = out[f + R.OUT_CORRECTED:f + R.OUT_CORRECTED + 3]
    placed = np.empty(R.TIPS_SIZE)
    if same:
        for i in range(R.TIPS_SIZE):
            placed[i] = out[f + R.OUT_PLACED + i]
        if flipped:  # the same ends in the other order
            for i in range(3):
                placed[R.TIPS_POINTS + i], placed[R.TIPS_POINTS + 3 + i] = (placed[R.TIPS_POINTS + 3 + i],
                                                                            placed[R.TIPS_POINTS + i])
    else:
        fp, fq = OUT_VIEW, OUT_VIEW + OUT_VIEW_SIZE
        c = roi_kernels.CENTROID
        R._place(G, centre, d, tips[0], plus[0], tips[1], plus[1], out[fp + c:fp + c + 2], out[fq + c:fq + c + 2],
                 placed, 0)
    length, reprojection = placed[R.TIPS_LENGTH], placed[R.TIPS_REPROJECTION]
    if math.isfinite(reprojection) and reprojection > inp[IN_FINISH + 3]:
        return  # off its images: lost, with a reason
    if not _robot_like(out, inp, centre, d, length):
        return
    for i in range(3):
        out[P + P_CENTROID + i] = centre[i]
        out[P + P_DIRECTION + i] = d[i]
    for i in range(6):
        out[P + P_TIPS + i] = placed[R.TIPS_POINTS + i]
    out[P + P_LENGTH], out[P + P_REPROJECTION] = length, reprojection
    for view in range(2):
        k = P + P_VIEW_TIPS + 4 * view
        first = 0 if plus[view] == 0 else 1
        out[k], out[k + 1] = tips[view, first, 0], tips[view, first, 1]
        out[k + 2], out[k + 3] = tips[view, 1 - first, 0], tips[view, 1 - first, 1]
    out[P + P_PLAIN] = 1.0


@kernel
def _place_body(out, inp, G):  # pragma: no cover - compiled
    """The body prior on a plain frame's posture into ``out[OUT_BODY:]``: :func:`.body_kernels.place` on the
    numbers :func:`.body_prior.place_body` takes of that posture (its centroid and direction, per view its
    centroid, tips and clutter, no end measured (a plain frame has no clutter to measure them for), the
    measured length, the front's axis sigma, ``max_clutter`` and the head identified), where the body is known
    and the frame is plain; in the same call, so a plain frame's Python makes no second call nor its arrays
    (issue 8)."""
    B = body_kernels
    placed = out[OUT_BODY:OUT_BODY + B.OUT_SIZE]
    placed[B.OUT_PLACED] = 0.0
    placed[B.OUT_FLAG] = B.FLAG_NONE
    P = OUT_POSTURE
    if inp[IN_BODY] == 0.0 or out[P + P_PLAIN] != 1.0:
        return
    b = np.empty(B.IN_SIZE)
    for i in range(3):
        b[B.IN_CENTROID + i] = out[P + P_CENTROID + i]
        b[B.IN_DIRECTION + i] = out[P + P_DIRECTION + i]
    for view in range(2):
        i = B.IN_VIEW + view * B.IN_VIEW_SIZE
        o = OUT_VIEW + view * OUT_VIEW_SIZE
        k = P + P_VIEW_TIPS + 4 * view
        b[i + B.V_PRESENT] = 1.0
        c = o + roi_kernels.CENTROID
        b[i + B.V_CENTROID], b[i + B.V_CENTROID + 1] = out[c], out[c + 1]
        for j in range(4):
            b[i + B.V_TIPS + j] = out[k + j]
        b[i + B.V_CLUTTER] = out[o + roi_kernels.REFINED + 11]
        b[i + B.V_ENDS], b[i + B.V_ENDS + 1] = 0.0, 0.0
    b[B.IN_MEASURED] = out[P + P_LENGTH]
    b[B.IN_AXIS_SIGMA] = out[OUT_FRONT + reconstruction_kernels.OUT_SIGMA]
    b[B.IN_MAX_CLUTTER] = inp[IN_FINISH]
    b[B.IN_HEAD_IDENTIFIED] = 1.0
    # (a plain frame is not weighed against the body: the general path's check)
    b[B.IN_CENTROID_SLIDE] = 0.0
    B.place(G, b, inp[IN_BODY + 1:IN_BODY + 1 + B.B_SIZE], placed)


@kernel
def search_pair(image_p, image_q, coarse_p, coarse_q, log_table, g, params, ring_outer, ring_inner, near_hw,
                levels, search_settings, G, inp, prev, weights_buf, masks_buf, work,
                out):  # pragma: no cover - compiled
    """Both views' steady-state search and the reconstruction's front (see the module docstring).

    ``search_settings``: ``[detect_sigma, smooth_gain, floor, min_pixels, max_tries, max_candidates,
    gate_px, axis_saturation, head_ramp_ratio, head_min_ramp_px]`` as roi_search passes them to
    search_view; ``params``, ``ring_*``, ``near_hw``, ``levels`` as search_view takes them; ``G`` the
    packed calibration; ``prev`` the previous pair's output (read where ``V_LEAN`` asks for the lean pass).
    ``weights_buf`` (float32) and ``masks_buf`` (uint8), each ``(2, WINDOW_CAPACITY)``, get each found
    view's weights and mask (their shape at ``OUT_WINDOW_SHAPES``); ``work`` (uint8, :data:`LEAN_WORK_BYTES`) is
    the lean pass's workspace, the same buffer every frame (:func:`lean_view`). Returns the status: the chosen blobs'
    arrays are written, not returned, because each array a kernel returns is a new Python object (about
    8 us for four after a frame's copy, issue 8).
    """
    projected = project_segment(G, inp[IN_CENTRE], inp[IN_CENTRE + 1], inp[IN_CENTRE + 2], inp[IN_DIRECTION],
                                inp[IN_DIRECTION + 1], inp[IN_DIRECTION + 2], inp[IN_HALF])
    detect_sigma, smooth_gain, floor = search_settings[0], search_settings[1], search_settings[2]
    min_pixels, max_tries, max_candidates = int(search_settings[3]), int(search_settings[4]), int(search_settings[5])
    gate_px, axis_saturation = search_settings[6], search_settings[7]
    head_ramp_ratio, head_min_ramp_px = search_settings[8], search_settings[9]
    warmed = 0.0
    for view in range(2):
        v = IN_VIEW + view * IN_VIEW_SIZE
        o = OUT_VIEW + view * OUT_VIEW_SIZE
        pu, pv = projected[view, 0, 0], projected[view, 0, 1]
        eu0, ev0 = projected[view, 1, 0], projected[view, 1, 1]
        eu1, ev1 = projected[view, 2, 0], projected[view, 2, 1]
        margin = inp[IN_MARGIN]
        half_width = 0.0
        if inp[v + V_HAS_OUTLINE] != 0.0:
            # As the tracker: the last frame's 2D ends moved with the predicted image centroid, and the
            # margin counted from the body's edge.
            k = v + V_OUTLINE
            cu, cv, u0, v0, u1, v1, half_width = (inp[k], inp[k + 1], inp[k + 2], inp[k + 3], inp[k + 4],
                                                  inp[k + 5], inp[k + 6])
            du, dv = pu - cu, pv - cv
            eu0, ev0, eu1, ev1 = u0 + du, v0 + dv, u1 + du, v1 + dv
            margin += half_width
        ok, x0, y0, x1, y1 = _roi(pu, pv, eu0, ev0, eu1, ev1, margin, int(inp[v + V_HEIGHT]), int(inp[v + V_WIDTH]))
        if not ok:
            return PAIR_PER_VIEW
        image = image_p if view == 0 else image_q
        coarse = coarse_p if view == 0 else coarse_q
        out[OUT_TABLE_WARMED] = warmed
        view_out = out[o:o + SEARCH_SIZE]
        lean = False
        if inp[v + V_LEAN] != 0.0:
            # The last body moved by its centroid's predicted motion in this view.
            lu, lv = project_point(G, view * VIEW_SIZE, inp[IN_LAST_CENTRE], inp[IN_LAST_CENTRE + 1],
                                   inp[IN_LAST_CENTRE + 2])
            qu = prev[o + roi_kernels.CENTROID] + (pu - lu)
            qv = prev[o + roi_kernels.CENTROID + 1] + (pv - lv)
            lean, lh, lw, lx0, ly0 = lean_view(
                image, coarse, inp[v + V_FY], inp[v + V_FX], log_table, g, prev, o, qu, qv, inp[v + V_KNOWN_SIGMA],
                params, near_hw, levels, axis_saturation, head_ramp_ratio, head_min_ramp_px, gate_px, out, o, work,
                weights_buf[view], masks_buf[view])
            warmed = out[OUT_TABLE_WARMED]  # (the lean pass warms the log table over its capsule)
            if lean:
                x0, y0 = lx0, ly0
        if not lean:
            warmed += _warm_log_table(image, y0, y1, x0, x1, log_table)
            out[OUT_TABLE_WARMED] = warmed
        found, via = lean, FOUND_BY_LEAN if lean else FOUND_BY_ROI
        if not found and inp[IN_TIGHT] != 0.0 and inp[v + V_HAS_OUTLINE] != 0.0 and inp[v + V_KNOWN_SIGMA] > 0.0:
            # The tight ROI first, where the last frame's prediction error allows one (NaN: it does not) and the
            # noise sigma is known (it is measured on the ROI: its pixels, not the tight ROI's).
            allowance = 2.0 * prev[o + R_RESIDUAL] + 1.0
            tight = TIGHT_MARGIN_PX + allowance + half_width
            if tight < margin:
                ok, tx0, ty0, tx1, ty1 = _roi(pu, pv, eu0, ev0, eu1, ev1, tight, int(inp[v + V_HEIGHT]),
                                              int(inp[v + V_WIDTH]))
                if ok:
                    status, weights, mask = roi_kernels.search_view(
                        image, ty0, ty1, tx0, tx1, coarse, inp[v + V_FY], inp[v + V_FX], log_table, g, detect_sigma,
                        smooth_gain, floor, inp[v + V_KNOWN_SIGMA], min_pixels, max_tries, max_candidates, params,
                        ring_outer, ring_inner, near_hw, pu, pv, gate_px, axis_saturation, levels, head_ramp_ratio,
                        head_min_ramp_px, view_out)
                    if status == roi_kernels.FOUND and _is_as_predicted(view_out, prev, o, pu, pv, allowance):
                        found, via = True, FOUND_BY_TIGHT
                        x0, y0, x1, y1 = tx0, ty0, tx1, ty1
        if not found:
            status, weights, mask = roi_kernels.search_view(
                image, y0, y1, x0, x1, coarse, inp[v + V_FY], inp[v + V_FX], log_table, g, detect_sigma, smooth_gain,
                floor, inp[v + V_KNOWN_SIGMA], min_pixels, max_tries, max_candidates, params, ring_outer, ring_inner,
                near_hw, pu, pv, gate_px, axis_saturation, levels, head_ramp_ratio, head_min_ramp_px, view_out)
            if status != roi_kernels.FOUND:
                return PAIR_PER_VIEW
        out[o + R_ROI], out[o + R_ROI + 1], out[o + R_ROI + 2], out[o + R_ROI + 3] = x0, y0, x1, y1
        out[o + R_FOUND_BY] = via
        c = roi_kernels.CENTROID
        out[o + R_RESIDUAL] = math.hypot(view_out[c] - pu, view_out[c + 1] - pv)
        if lean:  # (its weights and mask are in the buffers already)
            mask = masks_buf[view, :lh * lw].reshape((lh, lw))
        _extent(out, o, mask, x0 + int(view_out[roi_kernels.REFINED + 2]), y0 + int(view_out[roi_kernels.REFINED]))
        r = roi_kernels.REFINED
        clutter_sigma = clutter_axis_sigma(view_out[r + 11], int(view_out[r + 12]), view_out[r + 4], view_out[r + 6],
                                           view_out[roi_kernels.EIGENVALUES], view_out[roi_kernels.EIGENVALUES + 1])
        out[o + R_AXIS_SIGMA] = math.hypot(view_out[roi_kernels.AXIS_SIGMA], clutter_sigma)
        if lean:
            out[OUT_WINDOW_SHAPES + 2 * view], out[OUT_WINDOW_SHAPES + 2 * view + 1] = lh, lw
            continue
        wh, ww = weights.shape
        if wh * ww > WINDOW_CAPACITY:
            return PAIR_PER_VIEW
        out[OUT_WINDOW_SHAPES + 2 * view], out[OUT_WINDOW_SHAPES + 2 * view + 1] = wh, ww
        for y in range(wh):
            for x in range(ww):
                weights_buf[view, y * ww + x] = weights[y, x]
                masks_buf[view, y * ww + x] = mask[y, x]
    fp = OUT_VIEW
    fq = OUT_VIEW + OUT_VIEW_SIZE
    c, a, t, e, h = roi_kernels.CENTROID, roi_kernels.AXIS, roi_kernels.TIPS, roi_kernels.EIGENVALUES, roi_kernels.HEAD
    f = IN_FRONT
    front = out[OUT_FRONT:OUT_FRONT + reconstruction_kernels.OUT_SIZE]
    status = reconstruction_kernels.weighted_front(
        G, out[fp + c:fp + c + 2], out[fp + a:fp + a + 2], out[fp + t:fp + t + 4].reshape((2, 2)),
        out[fq + c:fq + c + 2], out[fq + a:fq + a + 2], out[fq + t:fq + t + 4].reshape((2, 2)),
        out[fp + e], out[fp + e + 1], out[fp + R_AXIS_SIGMA], int(out[fp + h]),
        out[fq + e], out[fq + e + 1], out[fq + R_AXIS_SIGMA], int(out[fq + h]),
        inp[IN_PREVIOUS], inp[IN_PREVIOUS + 1], inp[IN_PREVIOUS + 2], inp[IN_PREVIOUS + 3] != 0.0,
        inp[f], inp[f + 1], inp[f + 2], inp[f + 3], inp[f + 4], inp[f + 5], inp[f + 6], front)
    out[OUT_FRONT_STATUS] = status
    _finish(out, inp, G)
    _place_body(out, inp, G)
    return PAIR_FOUND


def warm_up() -> None:
    """Compile :func:`search_pair` on a tiny biplane scene, for writable and read-only frames."""
    from appliance.geometry_kernels import pack_view, pack_views

    K = np.array([[400.0, 0.0, 20.0], [0.0, 400.0, 16.0], [0.0, 0.0, 1.0]])
    turn = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    views = [pack_view(K, np.linalg.inv(K), R, np.array([0.0, 0.0, 500.0]), np.zeros(5)) for R in (np.eye(3), turn)]
    G = pack_views(views[0], views[1], np.ones((3, 3)) / 3.0, 500.0)
    h, w = 32, 40
    yy, xx = np.mgrid[0:h, 0:w]
    body = np.exp(-(((xx - 20.0) / 8.0) ** 2 + ((yy - 16.0) / 2.0) ** 2))
    image = (20000 * np.exp(-body)).astype(np.uint16)
    table = np.log(np.maximum(np.arange(65536, dtype=np.float32), np.float32(1.0)))
    coarse = np.full((4, 5), np.float32(math.log(20000.0)), dtype=np.float32)
    disk = np.array([1, 2, 2, 2, 1], dtype=np.int64)
    params = np.array([0.25, 0.5, 8, 420, 40.0, 0.7, 2, 3.0, 0.2, 0.29, 3, 7, 4, 1, 3.0], dtype=np.float64)
    levels = np.array([0.2, 0.25, 0.5, 0.64, 0.8])
    settings = np.array([6.0, 0.29, 0.125, 8, 24, 8, 40.0, 1.0, 1.6, 1.0])
    inp = np.zeros(IN_SIZE)
    inp[IN_HALF], inp[IN_MARGIN] = 5.0, 14.0
    for view in range(2):
        v = IN_VIEW + view * IN_VIEW_SIZE
        inp[v + V_FY], inp[v + V_FX], inp[v + V_HEIGHT], inp[v + V_WIDTH] = 8.0, 8.0, h, w
    inp[IN_FRONT:IN_FRONT + FRONT_SETTINGS] = [3.0, 4.0, 12.0, 1.3, 0.001, 0.7, 0.25]
    inp[IN_FINISH:IN_FINISH + FINISH_SETTINGS] = [0.15, 20.0, 0.25, 6.0, 0.5]
    inp[IN_SOURCES:IN_SOURCES + 8] = [0.0, 0.0, -500.0, 400.0, 500.0, 0.0, 0.0, 400.0]
    inp[IN_BODY:IN_BODY + 1 + body_kernels.B_SIZE] = [1.0, 2.0, 0.9, 0.5, 0.5]
    frozen = image.copy()
    frozen.flags.writeable = False
    for frame in (image, frozen):
        for lean in (0.0, 1.0):
            inp[IN_VIEW + V_LEAN] = inp[IN_VIEW + IN_VIEW_SIZE + V_LEAN] = lean
            search_pair(frame, frame, coarse, coarse, table, view_kernels.GAUSSIAN_5, params, disk, disk, disk,
                        levels, settings, G, inp, np.zeros(OUT_SIZE), np.empty((2, WINDOW_CAPACITY), dtype=np.float32),
                        np.empty((2, WINDOW_CAPACITY), dtype=np.uint8), np.empty(LEAN_WORK_BYTES, dtype=np.uint8),
                        np.empty(OUT_SIZE))


register_warm_up(__name__)
