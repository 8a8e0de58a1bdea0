"""3D posture from the two views' features: centroid, axis, tips, head, length, reprojection error.

Default (``weighted``) method, built so the orientation is not spoiled by the tips (architecture.md,
known traps):

* centroid: the weighted image centroids, triangulated with the optimal (Hartley-Sturm) correction;
* axis line: each view's 2D axis back-projects to a plane through its source that holds the 3D axis,
  so the axis is the intersection of the two planes through the centroid. When the planes (nearly)
  coincide - the axis lies in an epipolar plane - the line's direction inside that plane comes from the
  triangulated tips of the chosen pairing instead, and the pairing must come from the A/B test, the
  head's asymmetry or the previous frames (the frame is then flagged ``ambiguous``);
* tips: each view's 2D tip back-projects to a ray; its closest point on the axis line gives the tip's
  position along the axis, and the views are averaged with weight ``sin^2`` of the ray-axis angle (a
  ray nearly along the axis says little about where along it the tip is);
* head: the conical end's longer intensity ramp, in whichever views show it, mapped to the same end
  of the 3D axis; views that disagree leave the head unidentified, and so does a single view's claim
  when the tips and the axis planes disagree and the ends reproject badly (its ends may be mapped to
  the wrong 3D end).

The ``paper`` method triangulates the tips of the chosen pairing (linear triangulation) and takes the
axis from them, as in the seed paper.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace

import numpy as np

from appliance.geometry import Calibration, View, reprojection_error_px, triangulate
from appliance.recognition.correspondence import CASE_A, CASE_B, Pairing, choose_pairing
from appliance.recognition.features import Features2D
from appliance.recognition.settings import RecognitionSettings

log = logging.getLogger(__name__)


@dataclass
class Reconstruction:
    """The 3D result of one frame pair (``direction`` None when a mirror ambiguity is unresolved)."""

    centroid: np.ndarray
    direction: np.ndarray | None
    tips: np.ndarray | None  # (2,3), head first when head_identified, else +direction end first
    head_identified: bool
    length_mm: float | None
    reprojection_px: float | None
    pairing: Pairing
    plane_angle_deg: float
    ambiguous: bool = False
    reasons: list[str] = field(default_factory=list)
    candidates: list[np.ndarray] | None = None
    #: Per view, the 2D tips ordered like ``tips`` (head first when identified) and the head's 2D index.
    view_tips: dict[str, np.ndarray] = field(default_factory=dict)
    view_features: dict[str, Features2D] = field(default_factory=dict)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of two 3-vectors (np.cross's generality costs ~100x the arithmetic for one pair)."""
    a0, a1, a2 = float(a[0]), float(a[1]), float(a[2])
    b0, b1, b2 = float(b[0]), float(b[1]), float(b[2])
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def line_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two lines (sign of the directions ignored), degrees."""
    c = abs(float(np.dot(_unit(a), _unit(b))))
    return math.degrees(math.acos(min(1.0, c)))


def axis_plane(view: View, feat: Features2D) -> np.ndarray:
    """The plane ``(n, d)`` through the view's source and the 2D axis line of ``feat``."""
    half = max(2.0, math.sqrt(max(feat.eigenvalues[0], 0.0)))
    return view.backproject_plane(feat.centroid - half * feat.axis, feat.centroid + half * feat.axis)


