"""3D posture from the two views' features: centroid, axis, tips, head, length, reprojection error.

Default (``weighted``) method, built so the orientation is not spoiled by the tips (architecture.md,
known traps):

* centroid: the weighted image centroids, triangulated with the optimal (Hartley-Sturm) correction;
* axis line: each view's 2D axis back-projects to a plane through its source that holds the 3D axis,
  so the axis is the intersection of the two planes through the centroid. (The 2D axis is the blob's
  principal direction in angles about the source, not in pixels: see
  :func:`.reconstruction_kernels._plane_normal`.) When the planes (nearly)
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

The default method's arithmetic runs compiled (:mod:`.reconstruction_kernels`, two calls per frame
pair, issue 8); the decisions that need the features' head models and the operator's sentences stay
here. The paper's method stays in numpy (it is a reference, not the steady-state path).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace

import numpy as np

from appliance.geometry import (
    Calibration,
    View,
    epipolar_distance_px,
    reprojection_error_px,
    triangulate,
)
from appliance.recognition import reconstruction_kernels as kernels
from appliance.recognition.correspondence import CASE_A, CASE_B, Pairing, choose_pairing
from appliance.recognition.features import Features2D
from appliance.recognition.roi_search import _frozen
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
    #: Symmetric epipolar distance (px) of the two views' image centroids (the tracker's correspondence test).
    centroid_epipolar_px: float | None = None
    #: Standard deviation (rad) of the 3D axis direction from the views' axis noise (the default method's),
    #: None where not computed: how far the ends' rays may meet the axis off their place (:mod:`.body_prior`).
    axis_sigma_rad: float | None = None


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of two 3-vectors (np.cross's generality costs ~100x the arithmetic for one pair)."""
    a0, a1, a2 = float(a[0]), float(a[1]), float(a[2])
    b0, b1, b2 = float(b[0]), float(b[1]), float(b[2])
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def axis_plane(view: View, feat: Features2D) -> np.ndarray:
    """The plane ``(n, d)`` through the view's source and the 2D axis line of ``feat`` (its pixel axis: the
    paper's method and the declutter use it; the default method's planes take the principal direction
    in angles, :func:`.reconstruction_kernels._plane_normal`)."""
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
    """The 3D posture from both views' features (see the module docstring for the method).

    ``F`` is the calibration's fundamental matrix (the paper's estimator tests its pairings with it; the
    default one has it packed with the views).
    """
    if settings.estimator == "paper":
        return _reconstruct_paper(calibration, F, feat_p, feat_q, settings, previous_direction)
    return _reconstruct_weighted(calibration, feat_p, feat_q, settings, previous_direction)


def _reconstruct_weighted(calibration: Calibration, feat_p: Features2D, feat_q: Features2D,
                          settings: RecognitionSettings, previous: np.ndarray | None) -> Reconstruction:
    """The default method: the arithmetic in two compiled calls, the decisions on Python objects here."""
    s = settings
    G = calibration.packed
    out = np.empty(kernels.OUT_SIZE)
    sigma_p = _plane_sigma(feat_p, s)
    sigma_q = _plane_sigma(feat_q, s)
    head_p = feat_p.head_index if feat_p.head_index is not None else -1
    head_q = feat_q.head_index if feat_q.head_index is not None else -1
    if previous is not None:
        prev0, prev1, prev2 = previous.tolist()
    else:
        prev0 = prev1 = prev2 = 0.0
    status = kernels.weighted_front(
        G, feat_p.centroid, feat_p.axis, feat_p.tips, feat_q.centroid, feat_q.axis, feat_q.tips,
        feat_p.eigenvalues[0], feat_p.eigenvalues[1], sigma_p, head_p, feat_q.eigenvalues[0], feat_q.eigenvalues[1],
        sigma_q, head_q, prev0, prev1, prev2, previous is not None, s.ambiguity_px, s.min_plane_angle_deg,
        s.max_axis_disagreement_deg, s.min_view_elongation, s.axis_floor_rad, s.tip_sigma_px, s.tip_rim_fraction,
        out)
    return _finish_front(calibration, feat_p, feat_q, settings, previous, status, out)


