"""Synthetic biplane X-ray frames with ground truth: the simulated fluoroscope behind the loopback grabber.

Per detector pixel a ray leaves the X-ray source through the pixel (distorted pixel -> ideal ray);
closed-form chords through the robot (cylinder + cone), calibration beads (spheres) and contrast
vessels (mitred tubes) give path lengths, and Beer-Lambert gives the expected photon count
``I0(u,v) * exp(-sum mu_i L_i)``. ``I0`` carries the geometric cos^3 falloff, an anode heel gradient
along the image's x axis and a radial vignette, so no single gray threshold fits the whole image.
A robot inside a vessel's lumen pushes its contrast aside (its net attenuation there is
``mu_robot - mu_contrast``). Quantum noise is Poisson (a variance-matched Gaussian where counts are
high, exact Poisson below 30 photons), the detector's light spread is a Gaussian blur applied after
the noise (as in a scintillator), and the result is offset and scaled into 16 bits. The robot is
darker than its surroundings.

Speed: the static scene (field x vessels x beads) is rendered once per view; per frame only the
robot's projected bounding box is traced, at pixel centres, and only the pixels on its silhouette's
edge are supersampled (``supersample``^2 rays) for anti-aliasing. Unit normal noise comes from
windows at random offsets into a bank drawn once (``fresh_noise`` draws anew each frame). Noise,
blur and 16-bit conversion are full-frame numpy/OpenCV passes. ``benchmarks/render_speed.py``
measures it.

Not modelled: scatter, beam hardening, detector lag, pixel defects, image-intensifier S-distortion
(only OpenCV's radial-tangential model), focal-spot penumbra (fold it into ``blur_sigma_px``), a
robot's inner structure (a polymer-bodied robot is one homogeneous effective attenuation), and a
robot half in, half out of a lumen (its centroid decides).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Callable, Sequence

import cv2
import numpy as np

from drivers.loopback.xray_scene import (  # noqa: F401  (re-exported: the renderer's public types)
    MAX_CONE_FRACTION,
    RobotBody,
    RobotPose,
    TrueView,
    VesselPhantom,
    biplane_views,
    robot_chords,
    robot_chords_from_dots,
    sphere_chords,
    tube_segment_chords,
    vessel_chords,
)

log = logging.getLogger(__name__)

# Below this many expected photons the Gaussian approximation of Poisson noise is visibly skewed.
_POISSON_EXACT_BELOW = 30.0
_ROWS_PER_CHUNK = 128
_NOISE_BANK_FRAMES = 8
_BBOX_PAD_PX = 2

Bbox = tuple[int, int, int, int]  # x0, y0, x1, y1 (exclusive)


@dataclass(frozen=True)
class ImagingSettings:
    """Exposure and detector model. Defaults resemble a pulsed fluoroscopy frame on a flat panel:
    2000 detected photons per pixel in the open field (2.2 % quantum noise before the blur).

    ``field_nonuniformity``: heel gradient of +-f/2 across the width times a radial vignette down to
    1 - f/2 at the corners. ``full_scale_fraction``: the brightest flat-field pixel maps to this
    fraction of the range above ``dark_level``.
    """

    photons_per_pixel: float = 2000.0
    field_nonuniformity: float = 0.3
    blur_sigma_px: float = 0.7
    noise: bool = True
    supersample: int = 4
    dark_level: int = 1000
    max_value: int = 65535
    full_scale_fraction: float = 0.8
    fresh_noise: bool = False        # draw new normals every frame instead of windows of a bank

    def __post_init__(self) -> None:
        if not (self.photons_per_pixel > 0 and 0 <= self.field_nonuniformity < 1
                and self.blur_sigma_px >= 0 and self.supersample >= 1
                and 0 <= self.dark_level < self.max_value <= 65535
                and 0 < self.full_scale_fraction <= 1):
            raise ValueError(f"inconsistent imaging settings: {self}")

    @classmethod
    def exact(cls, supersample: int = 4) -> "ImagingSettings":
        """No noise, no blur, uniform field (geometric falloff only): for exact tests."""
        return cls(noise=False, blur_sigma_px=0.0, field_nonuniformity=0.0, supersample=supersample)


@dataclass(frozen=True)
class ViewTruth:
    """Ground truth of the robot in one view (pixels, OpenCV convention)."""

    centroid_px: np.ndarray          # perspective projection of the 3D volume centroid
    head_px: np.ndarray              # projection of the cone's apex
    tail_px: np.ndarray              # projection of the tail face's centre
    pixel_count: int                 # pixels more than half covered by the robot's shadow
    bbox: Bbox                       # of every pixel the shadow touches; (0, 0, 0, 0) if none
    in_view: bool = True             # some of the shadow falls on the detector
    fully_in_view: bool = True       # none of the shadow falls off the detector
    area_px: float = 0.0             # the shadow's area on the detector, in pixels (sum of coverage)
    # (bbox h, bbox w): the fraction of each pixel the shadow covers
    coverage: np.ndarray | None = field(default=None, repr=False)


@dataclass(frozen=True)
class RenderedPair:
    """One biplane exposure: 16-bit images and the truth they were rendered from."""

    images: dict[str, np.ndarray]    # "p", "q": uint16 (h, w)
    truth: dict[str, ViewTruth]      # empty when rendered without a robot
    pose: RobotPose | None
    head_mm: np.ndarray | None
    tail_mm: np.ndarray | None


# A traced object's chord function: ideal normalized camera coordinates (x, y arrays) to the path
# length (mm) through the object along those rays.
_Tracer = Callable[[np.ndarray, np.ndarray], np.ndarray]


class _ViewState:
    """Per-view precomputation: ray maps, flat field and the static background."""

    def __init__(self, view: TrueView) -> None:
        self.view = view
        self.w, self.h = view.image_size
        self.K_inv = np.linalg.inv(view.K)
        self.source = view.source_mm
        self.maps: tuple[np.ndarray, np.ndarray] | None = None
        if view.has_distortion:
            u, v = np.meshgrid(np.arange(self.w, dtype=float), np.arange(self.h, dtype=float))
            xy = view.undistort_normalized(np.stack([u.ravel(), v.ravel()], axis=1))
            self.maps = (xy[:, 0].reshape(self.h, self.w), xy[:, 1].reshape(self.h, self.w))
        self.bg_counts = np.zeros((self.h, self.w), np.float32)   # expected photons, no robot
        self.bg_min = 0.0
        self.bg_dn = self.bg_counts                               # the same in gray levels
        self.bg_sd_dn = self.bg_counts                            # its quantum noise, gray levels

    def normalized_block(self, x0: int, y0: int, x1: int, y1: int) -> tuple[np.ndarray, np.ndarray]:
        """Ideal normalized coordinates of the pixel centres of a block (broadcastable arrays)."""
        if self.maps is not None:
            return self.maps[0][y0:y1, x0:x1], self.maps[1][y0:y1, x0:x1]
        u = np.arange(x0, x1, dtype=float)[None, :]
        v = np.arange(y0, y1, dtype=float)[:, None]
        ki = self.K_inv
        return ki[0, 0] * u + (ki[0, 1] * v + ki[0, 2]), ki[1, 1] * v + ki[1, 2] + 0.0 * u

    def normalized_points(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.maps is not None:
            xy = self.view.undistort_normalized(np.stack([u.ravel(), v.ravel()], axis=1))
            return xy[:, 0].reshape(u.shape), xy[:, 1].reshape(u.shape)
        ki = self.K_inv
        return ki[0, 0] * u + ki[0, 1] * v + ki[0, 2], ki[1, 1] * v + ki[1, 2]

    def world_dirs(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        x, y = np.broadcast_arrays(x, y)
        cam = np.stack([x, y, np.ones_like(x)], axis=-1)
        cam /= np.linalg.norm(cam, axis=-1, keepdims=True)
        return cam @ self.view.R

    def bbox_of(self, points_mm: np.ndarray) -> tuple[Bbox | None, bool]:
        """Pixel bbox (clipped) of the projection of a convex set's bounding points, and whether
        clipping removed anything. None if nothing is on the detector or a point is behind the source."""
        px = self.view.project(points_mm)
        if not np.all(np.isfinite(px)):
            return None, False
        lo = np.floor(px.min(axis=0)).astype(int) - _BBOX_PAD_PX
        hi = np.ceil(px.max(axis=0)).astype(int) + _BBOX_PAD_PX + 1
        x0, y0 = max(lo[0], 0), max(lo[1], 0)
        x1, y1 = min(hi[0], self.w), min(hi[1], self.h)
        clipped = (x0, y0, x1, y1) != (lo[0], lo[1], hi[0], hi[1])
        if x1 <= x0 or y1 <= y0:
            return None, True
        return (int(x0), int(y0), int(x1), int(y1)), clipped


def _box_corners(points: np.ndarray, margin: float) -> np.ndarray:
    """The 8 corners of the axis-aligned box around ``points`` grown by ``margin``."""
    lo, hi = points.min(axis=0) - margin, points.max(axis=0) + margin
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def _edge_of(mask: np.ndarray) -> np.ndarray:
    """Pixels within one pixel of the mask's boundary (inside or outside)."""
    m = mask.astype(np.uint8)
    kernel = np.ones((3, 3), np.uint8)
    return (cv2.dilate(m, kernel) > 0) & ~(cv2.erode(m, kernel, borderType=cv2.BORDER_REPLICATE) > 0)


