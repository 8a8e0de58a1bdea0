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
from typing import Any, TypeVar

import numpy as np

from appliance.recognition import roi_kernels, view_kernels
from appliance.recognition.features import _LEVELS, _LEVELS_ARRAY, Features2D, clutter_axis_sigma_rad, features
from appliance.recognition.segmentation import (
    _SMOOTH_NOISE_GAIN,
    MAX_CANDIDATES,
    Blob,
    LogBackground,
    Roi,
    _log_table,
    _refine_parameters,
    body_width_px,
    segment,
)
from appliance.recognition.settings import RecognitionSettings

_N_LEVELS = len(_LEVELS)
_OUT_SIZE = roi_kernels.OUT_SIZE + 2 * _N_LEVELS
_CENTROID, _AXIS, _TIPS = roi_kernels.CENTROID, roi_kernels.AXIS, roi_kernels.TIPS
T = TypeVar("T")


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


def _kernel_settings(settings: RecognitionSettings) -> tuple:
    """The settings as :func:`.roi_kernels.search_view` takes them, cached per settings object (frozen)."""
    cached = _KERNEL_SETTINGS.get(id(settings))
    if cached is not None and cached[0] is settings:
        return cached[1]
    params, ring_outer, ring_inner, near = _refine_parameters(settings)
    value = (_log_table(float(settings.dark_level)), settings.detect_sigma,
             settings.core_fraction * settings.min_peak_attenuation, int(settings.min_pixels), params, ring_outer,
             ring_inner, near, float(settings.gate_px), float(settings.axis_saturation),
             float(settings.head_ramp_ratio), float(settings.head_min_ramp_px))
    if len(_KERNEL_SETTINGS) > 16:
        _KERNEL_SETTINGS.clear()
    _KERNEL_SETTINGS[id(settings)] = (settings, value)
    return value


_KERNEL_SETTINGS: dict[int, tuple[RecognitionSettings, tuple]] = {}


def _frozen(cls: type[T], fields: dict[str, Any]) -> T:
    """An instance of the frozen dataclass ``cls`` holding ``fields`` (every field, by name), made without
    its generated ``__init__``: that one sets each field through ``object.__setattr__`` (~3 us for a
    :class:`Blob` or a :class:`Features2D`, one of each per view and frame). None of the classes built
    so (:class:`Blob`, :class:`Features2D`, :class:`Roi`, :class:`.ViewObservation`, :class:`.Pairing`; and
    the tracker's :class:`.Posture`, not frozen, whose ``__init__`` is cold code on a frame off the plain
    path) has a ``__post_init__``; the tests compare every field with the ones ``__init__`` builds."""
    instance = object.__new__(cls)
    instance.__dict__.update(fields)
    return instance


def _compiled(image: np.ndarray, log_bg: LogBackground, roi: Roi, settings: RecognitionSettings,
              predicted_px: tuple[float, float], sigma: float | None) -> tuple[Blob, Features2D] | None | bool:
    """One compiled call; False where its gate test was too close to call (the caller takes the general path)."""
    (table, detect_sigma, floor, min_pixels, params, ring_outer, ring_inner, near, gate_px, axis_saturation,
     head_ramp_ratio, head_min_ramp_px) = _kernel_settings(settings)
    known = float(sigma) if sigma is not None and math.isfinite(sigma) and sigma > 0 else 0.0
    out = np.empty(_OUT_SIZE)
    x0, y0 = roi.x0, roi.y0
    status, weights, mask = roi_kernels.search_view(
        image, y0, roi.y1, x0, roi.x1, log_bg.coarse, log_bg.fy, log_bg.fx, table, view_kernels.GAUSSIAN_5,
        detect_sigma, _SMOOTH_NOISE_GAIN, floor, known, min_pixels, MAX_CANDIDATES * 3, MAX_CANDIDATES, params,
        ring_outer, ring_inner, near, predicted_px[0], predicted_px[1], gate_px, axis_saturation, _LEVELS_ARRAY,
        head_ramp_ratio, head_min_ramp_px, out)
    if status == roi_kernels.NOT_FOUND:
        return None
    if status == roi_kernels.BORDERLINE:
        return False
    if status == roi_kernels.NO_WEIGHT:
        raise ValueError("weights sum to zero or less")
    return blob_and_features(out, weights, mask, x0, y0, None)


def blob_and_features(out: np.ndarray, weights: np.ndarray, mask: np.ndarray, x0: int, y0: int,
                      axis_sigma_rad: float | None) -> tuple[Blob, Features2D]:
    """The :class:`Blob` and :class:`Features2D` of a found view from :func:`.roi_kernels.search_view`'s output
    ``out`` (its first ``OUT_SIZE + 2 * levels`` numbers; the features' arrays are views of it), the chosen
    blob's ``weights`` and ``mask``, and the ROI's origin ``x0, y0``. ``axis_sigma_rad``: the axis
    uncertainty with the clutter term if already computed (by :mod:`.steady_kernels`), else None (here)."""
    (wy0, wy1, wx0, wx1, height, baseline, strength, cx, cy, edge, minor, clutter, count, used_sigma,
     _, _, _, _, _, _, _, _, l1, l2, axis_sigma, head, ramp_plus, ramp_minus, *reaches) = out[:_OUT_SIZE].tolist()
    window = _frozen(Roi, {"x0": x0 + int(wx0), "y0": y0 + int(wy0), "x1": x0 + int(wx1), "y1": y0 + int(wy1)})
    pixel_count = int(count)
    # As segmentation._blob_from_component builds it.
    blob = _frozen(Blob, {
        "window": window, "weights": weights, "mask": mask.view(bool), "pixel_count": pixel_count, "peak": height,
        "baseline": baseline, "sigma": used_sigma, "strength": strength,
        "centroid_px": (window.x0 + cx, window.y0 + cy), "touches_border": bool(edge),
        "width_px": body_width_px(minor, strength), "clutter": clutter})
    if axis_sigma_rad is None:
        axis_sigma_rad = math.hypot(axis_sigma, clutter_axis_sigma_rad(clutter, pixel_count, height, strength, l1, l2))
    # As features.weighted_features builds them; the arrays are views of this call's own output.
    feat = _frozen(Features2D, {
        "centroid": out[_CENTROID:_CENTROID + 2], "axis": out[_AXIS:_AXIS + 2], "eigenvalues": (l1, l2),
        "tips": out[_TIPS:_TIPS + 4].reshape(2, 2), "pixel_count": pixel_count,
        "head_index": None if head < 0 else int(head), "ramp_px": (ramp_plus, ramp_minus),
        "reach": (dict(zip(_LEVELS, reaches[:_N_LEVELS])), dict(zip(_LEVELS, reaches[_N_LEVELS:]))),
        "axis_sigma_rad": axis_sigma_rad})
    return blob, feat
