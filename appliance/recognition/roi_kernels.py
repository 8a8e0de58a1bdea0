"""The tracker's steady-state search of one view, as one compiled call.

While the robot is tracked, a view's step is always the same chain: attenuation on the region of
interest (ROI) against the coarse background, candidate components (with the noise sigma the tracker
reuses), each component refined into a blob (strongest components first), the strongest blob that is
whole and near the predicted centroid chosen, and its weighted features. As separate calls from
Python this chain cost about as much in call overhead and boxed arrays (one per returned array) as in
arithmetic (issue 8), so :func:`search_view` runs it in one call with the kernels of
:mod:`.view_kernels`, and returns one flat array of numbers plus the chosen blob's weights and mask.

The choice is the one :func:`.segmentation.segment` and the tracker make in Python (and the tests
compare them): components in the order of :func:`.view_kernels.candidates`, at most
``max_tries`` of them, stopping at the first one smaller than ``min_pixels``; the accepted blobs
ranked by decreasing strength (ties in component order) and only the first ``max_candidates`` kept;
of those, the first that does not touch the ROI's border and whose centroid lies within ``gate_px``
of the prediction. Where that distance is within rounding of the gate (numba's ``hypot`` and
Python's may differ in the last bit) the call says so, and the caller decides in Python.
"""
from __future__ import annotations

import math

import numpy as np

from appliance.compiled import kernel, register_warm_up
from appliance.recognition import view_kernels

#: Status of :func:`search_view`.
FOUND = 0
NOT_FOUND = 1  # no whole blob near the prediction among the kept candidates
NO_WEIGHT = 2  # the chosen blob's weights sum to zero or less (features undefined)
BORDERLINE = 3  # a blob's distance from the prediction is within rounding of the gate: decide in Python

#: Layout of :func:`search_view`'s output: first the refinement's scalars as
#: :func:`.view_kernels.refine` returns them (window ``y0, y1, x0, x1`` in ROI pixels, peak above the
#: baseline, baseline, strength, centroid x, y in window pixels, edge, minor moment, clutter, pixel
#: count), then the noise sigma used, then the features in image pixels.
REFINED = 0
REFINED_SIZE = 13
SIGMA = 13
CENTROID = 14  # x, y (image px)
AXIS = 16  # unit x, y
TIPS = 18  # (2, 2): the +axis end, then the -axis end
EIGENVALUES = 22  # l1, l2
AXIS_SIGMA = 24
HEAD = 25  # 0 or 1, -1 if not identified
RAMPS = 26  # per end: reach at 0.2 minus reach at 0.8 of the plateau
REACH = 28  # per end (+axis, then -axis), the outward distance at each level
OUT_SIZE = REACH  # plus 2 x the number of levels

#: The gate test is left to Python when the distance is within this fraction of the gate.
_GATE_ROUNDING = 1e-9


@kernel
def _tip_distance(out, first, conical):  # pragma: no cover - compiled
    """features._tip_distance on the reaches ``out[first:first + 5]`` (levels 0.2, 0.25, 0.5, 0.64, 0.8)."""
    if conical:
        cone = (out[first + 1] - out[first + 3]) / (0.8 - 0.5)
        return out[first + 1] + 0.5 * cone
    return out[first + 2]