#: The axis-angle sigma (rad) the compiled front takes for a view that gives no axis plane (its own for a view
#: elongated less than ``min_view_elongation``).
_NO_PLANE_SIGMA_RAD = 1.0


def _in_end_on_band(feat: Features2D, s: RecognitionSettings) -> bool:
    """Whether the view's image is elongated by ``min_view_elongation`` to ``end_on_flag_elongation``."""
    l1, l2 = feat.eigenvalues
    return s.min_view_elongation * l2 <= l1 < s.end_on_flag_elongation * l2


def _plane_withheld(feat: Features2D, s: RecognitionSettings) -> bool:
    """Whether a view in the end-on band gives no axis plane: its own axis sigma is unknown or above
    ``settings.end_on_plane_max_sigma_deg`` where that is set (a stubby body's, robot 4's: its near-round views'
    axes are off by more than their sigmas)."""
    limit = s.end_on_plane_max_sigma_deg
    return limit is not None and _in_end_on_band(feat, s) and (
        feat.axis_sigma_rad is None or math.degrees(feat.axis_sigma_rad) > limit)


def _plane_sigma(feat: Features2D, s: RecognitionSettings) -> float:
    """The view's axis-angle sigma for the compiled front (NaN if unknown; a withheld plane's as none)."""
    if _plane_withheld(feat, s):
        return _NO_PLANE_SIGMA_RAD
    return feat.axis_sigma_rad if feat.axis_sigma_rad is not None else math.nan


def _flagged_end_on(calibration: Calibration, feat_p: Features2D, feat_q: Features2D, s: RecognitionSettings,
                    previous: np.ndarray | None, reasons: list[str]) -> bool:
    """Whether a view seen nearly end-on (its image elongated by ``settings.min_view_elongation`` to
    ``settings.end_on_flag_elongation``) carries the axis: without its plane (as below ``min_view_elongation``)
    the axis would be uncertain beyond ``settings.max_axis_sigma_deg``. Such a view's 2D axis is mostly right
    (robot 6: 0.03 deg) and its plane is taken, but the frame keeps the flag it had without it, with the reason
    appended (on the dev seeds robot 4's frames it unflagged were 0.2-1.7 deg off: median 0.544 -> 0.568 on
    seed 7)."""
    band = [name for name, f in (("p", feat_p), ("q", feat_q)) if _in_end_on_band(f, s) and not _plane_withheld(f, s)]
    if not band:
        return False
    strict = _reconstruct_weighted(calibration, feat_p, feat_q,
                                   s.model_copy(update={"min_view_elongation": s.end_on_flag_elongation}), previous)
    sigma = strict.axis_sigma_rad
    if sigma is not None and math.degrees(sigma) <= s.max_axis_sigma_deg:
        return False
    without = f"{math.degrees(sigma):.1f} deg" if sigma is not None else "far"
    reasons.append(f"the axis rests on view {' and '.join(band)}, which sees the robot nearly end-on (without its "
                   f"axis plane it is uncertain by {without})")
    return True


def reconstruct_from_front(calibration: Calibration, feat_p: Features2D, feat_q: Features2D,
                           settings: RecognitionSettings, previous: np.ndarray | None, status: int,
                           out: np.ndarray) -> Reconstruction:
    """The default method's decisions on what :func:`.reconstruction_kernels.weighted_front` returned
    (``status``) and wrote (``out``, its layout) for these features: the tracker's steady state runs
    the front inside its one compiled call per pair (:mod:`.steady_kernels`) and finishes here. That front
    takes every view's plane from ``min_view_elongation`` up; where a view's is withheld (:func:`_plane_withheld`)
    the front is made again without it (rare: a view seen nearly end-on)."""
    if _plane_withheld(feat_p, settings) or _plane_withheld(feat_q, settings):
        return _reconstruct_weighted(calibration, feat_p, feat_q, settings, previous)
    return _finish_front(calibration, feat_p, feat_q, settings, previous, status, out)


