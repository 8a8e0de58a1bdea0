"""Compiled kernels of one view's recognition step: attenuation, candidates, the robot's weights, features.

A tracked frame's region of interest holds a few thousand pixels per view, and the numpy version of
this step made some 1500 calls on them (about 2 us each, whatever their size): the step cost
milliseconds for microseconds of arithmetic. These kernels do the same arithmetic in a handful of
compiled calls; :mod:`.segmentation` and :mod:`.features` keep the public Python API (the dataclasses)
around them and hold the documentation of what each step means. Numerics follow the numpy code they
replaced: float32 where it computed in float32 (the attenuation, the smoothed image, its comparisons
with thresholds), float64 where it did (coordinates, moments, the background fill).

Kernels take plain arrays and scalars. Masks are uint8 (0/1). Windows are ``(y0, y1, x0, x1)``.
"""
from __future__ import annotations

import math

import numpy as np

from appliance.compiled import kernel, register_warm_up

#: The 5-tap sigma=1 Gaussian (OpenCV's getGaussianKernel(5, 1.0) in float32).
GAUSSIAN_5 = np.array([0.05448868, 0.24420135, 0.40261996, 0.24420135, 0.05448868], dtype=np.float32)


# ------------------------------------------------------------------------------------- order statistics
@kernel
def _select(buf, n, k):  # pragma: no cover - compiled
    """The ``k``-th smallest of ``buf[:n]`` (0-based), partially reordering ``buf`` (Hoare's quickselect).

    Afterwards ``buf[:k]`` holds values <= the result, so the (k-1)-th smallest is their maximum."""
    lo, hi = 0, n - 1
    while hi > lo:
        mid = (lo + hi) >> 1
        # Median of three as the pivot: sorted or constant runs (common in images) stay O(n).
        a, b, c = buf[lo], buf[mid], buf[hi]
        if a > b:
            a, b = b, a
        if b > c:
            b = c
            if a > b:
                b = a
        pivot = b
        i, j = lo, hi
        while i <= j:
            while buf[i] < pivot:
                i += 1
            while buf[j] > pivot:
                j -= 1
            if i <= j:
                t = buf[i]
                buf[i] = buf[j]
                buf[j] = t
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            return buf[k]
    return buf[k]


@kernel
def median_inplace(buf, n):  # pragma: no cover - compiled
    """``np.median(buf[:n])`` in the array's dtype arithmetic (float32 stays float32), reordering ``buf``."""
    k = n // 2
    upper = _select(buf, n, k)
    if n % 2:
        return upper
    lower = buf[0]
    for i in range(1, k):
        if buf[i] > lower:
            lower = buf[i]
    return (lower + upper) / 2


@kernel
def noise_sigma_of(a):  # pragma: no cover - compiled
    """Robust noise standard deviation from the median of ``|a[:, x+1] - a[:, x]|``; NaN if there is none."""
    h, w = a.shape
    if w < 2 or h == 0:
        return np.nan
    n = h * (w - 1)
    d = np.empty(n, dtype=a.dtype)
    k = 0
    for y in range(h):
        for x in range(w - 1):
            d[k] = abs(a[y, x + 1] - a[y, x])
            k += 1
    return 1.4826 * float(median_inplace(d, n)) / math.sqrt(2.0)


# ------------------------------------------------------------------------------------------ attenuation
@kernel
def attenuation_from_coarse(image, y0, y1, x0, x1, coarse, fy, fx, log_table):  # pragma: no cover
    """``log B - log(max(I - dark, 1))`` (float32) on a window, ``log B`` interpolated from ``coarse``.

    The interpolation is the bilinear upsampling's (OpenCV's INTER_LINEAR: pixel centre ``x`` at
    ``(x + 0.5) / f - 0.5`` of the coarse grid, clamped), in float32 like the numpy code; ``log_table``
    holds the log term per gray level (dark level applied)."""
    hs, ws = coarse.shape
    h, w = y1 - y0, x1 - x0
    ix0 = np.empty(w, dtype=np.int64)
    ix1 = np.empty(w, dtype=np.int64)
    wx = np.empty(w, dtype=np.float32)
    for x in range(w):
        s = min(max((x + x0 + 0.5) / fx - 0.5, 0.0), ws - 1.0)
        i = min(int(s), max(ws - 2, 0))
        ix0[x] = i
        ix1[x] = min(i + 1, ws - 1)
        wx[x] = np.float32(s - i)
    out = np.empty((h, w), dtype=np.float32)
    row = np.empty(ws, dtype=np.float32)
    one = np.float32(1.0)
    lo, hi = ix0[0], ix1[w - 1] + 1 if w > 0 else 0
    for y in range(h):
        s = min(max((y + y0 + 0.5) / fy - 0.5, 0.0), hs - 1.0)
        i = min(int(s), max(hs - 2, 0))
        j = min(i + 1, hs - 1)
        wy = np.float32(s - i)
        for c in range(lo, hi):
            row[c] = coarse[i, c] * (one - wy) + coarse[j, c] * wy
        for x in range(w):
            bg = row[ix0[x]] * (one - wx[x]) + row[ix1[x]] * wx[x]
            out[y, x] = bg - log_table[image[y + y0, x + x0]]
    return out