def _trace(state: _ViewState, objects: list[tuple[Bbox, _Tracer, float]], region: Bbox,
           supersample: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean transmission and shadow coverage of ``region``'s pixels through ``objects``, each a
    (bbox, chord function, attenuation per mm).

    Pixel centres first; pixels on an object's silhouette edge are then re-traced with
    ``supersample``^2 sub-pixel rays and their transmission averaged (exp of the sum per ray, so
    overlapping objects combine correctly)."""
    rx0, ry0, rx1, ry1 = region
    acc = np.zeros((ry1 - ry0, rx1 - rx0))
    covered = np.zeros(acc.shape, bool)
    edge = np.zeros(acc.shape, bool)
    for (x0, y0, x1, y1), chords, mu in objects:
        x0, y0, x1, y1 = max(x0, rx0), max(y0, ry0), min(x1, rx1), min(y1, ry1)
        if x1 <= x0 or y1 <= y0:
            continue
        lengths = np.empty((y1 - y0, x1 - x0))
        for r0 in range(y0, y1, _ROWS_PER_CHUNK):
            r1 = min(r0 + _ROWS_PER_CHUNK, y1)
            lengths[r0 - y0:r1 - y0] = chords(*state.normalized_block(x0, r0, x1, r1))
        block = np.s_[y0 - ry0:y1 - ry0, x0 - rx0:x1 - rx0]
        acc[block] += mu * lengths
        hit = lengths > 0
        covered[block] |= hit
        edge[block] |= _edge_of(hit)
    transmission = np.exp(-acc)
    coverage = covered.astype(float)
    if supersample > 1 and edge.any():
        rows, cols = np.nonzero(edge)
        offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
        du, dv = np.meshgrid(offsets, offsets)
        u = (cols + rx0)[:, None] + du.ravel()[None, :]
        v = (rows + ry0)[:, None] + dv.ravel()[None, :]
        x, y = state.normalized_points(u, v)
        sub = np.zeros(u.shape)
        sub_hit = np.zeros(u.shape, bool)
        for (x0, y0, x1, y1), chords, mu in objects:
            inside = (u[:, 0] >= x0 - 1) & (u[:, 0] < x1 + 1) & (v[:, 0] >= y0 - 1) & (v[:, 0] < y1 + 1)
            if inside.any():
                lengths = chords(x[inside], y[inside])
                sub[inside] += mu * lengths
                sub_hit[inside] |= lengths > 0
        transmission[rows, cols] = np.exp(-sub).mean(axis=1)
        coverage[rows, cols] = sub_hit.mean(axis=1)
    return transmission, coverage


class BiplaneRenderer:
    """Renders biplane exposures of a robot (optionally in a vessel phantom, with beads).

    ``body`` None renders phantoms only. ``seed`` fixes the noise sequence: the same seed and the
    same sequence of ``render`` calls give identical images. Not thread-safe (one noise generator):
    render from one thread, or give each thread its own renderer.
    """

    def __init__(self, views: dict[str, TrueView], body: RobotBody | None, *,
                 vessel: VesselPhantom | Sequence[VesselPhantom] | None = None,
                 beads: tuple[np.ndarray, float, float] | None = None,
                 settings: ImagingSettings = ImagingSettings(), seed: int | None = None) -> None:
        if not views:
            raise ValueError("need at least one view")
        self.views = dict(views)
        self.body = body
        if vessel is None:
            self.vessels: tuple[VesselPhantom, ...] = ()
        elif isinstance(vessel, VesselPhantom):
            self.vessels = (vessel,)
        else:
            self.vessels = tuple(vessel)
        self.vessel = self.vessels[0] if self.vessels else None
        self.settings = settings
        self._rng = np.random.default_rng(seed)
        self._beads = None
        if beads is not None:
            centres, radius, mu = beads
            centres = np.asarray(centres, dtype=float).reshape(-1, 3)
            if radius <= 0 or mu < 0 or not np.all(np.isfinite(centres)):
                raise ValueError("beads need finite centres, radius > 0 and attenuation >= 0")
            self._beads = (centres, float(radius), float(mu))
        self._states = {name: _ViewState(view) for name, view in self.views.items()}
        flat_max = 0.0
        for state in self._states.values():
            flat = self._flat_field(state)
            state.bg_counts = (flat * self._static_transmission(state)).astype(np.float32)
            state.bg_min = float(state.bg_counts.min())
            flat_max = max(flat_max, float(flat.max()))
        s = settings
        # One gain for both planes so their gray levels are comparable, as with one generator.
        self.gain = s.full_scale_fraction * (s.max_value - s.dark_level) / flat_max
        for state in self._states.values():
            state.bg_dn = (s.dark_level + 0.5 + self.gain * state.bg_counts).astype(np.float32)
            state.bg_sd_dn = (self.gain * np.sqrt(state.bg_counts)).astype(np.float32)
        self._bank: np.ndarray | None = None
        if s.noise and not s.fresh_noise:
            pixels = max(state.h * state.w for state in self._states.values())
            self._bank = self._rng.standard_normal(_NOISE_BANK_FRAMES * pixels, dtype=np.float32)
            self._bank.setflags(write=False)

    # ------------------------------------------------------------------------------ static
    def _flat_field(self, state: _ViewState) -> np.ndarray:
        """Expected photons per pixel without any object."""
        s = self.settings
        x, y = state.normalized_block(0, 0, state.w, state.h)
        x, y = np.broadcast_arrays(x, y)
        cos3 = (1.0 + x * x + y * y) ** -1.5        # inverse square x obliquity on a flat detector
        u = np.arange(state.w, dtype=float)[None, :]
        v = np.arange(state.h, dtype=float)[:, None]
        cx, cy = (state.w - 1) / 2.0, (state.h - 1) / 2.0
        heel = 1.0 + 0.5 * s.field_nonuniformity * (u - cx) / cx
        rho2 = ((u - cx) ** 2 + (v - cy) ** 2) / (cx * cx + cy * cy)
        vignette = 1.0 - 0.5 * s.field_nonuniformity * rho2
        return s.photons_per_pixel * cos3 * heel * vignette

    def _static_transmission(self, state: _ViewState) -> np.ndarray:
        objects: list[tuple[Bbox, _Tracer, float]] = []
        for vessel in self.vessels:
            mu, radius = vessel.attenuation_per_mm, vessel.radius_mm
            for start, end, n_start, n_end in vessel.segments():
                # A mitre plane tilted by half the bend reaches radius / cos(half bend) from the
                # joint's centre.
                axis = (end - start) / np.linalg.norm(end - start)
                reach = radius / max(min(float(n_start @ axis), float(n_end @ axis)), 0.1)
                bbox, _ = state.bbox_of(_box_corners(np.vstack([start, end]), reach))
                if bbox is None:
                    continue
                objects.append((bbox, _segment_tracer(state, start, end, n_start, n_end, radius), mu))
        if self._beads is not None:
            centres, radius, mu = self._beads
            for centre in centres:
                bbox, _ = state.bbox_of(_box_corners(centre[None, :], radius))
                if bbox is not None:
                    objects.append((bbox, _sphere_tracer(state, centre, radius), mu))
        if not objects:
            return np.ones((state.h, state.w))
        log.debug("view %s: tracing %d static objects", state.view.name, len(objects))
        transmission, _ = _trace(state, objects, (0, 0, state.w, state.h), self.settings.supersample)
        return transmission

    # ------------------------------------------------------------------------------ per frame
    def render(self, pose: RobotPose | None) -> RenderedPair:
        """One exposure of every view. ``pose`` None: no robot in the scene."""
        if pose is not None and self.body is None:
            raise ValueError("this renderer has no robot body; render(None) for phantoms only")
        images: dict[str, np.ndarray] = {}
        truth: dict[str, ViewTruth] = {}
        for name, state in self._states.items():
            patch = None
            if pose is not None:
                truth[name], patch = self._robot_in_view(state, pose)
            images[name] = self._expose(state, patch)
        head = tail = None
        if pose is not None and self.body is not None:
            head, tail = pose.head_mm(self.body), pose.tail_mm(self.body)
        return RenderedPair(images=images, truth=truth, pose=pose, head_mm=head, tail_mm=tail)

    def _robot_in_view(self, state: _ViewState, pose: RobotPose
                       ) -> tuple[ViewTruth, tuple[Bbox, np.ndarray] | None]:
        body = self.body
        assert body is not None
        view = state.view
        head, tail = pose.head_mm(body), pose.tail_mm(body)
        marks = view.project(np.vstack([pose.centroid_mm, head, tail]))
        bbox, clipped = state.bbox_of(_box_corners(np.vstack([head, tail]), body.radius_mm))
        transmission = coverage = None
        if bbox is not None:
            mu = body.attenuation_per_mm - self._displaced_mu(pose)
            transmission, coverage = _trace(state, [(bbox, _robot_tracer(state, body, pose), mu)],
                                            bbox, self.settings.supersample)
        if coverage is None or not coverage.any():
            none = ViewTruth(centroid_px=marks[0], head_px=marks[1], tail_px=marks[2], pixel_count=0,
                             bbox=(0, 0, 0, 0), in_view=False, fully_in_view=False)
            return none, None
        rows, cols = np.nonzero(coverage > 0)
        x0, y0 = bbox[0], bbox[1]
        shadow_bbox = (x0 + int(cols.min()), y0 + int(rows.min()),
                       x0 + int(cols.max()) + 1, y0 + int(rows.max()) + 1)
        # The shadow touches the image border only if clipping cut it.
        touches = (shadow_bbox[0] == 0 or shadow_bbox[1] == 0 or shadow_bbox[2] == state.w
                   or shadow_bbox[3] == state.h)
        crop = coverage[rows.min():rows.max() + 1, cols.min():cols.max() + 1].astype(np.float32)
        crop.setflags(write=False)
        truth = ViewTruth(centroid_px=marks[0], head_px=marks[1], tail_px=marks[2],
                          pixel_count=_half_covered(coverage, bbox), bbox=shadow_bbox,
                          in_view=True, fully_in_view=not (clipped and touches),
                          area_px=float(coverage.sum()), coverage=crop)
        return truth, (bbox, transmission.astype(np.float32))

    def _displaced_mu(self, pose: RobotPose) -> float:
        """Attenuation of the contrast the robot pushes aside: the vessels whose lumen holds its
        centroid (the body is taken as wholly inside that lumen)."""
        return sum(v.attenuation_per_mm for v in self.vessels
                   if v.distance_mm(pose.centroid_mm[None, :])[0] <= v.radius_mm)

    def _expose(self, state: _ViewState, patch: tuple[Bbox, np.ndarray] | None) -> np.ndarray:
        """Expected counts (static background times the robot's transmission patch) -> noisy,
        blurred 16-bit image. Works in gray levels: the offset and gain are linear, so they commute
        with the blur, and the background's mean and noise scale are precomputed in gray levels."""
        s = self.settings
        offset = np.float32(s.dark_level + 0.5)    # + 0.5: round to nearest on the final cast
        gain = np.float32(self.gain)
        block = counts = None
        if patch is not None:
            (x0, y0, x1, y1), transmission = patch
            block = np.s_[y0:y1, x0:x1]
            counts = state.bg_counts[block] * transmission
        if not s.noise:
            image = state.bg_dn.copy()
            if block is not None:
                image[block] = offset + gain * counts
        elif state.bg_min < _POISSON_EXACT_BELOW:
            image = self._exact_poisson(state, block, counts) * gain + offset   # very low dose
        else:
            z = self._unit_normals(state.h, state.w)
            image = z * state.bg_sd_dn
            image += state.bg_dn
            if block is not None:
                noisy = counts + np.sqrt(counts) * z[block]
                # Behind a dense magnet only a few photons arrive: draw those exactly.
                low = counts < _POISSON_EXACT_BELOW
                if low.any():
                    noisy[low] = self._rng.poisson(counts[low])
                image[block] = offset + gain * noisy
        if s.blur_sigma_px > 0:
            image = cv2.GaussianBlur(image, (0, 0), s.blur_sigma_px, borderType=cv2.BORDER_REFLECT)
        np.clip(image, 0, s.max_value, out=image)
        return image.astype(np.uint16)

    def _unit_normals(self, h: int, w: int) -> np.ndarray:
        """Standard normal noise for one frame: a window at a random offset into a pre-drawn bank
        (or fresh draws with ``fresh_noise``). Drawing ~0.5 M normals costs several ms; a window
        costs nothing. A window's pixels are independent; two frames share samples only shifted
        by their offsets' difference, so no pixel repeats its own noise."""
        if self._bank is None:
            return self._rng.standard_normal((h, w), dtype=np.float32)
        start = int(self._rng.integers(0, self._bank.size - h * w + 1))
        return self._bank[start:start + h * w].reshape(h, w)

    def _exact_poisson(self, state: _ViewState, block: tuple[slice, slice] | None,
                       counts: np.ndarray | None) -> np.ndarray:
        """Photon counts with Poisson noise drawn exactly where the mean is low (slow path)."""
        lam = state.bg_counts.copy()
        if block is not None:
            lam[block] = counts
        noisy = lam + np.sqrt(lam) * self._rng.standard_normal(lam.shape, dtype=np.float32)
        low = lam < _POISSON_EXACT_BELOW
        noisy[low] = self._rng.poisson(lam[low]).astype(np.float32)
        return noisy

    # ------------------------------------------------------------------------------ helpers
    def to_photons(self, image: np.ndarray) -> np.ndarray:
        """Invert the detector's offset and gain: gray levels -> photons per pixel (float)."""
        return (image.astype(float) - self.settings.dark_level) / self.gain

    def expected_photons(self, name: str) -> np.ndarray:
        """The noise-free static background (field x vessel x beads) of one view, in photons."""
        return self._states[name].bg_counts.astype(float)


def _half_covered(coverage: np.ndarray, bbox: Bbox) -> int:
    """Pixels more than half covered; pixels covered exactly half (a tie of the sub-pixel samples)
    count every other one, on a checkerboard, so the count does not drift above the area."""
    rows, cols = np.nonzero(coverage == 0.5)
    ties = int(np.count_nonzero((rows + cols + bbox[0] + bbox[1]) % 2 == 0))
    return int(np.count_nonzero(coverage > 0.5)) + ties


def _dot(x: np.ndarray, y: np.ndarray, inv_n: np.ndarray, vec_cam: np.ndarray) -> np.ndarray:
    """World ray direction (through normalized (x, y)) dotted with a vector given in camera axes."""
    return (x * vec_cam[0] + y * vec_cam[1] + vec_cam[2]) * inv_n


def _robot_tracer(state: _ViewState, body: RobotBody, pose: RobotPose) -> _Tracer:
    u = pose.direction
    o = state.source - pose.tail_mm(body)
    opar = float(o @ u)
    operp = o - opar * u
    operp2 = float(operp @ operp)
    ru, ro = state.view.R @ u, state.view.R @ operp     # camera-axis forms: two dots per ray

    def tracer(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        inv_n = 1.0 / np.sqrt(x * x + y * y + 1.0)
        return robot_chords_from_dots(body, opar, operp2, _dot(x, y, inv_n, ru), _dot(x, y, inv_n, ro))
    return tracer


def _sphere_tracer(state: _ViewState, centre: np.ndarray, radius: float) -> _Tracer:
    def tracer(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return sphere_chords(centre, radius, state.source, state.world_dirs(x, y))
    return tracer


def _segment_tracer(state: _ViewState, start: np.ndarray, end: np.ndarray, n_start: np.ndarray,
                    n_end: np.ndarray, radius: float) -> _Tracer:
    def tracer(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return tube_segment_chords(start, end, n_start, n_end, radius, state.source,
                                   state.world_dirs(x, y))
    return tracer

