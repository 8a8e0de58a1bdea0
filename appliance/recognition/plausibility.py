"""Is the recognised object the robot, and whole? Post-reconstruction checks and the vessel-overlap fix.

The candidate pairing of :mod:`.tracker` accepts blobs that stand out of the noise and correspond
between the views; a contrast-filled vessel can do both (seen foreshortened in one view it is dense
there, and its two images can lie on each other's epipolar lines). Once the 3D axis is known the
object can be judged as a body: :func:`not_robot_like` checks its attenuation per mm of X-ray path
and its length over width; :func:`cut_by_edge` refuses a robot image cut by a detector's edge.
:func:`off_its_images` refuses a rod that does not reproject onto its images, :func:`part_of_body` one
whose ends are much closer together than the robot's body is long, and :func:`narrower_than_body` an
object much thinner than the robot.
:func:`declutter` places the centroid by the clean view where the robot overlaps a vessel in the
other. Each costs a few scalar operations per frame (no pixel work beyond the blob's own mask edges).
"""
from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np

from appliance.geometry import Calibration, View
from appliance.recognition.body_prior import BodyModel
from appliance.recognition.reconstruction import (
    Reconstruction,
    axis_plane,
    ray_line_parameters,
)
from appliance.recognition.segmentation import Blob, the_one_clean_view
from appliance.recognition.settings import RecognitionSettings

#: The clean view must see the axis at least this far from end-on (sine) to place the centroid along it.
_MIN_DECLUTTER_SIN = 0.3
#: The clean centroid ray must cross the cluttered view's axis plane at least this steeply (sine).
_MIN_PLANE_SIN = 0.3
#: ... and the cluttered view be cluttered this much (fraction of the robot's contrast): below it, its
#: blob slides less than the noise of the clean view's ray depth, and the triangulated axis line is kept.
_PLANE_CLUTTER = 0.2
#: The last calibration seen and, per view, its source position (mm) and focal length (px) as floats.
_LAST_SCALARS: tuple[Calibration, dict[str, tuple[float, float, float, float]]] | None = None


def _view_scalars(calibration: Calibration) -> dict[str, tuple[float, float, float, float]]:
    """Per view, the source's position (mm) and the focal length (px) as plain floats.

    The checks below run on every frame, where numpy's per-call overhead on 3-vectors (~1 us a call)
    would cost more than the arithmetic. Calibrations are immutable and a tracker keeps one, so the
    last one's scalars are kept (compared by identity).
    """
    global _LAST_SCALARS
    if _LAST_SCALARS is None or _LAST_SCALARS[0] is not calibration:
        scalars = {}
        for name, view in calibration.views.items():
            sx, sy, sz = (float(x) for x in view.source_mm)
            scalars[name] = (sx, sy, sz, float(view.K[0, 0]))
        _LAST_SCALARS = (calibration, scalars)
    return _LAST_SCALARS[1]