@kernel
def search_view(image, y0, y1, x0, x1, coarse, fy, fx, log_table, g, detect_sigma, smooth_gain, floor,
                known_sigma, min_pixels, max_tries, max_candidates, params, ring_outer, ring_inner, near_hw,
                gate_u, gate_v, gate_px, axis_saturation, levels, head_ramp_ratio, head_min_ramp_px,
                out):  # pragma: no cover - compiled
    """The steady-state search of one view's ROI ``y0:y1, x0:x1`` (see the module docstring).

    Arguments as :func:`.view_kernels.attenuation_from_coarse`, :func:`.view_kernels.candidates` and
    :func:`.view_kernels.refine` take them; ``gate_u, gate_v`` the predicted centroid (image px);
    ``axis_saturation`` < 1 caps the weights at that fraction of the blob's peak for the axis;
    ``levels`` must be features._LEVELS. Writes ``out`` (the layout above, ``OUT_SIZE + 2 *
    levels.size``) and returns ``(status, weights, mask)`` of the chosen blob.
    """
    a = view_kernels.attenuation_from_coarse(image, y0, y1, x0, x1, coarse, fy, fx, log_table)
    sigma, smooth, labels, stats, order = view_kernels.candidates(a, g, detect_sigma, smooth_gain, floor,
                                                                  known_sigma)
    out[SIGMA] = sigma
    best_w = np.zeros((0, 0), dtype=np.float32)
    best_m = np.zeros((0, 0), dtype=np.uint8)
    strengths = np.empty(max_tries)
    n_accepted, best, best_strength = 0, -1, 0.0
    borderline = False
    for k in range(min(order.size, max_tries)):
        label = order[k]
        if stats[label, 4] < min_pixels:
            break
        status, weights, mask, sc = view_kernels.refine(a, smooth, labels, label, stats[label, 0],
                                                        stats[label, 1], stats[label, 2], stats[label, 3],
                                                        sigma, params, ring_outer, ring_inner, near_hw)
        if not status:
            continue
        strength = sc[6]
        strengths[n_accepted] = strength
        n_accepted += 1
        if sc[9] != 0.0:  # touches the ROI's border
            continue
        # The centroid in image pixels as the Blob has it: window origin (int) plus the local centroid.
        cu = (x0 + int(sc[2])) + sc[7]
        cv = (y0 + int(sc[0])) + sc[8]
        distance = math.hypot(cu - gate_u, cv - gate_v)
        if abs(distance - gate_px) <= _GATE_ROUNDING * gate_px:
            borderline = True
        if not distance <= gate_px:
            continue
        if best < 0 or strength > best_strength:
            best, best_strength = n_accepted - 1, strength
            best_w, best_m = weights, mask
            for i in range(REFINED_SIZE):
                out[REFINED + i] = sc[i]
    if borderline:
        return BORDERLINE, best_w, best_m
    if best < 0:
        return NOT_FOUND, best_w, best_m
    # Rank among the accepted blobs by decreasing strength, ties in component order (a stable sort).
    rank = 0
    for i in range(n_accepted):
        if strengths[i] > best_strength or (strengths[i] == best_strength and i < best):
            rank += 1
    if rank >= max_candidates:
        return NOT_FOUND, best_w, best_m
    # The weighted features of the chosen blob (features.weighted_features).
    cap = axis_saturation * out[REFINED + 4] if axis_saturation < 1.0 else np.inf
    status, f = view_kernels.weighted_view_features(best_w, cap, sigma, levels)
    if not status:
        return NO_WEIGHT, best_w, best_m
    n = levels.size
    cx, cy, l1, l2, vx, vy = f[0], f[1], f[2], f[3], f[4], f[5]
    for k in range(2 * n):
        out[REACH + k] = f[7 + k]
    # Ramps (levels 0.2 and 0.8) and the head: the end whose ramp is clearly the longer one.
    ramp_plus = out[REACH] - out[REACH + n - 1]
    ramp_minus = out[REACH + n] - out[REACH + 2 * n - 1]
    head = -1
    for end in range(2):
        long_ = ramp_plus if end == 0 else ramp_minus
        short = ramp_minus if end == 0 else ramp_plus
        # Python's max(short, 1e-6) as features.py evaluates it (NaN included), not numba's max.
        floor_short = 1e-6 if 1e-6 > short else short  # noqa: FURB136
        if long_ >= head_ramp_ratio * floor_short and long_ - short >= head_min_ramp_px:
            head = end
    px = cx + (x0 + int(out[REFINED + 2]))
    py = cy + (y0 + int(out[REFINED + 0]))
    d0 = _tip_distance(out, REACH, head == 0)
    d1 = _tip_distance(out, REACH + n, head == 1)
    out[CENTROID], out[CENTROID + 1] = px, py
    out[AXIS], out[AXIS + 1] = vx, vy
    out[TIPS], out[TIPS + 1] = px + vx * d0, py + vy * d0
    out[TIPS + 2], out[TIPS + 3] = px - vx * d1, py - vy * d1
    out[EIGENVALUES], out[EIGENVALUES + 1] = l1, l2
    out[AXIS_SIGMA] = f[6]
    out[HEAD] = head
    out[RAMPS], out[RAMPS + 1] = ramp_plus, ramp_minus
    return FOUND, best_w, best_m


def warm_up() -> None:
    """Compile :func:`search_view` on a tiny view, for writable and read-only frames (a grabber's or a
    recording's buffer), so that no tracked frame compiles."""
    h, w = 32, 40
    yy, xx = np.mgrid[0:h, 0:w]
    body = np.exp(-(((xx - 20.0) / 8.0) ** 2 + ((yy - 16.0) / 2.0) ** 2))
    image = (20000 * np.exp(-body)).astype(np.uint16)
    table = np.log(np.maximum(np.arange(65536, dtype=np.float32), np.float32(1.0)))
    coarse = np.full((4, 5), np.float32(math.log(20000.0)), dtype=np.float32)
    disk = np.array([1, 2, 2, 2, 1], dtype=np.int64)
    params = np.array([0.25, 0.5, 8, 420, 40.0, 0.7, 2, 3.0, 0.2, 0.29, 3, 7, 4, 1, 3.0], dtype=np.float64)
    levels = np.array([0.2, 0.25, 0.5, 0.64, 0.8])
    out = np.empty(OUT_SIZE + 2 * levels.size)
    frozen = image.copy()
    frozen.flags.writeable = False
    for frame in (image, frozen):
        for saturation in (1.0, 0.5):
            search_view(frame, 0, h, 0, w, coarse, 8.0, 8.0, table, view_kernels.GAUSSIAN_5, 6.0, 0.29, 0.125,
                        0.0, 8, 24, 8, params, disk, disk, disk, 20.0, 16.0, 40.0, saturation, levels, 1.6, 1.0,
                        out)


register_warm_up(__name__)
