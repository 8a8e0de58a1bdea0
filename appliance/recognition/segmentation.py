"""Segmentation of the robot in one X-ray view, in attenuation space.

The detector records ``I = I0(u, v) exp(-integral of mu)``: the open field ``I0`` is not uniform (heel
effect, vignetting) and quantum noise grows where fewer photons arrive. So the image is turned into
attenuation ``A = -log(I / B)`` against a background estimate ``B`` (:mod:`.background`: a grey closing
of a downsampled frame). It is computed once per full-frame detection and then only windowed, so a
tracked frame works on the region of interest (ROI) only, never a full-frame pass; a full-frame
detection (:func:`detect`) finds candidates on the coarse image and examines only windows around them
at full resolution, with this same :func:`segment`.

A ROI holds a few thousand pixels and the step has a budget of microseconds (issue 8), so its
arithmetic runs as compiled kernels (:mod:`.view_kernels`, a few calls per view); this module keeps
the public API (:class:`Roi`, :class:`Blob`) and says what each step means.

Thresholds are relative: candidates stand out of the noise (``detect_sigma`` robust standard
deviations), the robot's core is the part above ``core_fraction`` of its own peak (which excludes the
weaker contrast-filled vessel around it), and the body is what stands above the attenuation beside it
(vessel, residual field), slice by slice along its axis. The robot's weights are the attenuation above
the background interpolated under it, on a support slightly wider than the visible body, so blurred
rims and the faint cone tip count.
"""
from __future__ import annotations

import functools
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from appliance.recognition import view_kernels
from appliance.recognition.background import LogBackground, log_background  # noqa: F401  (re-exported)
from appliance.recognition.settings import RecognitionSettings

log = logging.getLogger(__name__)

#: Noise reduction of the 5x5, sigma=1 Gaussian used for candidate detection (sqrt of the kernel's sum of squares).
_SMOOTH_NOISE_GAIN = 0.29
MAX_CANDIDATES = 8
#: Rows beyond the body and neighbouring columns averaged for the background fill across the body
#: (the columns only along image columns or rows, see ``RecognitionSettings.background_along_structure``).
_FILL_ROWS = 3
_FILL_COLS = 7
#: Slices (px) over which a body's attenuation must fall beyond its core's end.
_FADE_STEP = 4
#: How much more background (smoothed-noise sigmas, on average under the body) oblique lines must find
#: at both of their ends than lines across the axis before the background is interpolated along them
#: (:func:`.view_kernels.background_shear`).
_DIRECTION_MARGIN = 3.0


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
        """The bounding box of ``points_px`` (N,2) grown by ``margin_px`` and clipped; None if nothing is left.

        Plain floats (``tolist`` and ``math``): the tracker calls this twice per frame on three points,
        where numpy's per-call overhead (~15-30 us) would be most of the work.
        """
        coords = np.asarray(points_px, dtype=np.float64).ravel().tolist()
        if not coords or len(coords) % 2:
            raise ValueError(f"expected (N, 2) points, got {len(coords)} coordinates")
        return cls.around_coordinates(coords[0::2], coords[1::2], margin_px, shape)

    @classmethod
    def around_coordinates(cls, xs: Sequence[float], ys: Sequence[float], margin_px: float,
                           shape: tuple[int, ...]) -> Roi | None:
        """:meth:`around` on points given as their x and y coordinates (plain floats, not empty): what the
        tracker has in hand, without building an array for three points."""
        if not (all(map(math.isfinite, xs)) and all(map(math.isfinite, ys))):
            return None
        h, w = int(shape[0]), int(shape[1])
        x0 = max(0, math.floor(min(xs) - margin_px))
        y0 = max(0, math.floor(min(ys) - margin_px))
        x1 = min(w, math.ceil(max(xs) + margin_px) + 1)
        y1 = min(h, math.ceil(max(ys) + margin_px) + 1)
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
    #: How much the interpolated background under the body varies, as a fraction of the body's peak
    #: (with ``background_along_structure``, also the attenuation read beside the body and beyond its
    #: flat ends): near 0 on a clean background, large where the robot overlaps a vessel or another object.
    clutter: float = 0.0


