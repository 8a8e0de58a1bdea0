"""Full-frame detection: robot candidates anywhere in one view, coarse to fine.

The coarse attenuation image kept by :func:`~appliance.recognition.background.log_background` is
searched for strong components; each one gives a window that :func:`~.segmentation.segment` then
examines at full resolution, exactly as a tracked frame's region of interest is. So a cold frame
never makes a full-resolution pass beyond the background's downsampling.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from appliance.recognition.background import LogBackground
from appliance.recognition.segmentation import MAX_CANDIDATES, Blob, Roi, core_of, noise_sigma, segment
from appliance.recognition.settings import RecognitionSettings


def detect(image: np.ndarray, background: LogBackground, settings: RecognitionSettings | None = None) -> list[Blob]:
    """Robot candidates anywhere in the image, strongest first, without a full-resolution pass.

    Candidates are found on the coarse attenuation image kept by :func:`log_background` (each coarse
    pixel the mean of ``f x f`` pixels: ``f`` times less noise, ``f^2`` times fewer pixels); each one's
    strong core (``core_fraction`` of its coarse peak: this leaves out the weaker vessel the robot lies
    in) gives a window that :func:`segment` then examines at full resolution, exactly as a tracked
    frame's ROI is. Cores longer than ``max_extent_px`` (a vessel seen lengthwise) are not robots.
    """
    settings = settings or RecognitionSettings()
    a = background.coarse_attenuation
    # Every other row: a quarter of the median's cost, and still tens of thousands of differences.
    sigma = noise_sigma(a[::2])
    if not np.isfinite(sigma) or sigma <= 0:
        sigma = 1e-3
    # The coarse image is the area mean, not the blur, of the full one: its noise is sigma itself, and a
    # thin robot's peak is diluted by the averaging (hence half the full-resolution floor).
    floor = 0.5 * settings.min_peak_attenuation
    threshold = max(settings.detect_sigma * sigma, settings.core_fraction * floor)
    n, labels, stats, _ = cv2.connectedComponentsWithStats((a > threshold).view(np.uint8), connectivity=8)
    order = np.argsort(-stats[1:, cv2.CC_STAT_AREA])[:MAX_CANDIDATES * 3] + 1
    fx, fy = background.fx, background.fy
    blobs: list[Blob] = []
    for label in order:
        x, y, bw, bh = (int(v) for v in stats[label, :4])
        comp = labels[y:y + bh, x:x + bw] == label
        values = a[y:y + bh, x:x + bw]
        peak = float(values[comp].max())
        if peak < floor:
            continue
        core = comp & (values >= settings.core_fraction * peak)
        ys, xs = np.nonzero(core)
        extent = max((xs.max() - xs.min() + 1) * fx, (ys.max() - ys.min() + 1) * fy)
        if extent > settings.max_extent_px:
            ys, xs = np.nonzero(core_of(values, comp, peak, settings.core_fraction))
            extent = max((xs.max() - xs.min() + 1) * fx, (ys.max() - ys.min() + 1) * fy)
            if extent > settings.max_extent_px:
                continue
        # Room for the faint cone beyond the core, the ring and the background fill around the body.
        margin = settings.roi_margin_px + settings.cone_reach * extent + 2.0 * max(fx, fy)
        corners = np.array([[(x + xs.min()) * fx, (y + ys.min()) * fy],
                            [(x + xs.max() + 1) * fx, (y + ys.max() + 1) * fy]])
        roi = Roi.around(corners, margin, image.shape)
        if roi is None:
            continue
        for blob in segment(image, background, roi, settings):
            # Neighbouring coarse components may hold the same body.
            if all(math.hypot(blob.centroid_px[0] - b.centroid_px[0], blob.centroid_px[1] - b.centroid_px[1]) > 2.0
                   for b in blobs):
                blobs.append(blob)
    blobs.sort(key=lambda b: -b.strength)
    return blobs[:MAX_CANDIDATES]
