"""The open-field background of one X-ray view, ``log B``, kept at a coarse scale.

The detector records ``I = I0(u, v) exp(-integral of mu)`` with a non-uniform open field ``I0`` (heel
effect, vignetting). Its estimate ``B`` is a grey closing (a max filter then a min filter, wider than
any robot) of an area-downsampled frame, which removes dark objects and keeps the smooth field.
The frame is read once, by a compiled block mean (:mod:`.background_kernels`); the closing and its
blur run on a grid coarser still, so a cold frame costs little more than that read (issue 8).

Only the downsampled estimate is stored. A full-resolution window of ``log B`` is interpolated when
a region of the image is examined, with the same bilinear mapping a full upsampling would use, so a
full-frame detection never writes a full-frame float image: it reads the 16-bit frame once (the
area downsampling) and then works on the coarse image and on windows around candidates. The coarse
attenuation (``closed - log`` of the downsampled frame) is kept too: it is where a full-frame
detection looks for candidates.
"""
from __future__ import annotations

import functools
from typing import Any

import cv2
import numpy as np

from appliance.recognition import background_kernels

#: Margin (px) by which an interpolated window is grown for the next ROIs to reuse.
_WINDOW_SLACK_PX = 24


class LogBackground:
    """``log B`` of one view: coarse arrays plus full-resolution windows on demand.

    Indexing with a pair of slices (``bg[rows, cols]``) returns that window at full resolution
    (float32), exactly like slicing the bilinearly upsampled image; ``np.asarray(bg)`` returns the
    whole upsampled image (computed once, for callers that want an array).
    """

    def __init__(self, coarse_log: np.ndarray, coarse_background: np.ndarray, shape: tuple[int, int],
                 coarse_attenuation: np.ndarray | None = None) -> None:
        #: log of the downsampled frame (dark level removed) and its closing: their difference is the
        #: coarse attenuation image.
        self.coarse_log = coarse_log
        self.coarse = coarse_background
        self.shape = (int(shape[0]), int(shape[1]))
        hs, ws = coarse_background.shape
        #: Full-resolution pixels per coarse pixel along y and x.
        self.fy = self.shape[0] / hs
        self.fx = self.shape[1] / ws
        self._full: np.ndarray | None = None
        #: (Given when it was computed with the background, else computed at first use.)
        self._coarse_attenuation: np.ndarray | None = coarse_attenuation
        # The last interpolated window, grown by _WINDOW_SLACK_PX: a tracked robot's ROI moves a few
        # pixels a frame, so most ROIs are slices of it.
        self._window: tuple[int, int, int, int, np.ndarray] | None = None

    @property
    def coarse_attenuation(self) -> np.ndarray:
        """``-log(I / B)`` on the coarse grid (float32; robot and vessels positive), computed once."""
        if self._coarse_attenuation is None:
            self._coarse_attenuation = self.coarse - self.coarse_log
        return self._coarse_attenuation

    @staticmethod
    def _taps(lo: int, hi: int, factor: float, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # The upsampling's mapping (OpenCV's INTER_LINEAR): a pixel centre x sits at (x + 0.5) / f - 0.5
        # on the coarse grid, clamped to its border.
        s = np.clip((np.arange(lo, hi, dtype=np.float64) + 0.5) / factor - 0.5, 0.0, n - 1)
        i0 = np.minimum(s.astype(np.int64), max(n - 2, 0))
        return i0, np.minimum(i0 + 1, n - 1), (s - i0).astype(np.float32)

    def __getitem__(self, key: tuple[slice, slice]) -> np.ndarray:
        rows, cols = key
        y0, y1, _ = rows.indices(self.shape[0])
        x0, x1, _ = cols.indices(self.shape[1])
        if self._full is not None:
            return self._full[y0:y1, x0:x1]
        cached = self._window
        if cached is None or not (cached[0] <= y0 and y1 <= cached[1] and cached[2] <= x0 and x1 <= cached[3]):
            g = _WINDOW_SLACK_PX
            wy0, wy1 = max(0, y0 - g), min(self.shape[0], y1 + g)
            wx0, wx1 = max(0, x0 - g), min(self.shape[1], x1 + g)
            cached = self._window = (wy0, wy1, wx0, wx1, self._interpolate(wy0, wy1, wx0, wx1))
        wy0, _, wx0, _, window = cached
        return window[y0 - wy0:y1 - wy0, x0 - wx0:x1 - wx0]

    def _interpolate(self, y0: int, y1: int, x0: int, x1: int) -> np.ndarray:
        hs, ws = self.coarse.shape
        iy0, iy1, wy = self._taps(y0, y1, self.fy, hs)
        ix0, ix1, wx = self._taps(x0, x1, self.fx, ws)
        lo, hi = int(ix0.min()), int(ix1.max()) + 1
        band = self.coarse[:, lo:hi]
        along_y = band[iy0] * (1.0 - wy)[:, None] + band[iy1] * wy[:, None]
        return along_y[:, ix0 - lo] * (1.0 - wx) + along_y[:, ix1 - lo] * wx

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        if self._full is None:
            self._full = cv2.resize(self.coarse, (self.shape[1], self.shape[0]), interpolation=cv2.INTER_LINEAR)
        return self._full if dtype is None else self._full.astype(dtype)


#: Gray-level -> ``log(max(level - dark, 1))`` tables by dark level (one per detector, a few at most).
_LOG_TABLES: dict[float, np.ndarray] = {}


def _log_table(dark_level: float) -> np.ndarray:
    """``log(max(level - dark_level, 1))`` for every 16-bit gray level (float32), built once per dark level."""
    table = _LOG_TABLES.get(dark_level)
    if table is None:
        if len(_LOG_TABLES) >= 8:
            _LOG_TABLES.clear()
        levels = np.arange(65536, dtype=np.float32)
        table = _LOG_TABLES[dark_level] = np.log(np.maximum(levels - np.float32(dark_level), 1.0))
    return table


def _downsample_log(image: np.ndarray, f: int, dark_level: float) -> tuple[np.ndarray, np.ndarray | None]:
    """log of the ``f x f`` area mean of ``image`` (dark level removed, floored at 1), float32; and its
    ``INTER_AREA`` halving (the closing's grid) where the compiled ``f = 4`` pass gives it (even sides),
    else None.

    The mean is rounded to a gray level as OpenCV's ``INTER_AREA`` downsampling of a 16-bit frame
    rounds it. A 16-bit frame whose sides are multiples of ``f`` (every detector we use) takes one
    compiled pass; anything else goes through OpenCV (fractional area weights).
    """
    h, w = image.shape[:2]
    hs, ws = max(1, h // f), max(1, w // f)
    # (OpenCV's 2x2 path rounds half up, unlike its general one: f = 2 is left to it.)
    if image.dtype == np.uint16 and image.ndim == 2 and h == hs * f and w == ws * f and f != 2:
        out = np.empty((hs, ws), dtype=np.float32)
        image = np.ascontiguousarray(image)
        if f == 4:
            half = np.empty((hs // 2, ws // 2) if hs % 2 == 0 and ws % 2 == 0 else (0, 0), dtype=np.float32)
            background_kernels.block_mean_log_4(image.view(np.uint64), _log_table(float(dark_level)), out, half)
            return out, half if half.size else None
        background_kernels.block_mean_log(image, f, _log_table(float(dark_level)), out)
        return out, None
    small = cv2.resize(image, (ws, hs), interpolation=cv2.INTER_AREA).astype(np.float32)
    return np.log(np.maximum(small - np.float32(dark_level), 1.0)), None


def log_background(image: np.ndarray, scale_px: int = 48, dark_level: float = 0.0) -> LogBackground:
    """``log(B)`` of the open-field background of ``image`` with dark objects removed.

    Downsampling by ``f`` averages ``f^2`` pixels (less noise, cheaper filters; done on the raw 16-bit
    frame in one pass, so no full-frame float copy is made): that grid is where :func:`detect` looks
    for candidates. The open field is smooth over far more than ``f`` pixels, so its closing at
    ``scale_px`` (which removes anything narrower) and the blur that smooths the closing's plateau
    steps run on a grid twice as coarse, a quarter of the pixels, and the result is interpolated back
    onto the detection grid.
    """
    h, w = image.shape[:2]
    f = max(1, min(8, scale_px // 12))
    logs, field = _downsample_log(image, f, dark_level)
    hs, ws = logs.shape
    hb, wb = max(1, hs // 2), max(1, ws // 2)
    if field is None:
        field = cv2.resize(logs, (wb, hb), interpolation=cv2.INTER_AREA)
    k = max(3, (scale_px // (2 * f)) | 1)
    if k == background_kernels.CLOSING_SIZE and field.dtype == np.float32:
        # (The scale every setting gives: the same values as OpenCV's, in half its time.)
        closed = np.empty_like(field)
        background_kernels.closing_7(np.ascontiguousarray(field), _row_half_widths(k), closed)
    else:
        closed = cv2.morphologyEx(field, cv2.MORPH_CLOSE, _ellipse(k), borderType=cv2.BORDER_REPLICATE)
    taps = _gaussian_taps(k / 3.0)
    if taps.size == background_kernels.BLUR_TAPS and hb >= 8 and wb % 8 == 0:
        # (OpenCV's blur, to the last bit, at a third of its cost; see gaussian_blur_21.)
        blurred = np.empty_like(closed)
        background_kernels.gaussian_blur_21(closed, taps, blurred)
        closed = blurred
    else:
        closed = cv2.GaussianBlur(closed, (0, 0), k / 3.0, borderType=cv2.BORDER_REPLICATE)
    if (hs, ws) == (2 * hb, 2 * wb):
        # Back onto the detection grid and the coarse attenuation in one compiled pass (a resize, a
        # subtraction and their temporaries otherwise).
        coarse = np.empty((hs, ws), dtype=np.float32)
        attenuation = np.empty_like(coarse)
        background_kernels.upsample_attenuation(np.ascontiguousarray(closed, dtype=np.float32), logs, coarse,
                                                attenuation)
        return LogBackground(logs, coarse, (h, w), attenuation)
    coarse = cv2.resize(closed, (ws, hs), interpolation=cv2.INTER_LINEAR)
    return LogBackground(logs, coarse, (h, w))


@functools.lru_cache(maxsize=8)
def _ellipse(k: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))


@functools.lru_cache(maxsize=8)
def _gaussian_taps(sigma: float) -> np.ndarray:
    """The float32 kernel ``cv2.GaussianBlur(..., (0, 0), sigma)`` uses on a float32 image: ``round(8 sigma + 1)``
    taps, made odd (OpenCV's size for float images), of ``cv2.getGaussianKernel``."""
    size = round(sigma * 8 + 1) | 1
    return cv2.getGaussianKernel(size, sigma, cv2.CV_32F).ravel().astype(np.float32)


@functools.lru_cache(maxsize=8)
def _row_half_widths(k: int) -> np.ndarray:
    """Half width of each row of :func:`_ellipse` (its rows are centred runs): the compiled closing's input."""
    counts = _ellipse(k).sum(axis=1).astype(np.int64)
    assert np.all(counts % 2 == 1), "the ellipse's rows are centred runs"
    return (counts - 1) // 2