@kernel
def attenuation_from_dense(image, log_bg, log_table):  # pragma: no cover - compiled
    """``log_bg - log(max(I - dark, 1))`` (float32) on two windows of the same shape."""
    h, w = image.shape
    out = np.empty((h, w), dtype=np.float32)
    for y in range(h):
        for x in range(w):
            out[y, x] = np.float32(log_bg[y, x]) - log_table[image[y, x]]
    return out


# ---------------------------------------------------------------------------- smoothing and components
@kernel
def gaussian5(a, g):  # pragma: no cover - compiled
    """5x5 separable Gaussian ``g`` with replicated borders (cv2.GaussianBlur's BORDER_REPLICATE), float32."""
    h, w = a.shape
    tmp = np.empty((h, w), dtype=np.float32)
    for y in range(h):
        for x in range(w):
            acc = np.float32(0.0)
            for k in range(5):
                xx = min(max(x + k - 2, 0), w - 1)
                acc += g[k] * a[y, xx]
            tmp[y, x] = acc
    out = np.empty((h, w), dtype=np.float32)
    for y in range(h):
        for x in range(w):
            acc = np.float32(0.0)
            for k in range(5):
                yy = min(max(y + k - 2, 0), h - 1)
                acc += g[k] * tmp[yy, x]
            out[y, x] = acc
    return out


