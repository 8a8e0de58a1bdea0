"""Compiled kernels of the cold path: the background's one pass over the frame and the coarse
candidate search of a full-frame detection (issue 8).

A cold frame pair must cost a few times the memory floor (copying both frames), so the only
full-resolution work is one read of the 16-bit frame that block-averages it; everything after runs on
the coarse grid (1/16 of the pixels), where an OpenCV call (the resampling) is cheap, and the
closing, the blur (OpenCV's values, at half its cost or less) and the per-pixel work that numpy would
spread over dozens of calls are compiled loops:

* :func:`block_mean_log` / :func:`block_mean_log_4` - the ``f x f`` block mean, rounded to a gray
  level exactly as OpenCV's ``INTER_AREA`` downsampling of a 16-bit frame rounds it, then
  ``log(max(mean - dark, 1))`` read from a table of the 65536 gray levels (a table read is several
  times cheaper than a logarithm); the ``f = 4`` variant (the default scale) adds whole 64-bit words,
  four rows at once, and halves the result as the next step's ``INTER_AREA`` resize would;
* :func:`closing_7` - the grey closing of the coarse field by a 7 x 7 structuring element (the
  ellipse every background scale uses), exact min/max as OpenCV's ``MORPH_CLOSE`` with replicated
  borders, in a few vectorised passes instead of one pass per element pixel;
* :func:`gaussian_blur_21` - the blur of the closed field (21 taps, the one every background scale
  uses), the values of OpenCV's ``GaussianBlur`` to the last bit on a CPU with fused multiply-add
  (OpenCV's vector path fuses; its scalar tail does not, so it is used on widths that are multiples
  of 8), in a vectorised pass per direction;
* :func:`upsample_attenuation` - the closed field brought back onto the detection grid (OpenCV's
  bilinear ``2x`` mapping) and the coarse attenuation taken in the same pass, two rows at a time;
* :func:`median_abs_step` - the median absolute difference of horizontal neighbours on a row
  subsample (the robust noise estimate), by radix selection instead of a sort, and not at all when a
  count shows it below the level that could matter to the caller;
* :func:`coarse_components` - threshold, 8-connected components (unions of row runs) and, per
  component, its area, bounding box, peak and the bounding box of its strong core;
* :func:`coarse_candidates` - the noise, the threshold, the components and the full-resolution
  windows around the largest ones' cores: all of a coarse search in one call;
* :func:`window_attenuation` - a detection window's attenuation and its noise sigma (the median of
  neighbour differences, by radix selection instead of a histogram of them all), what
  :func:`~.segmentation.segment` would compute, handed to it.

Kernels take plain arrays and scalars; :mod:`.background` and :mod:`.detection` keep the Python API.
"""
from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from appliance.compiled import kernel, register_warm_up
from appliance.recognition import view_kernels
from appliance.recognition.run_sets import number_sets, union

#: Columns of :func:`coarse_components`' statistics rows.
STAT_AREA, STAT_X0, STAT_Y0, STAT_X1, STAT_Y1, STAT_CORE_X0, STAT_CORE_Y0, STAT_CORE_X1, STAT_CORE_Y1 = range(9)
STAT_COLUMNS = 9


