"""The robot's known body placed on the reconstructed axis: one axial position gives the centroid and both tips.

The appliance always knows which robot it tracks (``robot: {id: N}``, :class:`appliance.robots.RobotSpec`):
its length ``L`` and where its volume centroid lies from the tail face (``centroid_from_tail_mm``, not
``L / 2`` for a coned body). With the 3D axis reconstructed (accurate to a few hundredths of a degree on
the accuracy benchmark) and the head identified, the centroid and both tips follow from ONE number, the
body's position along that axis: ``tail = c - centroid_from_tail u``, ``head = tail + L u``.

That number is measured several ways, each with its own uncertainty (:func:`axial_evidence`):

* the moment centroid (the reconstruction's 3D centroid): the best single measurement on a clean frame,
  but over another structure the background interpolated under the body slopes along it and the whole
  axial profile, and with it the centroid, slides along the axis;
* each view's tail and head, their rays meeting the 3D axis, less the body's offset from that end to
  the centroid. A flat tail is a blurred step located at its half height (as sharp as the centroid);
  a cone's apex is extrapolated from its faint ramp (much less sharp: robot 6's polymer apex is the
  worst feature of all). An end is affected only by what lies near it (:func:`end_clutter`), so where
  a vessel crosses one end or the middle of the body, the other end still places the body.

The estimates are combined by inverse variance (:func:`place_body`): independent measurements of one
number, each Gaussian to first order, so that is their maximum-likelihood mean and the sigmas
decide, not a fixed rule per case. The apexes join only where they agree with the centroid and tails
(their errors have heavy tails). Where the centroid and the tails disagree by more than a clean frame's
noise, one of them ran on into a vessel, lost part of the body to it or slid with the background under
it, and the place along the axis is in doubt: the frame is flagged ambiguous with the estimate at odds,
never hidden. (The measured length says the same only where the apex is not the end that is off; where
the measured tips are kept, a length off the body's flags the frame.)

Where the head is not identified the tips' order is unknown, and so is the side of the centroid the
body's offset lies on: the measured ends then choose between the two placements only where one fits
decisively better (the head is still not claimed); otherwise the frame keeps its measured centroid and
tips. (Both ends measured as flat, the apex's half-height crossing falls short of it by about the
body's offset asymmetry, so such frames mostly stay undecided.)

Applied to the :class:`.Posture` (both the tracker's general path and the steady state's plain frames
build one, to the last bit the same), so both paths stay identical. The posture's ``length_mm`` stays
the measured length (the track's plausibility check compares it frame to frame) and its
``reprojection_px`` that of the measured centroid and ends.
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import cv2
import numpy as np

from appliance.geometry import Calibration
from appliance.geometry_kernels import _K, _SRC, VIEW_SIZE
from appliance.recognition.posture import Posture, ViewObservation
from appliance.recognition.reconstruction_kernels import _ray_line_b
from appliance.recognition.segmentation import Blob, LogBackground, Roi, attenuation
from appliance.recognition.settings import RecognitionSettings


@dataclass(frozen=True)
class BodyModel:
    """What the body prior needs of the robot (from :class:`appliance.robots.RobotSpec`)."""

    length_mm: float
    centroid_from_tail_mm: float
    cone_length_mm: float
    diameter_mm: float

    @classmethod
    def of(cls, spec: object) -> BodyModel:
        """The model of a catalogue robot (anything with RobotSpec's four attributes)."""
        return cls(float(spec.length_mm), float(spec.centroid_from_tail_mm),  # type: ignore[attr-defined]
                   float(spec.cone_length_mm), float(spec.diameter_mm))  # type: ignore[attr-defined]


# ------------------------------------------------------------------------------------- per-end clutter
#: Pixels beyond the body's edge and the end that the end's neighbourhood reaches: the support's pad
#: (``support_dilate_px + 1``) plus the rows the background under the body is interpolated from.
_END_REACH_PX = 7
#: Pixels around the body's outline left out of the end's neighbourhood (its blurred rim).
_RIM_PX = 3


def end_clutter(image: np.ndarray, log_bg: LogBackground | np.ndarray, blob: Blob, centroid_px: np.ndarray,
                tips_px: np.ndarray, settings: RecognitionSettings) -> tuple[float, float]:
    """Per end (the order of ``tips_px``), how much structure the attenuation around it shows, as a
    fraction of the body's peak: the 5-95 % range of the 3 x 3-averaged attenuation beside and beyond
    the end, off the body, less what the noise alone spreads it by.

    :attr:`.Blob.clutter` says the background under the body varies somewhere; where a vessel crosses
    the body's middle or one end, only the ends it reaches have their axial profile's edge moved by
    the background interpolated under it. The neighbourhood is what that interpolation reads near the
    end: out to the support's rim and the rows beyond it (``_END_REACH_PX``), along the body from
    ``width`` before the end to beyond it.
    """
    half = 0.5 * blob.width_px
    reach = half + _END_REACH_PX
    (cu, cv) = (float(centroid_px[0]), float(centroid_px[1]))
    out = []
    h, w = image.shape
    for tip in np.asarray(tips_px, dtype=np.float64):
        tu, tv = float(tip[0]), float(tip[1])
        au, av = tu - cu, tv - cv
        norm = math.hypot(au, av)
        if not norm > 0:
            out.append(math.inf)
            continue
        au, av = au / norm, av / norm
        x0, x1 = max(0, math.floor(tu - reach - 1)), min(w, math.ceil(tu + reach + 2))
        y0, y1 = max(0, math.floor(tv - reach - 1)), min(h, math.ceil(tv + reach + 2))
        if x1 - x0 < 4 or y1 - y0 < 4:
            out.append(math.inf)
            continue
        a = attenuation(image, log_bg, Roi(x0, y0, x1, y1), settings.dark_level)
        # 3 x 3 box mean: the structure, not the pixel noise (which it divides by 3).
        a = cv2.blur(a, (3, 3))[1:-1, 1:-1]
        ys, xs = np.mgrid[y0 + 1:y1 - 1, x0 + 1:x1 - 1]
        gs = (xs - tu) * au + (ys - tv) * av           # outward along the axis from the tip
        gt = np.abs(-(xs - tu) * av + (ys - tv) * au)   # across it
        near = (~_body_pixels(blob, x0 + 1, y0 + 1, x1 - 1, y1 - 1)) & (gs >= -(2.0 * half + _END_REACH_PX)) \
            & (gs <= reach) & (gt <= reach)
        values = a[near]
        if values.size < 16:
            out.append(math.inf)
            continue
        lo, hi = np.percentile(values, (5.0, 95.0))
        noise = 3.29 * blob.sigma / 3.0
        out.append(max(float(hi - lo) - noise, 0.0) / max(blob.peak, 1e-6))
    return out[0], out[1]


def _body_pixels(blob: Blob, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
    """Which pixels of the image rectangle ``x0:x1, y0:y1`` are the body's weighted support (its
    weights' non-zero pixels, which reach ``support_dilate_px`` beyond the segmented body) grown by
    ``_RIM_PX``: the body and its blurred rim, left out of an end's neighbourhood."""
    grow = _RIM_PX
    inside = np.zeros((y1 - y0 + 2 * grow, x1 - x0 + 2 * grow), dtype=np.uint8)
    win = blob.window
    wy0, wx0 = win.y0 - (y0 - grow), win.x0 - (x0 - grow)
    h, w = blob.weights.shape
    sy0, sx0 = max(wy0, 0), max(wx0, 0)
    sy1, sx1 = min(wy0 + h, inside.shape[0]), min(wx0 + w, inside.shape[1])
    if sy1 > sy0 and sx1 > sx0:
        inside[sy0:sy1, sx0:sx1] = blob.weights[sy0 - wy0:sy1 - wy0, sx0 - wx0:sx1 - wx0] != 0
    size = 2 * grow + 1
    grown = cv2.dilate(inside, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size)))
    return grown[grow:grow + (y1 - y0), grow:grow + (x1 - x0)].astype(bool)