def _finish_front(calibration: Calibration, feat_p: Features2D, feat_q: Features2D, settings: RecognitionSettings,
                  previous: np.ndarray | None, status: int, out: np.ndarray) -> Reconstruction:
    """:func:`reconstruct_from_front` on a front that took the views' planes as :func:`_plane_sigma` says."""
    s = settings
    if status == kernels.STATUS_PLANE_P or status == kernels.STATUS_PLANE_Q:
        name = "p" if status == kernels.STATUS_PLANE_P else "q"
        raise ValueError(f"view {name}: the two pixels coincide; no unique plane through them")
    values = out.tolist()
    rms_a, rms_b = values[kernels.OUT_RMS_A], values[kernels.OUT_RMS_B]
    # Pairing(...) without the frozen dataclass's __init__ (an object.__setattr__ per field).
    pairing = _frozen(Pairing, {"case": CASE_A if rms_a <= rms_b else CASE_B, "rms_a_px": rms_a, "rms_b_px": rms_b,
                                "separated": abs(rms_a - rms_b) >= s.ambiguity_px})
    plane_angle = values[kernels.OUT_PLANE_ANGLE]
    ambiguous = values[kernels.OUT_AMBIGUOUS] == 1.0
    reasons = _front_reasons(values, pairing, plane_angle)
    feats = {"p": feat_p, "q": feat_q}
    epipolar_px = values[kernels.OUT_CENTROID_EPIPOLAR]
    if status == kernels.STATUS_UNRESOLVED:
        candidates = [out[kernels.OUT_CANDIDATES:kernels.OUT_CANDIDATES + 3].copy(),
                      out[kernels.OUT_CANDIDATES + 3:kernels.OUT_CANDIDATES + 6].copy()]
        return Reconstruction(out[kernels.OUT_CENTROID:kernels.OUT_CENTROID + 3].copy(), None, None, False, None, None,
                              pairing, plane_angle, True, reasons, candidates, {"p": feat_p.tips, "q": feat_q.tips},
                              feats, epipolar_px)
    if status == kernels.STATUS_TIPS_DEGENERATE:
        raise ValueError("triangulated tips coincide or lie behind a source")
    sigma_deg = math.degrees(values[kernels.OUT_SIGMA])
    if sigma_deg > s.max_axis_sigma_deg and not ambiguous:
        ambiguous = True
        views = [name for name, f in feats.items()
                 if f.axis_sigma_rad is None or math.degrees(f.axis_sigma_rad) > s.max_axis_sigma_deg]
        where = (f" (the robot is seen nearly end-on, or over another structure, in view {' and '.join(views)})"
                 if views else "")
        reasons.append(f"the axis is uncertain by about {sigma_deg:.1f} deg{where}")
    if not ambiguous:
        ambiguous = _flagged_end_on(calibration, feat_p, feat_q, s, previous, reasons)
    d = out[kernels.OUT_DIRECTION:kernels.OUT_DIRECTION + 3].copy()
    centroid = out[kernels.OUT_CORRECTED:kernels.OUT_CORRECTED + 3].copy()
    plus_index = {"p": int(values[kernels.OUT_PLUS]), "q": int(values[kernels.OUT_PLUS + 1])}
    side = {"p": values[kernels.OUT_SIDE], "q": values[kernels.OUT_SIDE + 1]}
    # Where the views put the head: (how side-on the view sees the axis, the head is the +d end).
    votes = sorted(((side[name], feat.head_index == plus_index[name]) for name, feat in feats.items()
                    if feat.head_index is not None), reverse=True)
    # With the triangulated tips and the axis planes disagreeing (a blob bent or lengthened by clutter),
    # a view's ends may map to the wrong 3D end: unless both views see the head at the same end, the
    # claim is checked against the reprojection below (a wrong claim puts the tips a body length off).
    doubtful = values[kernels.OUT_ENDS_IN_DOUBT] == 1.0 and not (len(votes) > 1 and votes[0][1] == votes[1][1])
    if len(votes) > 1 and votes[0][1] != votes[1][1] and votes[1][0] < s.head_foreshortening * votes[0][0]:
        # A view that sees the axis strongly foreshortened squeezes the cone's ramp into the body's
        # blurred end (and a flat end seen obliquely shows its rim as a ramp): its vote is the weaker
        # evidence, so the side-on view decides.
        votes = votes[:1]
    head_identified = bool(votes) and all(v[1] == votes[0][1] for v in votes)
    if votes and not head_identified:
        reasons.append("the two views disagree on which end is the head")
    flipped = (head_identified and not votes[0][1]) or (not head_identified and previous is not None
                                                         and float(d @ previous) < 0)
    if flipped:
        d = -d
        plus_index = {k: 1 - v for k, v in plus_index.items()}
    # Re-estimate each view's tips with the head's (conical) end model where the head is known, then
    # place both ends on the 3D axis.
    views = {"p": (calibration.p, feat_p), "q": (calibration.q, feat_q)}
    cone_end = None if head_identified else _likely_cone_end(views, plus_index, s)
    view_tips: dict[str, np.ndarray] = {}
    final: dict[str, Features2D] = {}
    for name, feat in feats.items():
        plus = plus_index[name]
        if head_identified:
            feat = _with_head(feat, plus)
        elif cone_end is not None:
            # Tips only: the end whose profile ramps in both views is measured as a cone (apex), the other
            # as a step; the head is still reported as not identified.
            feat = replace(feat.with_head(plus if cone_end == 0 else 1 - plus), head_index=None)
        else:
            feat = _with_head(feat, None)
        final[name] = feat
        view_tips[name] = feat.tips if plus == 0 else feat.tips[::-1]
    if final["p"] is feat_p and final["q"] is feat_q:
        # The tips as measured: the front placed them already (for -d, the same ends in the other order).
        placed = out[kernels.OUT_PLACED:kernels.OUT_PLACED + kernels.TIPS_SIZE]
        tips = placed[kernels.TIPS_POINTS:kernels.TIPS_POINTS + 6].reshape(2, 3)
        tips = tips[::-1].copy() if flipped else tips.copy()
    else:
        placed = np.empty(kernels.TIPS_SIZE)
        kernels.place_tips(calibration.packed, centroid, d, final["p"].tips, plus_index["p"], final["q"].tips,
                           plus_index["q"], feat_p.centroid, feat_q.centroid, placed)
        tips = placed[kernels.TIPS_POINTS:kernels.TIPS_POINTS + 6].reshape(2, 3)
    length, reproj = placed[kernels.TIPS_LENGTH:kernels.TIPS_REPROJECTION + 1].tolist()
    reprojection = reproj if math.isfinite(reproj) else None
    if head_identified and doubtful and (reprojection is None or reprojection > s.head_doubt_reprojection_px):
        # The demoted end keeps its cone-model tip (like the two-view cone-end test); only the claim goes.
        head_identified = False
        final = {name: replace(feat, head_index=None) for name, feat in final.items()}
        reasons.append(f"the head is not claimed: the tips and the axis planes disagree, the ends reproject "
                       f"{reprojection or float('nan'):.1f} px off one line, and the views do not both see the head")
    return Reconstruction(centroid, d, tips, head_identified, length, reprojection, pairing, plane_angle, ambiguous,
                          reasons, None, view_tips, final, epipolar_px, values[kernels.OUT_SIGMA])


