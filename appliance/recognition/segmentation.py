"""Segmentation of the robot in one X-ray view, in attenuation space.

The detector records ``I = I0(u, v) exp(-integral of mu)``: the open field ``I0`` is not uniform (heel
effect, vignetting) and quantum noise grows where fewer photons arrive. So the image is turned into
attenuation ``A = -log(I / B)`` against a background estimate ``B`` (:mod:`.background`: a grey closing
of a downsampled frame). It is computed once per full-frame detection and then only windowed, so a
tracked frame costs a handful of vectorised operations on the region of interest (ROI), never a
full-frame pass; a full-frame detection (:func:`detect`) finds candidates on the coarse image and
examines only windows around them at full resolution.

Thresholds are relative: candidates stand out of the noise (``detect_sigma`` robust standard
deviations), the robot's core is the part above ``core_fraction`` of its own peak (which excludes the
weaker contrast-filled vessel around it), and the local baseline under the robot (vessel, residual field)
is the median attenuation of a ring around the core. The robot's weights are the attenuation above that
baseline on a support slightly wider than the visible body, so blurred rims and the faint cone tip count.
"""
from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np

from appliance.recognition.background import LogBackground, log_background  # noqa: F401  (re-exported)
from appliance.recognition.settings import RecognitionSettings

log = logging.getLogger(__name__)

#: Noise reduction of the 5x5, sigma=1 Gaussian used for candidate detection (sqrt of the kernel's sum of squares).
_SMOOTH_NOISE_GAIN = 0.29
MAX_CANDIDATES = 8
#: Rows beyond the body and neighbouring columns averaged for the background fill across the body.
_FILL_ROWS = 3
_FILL_COLS = 7
#: Slices (px) over which a body's attenuation must fall beyond its core's end.
_FADE_STEP = 4


@dataclass(frozen=True)
class Roi:
    """A rectangle of the image, ``x0 <= x < x1``, ``y0 <= y < y1`` (pixels)."""

    x0: int
    y0: int
    x1: int
    y1: int

    @classmethod
    def full(cls, shape: tuple[int, ...]) -> Roi:
        return cls(0, 0, int(shape[1]), int(shape[0]))

    @classmethod
    def around(cls, points_px: np.ndarray, margin_px: float, shape: tuple[int, ...]) -> Roi | None:
        """The bounding box of ``points_px`` (N,2) grown by ``margin_px`` and clipped; None if nothing is left."""
        points = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
        if not np.all(np.isfinite(points)):
            return None
        h, w = int(shape[0]), int(shape[1])
        x0 = max(0, int(np.floor(points[:, 0].min() - margin_px)))
        y0 = max(0, int(np.floor(points[:, 1].min() - margin_px)))
        x1 = min(w, int(np.ceil(points[:, 0].max() + margin_px)) + 1)
        y1 = min(h, int(np.ceil(points[:, 1].max() + margin_px)) + 1)
        if x1 - x0 < 4 or y1 - y0 < 4:
            return None
        return cls(x0, y0, x1, y1)

    @property
    def slices(self) -> tuple[slice, slice]:
        return slice(self.y0, self.y1), slice(self.x0, self.x1)

    @property
    def shape(self) -> tuple[int, int]:
        return self.y1 - self.y0, self.x1 - self.x0


@dataclass(frozen=True)
class Blob:
    """One candidate robot image: its weights and binary cloud on a window of the image."""

    window: Roi  # where ``weights`` and ``mask`` sit in the image
    weights: np.ndarray  # float32 attenuation above the local baseline on the support, 0 elsewhere
    mask: np.ndarray  # bool: the segmented pixels (the binary point cloud of the paper's estimator)
    pixel_count: int  # pixels in ``mask``
    peak: float  # peak smoothed attenuation above the baseline
    baseline: float  # local attenuation under the robot (vessel, residual field), from the ring
    sigma: float  # robust noise standard deviation of the attenuation image
    strength: float  # integrated weight: the robot's "mass" in attenuation units x pixels
    centroid_px: tuple[float, float]  # weighted centroid in image pixels (for candidate pairing)
    touches_border: bool  # the support reaches the edge of the searched region: the robot may be cut
    width_px: float = 0.0  # the body's diameter from its weighted spread across the axis (4 sqrt(l2))
    #: How much the interpolated background under the body varies, as a fraction of the body's peak:
    #: near 0 on a clean background, large where the robot overlaps a vessel or another object.
    clutter: float = 0.0


def attenuation(image: np.ndarray, log_bg: np.ndarray | LogBackground, region: Roi,
                dark_level: float = 0.0) -> np.ndarray:
    """``-log(I / B)`` (float32) on ``region``; slices only, no full-frame copy.

    ``I`` is the gray level minus the detector's dark level (its output with no X-rays): attenuation
    is a ratio of photon counts, and an offset left in would compress the robot's thick parts. Gray
    levels at or below the dark level (no photon through a dense part) count as 1.
    """
    sl = region.slices
    raw = image[sl].astype(np.float32)
    if dark_level:
        raw -= np.float32(dark_level)
    np.maximum(raw, 1.0, out=raw)
    return log_bg[sl] - np.log(raw)