# ------------------------------------------------------------------------------------------- evidence
#: Noise (px along the image axis, on a clean view seen side-on) of the moment centroid and of a flat
#: end's half-height crossing, and of a cone's apex (plus this fraction of the cone's image length: its
#: ramp is extrapolated to the apex). Measured on the accuracy benchmark's clean frames (dev seeds 1-12,
#: robots 1-7): tails 0.1-0.3 px RMS, apexes 0.4-1.2 px with heavy tails, 3D centroids 0.02-0.05 mm.
CENTROID_SIGMA_PX = 0.2
FLAT_END_SIGMA_PX = 0.2
APEX_SIGMA_PX = 0.3
APEX_SIGMA_PER_CONE_PX = 0.01
#: An end face seen obliquely blurs its crossing by the rim: this fraction of the body's image width
#: times cos^6 of the ray-axis angle (negligible until the view is nearly end-on; measured: tails
#: 0.15-0.3 px RMS below cos 0.85, 0.4-1.8 px above).
RIM_FRACTION = 0.1
RIM_POWER = 6
#: Over another structure, a sigma grows by this much per (clutter / max_clutter)^2: the centroid by its
#: frame's worst view, an end by its own view's clutter, and (views over another structure) by this
#: much per end_clutter / max_clutter more. On the dev seeds a cluttered view's tail was 0.2-0.4 mm off
#: where the end's neighbourhood looked clean (the interpolated background slopes along the body), so
#: the view's clutter counts for its ends too.
CENTROID_CLUTTER_GAIN = 4.0
VIEW_CLUTTER_GAIN = 4.0
END_CLUTTER_GAIN = 4.0
#: An apex estimate joins only if it lies within this many sigmas of the centroid's and tails' mean: the
#: apex's errors have heavy tails (a faint cone lost to noise or run on into a vessel: 1-3 mm).
APEX_GATE_SIGMAS = 3.0
#: Where the body is placed, the centroid and the tails are inconsistent beyond this many sigmas (per degree
#: of freedom, chi-square) of a clean frame's noise (the sigmas without the clutter terms; with them, a
#: frame just under ``max_clutter`` whose moment centroid slid 0.8 mm passed as clean: dev seed 14, robot
#: 6). On the dev seeds' frames not flagged otherwise it flagged 3 of 611, 2 of them > 0.15 mm off. The
#: measured length is no such sign there: an apex off alone (flagged by it in 1 of 30 frames of robots 1
#: and 5) is not used, and the frame is placed well.
CORE_SIGMAS = 4.0
#: Where the measured tips are kept (head not identified, order undecided), their length is implausible
#: beyond this many sigmas of a clean frame's noise: an end is off (the apex measured as a flat end falls
#: short by ~0.7 of the cone).
LENGTH_SIGMAS = 4.0
#: The ends' order is taken from the body's offset where one order fits the ends better by this much
#: (chi-square), with the head not identified.
ORDER_CHI2 = 25.0


