"""Full-frame detection: robot candidates anywhere in one view, coarse to fine.

The coarse attenuation image kept by :func:`~appliance.recognition.background.log_background` is
searched for strong components; each one gives a window that :func:`~.segmentation.segment` then
examines at full resolution, exactly as a tracked frame's region of interest is. So a cold frame
never makes a full-resolution pass beyond the background's downsampling.
"""
from __future__ import annotations

import math

import numpy as np

from appliance.recognition import background_kernels
from appliance.recognition.background import LogBackground
from appliance.recognition.segmentation import (
    MAX_CANDIDATES,
    Blob,
    Roi,
    _log_table,
    core_of,
    segment,
)
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
    blobs: list[Blob] = []
    compiled = image.dtype in (np.uint16, np.uint8)
    table = _log_table(float(settings.dark_level)) if compiled else None
    for roi in coarse_windows(background, settings):
        a: np.ndarray | None = None
        sigma: float | None = None
        if compiled:
            # The window's attenuation and its noise in one compiled call: the values segment would
            # compute, without its second pass over the window for the noise.
            a, sigma = background_kernels.window_attenuation(image, roi.y0, roi.y1, roi.x0, roi.x1,
                                                             background.coarse, background.fy, background.fx,
                                                             table)
            if sigma < 0:
                sigma = None
        for blob in segment(image, background, roi, settings, sigma=sigma, region_attenuation=a,
                            touching_bodies=True):
            # Neighbouring coarse components may hold the same body.
            if all(math.hypot(blob.centroid_px[0] - b.centroid_px[0], blob.centroid_px[1] - b.centroid_px[1]) > 2.0
                   for b in blobs):
                blobs.append(blob)
    blobs.sort(key=lambda b: -b.strength)
    return blobs[:MAX_CANDIDATES]


def coarse_windows(background: LogBackground, settings: RecognitionSettings) -> list[Roi]:
    """The full-resolution windows around the coarse image's candidates, largest component first.

    The threshold, the components, their peaks, the bounding boxes of their cores and the windows
    around them come from one compiled kernel (:func:`~.background_kernels.coarse_candidates`); Python
    sees one row per window, and cuts the rare core too long to be a robot.
    """
    # (float32 C-contiguous, the kernels' compiled signature, whoever built the background.)
    a = np.ascontiguousarray(background.coarse_attenuation, dtype=np.float32)
    # The coarse image is the area mean, not the blur, of the full one: its noise is sigma itself, and a
    # thin robot's peak is diluted by the averaging (hence half the full-resolution floor).
    floor = 0.5 * settings.min_peak_attenuation
    least = settings.core_fraction * floor
    # The robust noise from neighbour differences (edges are too few to matter) on every fourth row:
    # still some 16000 differences (1 % standard error) on the 1024 px detector's coarse grid. Below
    # `quiet` (a little under the median at which detect_sigma * sigma reaches `least`) the threshold is
    # `least` whatever the median is, and the kernel skips the selection (at the simulated dose the
    # noise term is ~0.43 of it).
    quiet = 0.999 * least / settings.detect_sigma * math.sqrt(2.0) / 1.4826
    fx, fy = background.fx, background.fy
    height, width = background.shape
    # Room for the faint cone beyond the core, the ring and the background fill around the body: the
    # core's box grown by roi_margin_px + cone_reach x its extent + two coarse pixels.
    rows, peaks, threshold = background_kernels.coarse_candidates(
        a, 4, quiet, settings.detect_sigma, least, floor, settings.core_fraction, MAX_CANDIDATES * 3, fx, fy,
        float(settings.max_extent_px), float(settings.roi_margin_px), settings.cone_reach, height, width)
    labels: np.ndarray | None = None
    windows: list[Roi] = []
    for kind, x0, y0, x1, y1, label in rows.tolist():
        if kind == background_kernels.WINDOW:
            windows.append(Roi(x0, y0, x1, y1))
            continue
        # A long core may be a vessel with the robot on it: keep only the part connected to the peak.
        bx0, by0, bx1, by1 = x0, y0, x1, y1
        if labels is None:   # the label image, only for this (rare) case: the components again
            labels = np.zeros(a.shape, dtype=np.int32)
            background_kernels.coarse_components(a, threshold, settings.core_fraction, labels)
        comp = labels[by0:by1, bx0:bx1] == label
        ys, xs = np.nonzero(core_of(a[by0:by1, bx0:bx1], comp, float(peaks[label]), settings.core_fraction))
        x0, y0, x1, y1 = bx0 + int(xs.min()), by0 + int(ys.min()), bx0 + int(xs.max()) + 1, by0 + int(ys.max()) + 1
        extent = max((x1 - x0) * fx, (y1 - y0) * fy)
        if extent > settings.max_extent_px:
            continue
        margin = settings.roi_margin_px + settings.cone_reach * extent + 2.0 * max(fx, fy)
        roi = Roi.around(np.array([[x0 * fx, y0 * fy], [x1 * fx, y1 * fy]]), margin, background.shape)
        if roi is not None:
            windows.append(roi)
    return windows
