"""Sub-pixel detection of calibration beads: dark (metal) blobs in a raw X-ray image.

A steel bead attenuates the beam, so it is darker than its surroundings. Working on attenuation
``a = log(background) - log(I)`` (background from a grey-level closing larger than any bead) makes the
detector independent of exposure and of slow intensity ramps (heel effect, plate thickness). A bead's
centre is the attenuation-weighted centroid of its blob: the projection of a sphere weighted by its
path length is symmetric about the projected centre, so this centroid is unbiased to a small fraction
of a pixel, unlike a binary centroid of a thresholded blob.

Blobs whose shape is not round (two beads overlapping in projection, a wire, the edge of the phantom
frame) are rejected rather than given a biased centre: the calibration has beads to spare.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from appliance.errors import CalibrationError, InputDataError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BeadDetections:
    """Detected bead centres ``uv`` (M,2) px, equivalent radii (M,) px, peak attenuation (M,), rejects."""

    uv: np.ndarray
    radius_px: np.ndarray
    peak_attenuation: np.ndarray
    rejected_uv: np.ndarray  # blobs found but not round or out of size range, for the report

    def __len__(self) -> int:
        return len(self.uv)


def _as_float_image(image: np.ndarray, what: str) -> np.ndarray:
    array = np.asarray(image)
    if array.ndim == 3 and array.shape[2] in (3, 4):
        array = array[..., :3].mean(axis=2)
    if array.ndim != 2 or min(array.shape) < 16:
        raise InputDataError(f"{what}: expected a 2D grey image of at least 16x16 pixels, got shape {array.shape}")
    out = array.astype(np.float32)
    if not np.all(np.isfinite(out)):
        raise InputDataError(f"{what}: image has non-finite pixels")
    return out


def attenuation_image(image: np.ndarray, max_radius_px: float, *, bright: bool = False,
                      what: str = "image") -> np.ndarray:
    """``log(background / I)``: >0 where something absorbs; background from a closing (opening if bright)."""
    raw = _as_float_image(image, what)
    span = float(raw.max() - raw.min())
    if span <= 0:
        raise CalibrationError(f"{what}: the image is uniform (no beads can be found)")
    # Raw detector values (not shifted to their minimum: the darkest pixel would then sit near log 0 and
    # dominate); the small offset only keeps log finite at zero.
    level = np.maximum(raw, 0.0) + max(1.0, 1e-3 * span)
    size = 2 * int(np.ceil(max_radius_px)) + 3
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    # The closing of a noisy image rides on the noise peaks: close a smoothed copy, smooth the result,
    # and take the remaining offset (the median over the mostly empty image) off the signal.
    log_level = np.log(level)
    smoothed = cv2.GaussianBlur(log_level, (0, 0), 1.5)
    operation = cv2.MORPH_OPEN if bright else cv2.MORPH_CLOSE
    # Pad by replication ourselves: OpenCV's morphology treats the outside as neutral whatever the border
    # mode, so a closing next to the edge of an intensity ramp would take the ramp's far value.
    padded = cv2.copyMakeBorder(smoothed, size, size, size, size, cv2.BORDER_REPLICATE)
    closed = cv2.morphologyEx(padded, operation, kernel)[size:-size, size:-size]
    background = cv2.GaussianBlur(closed, (0, 0), size / 4.0)
    signal = (log_level - background) if bright else (background - log_level)
    signal -= np.median(signal)
    return signal.astype(np.float32)


def _noise_sigma(signal: np.ndarray) -> float:
    """Robust noise level of a (mostly empty) signal image: scaled median absolute deviation.

    Taken on the values, not on pixel differences: a detector's light spread correlates neighbouring
    pixels, which makes differences understate the noise a blob detector sees.
    """
    values = signal[::2, ::2].ravel()
    mad = float(np.median(np.abs(values - np.median(values))))
    return max(1.4826 * mad, 1e-6)


def detect_beads(image: np.ndarray, *, min_radius_px: float = 1.5, max_radius_px: float = 15.0,
                 bright: bool = False, threshold_sigma: float = 5.0, min_contrast: float = 0.01,
                 max_elongation: float = 1.35, what: str = "image") -> BeadDetections:
    """Find round dark (or ``bright``) blobs with radius in [min_radius_px, max_radius_px].

    ``threshold_sigma`` times the noise level (and at least ``min_contrast`` in attenuation units)
    separates beads from noise; ``max_elongation`` (ratio of the blob's principal standard deviations)
    rejects overlapping beads. Raises :class:`CalibrationError` when nothing bead-like is found.
    """
    signal = attenuation_image(image, max_radius_px, bright=bright, what=what)
    smooth = cv2.GaussianBlur(signal, (0, 0), 0.8)
    sigma = _noise_sigma(smooth)
    level = max(threshold_sigma * sigma, min_contrast)
    mask = (smooth > level).astype(np.uint8)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    min_area = np.pi * min_radius_px ** 2 * 0.5
    max_area = np.pi * max_radius_px ** 2 * 1.5
    h, w = signal.shape
    centres, radii, peaks, rejected = [], [], [], []
    for label in range(1, count):
        x0, y0, bw, bh, area = (int(v) for v in stats[label])
        if area < min_area:
            continue  # noise speck: not worth a report line
        # Weight pixels by attenuation in a window a little larger than the blob, so the faint rim counts
        # symmetrically on all sides; pixels of other blobs are masked out.
        pad = 2
        xa, ya = max(0, x0 - pad), max(0, y0 - pad)
        xb, yb = min(w, x0 + bw + pad), min(h, y0 + bh + pad)
        window_labels = labels[ya:yb, xa:xb]
        own = cv2.dilate((window_labels == label).astype(np.uint8), np.ones((2 * pad + 1, 2 * pad + 1), np.uint8))
        own &= ((window_labels == 0) | (window_labels == label)).astype(np.uint8)
        weights = np.where(own > 0, np.clip(signal[ya:yb, xa:xb], 0.0, None), 0.0).astype(np.float64)
        total = weights.sum()
        ys, xs = np.mgrid[ya:yb, xa:xb]
        if total <= 0:
            continue
        cu, cv = float((weights * xs).sum() / total), float((weights * ys).sum() / total)
        du, dv = xs - cu, ys - cv
        cov = np.array([[(weights * du * du).sum(), (weights * du * dv).sum()],
                        [(weights * du * dv).sum(), (weights * dv * dv).sum()]]) / total
        eig = np.linalg.eigvalsh(cov)
        elongation = float(np.sqrt(eig[1] / max(eig[0], 1e-12)))
        radius = float(np.sqrt(area / np.pi))
        touches_edge = x0 == 0 or y0 == 0 or x0 + bw == w or y0 + bh == h
        if area > max_area or elongation > max_elongation or touches_edge or radius < min_radius_px:
            rejected.append((cu, cv))
            continue
        centres.append((cu, cv))
        radii.append(radius)
        peaks.append(float(signal[ya:yb, xa:xb][own > 0].max()))
    if not centres:
        raise CalibrationError(
            f"{what}: no beads found (no round {'bright' if bright else 'dark'} blobs of radius "
            f"{min_radius_px:g}-{max_radius_px:g} px above {level:.3g} attenuation; {len(rejected)} blobs rejected "
            "as not round or out of size range)")
    log.info("%s: %d beads detected, %d blobs rejected (noise %.2g)", what, len(centres), len(rejected), sigma)
    return BeadDetections(np.asarray(centres), np.asarray(radii), np.asarray(peaks),
                          np.asarray(rejected, dtype=np.float64).reshape(-1, 2))