@dataclass(frozen=True)
class AxialEstimate:
    """One measurement of the body centroid's position along the axis (mm from the posture's centroid)."""

    what: str          # "centroid", or "<view> head" / "<view> tail"
    b_mm: float        # the body centroid's position it implies
    sigma_mm: float
    #: What the sigma would be on a clean frame (no clutter terms): the yardstick for the consistency checks.
    clean_sigma_mm: float


def _view_rays(G: np.ndarray, view: int, obs: ViewObservation, c: np.ndarray, u: np.ndarray
               ) -> tuple[list[tuple[float, float]], float]:
    """For the view's (0: p, 1: q) centroid and both tips, ``(b, sine)``: the parameter of the point of
    ``c + b u`` nearest the pixel's ray and the ray-axis sine (the reconstruction's compiled
    ``_ray_line_b``: a steady-state frame pays ~1 us a ray, not numpy's ~10); and the view's mm per px at ``c``."""
    o = view * VIEW_SIZE
    (cu, cv), ((u0, v0), (u1, v1)) = obs.centroid_px.tolist(), obs.tips_px.tolist()
    out = []
    for pu, pv in ((cu, cv), (u0, v0), (u1, v1)):
        b, sin2 = _ray_line_b(G, o, pu, pv, c, u)
        out.append((b, math.sqrt(sin2)))
    w0, w1, w2 = (G[o + _SRC:o + _SRC + 3] - c).tolist()
    return out, math.sqrt(w0 * w0 + w1 * w1 + w2 * w2) / float(G[o + _K])


