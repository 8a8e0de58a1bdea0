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
from appliance.recognition.run_sets import number_sets, union

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
            b = max(b, a)
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
def median_f32(values, n):  # pragma: no cover - compiled
    """:func:`median_inplace` of ``values[:n]`` (float32, no NaN, C-contiguous; left unchanged), found on the
    values' bits instead of by partitioning: quickselect's comparisons are branches the processor mispredicts
    about every other time, and the ring median of :func:`refine` (a few hundred values) cost ~5 us a view.

    Each float32 maps to an integer key in the same order (positive: the bits with the sign bit set;
    negative: the bits inverted), and the k-th smallest key is found a byte at a time (four histograms of
    the keys whose higher bytes are already known). Equal values have equal keys, so the value returned is
    the k-th smallest as quickselect returns it; only a zero's sign orders (-0 before +0) where quickselect
    takes either."""
    k = n // 2
    bits = values.view(np.uint32)
    keys = np.empty(n, dtype=np.int64)
    for i in range(n):
        b = np.int64(bits[i])
        keys[i] = (b ^ 0xFFFFFFFF) if b >= 0x80000000 else (b | 0x80000000)
    hist = np.empty(256, dtype=np.int64)
    prefix, known, rank = 0, 0, k
    for step in range(4):
        shift = 24 - 8 * step
        hist[:] = 0
        for i in range(n):
            key = keys[i]
            hist[(key >> shift) & 255] += 1 if (key & known) == prefix else 0
        below, b = 0, 0
        while below + hist[b] <= rank:
            below += hist[b]
            b += 1
        prefix |= b << shift
        known |= 255 << shift
        rank -= below
    # ``prefix`` is the k-th smallest key; the (k-1)-th is it too unless fewer than k keys lie below it.
    upper = values[0]
    lower_key, n_below = -1, 0
    for i in range(n):
        key = keys[i]
        if key == prefix:
            upper = values[i]
        elif key < prefix:
            n_below += 1
            lower_key = max(lower_key, key)
    if n % 2:
        return upper
    lower = upper
    if n_below >= k:
        for i in range(n):
            if keys[i] == lower_key:
                lower = values[i]
                break
    return (lower + upper) / 2


@kernel
def median_inplace(buf, n):  # pragma: no cover - compiled
    """``np.median(buf[:n])`` in the array's dtype arithmetic (float32 stays float32), reordering ``buf``."""
    k = n // 2
    upper = _select(buf, n, k)
    if n % 2:
        return upper
    lower = buf[0]
    for i in range(1, k):
        lower = max(lower, buf[i])
    return (lower + upper) / 2


@kernel
def _abs_row_differences(a):  # pragma: no cover - compiled
    """``|a[:, x+1] - a[:, x]|`` of every row, flattened, in ``a``'s dtype (the noise statistics' sample)."""
    h, w = a.shape
    d = np.empty(h * (w - 1), dtype=a.dtype)
    k = 0
    for y in range(h):
        row = a[y]
        for x in range(w - 1):
            d[k] = abs(row[x + 1] - row[x])
            k += 1
    return d


@kernel
def noise_sigma_of(a):  # pragma: no cover - compiled
    """Robust noise standard deviation from the median of ``|a[:, x+1] - a[:, x]|``; NaN if there is none."""
    h, w = a.shape
    if w < 2 or h == 0:
        return np.nan
    n = h * (w - 1)
    d = _abs_row_differences(a)
    return 1.4826 * float(median_inplace(d, n)) / math.sqrt(2.0)


#: Histogram bins of the float32 noise median: the top 13 bits of a non-negative float32 (exponent and
#: 4 mantissa bits, 16 bins an octave), so the bins containing the median hold a few percent of the values.
_BIN_SHIFT = 19
_N_BINS = 1 << (31 - _BIN_SHIFT)


@kernel
def _select_in_bins(values, bits, lo_bin, hi_bin, shift, k):  # pragma: no cover - compiled
    """The ``(k-1)``-th and ``k``-th smallest of the ``values`` whose ``bits >> shift`` lies in
    ``[lo_bin, hi_bin]`` (the first is the second if ``k`` is 0)."""
    m = 0
    for i in range(bits.size):
        b = bits[i] >> shift
        if b >= lo_bin and b <= hi_bin:
            m += 1
    buf = np.empty(m, dtype=values.dtype)
    m = 0
    for i in range(bits.size):
        b = bits[i] >> shift
        if b >= lo_bin and b <= hi_bin:
            buf[m] = values[i]
            m += 1
    upper = _select(buf, m, k)
    lower = upper
    if k > 0:
        lower = buf[0]
        for i in range(1, k):
            lower = max(lower, buf[i])
    return lower, upper


@kernel
def noise_sigma_f32(a):  # pragma: no cover - compiled
    """:func:`noise_sigma_of` for float32 images: the same order statistic, found by a histogram of the
    differences' bit patterns (monotonic in the value for non-negative floats) and a selection among
    the few values in the bins holding the median, instead of partitioning every difference."""
    h, w = a.shape
    if w < 2 or h == 0:
        return np.nan
    n = h * (w - 1)
    d = _abs_row_differences(a)
    bits = d.view(np.uint32)
    # Two histograms, alternating, so that runs of equal bins do not wait on each other's increments.
    hist = np.zeros((2, _N_BINS), dtype=np.int64)
    for i in range(0, n - 1, 2):
        hist[0, bits[i] >> _BIN_SHIFT] += 1
        hist[1, bits[i + 1] >> _BIN_SHIFT] += 1
    if n % 2:
        hist[0, bits[n - 1] >> _BIN_SHIFT] += 1
    # The bins of the (k-1)-th and k-th smallest, and how many values lie below the first.
    upper_rank = n // 2
    lower_rank = upper_rank - 1 if n % 2 == 0 else upper_rank
    below, b_lo, b_hi, base = 0, -1, -1, 0
    for b in range(_N_BINS):
        c = hist[0, b] + hist[1, b]
        if b_lo < 0 and below + c > lower_rank:
            b_lo, base = b, below
        if below + c > upper_rank:
            b_hi = b
            break
        below += c
    if b_hi < 0:  # NaN differences beyond every bin: as numpy, the median is NaN
        return np.nan
    lower, upper = _select_in_bins(d, bits, b_lo, b_hi, _BIN_SHIFT, upper_rank - base)
    med = upper if n % 2 else (lower + upper) / np.float32(2.0)
    return 1.4826 * float(med) / math.sqrt(2.0)


# ------------------------------------------------------------------------------------------ attenuation
@kernel
def bilinear_columns(w, x0, fx, ws):  # pragma: no cover - compiled
    """For columns ``x0 .. x0 + w - 1`` of the full image, the two coarse columns and the float32 weight of
    the second in the bilinear upsampling by ``fx`` of ``ws`` coarse columns (OpenCV's INTER_LINEAR: pixel
    centre ``x`` at ``(x + 0.5) / f - 0.5`` of the coarse grid, clamped)."""
    ix0 = np.empty(w, dtype=np.int64)
    ix1 = np.empty(w, dtype=np.int64)
    wx = np.empty(w, dtype=np.float32)
    bilinear_columns_into(w, x0, fx, ws, ix0, ix1, wx)
    return ix0, ix1, wx


@kernel
def bilinear_columns_into(w, x0, fx, ws, ix0, ix1, wx):  # pragma: no cover - compiled
    """:func:`bilinear_columns` into the caller's arrays (their first ``w`` elements)."""
    for x in range(w):
        s = min(max((x + x0 + 0.5) / fx - 0.5, 0.0), ws - 1.0)
        i = min(int(s), max(ws - 2, 0))
        ix0[x] = i
        ix1[x] = min(i + 1, ws - 1)
        wx[x] = np.float32(s - i)


@kernel
def coarse_row_at(coarse, y, fy, lo, hi, row):  # pragma: no cover - compiled
    """Fill ``row[lo:hi]`` with the coarse grid interpolated (bilinear, as :func:`bilinear_columns`) to
    full-image row ``y``, in float32."""
    hs = coarse.shape[0]
    one = np.float32(1.0)
    s = min(max((y + 0.5) / fy - 0.5, 0.0), hs - 1.0)
    i = min(int(s), max(hs - 2, 0))
    j = min(i + 1, hs - 1)
    wy = np.float32(s - i)
    for c in range(lo, hi):
        row[c] = coarse[i, c] * (one - wy) + coarse[j, c] * wy


@kernel
def attenuation_from_coarse(image, y0, y1, x0, x1, coarse, fy, fx, log_table):  # pragma: no cover
    """``log B - log(max(I - dark, 1))`` (float32) on a window, ``log B`` interpolated from ``coarse``.

    The interpolation is the bilinear upsampling's (OpenCV's INTER_LINEAR: pixel centre ``x`` at
    ``(x + 0.5) / f - 0.5`` of the coarse grid, clamped), in float32 like the numpy code; ``log_table``
    holds the log term per gray level (dark level applied)."""
    ws = coarse.shape[1]
    h, w = y1 - y0, x1 - x0
    ix0, ix1, wx = bilinear_columns(w, x0, fx, ws)
    out = np.empty((h, w), dtype=np.float32)
    row = np.empty(ws, dtype=np.float32)
    one = np.float32(1.0)
    lo, hi = ix0[0], ix1[w - 1] + 1 if w > 0 else 0
    for y in range(h):
        coarse_row_at(coarse, y + y0, fy, lo, hi, row)
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
    """5x5 separable Gaussian ``g`` with replicated borders (cv2.GaussianBlur's BORDER_REPLICATE), float32.

    Rows first, then columns; each output is ``g0 v0 + g1 v1 + ... + g4 v4`` summed in that order.
    The interior runs without index clamping so that the compiler vectorises it. Rows are indexed in
    2D, not taken as row views (each view takes and releases a reference count: eight a row cost
    more than the row's arithmetic on a ROI's ~60-px rows)."""
    h, w = a.shape
    g0, g1, g2, g3, g4 = g[0], g[1], g[2], g[3], g[4]
    tmp = np.empty((h, w), dtype=np.float32)
    for y in range(h):
        for x in range(min(2, w)):
            tmp[y, x] = (g0 * a[y, max(x - 2, 0)] + g1 * a[y, max(x - 1, 0)] + g2 * a[y, x]
                         + g3 * a[y, min(x + 1, w - 1)] + g4 * a[y, min(x + 2, w - 1)])
        for x in range(2, w - 2):
            tmp[y, x] = g0 * a[y, x - 2] + g1 * a[y, x - 1] + g2 * a[y, x] + g3 * a[y, x + 1] + g4 * a[y, x + 2]
        for x in range(max(w - 2, 2), w):
            tmp[y, x] = (g0 * a[y, max(x - 2, 0)] + g1 * a[y, max(x - 1, 0)] + g2 * a[y, x]
                         + g3 * a[y, min(x + 1, w - 1)] + g4 * a[y, min(x + 2, w - 1)])
    out = np.empty((h, w), dtype=np.float32)
    for y in range(h):
        y0, y1, y3, y4 = max(y - 2, 0), max(y - 1, 0), min(y + 1, h - 1), min(y + 2, h - 1)
        for x in range(w):
            out[y, x] = g0 * tmp[y0, x] + g1 * tmp[y1, x] + g2 * tmp[y, x] + g3 * tmp[y3, x] + g4 * tmp[y4, x]
    return out


