"""The tracker's search of one view's region of interest: the robot's blob near the prediction and its features.

``find_in_roi`` gives what :func:`.segmentation.segment` followed by the tracker's gate and
:func:`.features.features` give (the strongest whole blob within ``settings.gate_px`` of the predicted
centroid among the kept candidates, and its features), for the same inputs bit for bit. For the
steady state's usual inputs (16-bit frames, a coarse :class:`LogBackground`, the weighted estimator)
the whole chain is one compiled call (:func:`.roi_kernels.search_view`) and the :class:`Blob` and
:class:`Features2D` are built from its numbers; any other input takes the general path.
"""
from __future__ import annotations

import math

import numpy as np

from appliance.recognition import roi_kernels, view_kernels
from appliance.recognition.features import _LEVELS, _LEVELS_ARRAY, Features2D, features
from appliance.recognition.segmentation import (
    _SMOOTH_NOISE_GAIN,
    MAX_CANDIDATES,
    Blob,
    LogBackground,
    Roi,
    _log_table,
    _refine_parameters,
    segment,
)
from appliance.recognition.settings import RecognitionSettings

_N_LEVELS = len(_LEVELS)
_OUT_SIZE = roi_kernels.OUT_SIZE + 2 * _N_LEVELS
_R = roi_kernels.REACH


def find_in_roi(image: np.ndarray, log_bg: np.ndarray | LogBackground, roi: Roi, settings: RecognitionSettings,
                predicted_px: tuple[float, float], *, sigma: float | None = None) -> tuple[Blob, Features2D] | None:
    """The robot's blob in ``roi`` and its features, or None if no whole blob lies near ``predicted_px``.

    ``sigma`` is the view's known noise sigma (None: measured on the ROI), as for :func:`.segment`.
    Raises ValueError where :func:`.features.features` does (weights summing to zero or less).
    """
    if (settings.estimator == "weighted" and isinstance(log_bg, LogBackground) and image.dtype == np.uint16
            and image.flags.c_contiguous):
        found = _compiled(image, log_bg, roi, settings, predicted_px, sigma)
        if found is not False:
            return found
    return _general(image, log_bg, roi, settings, predicted_px, sigma)


def _general(image: np.ndarray, log_bg: np.ndarray | LogBackground, roi: Roi, settings: RecognitionSettings,
             predicted_px: tuple[float, float], sigma: float | None) -> tuple[Blob, Features2D] | None:
    """The definition: :func:`.segment`, the gate on the candidates, :func:`.features`."""
    u, v = predicted_px
    near = [b for b in segment(image, log_bg, roi, settings, sigma=sigma) if not b.touches_border
            and math.hypot(b.centroid_px[0] - u, b.centroid_px[1] - v) <= settings.gate_px]
    if not near:
        return None
    return near[0], features(near[0], settings)


def _compiled(image: np.ndarray, log_bg: LogBackground, roi: Roi, settings: RecognitionSettings,
              predicted_px: tuple[float, float], sigma: float | None) -> tuple[Blob, Features2D] | None | bool:
    """One compiled call; False where its gate test was too close to call (the caller takes the general path)."""
    params, ring_outer, ring_inner, near = _refine_parameters(settings)
    known = float(sigma) if sigma is not None and math.isfinite(sigma) and sigma > 0 else 0.0
    out = np.empty(_OUT_SIZE)
    status, weights, mask = roi_kernels.search_view(
        image, roi.y0, roi.y1, roi.x0, roi.x1, log_bg.coarse, log_bg.fy, log_bg.fx, _log_table(float(settings.dark_level)),
        view_kernels.GAUSSIAN_5, settings.detect_sigma, _SMOOTH_NOISE_GAIN,
        settings.core_fraction * settings.min_peak_attenuation, known, settings.min_pixels, MAX_CANDIDATES * 3,
        MAX_CANDIDATES, params, ring_outer, ring_inner, near, predicted_px[0], predicted_px[1], settings.gate_px,
        settings.axis_saturation, _LEVELS_ARRAY, settings.head_ramp_ratio, settings.head_min_ramp_px, out)
    if status == roi_kernels.NOT_FOUND:
        return None
    if status == roi_kernels.BORDERLINE:
        return False
    if status == roi_kernels.NO_WEIGHT:
        raise ValueError("weights sum to zero or less")
    (wy0, wy1, wx0, wx1, height, baseline, strength, cx, cy, edge, minor, clutter, count, used_sigma,
     _, _, _, _, _, _, _, _, l1, l2, axis_sigma, head, ramp_plus, ramp_minus, *reaches) = out.tolist()
    window = Roi(roi.x0 + int(wx0), roi.y0 + int(wy0), roi.x0 + int(wx1), roi.y0 + int(wy1))
    pixel_count = int(count)
    # As segmentation._blob_from_component builds it (a cylinder's chord profile has variance r^2 / 4).
    blob = Blob(window=window, weights=weights, mask=mask.view(bool), pixel_count=pixel_count, peak=height,
                baseline=baseline, sigma=used_sigma, strength=strength, centroid_px=(window.x0 + cx, window.y0 + cy),
                touches_border=bool(edge), width_px=4.0 * math.sqrt(max(minor / strength, 0.0625)), clutter=clutter)
    # As features.weighted_features builds them; the arrays are views of this call's own output.
    reach = (dict(zip(_LEVELS, reaches[:_N_LEVELS])), dict(zip(_LEVELS, reaches[_N_LEVELS:])))
    feat = Features2D(out[roi_kernels.CENTROID:roi_kernels.CENTROID + 2], out[roi_kernels.AXIS:roi_kernels.AXIS + 2],
                      (l1, l2), out[roi_kernels.TIPS:roi_kernels.TIPS + 4].reshape(2, 2), pixel_count,
                      None if head < 0 else int(head), (ramp_plus, ramp_minus), reach, axis_sigma)
    return blob, feat