def ray_line_parameters(view: View, pixels: np.ndarray, point: np.ndarray, direction: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """For each pixel's ray, the parameter ``b`` of its closest point ``point + b direction`` on the line,
    and the weight ``sin^2`` of the ray-line angle (how well the ray pins ``b`` down)."""
    origins, rays = view.rays(pixels)
    k = rays @ direction
    w0 = origins - point
    sin2 = np.maximum(1.0 - k * k, 1e-12)
    b = (w0 @ direction - k * np.einsum("ij,ij->i", w0, rays)) / sin2
    return b, sin2


def fuse_axis(calibration: Calibration, centroid: np.ndarray, feats: dict[str, Features2D], d_tips: np.ndarray,
              settings: RecognitionSettings, normals: dict[str, np.ndarray] | None = None) -> tuple[np.ndarray, float]:
    """The 3D axis that best fits both views' axis planes and the triangulated tips, by their precision.

    Each view says ``n . d = 0`` for its plane's normal ``n``, to within its 2D axis' angular noise times
    the sine of the axis' angle to the view's ray (a plane turning about a ray the axis nearly lies on
    hardly moves the axis); the tips say ``d ~ d_tips`` to within the tip noise over the length. The
    unit ``d`` minimising the weighted squared residuals is the smallest eigenvector of their sum, and
    the inverse square root of the next eigenvalue is its standard deviation (radians) in the worst
    direction.
    Far from an epipolar plane the planes dominate (the tips' rim biases do not reach the axis); in it,
    only the tips can say where in the common plane the axis lies. ``normals``: the views' axis-plane
    normals when the caller has them already.
    """
    sigma_tips = 0.0
    M = np.zeros((3, 3))
    for name, feat in feats.items():
        view = calibration.views[name]
        n = normals[name] if normals is not None else axis_plane(view, feat)[:3]
        ray = _unit(centroid - view.source_mm)
        sin_a = max(float(np.linalg.norm(_cross(ray, d_tips))), 0.05)
        angle_sigma = feat.axis_sigma_rad if feat.axis_sigma_rad is not None else 0.01
        if feat.eigenvalues[0] < settings.min_view_elongation * feat.eigenvalues[1]:
            # A nearly round image (robot seen end-on): the end face's ellipse lies across the short
            # projected axis, so the principal axis says nothing reliable, whatever the noise.
            angle_sigma = 1.0
        sigma = math.hypot(angle_sigma * sin_a, settings.axis_floor_rad)
        M += np.outer(n, n) / sigma ** 2
        # The tips' direction is only as good as the worst view's tips over its image length. Seen
        # obliquely, an end shows its face's rim (an ellipse as long as the diameter times the cosine
        # of the ray-axis angle) along the axis; nearly end-on that dwarfs the image's short length.
        image_length = max(float(np.linalg.norm(feat.tips[0] - feat.tips[1])), 1.0)
        width_px = 4.0 * math.sqrt(max(feat.eigenvalues[1], 0.0))
        cos_a = abs(float(np.dot(ray, d_tips)))
        tip_sigma = math.hypot(settings.tip_sigma_px, settings.tip_rim_fraction * width_px * cos_a)
        sigma_tips = max(sigma_tips, tip_sigma * math.sqrt(2.0) / image_length)
    M += (np.eye(3) - np.outer(d_tips, d_tips)) / sigma_tips ** 2
    values, vectors = np.linalg.eigh(M)
    d = vectors[:, 0]
    sigma = 1.0 / math.sqrt(max(float(values[1] - values[0]), 1e-12))
    return (d if float(np.dot(d, d_tips)) >= 0 else -d), sigma


def _hypotheses(calibration: Calibration, feat_p: Features2D, feat_q: Features2D, optimal: bool
                ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The triangulated centroid, and tips (2,3) for cases A and B; row 0 comes from p's tip 0 (its +axis end).

    One call for all five points: triangulation is per point, and its fixed cost (undistortion, the
    optimal correction, the batched SVD) is most of the time for so few.
    """
    uv_p = np.vstack([feat_p.centroid[None, :], feat_p.tips, feat_p.tips])
    uv_q = np.vstack([feat_q.centroid[None, :], feat_q.tips, feat_q.tips[::-1]])
    X = triangulate(calibration.p, calibration.q, uv_p, uv_q, optimal=optimal)
    return X[0], {CASE_A: X[1:3], CASE_B: X[3:5]}


def _resolve(pairing: Pairing, hyps: dict[str, np.ndarray], feat_p: Features2D, feat_q: Features2D,
             previous: np.ndarray | None, use_heads: bool) -> tuple[str | None, str]:
    """Pick case A/B for an unseparated pairing: by the heads, then by the previous direction."""
    if use_heads and feat_p.head_index is not None and feat_q.head_index is not None:
        case = CASE_A if feat_p.head_index == feat_q.head_index else CASE_B
        return case, "resolved by the head seen in both views"
    if previous is not None:
        scores = {c: abs(float(np.dot(_unit(t[0] - t[1]), previous))) for c, t in hyps.items()
                  if np.all(np.isfinite(t))}
        if scores:
            return max(scores, key=scores.__getitem__), "resolved from the previous frames' direction"
    return None, "no previous frame to resolve it"


def reconstruct(calibration: Calibration, F: np.ndarray, feat_p: Features2D, feat_q: Features2D,
                settings: RecognitionSettings, previous_direction: np.ndarray | None = None) -> Reconstruction:
    """The 3D posture from both views' features (see the module docstring for the method)."""
    p, q = calibration.p, calibration.q
    paper = settings.estimator == "paper"
    centroid, hyps = _hypotheses(calibration, feat_p, feat_q, optimal=not paper)
    pairing = choose_pairing(F, p.undistort_points(feat_p.tips), q.undistort_points(feat_q.tips),
                             settings.ambiguity_px)
    n_p, n_q = axis_plane(p, feat_p)[:3], axis_plane(q, feat_q)[:3]
    cross = _cross(n_p, n_q)
    plane_angle = math.degrees(math.asin(min(1.0, float(np.linalg.norm(cross)))))
    reasons: list[str] = []
    ambiguous = False
    ends_in_doubt = False  # the tips and the axis planes disagree: the 2D ends may map to the wrong 3D ends
    case: str | None = pairing.case
    degenerate = paper or plane_angle < settings.min_plane_angle_deg

    if not degenerate:
        d_planes = _unit(cross)
        # The planes fix the line; the case is the one whose tips run along it.
        implied = min(hyps, key=lambda c: line_angle_deg(hyps[c][0] - hyps[c][1], d_planes)
                      if np.all(np.isfinite(hyps[c])) else 180.0)
        case = implied
        tips_dir = hyps[implied][0] - hyps[implied][1]
        disagreement = line_angle_deg(tips_dir, d_planes) if np.all(np.isfinite(tips_dir)) else 90.0
        if pairing.separated and implied != pairing.case:
            ambiguous = ends_in_doubt = True
            reasons.append(f"the axis planes imply pairing {implied} but the tips' epipolar test says "
                           f"{pairing.case} (RMS A {pairing.rms_a_px:.1f} px, B {pairing.rms_b_px:.1f} px)")
        elif disagreement > settings.max_axis_disagreement_deg:
            ambiguous = ends_in_doubt = True
            reasons.append(f"the axis from the two views' planes and from the triangulated tips differ by "
                           f"{disagreement:.1f} deg")
    elif pairing.separated:
        case = pairing.case
    else:
        ambiguous = True
        what = (f"pairings A and B fit equally well (RMS epipolar distance {pairing.rms_a_px:.1f} vs "
                f"{pairing.rms_b_px:.1f} px)")
        if not paper:
            what = f"the axis lies within {plane_angle:.1f} deg of an epipolar plane: " + what
        case, how = _resolve(pairing, hyps, feat_p, feat_q, previous_direction, use_heads=not paper)
        reasons.append(f"{what}; {how}")
        if case is None:
            return Reconstruction(centroid, None, None, False, None, None, pairing, plane_angle, True, reasons,
                                  [_unit(hyps[c][0] - hyps[c][1]) for c in (CASE_A, CASE_B)],
                                  {"p": feat_p.tips, "q": feat_q.tips}, {"p": feat_p, "q": feat_q})
    assert case is not None
    d = hyps[case][0] - hyps[case][1]
    if not paper and np.all(np.isfinite(d)) and np.linalg.norm(d) > 1e-9:
        d, sigma = fuse_axis(calibration, centroid, {"p": feat_p, "q": feat_q}, _unit(d), settings,
                             {"p": n_p, "q": n_q})
        if math.degrees(sigma) > settings.max_axis_sigma_deg and not ambiguous:
            ambiguous = True
            views = [name for name, f in (("p", feat_p), ("q", feat_q))
                     if f.axis_sigma_rad is None or math.degrees(f.axis_sigma_rad) > settings.max_axis_sigma_deg]
            where = f" (the robot is seen nearly end-on in view {' and '.join(views)})" if views else ""
            reasons.append(f"the axis is uncertain by about {math.degrees(sigma):.1f} deg{where}")
    if not np.all(np.isfinite(d)) or np.linalg.norm(d) < 1e-9:
        raise ValueError("triangulated tips coincide or lie behind a source")
    d = _unit(d)
    if paper:
        return _finish_paper(calibration, centroid, d, hyps[case or pairing.case], feat_p, feat_q, pairing,
                             plane_angle, ambiguous, reasons, previous_direction)
    return _finish_weighted(calibration, centroid, d, feat_p, feat_q, pairing, plane_angle, ambiguous, reasons,
                            previous_direction, settings, ends_in_doubt)


def _finish_paper(calibration: Calibration, centroid: np.ndarray, d: np.ndarray, tips: np.ndarray,
                  feat_p: Features2D, feat_q: Features2D, pairing: Pairing, plane_angle: float, ambiguous: bool,
                  reasons: list[str], previous: np.ndarray | None) -> Reconstruction:
    q_order = [0, 1] if np.dot(tips[0] - tips[1], d) >= 0 else [1, 0]
    tips = tips[q_order]
    # Which q tip went with p's tip 0 is the case; reorder q's 2D tips like the 3D ones.
    case_tips_q = feat_q.tips if pairing.case == CASE_A else feat_q.tips[::-1]
    view_tips = {"p": feat_p.tips[q_order], "q": case_tips_q[q_order]}
    if previous is not None and np.dot(d, previous) < 0:
        d, tips = -d, tips[::-1]
        view_tips = {k: v[::-1] for k, v in view_tips.items()}
    reproj = _reprojection(calibration, centroid, tips, feat_p, feat_q, view_tips)
    return Reconstruction(centroid, d, tips, False, float(np.linalg.norm(tips[0] - tips[1])), reproj, pairing,
                          plane_angle, ambiguous, reasons, None, view_tips, {"p": feat_p, "q": feat_q})


def perspective_corrected_centroid(calibration: Calibration, feats: dict[str, Features2D], centroid: np.ndarray,
                                   d: np.ndarray) -> np.ndarray:
    """Re-triangulate the centroid after removing the perspective bias of each view's weighted centroid.

    A body element at ``s`` along the axis (from the centroid) appears with weight ``~ 1/depth^2`` (more
    rays cross what is nearer the source) at an image position compressed as ``1/depth``; to first order
    the image's weighted centroid is the projection of ``C - 3 k Var / z d``, where ``Var`` is the
    body's mass variance along its axis, ``z`` the source distance and ``k = d . ray``. For a 30 mm
    robot that is 0.3 mm, three times the accuracy we aim for; for a 3 mm robot it is negligible.
    """
    best = None
    for name, feat in feats.items():
        view = calibration.views[name]
        ray = centroid - view.source_mm
        z = float(np.linalg.norm(ray))
        sin2 = 1.0 - float(np.dot(ray / z, d)) ** 2
        mm_per_px = z / float(view.K[0, 0])
        if best is None or sin2 > best[0]:
            best = (sin2, feat.eigenvalues[0] * mm_per_px ** 2 / max(sin2, 1e-6))
    assert best is not None
    variance = best[1]
    corrected = {}
    for name, feat in feats.items():
        view = calibration.views[name]
        ray = centroid - view.source_mm
        z = float(np.linalg.norm(ray))
        shift = -3.0 * float(np.dot(ray / z, d)) * variance / z
        seen, true = view.project(np.vstack([centroid + shift * d, centroid]))
        corrected[name] = feat.centroid + (true - seen)
    return triangulate(calibration.p, calibration.q, corrected["p"], corrected["q"], optimal=True)[0]


def _finish_weighted(calibration: Calibration, centroid: np.ndarray, d: np.ndarray, feat_p: Features2D,
                     feat_q: Features2D, pairing: Pairing, plane_angle: float, ambiguous: bool, reasons: list[str],
                     previous: np.ndarray | None, settings: RecognitionSettings | None = None,
                     ends_in_doubt: bool = False) -> Reconstruction:
    settings = settings or RecognitionSettings()
    views = {"p": (calibration.p, feat_p), "q": (calibration.q, feat_q)}
    centroid = perspective_corrected_centroid(calibration, {"p": feat_p, "q": feat_q}, centroid, d)
    # Which 2D tip of each view is the +d end, and where the views put the head.
    plus_index: dict[str, int] = {}
    votes: list[tuple[float, bool]] = []  # (how side-on the view sees the axis, the head is the +d end)
    for name, (view, feat) in views.items():
        b, _ = ray_line_parameters(view, feat.tips, centroid, d)
        plus_index[name] = 0 if b[0] >= b[1] else 1
        if feat.head_index is not None:
            ray = _unit(centroid - view.source_mm)
            votes.append((float(np.linalg.norm(_cross(ray, d))), feat.head_index == plus_index[name]))
    votes.sort(reverse=True)
    # With the triangulated tips and the axis planes disagreeing (a blob bent or lengthened by clutter),
    # a view's ends may map to the wrong 3D end: unless both views see the head at the same end, the
    # claim is checked against the reprojection below (a wrong claim puts the tips a body length off).
    doubtful = ends_in_doubt and not (len(votes) > 1 and votes[0][1] == votes[1][1])
    if len(votes) > 1 and votes[0][1] != votes[1][1] and votes[1][0] < settings.head_foreshortening * votes[0][0]:
        # A view that sees the axis strongly foreshortened squeezes the cone's ramp into the body's
        # blurred end (and a flat end seen obliquely shows its rim as a ramp): its vote is the weaker
        # evidence, so the side-on view decides.
        votes = votes[:1]
    head_identified = bool(votes) and all(v[1] == votes[0][1] for v in votes)
    if votes and not head_identified:
        reasons.append("the two views disagree on which end is the head")
    if head_identified and not votes[0][1]:
        d = -d
        plus_index = {k: 1 - v for k, v in plus_index.items()}
    elif not head_identified and previous is not None and np.dot(d, previous) < 0:
        d = -d
        plus_index = {k: 1 - v for k, v in plus_index.items()}
    # Re-estimate each view's tips with the head's (conical) end model where the head is known, then
    # place both ends on the 3D axis.
    cone_end = None if head_identified else _likely_cone_end(views, plus_index, settings)
    sums = np.zeros(2)
    weights = np.zeros(2)
    view_tips: dict[str, np.ndarray] = {}
    final: dict[str, Features2D] = {}
    for name, (view, feat) in views.items():
        plus = plus_index[name]
        if head_identified:
            feat = feat.with_head(plus)
        elif cone_end is not None:
            # Tips only: the end whose profile ramps in both views is measured as a cone (apex), the other
            # as a step; the head is still reported as not identified.
            feat = replace(feat.with_head(plus if cone_end == 0 else 1 - plus), head_index=None)
        else:
            feat = feat.with_head(None)
        final[name] = feat
        ordered = feat.tips[[plus, 1 - plus]]
        view_tips[name] = ordered
        b, sin2 = ray_line_parameters(view, ordered, centroid, d)
        sums += b * sin2
        weights += sin2
    b_plus, b_minus = sums / weights
    tips = np.array([centroid + b_plus * d, centroid + b_minus * d])
    reproj = _reprojection(calibration, centroid, tips, final["p"], final["q"], view_tips)
    if head_identified and doubtful and (reproj is None or reproj > settings.head_doubt_reprojection_px):
        # The demoted end keeps its cone-model tip (like the two-view cone-end test); only the claim goes.
        head_identified = False
        final = {name: replace(feat, head_index=None) for name, feat in final.items()}
        reasons.append(f"the head is not claimed: the tips and the axis planes disagree, the ends reproject "
                       f"{reproj or float('nan'):.1f} px off one line, and the views do not both see the head")
    return Reconstruction(centroid, d, tips, head_identified, float(b_plus - b_minus), reproj, pairing,
                          plane_angle, ambiguous, reasons, None, view_tips, final)


def _likely_cone_end(views: dict[str, tuple[View, Features2D]], plus_index: dict[str, int],
                     settings: RecognitionSettings) -> int | None:
    """Which 3D end (0: +d, 1: -d) both views' axial profiles show as a ramp rather than a step, if any.

    Below the head-identification ratio a view's evidence is weak, but where both views see the same 3D
    end ramp longer (each by ``tip_cone_ratio`` and half ``head_min_ramp_px``), a cone there is far
    likelier than a flat end: its apex is placed by the cone model instead of at the profile's half
    height (which falls short of the apex by ~0.7 of the cone's length).
    """
    ends = []
    # Two agreeing views are stronger evidence than one: half the single view's margin each.
    margin = 0.5 * settings.head_min_ramp_px
    for name, (_, feat) in views.items():
        if feat.ramp_px is None:
            return None
        plus = plus_index[name]
        ramp_plus, ramp_minus = feat.ramp_px[plus], feat.ramp_px[1 - plus]
        if ramp_plus >= settings.tip_cone_ratio * max(ramp_minus, 1e-6) and ramp_plus - ramp_minus >= margin:
            ends.append(0)
        elif ramp_minus >= settings.tip_cone_ratio * max(ramp_plus, 1e-6) and ramp_minus - ramp_plus >= margin:
            ends.append(1)
        else:
            return None
    return ends[0] if len(set(ends)) == 1 else None


def _reprojection(calibration: Calibration, centroid: np.ndarray, tips: np.ndarray, feat_p: Features2D,
                  feat_q: Features2D, view_tips: dict[str, np.ndarray]) -> float | None:
    """RMS (px) over centroid and both tips, both views, of projected 3D points against measured 2D ones."""
    X = np.vstack([centroid[None, :], tips])
    uv_p = np.vstack([feat_p.centroid[None, :], view_tips["p"]])
    uv_q = np.vstack([feat_q.centroid[None, :], view_tips["q"]])
    err = reprojection_error_px(calibration.p, calibration.q, X, uv_p, uv_q)
    value = float(np.sqrt(np.mean(err ** 2)))
    return value if math.isfinite(value) else None