def _end_sigma_mm(head: bool, body: BodyModel, mm_per_px: float, sine: float, inflation: float) -> float:
    """One view's end: its crossing's noise (px), the rim's, along the 3D axis (/ sine), inflated."""
    cosine = math.sqrt(max(1.0 - sine * sine, 0.0))
    rim = RIM_FRACTION * (body.diameter_mm / mm_per_px) * cosine ** RIM_POWER
    base = (APEX_SIGMA_PX + APEX_SIGMA_PER_CONE_PX * body.cone_length_mm / mm_per_px if head and body.cone_length_mm > 0
            else FLAT_END_SIGMA_PX)
    return (base + rim) * mm_per_px / max(sine, 1e-3) * inflation


def axial_evidence(calibration: Calibration, posture: Posture, body: BodyModel, settings: RecognitionSettings,
                   clutter: dict[str, float], ends: dict[str, tuple[float, float]], head_end: int = 0,
                   axis_sigma_rad: float = 0.0) -> tuple[list[AxialEstimate], list[AxialEstimate], dict[str, float]]:
    """The measurements of the body's axial position in this posture: ``(core, apexes, end sigmas)``.

    ``core`` holds the moment centroid and each view's tail (a flat end's crossing is as sharp as the
    centroid), ``apexes`` each view's head (gated by :func:`place_body`); ``head_end`` is which of the
    posture's tips (0 or 1) is taken for the head. The end sigmas (3D, ``"head"``, ``"tail"``) are those of
    the ends as a clean frame would measure them (no clutter term), for the length's noise. ``clutter``: per view, :attr:`.Blob.clutter`; ``ends``:
    per view over another structure, :func:`end_clutter` of its tips in the posture's order;
    ``axis_sigma_rad``: the 3D axis' standard deviation, which blurs where the ends' rays meet it.

    A tail is used only where the body's cylinder is at least as long as it is wide: a shorter one
    (robot 4: 0.6 mm of cylinder, 1.5 mm wide) never shows the plateau its half height is taken from,
    and its crossing is biased (dev seeds: 0.2 mm towards the tail).
    """
    assert posture.centroid_mm is not None and posture.direction is not None
    c, u = posture.centroid_mm, posture.direction
    G = calibration.packed
    core: list[AxialEstimate] = []
    apexes: list[AxialEstimate] = []
    to_head = body.length_mm - body.centroid_from_tail_mm
    sign = 1.0 if head_end == 0 else -1.0   # +1: the posture's direction points from the tail to the head
    flat_tail = body.length_mm - body.cone_length_mm >= body.diameter_mm
    weights = {"head": 0.0, "tail": 0.0}
    sin2_sum, mm_sum, views = 0.0, 0.0, 0
    worst = 0.0
    for name in ("p", "q"):
        obs = posture.views.get(name)
        if obs is None:
            continue
        found, mm_per_px = _view_rays(G, 0 if name == "p" else 1, obs, c, u)
        (_, sine_c), tips = found[0], found[1:]
        sin2_sum += sine_c * sine_c
        mm_sum += mm_per_px
        views += 1
        level = clutter.get(name, 0.0)
        worst = max(worst, level)
        view_gain = 1.0 + VIEW_CLUTTER_GAIN * (level / settings.max_clutter) ** 2
        near = ends.get(name, (0.0, 0.0))
        for end in (0, 1):
            b, sine = tips[end]
            head = end == head_end
            local = near[end]
            inflation = view_gain + (END_CLUTTER_GAIN * local / settings.max_clutter if math.isfinite(local) else 1e6)
            # An axis turned by delta about the centroid moves where an end's ray meets it by up to
            # |b| delta cos / sin of the ray-axis angle (a ray across the axis meets it in the same place to
            # first order): a view that sees the axis foreshortened says little of the body's place when
            # the axis is uncertain by degrees.
            tilt = abs(b) * axis_sigma_rad * math.sqrt(max(1.0 - sine * sine, 0.0)) / max(sine, 1e-3)
            sigma = math.hypot(_end_sigma_mm(head, body, mm_per_px, sine, inflation), tilt)
            # The checks' yardstick is a clean end's noise (no clutter term): the question is whether the
            # ends are where clean measurements of this body would put them.
            clean = math.hypot(_end_sigma_mm(head, body, mm_per_px, sine, 1.0), tilt)
            weights["head" if head else "tail"] += 1.0 / (clean * clean)
            if head:
                apexes.append(AxialEstimate(f"{name} head", b - sign * to_head, sigma, clean))
            elif flat_tail:
                core.append(AxialEstimate(f"{name} tail", b + sign * body.centroid_from_tail_mm, sigma, clean))
    if views:
        clean_c = CENTROID_SIGMA_PX * (mm_sum / views) / math.sqrt(max(sin2_sum, 1e-6))
        sigma_c = clean_c * (1.0 + CENTROID_CLUTTER_GAIN * (worst / settings.max_clutter) ** 2)
        core.insert(0, AxialEstimate("centroid", 0.0, sigma_c, clean_c))
    sigmas = {k: (1.0 / math.sqrt(w) if w > 0 else math.inf) for k, w in weights.items()}
    return core, apexes, sigmas


