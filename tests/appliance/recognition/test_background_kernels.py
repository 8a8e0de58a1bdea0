"""The cold path's compiled kernels give what the OpenCV/numpy steps they replaced give: the block mean's
rounding, the noise median, the components and their statistics."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from appliance.recognition import background_kernels as kernels
from appliance.recognition import view_kernels
from appliance.recognition.background import _downsample_log, _log_table, log_background
from appliance.recognition.segmentation import Roi, attenuation


def _reference_log(image: np.ndarray, f: int, dark: float) -> np.ndarray:
    h, w = image.shape
    small = cv2.resize(image, (w // f, h // f), interpolation=cv2.INTER_AREA).astype(np.float32)
    return np.log(np.maximum(small - np.float32(dark), 1.0))


@pytest.mark.parametrize("f", [1, 2, 3, 4, 8])  # 2: OpenCV rounds half up (its own 2x2 path); we use OpenCV
def test_block_mean_log_rounds_like_opencv_area_downsampling(f: int) -> None:
    rng = np.random.default_rng(f)
    h, w = 24 * f, 40 * f
    image = rng.integers(0, 65536, (h, w), dtype=np.uint16)
    # Blocks whose sums fall half-way between two gray levels (ties round to even), the extremes of
    # the 16-bit range (no overflow), and levels at and below the dark level (floored at 1).
    image[:f, :f * 6] = np.repeat([[0, 1, 2, 3, 65535, 65534]], f * f, axis=0).reshape(f, f, 6).transpose(0, 2, 1).reshape(f, 6 * f)
    image[f:2 * f, :4 * f] = 65535
    if f > 1:
        image[2 * f:3 * f, :f] = 1000
        image[2 * f, 0] = 1001   # a sum of (f^2 - 1) * 1000 + 1001: a fraction 1/f^2 above 1000
    out, _ = _downsample_log(image, f, 1000.0)
    np.testing.assert_array_equal(out, _reference_log(image, f, 1000.0))


def test_block_mean_log_4_ties_and_extremes() -> None:
    # Every block sum from 0 to 16 * 65535 in steps that hit .5 exactly: s = 16 q + 8.
    sums = np.concatenate([np.arange(8, 16 * 65535, 16 * 4099 + 16), [0, 7, 8, 9, 24, 16 * 65535]])
    blocks = np.zeros((len(sums), 16), dtype=np.int64)
    for i, s in enumerate(sums):
        q, r = divmod(int(s), 16)
        blocks[i] = q
        blocks[i, :r] += 1
    image = blocks.reshape(1, len(sums), 4, 4).transpose(0, 2, 1, 3).reshape(4, 4 * len(sums)).astype(np.uint16)
    out = np.empty((1, len(sums)), dtype=np.float32)
    table = _log_table(0.0)
    kernels.block_mean_log_4(image.view(np.uint64), table, out, np.empty((0, 0), dtype=np.float32))
    np.testing.assert_array_equal(out, _reference_log(image, 4, 0.0))
    generic = np.empty_like(out)
    kernels.block_mean_log(image, 4, table, generic)
    np.testing.assert_array_equal(generic, out)


def test_block_mean_log_4_halves_its_output_as_opencvs_area_resize() -> None:
    """The halving the f = 4 pass gives is ``cv2.resize(..., INTER_AREA)`` of its output, bit for bit; an odd
    grid gets none (the caller resizes)."""
    rng = np.random.default_rng(12)
    for image in (rng.integers(0, 65536, (256, 512), dtype=np.uint16),
                  (20000 + rng.normal(0, 3000, (512, 256))).clip(0, 65535).astype(np.uint16)):
        logs, half = _downsample_log(image, 4, 900.0)
        assert half is not None and half.shape == (logs.shape[0] // 2, logs.shape[1] // 2)
        expected = cv2.resize(logs, (half.shape[1], half.shape[0]), interpolation=cv2.INTER_AREA)
        np.testing.assert_array_equal(half.view(np.uint32), expected.view(np.uint32))
    logs, half = _downsample_log(rng.integers(900, 40000, (36, 64), dtype=np.uint16), 4, 900.0)
    assert logs.shape == (9, 16) and half is None
    untouched = np.full((2, 2), 7.0, dtype=np.float32)   # not the (1, 1) halving of a (2, 2) output
    kernels.block_mean_log_4(np.zeros((8, 8), dtype=np.uint16).view(np.uint64), _log_table(0.0),
                             np.empty((2, 2), dtype=np.float32), untouched)
    assert np.all(untouched == 7.0)


def test_downsampling_of_sizes_that_are_not_multiples_goes_through_opencv() -> None:
    rng = np.random.default_rng(7)
    image = rng.integers(900, 40000, (150, 213), dtype=np.uint16)
    np.testing.assert_allclose(_downsample_log(image, 4, 1000.0)[0], _reference_log(image, 4, 1000.0), atol=1e-6)


@pytest.mark.parametrize("shape", [(128, 128), (45, 35), (7, 9), (1, 5), (3, 1), (1, 1)])
@pytest.mark.parametrize("element", [cv2.MORPH_ELLIPSE, cv2.MORPH_RECT, cv2.MORPH_CROSS])
def test_closing_7_is_opencvs_closing_to_the_last_bit(shape: tuple[int, int], element: int) -> None:
    rng = np.random.default_rng(shape[0] * 7 + shape[1] + element)
    kernel = cv2.getStructuringElement(element, (kernels.CLOSING_SIZE, kernels.CLOSING_SIZE))
    half_widths = (kernel.sum(axis=1).astype(np.int64) - 1) // 2
    # Noise, plateaus with ties (a closing's output is made of them) and negative values.
    for field in (rng.random(shape, dtype=np.float32), (3 * rng.random(shape)).round().astype(np.float32),
                  -1e3 * rng.random(shape, dtype=np.float32)):
        closed = np.empty_like(field)
        kernels.closing_7(field, half_widths, closed)
        expected = cv2.morphologyEx(field, cv2.MORPH_CLOSE, kernel, borderType=cv2.BORDER_REPLICATE)
        np.testing.assert_array_equal(closed, expected)


def _cpu_fuses_multiply_adds() -> bool:
    try:
        return " fma " in " " + Path("/proc/cpuinfo").read_text().replace("\t", " ").replace("\n", " ") + " "
    except OSError:
        return False


def _assert_opencvs_blur(got: np.ndarray, expected: np.ndarray) -> None:
    """To the last bit where OpenCV's vector path fuses its multiply-adds (a CPU with FMA, as CI's); elsewhere
    its unfused sums may differ from the compiled kernel's in the last bits of a 21-tap sum."""
    if _cpu_fuses_multiply_adds():
        np.testing.assert_array_equal(got, expected)
    else:
        np.testing.assert_allclose(got, expected, rtol=2e-6, atol=0)