def not_robot_like(calibration: Calibration, rec: Reconstruction, blobs: dict[str, Blob],
                   settings: RecognitionSettings) -> str | None:
    """Why the reconstructed object is not a dense rod (None if it is one).

    A rod of diameter ``w`` whose axis makes the angle ``theta`` with a view's central ray is crossed
    by that ray over ``w / sin(theta)``: the view that sees it most side-on gives its attenuation per
    mm of path, which for metal is far above contrast medium's. The per-width test of the candidate
    pairing cannot tell a vessel seen foreshortened (strong, short, as wide as its lumen) from the
    robot; the path can. A robot is also of bounded length over width. (The two views' widths are
    not compared here: where the robot crosses a vessel one view's width is unreliable, and such
    frames are flagged by the clutter test instead.)

    Plain-float arithmetic (a few microseconds a frame): it runs on every tracked frame.
    """
    s = settings
    cx, cy, cz = rec.centroid.tolist()
    # Per view: the ray from the source to the reconstructed centroid, its length, and the blob's
    # width in mm there (magnification from the source distance).
    scalars = _view_scalars(calibration)
    rays: dict[str, tuple[float, float, float, float]] = {}
    widths: dict[str, float] = {}
    for name, blob in blobs.items():
        sx, sy, sz, fx = scalars[name]
        rx, ry, rz = cx - sx, cy - sy, cz - sz
        distance = math.sqrt(rx * rx + ry * ry + rz * rz)
        rays[name] = (rx, ry, rz, distance)
        widths[name] = blob.width_px * distance / fx
    width = 0.5 * (widths["p"] + widths["q"])
    if rec.length_mm is not None and rec.length_mm > s.max_length_over_width * width:
        return (f"no robot-like object in view p and q: the object seen is {rec.length_mm:.1f} mm long and "
                f"{width:.1f} mm wide, longer than any robot (a stretch of vessel)")
    directions = [rec.direction] if rec.direction is not None else list(rec.candidates or [])
    best: tuple[float, str] | None = None
    for direction in directions:
        dx, dy, dz = direction.tolist()
        # Per direction hypothesis: the view seeing the axis most side-on, and the rod's chord there.
        side, side_sine = "", -1.0
        for name in blobs:
            rx, ry, rz, distance = rays[name]
            cosine = abs(rx * dx + ry * dy + rz * dz) / distance
            sine = math.sqrt(max(0.0, 1.0 - cosine * cosine))
            if sine > side_sine:
                side, side_sine = name, sine
        mu = blobs[side].peak * max(side_sine, 1e-3) / max(widths[side], 1e-6)
        if best is None or mu > best[0]:
            best = (mu, side)
    if best is not None and best[0] < s.min_path_attenuation_per_mm:
        return (f"no robot-like object in view {'p' if best[1] == 'q' else 'q'}: the object attenuates "
                f"{best[0]:.2f}/mm of path in view {best[1]} (seen side-on there), like contrast medium, "
                f"not like the robot (>= {s.min_path_attenuation_per_mm:g}/mm)")
    return None


def _clean_view(calibration: Calibration, rec: Reconstruction, blobs: dict[str, Blob],
                settings: RecognitionSettings) -> str | None:
    """The view that places the centroid along the axis when the other overlaps a vessel, if any: the
    other view alone is cluttered and this one sees the axis well away from end-on (see :func:`declutter`).
    The paper's estimator stays verbatim (None)."""
    if rec.direction is None or settings.estimator == "paper":
        return None
    clean = the_one_clean_view(blobs, settings.max_clutter)
    if clean is None:
        return None  # neither view or both cluttered: nothing to place by
    sx, sy, sz, _ = _view_scalars(calibration)[clean]
    cx, cy, cz = rec.centroid.tolist()
    dx, dy, dz = rec.direction.tolist()
    rx, ry, rz = cx - sx, cy - sy, cz - sz
    cosine = (rx * dx + ry * dy + rz * dz) / math.sqrt(rx * rx + ry * ry + rz * rz)
    return clean if 1.0 - cosine * cosine >= _MIN_DECLUTTER_SIN ** 2 else None