def the_one_clean_view(blobs: dict[str, Blob], max_clutter: float) -> str | None:
    """The name of the view whose blob is clear of other structures (``clutter`` not above ``max_clutter``)
    where the other view's blob is over one; None where both or neither are (or the views are not two)."""
    clean = [name for name, blob in blobs.items() if not blob.clutter > max_clutter]
    return clean[0] if len(blobs) == 2 and len(clean) == 1 else None


def _log_table(dark_level: float) -> np.ndarray:
    """``log(max(g - dark_level, 1))`` (float32) for every 16-bit gray level ``g``: the attenuation's
    per-pixel log as one table look-up (the same float32 values the elementwise numpy log gives)."""
    table = _LOG_TABLES.get(dark_level)
    if table is None:
        levels = np.arange(65536, dtype=np.float32) - np.float32(dark_level)
        table = _LOG_TABLES[dark_level] = np.log(np.maximum(levels, np.float32(1.0)))
    return table


_LOG_TABLES: dict[float, np.ndarray] = {}


def attenuation(image: np.ndarray, log_bg: np.ndarray | LogBackground, region: Roi,
                dark_level: float = 0.0) -> np.ndarray:
    """``-log(I / B)`` (float32) on ``region``; no full-frame pass.

    ``I`` is the gray level minus the detector's dark level (its output with no X-rays): attenuation
    is a ratio of photon counts, and an offset left in would compress the robot's thick parts. Gray
    levels at or below the dark level (no photon through a dense part) count as 1. With a
    :class:`LogBackground`, ``log B`` is interpolated from its coarse grid inside the kernel (the
    bilinear upsampling's values, never materialised).
    """
    if image.dtype in (np.uint16, np.uint8) and region.x1 > region.x0 and region.y1 > region.y0:
        table = _log_table(float(dark_level))
        if isinstance(log_bg, LogBackground):
            return view_kernels.attenuation_from_coarse(image, region.y0, region.y1, region.x0, region.x1,
                                                        log_bg.coarse, log_bg.fy, log_bg.fx, table)
        sl = region.slices
        return view_kernels.attenuation_from_dense(image[sl], log_bg[sl], table)
    sl = region.slices
    raw = image[sl].astype(np.float32)
    if dark_level:
        raw -= np.float32(dark_level)
    np.maximum(raw, 1.0, out=raw)
    return np.asarray(log_bg[sl], dtype=np.float32) - np.log(raw)


def noise_sigma(a: np.ndarray) -> float:
    """Robust standard deviation of pixel noise from neighbour differences (edges are too few to matter):
    ``1.4826 median(|a[:, x+1] - a[:, x]|) / sqrt(2)``; NaN for an image narrower than 2 px."""
    a = np.asarray(a)
    if a.ndim != 2 or a.dtype not in (np.float32, np.float64):
        a = np.atleast_2d(a).astype(np.float64)
    return float(view_kernels.noise_sigma_of(a))