@pytest.mark.parametrize("shape", [(128, 128), (64, 64), (33, 24), (8, 256)])
def test_gaussian_blur_21_is_opencvs_blur_to_the_last_bit(shape: tuple[int, int]) -> None:
    """On widths that are multiples of 8 (where OpenCV's vector path, which fuses its multiply-adds on a CPU
    with FMA, computes every pixel), the compiled blur is OpenCV's."""
    from appliance.recognition.background import _gaussian_taps

    rng = np.random.default_rng(shape[0] + 3 * shape[1])
    taps = _gaussian_taps(7 / 3.0)
    assert taps.size == kernels.BLUR_TAPS
    for field in (rng.random(shape, dtype=np.float32), (5 + 3 * rng.random(shape)).astype(np.float32)):
        blurred = np.empty_like(field)
        kernels.gaussian_blur_21(field, taps, blurred)
        expected = cv2.GaussianBlur(field, (0, 0), 7 / 3.0, borderType=cv2.BORDER_REPLICATE)
        _assert_opencvs_blur(blurred, expected)


def test_log_background_closes_and_blurs_the_field_as_opencv_does() -> None:
    """The background of a frame is what OpenCV's closing and blur of its field would give, to the last bit."""
    rng = np.random.default_rng(11)
    y, x = np.mgrid[0:512, 0:512]
    image = (30000 - 8 * np.hypot(y - 200, x - 300) + rng.normal(0, 300, (512, 512))).astype(np.uint16)
    image[250:262, 100:180] = 9000   # a dark bar the closing removes
    background = log_background(image, 48, 1000.0)
    logs, _ = _downsample_log(image, 4, 1000.0)
    field = cv2.resize(logs, (64, 64), interpolation=cv2.INTER_AREA)
    closed = cv2.morphologyEx(field, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (7, 7)),
                              borderType=cv2.BORDER_REPLICATE)
    closed = cv2.GaussianBlur(closed, (0, 0), 7 / 3.0, borderType=cv2.BORDER_REPLICATE)
    coarse = np.empty_like(logs)
    kernels.upsample_attenuation(closed, logs, coarse, np.empty_like(logs))
    _assert_opencvs_blur(background.coarse, coarse)