def _median(values: np.ndarray) -> float:
    """``np.median`` of a 1-D array, same value and dtype arithmetic, without its generic-axis overhead
    (~50 us a call, several calls per view and frame)."""
    n = values.size
    k = n // 2
    if n % 2:
        return float(np.partition(values, k)[k])
    part = np.partition(values, (k - 1, k))
    return float((part[k - 1] + part[k]) / 2)


def noise_sigma(a: np.ndarray) -> float:
    """Robust standard deviation of pixel noise from neighbour differences (edges are too few to matter)."""
    d = np.abs(np.diff(a, axis=1))
    if d.size == 0:
        return float("nan")
    return float(1.4826 * _median(d.ravel()) / np.sqrt(2.0))


@functools.lru_cache(maxsize=32)
def _disk(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def _grow(mask: np.ndarray, radius: int) -> np.ndarray:
    if radius <= 0:
        return mask
    return cv2.dilate(mask.view(np.uint8), _disk(radius)).view(bool)


def _pad_edge(v: np.ndarray, half: int) -> np.ndarray:
    """``np.pad(v, half, mode="edge")`` for 1-D ``v``, without np.pad's generality (~40 us a call)."""
    return np.concatenate([np.full(half, v[0], dtype=v.dtype), v, np.full(half, v[-1], dtype=v.dtype)])


def _fill_across(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``values`` with each column's masked run replaced by the straight line between the pixels above
    and below it (the caller transposes for rows). Each column's masked pixels must be one run that
    does not touch the array's edge."""
    h = mask.shape[0]
    cols = np.flatnonzero(mask.any(axis=0))
    sub = mask[:, cols]
    top = np.argmax(sub, axis=0) - 1
    bottom = h - np.argmax(sub[::-1], axis=0)
    # Average a few rows beyond each end and a few neighbouring columns: the fill's noise would
    # otherwise add a random tilt to every column of the robot.
    v_top = sum(values[np.maximum(top - k, 0), cols] for k in range(_FILL_ROWS)) / _FILL_ROWS
    v_bottom = sum(values[np.minimum(bottom + k, h - 1), cols] for k in range(_FILL_ROWS)) / _FILL_ROWS
    if len(cols) >= _FILL_COLS:
        kernel = np.ones(_FILL_COLS, dtype=np.float32) / _FILL_COLS
        half = _FILL_COLS // 2
        v_top = np.convolve(_pad_edge(v_top, half), kernel, mode="valid")
        v_bottom = np.convolve(_pad_edge(v_bottom, half), kernel, mode="valid")
    rows = np.arange(h, dtype=np.float32)[:, None]
    fill = v_top + (v_bottom - v_top) * ((rows - top) / (bottom - top).astype(np.float32))
    out = values.copy()
    out[:, cols] = np.where(sub, fill, values[:, cols])
    return out


def core_of(values: np.ndarray, comp: np.ndarray, peak: float, fraction: float) -> np.ndarray:
    """The component's strong part that is connected to its peak."""
    core = comp & (values >= fraction * peak)
    n, labels = cv2.connectedComponents(core.view(np.uint8), connectivity=8)
    if n > 2:
        iy, ix = np.unravel_index(int(np.argmax(np.where(core, values, -np.inf))), core.shape)
        core = labels == labels[iy, ix]
    return core


def _blob_from_component(a: np.ndarray, smooth: np.ndarray, labels: np.ndarray, label: int,
                         stats: np.ndarray, region: Roi, sigma: float, settings: RecognitionSettings) -> Blob | None:
    """Refine one detected component into a robot candidate, or None if it is not plausible.

    The robot's core (strong part) gives a provisional axis; the body's full extent is the part above
    the local baseline connected to the core, limited to a capsule along that axis so a vessel it
    crosses cannot leak in. The background under the body is then interpolated across the axis, from
    the pixels just outside either long side of a rectangle around the body: exact for a vessel
    crossing the robot, and only slightly low for a vessel the robot lies in.
    """
    sigma_s = sigma * _SMOOTH_NOISE_GAIN
    x, y, bw, bh = (int(v) for v in stats[label, :4])
    comp = labels[y:y + bh, x:x + bw] == label
    values = smooth[y:y + bh, x:x + bw]
    peak = float(values[comp].max())
    if peak < settings.min_peak_attenuation:
        return None
    core = core_of(values, comp, peak, settings.core_fraction)
    ys, xs = np.nonzero(core)
    if len(xs) < settings.min_pixels:
        return None
    extent = int(max(xs.max() - xs.min(), ys.max() - ys.min())) + 1
    if extent > settings.max_extent_px:
        return None
    xs_f, ys_f = xs.astype(np.float64), ys.astype(np.float64)
    cx, cy = xs_f.mean(), ys_f.mean()
    dx, dy = xs_f - cx, ys_f - cy
    l1, l2, axis = _principal(float(dx @ dx), float(dy @ dy), float(dx @ dy), len(xs))
    if np.sqrt(l1 / max(l2, 1e-3)) > settings.max_elongation:
        return None
    s_core = dx * axis[0] + dy * axis[1]
    t_core = np.abs(-dx * axis[1] + dy * axis[0])
    core_len = float(s_core.max() - s_core.min())
    reach = settings.cone_reach * core_len + 3.0  # how far beyond the core a faint cone tip may go
    pad = settings.support_dilate_px + 1.0
    half_width = float(t_core.max()) + pad + 2.0
    grow = int(np.ceil(reach + half_width + pad + _FILL_ROWS + 2))
    H, W = a.shape
    wx0, wy0 = max(0, x + int(xs.min()) - grow), max(0, y + int(ys.min()) - grow)
    wx1, wy1 = min(W, x + int(xs.max()) + grow + 1), min(H, y + int(ys.max()) + grow + 1)
    a_w, s_w = a[wy0:wy1, wx0:wx1], smooth[wy0:wy1, wx0:wx1]
    gx = np.arange(wx0, wx1, dtype=np.float64)[None, :] - (x + cx)
    gy = np.arange(wy0, wy1, dtype=np.float64)[:, None] - (y + cy)
    s_w_ = gx * axis[0] + gy * axis[1]
    t_w_ = -gx * axis[1] + gy * axis[0]
    core_w = np.zeros(a_w.shape, dtype=bool)
    core_w[ys + y - wy0, xs + x - wx0] = True
    capsule = ((np.abs(t_w_) <= half_width) & (s_w_ >= s_core.min() - reach) & (s_w_ <= s_core.max() + reach))
    # The local baseline: the median of a ring around the core (vessel, residual field).
    gap = settings.support_dilate_px + 1
    ring = _grow(core_w, gap + settings.ring_px) & ~_grow(core_w, gap)
    baseline = _median(s_w[ring]) if ring.any() else 0.0
    height = peak - baseline
    if height < settings.min_peak_attenuation:
        return None
    level = max(settings.support_sigma * sigma_s, settings.support_fraction * height)
    above = ((s_w - baseline) > level) & capsule
    n, sup_labels = cv2.connectedComponents(above.view(np.uint8), connectivity=8)
    keep = np.unique(sup_labels[core_w & above])
    # Labels touching the core, by table look-up (np.isin sorts; a table of n labels is one gather).
    touching = np.zeros(n, dtype=bool)
    touching[keep[keep > 0]] = True
    mask = touching[sup_labels] | core_w
    mask &= _end_limits(s_w, mask, s_w_, float(s_core.min()), float(s_core.max()), 3.0 * sigma_s * np.sqrt(2.0))
    # The support: a rectangle around the body (convex, so each column/row crosses it once).
    s_in, t_in = s_w_[mask], np.abs(t_w_[mask])
    support = ((s_w_ >= s_in.min() - pad) & (s_w_ <= s_in.max() + pad) & (np.abs(t_w_) <= t_in.max() + pad))
    m_ = _FILL_ROWS
    edge = bool(support[:m_].any() or support[-m_:].any() or support[:, :m_].any() or support[:, -m_:].any())
    if edge:
        # The rectangle reaches the window's edge: only possible where the window was clipped by the
        # searched region, i.e. the robot may be cut; shrink it to keep the interpolation inside.
        support[:m_] = support[-m_:] = False
        support[:, :m_] = support[:, -m_:] = False
    if abs(axis[0]) >= abs(axis[1]):
        background = _fill_across(s_w, support)
    else:
        background = _fill_across(s_w.T, support.T).T
    # Weigh only near the body: every background pixel adds noise to the moments, more so far out.
    near = _grow(mask, settings.support_dilate_px) & support
    weights = np.where(near, a_w - background, 0.0).astype(np.float32)
    m = cv2.moments(weights)
    if m["m00"] <= 0:
        return None
    window = Roi(region.x0 + wx0, region.y0 + wy0, region.x0 + wx1, region.y0 + wy1)
    # A cylinder's chord profile 2 sqrt(r^2 - t^2) has variance r^2 / 4 across its axis.
    _, minor, _ = _principal(m["mu20"], m["mu02"], m["mu11"], 1)
    return Blob(window=window, weights=weights, mask=mask, pixel_count=int(mask.sum()), peak=height,
                baseline=baseline, sigma=sigma, strength=float(m["m00"]),
                centroid_px=(window.x0 + m["m10"] / m["m00"], window.y0 + m["m01"] / m["m00"]),
                touches_border=edge, width_px=4.0 * float(np.sqrt(max(minor / m["m00"], 0.0625))),
                clutter=float(np.ptp(background[near])) / height if near.any() else 0.0)


def _end_limits(smooth: np.ndarray, mask: np.ndarray, s: np.ndarray, s_lo: float, s_hi: float,
                tolerance: float) -> np.ndarray:
    """Where the body may extend beyond its core along the axis (bool, like ``mask``).

    Beyond each end of the core the body can only fade: a cone's attenuation falls steadily to its
    apex, a flat end's within the blur. Walking outward in 1-px slices, the body ends where the
    slice's strongest pixel stops falling (over ``_FADE_STEP`` slices, by more than ``tolerance``):
    what continues at a steady level is something else, such as a vessel the robot touches.
    """
    keep = np.ones(mask.shape, dtype=bool)
    values, positions = smooth[mask], s[mask]
    # ...nor can it get wider than it is along its core (a cone narrows, a vessel need not).
    inside = (positions >= s_lo) & (positions <= s_hi)
    core_width = np.bincount(np.floor(positions[inside] - s_lo).astype(np.int64)) if inside.any() else np.zeros(1)
    max_width = 1.2 * _median(core_width) + 2.0
    for sign, start in ((1.0, s_hi), (-1.0, s_lo)):
        beyond = sign * (positions - start)
        outside = beyond > 0
        if not outside.any():
            continue
        bins = np.floor(beyond[outside]).astype(np.int64)
        peak = np.full(int(bins.max()) + 1, -np.inf)
        np.maximum.at(peak, bins, values[outside])
        width = np.bincount(bins, minlength=len(peak))
        stop = len(peak)
        peaks, widths = peak.tolist(), width.tolist()  # Python floats: this loop is scalar work
        for b in range(len(peaks)):
            if (not math.isfinite(peaks[b]) or widths[b] > max_width
                    or (b >= _FADE_STEP and peaks[b] > peaks[b - _FADE_STEP] - tolerance)):
                stop = b
                break
        keep &= sign * (s - start) < stop
    return keep


def _principal(sxx: float, syy: float, sxy: float, n: int) -> tuple[float, float, np.ndarray]:
    """Eigenvalues and major unit axis of a pixel cloud's scatter (sums of centred products over n)."""
    # Closed form in scalars: a LAPACK call costs more than the arithmetic for a 2x2.
    k = 1.0 / max(n, 1)
    a, c, b = float(sxx) * k, float(syy) * k, float(sxy) * k
    root = math.hypot(a - c, 2.0 * b)
    l1, l2 = 0.5 * (a + c + root), 0.5 * (a + c - root)
    # Of the two equivalent forms of the eigenvector, the one without cancellation.
    vx, vy = (l1 - c, b) if a >= c else (b, l1 - a)
    norm = math.hypot(vx, vy)
    if norm < 1e-300:  # isotropic: any direction is principal
        return l1, l2, np.array([1.0, 0.0])
    return l1, l2, np.array([vx / norm, vy / norm])


def segment(image: np.ndarray, log_bg: np.ndarray | LogBackground, roi: Roi | None = None,
            settings: RecognitionSettings | None = None) -> list[Blob]:
    """Robot candidates in ``roi`` (whole image if None), strongest first; empty if none is plausible.

    ``log_bg`` is :func:`log_background` of a recent frame of the same view (or a full-frame float32
    ``log B``). With ``roi`` None every pixel is examined; :func:`detect` finds the same candidates
    from the coarse image without that full-resolution pass.
    """
    settings = settings or RecognitionSettings()
    region = roi or Roi.full(image.shape)
    a = attenuation(image, log_bg, region, settings.dark_level)
    sigma = noise_sigma(a)
    if not np.isfinite(sigma) or sigma <= 0:
        sigma = 1e-3
    smooth = cv2.GaussianBlur(a, (5, 5), 1.0, borderType=cv2.BORDER_REPLICATE)
    threshold = max(settings.detect_sigma * sigma * _SMOOTH_NOISE_GAIN,
                    settings.core_fraction * settings.min_peak_attenuation)
    detected = (smooth > threshold).view(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(detected, connectivity=8)
    order = np.argsort(-stats[1:, cv2.CC_STAT_AREA])[:MAX_CANDIDATES * 3] + 1
    blobs = []
    for label in order:
        if stats[label, cv2.CC_STAT_AREA] < settings.min_pixels:
            break
        blob = _blob_from_component(a, smooth, labels, int(label), stats, region, sigma, settings)
        if blob is not None:
            blobs.append(blob)
    blobs.sort(key=lambda b: -b.strength)
    return blobs[:MAX_CANDIDATES]