def declutter(calibration: Calibration, rec: Reconstruction, blobs: dict[str, Blob],
              settings: RecognitionSettings) -> Reconstruction:
    """The centroid placed along the axis by the clean view alone when the other overlaps a vessel.

    Where the robot overlaps a vessel in one view, its blob there merges with the vessel and its
    centroid slides along the axis; the 3D axis (from both views' axis planes) and the position
    across it are hardly affected. The clean view's centroid ray then fixes where along the axis
    the centroid is, provided that view sees the axis well away from end-on.
    """
    d = rec.direction
    clean = _clean_view(calibration, rec, blobs, settings)
    if d is None or clean is None:
        return rec
    cluttered = ["q" if clean == "p" else "p"]
    view, feat = calibration.views[clean], rec.view_features[clean]
    ray = rec.centroid - view.source_mm
    z = float(np.linalg.norm(ray))
    cosine = float(np.dot(ray, d)) / z
    sin2 = 1.0 - cosine * cosine
    # The clean view's weighted centroid, less its perspective bias (as perspective_corrected_centroid).
    mm_per_px = z / float(view.K[0, 0])
    shift = -3.0 * cosine * feat.eigenvalues[0] * mm_per_px ** 2 / sin2 / z
    seen, true = view.project(np.vstack([rec.centroid + shift * d, rec.centroid]))
    pixel = feat.centroid + (true - seen)
    origins, rays = view.rays(pixel[None, :])
    # The cluttered view's blob slides along its axis but hardly across it: the plane through its
    # source and 2D axis line still holds the robot's axis. Where the clean ray crosses that plane is
    # the centroid (the triangulation had spread the cluttered view's error over both rays, and so
    # moved the 3D axis line across too).
    plane = axis_plane(calibration.views[cluttered[0]], rec.view_features[cluttered[0]])
    normal, offset = plane[:3], float(plane[3])
    k = float(np.dot(normal, rays[0]))
    if abs(k) > _MIN_PLANE_SIN and blobs[cluttered[0]].clutter > _PLANE_CLUTTER:
        centroid = origins[0] - (float(np.dot(normal, origins[0])) + offset) / k * rays[0]
    else:
        # The clean ray nearly lies in that plane: the point of the clean ray nearest the 3D axis instead.
        b, _ = ray_line_parameters(view, pixel[None, :], rec.centroid, d)
        along = rec.centroid + float(b[0]) * d - origins[0]
        centroid = origins[0] + float(np.dot(along, rays[0])) * rays[0]
    return replace(rec, centroid=centroid, **_clean_tips(view, rec, clean, centroid, d))


def _clean_tips(view: View, rec: Reconstruction, clean: str, centroid: np.ndarray, d: np.ndarray
                ) -> dict[str, Any]:
    """The 3D tips where the clean view's 2D tip rays pass nearest the axis through ``centroid``.

    The cluttered view's blob runs on into the vessel or loses a faint end to it, and its tip there
    is off by up to a body length (robot 6 over the vessel: 13 mm); the triangulation spreads that
    over both 3D tips. The clean view, which sees the axis well away from end-on, places each end
    alone (its error along the axis grows as 1 / sine of the ray-axis angle, <= 3.3x here)."""
    if rec.tips is None or clean not in rec.view_tips:
        return {}
    b, _ = ray_line_parameters(view, np.asarray(rec.view_tips[clean], dtype=np.float64), centroid, d)
    tips = centroid[None, :] + b[:, None] * d[None, :]
    return {"tips": tips, "length_mm": float(abs(b[0] - b[1]))}


