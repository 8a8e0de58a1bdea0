"""The robot's known body placed on the reconstructed axis: one axial position gives the centroid and both tips.

The appliance always knows which robot it tracks (``robot: {id: N}``, :class:`appliance.robots.RobotSpec`):
its length ``L`` and where its volume centroid lies from the tail face (``centroid_from_tail_mm``, not
``L / 2`` for a coned body). With the 3D axis reconstructed (accurate to a few hundredths of a degree on
the accuracy benchmark) and the head identified, the centroid and both tips follow from ONE number, the
body's position along that axis: ``tail = c - centroid_from_tail u``, ``head = tail + L u``.

That number is measured several ways, each with its own uncertainty:

* the moment centroid (the reconstruction's 3D centroid): the best single measurement on a clean frame,
  but over another structure the background interpolated under the body slopes along it and the whole
  axial profile, and with it the centroid, slides along the axis;
* each view's tail and head, their rays meeting the 3D axis, less the body's offset from that end to
  the centroid. A flat tail is a blurred step located at its half height (as sharp as the centroid);
  a cone's apex is extrapolated from its faint ramp (much less sharp: robot 6's polymer apex is the
  worst feature of all). An end is affected only by what lies near it (:func:`end_clutter`), so where
  a vessel crosses one end or the middle of the body, the other end still places the body.

Over another structure each sigma grows with the clutter; a flat tail's growth is scaled down
(:data:`.body_kernels.CLUTTERED_TAIL_INFLATION`): the moment centroid slides with the background under the
whole body, a tail's step moves little (dev seeds: their errors were 0.47 and 0.18 of the sigmas before).

The estimates are combined by inverse variance (:func:`place_body`): independent measurements of one
number, each Gaussian to first order, so that is their maximum-likelihood mean and the sigmas
decide, not a fixed rule per case. The apexes join only where they agree with the centroid and tails
(their errors have heavy tails). Where the centroid and the tails disagree by more than a clean frame's
noise, one of them ran on into a vessel, lost part of the body to it or slid with the background under
it, and the place along the axis is in doubt: the frame is flagged ambiguous with the estimate at odds,
never hidden. (The measured length says the same only where the apex is not the end that is off; where
the order stays undecided, a measured length off the body's flags the frame.)

Before that, the centroid is moved across the axis onto the line where the views' axis planes meet
(:func:`.body_kernels._onto_axis_planes`): each view's 2D axis goes through its image centroid, so where one
image centroid slid along its axis the triangulated point leaves the axis, across it as well as along it;
the planes put it back (held to the moment centroid's sigma, and not on an axis uncertain beyond 2.5 deg).

Where the head is not identified the tips' order is unknown, and so is the side of the centroid the
body's offset lies on: the measured ends then choose between the two placements only where one fits
decisively better (the head is still not claimed); otherwise the frame keeps its measured place along
the axis and its tips are put half the body's length either side of it, where each errs least whichever end is the
head (by the offset asymmetry ``L / 2 - centroid_from_tail``; a measured apex end errs by ~0.7 of the
cone). (Both ends measured as flat, the apex's half-height crossing falls short of it by about the
body's offset asymmetry, so such frames mostly stay undecided. The tracker first tries each end measured
as the cone's apex, :mod:`.head_by_body`: what reaches this unidentified, the body's shape could not tell;
where it told the head but the frame redone with that claim failed its checks, the head is given with the ends
as measured, :func:`.body_corrections.head_by_body`.
A body without a flat tail, robot 4, gives no order evidence and keeps its measured tips.)

Applied to the :class:`.Posture` (both the tracker's general path and the steady state's plain frames
build one, to the last bit the same) by one compiled kernel (:func:`.body_kernels.place`, issue 8: as
Python it cost a plain frame ~45 us), so both paths stay identical: :func:`place_body` for any posture;
a plain frame's is placed within the steady pair's compiled call (:func:`.steady_kernels._place_body`, the
numbers :func:`place_body` would take of it: as a second call from Python it cost a plain frame ~20 us),
and one the checks flag takes the general path. Python keeps only the postures and the reasons, made on
the rare flagged frames. The posture's ``length_mm`` stays the measured length (the track's plausibility
check compares it frame to frame) and its ``reprojection_px`` that of the measured centroid and ends.
"""
from __future__ import annotations

import copy
import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from appliance.geometry import Calibration
from appliance.recognition import body_kernels as bk
from appliance.recognition.posture import Posture
from appliance.recognition.segmentation import Blob, LogBackground, Roi, attenuation
from appliance.recognition.settings import RecognitionSettings