@functools.lru_cache(maxsize=32)
def _disk(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


@functools.lru_cache(maxsize=32)
def _disk_spans(radius: int) -> np.ndarray:
    """Half-width of each row of :func:`_disk` (its rows are centred runs): the dilation kernel's input."""
    disk = _disk(max(radius, 0))
    counts = disk.sum(axis=1).astype(np.int64)
    assert np.all(counts % 2 == 1), "the ellipse's rows are centred runs"
    return (counts - 1) // 2


def core_of(values: np.ndarray, comp: np.ndarray, peak: float, fraction: float) -> np.ndarray:
    """The component's strong part that is connected to its peak."""
    core = comp & (values >= fraction * peak)
    n, labels = cv2.connectedComponents(core.view(np.uint8), connectivity=8)
    if n > 2:
        iy, ix = np.unravel_index(int(np.argmax(np.where(core, values, -np.inf))), core.shape)
        core = labels == labels[iy, ix]
    return core


def _refine_parameters(settings: RecognitionSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The settings as the refinement kernel takes them (cached per settings object: they are frozen)."""
    cached = _PARAMETERS.get(id(settings))
    if cached is not None and cached[0] is settings:
        return cached[1]
    params = np.array([settings.min_peak_attenuation, settings.core_fraction, settings.min_pixels,
                       settings.max_extent_px, settings.max_elongation, settings.cone_reach,
                       settings.support_dilate_px, settings.support_sigma, settings.support_fraction,
                       _SMOOTH_NOISE_GAIN, _FILL_ROWS, _FILL_COLS, _FADE_STEP,
                       1.0 if settings.background_along_structure else 0.0, _DIRECTION_MARGIN], dtype=np.float64)
    gap = settings.support_dilate_px + 1
    value = (params, _disk_spans(gap + settings.ring_px), _disk_spans(gap), _disk_spans(settings.support_dilate_px))
    if len(_PARAMETERS) > 16:
        _PARAMETERS.clear()
    _PARAMETERS[id(settings)] = (settings, value)
    return value


_PARAMETERS: dict[int, tuple[RecognitionSettings, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]] = {}


def body_width_px(minor_moment: float, strength: float) -> float:
    """The body's diameter (px) from its weights' central moment across the axis: a cylinder's chord profile
    ``2 sqrt(r^2 - t^2)`` has variance ``r^2 / 4`` across its axis, so ``D = 4 sqrt(mu / W)`` (at least 1 px)."""
    return 4.0 * math.sqrt(max(minor_moment / strength, 0.0625))


def _blob_from_component(a: np.ndarray, smooth: np.ndarray, labels: np.ndarray, label: int,
                         box: list[int], region: Roi, sigma: float, settings: RecognitionSettings) -> Blob | None:
    """Refine one detected component into a robot candidate, or None if it is not plausible.

    The robot's core (strong part connected to the peak) gives a provisional axis; the body's full
    extent is the part above the attenuation beside it, slice by slice along that axis (a vessel
    crossing or running along the robot raises that baseline only where it is), connected to the
    core, limited to a capsule along the axis so a vessel it crosses cannot leak in, and cut where,
    beyond either end of the core, its contrast stops fading or it gets wider than along the core
    (what continues at a steady level is something else, such as a vessel the robot touches). The
    median of a ring around the core is the blob's single ``baseline`` (its ``peak`` is above it). The
    background under the body is then interpolated across it, along image columns or rows, from the
    pixels just outside a rectangle around the body: exact for a vessel crossing the robot at right
    angles, a wedge smeared along the body for one crossing it obliquely, and low for a vessel the robot
    lies in. With ``settings.background_along_structure`` it is interpolated along lines across a strip
    around the body instead, from the pixels just outside its two long sides: across the axis, or
    along a vessel that crosses the body obliquely (where lines that way find more attenuation at both
    of their ends, and the sides match along them): exact for a straight vessel crossing the robot at
    any angle, still low for one the robot lies in (the sides see its edges only) or one that ends
    under it; the blob's ``clutter`` then also counts what the strip's sides and the body's flat ends
    see, so such frames are flagged. The weights are the attenuation above that background near the
    body. The arithmetic is :func:`.view_kernels.refine`.
    """
    params, ring_outer, ring_inner, near = _refine_parameters(settings)
    x, y, bw, bh = box
    status, weights, mask, sc = view_kernels.refine(a, smooth, labels, label, x, y, bw, bh, sigma, params,
                                                    ring_outer, ring_inner, near)
    if not status:
        return None
    wy0, wy1, wx0, wx1, height, baseline, strength, cx, cy, edge, minor, clutter, count = sc.tolist()
    window = Roi(region.x0 + int(wx0), region.y0 + int(wy0), region.x0 + int(wx1), region.y0 + int(wy1))
    return Blob(window=window, weights=weights, mask=mask.view(bool), pixel_count=int(count), peak=height,
                baseline=baseline, sigma=sigma, strength=strength, centroid_px=(window.x0 + cx, window.y0 + cy),
                touches_border=bool(edge), width_px=body_width_px(minor, strength), clutter=clutter)


def _other_body(a: np.ndarray, smooth: np.ndarray, labels: np.ndarray, label: int, box: list[int], region: Roi,
                sigma: float, settings: RecognitionSettings, first: Blob) -> Blob | None:
    """A second body in a component that already gave ``first``, or None.

    The refinement grows a blob from its component's peak. Where the robot touches something as
    strong as itself, the component's peak can be the other thing's: a vessel that curves towards the
    source is dark where it is seen end on, and where the robot's end lies on that spot the two
    stack. The blob refined from there is the vessel's end (wider than any robot, over clutter), and
    the robot beside it, never a candidate of its own, cannot be found. So the component is refined
    once more without ``first``'s pixels (grown by the support's dilation, which also removes the
    faint rim around a body): whatever strong part is left is grown from its own peak, by the same
    rules, and the candidates' ranking and the pairing across views choose between the two. Only a
    blob over another structure (clutter above ``settings.max_clutter``, as that vessel end's is) gets
    the second look: off structures, the parts it finds beside a clean body (its own faint cone, a
    vessel it touches) only add candidates for the pairing to get wrong (dev seed 2: two good frames of
    robots 2 and 6 lost or paired 16.8 mm off).
    """
    x, y, bw, bh = box
    # first's mask in the component's box (both in region pixels), grown by the support's dilation.
    ox, oy = first.window.x0 - region.x0 - x, first.window.y0 - region.y0 - y
    mh, mw = first.mask.shape
    cx0, cy0, cx1, cy1 = max(ox, 0), max(oy, 0), min(ox + mw, bw), min(oy + mh, bh)
    if cx0 >= cx1 or cy0 >= cy1:
        return None
    taken = np.zeros((bh, bw), dtype=np.uint8)
    taken[cy0:cy1, cx0:cx1] = first.mask[cy0 - oy:cy1 - oy, cx0 - ox:cx1 - ox]
    grow = 2 * settings.support_dilate_px + 1
    taken = cv2.dilate(taken, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (grow, grow))).view(bool)
    box_labels = labels[y:y + bh, x:x + bw]
    rest = (box_labels == label) & ~taken
    if not rest.any() or float(smooth[y:y + bh, x:x + bw][rest].max()) < settings.min_peak_attenuation:
        return None
    removed = (box_labels == label) & taken
    box_labels[removed] = 0
    try:
        return _blob_from_component(a, smooth, labels, label, box, region, sigma, settings)
    finally:
        box_labels[removed] = label


def segment(image: np.ndarray, log_bg: np.ndarray | LogBackground, roi: Roi | None = None,
            settings: RecognitionSettings | None = None, *, sigma: float | None = None,
            region_attenuation: np.ndarray | None = None, touching_bodies: bool = False) -> list[Blob]:
    """Robot candidates in ``roi`` (whole image if None), strongest first; empty if none is plausible.

    ``log_bg`` is :func:`log_background` of a recent frame of the same view (or a full-frame float32
    ``log B``). With ``roi`` None every pixel is examined; :func:`detect` finds the same candidates
    from the coarse image without that full-resolution pass.

    ``sigma`` is the attenuation image's noise standard deviation if already known (None: measured
    on the region, :func:`noise_sigma`, ~15 us). The tracker passes the one a recent frame of the same
    view measured: the detector and the dose, hence the noise, do not change from frame to frame.
    ``region_attenuation`` is :func:`attenuation` of the region if the caller has it already (a
    full-frame detection takes it with the window's noise in one compiled call). With
    ``touching_bodies`` a component that gave a blob over another structure is refined once more without
    it (:func:`_other_body`: a robot touching something stronger); the full-frame detection asks for that,
    the tracked ROI's search does not (it is compiled as one call, and a robot it misses that way is found
    by the detection).
    """
    settings = settings or RecognitionSettings()
    region = roi or Roi.full(image.shape)
    a = (attenuation(image, log_bg, region, settings.dark_level) if region_attenuation is None
         else region_attenuation)
    # Noise sigma, the 5x5 sigma=1 Gaussian, components above the threshold, largest first.
    known = float(sigma) if sigma is not None and math.isfinite(sigma) and sigma > 0 else 0.0
    sigma, smooth, labels, stats, order = view_kernels.candidates(
        a, view_kernels.GAUSSIAN_5, settings.detect_sigma, _SMOOTH_NOISE_GAIN,
        settings.core_fraction * settings.min_peak_attenuation, known)
    blobs = []
    for label in order[:MAX_CANDIDATES * 3].tolist():
        x, y, bw, bh, area = stats[label].tolist()
        if area < settings.min_pixels:
            break
        blob = _blob_from_component(a, smooth, labels, label, [x, y, bw, bh], region, sigma, settings)
        if blob is not None:
            blobs.append(blob)
            other = (_other_body(a, smooth, labels, label, [x, y, bw, bh], region, sigma, settings, blob)
                     if touching_bodies and blob.clutter > settings.max_clutter else None)
            if other is not None:
                blobs.append(other)
    blobs.sort(key=lambda b: -b.strength)
    return blobs[:MAX_CANDIDATES]