def off_its_images(calibration: Calibration, rec: Reconstruction, blobs: dict[str, Blob],
                   settings: RecognitionSettings) -> str | None:
    """Why the reconstructed rod cannot be trusted to the appliance's accuracy (None if it can).

    The 3D centroid and tips are re-projected into both views and compared with the 2D centroid and
    ends they were made from. A rod that reprojects ``settings.max_reprojection_px`` or more off its images is
    not one rod seen twice: one view's blob runs on into a vessel or another structure, or its ends
    were mapped to the wrong 3D end. Its centroid may still be close, but nothing in the frame says
    whether it is (on the accuracy benchmark such frames are 0.03 to 1.0 mm off, against <= 0.1 mm
    asked); the frame is reported lost with this reason rather than ok with an error nobody can bound.
    Where a view overlaps another structure (clutter above ``settings.max_clutter``) the limit is
    ``settings.max_cluttered_reprojection_px`` (3 px), whether or not :func:`declutter` then places the
    centroid by the clean view: at 1024 px such frames beyond 3 px were 0.2 to 1.8 mm off in 8 of 13 on
    the accuracy benchmark's seeds 1-3, placed or not (robot 6: 0.67 and 0.80 mm after placement at
    11.1 and 7.6 px), while clean frames reproject <= 3 px. (Until the vessel-overlap segmentation
    changes, placed frames were spared up to any reprojection; the figures above are what ended it.)
    With ``settings.background_along_structure`` the limit there is tighter
    (``max_cluttered_reprojection_along_px``, 2 px; ``max_both_cluttered_reprojection_along_px``, 1.5 px where
    both views are cluttered): that background makes a blob that ran on into the vessel consistent with
    itself, so the other view's disagreement is the only sign left of it (see the settings' figures).
    The paper's estimator is left verbatim (its reprojection is that of its own triangulated tips).
    """
    if settings.estimator == "paper" or rec.reprojection_px is None:
        return None
    cluttered = [name for name, blob in blobs.items() if blob.clutter > settings.max_clutter]
    limit = settings.max_cluttered_reprojection_px
    if settings.background_along_structure:
        limit = (settings.max_both_cluttered_reprojection_along_px if len(cluttered) == len(blobs)
                 else settings.max_cluttered_reprojection_along_px)
    if cluttered and rec.reprojection_px > limit:
        return (f"the robot overlaps another structure in view {' and '.join(cluttered)} and its centroid and "
                f"ends reproject {rec.reprojection_px:.1f} px (RMS) off its images (> "
                f"{limit:g} px): its blob there runs on into that structure or "
                f"lost part of the robot to it, so its position cannot be trusted to the appliance's accuracy")
    if rec.reprojection_px <= settings.max_reprojection_px:
        return None
    return (f"the robot's centroid and ends reproject {rec.reprojection_px:.1f} px (RMS) off its images in view p "
            f"and q (> {settings.max_reprojection_px:g} px): the two blobs do not fit one rod (one likely runs on into "
            f"another structure), so its position cannot be trusted to the appliance's accuracy")


def part_of_body(rec: Reconstruction, body: BodyModel | None, settings: RecognitionSettings) -> str | None:
    """Why the rod is too short to be the whole robot (None if it may be; always None without a body).

    The 3D distance between the triangulated ends does not depend on how foreshortened either view sees
    the robot, so a rod much shorter than the body is not the body: only a part of it was found (the rest
    too faint beside, or lost into, another structure), or the object is something else. The body prior
    would place the whole body from that part and report it with the noise of a clean frame, a body
    length off: seed 6264338, robot 6 (30 mm), tracked pose 1 had its ends 5.3 mm apart over the vessel in
    both views and was reported ok (flagged) 23.4 mm off. A rod is refused where it is shorter than
    ``settings.min_length_fraction`` of the body and also more than two diameters short of it: a stubby
    body's ends are set by its width nearly as much as by its length (robot 4, 3 x 1.5 mm, measures
    0.46-0.57 of its length on some frames reported ok; the other robots' ok frames measure >= 0.77 on
    dev seeds 1-20, cold and tracked). The paper's estimator is left verbatim.
    """
    if settings.estimator == "paper" or body is None or rec.length_mm is None:
        return None
    length, measured = body.length_mm, rec.length_mm
    if measured >= settings.min_length_fraction * length or length - measured <= 2.0 * body.diameter_mm:
        return None
    return (f"the robot's ends are {measured:.1f} mm apart, against its {length:g} mm body (< "
            f"{settings.min_length_fraction:.0%} of it): only part of the robot was found (the rest lost into "
            f"another structure), or the object is not the robot")