@kernel
def _find(parent, i):  # pragma: no cover - compiled
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@kernel
def label_components(mask):  # pragma: no cover - compiled
    """8-connected components of a 0/1 mask: ``(n, labels, stats)`` like cv2.connectedComponentsWithStats.

    Labels run 1..n-1 in the raster order of each component's first pixel (0 is the background);
    ``stats[label]`` is ``[x, y, width, height, area]``."""
    h, w = mask.shape
    labels = np.zeros((h, w), dtype=np.int32)
    parent = np.empty(h * w // 2 + 2, dtype=np.int32)
    parent[0] = 0
    nxt = 1
    for y in range(h):
        for x in range(w):
            if mask[y, x] == 0:
                continue
            best = 0
            # The already visited 8-neighbours: left, and the three above.
            for dy, dx in ((0, -1), (-1, -1), (-1, 0), (-1, 1)):
                yy, xx = y + dy, x + dx
                if yy < 0 or xx < 0 or xx >= w:
                    continue
                lab = labels[yy, xx]
                if lab == 0:
                    continue
                if best == 0:
                    best = lab
                else:
                    ra, rb = _find(parent, best), _find(parent, lab)
                    if ra != rb:
                        if ra < rb:
                            parent[rb] = ra
                        else:
                            parent[ra] = rb
            if best == 0:
                if nxt >= parent.size:
                    grown = np.empty(parent.size * 2, dtype=np.int32)
                    grown[:parent.size] = parent
                    parent = grown
                parent[nxt] = nxt
                best = nxt
                nxt += 1
            labels[y, x] = best
    # Final labels: roots numbered in order of their first pixel (the smallest provisional label of
    # a set is its root, and provisional labels were handed out in raster order).
    final = np.zeros(nxt, dtype=np.int32)
    n = 1
    for i in range(1, nxt):
        r = _find(parent, i)
        if r == i:
            final[i] = n
            n += 1
        else:
            final[i] = final[r]
    stats = np.zeros((n, 5), dtype=np.int64)
    for i in range(1, n):
        stats[i, 0] = w
        stats[i, 1] = h
        stats[i, 2] = -1
        stats[i, 3] = -1
    for y in range(h):
        for x in range(w):
            lab = labels[y, x]
            if lab == 0:
                continue
            lab = final[lab]
            labels[y, x] = lab
            st = stats[lab]
            st[0] = min(st[0], x)
            st[1] = min(st[1], y)
            st[2] = max(st[2], x)
            st[3] = max(st[3], y)
            st[4] += 1
    for i in range(1, n):
        stats[i, 2] = stats[i, 2] - stats[i, 0] + 1
        stats[i, 3] = stats[i, 3] - stats[i, 1] + 1
    return n, labels, stats


@kernel
def candidates(a, g, detect_sigma, smooth_gain, floor):  # pragma: no cover - compiled
    """The candidate step of :func:`segment`: noise sigma, smoothed image, components above threshold.

    Returns ``(sigma, smooth, labels, stats, order)``: ``order`` lists the labels by decreasing area
    (ties in label order)."""
    sigma = noise_sigma_of(a)
    if not (sigma > 0.0) or not math.isfinite(sigma):
        sigma = 1e-3
    smooth = gaussian5(a, g)
    threshold = np.float32(max(detect_sigma * sigma * smooth_gain, floor))
    h, w = a.shape
    detected = np.empty((h, w), dtype=np.uint8)
    for y in range(h):
        for x in range(w):
            detected[y, x] = 1 if smooth[y, x] > threshold else 0
    n, labels, stats = label_components(detected)
    order = np.argsort(-stats[1:, 4], kind="mergesort") + 1
    return sigma, smooth, labels, stats, order


# ----------------------------------------------------------------------------------- binary morphology
@kernel
def dilate_runs(mask, half_widths):  # pragma: no cover - compiled
    """Dilation of a 0/1 mask by a structuring element given as row spans (cv2.dilate with an ellipse).

    ``half_widths[r + dy]`` is the element's half-width in its row ``dy`` (``-r..r``). Each run of set
    pixels in a row marks, in every row ``dy`` away, the run grown by that half-width; a prefix sum of
    the marks gives the result: cost proportional to the runs, not to pixels times element area."""
    h, w = mask.shape
    r = (half_widths.size - 1) // 2
    marks = np.zeros((h, w + 1), dtype=np.int32)
    for y in range(h):
        x = 0
        while x < w:
            if mask[y, x] == 0:
                x += 1
                continue
            start = x
            while x < w and mask[y, x] != 0:
                x += 1
            end = x  # exclusive
            for dy in range(-r, r + 1):
                yy = y + dy
                if yy < 0 or yy >= h:
                    continue
                hw = half_widths[dy + r]
                marks[yy, max(start - hw, 0)] += 1
                marks[yy, min(end + hw, w)] -= 1
    out = np.empty((h, w), dtype=np.uint8)
    for y in range(h):
        acc = 0
        for x in range(w):
            acc += marks[y, x]
            out[y, x] = 1 if acc > 0 else 0
    return out


@kernel
def _principal(sxx, syy, sxy, n):  # pragma: no cover - compiled
    """Eigenvalues and major unit axis of a scatter (sums of centred products over n), closed form."""
    k = 1.0 / max(n, 1)
    a, c, b = sxx * k, syy * k, sxy * k
    root = math.hypot(a - c, 2.0 * b)
    l1, l2 = 0.5 * (a + c + root), 0.5 * (a + c - root)
    if a >= c:
        vx, vy = l1 - c, b
    else:
        vx, vy = b, l1 - a
    norm = math.hypot(vx, vy)
    if norm < 1e-300:
        return l1, l2, 1.0, 0.0
    return l1, l2, vx / norm, vy / norm


@kernel
def moments(weights):  # pragma: no cover - compiled
    """``m00, m10, m01, mu20, mu02, mu11`` of a float image (cv2.moments' values, double accumulation)."""
    h, w = weights.shape
    m00 = m10 = m01 = m20 = m02 = m11 = 0.0
    for y in range(h):
        r0 = r1 = r2 = 0.0
        for x in range(w):
            v = float(weights[y, x])
            r0 += v
            r1 += v * x
            r2 += v * x * x
        m00 += r0
        m10 += r1
        m01 += r0 * y
        m20 += r2
        m11 += r1 * y
        m02 += r0 * y * y
    if m00 == 0.0:
        return m00, m10, m01, 0.0, 0.0, 0.0
    cx, cy = m10 / m00, m01 / m00
    mu20 = m20 - cx * m10
    mu11 = m11 - cx * m01
    mu02 = m02 - cy * m01
    return m00, m10, m01, mu20, mu02, mu11


# ------------------------------------------------------------------------------------ one candidate
@kernel
def _flood(allowed, seeds, out):  # pragma: no cover - compiled
    """Marks in ``out`` the 8-connected parts of ``allowed`` that contain a pixel of ``seeds``."""
    h, w = allowed.shape
    stack = np.empty(h * w, dtype=np.int64)
    top = 0
    for y in range(h):
        for x in range(w):
            if seeds[y, x] != 0 and allowed[y, x] != 0 and out[y, x] == 0:
                out[y, x] = 1
                stack[top] = y * w + x
                top += 1
    while top > 0:
        top -= 1
        p = stack[top]
        y, x = p // w, p % w
        for dy in range(-1, 2):
            yy = y + dy
            if yy < 0 or yy >= h:
                continue
            for dx in range(-1, 2):
                xx = x + dx
                if xx < 0 or xx >= w or out[yy, xx] != 0 or allowed[yy, xx] == 0:
                    continue
                out[yy, xx] = 1
                stack[top] = yy * w + xx
                top += 1


@kernel
def _end_keep(smooth, mask, s, s_lo, s_hi, tolerance, fade_step):  # pragma: no cover - compiled
    """The ``stop`` distance beyond each end of the core (see segmentation._end_limits): ``(stop_hi, stop_lo)``."""
    h, w = mask.shape
    # The body's width per 1-px slice along its core.
    nbins_core = int(math.floor(s_hi - s_lo)) + 1
    core_width = np.zeros(max(nbins_core, 1) + 1, dtype=np.int64)
    n_inside = 0
    top_bin = -1
    far_hi, far_lo = 0.0, 0.0
    for y in range(h):
        for x in range(w):
            if mask[y, x] == 0:
                continue
            p = s[y, x]
            if p >= s_lo and p <= s_hi:
                b = int(math.floor(p - s_lo))
                core_width[b] += 1
                n_inside += 1
                top_bin = max(top_bin, b)
            far_hi = max(far_hi, p - s_hi)
            far_lo = max(far_lo, s_lo - p)
    if n_inside == 0:
        max_width = 1.2 * 0.0 + 2.0
    else:
        counts = core_width[:top_bin + 1].astype(np.float64)
        max_width = 1.2 * float(median_inplace(counts, top_bin + 1)) + 2.0
    stops = np.zeros(2, dtype=np.float64)
    for side in range(2):
        sign = 1.0 if side == 0 else -1.0
        start = s_hi if side == 0 else s_lo
        far = far_hi if side == 0 else far_lo
        if not far > 0.0:
            stops[side] = np.inf  # nothing beyond this end: no limit
            continue
        nb = int(math.floor(far)) + 1
        peak = np.full(nb, -np.inf)
        width = np.zeros(nb, dtype=np.int64)
        for y in range(h):
            for x in range(w):
                if mask[y, x] == 0:
                    continue
                beyond = sign * (s[y, x] - start)
                if beyond > 0.0:
                    b = int(math.floor(beyond))
                    v = float(smooth[y, x])
                    if v > peak[b]:
                        peak[b] = v
                    width[b] += 1
        stop = nb
        for b in range(nb):
            if (not math.isfinite(peak[b]) or width[b] > max_width
                    or (b >= fade_step and peak[b] > peak[b - fade_step] - tolerance)):
                stop = b
                break
        stops[side] = stop
    return stops


@kernel
def _fill_columns(values, support, fill_rows, fill_cols, transpose):  # pragma: no cover - compiled
    """The background under the body (see segmentation._fill_across), along columns or, transposed, rows.

    Each column (row) crossing ``support`` has its supported run replaced by the straight line between
    the means of ``fill_rows`` pixels beyond either end, smoothed over ``fill_cols`` neighbouring lines."""
    if transpose:
        v = values.T
        m = support.T
    else:
        v = values
        m = support
    h, w = v.shape
    out = values.copy()
    o = out.T if transpose else out
    # The lines crossing the support are contiguous (it is convex).
    c0, c1 = -1, -1
    for c in range(w):
        for r in range(h):
            if m[r, c] != 0:
                if c0 < 0:
                    c0 = c
                c1 = c + 1
                break
    if c0 < 0:
        return out
    nc = c1 - c0
    tops = np.empty(nc, dtype=np.int64)
    bottoms = np.empty(nc, dtype=np.int64)
    v_top = np.empty(nc, dtype=np.float32)
    v_bottom = np.empty(nc, dtype=np.float32)
    third = np.float32(fill_rows)
    for i in range(nc):
        c = c0 + i
        first = 0
        while m[first, c] == 0:
            first += 1
        last = h - 1
        while m[last, c] == 0:
            last -= 1
        top, bottom = first - 1, last + 1
        tops[i], bottoms[i] = top, bottom
        acc_t = np.float32(0.0)
        acc_b = np.float32(0.0)
        for k in range(fill_rows):
            acc_t += v[max(top - k, 0), c]
            acc_b += v[min(bottom + k, h - 1), c]
        v_top[i] = acc_t / third
        v_bottom[i] = acc_b / third
    if nc >= fill_cols:
        half = fill_cols // 2
        kern = np.float32(1.0) / np.float32(fill_cols)
        sm_t = np.empty(nc, dtype=np.float32)
        sm_b = np.empty(nc, dtype=np.float32)
        for i in range(nc):
            acc_t = np.float32(0.0)
            acc_b = np.float32(0.0)
            for k in range(-half, half + 1):
                j = min(max(i + k, 0), nc - 1)
                acc_t += v_top[j] * kern
                acc_b += v_bottom[j] * kern
            sm_t[i] = acc_t
            sm_b[i] = acc_b
        v_top, v_bottom = sm_t, sm_b
    for i in range(nc):
        c = c0 + i
        top, bottom = tops[i], bottoms[i]
        span = float(np.float32(bottom - top))
        # float32 difference, float64 line: the arithmetic of the numpy code this replaced.
        vt, rise = float(v_top[i]), float(v_bottom[i] - v_top[i])
        for r in range(top + 1, bottom):
            if m[r, c] != 0:
                o[r, c] = np.float32(vt + rise * ((float(np.float32(r)) - top) / span))
    return out


@kernel
def refine(a, smooth, labels, label, bx, by, bw, bh, sigma, p, ring_outer, ring_inner, near_hw):  # pragma: no cover
    """One detected component refined into the robot's weights (see segmentation._blob_from_component).

    ``p`` holds the settings: ``[min_peak_attenuation, core_fraction, min_pixels, max_extent_px,
    max_elongation, cone_reach, support_dilate_px, support_sigma, support_fraction, smooth_gain,
    fill_rows, fill_cols, fade_step]``; ``ring_outer``/``ring_inner``/``near_hw`` the row spans of the
    dilations (ring and weighted support).

    Returns ``(status, window, weights, mask, scalars)``: status 0 if the component is not a plausible
    robot; ``window`` ``[y0, y1, x0, x1]`` in ``a``'s pixels; ``scalars`` ``[peak above baseline,
    baseline, strength, centroid x, centroid y (window px), edge, minor moment, clutter, pixel count]``."""
    min_peak, core_fraction = p[0], p[1]
    min_pixels, max_extent = int(p[2]), p[3]
    max_elongation, cone_reach = p[4], p[5]
    dilate_px, support_sigma, support_fraction = int(p[6]), p[7], p[8]
    smooth_gain, fill_rows, fill_cols, fade_step = p[9], int(p[10]), int(p[11]), int(p[12])
    sigma_s = sigma * smooth_gain
    empty_w = np.zeros((0, 0), dtype=np.float32)
    empty_m = np.zeros((0, 0), dtype=np.uint8)
    nothing = np.zeros(4, dtype=np.int64)
    no_scalars = np.zeros(9)
    # The component's peak, and its core: the part above core_fraction of it connected to the peak.
    peak32 = np.float32(-np.inf)
    for y in range(by, by + bh):
        for x in range(bx, bx + bw):
            if labels[y, x] == label and smooth[y, x] > peak32:
                peak32 = smooth[y, x]
    peak = float(peak32)
    if peak < min_peak:
        return 0, nothing, empty_w, empty_m, no_scalars
    level32 = np.float32(core_fraction * peak)
    strong = np.zeros((bh, bw), dtype=np.uint8)
    best, by_, bx_ = np.float32(-np.inf), -1, -1
    for y in range(bh):
        for x in range(bw):
            v = smooth[by + y, bx + x]
            if labels[by + y, bx + x] == label and v >= level32:
                strong[y, x] = 1
                if v > best:
                    best, by_, bx_ = v, y, x
    seed = np.zeros((bh, bw), dtype=np.uint8)
    seed[by_, bx_] = 1
    core = np.zeros((bh, bw), dtype=np.uint8)
    _flood(strong, seed, core)
    n = 0
    sx = sy = 0.0
    xmin, xmax, ymin, ymax = bw, -1, bh, -1
    for y in range(bh):
        for x in range(bw):
            if core[y, x]:
                n += 1
                sx += x
                sy += y
                xmin, xmax = min(xmin, x), max(xmax, x)
                ymin, ymax = min(ymin, y), max(ymax, y)
    if n < min_pixels:
        return 0, nothing, empty_w, empty_m, no_scalars
    if max(xmax - xmin, ymax - ymin) + 1 > max_extent:
        return 0, nothing, empty_w, empty_m, no_scalars
    cx, cy = sx / n, sy / n
    sxx = syy = sxy = 0.0
    for y in range(bh):
        for x in range(bw):
            if core[y, x]:
                dx, dy = x - cx, y - cy
                sxx += dx * dx
                syy += dy * dy
                sxy += dx * dy
    l1, l2, ax, ay = _principal(sxx, syy, sxy, n)
    if math.sqrt(l1 / max(l2, 1e-3)) > max_elongation:
        return 0, nothing, empty_w, empty_m, no_scalars
    s_min, s_max, t_max = np.inf, -np.inf, 0.0
    for y in range(bh):
        for x in range(bw):
            if core[y, x]:
                dx, dy = x - cx, y - cy
                s_ = dx * ax + dy * ay
                t_ = abs(-dx * ay + dy * ax)
                s_min, s_max, t_max = min(s_min, s_), max(s_max, s_), max(t_max, t_)
    core_len = s_max - s_min
    reach = cone_reach * core_len + 3.0
    pad = dilate_px + 1.0
    half_width = t_max + pad + 2.0
    grow = int(math.ceil(reach + half_width + pad + fill_rows + 2))
    H, W = a.shape
    wx0, wy0 = max(0, bx + xmin - grow), max(0, by + ymin - grow)
    wx1, wy1 = min(W, bx + xmax + grow + 1), min(H, by + ymax + grow + 1)
    hh, ww = wy1 - wy0, wx1 - wx0
    ox, oy = bx + cx, by + cy  # the core's centroid in a's pixels
    s_w = np.empty((hh, ww))
    t_w = np.empty((hh, ww))
    for y in range(hh):
        gy = (wy0 + y) - oy
        for x in range(ww):
            gx = (wx0 + x) - ox
            s_w[y, x] = gx * ax + gy * ay
            t_w[y, x] = -gx * ay + gy * ax
    core_w = np.zeros((hh, ww), dtype=np.uint8)
    dyc, dxc = by - wy0, bx - wx0
    for y in range(bh):
        for x in range(bw):
            if core[y, x]:
                core_w[y + dyc, x + dxc] = 1
    # The local baseline: the median of a ring around the core.
    outer = dilate_runs(core_w, ring_outer)
    inner = dilate_runs(core_w, ring_inner)
    ring_vals = np.empty(hh * ww, dtype=np.float32)
    nr = 0
    for y in range(hh):
        for x in range(ww):
            if outer[y, x] and not inner[y, x]:
                ring_vals[nr] = smooth[wy0 + y, wx0 + x]
                nr += 1
    baseline = float(median_inplace(ring_vals, nr)) if nr > 0 else 0.0
    height = peak - baseline
    if height < min_peak:
        return 0, nothing, empty_w, empty_m, no_scalars
    level = max(support_sigma * sigma_s, support_fraction * height)
    base32, level32 = np.float32(baseline), np.float32(level)
    lo_s, hi_s = s_min - reach, s_max + reach
    above = np.zeros((hh, ww), dtype=np.uint8)
    for y in range(hh):
        for x in range(ww):
            if ((smooth[wy0 + y, wx0 + x] - base32) > level32 and abs(t_w[y, x]) <= half_width
                    and s_w[y, x] >= lo_s and s_w[y, x] <= hi_s):
                above[y, x] = 1
    mask = np.zeros((hh, ww), dtype=np.uint8)
    _flood(above, core_w, mask)
    for y in range(hh):
        for x in range(ww):
            if core_w[y, x]:
                mask[y, x] = 1
    s_win = smooth[wy0:wy1, wx0:wx1]
    tolerance = 3.0 * sigma_s * math.sqrt(2.0)
    stops = _end_keep(s_win, mask, s_w, s_min, s_max, tolerance, fade_step)
    count = 0
    in_lo, in_hi, in_t = np.inf, -np.inf, -np.inf
    for y in range(hh):
        for x in range(ww):
            if mask[y, x]:
                s_ = s_w[y, x]
                if not ((s_ - s_max) < stops[0] and -(s_ - s_min) < stops[1]):
                    mask[y, x] = 0
                    continue
                count += 1
                in_lo, in_hi, in_t = min(in_lo, s_), max(in_hi, s_), max(in_t, abs(t_w[y, x]))
    if count == 0:
        return 0, nothing, empty_w, empty_m, no_scalars
    # The support: a rectangle around the body.
    support = np.zeros((hh, ww), dtype=np.uint8)
    edge = False
    for y in range(hh):
        for x in range(ww):
            s_ = s_w[y, x]
            if s_ >= in_lo - pad and s_ <= in_hi + pad and abs(t_w[y, x]) <= in_t + pad:
                support[y, x] = 1
                if y < fill_rows or y >= hh - fill_rows or x < fill_rows or x >= ww - fill_rows:
                    edge = True
    if edge:
        for y in range(hh):
            for x in range(ww):
                if y < fill_rows or y >= hh - fill_rows or x < fill_rows or x >= ww - fill_rows:
                    support[y, x] = 0
    background = _fill_columns(s_win, support, fill_rows, fill_cols, abs(ax) < abs(ay))
    near = dilate_runs(mask, near_hw)
    weights = np.zeros((hh, ww), dtype=np.float32)
    bmin, bmax, any_near = np.inf, -np.inf, False
    for y in range(hh):
        for x in range(ww):
            if near[y, x] and support[y, x]:
                weights[y, x] = a[wy0 + y, wx0 + x] - background[y, x]
                b = float(background[y, x])
                bmin, bmax, any_near = min(bmin, b), max(bmax, b), True
    m00, m10, m01, mu20, mu02, mu11 = moments(weights)
    if not m00 > 0.0:
        return 0, nothing, empty_w, empty_m, no_scalars
    _, minor, _, _ = _principal(mu20, mu02, mu11, 1)
    window = np.array([wy0, wy1, wx0, wx1], dtype=np.int64)
    scalars = np.array([height, baseline, m00, m10 / m00, m01 / m00, 1.0 if edge else 0.0, minor,
                        (bmax - bmin) / height if any_near else 0.0, float(count)])
    return 1, window, weights, mask, scalars


# ------------------------------------------------------------------------------------------- features
@kernel
def _eig2(s11, s22, s12):  # pragma: no cover - compiled
    """Eigenvalues (l1 >= l2) and major unit eigenvector of a 2x2 covariance (paper eq. 3)."""
    root = math.sqrt((s11 - s22) ** 2 + 4.0 * s12 * s12)
    l1, l2 = 0.5 * (s11 + s22 + root), 0.5 * (s11 + s22 - root)
    norm = math.hypot(l1 - s11, s12)
    if norm < 1e-12:
        if s11 >= s22:
            return l1, l2, 1.0, 0.0
        return l1, l2, 0.0, 1.0
    return l1, l2, s12 / norm, (l1 - s11) / norm


@kernel
def axial_profile_of(weights, c0, c1, v0, v1):  # pragma: no cover - compiled
    """The weights' axial profile in 1-px bins with linear interpolation, [1 2 1]/4 smoothed; ``(profile, s0)``."""
    h, w = weights.shape
    s_min, i_max = np.inf, -1
    for y in range(h):
        for x in range(w):
            if weights[y, x] != 0:
                s = (x - c0) * v0 + (y - c1) * v1
                s_min = min(s_min, s)
    s0 = math.floor(s_min) - 2.0
    for y in range(h):
        for x in range(w):
            if weights[y, x] != 0:
                i_max = max(i_max, int(((x - c0) * v0 + (y - c1) * v1) - s0))
    n = i_max + 4
    lower = np.zeros(n)
    upper = np.zeros(n)
    for y in range(h):
        for x in range(w):
            wt = float(weights[y, x])
            if wt != 0:
                u = ((x - c0) * v0 + (y - c1) * v1) - s0
                i = int(u)
                frac = u - i
                lower[i] += wt * (1.0 - frac)
                upper[i + 1] += wt * frac
    raw = lower + upper
    profile = raw.copy()
    for i in range(1, n - 1):
        profile[i] = 0.25 * raw[i - 1] + 0.5 * raw[i] + 0.25 * raw[i + 1]
    return profile, s0


@kernel
def axis_sigma_of(weights, c0, c1, v0, v1, spread, pixel_sigma):  # pragma: no cover - compiled
    """Standard deviation (rad) of the principal axis' angle from pixel noise (see features.axis_sigma_rad)."""
    h, w = weights.shape
    total, acc = 0.0, 0.0
    for y in range(h):
        for x in range(w):
            wt = weights[y, x]
            total += wt
            if wt != 0:
                dx, dy = x - c0, y - c1
                s = dx * v0 + dy * v1
                t = -dx * v1 + dy * v0
                gain = np.exp(min(max(wt, np.float32(0.0)), np.float32(12.0)))
                acc += (s * t) ** 2 * gain
    if total <= 0 or spread <= 0:
        return np.inf
    return pixel_sigma * math.sqrt(acc) / (total * spread)


@kernel
def reach_at(profile, s0, level, direction):  # pragma: no cover - compiled
    """Outward distance from s = 0 where the profile last exceeds ``level`` on one side (sub-bin)."""
    n = profile.size
    if direction > 0:
        j = n - 1
        while profile[j] < level:
            j -= 1
        if j + 1 >= n:
            return s0 + j
        step = profile[j] - profile[j + 1]
        return s0 + j + ((profile[j] - level) / step if step > 0 else 0.0)
    j = 0
    while profile[j] < level:
        j += 1
    if j == 0:
        return -(s0 + j)
    step = profile[j] - profile[j - 1]
    return -(s0 + j - ((profile[j] - level) / step if step > 0 else 0.0))


@kernel
def weighted_view_features(weights, cap, pixel_sigma, levels):  # pragma: no cover - compiled
    """The weighted estimator's numbers (see features.weighted_features).

    ``cap`` < inf saturates the weights for the axis. Returns ``(status, out, reach)``: status 0 if
    the weights sum to zero or less; ``out`` ``[cx, cy, l1, l2, vx, vy, axis_sigma]`` (window px);
    ``reach[end, level]`` the outward distances of both ends (0: +axis) at each of ``levels``."""
    out = np.zeros(7)
    reach = np.zeros((2, levels.size))
    m00, m10, m01, mu20, mu02, mu11 = moments(weights)
    if not m00 > 0:
        return 0, out, reach
    c0, c1 = m10 / m00, m01 / m00
    l1, l2, v0, v1 = _eig2(mu20 / m00, mu02 / m00, mu11 / m00)
    if math.isfinite(cap):
        capped = np.minimum(weights, np.float32(cap))
        t00, _, _, t20, t02, t11 = moments(capped)
        if not t00 > 0:
            return 0, out, reach
        _, _, a0, a1 = _eig2(t20 / t00, t02 / t00, t11 / t00)
        if a0 * v0 + a1 * v1 >= 0:
            v0, v1 = a0, a1
        else:
            v0, v1 = -a0, -a1
    profile, s0 = axial_profile_of(weights, c0, c1, v0, v1)
    axis_sigma = axis_sigma_of(weights, c0, c1, v0, v1, l1 - l2, pixel_sigma)
    plateau = profile.max()
    for k in range(levels.size):
        reach[0, k] = reach_at(profile, s0, levels[k] * plateau, 1)
        reach[1, k] = reach_at(profile, s0, levels[k] * plateau, -1)
    out[0], out[1], out[2], out[3], out[4], out[5], out[6] = c0, c1, l1, l2, v0, v1, axis_sigma
    return 1, out, reach


# ------------------------------------------------------------------------------------------- warm-up
def warm_up() -> None:
    """Compile (or load from the on-disk cache) every kernel on a tiny synthetic view."""
    h, w = 32, 40
    yy, xx = np.mgrid[0:h, 0:w]
    body = np.exp(-(((xx - 20.0) / 8.0) ** 2 + ((yy - 16.0) / 2.0) ** 2)).astype(np.float32)
    image = (20000 * np.exp(-body)).astype(np.uint16)
    table = np.log(np.maximum(np.arange(65536, dtype=np.float32), np.float32(1.0)))
    coarse = np.full((4, 5), np.float32(math.log(20000.0)))
    a = attenuation_from_coarse(image, 0, h, 0, w, coarse, 8.0, 8.0, table)
    attenuation_from_dense(image, np.full((h, w), np.float32(math.log(20000.0))), table)
    sigma, smooth, labels, stats, order = candidates(a, GAUSSIAN_5, 6.0, 0.29, 0.125)
    disk = np.array([1, 2, 2, 2, 1], dtype=np.int64)
    params = np.array([0.25, 0.5, 8, 420, 40.0, 0.7, 2, 3.0, 0.2, 0.29, 3, 7, 4], dtype=np.float64)
    for label in order:
        x, y, bw, bh = (int(v) for v in stats[label, :4])
        refine(a, smooth, labels, int(label), x, y, bw, bh, 0.01, params, disk, disk, disk)
    weights = np.maximum(body - np.float32(0.05), np.float32(0.0))
    levels = np.array([0.2, 0.25, 0.5, 0.64, 0.8])
    weighted_view_features(weights, np.inf, 0.01, levels)
    weighted_view_features(weights, 0.5, 0.01, levels)
    axial_profile_of(weights, 20.0, 16.0, 1.0, 0.0)
    noise_sigma_of(a)
    median_inplace(np.array([3.0, 1.0, 2.0, 5.0]), 4)


register_warm_up(__name__)