@pytest.mark.parametrize("shape", [(64, 64), (25, 19), (1, 7), (6, 1), (1, 1)])
def test_upsample_attenuation_is_opencvs_bilinear_doubling_less_the_logs(shape: tuple[int, int]) -> None:
    rng = np.random.default_rng(shape[0] * 10 + shape[1])
    closed = rng.uniform(8.0, 10.0, shape).astype(np.float32)
    logs = rng.uniform(7.0, 10.0, (2 * shape[0], 2 * shape[1])).astype(np.float32)
    coarse, attenuation = np.empty_like(logs), np.empty_like(logs)
    kernels.upsample_attenuation(closed, logs, coarse, attenuation)
    expected = cv2.resize(closed, (2 * shape[1], 2 * shape[0]), interpolation=cv2.INTER_LINEAR)
    # The same taps; only the rounding of the two products' sum may differ (OpenCV may fuse them).
    np.testing.assert_allclose(coarse, expected, rtol=0, atol=4e-6)
    np.testing.assert_array_equal(attenuation, coarse - logs)


@pytest.mark.parametrize("shape, step", [((9, 12), 2), ((40, 31), 4), ((64, 64), 4), ((5, 2), 1), ((3, 3), 3)])
def test_median_abs_step_equals_numpy(shape: tuple[int, int], step: int) -> None:
    rng = np.random.default_rng(shape[0] * 100 + shape[1])
    for trial in range(20):
        a = rng.normal(9.0, 0.01, shape).astype(np.float32)
        if trial % 3 == 0:   # many ties, as on a table-quantised log image
            a = np.round(a, 2).astype(np.float32)
        if trial % 5 == 0:
            a[:, : shape[1] // 2] = 9.0   # zero differences: the median may be an exact 0
        steps = np.abs(np.diff(a[::step], axis=1))
        expected = float(np.median(steps))
        assert kernels.median_abs_step(a, step, -np.inf) == expected
        # Given a level that matters, max(level, median): whether the count settles it (most steps at or
        # below the level) or the selection runs, at the steps' own values (ties) and between them.
        for low in (0.0, float(np.min(steps)), float(np.quantile(steps, 0.3)), expected,
                    float(np.float32(expected) + np.float32(1e-6)), float(np.quantile(steps, 0.7)), 1.0):
            assert kernels.median_abs_step(a, step, low) == max(low, expected), (low, expected)


def test_median_abs_step_has_no_answer_for_nothing_or_a_non_finite_value() -> None:
    assert np.isnan(kernels.median_abs_step(np.zeros((4, 1), np.float32), 1, 0.0))
    a = np.zeros((4, 6), np.float32)
    a[2, 3] = np.inf
    assert np.isnan(kernels.median_abs_step(a, 1, 0.5))   # even though most steps are below the level
    a[2, 3] = np.nan
    assert np.isnan(kernels.median_abs_step(a, 1, 0.5))


def test_coarse_components_match_opencv_and_the_core_boxes() -> None:
    rng = np.random.default_rng(11)
    a = cv2.GaussianBlur(rng.normal(0, 1, (96, 120)).astype(np.float32), (0, 0), 2.0)
    a[40:44, 10:90] += 0.8   # a long component spanning several noise blobs
    threshold, fraction = 0.15, 0.5
    labels = np.zeros(a.shape, dtype=np.int32)
    stats, peaks = kernels.coarse_components(a, threshold, fraction, labels)
    n, ref_labels, ref_stats, _ = cv2.connectedComponentsWithStats((a > threshold).view(np.uint8), connectivity=8)
    assert n > 5 and len(stats) == n
    # The same partition (OpenCV numbers its components in the order of 2x2 blocks, ours in the order
    # of their first pixel: the numbers may differ, the components may not).
    to_ref = np.zeros(n, dtype=np.int64)
    to_ref[labels.ravel()] = ref_labels.ravel()
    np.testing.assert_array_equal(to_ref[labels], ref_labels)
    assert len(set(to_ref.tolist())) == n
    ref = ref_stats[to_ref]
    np.testing.assert_array_equal(stats[1:, kernels.STAT_AREA], ref[1:, cv2.CC_STAT_AREA])
    np.testing.assert_array_equal(stats[1:, kernels.STAT_X0], ref[1:, cv2.CC_STAT_LEFT])
    np.testing.assert_array_equal(stats[1:, kernels.STAT_Y0], ref[1:, cv2.CC_STAT_TOP])
    np.testing.assert_array_equal(stats[1:, kernels.STAT_X1] - stats[1:, kernels.STAT_X0], ref[1:, cv2.CC_STAT_WIDTH])
    np.testing.assert_array_equal(stats[1:, kernels.STAT_Y1] - stats[1:, kernels.STAT_Y0], ref[1:, cv2.CC_STAT_HEIGHT])
    # Without a label image: the same statistics.
    unlabelled, unlabelled_peaks = kernels.coarse_components(a, threshold, fraction, np.zeros((0, 0), np.int32))
    np.testing.assert_array_equal(unlabelled, stats)
    np.testing.assert_array_equal(unlabelled_peaks, peaks)
    # Numbered in raster order of their first pixel.
    firsts = [int(np.flatnonzero(labels.ravel() == label)[0]) for label in range(1, n)]
    assert firsts == sorted(firsts)
    for label in range(1, n):
        comp = labels == label
        peak = float(a[comp].max())
        assert peaks[label] == peak
        ys, xs = np.nonzero(comp & (a >= fraction * peak))
        box = stats[label, kernels.STAT_CORE_X0:kernels.STAT_CORE_Y1 + 1]
        assert tuple(box) == (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)


def test_coarse_components_of_nothing_of_everything_and_of_a_checkerboard() -> None:
    a = np.zeros((30, 40), np.float32)
    stats, peaks = kernels.coarse_components(a, 0.5, 0.5, np.zeros(a.shape, np.int32))
    assert len(stats) == 1 and len(peaks) == 1
    a[:] = 1.0   # one component filling the image
    labels = np.zeros(a.shape, np.int32)
    stats, peaks = kernels.coarse_components(a, 0.5, 0.5, labels)
    assert len(stats) == 2 and stats[1, kernels.STAT_AREA] == a.size and (labels == 1).all()
    # The most runs there can be, each pixel its own run, all joined diagonally.
    board = (np.indices((31, 40)).sum(axis=0) % 2).astype(np.float32)
    labels = np.zeros(board.shape, np.int32)
    stats, peaks = kernels.coarse_components(board, 0.5, 0.5, labels)
    assert len(stats) == 2 and stats[1, kernels.STAT_AREA] == board.sum() and (labels == board).all()
    assert tuple(stats[1, kernels.STAT_X0:kernels.STAT_Y1 + 1]) == (0, 0, 40, 31)


def test_a_read_only_frame_compiles_nothing_after_the_warm_up() -> None:
    from appliance.recognition import RecognitionSettings, detect, log_background

    kernels.warm_up()
    names = ("block_mean_log", "block_mean_log_4", "median_abs_step", "coarse_components", "upsample_attenuation",
             "window_attenuation", "coarse_candidates")
    compiled = {name: len(getattr(kernels, name).signatures) for name in names}
    image = np.random.default_rng(3).normal(30000, 60, (256, 256)).astype(np.uint16)
    image[100:108, 60:160] = 9000
    image.flags.writeable = False   # a grabber's or a recording's buffer
    blobs = detect(image, log_background(image, 48, 1000.0), RecognitionSettings(dark_level=1000.0))
    assert len(blobs) == 1
    assert {name: len(getattr(kernels, name).signatures) for name in names} == compiled


def _window_noise_cases() -> list[np.ndarray]:
    rng = np.random.default_rng(17)
    cases = [rng.normal(0, 0.02, (h, w)).astype(np.float32) for h, w in [(1, 2), (1, 3), (2, 2), (7, 9), (40, 61),
                                                                          (97, 130), (3, 700)]]
    cases.append((rng.integers(0, 4, (50, 70)) * 0.01).astype(np.float32))   # many ties at the median
    cases.append(np.full((30, 40), 0.25, np.float32))                         # all differences zero
    return cases


@pytest.mark.parametrize("case", range(len(_window_noise_cases())))
def test_window_attenuation_is_segments_attenuation_and_its_noise(case: int) -> None:
    values = _window_noise_cases()[case]
    h, w = values.shape
    # A frame whose gray levels index a table holding the wanted attenuations (the coarse log B is 0),
    # placed inside a larger frame so that the window is not the whole image.
    frame = np.zeros((h + 10, w + 6), np.uint16)
    frame[4:4 + h, 2:2 + w] = np.arange(1, h * w + 1, dtype=np.uint16).reshape(h, w) if h * w < 65535 else 0
    table = np.zeros(65536, np.float32)
    table[1:h * w + 1] = -values.ravel()
    coarse = np.zeros((max(1, (h + 10) // 4), max(1, (w + 6) // 4)), np.float32)
    fy, fx = (h + 10) / coarse.shape[0], (w + 6) / coarse.shape[1]
    a, sigma = kernels.window_attenuation(frame, 4, 4 + h, 2, 2 + w, coarse, fy, fx, table)
    reference = view_kernels.attenuation_from_coarse(frame, 4, 4 + h, 2, 2 + w, coarse, fy, fx, table)
    np.testing.assert_array_equal(a, reference)
    np.testing.assert_array_equal(a, values)
    assert sigma == view_kernels.noise_sigma_f32(reference)
    d = np.abs(np.diff(values, axis=1)).ravel()
    assert sigma == pytest.approx(1.4826 * float(np.median(d)) / np.sqrt(2.0), rel=1e-6, abs=1e-12)


def test_window_attenuation_leaves_the_noise_to_segment_where_it_is_not_a_plain_median() -> None:
    frame = np.full((16, 16), 5, np.uint16)
    table = np.zeros(65536, np.float32)
    coarse = np.zeros((4, 4), np.float32)
    assert kernels.window_attenuation(frame, 0, 16, 3, 4, coarse, 4.0, 4.0, table)[1] == -1.0   # 1 px wide
    table[5] = np.inf
    assert kernels.window_attenuation(frame, 0, 16, 0, 16, coarse, 4.0, 4.0, table)[1] == -1.0


def test_median_pair_gives_numpys_order_statistics() -> None:
    # Uniform values, and values with every 16th far above the rest (a strided sample of them would
    # see only those): both give numpy's order statistics, ties at the end included.
    rng = np.random.default_rng(23)
    for misleading in (True, False):
        values = rng.random(4096).astype(np.float32)
        if misleading:
            values[::16] = 10.0 + rng.random(256).astype(np.float32)
        bits = values.view(np.uint32)
        for k in (0, 100, 2047, 4094):
            lower, upper = kernels._median_pair(bits.copy(), bits.size, k)
            ordered = np.sort(values)
            got = np.array([lower, upper], dtype=np.uint32).view(np.float32)
            assert (got[0], got[1]) == (ordered[k], ordered[k + 1])


def _reference_windows(a: np.ndarray, shape: tuple[int, int], fx: float, fy: float, margin_px: float,
                       cone_reach: float, max_extent_px: float, threshold: float, floor: float) -> list[Roi]:
    """The windows as detection computed them before coarse_candidates: components, their cores' boxes
    in Python (long cores left out), Roi.around."""
    labels = np.zeros(a.shape, np.int32)
    stats, peaks = kernels.coarse_components(a, threshold, 0.5, labels)
    order = np.argsort(-stats[1:, kernels.STAT_AREA], kind="stable")[:24] + 1
    windows = []
    for label in order.tolist():
        if float(peaks[label]) < floor:
            continue
        x0, y0, x1, y1 = (int(v) for v in stats[label, kernels.STAT_CORE_X0:kernels.STAT_CORE_Y1 + 1])
        extent = max((x1 - x0) * fx, (y1 - y0) * fy)
        if extent > max_extent_px:
            continue
        roi = Roi.around(np.array([[x0 * fx, y0 * fy], [x1 * fx, y1 * fy]]),
                         margin_px + cone_reach * extent + 2.0 * max(fx, fy), shape)
        if roi is not None:
            windows.append(roi)
    return windows


def test_coarse_candidates_give_the_windows_of_the_python_steps() -> None:
    rng = np.random.default_rng(29)
    a = cv2.GaussianBlur(rng.normal(0, 0.05, (120, 150)).astype(np.float32), (0, 0), 1.0)
    for _ in range(40):   # blobs of all sizes and strengths, some at the edges
        y, x = rng.integers(-4, 120), rng.integers(-4, 150)
        a[max(y, 0):y + rng.integers(1, 12), max(x, 0):x + rng.integers(1, 12)] += rng.uniform(0.05, 1.0)
    a[60:63, 5:145] += 0.4   # a long core
    shape = (480, 600)
    for margin, reach, longest in ((14.0, 0.7, 420.0), (40.0, 0.0, 60.0), (4.0, 2.0, 20.0)):
        rows, peaks, threshold = kernels.coarse_candidates(a, 4, 0.0, 6.0, 0.0625, 0.125, 0.5, 24, 4.0, 4.0, longest,
                                                           margin, reach, shape[0], shape[1])
        assert threshold >= 0.0625
        windows = [Roi(*row[1:5]) for row in rows.tolist() if row[0] == kernels.WINDOW]
        expected = _reference_windows(a, shape, 4.0, 4.0, margin, reach, longest, threshold, 0.125)
        assert windows == expected and len(windows) > 3
        long_cores = [row for row in rows.tolist() if row[0] == kernels.LONG_CORE]
        assert long_cores or longest == 420.0


def test_coarse_windows_and_segment_see_the_windows_as_before() -> None:
    """detect's windows, attenuation and noise: segment on them gives what it gives measuring them itself."""
    from appliance.recognition import RecognitionSettings, detect
    from appliance.recognition.detection import coarse_windows
    from appliance.recognition.segmentation import segment

    rng = np.random.default_rng(31)
    image = rng.poisson(20000, (384, 384)).astype(np.uint16)
    image[100:108, 60:140] = rng.poisson(9000, (8, 80))
    image[250:262, 200:230] = rng.poisson(12000, (12, 30))
    settings = RecognitionSettings(dark_level=1000.0)
    background = log_background(image, 48, 1000.0)
    windows = coarse_windows(background, settings)
    assert len(windows) == 2
    blobs = detect(image, background, settings)
    expected = sorted((b for roi in windows for b in segment(image, background, roi, settings)),
                      key=lambda b: -b.strength)
    assert len(blobs) == len(expected) == 2
    for got, want in zip(blobs, expected):
        assert got.window == want.window and got.sigma == want.sigma and got.centroid_px == want.centroid_px
        np.testing.assert_array_equal(got.weights, want.weights)
        np.testing.assert_array_equal(got.mask, want.mask)
    a = attenuation(image, background, windows[0], 1000.0)
    assert blobs[0].sigma == view_kernels.noise_sigma_f32(a) or blobs[1].sigma == view_kernels.noise_sigma_f32(a)