def _with_head(feat: Features2D, head_index: int | None) -> Features2D:
    """``feat.with_head(head_index)``, without rebuilding features that already have that head: tips from
    the axial profile (``reach``) are a function of the head's end alone, and rebuilding them (a new
    Features2D per view) was a third of a steady-state frame's reconstruction time. Where they change,
    the tips are :meth:`.Features2D.with_head`'s, in the same operations on plain floats, and the new
    features are made without the frozen dataclass's ``__init__`` (a test compares both ways)."""
    if feat.reach is None:
        return feat.with_head(head_index)
    if feat.head_index == head_index:
        return feat
    (c0, c1), (a0, a1) = feat.centroid.tolist(), feat.axis.tolist()
    d0, d1 = _tip_distance(feat.reach[0], head_index == 0), _tip_distance(feat.reach[1], head_index == 1)
    tips = np.array([[c0 + a0 * d0, c1 + a1 * d0], [c0 - a0 * d1, c1 - a1 * d1]])
    return _frozen(Features2D, {**feat.__dict__, "tips": tips, "head_index": head_index})


def _tip_distance(reach: dict[float, float], conical: bool) -> float:
    """:meth:`.Features2D.tip_distance` of one end from its reaches (the same operations)."""
    if conical:
        cone = (reach[0.25] - reach[0.64]) / (0.8 - 0.5)
        return reach[0.25] + 0.5 * cone
    return reach[0.5]