def _combine(core: list[AxialEstimate], apexes: list[AxialEstimate]) -> tuple[float, float, int]:
    """The inverse-variance mean of the core estimates and the apexes consistent with it (within
    ``APEX_GATE_SIGMAS``): ``(b, chi-square, estimates used)``.

    Independent Gaussian measurements of one number: their inverse-variance mean is the
    maximum-likelihood one, and its variance the smallest of any linear combination. The apexes are
    gated because their errors are not Gaussian (a cone's faint apex lost or run on into a vessel)."""
    w = [1.0 / (e.sigma_mm * e.sigma_mm) for e in core]
    total = sum(w)
    b = sum(wi * e.b_mm for wi, e in zip(w, core)) / total
    used = list(core)
    for e in apexes:
        if abs(e.b_mm - b) <= APEX_GATE_SIGMAS * math.sqrt(e.sigma_mm ** 2 + 1.0 / total):
            used.append(e)
    w = [1.0 / (e.sigma_mm * e.sigma_mm) for e in used]
    b = sum(wi * e.b_mm for wi, e in zip(w, used)) / sum(w)
    chi2 = sum(wi * (e.b_mm - b) ** 2 for wi, e in zip(w, used))
    return b, chi2, len(used)


def _disagreement(core: list[AxialEstimate]) -> tuple[float, int, str, float]:
    """How far the centroid and the tails disagree, measured by a clean frame's noise: the chi-square of their
    inverse-variance mean with the clean sigmas, its degrees of freedom, and the estimate most at odds with it
    with how far (mm) it puts the body from where the others do."""
    w = [1.0 / (e.clean_sigma_mm * e.clean_sigma_mm) for e in core]
    total = sum(w)
    b = sum(wi * e.b_mm for wi, e in zip(w, core)) / total
    chi2 = sum(wi * (e.b_mm - b) ** 2 for wi, e in zip(w, core))
    k = max(range(len(core)), key=lambda i: w[i] * (core[i].b_mm - b) ** 2)
    others = total - w[k]
    rest = (b * total - w[k] * core[k].b_mm) / others if others > 0 else b
    return chi2, len(core) - 1, core[k].what, core[k].b_mm - rest


