"""Each view's blob weighed against the robot's body: its integrated attenuation at the object, in mm^2.

A blob's :attr:`.Blob.strength` is the sum of its pixels' attenuation line integrals; times the pixel's
area at the object (``(distance from the source / focal length)^2``, mm^2) it is the object's attenuation
integrated over its volume, the same in both views and, for the robot, its attenuation per mm times its
volume (:attr:`.BodyModel.mass_mm2`). A piece of another structure merged into one view's blob (a
contrast-filled vessel at robot 6's faint polymer cone) makes that view heavier than the body, and the
blob's moment centroid slides toward it.

Where one view is heavier than the body and the other is not (:func:`heavy_view`), the moment centroid's
sigma along the axis grows by the slide the excess can make (:func:`centroid_slide_mm`), so the body's ends
place it (:func:`.body_prior.place_body`), and the frame is flagged. (Tried: each view's centroid ray
meeting the axis, the heavy one's weighed down by the slide, as the moment centroid: on robot 6's eight
heavy-view frames of seeds 1029384, 6660666, 1357911, 5318008 the errors' sum of squares was 1.57 and,
the clutter counted as the body prior counts it, 0.77 mm^2, against 0.70 with the sigma alone; base 1.15.)
Both are off by default (:attr:`.RecognitionSettings.mass_rule`): on held-out seeds the sigma made robot 6's
centroid worse and the flag fell on frames other checks had flagged already.
"""
from __future__ import annotations

import math

import numpy as np

from appliance.geometry import Calibration, triangulate
from appliance.recognition.segmentation import Blob


def pixel_scales_mm(calibration: Calibration, point_mm: np.ndarray) -> dict[str, float]:
    """Per view, one pixel's size (mm) at ``point_mm``: its distance from the view's source over the focal length."""
    return {name: float(np.linalg.norm(point_mm - view.source_mm)) / float(view.K[0, 0])
            for name, view in calibration.views.items()}


def view_masses_mm2(calibration: Calibration, blobs: dict[str, Blob], point_mm: np.ndarray | None = None,
                    scales: dict[str, float] | None = None) -> dict[str, float]:
    """Per view, the blob's strength times the pixel's area at ``point_mm`` (default: the blobs' centroids
    triangulated); NaN for every view where that point is not finite. ``scales``: the caller's
    :func:`pixel_scales_mm` at that point, where it has them already."""
    if scales is None:
        if point_mm is None:
            point_mm = triangulate(calibration.p, calibration.q, blobs["p"].centroid_px, blobs["q"].centroid_px,
                                   optimal=False)[0]
        if not np.all(np.isfinite(point_mm)):
            return {name: math.nan for name in blobs}
        scales = pixel_scales_mm(calibration, point_mm)
    return {name: blob.strength * scales[name] ** 2 for name, blob in blobs.items()}


def heavy_view(masses_mm2: dict[str, float], body_mass_mm2: float, excess: float, deficit: float) -> str | None:
    """The view whose blob is heavier than the body by more than ``excess`` (a fraction) while the other's
    weighs it within ``deficit`` below to ``excess`` above (clean): the view with another structure merged
    into its blob. None otherwise.

    A clean view weighs the body to a few % where its attenuation is linear in the path (robot 6, dev seeds
    1-5, cold and tracked: 0.93-1.007 over views clear of other structure), less where a metal body's
    long chords starve the detector or a thin body's blurred rim is left out (robots 1, 2, 4, 5, 7: median
    0.82-0.87, down to 0.2), never more. A light other view has lost part of the body (to a vessel's
    lumen, or to the background interpolated under it): its ends are no better evidence than the heavy
    view's centroid (robot 6 dev seed 5 pose 19, the other view 0.90: 0.03 -> 0.18 mm placed by them).
    """
    over = [name for name, mass in masses_mm2.items() if mass > (1.0 + excess) * body_mass_mm2]
    if len(over) != 1:
        return None
    other = "q" if over[0] == "p" else "p"
    return over[0] if masses_mm2[other] >= (1.0 - deficit) * body_mass_mm2 else None


def centroid_slide_mm(masses_mm2: dict[str, float], heavy: str, body_mass_mm2: float, length_mm: float) -> float:
    """How far (mm, one sigma) the excess of the ``heavy`` view can move the moment centroid along the axis:
    the excess' fraction of that view's blob times L / sqrt(12), the RMS lever arm of an excess that may lie
    anywhere along the body, uniformly (robot 6, 1357911 pose 12: 12 % of view q's blob, the centroid 0.59 mm
    off along the axis; L / 2 instead measured within 0.001 mm on dev seeds 1-20, robots 3 and 6)."""
    mass = masses_mm2[heavy]
    return max(mass - body_mass_mm2, 0.0) / mass * length_mm / math.sqrt(12.0)