def _front_reasons(values: list[float], pairing: Pairing, plane_angle: float) -> list[str]:
    """The operator's sentences for what the compiled front found (its reason code)."""
    code = int(values[kernels.OUT_REASON])
    if code == kernels.REASON_NONE:
        return []
    if code == kernels.REASON_PAIRING_CONFLICT:
        implied = CASE_A if values[kernels.OUT_IMPLIED] == 0 else CASE_B
        return [f"the axis planes imply pairing {implied} but the tips' epipolar test says "
                f"{pairing.case} (RMS A {pairing.rms_a_px:.1f} px, B {pairing.rms_b_px:.1f} px)"]
    if code == kernels.REASON_DISAGREEMENT:
        return [f"the axis from the two views' planes and from the triangulated tips differ by "
                f"{values[kernels.OUT_DISAGREEMENT]:.1f} deg"]
    how = {kernels.REASON_BY_HEADS: "resolved by the head seen in both views",
           kernels.REASON_BY_PREVIOUS: "resolved from the previous frames' direction",
           kernels.REASON_UNRESOLVED: "no previous frame to resolve it"}[code]
    return [f"the axis lies within {plane_angle:.1f} deg of an epipolar plane: pairings A and B fit equally well "
            f"(RMS epipolar distance {pairing.rms_a_px:.1f} vs {pairing.rms_b_px:.1f} px); {how}"]


def _reconstruct_paper(calibration: Calibration, F: np.ndarray, feat_p: Features2D, feat_q: Features2D,
                       settings: RecognitionSettings, previous: np.ndarray | None) -> Reconstruction:
    """The seed paper's method: the tips of the pairing chosen by the epipolar test, linearly triangulated."""
    p, q = calibration.p, calibration.q
    centroid, hyps = _hypotheses(calibration, feat_p, feat_q, optimal=False)
    pairing = choose_pairing(F, p.undistort_points(feat_p.tips), q.undistort_points(feat_q.tips),
                             settings.ambiguity_px)
    cross = _cross(axis_plane(p, feat_p)[:3], axis_plane(q, feat_q)[:3])
    plane_angle = math.degrees(math.asin(min(1.0, float(np.linalg.norm(cross)))))
    reasons: list[str] = []
    ambiguous = False
    case: str | None = pairing.case
    if not pairing.separated:
        ambiguous = True
        case, how = _resolve(pairing, hyps, feat_p, feat_q, previous, use_heads=False)
        reasons.append(f"pairings A and B fit equally well (RMS epipolar distance {pairing.rms_a_px:.1f} vs "
                       f"{pairing.rms_b_px:.1f} px); {how}")
        if case is None:
            return Reconstruction(centroid, None, None, False, None, None, pairing, plane_angle, True, reasons,
                                  [_unit(hyps[c][0] - hyps[c][1]) for c in (CASE_A, CASE_B)],
                                  {"p": feat_p.tips, "q": feat_q.tips}, {"p": feat_p, "q": feat_q},
                                  float(epipolar_distance_px(F, p.undistort_points(feat_p.centroid),
                                                             q.undistort_points(feat_q.centroid))[0]))
    d = hyps[case][0] - hyps[case][1]
    if not np.all(np.isfinite(d)) or np.linalg.norm(d) < 1e-9:
        raise ValueError("triangulated tips coincide or lie behind a source")
    rec = _finish_paper(calibration, centroid, _unit(d), hyps[case], feat_p, feat_q, pairing, plane_angle,
                        ambiguous, reasons, previous)
    rec.centroid_epipolar_px = float(epipolar_distance_px(F, p.undistort_points(feat_p.centroid),
                                                          q.undistort_points(feat_q.centroid))[0])
    return rec


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