def place_body(calibration: Calibration, posture: Posture, body: BodyModel, settings: RecognitionSettings,
               clutter: dict[str, float] | None = None, axis_sigma_rad: float = 0.0,
               ends: dict[str, tuple[float, float]] | None = None) -> Posture:
    """The posture with its centroid and tips placed by the known body (see the module docstring).

    ``clutter``: per view, :attr:`.Blob.clutter` (both paths have it; a view left out counts as clean);
    ``axis_sigma_rad``: the 3D axis' standard deviation (:attr:`.Reconstruction.axis_sigma_rad`);
    ``ends``: per view over another structure (clutter above ``settings.max_clutter``), its
    :func:`end_clutter`. A lost posture, one without an axis (unresolved mirror ambiguity) or without
    tips is returned as it is, and so is every posture of the paper's estimator (kept verbatim).
    """
    if (not posture.ok or posture.direction is None or posture.tips_mm is None or posture.centroid_mm is None
            or settings.estimator == "paper"):
        return posture
    clutter = clutter or {}
    ends = ends or {}
    c, u = posture.centroid_mm, posture.direction
    cft, length = body.centroid_from_tail_mm, body.length_mm
    reasons = [posture.reason] if posture.reason else []
    ambiguous = posture.ambiguous
    decisive = False
    if posture.head_identified:
        core, apexes, sigmas = axial_evidence(calibration, posture, body, settings, clutter, ends, 0, axis_sigma_rad)
        b, _, _ = _combine(core, apexes)
        centroid = c + b * u
        tail = centroid - cft * u
        tips = np.array([tail + length * u, tail])
    else:
        # The tips' order is unknown, and with it the side of the centroid the body's offset lies on:
        # each order is a hypothesis, and the ends choose only where one fits decisively better.
        fits = []
        for head_end in (0, 1):
            core, apexes, sigmas = axial_evidence(calibration, posture, body, settings, clutter, ends, head_end,
                                                   axis_sigma_rad)
            fits.append((_combine(core, apexes), head_end, core, sigmas))
        fits.sort(key=lambda f: f[0][1])
        (b, chi2, _), head_end, core, sigmas = fits[0]
        decisive = len(core) > 1 and fits[1][0][1] - chi2 >= ORDER_CHI2
        if decisive:
            centroid = c + b * u
            sign = 1.0 if head_end == 0 else -1.0   # +u points to the head under this order
            tail = centroid - sign * cft * u
            head = tail + sign * length * u
            tips = np.array([head, tail]) if head_end == 0 else np.array([tail, head])
        else:
            centroid, tips = c, posture.tips_mm
    placed_by_body = posture.head_identified or decisive
    measured = posture.length_mm
    if placed_by_body:
        # The body was placed by the centroid and the tails: where they disagree beyond a clean frame's noise,
        # one of them is off and the place is in doubt. (An apex off alone is not used, so it casts no doubt.)
        chi2, dof, what, off = _disagreement(core)
        if dof > 0 and chi2 > CORE_SIGMAS ** 2 * dof:
            ambiguous = True
            source = "the moment centroid" if what == "centroid" else f"view {what}"
            reasons.append(f"{source} puts the body {abs(off):.2f} mm along its axis from where the rest of the "
                           f"evidence does, more than their noise: the place along the axis is in doubt (over "
                           f"another structure, or an end lost or run on)")
    elif measured is not None and math.isfinite(measured):
        # The measured tips are kept: a length off the body's beyond their noise means they are off.
        noise = math.hypot(sigmas["head"], sigmas["tail"])
        if abs(measured - length) > LENGTH_SIGMAS * noise:
            ambiguous = True
            reasons.append(f"the measured length {measured:.1f} mm is not the robot's {length:g} mm (noise "
                           f"{noise:.2f} mm): an end runs on into another structure or was lost to it, or the "
                           f"cone's apex was measured as a flat end (the head is not identified)")
    placed = copy.copy(posture)  # (dataclasses.replace re-runs __init__: a few us a steady-state frame)
    placed.centroid_mm, placed.tips_mm, placed.ambiguous = centroid, tips, ambiguous
    placed.reason = "; ".join(reasons) if reasons else None
    return placed
