"""The fast paths measured by ``appliance bench`` give what the slow ones gave: the coarse background's
full-resolution windows are the upsampled image's, and coarse-to-fine detection finds the robot the
full-frame pass finds, with the same features."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from appliance.recognition import (
    LogBackground,
    RecognitionSettings,
    Roi,
    detect,
    features,
    log_background,
    segment,
)

SIZE = 384


@pytest.fixture(scope="module")
def scene() -> object:
    from appliance.commands.bench import RenderedScene

    return RenderedScene(SIZE, robot_id=1, seed=3)


@pytest.fixture(scope="module")
def frame(scene: object) -> np.ndarray:
    return next(scene.pairs())[0]  # type: ignore[attr-defined]


def test_background_windows_are_slices_of_the_upsampled_image() -> None:
    rng = np.random.default_rng(1)
    coarse = rng.normal(9.0, 0.2, (37, 53)).astype(np.float32)
    bg = LogBackground(coarse, coarse, (150, 213))   # sizes that are not multiples of the factor
    full = cv2.resize(coarse, (213, 150), interpolation=cv2.INTER_LINEAR)
    for rows, cols in ((slice(0, 150), slice(0, 213)), (slice(5, 40), slice(100, 213)),
                       (slice(140, 150), slice(0, 3)), (slice(77, 78), slice(99, 100))):
        np.testing.assert_allclose(bg[rows, cols], full[rows, cols], atol=2e-5)
    np.testing.assert_allclose(np.asarray(bg), full)
    assert bg[0:10, 0:10].shape == (10, 10)


def test_log_background_removes_a_dark_object() -> None:
    image = np.full((256, 256), 30000, dtype=np.uint16)
    image[100:110, 60:200] = 8000
    bg = log_background(image, 48, dark_level=1000.0)
    assert bg.shape == (256, 256)
    # The open field, not the object: log(29000) everywhere, the object's dip closed over.
    np.testing.assert_allclose(bg[95:115, 50:210], np.log(29000.0), atol=0.02)
    assert float(bg.coarse_attenuation.max()) > 0.5   # the object stands out of the coarse attenuation


def test_detect_finds_what_the_full_frame_pass_finds(frame: np.ndarray, scene: object) -> None:
    settings = RecognitionSettings(dark_level=scene.dark_level)  # type: ignore[attr-defined]
    bg = log_background(frame, settings.background_scale_px, settings.dark_level)
    coarse_to_fine = detect(frame, bg, settings)
    full = segment(frame, np.asarray(bg), None, settings)
    assert coarse_to_fine and full
    a, b = coarse_to_fine[0], full[0]
    assert a.pixel_count == b.pixel_count
    np.testing.assert_allclose(a.centroid_px, b.centroid_px, atol=0.05)
    fa, fb = features(a, settings), features(b, settings)
    np.testing.assert_allclose(fa.tips, fb.tips, atol=0.1)
    assert abs(float(fa.axis @ fb.axis)) > np.cos(np.radians(0.1))


def test_detect_ignores_an_empty_frame_and_a_long_vessel() -> None:
    settings = RecognitionSettings(dark_level=1000.0)
    rng = np.random.default_rng(2)
    image = (30000 + rng.normal(0, 60, (256, 256))).astype(np.uint16)
    assert detect(image, log_background(image, 48, 1000.0), settings) == []
    # A long, weak contrast-filled vessel: extent beyond any robot's.
    image[120:126, :] = (image[120:126, :] * 0.75).astype(np.uint16)
    settings_short = RecognitionSettings(dark_level=1000.0, max_extent_px=100)
    assert detect(image, log_background(image, 48, 1000.0), settings_short) == []


def test_roi_search_reads_the_same_window_either_way(frame: np.ndarray, scene: object) -> None:
    settings = RecognitionSettings(dark_level=scene.dark_level)  # type: ignore[attr-defined]
    bg = log_background(frame, settings.background_scale_px, settings.dark_level)
    blob = detect(frame, bg, settings)[0]
    roi = Roi(max(0, blob.window.x0 - 5), max(0, blob.window.y0 - 5), blob.window.x1 + 5, blob.window.y1 + 5)
    lazy = segment(frame, bg, roi, settings)[0]
    dense = segment(frame, np.asarray(bg), roi, settings)[0]
    assert lazy.pixel_count == dense.pixel_count
    np.testing.assert_allclose(lazy.centroid_px, dense.centroid_px, atol=1e-3)


def test_sliding_windows_reuse_the_cached_one_with_the_same_values() -> None:
    rng = np.random.default_rng(4)
    coarse = rng.normal(9.0, 0.2, (64, 64)).astype(np.float32)
    full = cv2.resize(coarse, (256, 256), interpolation=cv2.INTER_LINEAR)
    bg = LogBackground(coarse, coarse, (256, 256))
    for step in range(40):   # a ROI drifting by 3 px a frame, then jumping away and back
        y0, x0 = 50 + 3 * step if step < 30 else 10, 80 + 2 * step if step < 30 else 200
        window = bg[y0:y0 + 40, x0:x0 + 50]
        np.testing.assert_allclose(window, full[y0:y0 + 40, x0:x0 + 50], atol=2e-5)
        assert window.shape == (40, min(50, 256 - x0))


def test_scalar_profile_crossings_equal_the_array_ones() -> None:
    features_module = __import__("sys").modules["appliance.recognition.features"]
    rng = np.random.default_rng(5)
    for _ in range(200):
        n = int(rng.integers(3, 60))
        profile = np.convolve(rng.random(n), np.ones(3) / 3, mode="same")
        s0 = float(rng.normal(-20, 5))
        for fraction in (0.2, 0.25, 0.5, 0.64, 0.8, 1.0):
            level = fraction * float(profile.max())
            for direction in (+1, -1):
                assert features_module._reach_scalar(profile.tolist(), s0, level, direction) == \
                    features_module._reach(profile, s0, level, direction)