@kernel
def label_above(smooth, threshold):  # pragma: no cover - compiled
    """8-connected components of ``smooth > threshold``: ``(n, labels, stats)`` like
    cv2.connectedComponentsWithStats.

    Labels run 1..n-1 in the raster order of each component's first pixel (0 is the background);
    ``stats[label]`` is ``[x, y, width, height, area]``. Works on runs of pixels, not pixels: the
    rows are scanned once, and runs touching (8-connected) a run of the row above are merged."""
    h, w = smooth.shape
    cap = h * ((w + 1) // 2) + 1
    run_y = np.empty(cap, dtype=np.int64)
    run_x0 = np.empty(cap, dtype=np.int64)
    run_x1 = np.empty(cap, dtype=np.int64)
    parent = np.empty(cap, dtype=np.int64)
    n_runs = 0
    prev_start, prev_end = 0, 0  # runs of the row above: [prev_start, prev_end)
    for y in range(h):
        row_start = n_runs
        k = prev_start
        x = 0
        while x < w:
            if not smooth[y, x] > threshold:
                x += 1
                continue
            x0 = x
            while x < w and smooth[y, x] > threshold:
                x += 1
            r = n_runs
            run_y[r], run_x0[r], run_x1[r] = y, x0, x
            parent[r] = r
            n_runs += 1
            # Runs above that touch [x0 - 1, x] (8-connectivity); they are sorted by x.
            while k < prev_end and run_x1[k] < x0:
                k += 1
            j = k
            while j < prev_end and run_x0[j] <= x:
                union(parent, j, r)
                j += 1
            if j > k:
                k = j - 1  # the last touching run may touch the next run of this row too
        prev_start, prev_end = row_start, n_runs
    # Final labels: roots (the first run of each set, in raster order) numbered in order.
    final, n = number_sets(parent, n_runs)
    labels = np.zeros((h, w), dtype=np.int32)
    stats = np.zeros((n, 5), dtype=np.int64)
    for i in range(1, n):
        stats[i, 0], stats[i, 1], stats[i, 2], stats[i, 3] = w, h, -1, -1
    for r in range(n_runs):
        lab = final[r]
        y, x0, x1 = run_y[r], run_x0[r], run_x1[r]
        labels[y, x0:x1] = lab
        st = stats[lab]
        st[0] = min(st[0], x0)
        st[1] = min(st[1], y)
        st[2] = max(st[2], x1 - 1)
        st[3] = max(st[3], y)
        st[4] += x1 - x0
    for i in range(1, n):
        stats[i, 2] = stats[i, 2] - stats[i, 0] + 1
        stats[i, 3] = stats[i, 3] - stats[i, 1] + 1
    return n, labels, stats


@kernel
def candidates(a, g, detect_sigma, smooth_gain, floor, known_sigma):  # pragma: no cover - compiled
    """The candidate step of :func:`segment`: noise sigma, smoothed image, components above threshold.

    ``known_sigma`` > 0 is used as the noise sigma instead of measuring it (the tracker's steady state,
    where a view's noise does not change from frame to frame); 0 or NaN measures it here.
    Returns ``(sigma, smooth, labels, stats, order)``: ``order`` lists the labels by decreasing area
    (ties in label order)."""
    sigma = known_sigma if known_sigma > 0.0 else noise_sigma_f32(a)
    if not (sigma > 0.0) or not math.isfinite(sigma):
        sigma = 1e-3
    smooth = gaussian5(a, g)
    threshold = np.float32(max(detect_sigma * sigma * smooth_gain, floor))
    _, labels, stats = label_above(smooth, threshold)
    order = np.argsort(-stats[1:, 4], kind="mergesort") + 1
    return sigma, smooth, labels, stats, order


# ----------------------------------------------------------------------------------- binary morphology
@kernel
def _next_run(mask, y, x):  # pragma: no cover - compiled
    """The first run of set pixels in row ``y`` of ``mask`` at or after column ``x``: ``(start, end)``,
    ``end`` exclusive; ``(w, w)`` where there is none."""
    w = mask.shape[1]
    while x < w and mask[y, x] == 0:
        x += 1
    start = x
    while x < w and mask[y, x] != 0:
        x += 1
    return start, x


@kernel
def _mark_run(marks, y, start, end, half_widths):  # pragma: no cover - compiled
    """Of a dilation by row spans (:func:`dilate_runs`): the run ``[start, end)`` of set pixels in row ``y``
    marks, in every row ``dy`` away, the run grown by ``half_widths[r + dy]``, as a +1 where it starts
    and a -1 where it ends in ``marks`` (``h x (w + 1)``; a prefix sum along each row gives the dilation)."""
    h, w = marks.shape[0], marks.shape[1] - 1
    r = (half_widths.size - 1) // 2
    for dy in range(-r, r + 1):
        yy = y + dy
        if yy < 0 or yy >= h:
            continue
        hw = half_widths[dy + r]
        marks[yy, max(start - hw, 0)] += 1
        marks[yy, min(end + hw, w)] -= 1


@kernel
def _box_mask(ys, xs, n, r, hh, ww):  # pragma: no cover - compiled
    """The pixels ``(ys, xs)[:n]`` as a 0/1 mask on their bounding box grown by ``r`` and clipped to
    ``hh x ww``: ``(mask, y0, x0)``, the box's corner."""
    y0, y1, x0, x1 = hh, -1, ww, -1
    for i in range(n):
        y0, y1 = min(y0, ys[i]), max(y1, ys[i])
        x0, x1 = min(x0, xs[i]), max(x1, xs[i])
    y0, x0 = max(y0 - r, 0), max(x0 - r, 0)
    y1, x1 = min(y1 + r + 1, hh), min(x1 + r + 1, ww)
    src = np.zeros((y1 - y0, x1 - x0), dtype=np.uint8)
    for i in range(n):
        src[ys[i] - y0, xs[i] - x0] = 1
    return src, y0, x0


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
        start, end = _next_run(mask, y, 0)
        while start < w:
            _mark_run(marks, y, start, end, half_widths)
            start, end = _next_run(mask, y, end)
    out = np.empty((h, w), dtype=np.uint8)
    for y in range(h):
        acc = 0
        for x in range(w):
            acc += marks[y, x]
            out[y, x] = 1 if acc > 0 else 0
    return out


@kernel
def _nonzero_span(row):  # pragma: no cover - compiled
    """``lo, hi``: the first index of ``row`` not zero (a NaN counts) and one past the last; ``0, 0`` if none."""
    w = row.size
    lo = 0
    while lo < w and row[lo] == 0:
        lo += 1
    if lo == w:
        return 0, 0
    hi = w
    while row[hi - 1] == 0:
        hi -= 1
    return lo, hi


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
def _central(m00, m10, m01, m20, m02, m11):  # pragma: no cover - compiled
    """``m00, m10, m01, mu20, mu02, mu11`` from the raw moments (cv2.moments' central ones)."""
    if m00 == 0.0:
        return m00, m10, m01, 0.0, 0.0, 0.0
    cx, cy = m10 / m00, m01 / m00
    mu20 = m20 - cx * m10
    mu11 = m11 - cx * m01
    mu02 = m02 - cy * m01
    return m00, m10, m01, mu20, mu02, mu11


@kernel
def _with_pixel(r0, r1, r2, v, x):  # pragma: no cover - compiled
    """A row's sums of ``v``, ``v x``, ``v x x`` with pixel ``x``'s value ``v`` added."""
    return r0 + v, r1 + v * x, r2 + v * x * x


@kernel
def _with_row(m00, m10, m01, m20, m02, m11, r0, r1, r2, y):  # pragma: no cover - compiled
    """The raw moments with row ``y``'s sums (:func:`_with_pixel`) added."""
    return m00 + r0, m10 + r1, m01 + r0 * y, m20 + r2, m02 + r0 * y * y, m11 + r1 * y


@kernel
def moments(weights):  # pragma: no cover - compiled
    """``m00, m10, m01, mu20, mu02, mu11`` of a float image (cv2.moments' values, double accumulation)."""
    h = weights.shape[0]
    m00 = m10 = m01 = m20 = m02 = m11 = 0.0
    for y in range(h):
        r0 = r1 = r2 = 0.0
        lo, hi = _nonzero_span(weights[y])  # (a zero pixel's sums are zeros: they change no sum)
        for x in range(lo, hi):
            r0, r1, r2 = _with_pixel(r0, r1, r2, float(weights[y, x]), x)
        m00, m10, m01, m20, m02, m11 = _with_row(m00, m10, m01, m20, m02, m11, r0, r1, r2, y)
    return _central(m00, m10, m01, m20, m02, m11)


@kernel
def moments_and_capped(weights, cap):  # pragma: no cover - compiled
    """:func:`moments` of ``weights`` and of ``np.minimum(weights, np.float32(cap))``, in one pass and without
    the capped copy: the same sums in the same order as the two calls (12 numbers, the weights' first)."""
    h = weights.shape[0]
    cap32 = np.float32(cap)
    m00 = m10 = m01 = m20 = m02 = m11 = 0.0
    t00 = t10 = t01 = t20 = t02 = t11 = 0.0
    for y in range(h):
        r0 = r1 = r2 = 0.0
        q0 = q1 = q2 = 0.0
        lo, hi = _nonzero_span(weights[y])  # (a zero pixel's sums, capped or not, are zeros: they change no sum)
        for x in range(lo, hi):
            value = weights[y, x]
            r0, r1, r2 = _with_pixel(r0, r1, r2, float(value), x)
            # np.minimum's value (a NaN weight stays NaN)
            q0, q1, q2 = _with_pixel(q0, q1, q2, float(cap32 if cap32 < value else value), x)
        m00, m10, m01, m20, m02, m11 = _with_row(m00, m10, m01, m20, m02, m11, r0, r1, r2, y)
        t00, t10, t01, t20, t02, t11 = _with_row(t00, t10, t01, t20, t02, t11, q0, q1, q2, y)
    a00, a10, a01, a20, a02, a11 = _central(m00, m10, m01, m20, m02, m11)
    b00, b10, b01, b20, b02, b11 = _central(t00, t10, t01, t20, t02, t11)
    return a00, a10, a01, a20, a02, a11, b00, b10, b01, b20, b02, b11


# ------------------------------------------------------------------------------------ one candidate
@kernel
def _scanline_fill(allowed, out, seeds_y, seeds_x, n_seeds, ys, xs, n):  # pragma: no cover - compiled
    """8-connected flood fill of ``allowed`` (0/1) from the seeds, run by run: marks ``out`` and appends
    the new pixels to ``ys, xs`` after their first ``n``; returns the new count.

    A run is grown left and right in one sequential scan, then the rows above and below are scanned
    over its span (plus one pixel either side) for runs to fill next: every pixel is read a few
    times in predictable loops, where a pixel-by-pixel fill tests eight neighbours each."""
    h, w = allowed.shape
    # Rows and columns on two stacks: a packed index would cost two integer divisions a pop.
    stack = np.empty((2, 2 * h * w + n_seeds + 2), dtype=np.int64)  # (one allocation for both)
    stack_y, stack_x = stack[0], stack[1]
    top = 0
    for i in range(n_seeds):
        stack_y[top], stack_x[top] = seeds_y[i], seeds_x[i]
        top += 1
    # Pixels are read by 2D index, not through row views: a view costs a reference count taken and
    # released (two atomic calls), and this loop pops once per seed (every core pixel): the row views
    # were half the fill's time.
    while top > 0:
        top -= 1
        y, x = stack_y[top], stack_x[top]
        if out[y, x] or not allowed[y, x]:
            continue
        x0 = x
        while x0 > 0 and allowed[y, x0 - 1] and not out[y, x0 - 1]:
            x0 -= 1
        x1 = x
        while x1 < w - 1 and allowed[y, x1 + 1] and not out[y, x1 + 1]:
            x1 += 1
        for xx in range(x0, x1 + 1):
            out[y, xx] = 1
            ys[n], xs[n] = y, xx
            n += 1
        for ny in (y - 1, y + 1):
            if ny < 0 or ny >= h:
                continue
            inside = False
            for xx in range(max(x0 - 1, 0), min(x1 + 2, w)):
                free = allowed[ny, xx] != 0 and out[ny, xx] == 0
                if free and not inside:
                    stack_y[top], stack_x[top] = ny, xx
                    top += 1
                inside = free
    return n


@kernel
def _side_baseline(smooth, wy0, wx0, hh, ww, ox, oy, ax, ay, lo_s, nb, side_t):  # pragma: no cover
    """The attenuation beside the body, per 1-px slice along the axis: slice ``b`` (at ``s = lo_s + b
    + 0.5`` from the core's centroid ``ox, oy`` along ``ax, ay``) gets the mean of the smoothed image
    at ``side_t`` and ``side_t + 2`` px either side of the axis (nearest pixels, clamped to the window
    ``hh x ww`` at ``wy0, wx0``), averaged over the slice and its two neighbours (12 pixels).

    It is the baseline the body stands on where that varies along the body: a vessel crossing or
    running along the robot raises it there only, where the ring's single median is too high beyond
    the vessel (a faint cone tip leaving the vessel fell below it: robot 6, 4.8 mm of cone lost) and
    too low over it."""
    raw = np.empty(nb)
    for b in range(nb):
        s_ = lo_s + b + 0.5
        acc = 0.0
        for t_ in (-side_t - 2.0, -side_t, side_t, side_t + 2.0):
            gx = s_ * ax - t_ * ay + ox - wx0
            gy = s_ * ay + t_ * ax + oy - wy0
            x = min(max(math.floor(gx + 0.5), 0), ww - 1)
            y = min(max(math.floor(gy + 0.5), 0), hh - 1)
            acc += float(smooth[wy0 + y, wx0 + x])
        raw[b] = 0.25 * acc
    out = np.empty(nb, dtype=np.float32)
    for b in range(nb):
        lo, hi = max(b - 1, 0), min(b + 1, nb - 1)
        acc = 0.0
        for k in range(lo, hi + 1):
            acc += raw[k]
        out[b] = np.float32(acc / (hi - lo + 1))
    return out


@kernel
def _end_stops(smooth, wy0, wx0, ys, xs, n, s_of, s_lo, s_hi, tolerance, fade_step, side, side_s0):  # pragma: no cover
    """How far (px along the axis) the body may extend beyond each end of its core: ``(beyond s_hi,
    beyond s_lo)``, infinite where nothing lies beyond.

    Beyond each end of the core the body can only fade: a cone's attenuation falls steadily to its
    apex, a flat end's within the blur. Walking outward in 1-px slices, the body ends where the
    slice's contrast stops falling (over ``fade_step`` slices, by more than ``tolerance``), or where
    the slice is wider than the body along its core (1.2 x the median slice width + 2): what
    continues at a steady level or widens is something else, such as a vessel the robot touches.
    The contrast is the slice's strongest pixel above the attenuation beside the body there
    (``side``, per 1-px slice from ``s = side_s0``; :func:`_side_baseline`): a cone tip entering a
    wider vessel gains the vessel's attenuation both on and beside the body, and still fades (its
    strongest pixel alone rises there); a vessel continuing beyond a flat end is stronger on the axis
    than beside it, and stays. ``ys, xs`` (window px) and ``s_of`` (their axial coordinates) list
    the body's ``n`` pixels."""
    nbins_core = math.floor(s_hi - s_lo) + 1
    core_width = np.zeros(max(nbins_core, 1) + 1, dtype=np.int64)
    top_bin = -1
    far_hi, far_lo = 0.0, 0.0
    for i in range(n):
        p = s_of[i]
        if p >= s_lo and p <= s_hi:
            b = math.floor(p - s_lo)
            core_width[b] += 1
            top_bin = max(top_bin, b)
        far_hi = max(far_hi, p - s_hi)
        far_lo = max(far_lo, s_lo - p)
    if top_bin < 0:
        max_width = 2.0
    else:
        counts = core_width[:top_bin + 1].astype(np.float64)
        max_width = 1.2 * float(median_inplace(counts, top_bin + 1)) + 2.0
    stops = np.full(2, np.inf)
    nside = side.size
    for end in range(2):
        sign = 1.0 if end == 0 else -1.0
        start = s_hi if end == 0 else s_lo
        far = far_hi if end == 0 else far_lo
        if not far > 0.0:
            continue
        nb = math.floor(far) + 1
        peak = np.full(nb, -np.inf)
        width = np.zeros(nb, dtype=np.int64)
        for i in range(n):
            beyond = sign * (s_of[i] - start)
            if beyond > 0.0:
                b = math.floor(beyond)
                peak[b] = max(peak[b], float(smooth[wy0 + ys[i], wx0 + xs[i]]))
                width[b] += 1
        stop = nb
        # A slice without pixels is a gap of the pixel grid, not of the body (the mask is connected):
        # an axis along a pixel row puts every pixel an integer distance beyond the core's last one,
        # and slice 0 stayed empty, which cut every such body at its core's end. It takes the
        # contrast of the slice before it (of the first slice with pixels, before the first).
        last = -np.inf
        for b in range(nb):
            if math.isfinite(peak[b]):
                k = math.floor(start + sign * (b + 0.5) - side_s0)
                peak[b] -= side[min(max(k, 0), nside - 1)]
                if not math.isfinite(last):
                    for j in range(b):
                        peak[j] = peak[b]
                last = peak[b]
            else:
                peak[b] = last
        for b in range(nb):
            if (width[b] > max_width
                    or (b >= fade_step and peak[b] > peak[b - fade_step] - tolerance)):
                stop = b
                break
        stops[end] = stop
    return stops


#: Bytes of :func:`fill_values_into`'s scratch per line of the support's box (``max(sh, sw)`` lines): each line's
#: first and last supported pixel (int64), its two end means and their smoothing (float32), its line (float64).
FILL_SCRATCH_PER_LINE = 2 * 8 + 4 * 4 + 3 * 8


@kernel
def _fill_values(smooth, wy0, wx0, hh, ww, support, sy0, sy1, sx0, sx1, fill_rows, fill_cols,
                 transpose, out):  # pragma: no cover - compiled
    """:func:`fill_values_into` with a scratch of its own."""
    lines = max(sy1 - sy0, sx1 - sx0, 0)
    scratch = np.empty(FILL_SCRATCH_PER_LINE * lines, dtype=np.uint8)
    fill_values_into(smooth, wy0, wx0, hh, ww, support, sy0, sy1, sx0, sx1, fill_rows, fill_cols, transpose, out,
                     scratch)


@kernel
def fill_values_into(smooth, wy0, wx0, hh, ww, support, sy0, sy1, sx0, sx1, fill_rows, fill_cols,
                     transpose, out, scratch):  # pragma: no cover - compiled
    """The background under the body, written into ``out`` on the support (window px).

    Each column (a row if ``transpose``) crossing the support has its supported run replaced by the
    straight line between the means of ``fill_rows`` pixels beyond either end (clamped to the window),
    those means smoothed over ``fill_cols`` neighbouring lines (edge-replicated). Exact for a vessel
    crossing the robot, only slightly low for a vessel it lies in. ``support`` covers the box
    ``[sy0, sy1) x [sx0, sx1)`` of the window; each line crosses it once (it is convex). ``scratch``
    (uint8) holds at least :data:`FILL_SCRATCH_PER_LINE` ``x max(sy1 - sy0, sx1 - sx0)`` bytes: no
    allocation here (issue 8: the lean pass passes a part of its workspace)."""
    if transpose:
        line_len, l0, l1 = ww, sy0, sy1
    else:
        line_len, l0, l1 = hh, sx0, sx1
    nl = l1 - l0
    if nl <= 0 or sy1 <= sy0 or sx1 <= sx0:
        return
    cap = max(sy1 - sy0, sx1 - sx0)
    ends = scratch[:16 * cap].view(np.int64)
    firsts, lasts = ends[:nl], ends[cap:cap + nl]
    values = scratch[16 * cap:32 * cap].view(np.float32)
    lines = scratch[32 * cap:56 * cap].view(np.float64)
    # Each line's first and last supported pixel, in one pass over the support in its memory order (the
    # column-wise searches this replaced read it across rows; issue 8). Branch-free, unsigned indices.
    for j in range(nl):
        firsts[j], lasts[j] = -1, -1
    sw = sx1 - sx0
    if transpose:
        for j in range(nl):
            srow = support[j]
            first, last = -1, -1
            for x in range(sw - 1, -1, -1):
                first = x if srow[x] else first
            for x in range(sw):
                last = x if srow[x] else last
            if first >= 0:
                firsts[j], lasts[j] = first + sx0, last + sx0
    else:
        ufirst = firsts[:sw]
        ulast = lasts[:sw]
        for r in range(sy1 - 1, sy0 - 1, -1):
            srow = support[r - sy0]
            for x in range(np.uint64(sw)):
                ufirst[x] = r if srow[x] else ufirst[x]
        for r in range(sy0, sy1):
            srow = support[r - sy0]
            for x in range(np.uint64(sw)):
                ulast[x] = r if srow[x] else ulast[x]
    c0, c1 = -1, -1
    for j in range(nl):
        if firsts[j] >= 0:
            if c0 < 0:
                c0 = j
            c1 = j + 1
    if c0 < 0:
        return
    nc = c1 - c0
    tops, bottoms = firsts[c0:c1], lasts[c0:c1]
    for i in range(nc):
        tops[i] -= 1
        bottoms[i] += 1
    c0 += l0
    c1 += l0
    v_top, v_bottom = values[:nc], values[cap:cap + nc]
    third = np.float32(fill_rows)
    for i in range(nc):
        c = c0 + i
        top, bottom = tops[i], bottoms[i]
        acc_t = np.float32(0.0)
        acc_b = np.float32(0.0)
        for k in range(fill_rows):
            rt, rb = max(top - k, 0), min(bottom + k, line_len - 1)
            if transpose:
                acc_t += smooth[wy0 + c, wx0 + rt]
                acc_b += smooth[wy0 + c, wx0 + rb]
            else:
                acc_t += smooth[wy0 + rt, wx0 + c]
                acc_b += smooth[wy0 + rb, wx0 + c]
        v_top[i] = acc_t / third
        v_bottom[i] = acc_b / third
    if nc >= fill_cols:
        half = fill_cols // 2
        kern = np.float32(1.0) / np.float32(fill_cols)
        sm_t, sm_b = values[2 * cap:2 * cap + nc], values[3 * cap:3 * cap + nc]
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
    # float32 difference, float64 line: the arithmetic of the numpy code this replaced. Each line's
    # supported run lies inside the support's box: only its pixels are written (a line crossing no
    # support pixel has no run).
    if transpose:
        for i in range(nc):
            c = c0 + i
            top, bottom = tops[i], bottoms[i]
            span = float(np.float32(bottom - top))
            vt, rise = float(v_top[i]), float(v_bottom[i] - v_top[i])
            for r in range(max(top + 1, sx0), bottom):
                value = np.float32(vt + rise * ((float(np.float32(r)) - top) / span))
                if support[c - sy0, r - sx0]:
                    out[c, r] = value
        return
    # Lines are columns: filled row by row (the arrays' order, every line's division in one vector
    # loop) with each pixel's value as its column gives it.
    vts, rises, spans = lines[:nc], lines[cap:cap + nc], lines[2 * cap:2 * cap + nc]
    for i in range(nc):
        vts[i], rises[i] = float(v_top[i]), float(v_bottom[i] - v_top[i])
        spans[i] = float(np.float32(bottoms[i] - tops[i]))
    for r in range(sy0, sy1):
        rf = float(np.float32(r))
        for i in range(nc):
            if tops[i] < r and r < bottoms[i] and support[r - sy0, c0 + i - sx0]:
                out[r, c0 + i] = np.float32(vts[i] + rises[i] * ((rf - tops[i]) / spans[i]))


# The background under the body, along the structure it lies on. ``s`` runs along the axis from the
# core's centroid ``ox, oy`` (unit ``ax, ay``), ``t`` across it; the body's support lies inside the
# strip ``|t| <= half_t``, and the background is read on the strip's two sides, beyond ``half_t``.
@kernel
def _smooth_at(smooth, wy0, wx0, hh, ww, s_, t_, ox, oy, ax, ay):  # pragma: no cover - compiled
    """The smoothed image at body-frame point ``(s_, t_)``, bilinear, clamped to the window."""
    x = min(max(s_ * ax - t_ * ay + ox - wx0, 0.0), ww - 1.0)
    y = min(max(s_ * ay + t_ * ax + oy - wy0, 0.0), hh - 1.0)
    ix, iy = min(int(x), max(ww - 2, 0)), min(int(y), max(hh - 2, 0))
    fx, fy = x - ix, y - iy
    jx, jy = min(ix + 1, ww - 1), min(iy + 1, hh - 1)
    r0 = float(smooth[wy0 + iy, wx0 + ix]) * (1.0 - fx) + float(smooth[wy0 + iy, wx0 + jx]) * fx
    r1 = float(smooth[wy0 + jy, wx0 + ix]) * (1.0 - fx) + float(smooth[wy0 + jy, wx0 + jx]) * fx
    return r0 * (1.0 - fy) + r1 * fy


@kernel
def _at(profile, s_lo, s_):  # pragma: no cover - compiled
    """``profile`` (samples 1 px apart from ``s_lo``) at ``s_``, linear, clamped to its ends."""
    f = min(max(s_ - s_lo, 0.0), profile.size - 1.000001)
    i = int(f)
    w = f - i
    return profile[i] * (1.0 - w) + profile[i + 1] * w


#: Directions tried for the background's lines: across the axis, then 15-degree steps either side
#: (up to ``_MAX_SHEAR``, 75 degrees off it), refined by halving steps around the best (to
#: within a degree: a vessel's edge then lies within ~0.5 px of where it is across a 30 px strip).
_DIRECTION_STEP = math.radians(15.0)
_DIRECTION_STEPS = 5
_REFINE_STEPS = 4
#: Spacing (px along the axis) of the lines whose ends score a direction: the vessels are 4-5 times wider.
_SCORE_SPACING = 4.0


@kernel
def _shear_score(left, right, s_lo, s0, s1, reach, kappa):  # pragma: no cover - compiled
    """How much background the two sides agree on along lines of shear ``kappa`` (``ds/dt``): the mean,
    over lines crossing the axis every ``_SCORE_SPACING`` px along the body, of the lower of the two
    sides' values where the line meets them (``reach`` from the axis)."""
    acc, n = 0.0, 0
    s_ = s0
    while s_ <= s1:
        acc += min(_at(left, s_lo, s_ - reach * kappa), _at(right, s_lo, s_ + reach * kappa))
        n += 1
        s_ += _SCORE_SPACING
    return acc / max(n, 1)


@kernel
def _side_mismatch(left, right, s_lo, s0, s1, reach, kappa):  # pragma: no cover - compiled
    """How much the two sides differ along lines of shear ``kappa``: the mean, over the lines of
    :func:`_shear_score`, of the absolute difference of the two sides' values where the line meets them."""
    acc, n = 0.0, 0
    s_ = s0
    while s_ <= s1:
        acc += abs(_at(left, s_lo, s_ - reach * kappa) - _at(right, s_lo, s_ + reach * kappa))
        n += 1
        s_ += _SCORE_SPACING
    return acc / max(n, 1)


#: Oblique lines are taken only where the two sides match along them this much better than across.
_MATCH_FRACTION = 0.5


@kernel
def background_shear(left, right, s_lo, s0, s1, reach, max_shear, margin):  # pragma: no cover - compiled
    """The shear ``ds/dt`` of the lines along which the background under the body is interpolated: 0
    (across the axis) unless lines in another direction find more background at both of their ends,
    by ``margin`` on average over the body, and the two sides match along them (mean absolute
    difference under ``_MATCH_FRACTION`` of the one across): the direction of a straight vessel the
    robot crosses obliquely (then both ends of the lines along it lie in the vessel, and of lines
    across it only one, and one side's profile is the other's shifted). A vessel that curls around
    the body (lying beside it on both sides, not under it) can put both ends of some oblique lines in
    it, but the sides do not match along them. ``left``/``right`` sample the two sides 1 px apart from
    ``s_lo``; ``reach`` is their distance from the axis; shears beyond ``max_shear`` are not tried."""
    across = _shear_score(left, right, s_lo, s0, s1, reach, 0.0)
    best_angle, best = 0.0, across
    for k in range(1, _DIRECTION_STEPS + 1):
        for sign in (-1.0, 1.0):
            angle = sign * k * _DIRECTION_STEP
            kappa = math.tan(angle)
            if abs(kappa) > max_shear:
                continue
            score = _shear_score(left, right, s_lo, s0, s1, reach, kappa)
            if score > best:
                best_angle, best = angle, score
    delta = 0.5 * _DIRECTION_STEP
    for _ in range(_REFINE_STEPS):
        centre = best_angle
        for angle in (centre - delta, centre + delta):
            kappa = math.tan(angle)
            if abs(kappa) > max_shear:
                continue
            score = _shear_score(left, right, s_lo, s0, s1, reach, kappa)
            if score > best:
                best_angle, best = angle, score
        delta *= 0.5
    if not best > across + margin:
        return 0.0
    kappa = math.tan(best_angle)
    if not (_side_mismatch(left, right, s_lo, s0, s1, reach, kappa)
            < _MATCH_FRACTION * _side_mismatch(left, right, s_lo, s0, s1, reach, 0.0)):
        return 0.0
    return kappa


#: The steepest lines (degrees off the across-axis direction) the background is interpolated along.
_MAX_SHEAR = math.tan(math.radians(75.0))


@kernel
def _end_profile(smooth, wy0, wx0, hh, ww, ox, oy, ax, ay, s_end, sign, half_t, depth):  # pragma: no cover
    """The attenuation just beyond one end of the support (``s = s_end``, outward along ``sign``): per
    1 px across the strip from ``t = -half_t``, the mean of the smoothed image at 1..``depth`` px beyond."""
    nt = int(math.floor(2.0 * half_t)) + 2
    out = np.empty(nt)
    for i in range(nt):
        t_ = -half_t + i
        acc = 0.0
        for d in range(1, depth + 1):
            acc += _smooth_at(smooth, wy0, wx0, hh, ww, s_end + sign * d, t_, ox, oy, ax, ay)
        out[i] = acc / depth
    return out


@kernel
def _fill_across(smooth, wy0, wx0, hh, ww, ox, oy, ax, ay, s0, s1, half_t, depth, margin, open_lo, open_hi,
                 ys, xs, n, out):  # pragma: no cover - compiled
    """The background at the ``n`` window pixels ``(ys, xs)`` of the support, written into ``out``.

    The support is the rectangle ``s0 <= s <= s1``, ``|t| <= half_t``. Each pixel's background is
    linear along a line across the strip ``|t| <= half_t``, between the attenuation just beyond its
    two sides (the mean of the smoothed image at 1..``depth`` px beyond, read along the line's own
    direction, so that a structure running that way is read where the line continues). The lines
    are across the axis unless a vessel crosses the body obliquely (:func:`background_shear`): then
    they run along it, and its attenuation under the body is the one on either side where it enters
    and leaves the strip (across the axis, its band under the body came out smeared into a wedge).
    The sides reach beyond the body's ends where the lines are oblique (up to ``half_t + depth`` px;
    lines that would meet them further out take the value there), so the faint apex of a cone that
    lies beyond the support is never read as background.

    Returns the lowest and the highest attenuation found around the body: on the sides along the body
    and beyond each ``open`` end (one the body keeps its width to: a flat end; beyond a cone's the
    support is followed by its faint apex). A structure the lines miss (a vessel that ends under the
    body, or one it lies in) still shows there, so the blob's clutter stays honest about it."""
    # The sides are read from ``ext`` px before the support to ``ext`` px beyond it, and no further
    # (lines that would meet them further out take the value there): the tracker's region of interest
    # holds that much around the body (its margin counts from the body's edge), so a blob comes out the
    # same from it as from the full frame.
    span = 2.0 * half_t + depth
    max_shear = _MAX_SHEAR
    ext = half_t + depth
    s_lo = s0 - ext
    ns = int(math.floor(s1 + ext - s_lo)) + 1
    # The sides, sampled 1 px apart along the axis at each depth beyond the strip: the middle depth
    # as far as any shear tried reaches (it chooses the shear), the others as far as the chosen one.
    left = np.zeros((depth, ns))
    right = np.zeros((depth, ns))
    mid = (depth - 1) // 2
    for i in range(ns):
        s_ = s_lo + i
        left[mid, i] = _smooth_at(smooth, wy0, wx0, hh, ww, s_, -(half_t + mid + 1.0), ox, oy, ax, ay)
        right[mid, i] = _smooth_at(smooth, wy0, wx0, hh, ww, s_, half_t + mid + 1.0, ox, oy, ax, ay)
    kappa = background_shear(left[mid], right[mid], s_lo, s0, s1, half_t + mid + 1.0, max_shear, margin)
    reach_all = span * abs(kappa) + 2.0
    i_lo = max(int(math.floor(s0 - reach_all - s_lo)), 0)
    i_hi = min(int(math.ceil(s1 + reach_all - s_lo)) + 1, ns)
    for d in range(depth):
        if d == mid:
            continue
        tl, tr = -(half_t + d + 1.0), half_t + d + 1.0
        for i in range(i_lo, i_hi):
            s_ = s_lo + i
            left[d, i] = _smooth_at(smooth, wy0, wx0, hh, ww, s_, tl, ox, oy, ax, ay)
            right[d, i] = _smooth_at(smooth, wy0, wx0, hh, ww, s_, tr, ox, oy, ax, ay)
    # Per line (by where it crosses the axis, 1 px apart), the values beyond its two ends.
    c_lo = s0 - half_t * abs(kappa) - 1.0
    nc = int(math.floor(s1 + half_t * abs(kappa) + 1.0 - c_lo)) + 2
    end_l = np.empty(nc)
    end_r = np.empty(nc)
    for j in range(nc):
        c = c_lo + j
        acc_l, acc_r = 0.0, 0.0
        for d in range(depth):
            reach = half_t + d + 1.0
            acc_l += _at(left[d], s_lo, c - reach * kappa)
            acc_r += _at(right[d], s_lo, c + reach * kappa)
        end_l[j], end_r[j] = acc_l / depth, acc_r / depth
    rim_lo, rim_hi = np.inf, -np.inf
    for i in range(ns):
        s_ = s_lo + i
        if s_ >= s0 and s_ <= s1:
            for side in range(2):
                acc = 0.0
                for d in range(depth):
                    acc += left[d, i] if side == 0 else right[d, i]
                rim_lo, rim_hi = min(rim_lo, acc / depth), max(rim_hi, acc / depth)
    for end in range(2):
        if (open_lo if end == 0 else open_hi):
            profile = _end_profile(smooth, wy0, wx0, hh, ww, ox, oy, ax, ay, s0 if end == 0 else s1,
                                   -1.0 if end == 0 else 1.0, half_t, depth)
            rim_lo, rim_hi = min(rim_lo, profile.min()), max(rim_hi, profile.max())
    inv = 0.5 / half_t if half_t > 0 else 0.0
    for i in range(n):
        gx, gy = (wx0 + xs[i]) - ox, (wy0 + ys[i]) - oy
        s_, t_ = gx * ax + gy * ay, -gx * ay + gy * ax
        c = s_ - t_ * kappa
        w_r = min(max((t_ + half_t) * inv, 0.0), 1.0)
        value = _at(end_l, c_lo, c) * (1.0 - w_r) + _at(end_r, c_lo, c) * w_r
        out[ys[i], xs[i]] = np.float32(value)
    return rim_lo, rim_hi


@kernel
def _dilated_box(ys, xs, n, half_widths, hh, ww):  # pragma: no cover - compiled
    """The pixels ``(ys, xs)[:n]`` dilated by the row spans ``half_widths``, on their bounding box grown
    by the element's radius and clipped to ``hh x ww``: ``(mask, y0, x0)``."""
    src, y0, x0 = _box_mask(ys, xs, n, (half_widths.size - 1) // 2, hh, ww)
    return dilate_runs(src, half_widths), y0, x0


@kernel
def _ring_values(ys, xs, n, outer_hw, inner_hw, hh, ww, smooth, wy0, wx0):  # pragma: no cover - compiled
    """The smoothed image (window ``hh x ww`` at ``wy0, wx0``) on the ring around the pixels ``(ys, xs)[:n]``:
    their dilation by the row spans ``outer_hw`` less their dilation by ``inner_hw`` (or less the pixels
    themselves if that is one pixel wide), on the bounding box grown by the outer radius, in raster order;
    ``(values, count)``. The same pixels as :func:`_dilated_box` and :func:`dilate_runs` twice, in one pass:
    both dilations' marks from the same runs, one prefix sum over both."""
    g = (inner_hw.size - 1) // 2
    src, y0, x0 = _box_mask(ys, xs, n, (outer_hw.size - 1) // 2, hh, ww)
    h, w = src.shape
    marks = np.zeros((2, h, w + 1), dtype=np.int32)
    marks_o, marks_i = marks[0], marks[1]
    for y in range(h):
        start, end = _next_run(src, y, 0)
        while start < w:
            _mark_run(marks_o, y, start, end, outer_hw)
            if g > 0:
                _mark_run(marks_i, y, start, end, inner_hw)
            start, end = _next_run(src, y, end)
    values = np.empty(h * w, dtype=np.float32)
    count = 0
    for y in range(h):
        acc_o, acc_i = 0, 0
        for x in range(w):
            acc_o += marks_o[y, x]
            acc_i += marks_i[y, x]
            inner = acc_i > 0 if g > 0 else src[y, x] != 0
            if acc_o > 0 and not inner:
                values[count] = smooth[wy0 + y0 + y, wx0 + x0 + x]
                count += 1
    return values, count


@kernel
def _capsule_columns(gy, ax, ay, lo_s, hi_s, half_width, cx, ww):  # pragma: no cover - compiled
    """Of a window row at ``gy`` (px) from the centre along y, the columns ``[c0, c1)`` outside which no
    pixel has ``lo_s <= s <= hi_s`` and ``|t| <= half_width`` (``s = gx ax + gy ay``, ``t = -gx ay + gy ax``,
    ``gx = column - cx``; ``ax, ay`` unit): the two slabs' intersection widened by 2 px, far beyond any
    rounding of ``s`` and ``t`` (the slabs' bounds are only used where the axis' component is > 1e-6)."""
    lo, hi = -np.inf, np.inf
    if abs(ax) > 1e-6:
        u0, u1 = (lo_s - gy * ay) / ax, (hi_s - gy * ay) / ax
        lo, hi = max(lo, min(u0, u1)), min(hi, max(u0, u1))
    if abs(ay) > 1e-6:
        u0, u1 = (gy * ax - half_width) / ay, (gy * ax + half_width) / ay
        lo, hi = max(lo, min(u0, u1)), min(hi, max(u0, u1))
    if not lo <= hi:
        return 0, 0
    c0 = 0 if lo + cx - 2.0 < 0.0 else (ww if lo + cx - 2.0 > ww else math.floor(lo + cx - 2.0))
    c1 = ww if hi + cx + 3.0 > ww else (0 if hi + cx + 3.0 < 0.0 else math.ceil(hi + cx + 3.0))
    return c0, c1


@kernel
def _not_refined():  # pragma: no cover - compiled
    """:func:`refine`'s result for a component that is not a plausible robot (built only where returned:
    three allocations on every call otherwise)."""
    return 0, np.zeros((0, 0), dtype=np.float32), np.zeros((0, 0), dtype=np.uint8), np.zeros(13)


@kernel
def refine(a, smooth, labels, label, bx, by, bw, bh, sigma, p, ring_outer, ring_inner, near_hw):  # pragma: no cover
    """One detected component refined into the robot's weights (see segmentation._blob_from_component).

    ``p`` holds the settings: ``[min_peak_attenuation, core_fraction, min_pixels, max_extent_px,
    max_elongation, cone_reach, support_dilate_px, support_sigma, support_fraction, smooth_gain,
    fill_rows, fill_cols, fade_step, background_along_structure (0/1), direction_margin]``;
    ``ring_outer``/``ring_inner``/``near_hw`` the row spans of the dilations (ring and weighted support).
    The background under the body is :func:`_fill_values` (along image columns or rows), or with
    ``background_along_structure`` :func:`_fill_across` (along a strip's lines, oblique along a vessel
    crossing the body; the clutter then also counts what the strip's sides and flat ends see).

    Returns ``(status, weights, mask, scalars)``: status 0 if the component is not a plausible robot;
    ``scalars`` ``[y0, y1, x0, x1, peak above baseline, baseline, strength, centroid x, centroid y
    (window px), edge, minor moment, clutter, pixel count]``, where ``y0:y1, x0:x1`` (``a``'s pixels,
    the bounding box of the weighted pixels) is the window on which ``weights`` and ``mask`` sit.
    (One float array for all the numbers: each array a kernel returns costs a boxing in Python.)

    Pixels are visited as lists (flood fills from the core), so the cost follows the body, not the
    window around it."""
    min_peak, core_fraction = p[0], p[1]
    min_pixels, max_extent = int(p[2]), p[3]
    max_elongation, cone_reach = p[4], p[5]
    dilate_px, support_sigma, support_fraction = int(p[6]), p[7], p[8]
    smooth_gain, fill_rows, fill_cols, fade_step = p[9], int(p[10]), int(p[11]), int(p[12])
    along_structure, direction_margin = p[13] != 0.0, p[14]
    sigma_s = sigma * smooth_gain
    # The component's peak (its first maximum in raster order) and its core: the part above
    # core_fraction of the peak, 8-connected to it.
    # (Rows are sliced first throughout: indices from range(0, n) are known non-negative, so the
    # compiled loops carry no wraparound test and vectorise.)
    peak32, py, px = np.float32(-np.inf), -1, -1
    for y in range(bh):
        lrow, srow = labels[by + y, bx:bx + bw], smooth[by + y, bx:bx + bw]
        for x in range(bw):
            if lrow[x] == label and srow[x] > peak32:
                peak32, py, px = srow[x], by + y, bx + x
    peak = float(peak32)
    if peak < min_peak:
        return _not_refined()
    level32 = np.float32(core_fraction * peak)
    strong = np.empty((bh, bw), dtype=np.uint8)
    for y in range(bh):
        lrow, srow, out_row = labels[by + y, bx:bx + bw], smooth[by + y, bx:bx + bw], strong[y]
        for x in range(bw):
            out_row[x] = (lrow[x] == label) & (srow[x] >= level32)  # no branch: vectorised
    seen = np.zeros((bh, bw), dtype=np.uint8)
    # (Arrays of the same type in one allocation each: a kernel's allocations are ~10 % of a steady pair.)
    core = np.empty((2, bh * bw), dtype=np.int64)
    cys, cxs = core[0], core[1]
    seed = np.empty((2, 1), dtype=np.int64)
    seed[0, 0], seed[1, 0] = py - by, px - bx
    seed_y, seed_x = seed[0], seed[1]
    n = _scanline_fill(strong, seen, seed_y, seed_x, 1, cys, cxs, 0)
    if n < min_pixels:
        return _not_refined()
    sx = sy = 0
    xmin, xmax, ymin, ymax = bw, -1, bh, -1
    for i in range(n):
        sx += cxs[i]
        sy += cys[i]
        xmin, xmax = min(xmin, cxs[i]), max(xmax, cxs[i])
        ymin, ymax = min(ymin, cys[i]), max(ymax, cys[i])
    if max(xmax - xmin, ymax - ymin) + 1 > max_extent:
        return _not_refined()
    cx, cy = sx / n, sy / n
    # The scatter summed in raster order, as the numpy code did: a body at 45 degrees has equal
    # diagonal terms, and the rounding then picks the background fill's direction.
    sxx = syy = sxy = 0.0
    for y in range(ymin, ymax + 1):
        for x in range(xmin, xmax + 1):
            if seen[y, x]:
                dx, dy = x - cx, y - cy
                sxx += dx * dx
                syy += dy * dy
                sxy += dx * dy
    l1, l2, ax, ay = _principal(sxx, syy, sxy, n)
    if math.sqrt(l1 / max(l2, 1e-3)) > max_elongation:
        return _not_refined()
    s_min, s_max, t_max = np.inf, -np.inf, 0.0
    for i in range(n):
        dx, dy = cxs[i] - cx, cys[i] - cy
        s_ = dx * ax + dy * ay
        t_ = abs(-dx * ay + dy * ax)
        s_min, s_max, t_max = min(s_min, s_), max(s_max, s_), max(t_max, t_)
    core_len = s_max - s_min
    reach = cone_reach * core_len + 3.0  # how far beyond the core a faint cone tip may go
    pad = dilate_px + 1.0
    half_width = t_max + pad + 2.0
    grow = math.ceil(reach + half_width + pad + fill_rows + 2)
    H, W = a.shape
    wx0, wy0 = max(0, bx + xmin - grow), max(0, by + ymin - grow)
    wx1, wy1 = min(W, bx + xmax + grow + 1), min(H, by + ymax + grow + 1)
    hh, ww = wy1 - wy0, wx1 - wx0
    ox, oy = bx + cx, by + cy  # the core's centroid in a's pixels
    # Core pixels in window coordinates.
    for i in range(n):
        cys[i] += by - wy0
        cxs[i] += bx - wx0
    # The local baseline: the median of a ring around the core.
    ring_vals, nr = _ring_values(cys, cxs, n, ring_outer, ring_inner, hh, ww, smooth, wy0, wx0)
    baseline = float(median_f32(ring_vals, nr)) if nr > 0 else 0.0
    height = peak - baseline
    if height < min_peak:
        return _not_refined()
    # The body: above the attenuation beside it by ``level``, inside the capsule, 8-connected to the core.
    level = max(support_sigma * sigma_s, support_fraction * height)
    lvl32 = np.float32(level)
    lo_s, hi_s = s_min - reach, s_max + reach
    nside = math.floor(hi_s - lo_s) + 1
    side = _side_baseline(smooth, wy0, wx0, hh, ww, ox, oy, ax, ay, lo_s, nside, half_width + 1.0)
    # Above the lowest of those baselines first (vectorised), then the few pixels that are tested
    # against their own slice's (a gather on every pixel of the window cost ~35 % of the kernel). The
    # result is the same: float32 subtraction is monotonic, so a pixel above its slice's baseline is
    # above the lowest one.
    # Only the columns of each row that the capsule can reach are tested (_capsule_columns: the
    # capsule is a rotated rectangle, a third of its window or less); the others are outside it.
    low32 = side.min()
    above = np.zeros((hh, ww), dtype=np.uint8)
    for y in range(hh):
        gy = (wy0 + y) - oy
        c0, c1 = _capsule_columns(gy, ax, ay, lo_s, hi_s, half_width, ox - wx0, ww)
        if c1 <= c0:
            continue
        srow, arow = smooth[wy0 + y, wx0 + c0:wx0 + c1], above[y, c0:c1]
        for j in range(c1 - c0):
            gx = (wx0 + c0 + j) - ox
            s_, t_ = gx * ax + gy * ay, -gx * ay + gy * ax
            arow[j] = (((srow[j] - low32) > lvl32) & (abs(t_) <= half_width)  # no branch: vectorised
                       & (s_ >= lo_s) & (s_ <= hi_s))
        for j in range(c1 - c0):
            if arow[j]:
                k = min(max(int(((wx0 + c0 + j) - ox) * ax + gy * ay - lo_s), 0), nside - 1)
                if not (srow[j] - side[k]) > lvl32:
                    arow[j] = 0
    mask = np.zeros((hh, ww), dtype=np.uint8)
    body_px = np.empty((2, hh * ww), dtype=np.int64)
    mys, mxs = body_px[0], body_px[1]
    m = _scanline_fill(above, mask, cys, cxs, n, mys, mxs, 0)
    for i in range(n):  # the core belongs to the body even where it is below the level
        y, x = cys[i], cxs[i]
        if not mask[y, x]:
            mask[y, x] = 1
            mys[m], mxs[m] = y, x
            m += 1
    st_of = np.empty((2, m))
    s_of, t_of = st_of[0], st_of[1]
    for i in range(m):
        gx, gy = (wx0 + mxs[i]) - ox, (wy0 + mys[i]) - oy
        s_of[i] = gx * ax + gy * ay
        t_of[i] = -gx * ay + gy * ax
    tolerance = 3.0 * sigma_s * math.sqrt(2.0)
    stops = _end_stops(smooth, wy0, wx0, mys, mxs, m, s_of, s_min, s_max, tolerance, fade_step, side, lo_s)
    count = 0
    in_lo, in_hi, in_t = np.inf, -np.inf, -np.inf
    for i in range(m):
        s_ = s_of[i]
        if (s_ - s_max) < stops[0] and -(s_ - s_min) < stops[1]:
            mys[count], mxs[count] = mys[i], mxs[i]
            s_of[count], t_of[count] = s_, t_of[i]
            count += 1
            in_lo, in_hi, in_t = min(in_lo, s_), max(in_hi, s_), max(in_t, abs(t_of[i]))
        else:
            mask[mys[i], mxs[i]] = 0
    if count == 0:
        return _not_refined()
    # The support: a rectangle around the body (along its axis), on its bounding box in the window.
    lo_t, hi_s_, lo_s_, hi_t = in_t + pad, in_hi + pad, in_lo - pad, in_t + pad
    corners = np.empty((2, 4))
    gxs, gys = corners[0], corners[1]
    for k in range(4):
        s_ = lo_s_ if k < 2 else hi_s_
        t_ = -lo_t if k % 2 == 0 else hi_t
        gxs[k] = s_ * ax - t_ * ay + ox - wx0
        gys[k] = s_ * ay + t_ * ax + oy - wy0
    sy0, sy1 = max(math.floor(gys.min()) - 1, 0), min(math.ceil(gys.max()) + 2, hh)
    sx0, sx1 = max(math.floor(gxs.min()) - 1, 0), min(math.ceil(gxs.max()) + 2, ww)
    support = np.zeros((max(sy1 - sy0, 0), max(sx1 - sx0, 0)), dtype=np.uint8)
    edge = False
    for y in range(sy0, sy1):
        gy = (wy0 + y) - oy
        border_row = y < fill_rows or y >= hh - fill_rows
        for x in range(sx0, sx1):
            gx = (wx0 + x) - ox
            s_, t_ = gx * ax + gy * ay, -gx * ay + gy * ax
            if s_ >= lo_s_ and s_ <= hi_s_ and abs(t_) <= hi_t:
                if border_row or x < fill_rows or x >= ww - fill_rows:
                    # The rectangle reaches the window's edge: only possible where the window was
                    # clipped by the searched region, i.e. the robot may be cut; keep the
                    # interpolation inside.
                    edge = True
                else:
                    support[y - sy0, x - sx0] = 1
    # Weigh only near the body: every background pixel adds noise to the moments, more so far out.
    near, ny0, nx0 = _dilated_box(mys, mxs, count, near_hw, hh, ww)
    nh, nw = near.shape
    ky0, ky1, kx0, kx1 = hh, -1, ww, -1
    near_px = np.empty((2, nh * nw), dtype=np.int64)
    fys, fxs = near_px[0], near_px[1]
    nf = 0
    for y in range(nh):
        for x in range(nw):
            yy, xx = ny0 + y, nx0 + x
            inside = (near[y, x] and yy >= sy0 and yy < sy1 and xx >= sx0 and xx < sx1
                      and support[yy - sy0, xx - sx0])
            near[y, x] = 1 if inside else 0
            if inside:
                ky0, ky1, kx0, kx1 = min(ky0, yy), max(ky1, yy), min(kx0, xx), max(kx1, xx)
                fys[nf], fxs[nf] = yy, xx
                nf += 1
    # (Along the structure:) an end is open where the body keeps half its width within 3 px of it (a
    # flat end; a cone's apex, cut at the body's level, is much narrower there).
    w_lo, w_hi = 0.0, 0.0
    for i in range(count):
        if s_of[i] <= in_lo + 3.0:
            w_lo = max(w_lo, abs(t_of[i]))
        if s_of[i] >= in_hi - 3.0:
            w_hi = max(w_hi, abs(t_of[i]))
    # Only the support's pixels are written and read (its box ends at sy1, sx1): no need to clear the rest
    # of the window.
    background = np.zeros((max(sy1, 0), max(sx1, 0)), dtype=np.float32)
    bmin, bmax = np.inf, -np.inf
    if along_structure:
        bmin, bmax = _fill_across(smooth, wy0, wx0, hh, ww, ox, oy, ax, ay, lo_s_, hi_s_, hi_t, fill_rows,
                                  direction_margin * sigma_s, w_lo >= 0.5 * in_t, w_hi >= 0.5 * in_t, fys, fxs,
                                  nf, background)
    else:
        _fill_values(smooth, wy0, wx0, hh, ww, support, sy0, sy1, sx0, sx1, fill_rows, fill_cols,
                     abs(ax) < abs(ay), background)
    for i in range(nf):
        b = float(background[fys[i], fxs[i]])
        bmin, bmax = min(bmin, b), max(bmax, b)
    any_near = ky1 >= 0
    for i in range(count):  # the weights' window holds the mask too
        ky0, ky1, kx0, kx1 = min(ky0, mys[i]), max(ky1, mys[i]), min(kx0, mxs[i]), max(kx1, mxs[i])
    ky1 += 1
    kx1 += 1
    weights = np.zeros((ky1 - ky0, kx1 - kx0), dtype=np.float32)
    for y in range(nh):
        for x in range(nw):
            if near[y, x]:
                yy, xx = ny0 + y, nx0 + x
                weights[yy - ky0, xx - kx0] = a[wy0 + yy, wx0 + xx] - background[yy, xx]
    body = mask[ky0:ky1, kx0:kx1].copy()
    m00, m10, m01, mu20, mu02, mu11 = moments(weights)
    if not m00 > 0.0:
        return _not_refined()
    _, minor, _, _ = _principal(mu20, mu02, mu11, 1)
    scalars = np.array([float(wy0 + ky0), float(wy0 + ky1), float(wx0 + kx0), float(wx0 + kx1),
                        height, baseline, m00, m10 / m00, m01 / m00, 1.0 if edge else 0.0, minor,
                        (bmax - bmin) / height if any_near else 0.0, float(count)])
    return 1, weights, body, scalars


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
    profile, s0, _ = _profile_and_axis_sigma(weights, c0, c1, v0, v1, False, 0.0, 0.0)
    return profile, s0


@kernel
def _profile_and_axis_sigma(weights, c0, c1, v0, v1, with_sigma, spread, pixel_sigma):  # pragma: no cover
    """:func:`axial_profile_of`'s ``(profile, s0)`` and, if ``with_sigma``, :func:`axis_sigma_of` (else NaN)
    in the profile's pass over the weights: each pixel's terms and each sum's order as in the two kernels.

    (Issue 8: each row is taken between its first and last weighted pixel only, its terms computed for the
    whole span first in loops the compiler vectorises, the sums then added in the pixels' order. A zero
    weight's bin terms are zeros, which leave every bin's sum as it is, and its axis term is made zero.)"""
    h, w = weights.shape
    spans = np.empty(2 * h, dtype=np.int64)
    s_min, s_max, i_max = np.inf, -np.inf, -1
    for y in range(h):
        lo, hi = _nonzero_span(weights[y])
        spans[2 * y], spans[2 * y + 1] = lo, hi
        if hi > lo:
            # s is monotonic in x along a row (each rounded operation is), so a row's weighted pixels have
            # their least and largest s at its span's ends.
            for x in (lo, hi - 1):
                s = (x - c0) * v0 + (y - c1) * v1
                s_min = min(s_min, s)
                s_max = max(s_max, s)
    s0 = math.floor(s_min) - 2.0
    if s_max > -np.inf:
        # The last bin, max(int(s - s0)) over the weighted pixels, is that of the largest s: rounding
        # and truncation (s - s0 >= 2) are monotonic, so one pass over the weights gives both ends.
        i_max = int(s_max - s0)
    n = i_max + 4
    bins = np.zeros(2 * n)
    lower, upper = bins[:n], bins[n:]
    terms = np.empty(3 * w)
    part_lo, part_up, axis_terms = terms[:w], terms[w:2 * w], terms[2 * w:]
    index = np.empty(w, dtype=np.int64)
    gains = np.empty(w, dtype=np.float32)
    f0, f12 = np.float32(0.0), np.float32(12.0)
    total, acc = 0.0, 0.0
    for y in range(h):
        lo, hi = spans[2 * y], spans[2 * y + 1]
        if hi <= lo:
            continue
        m = np.uint64(hi - lo)
        row = weights[y, lo:hi]
        dy = y - c1
        ty = dy * v1
        for i in range(m):
            dx = float(lo + np.int64(i)) - c0
            u = (dx * v0 + ty) - s0
            k = int(u)
            frac = u - k
            wt = float(row[i])
            index[i] = k
            part_lo[i] = wt * (1.0 - frac)
            part_up[i] = wt * frac
        if with_sigma:
            for i in range(m):
                gains[i] = np.exp(min(max(row[i], f0), f12))
            for i in range(m):
                dx = float(lo + np.int64(i)) - c0
                s = dx * v0 + dy * v1
                t = -dx * v1 + dy * v0
                term = (s * t) ** 2 * gains[i]
                axis_terms[i] = term if row[i] != 0 else 0.0
            for i in range(m):  # (four chains of additions in one loop: they overlap)
                total += row[i]
                acc += axis_terms[i]
                k = index[i]
                lower[k] += part_lo[i]
                upper[k + 1] += part_up[i]
        else:
            for i in range(m):
                k = index[i]
                lower[k] += part_lo[i]
                upper[k + 1] += part_up[i]
    profile = np.empty(n)
    profile[0], profile[n - 1] = lower[0] + upper[0], lower[n - 1] + upper[n - 1]
    for i in range(1, n - 1):
        profile[i] = (0.25 * (lower[i - 1] + upper[i - 1]) + 0.5 * (lower[i] + upper[i])
                      + 0.25 * (lower[i + 1] + upper[i + 1]))
    return profile, s0, _axis_sigma_from(total, acc, spread, pixel_sigma) if with_sigma else np.nan


@kernel
def _axis_sigma_terms(wt, x, y, c0, c1, v0, v1, total, acc):  # pragma: no cover - compiled
    """:func:`axis_sigma_of`'s sums ``total, acc`` with the float32 weight ``wt`` of pixel ``x, y`` added."""
    total += wt
    if wt != 0:
        dx, dy = x - c0, y - c1
        s = dx * v0 + dy * v1
        t = -dx * v1 + dy * v0
        gain = np.exp(min(max(wt, np.float32(0.0)), np.float32(12.0)))
        acc += (s * t) ** 2 * gain
    return total, acc


@kernel
def _axis_sigma_from(total, acc, spread, pixel_sigma):  # pragma: no cover - compiled
    """:func:`axis_sigma_of` from its sums."""
    if total <= 0 or spread <= 0:
        return np.inf
    return pixel_sigma * math.sqrt(acc) / (total * spread)


@kernel
def axis_sigma_of(weights, c0, c1, v0, v1, spread, pixel_sigma):  # pragma: no cover - compiled
    """Standard deviation (rad) of the principal axis' angle from pixel noise (see features.axis_sigma_rad)."""
    h, w = weights.shape
    total, acc = 0.0, 0.0
    for y in range(h):
        for x in range(w):
            total, acc = _axis_sigma_terms(weights[y, x], x, y, c0, c1, v0, v1, total, acc)
    return _axis_sigma_from(total, acc, spread, pixel_sigma)


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


#: The longest piece of a cone's tip that the weights can have lost, as a fraction of the cone's length
#: (see :func:`missing_cone_shift`).
MISSING_CONE_MAX = 0.25


@kernel
def missing_cone_shift(profile, s0, plateau, total, plus, minus):  # pragma: no cover - compiled
    """How far (px along ``+axis``) the weighted centroid moves when the cone tips the weights lost are
    counted: ``profile`` (bin ``i`` at ``s0 + i``) holds ``total`` weight, ``plus``/``minus`` are the
    outward distances of either end at the levels ``features._LEVELS`` of ``plateau``.

    The body's weights stop where its contrast falls below ``support_fraction`` (0.2) of the peak
    (segmentation), and the peak through a cone's axis falls linearly to its apex: a faint tip, about
    a fifth of the cone, lies beyond the weights (robot 6: the last ~20 px of a 130 px cone). It is
    little mass but far out: the centroid came out ~0.2 px towards the tail on robot 6 (0.07-0.14 px on
    robots 7, 1 and 3; robot 6 rendered without vessel or noise: 3D centroid RMS 0.062 mm, 0.026 with
    the tip counted). The end's own profile says
    what is missing: ``sqrt(profile)`` falls linearly to the apex (the tip model of
    :meth:`.Features2D.tip_distance`, levels 0.25 and 0.64 giving the cone's length ``Lc`` and its
    apex), so beyond the weights' end ``e`` lies ``plateau L^3 / (3 Lc^2)`` of weight, ``L`` = apex - ``e``,
    centred ``L / 4`` beyond ``e``. ``L`` is at most ``MISSING_CONE_MAX Lc`` (a frame whose apex
    extrapolation runs far out, a vessel continuing the end, adds no more than a real cut tip can
    lose). A flat end's extrapolated apex lies inside the weights (they extend a blurred rim and a
    margin beyond it): nothing is added there."""
    n = profile.size
    first, last = 0, n - 1
    while last > 0 and profile[last] == 0:
        last -= 1
    while first < last and profile[first] == 0:
        first += 1
    num, den = 0.0, total
    for end in range(2):
        r = plus if end == 0 else minus
        # The outward distance where the weights end (the profile's last bin less its interpolation and
        # smoothing spill).
        edge = (s0 + last - 1.0) if end == 0 else -(s0 + first + 1.0)
        cone = (r[1] - r[3]) / (0.8 - 0.5)   # levels 0.25 and 0.64: sqrt 0.5 and 0.8
        if not cone > 0.0:
            continue
        lost = min(r[1] + 0.5 * cone - edge, MISSING_CONE_MAX * cone)
        if lost > 0.0:
            mass = plateau * lost ** 3 / (3.0 * cone * cone)
            reach = edge + 0.25 * lost
            num += mass * reach if end == 0 else -mass * reach
            den += mass
    return num / den


#: Standard deviation (px^2) of the normalised mixed moment ``mu_st / W`` in the principal frame that a
#: blurred, pixelated blob carries whatever the noise: the sampling of its edges and ends on the pixel
#: grid. The axis turns by ``mu_st / (W (l1 - l2))``, so this turns it by ``MOMENT_BIAS_PX2 / (l1 - l2)``:
#: nothing on a long robot (robot 2: l1 - l2 ~ 350 px^2, 0.004 deg), degrees on a stubby one seen
#: foreshortened (robot 4: l1 - l2 ~ 1-5 px^2). Measured on the clean views (clutter < 0.05) of the
#: accuracy benchmark's seeds 1-20, all seven robots: the constant that brings the RMS of the actual 2D
#: axis error over the predicted sigma to 1 came out 0.0225, 0.0230 and 0.0227 on robots 2, 4 and 7
#: (the three whose noise model fell short: ratios 1.3, 3.1, 1.9), and 0 on the others (already <= 1).
#: A fixed sub-pixel end error over the length (``c / sqrt(l1)``) needed 0.002-0.018: not one constant.
MOMENT_BIAS_PX2 = 0.023


@kernel
def weighted_view_features(weights, cap, pixel_sigma, levels):  # pragma: no cover - compiled
    """The weighted estimator's numbers (see features.weighted_features).

    ``cap`` < inf saturates the weights for the axis. Returns ``(status, out)``: status 0 if the
    weights sum to zero or less; ``out`` ``[cx, cy, l1, l2, vx, vy, axis_sigma]`` (window px) followed
    by the outward distances of the +axis end at each of ``levels``, then those of the -axis end (one
    array: each array a kernel returns costs a boxing in Python). ``levels`` must be
    ``features._LEVELS``. The centroid counts the cone tips beyond the weights
    (:func:`missing_cone_shift`), and the distances are from it; the moments, the axis and its
    noise are the weights' own; ``axis_sigma`` is the pixel noise's (:func:`axis_sigma_of`) and the
    mixed moment's sampling error (:data:`MOMENT_BIAS_PX2`) together."""
    if math.isfinite(cap):  # the capped weights' moments in the same pass (their axis, if the weights have any)
        return features_of_moments(weights, cap, pixel_sigma, levels, moments_and_capped(weights, cap))
    m00, m10, m01, mu20, mu02, mu11 = moments(weights)
    return features_of_moments(weights, cap, pixel_sigma, levels,
                               (m00, m10, m01, mu20, mu02, mu11, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))


@kernel
def features_of_moments(weights, cap, pixel_sigma, levels, sums):  # pragma: no cover - compiled
    """:func:`weighted_view_features` given the weights' :func:`moments_and_capped` (``sums``; where ``cap`` is
    infinite, :func:`moments` and six zeros), for a caller that has them already."""
    n = levels.size
    out = np.zeros(7 + 2 * n)
    capped = math.isfinite(cap)
    m00, m10, m01, mu20, mu02, mu11, t00, _, _, t20, t02, t11 = sums
    if not m00 > 0:
        return 0, out
    c0, c1 = m10 / m00, m01 / m00
    l1, l2, v0, v1 = _eig2(mu20 / m00, mu02 / m00, mu11 / m00)
    if capped:
        if not t00 > 0:
            return 0, out
        _, _, a0, a1 = _eig2(t20 / t00, t02 / t00, t11 / t00)
        if a0 * v0 + a1 * v1 >= 0:
            v0, v1 = a0, a1
        else:
            v0, v1 = -a0, -a1
    # The axial profile and the axis' noise in one pass over the weights (axial_profile_of, axis_sigma_of).
    profile, s0, axis_sigma = _profile_and_axis_sigma(weights, c0, c1, v0, v1, True, l1 - l2, pixel_sigma)
    if l1 - l2 > 0:  # (else axis_sigma_of's inf stands)
        axis_sigma = math.hypot(axis_sigma, MOMENT_BIAS_PX2 / (l1 - l2))
    plateau = profile.max()
    for k in range(n):
        out[7 + k] = reach_at(profile, s0, levels[k] * plateau, 1)
        out[7 + n + k] = reach_at(profile, s0, levels[k] * plateau, -1)
    shift = missing_cone_shift(profile, s0, plateau, m00, out[7:7 + n], out[7 + n:7 + 2 * n])
    for k in range(n):  # the same ends, measured from the moved centroid
        out[7 + k] -= shift
        out[7 + n + k] += shift
    out[0], out[1] = c0 + shift * v0, c1 + shift * v1
    out[2], out[3], out[4], out[5], out[6] = l1, l2, v0, v1, axis_sigma
    return 1, out


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
    _, smooth, labels, stats, order = candidates(a, GAUSSIAN_5, 6.0, 0.29, 0.125, 0.0)
    disk = np.array([1, 2, 2, 2, 1], dtype=np.int64)
    params = np.array([0.25, 0.5, 8, 420, 40.0, 0.7, 2, 3.0, 0.2, 0.29, 3, 7, 4, 1, 3.0], dtype=np.float64)
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