@dataclass(frozen=True)
class BodyModel:
    """What the body prior needs of the robot (from :class:`appliance.robots.RobotSpec`)."""

    length_mm: float
    centroid_from_tail_mm: float
    cone_length_mm: float
    diameter_mm: float
    #: The body's attenuation integrated over its volume (mm^2: attenuation per mm x volume), what a clean
    #: view's blob weighs (:func:`.body_mass.view_masses_mm2`); None where the robot's material is not known.
    mass_mm2: float | None = None

    @classmethod
    def of(cls, spec: object) -> BodyModel:
        """The model of a catalogue robot (anything with RobotSpec's four attributes; its mass where it has
        ``attenuation_per_mm`` and ``volume_mm3``)."""
        attenuation, volume = getattr(spec, "attenuation_per_mm", None), getattr(spec, "volume_mm3", None)
        mass = float(attenuation) * float(volume) if attenuation is not None and volume is not None else None
        return cls(float(spec.length_mm), float(spec.centroid_from_tail_mm),  # type: ignore[attr-defined]
                   float(spec.cone_length_mm), float(spec.diameter_mm), mass)  # type: ignore[attr-defined]

    @functools.cached_property
    def packed(self) -> np.ndarray:
        """The model as :func:`.body_kernels.place` takes it (its ``B_*`` layout; made once; writable, as
        the warm-up compiled it: a read-only array would be another signature, compiled at its first frame)."""
        body = np.empty(bk.B_SIZE)
        body[bk.B_LENGTH], body[bk.B_CENTROID_FROM_TAIL] = self.length_mm, self.centroid_from_tail_mm
        body[bk.B_CONE], body[bk.B_DIAMETER] = self.cone_length_mm, self.diameter_mm
        return body


# ------------------------------------------------------------------------------------- per-end clutter
#: Pixels beyond the body's edge and the end that the end's neighbourhood reaches: the support's pad
#: (``support_dilate_px + 1``) plus the rows the background under the body is interpolated from.
_END_REACH_PX = 7
#: Pixels around the body's outline left out of the end's neighbourhood (its blurred rim).
_RIM_PX = 3


def end_clutter(image: np.ndarray, log_bg: LogBackground | np.ndarray, blob: Blob, centroid_px: np.ndarray,
                tips_px: np.ndarray, settings: RecognitionSettings,
                which: tuple[bool, bool] = (True, True)) -> tuple[float, float]:
    """Per end (the order of ``tips_px``), how much structure the attenuation around it shows, as a
    fraction of the body's peak: the 5-95 % range of the 3 x 3-averaged attenuation beside and beyond
    the end, off the body, less what the noise alone spreads it by.

    :attr:`.Blob.clutter` says the background under the body varies somewhere; where a vessel crosses
    the body's middle or one end, only the ends it reaches have their axial profile's edge moved by
    the background interpolated under it. The neighbourhood is what that interpolation reads near the
    end: out to the support's rim and the rows beyond it (``_END_REACH_PX``), along the body from
    ``width`` before the end to beyond it, less the body's support grown by ``_RIM_PX`` (its blurred rim).

    ``which``: the ends to measure (:func:`ends_used`: :func:`place_body` reads only those); an end not
    measured is NaN. The neighbourhood, the body's pixels and the percentiles are one compiled call per end
    (:func:`.body_kernels.end_spread`; as numpy masks, a dilation and ``np.percentile`` it cost ~120 us an
    end, issue 8); the attenuation and its 3 x 3 mean (``cv2.blur``) are as before.
    """
    half = 0.5 * blob.width_px
    reach = half + _END_REACH_PX
    behind = 2.0 * half + _END_REACH_PX
    (cu, cv) = (float(centroid_px[0]), float(centroid_px[1]))
    out = []
    h, w = image.shape
    win = blob.window
    for wanted, tip in zip(which, np.asarray(tips_px, dtype=np.float64).tolist()):
        if not wanted:
            out.append(math.nan)
            continue
        tu, tv = tip
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
        spread, count = bk.end_spread(a, x0 + 1, y0 + 1, tu, tv, au, av, behind, reach, blob.weights,
                                      win.x0, win.y0, _RIM_DISK)
        if count < 16:
            out.append(math.inf)
            continue
        noise = 3.29 * blob.sigma / 3.0
        out.append(max(spread - noise, 0.0) / max(blob.peak, 1e-6))
    return out[0], out[1]


#: The body's rim grown by ``_RIM_PX``: cv2's elliptic structuring element, as the dilation used it.
_RIM_DISK = np.ascontiguousarray(cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * _RIM_PX + 1, 2 * _RIM_PX + 1)),
                                 dtype=np.uint8)


def ends_used(posture: Posture, body: BodyModel, settings: RecognitionSettings) -> tuple[bool, bool] | None:
    """Which ends' :func:`end_clutter` :func:`place_body` would read for ``posture`` (the order of its tips),
    or None for neither: it returns a posture it does not place as it is, and with the head identified a
    tail that is not flat (a body shorter than its cone and diameter) gives no estimate, so its sigma,
    the only thing the end's clutter changes, is not used (:func:`.body_kernels._evidence`)."""
    if (not posture.ok or posture.direction is None or posture.tips_mm is None or posture.centroid_mm is None
            or settings.estimator == "paper"):
        return None
    if posture.head_identified and not body.length_mm - body.cone_length_mm >= body.diameter_mm:
        return (True, False)
    return (True, True)


# ------------------------------------------------------------------------------------------ placement
#: A view left out of the posture, as :mod:`.body_kernels` takes a view (not observed: the rest unread).
_ABSENT = (0.0,) * bk.IN_VIEW_SIZE


