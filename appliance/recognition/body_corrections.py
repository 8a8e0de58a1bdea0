"""Corrections of a reconstruction by the robot's known body (a :class:`.BodyModel`).

:class:`.PostureTracker` applies these, in this order, to a frame whose reconstruction passed its checks:

* :func:`head_by_body` - a head left unidentified, or claimed over another structure or by one view alone,
  told by the body's shape where that is decisive (:mod:`.head_by_body`);
* :func:`mirror_by_body` - an unresolved mirror ambiguity (the axis near an epipolar plane) resolved by the
  body's fits under every hypothesis (:class:`.axis_by_length.PlaneScan`), or else its centroid placed where
  those fits agree on it (:func:`centroid_by_body`);
* :func:`axis_by_length` - the axis within an epipolar plane refitted by the body where the measured length
  is off the body's (:mod:`.axis_by_length`).

Each takes what it needs explicitly (the calibration, the fundamental matrix ``F``, the settings, the body or
None, the calibration's packed views for the compiled kernels) and returns the reconstruction it was given
where it does not apply. A correction that redoes the reconstruction has it pass the tracker's checks again:
``rejection`` is the tracker's (``PostureTracker._rejection``: why the views' blobs are not images of one
robot-like object, or None).
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from appliance.geometry import Calibration
from appliance.recognition import reconstruction_kernels
from appliance.recognition.axis_by_length import SCAN_HALF_RANGE_DEG, PlaneScan
from appliance.recognition.body_prior import BodyModel
from appliance.recognition.features import Features2D
from appliance.recognition.head_by_body import axial_rows, chi2_of
from appliance.recognition.reconstruction import Reconstruction, axis_plane, ray_line_parameters, reconstruct
from appliance.recognition.segmentation import Blob, the_one_clean_view
from appliance.recognition.settings import RecognitionSettings

#: The tracker's checks of a (redone) reconstruction: why it is not one robot-like object, or None.
Rejection = Callable[[Reconstruction, dict[str, Blob], dict[str, Features2D], np.ndarray | None], str | None]

#: An unresolved mirror ambiguity's centroid is the body's fits' mean where they lie within this fraction of
#: the body's diameter of each other (:func:`centroid_by_body`).
CENTROID_SPREAD_DIAMETERS = 0.25


def head_by_body(calibration: Calibration, F: np.ndarray, settings: RecognitionSettings, body: BodyModel | None,
                 rec: Reconstruction, blobs: dict[str, Blob], feats: dict[str, Features2D],
                 previous: np.ndarray | None, rejection: Rejection) -> Reconstruction:
    """The head told by the known body (:mod:`.head_by_body`) where the views' ramps leave it unidentified
    or claim it over another structure or by one view alone.

    Called on a frame that passed the checks (``rejection``, the tracker's). The body is fitted along the axis
    with its head at either end, each view's ends measured as the cone's apex and the flat tail
    accordingly; where one end fits better by ``settings.head_body_chi2`` and fits well itself
    (``settings.head_body_fit`` per degree of freedom), or, the views' claims disagreeing with one over another
    structure, the clean view claims that end and the fit leans to it by ``settings.head_body_clean_view_chi2``
    (:func:`_clean_view_agrees`), the head is there: the reconstruction is redone
    with both views claiming it (the cone's apex then extrapolated from its ramp), and taken if it
    passes the same checks; where it does not, and the head was unidentified, the first reconstruction is kept
    with the head at that end and its ends as measured (:func:`_oriented`, ``settings.head_body_orients_unclaimed``:
    a view over another structure lost part of its cone, so the apex extrapolated from what is left reprojects
    far off its image, while the order alone lets the body prior place the body by its tails and centroid).
    An unidentified head whose fit is not decisive stays unidentified; a claim over another
    structure, or by one view alone, stands unless the fit decisively puts the head at the other end (one
    clean view's ramps can lie too: a vessel alongside the tail, its clutter 0.12, made a 12 px "ramp" there,
    study seed 4040404 robot 2 pose 26; dev seeds 1-20 and standing seeds 20261121, 777, 4242: no other frame
    changed). A claim the fit leans against by ``settings.head_body_doubt_chi2``, short of decisive, is withdrawn
    (:func:`_claim_withdrawn`): the head is then reported unidentified, not flipped (seed 7757247 robot 7 pose 17,
    a wrong claim by view p over the vessel, 16.5 against it: tips 9.9 and 6.1 -> 0.73 mm; dev seeds 1-12 cold:
    no claim the fit leans against by more than 5.5). Claims by both views, both clean, are left alone, and so is a body whose cylinder is shorter
    than its diameter (robot 4: its tail is no step, :mod:`.body_kernels`). (A plain frame, :mod:`.steady_state`,
    never reaches this: one claimed by one clean view alone is not checked on the tracked path.)
    """
    s = settings
    if (body is None or s.estimator == "paper" or rec.direction is None or not body.cone_length_mm > 0
            or not body.length_mm - body.cone_length_mm >= body.diameter_mm
            or any(feat.reach is None for feat in feats.values())):
        return rec   # (a body without a flat tail, robot 4, has no tail crossing to measure: body_kernels)
    if (rec.head_identified and all(feat.head_index is not None for feat in feats.values())
            and not any(blobs[name].clutter > s.max_clutter for name in feats)):
        return rec   # claimed by both views, both clean
    clutter = {name: blob.clutter for name, blob in blobs.items()}
    rows_plus, rows_minus, plus_index = axial_rows(calibration, rec.centroid, rec.direction, feats, clutter, body)
    at_plus, at_minus = chi2_of(rows_plus, s.head_body_cap), chi2_of(rows_minus, s.head_body_cap)
    best, other = (at_plus, at_minus) if at_plus <= at_minus else (at_minus, at_plus)
    head_at_plus = at_plus <= at_minus
    fits = best <= s.head_body_fit * (len(rows_plus) - 1)
    if not (fits and (other - best >= s.head_body_chi2
                      or _clean_view_agrees(s, rec, blobs, feats, plus_index, head_at_plus, other - best))):
        if rec.head_identified and not head_at_plus and other - best >= s.head_body_doubt_chi2:
            return _claim_withdrawn(calibration, F, s, rec, blobs, feats, previous, rejection, other, best)
        return rec
    if rec.head_identified and head_at_plus:
        return rec   # the claim (the +direction end when identified) is the body's
    # Both views claim it (with_head: their tips re-estimated, the apex by the cone's model).
    claimed = {name: feat.with_head(plus_index[name] if head_at_plus else 1 - plus_index[name])
               for name, feat in feats.items()}
    try:
        redone = reconstruct(calibration, F, claimed["p"], claimed["q"], s, previous)
    except ValueError:
        return rec
    if (not redone.head_identified or redone.direction is None
            or (float(redone.direction @ rec.direction) > 0) != head_at_plus
            or rejection(redone, blobs, feats, previous) is not None):
        # (the redone frame must pass the checks the first one passed: a claim loses no frame)
        if rec.head_identified or not s.head_body_orients_unclaimed:
            return rec
        return _oriented(rec, head_at_plus, plus_index, best, other)
    redone.reasons.append(f"the head is told by the body's shape: measured as the cone's apex, that end puts "
                          f"the body where the rest of it is (chi-square {best:.1f} against {other:.1f})")
    return redone


def _clean_view_agrees(settings: RecognitionSettings, rec: Reconstruction, blobs: dict[str, Blob],
                       feats: dict[str, Features2D], plus_index: dict[str, int], head_at_plus: bool,
                       margin: float) -> bool:
    """Whether an unidentified head whose views' claims disagree, one view over another structure and the other
    clean, has the clean view's claim at the end the body's fit leans to by ``settings.head_body_clean_view_chi2``
    (short of ``head_body_chi2``): two independent pieces of evidence for one end, the other view's claim
    measuring the structure's edge (:meth:`.PostureTracker._head_by_clean_view`, whose redo alone a single claim
    cannot pass where the tips and the axis planes disagree)."""
    if rec.head_identified or margin < settings.head_body_clean_view_chi2:
        return False
    if any(feat.head_index is None for feat in feats.values()):
        return False
    name = the_one_clean_view(blobs, settings.max_clutter)
    if name is None:
        return False
    return (feats[name].head_index == plus_index[name]) == head_at_plus


def _oriented(rec: Reconstruction, head_at_plus: bool, plus_index: dict[str, int], best: float,
              other: float) -> Reconstruction:
    """``rec`` (its head unidentified) with the head where the body's fit decisively puts it, its ends kept as
    measured (both as flat ends), where the reconstruction redone with both views claiming that head failed the
    tracker's checks (:func:`head_by_body`): a view over another structure lost part of its cone, so its apex
    extrapolated from the ramp left is far off its image, but its tail and the moment centroid still place the
    body once the order is known. Left unidentified, the tips go half the body's length either side of its place
    (:mod:`.body_prior`), each off by the body's offset asymmetry (robot 6: 5.75 mm; J seed 2302585 pose 26,
    view p's cone cut by a vessel that ends under it: chi-square 21.3 against 43.9, tips 6.05/6.25 mm). The
    frame keeps every flag it had; the reason says the head is the body's."""
    if head_at_plus:
        direction, tips, view_tips = rec.direction, rec.tips, rec.view_tips
    else:
        direction = -rec.direction
        tips = None if rec.tips is None else rec.tips[::-1].copy()
        view_tips = {name: t[::-1].copy() for name, t in rec.view_tips.items()}
    final = {name: replace(feat, head_index=plus_index[name] if head_at_plus else 1 - plus_index[name])
             for name, feat in rec.view_features.items()}
    reason = (f"the head is told by the body's shape (chi-square {best:.1f} against {other:.1f}), its ends kept as "
              f"measured: with the head's apex extrapolated from its ramp the frame fails its checks")
    return replace(rec, direction=direction, tips=tips, view_tips=view_tips, head_identified=True,
                   view_features=final, reasons=rec.reasons + [reason])


def _claim_withdrawn(calibration: Calibration, F: np.ndarray, settings: RecognitionSettings, rec: Reconstruction,
                     blobs: dict[str, Blob], feats: dict[str, Features2D], previous: np.ndarray | None,
                     rejection: Rejection, claimed_chi2: float, other_chi2: float) -> Reconstruction:
    """``rec`` with its head claim withdrawn, the body's fit leaning against it by ``settings.head_body_doubt_chi2``
    but not decisively (:func:`head_by_body`): redone with neither view claiming the head (both ends measured as
    flat, the order left to the body prior), or, where the redone frame fails the checks or loses its axis, the
    claim only withheld (the claimed end keeps its cone-model tip, as :meth:`.PostureTracker._head_in_doubt`)."""
    reason = (f"the head is not claimed: the body's shape puts it at the other end (chi-square {other_chi2:.1f} "
              f"against {claimed_chi2:.1f} for the claim), not decisively")
    unclaimed = {name: feat.with_head(None) for name, feat in feats.items()}
    try:
        redone = reconstruct(calibration, F, unclaimed["p"], unclaimed["q"], settings, previous)
    except ValueError:
        redone = None
    if (redone is not None and redone.direction is not None and not redone.head_identified
            and rejection(redone, blobs, feats, previous) is None):
        redone.reasons.append(reason)
        return redone
    final = {name: replace(feat, head_index=None) for name, feat in rec.view_features.items()}
    return replace(rec, head_identified=False, view_features=final, reasons=rec.reasons + [reason])


def plane_normal(calibration: Calibration, feats: dict[str, Features2D]) -> np.ndarray:
    """The normal of the plane both views' axis planes (nearly) are: an epipolar plane."""
    n_p = axis_plane(calibration.p, feats["p"])[:3]
    n_q = axis_plane(calibration.q, feats["q"])[:3]
    normal = n_p + (1.0 if float(n_p @ n_q) >= 0 else -1.0) * n_q
    return normal / np.linalg.norm(normal)


def mirror_by_body(calibration: Calibration, F: np.ndarray, settings: RecognitionSettings, body: BodyModel | None,
                   rec: Reconstruction, blobs: dict[str, Blob], feats: dict[str, Features2D],
                   previous: np.ndarray | None, rejection: Rejection) -> Reconstruction:
    """An unresolved mirror ambiguity (the axis near an epipolar plane, the pairings alike, no heads in both
    views, no previous direction) resolved by the known body where that is decisive.

    Both candidate axes, each with the head at either end, are fitted by the body with the axis turned
    in the plane (:class:`.axis_by_length.PlaneScan`); where one hypothesis fits better than every other
    by ``settings.head_body_chi2`` and fits within ``settings.head_body_fit`` per degree of freedom, both
    views claim the head it puts, and the reconstruction is redone (resolved by the heads), taken if it
    passes the same checks and its axis is the fit's (within ``SCAN_HALF_RANGE_DEG``). (Its direction in
    the plane is the triangulated tips', refitted by :func:`axis_by_length` where their length is off: a
    refit of every such frame turned some right ones by 1-2 deg, dev seed 15 robot 6 pose 26.)
    """
    s = settings
    if (body is None or s.estimator == "paper" or rec.direction is not None or not rec.candidates
            or len(rec.candidates) != 2 or not all(np.all(np.isfinite(c)) for c in rec.candidates)
            or rec.plane_angle_deg >= s.min_plane_angle_deg
            or not body.length_mm - body.cone_length_mm >= body.diameter_mm
            or any(feat.reach is None for feat in feats.values())):
        return rec
    normal = plane_normal(calibration, feats)
    clutter = {name: blob.clutter for name, blob in blobs.items()}
    fits = []
    for candidate in rec.candidates:
        for sign in (1.0, -1.0):
            d = sign * candidate / np.linalg.norm(candidate)
            head_index = {}
            for name, feat in feats.items():
                b, _ = ray_line_parameters(calibration.views[name], feat.tips, rec.centroid, d)
                head_index[name] = 0 if b[0] >= b[1] else 1
            scan = PlaneScan(calibration, rec.centroid, d, normal, feats, head_index, clutter, body,
                             s.head_body_cap)
            fits.append((scan.best(), head_index))
    order = sorted(range(len(fits)), key=lambda k: fits[k][0].chi2)
    best, head_index = fits[order[0]]
    runner_up = fits[order[1]][0]
    if not (runner_up.chi2 - best.chi2 >= s.head_body_chi2
            and best.chi2 <= s.head_body_fit * (2 * best.measurements - 6)):
        return centroid_by_body(body, rec, [fit for fit, _ in fits])
    claimed = {name: feat.with_head(head_index[name]) for name, feat in feats.items()}
    try:
        redone = reconstruct(calibration, F, claimed["p"], claimed["q"], s, previous)
    except ValueError:
        return rec
    if (redone.direction is None or not redone.head_identified
            or math.degrees(math.acos(min(1.0, float(redone.direction @ best.direction))))
            > SCAN_HALF_RANGE_DEG
            or rejection(redone, blobs, feats, previous) is not None):
        return rec
    redone.reasons.append(f"the mirror ambiguity is resolved by the body's shape: that axis, the head at its "
                          f"end, fits the body best (chi-square {best.chi2:.1f} against {runner_up.chi2:.1f} "
                          f"for the next)")
    return redone


def centroid_by_body(body: BodyModel | None, rec: Reconstruction, fits: list) -> Reconstruction:
    """An unresolved mirror ambiguity's centroid where the body's fits under every hypothesis agree on it.

    The images' centroids triangulate to the centroid of the attenuation, not the body's: a cone head
    moves it along the axis (standing seed 1234567, robot 6, pose 6: 1.6 mm). The body fitted under
    each mirror hypothesis (:func:`mirror_by_body`) places the centroid; where the fits' centroids lie
    within ``CENTROID_SPREAD_DIAMETERS`` of the body's diameter of each other, their mean is taken (the
    axis stays unknown, the frame ambiguous), and the reason says how far apart they lie; otherwise the
    measured centroid stands (dev seed 3, robot 6, pose 17: fits 2.1 mm apart, their mean 1.2 mm off,
    the images' centroid 0.4 mm; the standing frame above: 0.85 mm apart, the mean 0.06 mm off).
    """
    centroids = np.array([fit.centroid for fit in fits])
    mean = centroids.mean(axis=0)
    spread = float(max(np.linalg.norm(a - b) for a in centroids for b in centroids))
    assert body is not None
    if not np.all(np.isfinite(mean)) or spread > CENTROID_SPREAD_DIAMETERS * body.diameter_mm:
        return rec
    reasons = rec.reasons + [f"the centroid is the body's, fitted under each mirror hypothesis (they lie within "
                             f"{spread:.2f} mm of each other; {float(np.linalg.norm(mean - rec.centroid)):.2f} mm "
                             f"from the images' centroid)"]
    return replace(rec, centroid=mean, reasons=reasons)


def axis_by_length(calibration: Calibration, packed: np.ndarray, settings: RecognitionSettings,
                   body: BodyModel | None, rec: Reconstruction, blobs: dict[str, Blob]) -> Reconstruction:
    """The axis within an epipolar plane refitted by the known body (:mod:`.axis_by_length`) where the
    measured length is off the body's by more than ``settings.plane_length_tolerance``.

    Near an epipolar plane (``settings.min_plane_angle_deg``) the axis planes fix nothing within it and the
    direction there is the triangulated tips': an end run on into another structure turns it (standing
    seed 1234567, robot 6, pose 6: 40 mm measured against 30, 6.5 deg off). The body, its head where
    the reconstruction put it, is fitted with its axis turned in the plane. No direction fitting within
    ``settings.head_body_fit`` per degree of freedom: the frame is reported without an axis (as an
    unresolved mirror ambiguity). The best is taken where the measured direction fits worse by
    ``settings.plane_refit_chi2``, its uncertainty in the plane the axis sigma (for the body prior);
    otherwise the measured direction stands. A body without a flat tail (robot 4) is left alone, as in
    :func:`head_by_body`.
    """
    s = settings
    if (body is None or s.estimator == "paper" or rec.direction is None or not rec.head_identified
            or not body.length_mm - body.cone_length_mm >= body.diameter_mm or rec.length_mm is None
            or rec.plane_angle_deg >= s.min_plane_angle_deg
            or abs(rec.length_mm - body.length_mm) <= s.plane_length_tolerance * body.length_mm):
        return rec
    feats = rec.view_features
    head_index = {name: feat.head_index for name, feat in feats.items()}
    if any(index is None for index in head_index.values()):
        return rec
    normal = plane_normal(calibration, feats)  # type: ignore[arg-type]
    clutter = {name: blob.clutter for name, blob in blobs.items()}
    scan = PlaneScan(calibration, rec.centroid, rec.direction, normal, feats, head_index,  # type: ignore[arg-type]
                     clutter, body, s.head_body_cap)
    if scan.chi2_at_start < s.plane_refit_chi2:
        return rec   # the measured direction fits: no refit could gain enough
    fit = scan.best()
    dof = 2 * fit.measurements - 6
    turned = math.degrees(math.acos(min(1.0, abs(float(fit.direction @ rec.direction)))))
    if fit.chi2 > s.head_body_fit * dof:
        reasons = rec.reasons + [
            f"no axis: it lies within {rec.plane_angle_deg:.1f} deg of an epipolar plane and its ends put the body "
            f"{rec.length_mm:.1f} mm long (the body is {body.length_mm:g} mm), and no direction in the plane "
            f"fits the body (chi-square {fit.chi2:.1f} for {dof} degrees of freedom)"]
        return replace(rec, direction=None, tips=None, head_identified=False, length_mm=None,
                       reprojection_px=None, ambiguous=True, reasons=reasons, candidates=[rec.direction],
                       view_tips={name: feat.tips for name, feat in feats.items()},
                       view_features={name: replace(feat, head_index=None) for name, feat in feats.items()})
    if fit.chi2_at_start - fit.chi2 < s.plane_refit_chi2:
        return rec   # the body does not tell the measured direction from the best
    placed = np.empty(reconstruction_kernels.TIPS_SIZE)
    reconstruction_kernels.place_tips(packed, fit.centroid, fit.direction, feats["p"].tips, head_index["p"],
                                      feats["q"].tips, head_index["q"], feats["p"].centroid, feats["q"].centroid,
                                      placed)
    points = reconstruction_kernels.TIPS_POINTS
    tips = placed[points:points + 6].reshape(2, 3).copy()
    length, reprojection = placed[reconstruction_kernels.TIPS_LENGTH:
                                  reconstruction_kernels.TIPS_REPROJECTION + 1].tolist()
    reasons = rec.reasons + [
        f"the axis is turned {turned:.1f} deg in the epipolar plane by the body: its ends put it "
        f"{rec.length_mm:.1f} mm long (the body is {body.length_mm:g} mm; fit chi-square {fit.chi2:.1f} "
        f"against {fit.chi2_at_start:.1f} as measured; the direction in the plane to {fit.sigma_deg:.1f} deg)"]
    sigma = max(rec.axis_sigma_rad or 0.0, math.radians(fit.sigma_deg))
    return replace(rec, centroid=fit.centroid, direction=fit.direction, tips=tips, length_mm=length,
                   reprojection_px=reprojection if math.isfinite(reprojection) else None, ambiguous=True,
                   reasons=reasons, axis_sigma_rad=sigma)