def narrower_than_body(calibration: Calibration, rec: Reconstruction, blobs: dict[str, Blob],
                       body: BodyModel | None, settings: RecognitionSettings) -> str | None:
    """Why the object is too thin to be the robot (None if it may be it; always None without a body).

    A rod's projected width is its diameter from any direction (end-on it is a disc of that diameter), and
    a blob's ``width_px`` (4 sqrt of its weighted cross-axis moment) measures it: the semicircular chord
    profile of a cylinder gives exactly the diameter, blur widens it and a vessel under the robot widens it
    more. So where both views' blobs, scaled to mm at the reconstructed centroid, are much narrower than
    the known body, the object is not the robot, however well its images correspond. This holds where
    the length cannot judge it: seed 5266249, robot 6 (5 mm across), cold pose 5 paired a 0.8 mm wide
    stretch of vessel lying in an epipolar plane in both views (axis unresolved, so no length) and
    reported it ok (ambiguous) 27 mm from the robot: its widest view measured 0.16 of the body's
    diameter, where every frame of the robot on dev seeds 1-6 (cold, all robots, and seed 1 tracked;
    1528 checks) measured >= 0.85 of its own. The paper's estimator is left verbatim.
    """
    if settings.estimator == "paper" or body is None:
        return None
    scalars = _view_scalars(calibration)
    cx, cy, cz = rec.centroid.tolist()
    widest = 0.0
    for name, blob in blobs.items():
        sx, sy, sz, fx = scalars[name]
        distance = math.sqrt((cx - sx) ** 2 + (cy - sy) ** 2 + (cz - sz) ** 2)
        widest = max(widest, blob.width_px * distance / fx)
    if widest >= settings.min_width_fraction * body.diameter_mm:
        return None
    return (f"the object is {widest:.1f} mm wide in its widest view, against the robot's {body.diameter_mm:g} mm "
            f"diameter (< {settings.min_width_fraction:.0%} of it): not the robot (a stretch of vessel or a "
            f"fragment)")


def at_odds_with_track(rec: Reconstruction, blobs: dict[str, Blob], previous_direction: np.ndarray | None,
                       previous_length_mm: float | None, settings: RecognitionSettings) -> str | None:
    """Why the reconstructed rod cannot be the tracked robot one frame later (None if it can be).

    A rigid robot keeps its length, and in one frame period it cannot turn its head round: a length
    that jumps by more than ``settings.max_length_change`` means one view's blob lost an end or ran on into a
    vessel (its tips, and with them the centroid's place along the axis, are off), and a head claim
    that points against the track's heading is a wrong claim from such an end. Both were seen where
    the ROI search follows a polymer robot over the vessel (seed 777, robot 3: length 19.0 -> 14.5 mm,
    head turned 180 deg, centroid 0.63 mm off, tips 20 mm off). Only with a track (the ROI path), and
    only where this frame is itself in doubt (ambiguous, or over another structure in a view): a clean
    frame outranks the track, which may come from a worse frame (seed 777, robot 2: a clean 14.9 mm
    after a 12.8 mm frame is right, 0.04 mm off).
    """
    if settings.estimator == "paper":
        return None
    if not (rec.ambiguous or any(blob.clutter > settings.max_clutter for blob in blobs.values())):
        return None
    if previous_length_mm and rec.length_mm is not None:
        change = abs(rec.length_mm - previous_length_mm) / previous_length_mm
        if change > settings.max_length_change:
            return (f"the robot's length changed from {previous_length_mm:.1f} to {rec.length_mm:.1f} mm in one "
                    f"frame: one view's blob lost an end or runs on into another structure")
    if rec.head_identified and rec.direction is not None and previous_direction is not None:
        (a0, a1, a2), (b0, b1, b2) = rec.direction.tolist(), previous_direction.tolist()
        cosine = a0 * b0 + a1 * b1 + a2 * b2
        if cosine < 0.0:
            return (f"the head seen points {math.degrees(math.acos(max(-1.0, cosine))):.0f} deg away from the "
                    f"tracked heading one frame earlier: a wrong end taken for the head")
    return None


def cut_by_edge(calibration: Calibration, blobs: dict[str, Blob]) -> str | None:
    """Why the robot's image is cut by a detector's edge (None if it is whole in both views).

    A robot partly outside a view's field leaves a shortened, off-centre image: its centroid and
    length would be invented from the part that is seen.
    """
    for name, blob in blobs.items():
        w, h = calibration.views[name].image_size
        win, mask = blob.window, blob.mask
        if ((win.x0 == 0 and mask[:, 0].any()) or (win.y0 == 0 and mask[0].any())
                or (win.x1 == w and mask[:, -1].any()) or (win.y1 == h and mask[-1].any())):
            return f"the robot's image reaches the edge of view {name}: it is partly outside the field"
    return None