@kernel
def block_mean_log(image: np.ndarray, f: int, table: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """``out[i, j] = table[mean of image[i*f:(i+1)*f, j*f:(j+1)*f]]``, the mean rounded to the nearest
    gray level (half to even, in float32) as OpenCV's ``INTER_AREA`` rounds a 16-bit frame's."""
    hs, ws = out.shape
    scale = np.float32(1.0) / np.float32(f * f)
    # The f rows of a block row are summed into one row first (contiguous, vectorised: this is the
    # pass over the frame), then each block's f sums; the gray levels are gathered from the table last.
    acc = np.empty(ws * f, dtype=np.int32)
    level = np.empty(ws, dtype=np.int32)
    for i in range(hs):
        acc[:] = 0
        for r in range(f):
            row = image[i * f + r]
            for x in range(ws * f):
                acc[x] += np.int32(row[x])
        for j in range(ws):
            s = np.int32(0)
            for k in range(f):
                s += acc[j * f + k]
            level[j] = np.int32(np.rint(np.float32(s) * scale))
        o = out[i]
        for j in range(ws):
            o[j] = table[level[j]]


@kernel
def block_mean_log_4(words: np.ndarray, table: np.ndarray, out: np.ndarray,
                     half: np.ndarray) -> None:  # pragma: no cover
    """:func:`block_mean_log` for ``f = 4`` (the default scale), the same values, several times faster;
    and, if ``half`` is shaped ``(hs // 2, ws // 2)`` for an even ``out`` of ``(hs, ws)`` (else it is left
    alone: pass a ``(0, 0)`` array), the 2 x 2 area mean of ``out`` in it, ``((a + b) + (c + d)) * 0.25`` in
    float32: OpenCV's ``INTER_AREA`` halving of a float32 image to the last bit, taken from each pair of
    rows while they are in the cache instead of a resize call that reads ``out`` again.

    ``words`` is the 16-bit frame viewed as 64-bit words, four pixels each: one word is one block's
    row. Masks split a word into two 32-bit lanes holding pixel sums ``p0 + p1`` and ``p2 + p3``, so
    a block's sum is whole-word additions of its four rows (read in the same loop, no accumulator
    row written and read back; sixteen pixels stay below 2^32 a lane) and one lane sum, all in a loop
    that vectorises. The gray levels are unsigned, so the table reads that follow (the scalar part)
    carry no negative-index wrap-around.
    """
    hs, ws = out.shape
    pairs = np.uint64(0x0000FFFF0000FFFF)
    low = np.uint64(0xFFFFFFFF)
    shift = np.uint64(16)
    level = np.empty(ws, dtype=np.uint32)
    halves = hs % 2 == 0 and ws % 2 == 0 and half.shape[0] == hs // 2 and half.shape[1] == ws // 2
    quarter = np.float32(0.25)
    for i in range(hs):
        r0, r1, r2, r3 = words[4 * i], words[4 * i + 1], words[4 * i + 2], words[4 * i + 3]
        for j in range(ws):
            v0, v1, v2, v3 = r0[j], r1[j], r2[j], r3[j]
            even = (v0 & pairs) + (v1 & pairs) + (v2 & pairs) + (v3 & pairs)
            odd = ((v0 >> shift) & pairs) + ((v1 >> shift) & pairs) + ((v2 >> shift) & pairs) + ((v3 >> shift) & pairs)
            a = even + odd
            s = np.uint32((a & low) + (a >> np.uint64(32)))
            # s / 16 rounded half to even, in integers (exact, as the float32 product is for 16).
            level[j] = (s + np.uint32(7) + ((s >> np.uint32(4)) & np.uint32(1))) >> np.uint32(4)
        o = out[i]
        for j in range(np.uint64(ws)):
            o[j] = table[level[j]]
        if halves and i % 2 == 1:
            above = out[i - 1]
            h = half[i // 2]
            for j in range(ws // 2):
                h[j] = ((above[2 * j] + above[2 * j + 1]) + (o[2 * j] + o[2 * j + 1])) * quarter


#: Rows (and the largest half width) of the structuring element :func:`closing_7` takes.
CLOSING_SIZE = 7


@kernel
def _larger(a: float, b: float) -> float:  # pragma: no cover
    """The larger of two finite values, as a comparison the compiler turns into a vector maximum."""
    return a if a > b else b


@kernel
def _spread_7(image: np.ndarray, half_widths: np.ndarray, sign: float, out: np.ndarray) -> None:  # pragma: no cover
    """``out = sign * max`` of ``sign * image`` over the 7 x 7 structuring element whose row ``r`` is the
    run of half width ``half_widths[r]`` (0..3) centred on the pixel's column, borders replicated: a
    dilation (``sign = 1``) or an erosion (``sign = -1``, as ``-max(-x)`` is ``min(x)`` exactly).

    Each row's running maxima over half widths 0..3 are taken once (a padded copy read at fixed
    offsets), stacked in one array, and every output pixel is the maximum of seven stacked rows: all
    reads of one array at fixed offsets, so both passes vectorise."""
    h, w = image.shape
    s = np.float32(sign)
    hp = h + 6
    padded = np.empty((hp, w + 6), dtype=np.float32)
    for yy in range(hp):
        y = min(max(yy - 3, 0), h - 1)
        left = image[y, 0] * s
        right = image[y, w - 1] * s
        for x in range(3):
            padded[yy, x] = left
            padded[yy, w + 3 + x] = right
        for x in range(w):
            padded[yy, x + 3] = image[y, x] * s
    # spans[k * hp + yy, x]: the maximum of padded row yy over columns x + 3 - k .. x + 3 + k.
    spans = np.empty((4 * hp, w), dtype=np.float32)
    for yy in range(hp):
        for x in range(w):
            m = padded[yy, x + 3]
            spans[yy, x] = m
            m = _larger(m, _larger(padded[yy, x + 2], padded[yy, x + 4]))
            spans[hp + yy, x] = m
            m = _larger(m, _larger(padded[yy, x + 1], padded[yy, x + 5]))
            spans[2 * hp + yy, x] = m
            spans[3 * hp + yy, x] = _larger(m, _larger(padded[yy, x], padded[yy, x + 6]))
    r0 = half_widths[0] * hp
    r1 = half_widths[1] * hp + 1
    r2 = half_widths[2] * hp + 2
    r3 = half_widths[3] * hp + 3
    r4 = half_widths[4] * hp + 4
    r5 = half_widths[5] * hp + 5
    r6 = half_widths[6] * hp + 6
    for y in range(h):
        for x in range(w):
            m = _larger(_larger(spans[r0 + y, x], spans[r1 + y, x]), _larger(spans[r2 + y, x], spans[r3 + y, x]))
            m = _larger(m, _larger(_larger(spans[r4 + y, x], spans[r5 + y, x]), spans[r6 + y, x]))
            out[y, x] = m * s


@kernel
def closing_7(image: np.ndarray, half_widths: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """``out`` = the grey closing (a dilation, then an erosion) of ``image`` (float32, finite) by the 7 x 7
    structuring element whose row ``r`` is the centred run of half width ``half_widths[r]`` (0..3), borders
    replicated: the values of ``cv2.morphologyEx(image, MORPH_CLOSE, element, borderType=BORDER_REPLICATE)``
    to the last bit (both are maxima and minima of the same pixels), about twice as fast on the coarse
    field."""
    dilated = np.empty_like(out)
    _spread_7(image, half_widths, 1.0, dilated)
    _spread_7(dilated, half_widths, -1.0, out)


@intrinsic
def _fused_multiply_add(typingctx, a, b, c):  # type: ignore[no-untyped-def]  # pragma: no cover
    """``a * b + c`` in float32 with one rounding (LLVM's ``fma``), as a SIMD ``v_muladd`` computes it."""
    signature = types.float32(types.float32, types.float32, types.float32)

    def codegen(context, builder, sig, args):  # type: ignore[no-untyped-def]
        f32 = ir.FloatType()
        fma = builder.module.declare_intrinsic("llvm.fma", [f32], ir.FunctionType(f32, [f32, f32, f32]))
        return builder.call(fma, args)

    return signature, codegen


#: Taps of the blur :func:`gaussian_blur_21` computes (``2 * 10 + 1``).
BLUR_TAPS = 21


@kernel
def gaussian_blur_21(image: np.ndarray, taps: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """``out`` = ``image`` (float32, h x w) filtered by the symmetric 21-tap kernel ``taps`` (float32) along
    rows, then along columns, borders replicated: ``cv2.GaussianBlur``'s separable filter, in its order
    of operations (each row sum fused multiply-adds from the first tap to the last; each column sum
    starts at the centre tap and adds the pairs of rows at equal distance, then fused multiply-adds
    them), so the values are OpenCV's where its vector path computes them (see the module docstring).

    The tap loops have constant trip counts, so they unroll and each pass vectorises along the row."""
    h, w = image.shape
    padded = np.empty(w + 20, dtype=np.float32)
    rows = np.empty((h + 20, w), dtype=np.float32)
    first = taps[0]
    for y in range(h):
        line = image[y]
        for x in range(10):
            padded[x] = line[0]
            padded[w + 10 + x] = line[w - 1]
        for x in range(w):
            padded[x + 10] = line[x]
        for x in range(w):
            s = padded[x] * first
            for k in range(1, 21):
                s = _fused_multiply_add(padded[x + k], taps[k], s)
            rows[y + 10, x] = s
    for y in range(10):
        for x in range(w):
            rows[y, x] = rows[10, x]
            rows[h + 10 + y, x] = rows[h + 9, x]
    centre = taps[10]
    for y in range(h):
        for x in range(w):
            s = rows[y + 10, x] * centre
            for k in range(1, 11):
                s = _fused_multiply_add(rows[y + 10 + k, x] + rows[y + 10 - k, x], taps[10 + k], s)
            out[y, x] = s


@kernel
def _doubled_row(src: np.ndarray, dst: np.ndarray) -> None:  # pragma: no cover
    """``dst`` (2n) = ``src`` (n) upsampled 2x by OpenCV's ``INTER_LINEAR`` mapping: output pixel ``x``
    sits at ``(x + 0.5) / 2 - 0.5`` on the source, so inside it is 3/4 of its nearer source pixel and
    1/4 of the other, and the two end pixels copy the source's ends."""
    n = src.shape[0]
    quarter = np.float32(0.25)
    three = np.float32(0.75)
    dst[0] = src[0]
    for k in range(n - 1):
        a = src[k]
        b = src[k + 1]
        dst[2 * k + 1] = a * three + b * quarter
        dst[2 * k + 2] = a * quarter + b * three
    dst[2 * n - 1] = src[n - 1]


@kernel
def _blend_rows(upper: np.ndarray, w_upper: np.float32, lower: np.ndarray, w_lower: np.float32,
                logs: np.ndarray, coarse: np.ndarray, attenuation: np.ndarray) -> None:  # pragma: no cover
    for x in range(coarse.shape[0]):
        v = upper[x] * w_upper + lower[x] * w_lower
        coarse[x] = v
        attenuation[x] = v - logs[x]


@kernel
def upsample_attenuation(closed: np.ndarray, logs: np.ndarray, coarse: np.ndarray,
                         attenuation: np.ndarray) -> None:  # pragma: no cover
    """``coarse`` = ``closed`` (h, w) upsampled to (2h, 2w) as ``cv2.resize(..., INTER_LINEAR)`` does it
    (within float rounding), and ``attenuation = coarse - logs``, in one pass over the output.

    Each output row blends the two source rows around it, doubled along x once each (two row buffers
    that swap roles), so no upsampled temporary is written and read back.
    """
    h = closed.shape[0]
    rows = coarse.shape[0]
    one = np.float32(1.0)
    zero = np.float32(0.0)
    quarter = np.float32(0.25)
    three = np.float32(0.75)
    buffers = np.empty((2, coarse.shape[1]), dtype=np.float32)
    upper, lower = buffers[0], buffers[1]
    _doubled_row(closed[0], upper)
    _blend_rows(upper, one, upper, zero, logs[0], coarse[0], attenuation[0])
    for k in range(h - 1):
        _doubled_row(closed[k + 1], lower)
        _blend_rows(upper, three, lower, quarter, logs[2 * k + 1], coarse[2 * k + 1], attenuation[2 * k + 1])
        _blend_rows(upper, quarter, lower, three, logs[2 * k + 2], coarse[2 * k + 2], attenuation[2 * k + 2])
        upper, lower = lower, upper
    _blend_rows(upper, one, upper, zero, logs[rows - 1], coarse[rows - 1], attenuation[rows - 1])


@kernel
def _select_digit(hist: np.ndarray, k: int) -> tuple[int, int]:  # pragma: no cover
    """The bin holding the ``k``-th smallest (0-based) of the values counted in the four interleaved
    copies of ``hist`` (4, bins), and ``k`` within that bin."""
    digit = 0
    while True:
        count = hist[0, digit] + hist[1, digit] + hist[2, digit] + hist[3, digit]
        if k < count:
            return digit, k
        k -= count
        digit += 1


@kernel
def _kth_smallest(bits: np.ndarray, k: int) -> np.uint32:  # pragma: no cover
    """The ``k``-th smallest (0-based) of ``bits``, the bit patterns of non-negative finite float32
    values (ordered like the values), by radix selection on 11, 11 and 10 bits: each pass histograms
    only the values that share the digits chosen so far, so ties cost nothing (unlike a quickselect's
    partitions). Four histogram copies, used in turn, keep runs of equal digits from queueing on one
    counter."""
    n = bits.shape[0]
    hist = np.zeros((4, 2048), dtype=np.int64)
    for i in range(n):
        hist[i & 3, bits[i] >> np.uint32(21)] += 1
    digit, k = _select_digit(hist, k)
    top = np.uint32(digit)
    # The values with that top digit, gathered once: the next passes only see them.
    rest = np.empty(n, dtype=np.uint32)
    m = 0
    for i in range(n):
        if bits[i] >> np.uint32(21) == top:
            rest[m] = bits[i]
            m += 1
    hist[:, :] = 0
    for i in range(m):
        hist[i & 3, (rest[i] >> np.uint32(10)) & np.uint32(2047)] += 1
    digit, k = _select_digit(hist, k)
    middle = (top << np.uint32(11)) | np.uint32(digit)
    hist[:, :] = 0
    for i in range(m):
        if rest[i] >> np.uint32(10) == middle:
            hist[i & 3, rest[i] & np.uint32(1023)] += 1
    digit, k = _select_digit(hist, k)
    return (middle << np.uint32(10)) | np.uint32(digit)


@kernel
def _next_order_statistic(bits: np.ndarray, n: int, value: np.uint32, rank: int) -> np.uint32:  # pragma: no cover
    """The ``rank + 1``-th smallest of ``bits[:n]`` given ``value``, its ``rank``-th: ``value`` again if it is
    repeated that far, else the smallest pattern above it (branch-free, so that it vectorises)."""
    at_most = 0
    above = np.uint32(0xFFFFFFFF)
    none = np.uint32(0xFFFFFFFF)
    for i in range(n):
        b = bits[i]
        at_most += b <= value
        above = min(above, b if b > value else none)
    return value if at_most > rank + 1 else above


@kernel
def _median_pair(bits: np.ndarray, n: int, k: int) -> tuple[np.uint32, np.uint32]:  # pragma: no cover
    """The ``k``-th and ``k + 1``-th smallest (0-based) of ``bits[:n]`` (bit patterns of non-negative finite
    float32 values, ordered like them), ``k + 1 < n``: the radix selection of the first
    (:func:`_kth_smallest`), then one branch-free pass for the next.

    (A strided sample's bracket around the median, gathered first so that only ~20 % are selected, was
    slower on a detection window, 24 against 17 us for its 22k differences, and at every size from 2k
    to 400k: the gathering pass is serial.)"""
    lower = _kth_smallest(bits[:n], k)
    return lower, _next_order_statistic(bits, n, lower, k)


@kernel
def _attenuation_and_steps(image: np.ndarray, y0: int, y1: int, x0: int, x1: int, coarse: np.ndarray, fy: float,
                           fx: float, log_table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """:func:`.view_kernels.attenuation_from_coarse`'s values (the same float32 operations on each pixel),
    in vectorisable passes a row: ``log B`` of the row from its coarse neighbours, then the gray levels'
    logs subtracted, instead of both inside one loop that the compiler leaves scalar; and the absolute
    differences of horizontal neighbours, row ``y``'s ``w - 1`` at ``y * (w - 1)``, taken while the row
    is in the cache (not in a second pass over the window)."""
    ws = coarse.shape[1]
    h, w = y1 - y0, x1 - x0
    ix0, ix1, wx = view_kernels.bilinear_columns(w, x0, fx, ws)
    wx0 = np.float32(1.0) - wx
    out = np.empty((h, w), dtype=np.float32)
    steps = np.empty(h * max(w - 1, 0), dtype=np.float32)
    row = np.empty(ws, dtype=np.float32)
    background = np.empty(w, dtype=np.float32)
    lo, hi = ix0[0], ix1[w - 1] + 1 if w > 0 else 0
    for y in range(h):
        view_kernels.coarse_row_at(coarse, y + y0, fy, lo, hi, row)
        for x in range(w):
            background[x] = row[ix0[x]] * wx0[x] + row[ix1[x]] * wx[x]
        levels = image[y + y0, x0:x1]
        o = out[y]
        for x in range(w):
            o[x] = background[x] - log_table[levels[x]]
        base = y * (w - 1)
        for x in range(w - 1):
            steps[base + x] = abs(o[x + 1] - o[x])
    return out, steps


@kernel
def window_attenuation(image: np.ndarray, y0: int, y1: int, x0: int, x1: int, coarse: np.ndarray, fy: float,
                       fx: float, log_table: np.ndarray) -> tuple[np.ndarray, float]:  # pragma: no cover
    """A detection window's attenuation (:func:`_attenuation_and_steps`, the values
    :func:`~.segmentation.segment` would compute) and its robust noise sigma, ``1.4826 m / sqrt(2)`` with
    ``m`` the median of the horizontal neighbours' absolute differences: the value segment's own
    measurement gives (the same order statistics, :func:`_median_pair`), at a fraction of its cost.
    The sigma is -1 where that measurement is not a plain median (a window narrower than 2 px,
    or a non-finite attenuation): the caller then lets segment measure it."""
    a, d = _attenuation_and_steps(image, y0, y1, x0, x1, coarse, fy, fx, log_table)
    h, w = a.shape
    if w < 2 or h == 0:
        return a, -1.0
    n = h * (w - 1)
    bits = d.view(np.uint32)
    largest = np.uint32(0)
    for i in range(n):
        largest = max(largest, bits[i])
    if largest >= np.uint32(0x7F800000):
        return a, -1.0
    if n == 1:
        return a, 1.4826 * float(d[0]) / math.sqrt(2.0)
    upper_rank = n // 2
    lower_rank = upper_rank - 1 if n % 2 == 0 else upper_rank
    lower, upper = _median_pair(bits, n, lower_rank)
    pair = np.array([lower, upper], dtype=np.uint32).view(np.float32)
    med = pair[0] if n % 2 else (pair[0] + pair[1]) / np.float32(2.0)
    return a, 1.4826 * float(med) / math.sqrt(2.0)


@kernel
def median_abs_step(a: np.ndarray, row_step: int, low: float) -> float:  # pragma: no cover
    """``max(low, m)`` with ``m`` the median of ``|a[y, x + 1] - a[y, x]|`` over every ``row_step``-th row
    as ``np.median`` gives it (the mean of the two middle values for an even count); NaN if there is
    no difference or one is not finite.

    A caller that only needs the median when it exceeds ``low`` (detection: noise below the signal
    floor does not change the threshold) gets ``low`` from a count made while the differences are
    taken, when more than half of them are at most ``low``; the selection runs only otherwise.
    """
    h, w = a.shape
    rows = (h + row_step - 1) // row_step
    n = rows * (w - 1)
    if w < 2 or n == 0:
        return np.nan
    d = np.empty(n, dtype=np.float32)
    k = 0
    at_most_low = 0
    for y in range(0, h, row_step):
        row = a[y]
        for x in range(w - 1):
            step = abs(row[x + 1] - row[x])
            d[k + x] = step
            at_most_low += step <= low
        k += w - 1
    bits = d.view(np.uint32)
    largest = np.uint32(0)
    for i in range(n):
        b = bits[i]
        largest = max(largest, b)
    if largest >= np.uint32(0x7F800000):   # an infinity or a NaN
        return np.nan
    if at_most_low >= n // 2 + 1:   # both middle values (one if n is odd) are at most low
        return low
    lower = _kth_smallest(bits, (n - 1) // 2)
    if n % 2:
        upper = lower
    else:
        # The next order statistic: the same value if it is repeated, else the smallest above it.
        at_most = 0
        above = np.uint32(0xFFFFFFFF)
        for i in range(n):
            b = bits[i]
            at_most += b <= lower
            if b > lower:
                above = min(above, b)
        upper = lower if at_most > n // 2 else above
    pair = np.array([lower, upper], dtype=np.uint32).view(np.float32)
    return max(low, float((pair[0] + pair[1]) / np.float32(2.0)))


@kernel
def coarse_components(a: np.ndarray, threshold: float, core_fraction: float,
                      labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """8-connected components of ``a > threshold``, labelled 1.. in raster order of their first pixel
    into ``labels`` (zeroed by the caller, shaped like ``a``; an empty array if the labels are not
    wanted), and one row of statistics each: area, bounding box
    ``x0, y0, x1, y1`` (exclusive ends), and the bounding box of the core (pixels at or above
    ``core_fraction`` of the component's peak); and each component's peak. Row 0 (the background's)
    is left zero.

    The components are unions of row runs (a run joins those of the row above that it touches,
    diagonals included), so the connectivity work is per run, not per pixel with eight neighbours; a
    contrast-filled vessel above the threshold is a few hundred runs of thousands of pixels.
    """
    h, w = a.shape
    # Pixels above the threshold per row (a branch-free count, vectorised; a float maximum is not,
    # without fastmath): most rows have none, and their total bounds the number of runs, so the run
    # arrays are sized once (growing them inside the loop would make it several times slower even
    # when it never grows) and small (a worst-case size would cost a fresh mapping every call).
    row_hits = np.zeros(h, dtype=np.int64)
    for y in range(h):
        line = a[y]
        hits = 0
        for x in range(w):
            hits += line[x] > threshold
        row_hits[y] = hits
    cap = max(1, int(row_hits.sum()))
    run_y = np.empty(cap, dtype=np.int32)
    run_x0 = np.empty(cap, dtype=np.int32)
    run_x1 = np.empty(cap, dtype=np.int32)
    parent = np.empty(cap, dtype=np.int32)
    nr = 0
    above_start = above_end = 0   # the previous row's runs
    for y in range(h):
        line = a[y]
        hits = row_hits[y]
        start = nr
        x = 0
        while hits > 0 and x < w:
            if not line[x] > threshold:
                x += 1
                continue
            x0 = x
            while x < w and line[x] > threshold:
                x += 1
            hits -= x - x0
            run_y[nr] = y
            run_x0[nr] = x0
            run_x1[nr] = x
            parent[nr] = nr
            nr += 1
        # Join the runs of the row above that touch (their pixels within one column of this run's);
        # the smaller index stays the root, so a component's root is its first run in raster order.
        j = above_start
        for i in range(start, nr):
            while j < above_end and run_x1[j] < run_x0[i]:
                j += 1
            k = j
            while k < above_end and run_x0[k] <= run_x1[i]:
                union(parent, i, k)
                k += 1
        above_start, above_end = start, nr
    with_labels = labels.shape[0] == h and labels.shape[1] == w
    label_of, n = number_sets(parent, nr)
    stats = np.zeros((n, STAT_COLUMNS), dtype=np.int64)
    peaks = np.zeros(n, dtype=np.float32)
    for label in range(1, n):
        stats[label, STAT_X0] = w
        stats[label, STAT_Y0] = h
        stats[label, STAT_CORE_X0] = w
        stats[label, STAT_CORE_Y0] = h
        peaks[label] = -np.inf
    for i in range(nr):
        label, y, x0, x1 = label_of[i], run_y[i], run_x0[i], run_x1[i]
        row = stats[label]
        row[STAT_AREA] += x1 - x0
        row[STAT_X0] = min(row[STAT_X0], x0)
        row[STAT_X1] = max(row[STAT_X1], x1)
        row[STAT_Y0] = min(row[STAT_Y0], y)
        row[STAT_Y1] = y + 1
        peak = peaks[label]
        line = a[y]
        for x in range(x0, x1):
            peak = max(peak, line[x])
        if with_labels:
            labels[y, x0:x1] = label
        peaks[label] = peak
    for i in range(nr):
        label, y, x0, x1 = label_of[i], run_y[i], run_x0[i], run_x1[i]
        level = core_fraction * peaks[label]
        line = a[y]
        first, last = -1, -1
        for x in range(x0, x1):
            if line[x] >= level:
                last = x
                if first < 0:
                    first = x
        if first >= 0:
            row = stats[label]
            row[STAT_CORE_X0] = min(row[STAT_CORE_X0], first)
            row[STAT_CORE_X1] = max(row[STAT_CORE_X1], last + 1)
            row[STAT_CORE_Y0] = min(row[STAT_CORE_Y0], y)
            row[STAT_CORE_Y1] = max(row[STAT_CORE_Y1], y + 1)
    return stats, peaks


#: Kinds of :func:`coarse_candidates`' rows: a window, or a core too long to be a robot whose part
#: connected to its peak must be looked at (the component's bounding box is given instead).
WINDOW, LONG_CORE = 0, 1


@kernel
def coarse_candidates(a: np.ndarray, row_step: int, quiet: float, detect_sigma: float, least: float, floor: float,
                      core_fraction: float, max_components: int, fx: float, fy: float, max_extent_px: float,
                      roi_margin_px: float, cone_reach: float, height: int, width: int
                      ) -> tuple[np.ndarray, np.ndarray, float]:  # pragma: no cover
    """:func:`~.detection.coarse_windows`' arithmetic in one call: the noise (:func:`median_abs_step` on
    every ``row_step``-th row, ``quiet`` its floor), the threshold, the components
    (:func:`coarse_components`), and for the ``max_components`` largest whose peak reaches ``floor``
    (largest first, ties in label order) one row ``kind, x0, y0, x1, y1, label``: a ``WINDOW`` is the
    full-resolution window around the core (its box grown by ``roi_margin_px + cone_reach x extent +
    2 max(fx, fy)`` and clipped to ``height x width``, as :meth:`~.segmentation.Roi.around` does it;
    too small a window gives no row); a ``LONG_CORE`` (longer than ``max_extent_px``) gives the
    component's bounding box for the caller to cut. Returns the rows, the components' peaks and the
    threshold, the same values as the Python steps they replace."""
    sigma = 1.4826 * median_abs_step(a, row_step, quiet) / math.sqrt(2.0)
    if not math.isfinite(sigma) or sigma <= 0:
        sigma = 1e-3
    threshold = max(detect_sigma * sigma, least)
    stats, peaks = coarse_components(a, threshold, core_fraction, np.zeros((0, 0), dtype=np.int32))
    order = np.argsort(-stats[1:, STAT_AREA], kind="mergesort")[:max_components] + 1
    rows = np.zeros((order.shape[0], 6), dtype=np.int64)
    k = 0
    grow = 2.0 * max(fx, fy)
    for label in order:
        if float(peaks[label]) < floor:
            continue
        st = stats[label]
        x0, y0, x1, y1 = st[STAT_CORE_X0], st[STAT_CORE_Y0], st[STAT_CORE_X1], st[STAT_CORE_Y1]
        extent = max((x1 - x0) * fx, (y1 - y0) * fy)
        if extent > max_extent_px:
            rows[k, 0] = LONG_CORE
            rows[k, 1], rows[k, 2], rows[k, 3], rows[k, 4] = st[STAT_X0], st[STAT_Y0], st[STAT_X1], st[STAT_Y1]
            rows[k, 5] = label
            k += 1
            continue
        margin = roi_margin_px + cone_reach * extent + grow
        wx0 = max(0, math.floor(min(x0 * fx, x1 * fx) - margin))
        wy0 = max(0, math.floor(min(y0 * fy, y1 * fy) - margin))
        wx1 = min(width, math.ceil(max(x0 * fx, x1 * fx) + margin) + 1)
        wy1 = min(height, math.ceil(max(y0 * fy, y1 * fy) + margin) + 1)
        if wx1 - wx0 < 4 or wy1 - wy0 < 4:
            continue
        rows[k, 0] = WINDOW
        rows[k, 1], rows[k, 2], rows[k, 3], rows[k, 4] = wx0, wy0, wx1, wy1
        rows[k, 5] = label
        k += 1
    return rows[:k], peaks, threshold


def warm_up() -> None:
    """Compile every kernel of this module on tiny inputs (see :mod:`appliance.compiled`)."""
    image = np.full((8, 8), 1000, dtype=np.uint16)
    table = np.zeros(65536, dtype=np.float32)
    small = np.zeros((2, 2), dtype=np.float32)
    # Frames may arrive read-only (a grabber's or a recording's buffer): another signature each.
    frozen = image.copy()
    frozen.flags.writeable = False
    for frame in (image, frozen):
        block_mean_log(frame, 4, table, small)
        block_mean_log_4(frame.view(np.uint64), table, small, np.empty((1, 1), dtype=np.float32))
    median_abs_step(small, 2, 0.0)
    for frame in (image, frozen):
        window_attenuation(frame, 0, 4, 0, 4, small, 4.0, 4.0, table)
    upsample_attenuation(np.zeros((1, 1), dtype=np.float32), small, np.empty_like(small), np.empty_like(small))
    closing_7(small, np.array([0, 2, 3, 3, 3, 2, 0], dtype=np.int64), np.empty_like(small))
    gaussian_blur_21(small, np.zeros(BLUR_TAPS, dtype=np.float32), np.empty_like(small))
    coarse_components(small, 0.5, 0.5, np.zeros((2, 2), dtype=np.int32))
    coarse_components(small, 0.5, 0.5, np.zeros((0, 0), dtype=np.int32))
    coarse_candidates(small, 4, 0.01, 6.0, 0.1, 0.2, 0.5, 24, 4.0, 4.0, 420.0, 14.0, 0.7, 8, 8)


register_warm_up(__name__)