def place_body(calibration: Calibration, posture: Posture, body: BodyModel, settings: RecognitionSettings,
               clutter: dict[str, float] | None = None, axis_sigma_rad: float = 0.0,
               ends: dict[str, tuple[float, float]] | None = None, *, fresh: bool = False,
               centroid_slide_mm: float = 0.0) -> Posture:
    """The posture with its centroid and tips placed by the known body (see the module docstring).

    ``clutter``: per view, :attr:`.Blob.clutter` (both paths have it; a view left out counts as clean);
    ``axis_sigma_rad``: the 3D axis' standard deviation (:attr:`.Reconstruction.axis_sigma_rad`);
    ``ends``: per view over another structure (clutter above ``settings.max_clutter``), its
    :func:`end_clutter`. A lost posture, one without an axis (unresolved mirror ambiguity) or without
    tips is returned as it is, and so is every posture of the paper's estimator (kept verbatim).
    Otherwise a copy (the posture given is left as it was); the arithmetic is :func:`.body_kernels.place`.
    ``centroid_slide_mm``: how far (one sigma) a view heavier than the body may have moved the moment centroid
    along the axis (:func:`.body_mass.centroid_slide_mm`), added to its sigma: the ends place the body.
    ``fresh``: the posture is the caller's own, just made and held by no one else (the tracker's general
    path): placed in place, without the copy (``copy.copy`` of a posture is ~100 us after a frame's copy
    has evicted the caches, more than the rest of the placement; issue 8).
    """
    if (not posture.ok or posture.direction is None or posture.tips_mm is None or posture.centroid_mm is None
            or settings.estimator == "paper"):
        return posture
    clutter = clutter or {}
    ends = ends or {}
    numbers = [*_floats(posture.centroid_mm), *_floats(posture.direction)]
    for name in ("p", "q"):
        obs = posture.views.get(name)
        if obs is None:
            numbers += _ABSENT
            continue
        (cu, cv), ((u0, v0), (u1, v1)) = obs.centroid_px.tolist(), obs.tips_px.tolist()
        near = ends.get(name, (0.0, 0.0))
        numbers += (1.0, cu, cv, u0, v0, u1, v1, clutter.get(name, 0.0), near[0], near[1])
    measured = posture.length_mm
    numbers += (math.nan if measured is None else measured, axis_sigma_rad, settings.max_clutter,
                1.0 if posture.head_identified else 0.0, centroid_slide_mm)
    # (copy.copy: dataclasses.replace re-runs __init__, a few us a frame)
    return _apply(calibration.packed, posture if fresh else copy.copy(posture), body, numbers)


def _floats(vector: np.ndarray) -> list[float]:
    """``np.asarray(vector, dtype=np.float64).tolist()`` without the conversion call where it is one already."""
    if type(vector) is np.ndarray and vector.dtype == _FLOAT64:
        return vector.tolist()
    return np.asarray(vector, dtype=np.float64).tolist()


_FLOAT64 = np.dtype(np.float64)


def _apply(packed: np.ndarray, placed: Posture, body: BodyModel, numbers: list[float]) -> Posture:
    """``placed`` (a posture no one else holds) updated by :func:`.body_kernels.place` on ``numbers`` (its
    ``inp``): the centroid and tips where the body placed them, the flag and its reason (made only on a
    flagged frame)."""
    out = np.empty(bk.OUT_SIZE)
    bk.place(packed, np.array(numbers), body.packed, out)
    was_placed, flag = out[bk.OUT_PLACED:bk.OUT_FLAG + 1].tolist()
    if was_placed:
        placed.centroid_mm = out[bk.OUT_CENTROID:bk.OUT_CENTROID + 3]
        placed.tips_mm = out[bk.OUT_TIPS:bk.OUT_TIPS + 6].reshape(2, 3)
    if flag == bk.FLAG_NONE:
        if not placed.reason:
            placed.reason = None
        return placed
    placed.ambiguous = True
    reasons = [placed.reason] if placed.reason else []
    what, off, noise = out[bk.OUT_WHAT:bk.OUT_NOISE + 1].tolist()
    if flag == bk.FLAG_DISAGREEMENT:
        # The body was placed by the centroid and the tails and they disagree beyond a clean frame's noise:
        # one of them is off and the place is in doubt. (An apex off alone is not used, so it casts no doubt.)
        source = "the moment centroid" if what < 0 else f"view {'pq'[int(what)]} tail"
        reasons.append(f"{source} puts the body {abs(off):.2f} mm along its axis from where the rest of the "
                       f"evidence does, more than their noise: the place along the axis is in doubt (over "
                       f"another structure, or an end lost or run on)")
    else:
        # The measured tips are kept, and their length is off the body's beyond their noise: they are off.
        reasons.append(f"the measured length {placed.length_mm:.1f} mm is not the robot's {body.length_mm:g} mm "
                       f"(noise {noise:.2f} mm): an end runs on into another structure or was lost to it, or the "
                       f"cone's apex was measured as a flat end (the head is not identified)")
    placed.reason = "; ".join(reasons)
    return placed
