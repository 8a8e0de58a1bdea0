"""Frame-to-frame posture tracking: a region of interest around the prediction, full-frame fallback.

``PostureTracker.process(image_p, image_q, frame=n, t=s)`` runs the whole pipeline on one biplane pair
and returns a :class:`Posture`. While the robot is tracked, each view is searched only inside a region
of interest (ROI) around the constant-velocity prediction of the robot's image, and the background
estimate is a slice of the one computed at the last full-frame detection, so a steady-state frame
touches only a few thousand pixels per view. Both views' searches and the reconstruction's arithmetic
are one compiled call per pair (:mod:`.steady_state`, :mod:`.steady_kernels`); a plain frame (no
ambiguity, no clutter, the head identified, every check passed) has its posture built from that call's
numbers, any other from the blobs and features as :func:`.roi_search.find_in_roi` and
:func:`.reconstruction.reconstruct` give them, with the same result to the last bit. When the ROI
search fails (nothing plausible, the blob reaches the ROI's edge, or it is far from the prediction),
the frame falls back to a full-frame detection, where the background is re-estimated and candidate
blobs of the two views are paired by the epipolar constraint (blobs narrower than any body's image, a
vessel's remainder, are not paired). A frame where that fails too, or whose object is not robot-like
(:mod:`.plausibility`), is reported lost (``ok: false`` with a reason), never with a made-up pose.
Where the views' head claims disagree and only one view overlaps another structure, the clean view's
claim is taken (``_head_by_clean_view``; the reconstruction alone leaves such a head unidentified).
A head claimed by one view alone, over another structure, whose profiles' evidence is weak
(:func:`head_claim_confidence`) is withheld (``_head_in_doubt``): a wrong claim swaps the tips.
Where the robot's body is known, a head left unidentified, or claimed over another structure or by one view
alone, is told by the body's shape where that is decisive (``_head_by_body``, :mod:`.head_by_body`); that and
the body's other corrections of a reconstruction (an unresolved mirror ambiguity, an axis in an epipolar plane whose length is
off the body's) are :mod:`.body_corrections`.
A tracker given the robot's body (``body=``, with ``settings.body_prior``) places the centroid and tips
of every ok posture by it (:func:`.body_prior.place_body`; on the plain frames' postures within the pair's
compiled call, :func:`.steady_kernels._place_body`: the same compiled arithmetic on the same numbers).
On the general path each view's blob is weighed against the body (:mod:`.body_mass`): a view heavier than
the body, the other clean, has another structure merged into it, its moment centroid's possible slide is
given to the placement (the ends place the body) and the frame is flagged.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, replace

import numpy as np

from appliance.errors import InputDataError
from appliance.geometry import (
    Calibration,
    epipolar_distance_px,
    fundamental_matrix,
    triangulate,
)
from appliance.geometry_kernels import project_segment
from appliance.recognition import body_corrections
from appliance.recognition.body_mass import centroid_slide_mm, heavy_view, pixel_scales_mm, view_masses_mm2
from appliance.recognition.body_prior import BodyModel, end_clutter, ends_used, place_body
from appliance.recognition.correspondence import pair_candidates, pairing_rms
from appliance.recognition.detection import detect
from appliance.recognition.features import Features2D, features
from appliance.recognition.plausibility import (
    at_odds_with_track,
    cut_by_edge,
    declutter,
    not_robot_like,
    off_its_images,
    narrower_than_body,
    part_of_body,
)
from appliance.recognition.posture import Posture, ViewObservation
from appliance.recognition.reconstruction import (
    Reconstruction,
    reconstruct,
    reconstruct_from_front,
)
from appliance.recognition.roi_search import _frozen, find_in_roi
from appliance.recognition.segmentation import (
    Blob,
    LogBackground,
    Roi,
    log_background,
    the_one_clean_view,
)
from appliance.recognition.settings import RecognitionSettings
from appliance.recognition.steady_state import SteadyPair

log = logging.getLogger(__name__)

VIEWS = ("p", "q")
_NO_DIRECTION = (0.0, 0.0, 0.0)
_NO_OUTLINES: dict[str, tuple[float, float, float, float, float, float, float]] = {}


def _image_length_px(feat: Features2D) -> float:
    (u0, v0), (u1, v1) = feat.tips.tolist()
    return math.hypot(u0 - u1, v0 - v1)


@dataclass(slots=True)
class _Track:
    """What the tracker remembers of the last recognised frames (a plain steady frame updates it in place)."""

    t: float
    #: The centroid (mm) and velocity (mm/s, zero until two frames are known) as plain floats: the
    #: prediction and the velocity are a few operations on three numbers, where numpy's per-call
    #: overhead would be most of the cost (the same IEEE operations either way).
    centroid: tuple[float, float, float]
    direction: np.ndarray | None
    length_mm: float | None
    velocity: tuple[float, float, float]
    lost_frames: int = 0
    #: Per view, the last image's centroid and ends and the body's half width (px, plain floats): the ROI
    #: must hold the whole blob with room for the segmentation's ring and fill across it, also for a wide
    #: robot (#6 is ~25 px wide at 1024 px) and when the 3D axis is unknown (unresolved mirror ambiguity).
    view_outline_px: dict[str, tuple[float, float, float, float, float, float, float]] | None = None
    #: ``direction`` as plain floats (None with it), for the next frame's prediction.
    direction_xyz: tuple[float, float, float] | None = None
    #: The heading a head claim is checked against (:func:`.plausibility.at_odds_with_track`): the direction of
    #: the last frame whose head was identified, or of a later one whose head was not, its sign chosen to agree
    #: with that heading (None until a head is identified). ``direction`` is no heading: an unclaimed frame's
    #: sign is arbitrary (a cold frame's, or a withdrawn claim's), and taken as one it had a right claim on the
    #: next frame rejected, or a wrong one passed.
    heading: np.ndarray | None = None


#: While tracking, a view's noise sigma is measured on one ROI and reused for the next frames (same
#: detector, same dose); measured again every this many frames so that a change of dose is followed.
NOISE_REMEASURE_FRAMES = 30


def head_claim_confidence(views: dict[str, tuple[Features2D, float, int | None]], floor_px: float) -> float:
    """How strongly the views' axial profiles say the claimed end is the head: per view, the ramp at the
    claimed end less the one at the other end, in units of ``floor_px`` plus the view's clutter times its
    longer ramp, summed over the views (a view leaning the other way subtracts).

    ``views`` maps a view to (its features, its :attr:`.Blob.clutter`, the claimed end's 2D index). The
    background under a body over another structure slopes along it by about the clutter fraction of the
    body's contrast, so a level crossing on a ramp moves by about that fraction of the ramp's length; a
    clean view's ramps are uncertain by the blur and the crossings' interpolation (``floor_px``). A view
    that claims no head still leans one way, and on a foreshortened or small image that lean is weak
    evidence that counts here (a wrong claim over a vessel had the clean view leaning the other way).
    """
    total = 0.0
    for feat, clutter, head in views.values():
        if head is None:
            continue
        at_head, other = feat.ramp_px[head], feat.ramp_px[1 - head]
        total += (at_head - other) / (floor_px + max(clutter, 0.0) * max(at_head, other))
    return total


def _for_body(settings: RecognitionSettings, body: BodyModel | object | None) -> RecognitionSettings:
    """The settings the tracker of ``body`` works with: a robot at least
    ``settings.along_structure_min_diameter_mm`` wide has its background interpolated along structure
    (``background_along_structure``; why: that setting's comment); a robot shorter than
    ``settings.end_on_plane_min_aspect`` times its diameter takes the axis plane of a view elongated less than
    ``settings.end_on_flag_elongation`` only where that view's axis sigma is at most
    ``settings.stubby_end_on_max_sigma_deg`` (``end_on_plane_max_sigma_deg``; why: that setting's comment).
    Without a known body, with the body prior off (the tracker given the body is then the model-free one) and
    for the paper's estimator (a reference, kept as it was), as given."""
    if body is None or settings.estimator == "paper" or not settings.body_prior:
        return settings
    update: dict[str, object] = {}
    diameter = getattr(body, "diameter_mm", None)
    if (diameter is not None and not settings.background_along_structure
            and float(diameter) >= settings.along_structure_min_diameter_mm):
        update["background_along_structure"] = True
    length = getattr(body, "length_mm", None)
    if (diameter is not None and length is not None and float(length) < settings.end_on_plane_min_aspect * float(diameter)
            and settings.end_on_plane_max_sigma_deg is None):
        update["end_on_plane_max_sigma_deg"] = settings.stubby_end_on_max_sigma_deg
    return settings.model_copy(update=update) if update else settings


class PostureTracker:
    """Recognises the robot's posture in successive biplane frame pairs (see the module docstring)."""

    def __init__(self, calibration: Calibration, settings: RecognitionSettings | None = None,
                 body: BodyModel | object | None = None) -> None:
        self.calibration = calibration
        self.settings = _for_body(settings or RecognitionSettings(), body)
        #: The robot's body (a :class:`.BodyModel`, or a catalogue :class:`appliance.robots.RobotSpec`) where
        #: the centroid and tips are placed by it (``settings.body_prior``); None: model-free.
        self.body: BodyModel | None = None
        if body is not None and self.settings.body_prior:
            self.body = body if isinstance(body, BodyModel) else BodyModel.of(body)
        self.F = fundamental_matrix(calibration.p, calibration.q)
        #: Both views packed for the compiled kernels (the calibration is immutable).
        self._packed = calibration.packed
        #: Each view's image shape (rows, columns) as the calibration gives it (process's input check).
        self._shapes = tuple((view.image_size[1], view.image_size[0]) for view in (calibration.p, calibration.q))
        #: The steady state's one compiled call per pair, and its output for the last frame if that one was
        #: found by it and remembered (what the lean pass starts from). It places the plain frames' postures
        #: by the body.
        self._pair = SteadyPair(calibration, self.settings, self.body)
        self._lean_from: np.ndarray | None = None
        self._log_bg: dict[str, LogBackground] = {}
        self._track: _Track | None = None
        self._last_search = "none"
        # Per view: the background a ROI's noise sigma was measured against, the sigma, and how many
        # frames it has served (entries are tied to the background object, so reset() need not clear them).
        self._roi_noise: dict[str, tuple[LogBackground, float, int]] = {}

    def reset(self) -> None:
        """Forget the history and the cached backgrounds (the next frame is a full-frame detection)."""
        self._log_bg.clear()
        self._track = None
        self._lean_from = None

    @property
    def tracking(self) -> bool:
        """True while the last frames give a prediction, i.e. the next frame searches ROIs first."""
        return self._track is not None

    @property
    def last_search(self) -> str:
        """How the last frame was searched: ``"roi"``, ``"full"`` or ``"none"`` (for tests and diagnostics)."""
        return self._last_search

    # ---------------------------------------------------------------------------------------- API
    def process(self, image_p: np.ndarray, image_q: np.ndarray, *, frame: int = 0, t: float = 0.0) -> Posture:
        """Recognise the robot in one biplane pair (raw detector intensities, robot darker than surroundings)."""
        # The usual input (an array of the calibrated size) passes without _checked's messages being made ready.
        if type(image_p) is not np.ndarray or image_p.shape != self._shapes[0]:
            self._checked(image_p, "p", frame)
        if type(image_q) is not np.ndarray or image_q.shape != self._shapes[1]:
            self._checked(image_q, "q", frame)
        timings = {"segmentation": 0.0, "features": 0.0, "correspondence": 0.0, "triangulation": 0.0}
        front: tuple[int, np.ndarray] | None = None
        found = None
        paired = False
        if self._track is not None:
            paired = self._search_pair(image_p, image_q, t, timings)
            if paired:
                pair = self._pair
                start = time.perf_counter_ns()
                plain = pair.plain_posture(frame, t, timings)
                if plain is not None:
                    # A plain frame: the posture the decisions below make (and the body prior, where the
                    # tracker has a body), built from the call's numbers.
                    timings["triangulation"] = (time.perf_counter_ns() - start) / 1e3
                    self._remember_plain(t, plain.direction)
                    self._lean_from = pair.out
                    return plain
                (blob_p, blob_q), (feat_p, feat_q), status, out = pair.objects()
                found = {"p": blob_p, "q": blob_q}, {"p": feat_p, "q": feat_q}
                front = (status, out) if status is not None else None
            else:
                found = self._search_rois({"p": image_p, "q": image_q}, t, timings)
        if found is None:
            found, failure = self._search_full({"p": image_p, "q": image_q}, timings)
            if found is None:
                self._lose()
                posture = Posture.lost(frame, t, failure)
                posture.timings_us = timings
                return posture
        blobs, feats = found
        start = time.perf_counter_ns()
        previous = self._track.direction if self._track is not None else None
        try:
            if front is not None:
                rec = reconstruct_from_front(self.calibration, feats["p"], feats["q"], self.settings, previous, *front)
            else:
                rec = reconstruct(self.calibration, self.F, feats["p"], feats["q"], self.settings, previous)
            rec = self._head_by_clean_view(rec, blobs, feats, previous)
            rec = self._head_in_doubt(rec, blobs, feats)
        except ValueError as err:
            self._lose()
            posture = Posture.lost(frame, t, f"reconstruction failed: {err}")
            posture.timings_us = timings
            return posture
        timings["triangulation"] = (time.perf_counter_ns() - start) / 1e3
        failure = self._rejection(rec, blobs, feats, previous)
        if failure is not None:
            # The two blobs are not images of one object: reporting a pose would be inventing one.
            log.debug("frame %d rejected: %s", frame, failure)
            self._lose()
            posture = Posture.lost(frame, t, failure)
            posture.timings_us = timings
            return posture
        rec = self._head_by_body(rec, blobs, feats, previous)
        rec = self._mirror_by_body(rec, blobs, feats, previous)
        rec = self._axis_by_length(rec, blobs)
        rec = declutter(self.calibration, rec, blobs, self.settings)
        posture = self._posture(frame, t, rec, blobs)
        if self.body is not None:
            posture = self._placed(posture, rec, blobs, {"p": image_p, "q": image_q})
        posture.timings_us = timings
        self._remember(posture)
        self._lean_from = self._pair.out if paired else None
        return posture

    # ----------------------------------------------------------------------------------- searches
    def _checked(self, image: np.ndarray, name: str, frame: int) -> np.ndarray:
        w, h = self.calibration.views[name].image_size
        if not isinstance(image, np.ndarray) or image.ndim != 2:
            raise InputDataError(f"frame {frame}, view {name}: expected a 2D grayscale image, "
                                 f"got shape {getattr(image, 'shape', None)}")
        if image.shape != (h, w):
            raise InputDataError(f"frame {frame}, view {name}: image is {image.shape[1]}x{image.shape[0]} px "
                                 f"but the calibration says {w}x{h}")
        return image

    def _features(self, blob: Blob) -> Features2D:
        return features(blob, self.settings)

    def _search_pair(self, image_p: np.ndarray, image_q: np.ndarray, t: float, timings: dict[str, float]) -> bool:
        """:meth:`_search_rois` and the reconstruction's front in one compiled call (:mod:`.steady_state`): True
        if both views were found (the results are in ``self._pair``), False where that call does not apply or
        a view is not plainly found (then :meth:`_search_rois`)."""
        track = self._track
        assert track is not None
        log_bg = self._log_bg
        bg_p, bg_q = log_bg.get("p"), log_bg.get("q")
        pair = self._pair
        if not pair.usable(image_p, image_q, bg_p, bg_q):
            return False
        assert bg_p is not None and bg_q is not None
        # The prediction as _search_rois makes it (the projection and the ROIs are in the call).
        dt = t - track.t
        (x, y, z), (vx, vy, vz) = track.centroid, track.velocity
        half = 0.5 * (track.length_mm or 0.0) + 1.0
        previous = track.direction_xyz
        outlines = track.view_outline_px or _NO_OUTLINES
        # Per view, the noise sigma to reuse (None: measure it) and how many frames it will have served.
        noise = self._roi_noise
        known_p, known_q = noise.get("p"), noise.get("q")
        sigma_p, served_p = ((known_p[1], known_p[2] + 1) if known_p is not None and known_p[0] is bg_p
                             and known_p[2] < NOISE_REMEASURE_FRAMES else (None, 1))
        sigma_q, served_q = ((known_q[1], known_q[2] + 1) if known_q is not None and known_q[0] is bg_q
                             and known_q[2] < NOISE_REMEASURE_FRAMES else (None, 1))
        start = time.perf_counter_ns()
        lean_from = self._lean_from if self.settings.lean_steady_state else None
        found = pair.search(image_p, image_q, bg_p, bg_q, (x + vx * dt, y + vy * dt, z + vz * dt),
                            previous or _NO_DIRECTION, half, outlines.get("p"), outlines.get("q"), sigma_p, sigma_q,
                            previous, lean_from, track.centroid, self._lean_from)
        if not found:
            return False
        used_p, used_q = pair.sigmas()
        noise["p"] = (bg_p, used_p, served_p)
        noise["q"] = (bg_q, used_q, served_q)
        # Both views' search and the reconstruction's front are one call: timed as segmentation.
        timings["segmentation"] += (time.perf_counter_ns() - start) / 1e3
        self._last_search = "roi"
        return True

    def _search_rois(self, images: dict[str, np.ndarray], t: float, timings: dict[str, float]
                     ) -> tuple[dict[str, Blob], dict[str, Features2D]] | None:
        track = self._track
        assert track is not None
        # The constant-velocity prediction in plain floats (the same IEEE operations as on the arrays,
        # without numpy's per-call overhead on three numbers).
        dt = t - track.t
        (x, y, z), (vx, vy, vz) = track.centroid, track.velocity
        c0, c1, c2 = x + vx * dt, y + vy * dt, z + vz * dt
        half = 0.5 * (track.length_mm or 0.0) + 1.0
        d0, d1, d2 = track.direction_xyz or _NO_DIRECTION
        # The robot's centre and ends, predicted, in both views ([view][centre, end, end][u, v]): one
        # compiled call, read as plain floats.
        projected = project_segment(self._packed, c0, c1, c2, d0, d1, d2, half).tolist()
        # Per view: (the background it was measured against, noise sigma, frames it has served). A new
        # background (reset, full-frame search) means a new measurement.
        noise = self._roi_noise
        blobs: dict[str, Blob] = {}
        feats: dict[str, Features2D] = {}
        start = time.perf_counter_ns()
        for index, name in enumerate(VIEWS):
            (pu, pv), (eu0, ev0), (eu1, ev1) = projected[index]
            margin = float(self.settings.roi_margin_px)
            outline = track.view_outline_px.get(name) if track.view_outline_px else None
            if outline is not None:
                # The last frame's 2D ends, moved with the predicted image centroid (the 3D ends at the
                # centroid +- half the length miss where a cone puts the centroid off the middle: 5.7 mm
                # on robot 6), and the margin counted from the body's edge, not its axis.
                cu, cv, u0, v0, u1, v1, half_width = outline
                du, dv = pu - cu, pv - cv
                eu0, ev0, eu1, ev1 = u0 + du, v0 + dv, u1 + du, v1 + dv
                margin += half_width
            roi = Roi.around_coordinates((pu, eu0, eu1), (pv, ev0, ev1), margin, images[name].shape)
            log_bg = self._log_bg.get(name)
            if roi is None or log_bg is None:
                return None
            known = noise.get(name)
            reuse = known is not None and known[0] is log_bg and known[2] < NOISE_REMEASURE_FRAMES
            found = find_in_roi(images[name], log_bg, roi, self.settings, (pu, pv),
                                sigma=known[1] if reuse and known is not None else None)
            if found is None:
                log.debug("view %s: robot not found in ROI %s; falling back to full frame", name, roi)
                return None
            blobs[name], feats[name] = found
            noise[name] = (log_bg, found[0].sigma, known[2] + 1 if reuse and known is not None else 1)
        # One compiled call per view finds the blob and its features (roi_search): both are timed as
        # segmentation here.
        timings["segmentation"] += (time.perf_counter_ns() - start) / 1e3
        self._last_search = "roi"
        return blobs, feats

    def _search_full(self, images: dict[str, np.ndarray], timings: dict[str, float]
                     ) -> tuple[tuple[dict[str, Blob], dict[str, Features2D]] | None, str]:
        start = time.perf_counter_ns()
        candidates: dict[str, list[Blob]] = {}
        for name in VIEWS:
            self._log_bg[name] = log_background(images[name], self.settings.background_scale_px,
                                                 self.settings.dark_level)
            candidates[name] = detect(images[name], self._log_bg[name], self.settings)
        timings["segmentation"] += (time.perf_counter_ns() - start) / 1e3
        self._last_search = "full"
        missing = [name for name in VIEWS if not candidates[name]]
        if missing:
            return None, f"no robot-like object in view {' and '.join(missing)}"
        start = time.perf_counter_ns()
        pairs = pair_candidates(self.calibration, self.F,
                                [b.centroid_px for b in candidates["p"]], [b.centroid_px for b in candidates["q"]],
                                [b.strength for b in candidates["p"]], [b.strength for b in candidates["q"]],
                                self.settings.epipolar_band_px)
        timings["correspondence"] += (time.perf_counter_ns() - start) / 1e3
        bodies = self._bodies_only(pairs, candidates)
        if pairs and not bodies:
            return None, (f"the only objects seen in both views are narrower than "
                          f"{self.settings.min_body_width_px:g} px across (the remainder of a vessel under an "
                          f"interpolated background), not a body")
        pairs, faint = self._metal_only(bodies, candidates)
        if not pairs and faint:
            return None, (f"the only objects seen in both views attenuate {faint:.2f}/mm, like contrast "
                          f"medium, not like the robot (>= {self.settings.min_attenuation_per_mm:g}/mm)")
        if not pairs:
            return None, (f"no pair of candidates satisfies the epipolar constraint within "
                          f"{self.settings.epipolar_band_px:g} px ({len(candidates['p'])} in p, "
                          f"{len(candidates['q'])} in q)")
        # Several pairs may pass the centroid test (a vessel end-on in one view, say); the robot's
        # tips must pair up along epipolar lines too, which a chance coincidence of centroids does not.
        start = time.perf_counter_ns()
        best: tuple[float, dict[str, Blob], dict[str, Features2D]] | None = None
        for i, j, distance in pairs:
            blobs = {"p": candidates["p"][i], "q": candidates["q"][j]}
            feats = {name: self._features(blobs[name]) for name in VIEWS}
            if len(pairs) == 1:
                best = (0.0, blobs, feats)
                break
            rms = pairing_rms(self.F, self.calibration.p.undistort_points(feats["p"].tips),
                              self.calibration.q.undistort_points(feats["q"].tips))
            width, strength = self._size_mismatch(blobs)
            cost = (min(rms) + distance + self.settings.width_mismatch_px * width
                    + self.settings.strength_mismatch_px * strength)
            if best is None or cost < best[0]:
                best = (cost, blobs, feats)
        timings["features"] += (time.perf_counter_ns() - start) / 1e3
        assert best is not None
        return (best[1], best[2]), ""

    def _size_mismatch(self, blobs: dict[str, Blob]) -> tuple[float, float]:
        """``|log|`` of the ratio of the two blobs' widths in mm, and of their integrated attenuations in
        mm^2, at the pair's triangulated position (0, 0 where it has none).

        A rod's projected width is its diameter from any direction (end-on it is a disc of that
        diameter), so the robot's two images agree; a vessel seen end-on in one view (as wide as its
        lumen) paired with the robot in the other does not, even when its centroid and ends happen to
        lie on the robot's epipolar lines. The sum of an object's line integrals over its image, times
        the pixel's area at the object, is its attenuation integrated over its volume, the same in both
        views; a piece of vessel split off beside the robot in one view (robot 3 over the vessel: 0.25
        of the robot's strength in the other view, the robot's own blob 1.2) does not match it either.
        """
        X = triangulate(self.calibration.p, self.calibration.q, blobs["p"].centroid_px, blobs["q"].centroid_px,
                        optimal=False)[0]
        if not np.all(np.isfinite(X)):
            return 0.0, 0.0
        scales = pixel_scales_mm(self.calibration, X)
        widths = [blob.width_px * scales[name] for name, blob in blobs.items()]
        strengths = list(view_masses_mm2(self.calibration, blobs, scales=scales).values())
        return (abs(math.log(max(widths[0], 1e-6) / max(widths[1], 1e-6))),
                abs(math.log(max(strengths[0], 1e-12) / max(strengths[1], 1e-12))))

    def _bodies_only(self, pairs: list[tuple[int, int, float]], candidates: dict[str, list[Blob]]
                     ) -> list[tuple[int, int, float]]:
        """Drop pairs with a blob narrower than any body's image (``settings.min_body_width_px``).

        Where a candidate is a piece of contrast-filled vessel, the attenuation beside it interpolated
        under it can leave only a ridge one pixel wide as its weights: such a blob has no width to judge
        its attenuation per mm by (:meth:`_metal_only` would divide by that pixel) and, a piece of one
        3D vessel seen in both views, its two images can pair up along epipolar lines better than the
        robot's short, round blobs do (robot 4, 3 x 1.5 mm: tips 3.4 px RMS against the vessel's 0.4
        px; the vessel pair was reported 7.4 mm from the robot).
        """
        floor = self.settings.min_body_width_px
        return [(i, j, distance) for i, j, distance in pairs
                if candidates["p"][i].width_px >= floor and candidates["q"][j].width_px >= floor]

    def _metal_only(self, pairs: list[tuple[int, int, float]], candidates: dict[str, list[Blob]]
                    ) -> tuple[list[tuple[int, int, float]], float]:
        """Drop pairs whose blobs attenuate too weakly per mm of their width to be the (metal) robot.

        A cylinder's peak attenuation is ``mu D``; the width ``D`` in mm follows from the blob's width in
        pixels and the magnification at the pair's triangulated position. A contrast-filled vessel seen
        from the side has a small ``mu``; seen end-on it is strong in that view, but not in the other.
        Returns the kept pairs and, if none is kept, the strongest rejected attenuation (/mm).
        """
        kept, strongest = [], 0.0
        for i, j, distance in pairs:
            blobs = {"p": candidates["p"][i], "q": candidates["q"][j]}
            X = triangulate(self.calibration.p, self.calibration.q, blobs["p"].centroid_px, blobs["q"].centroid_px,
                            optimal=False)[0]
            if not np.all(np.isfinite(X)):
                continue
            mu = min(blob.peak / (blob.width_px * float(np.linalg.norm(X - self.calibration.views[name].source_mm))
                                  / float(self.calibration.views[name].K[0, 0]))
                     for name, blob in blobs.items())
            if mu >= self.settings.min_attenuation_per_mm:
                kept.append((i, j, distance))
            else:
                strongest = max(strongest, mu)
        return kept, strongest

    def _centroid_mismatch_px(self, feats: dict[str, Features2D]) -> float:
        cp = self.calibration.p.undistort_points(feats["p"].centroid)
        cq = self.calibration.q.undistort_points(feats["q"].centroid)
        return float(epipolar_distance_px(self.F, cp, cq)[0])

    def _rejection(self, rec: Reconstruction, blobs: dict[str, Blob], feats: dict[str, Features2D],
                   previous: np.ndarray | None) -> str | None:
        """Why the two views' blobs are not images of one robot-like object (the frame is then lost), or None."""
        mismatch = rec.centroid_epipolar_px
        if mismatch is None:
            mismatch = self._centroid_mismatch_px(feats)
        tips_rms = min(rec.pairing.rms_a_px, rec.pairing.rms_b_px)
        if mismatch > self.settings.epipolar_band_px:
            return (f"the robot images of the two views do not correspond (centroids {mismatch:.1f} px from "
                    f"each other's epipolar lines)")
        if tips_rms > self.settings.tips_band_px and tips_rms > max(
                self.settings.tips_band_px, self.settings.tips_band_fraction * max(
                    _image_length_px(f) for f in feats.values())):
            return (f"the robot images' ends do not correspond in either pairing (RMS epipolar distance "
                    f"{tips_rms:.1f} px); one view's blob is not (only) the robot")
        return (not_robot_like(self.calibration, rec, blobs, self.settings)
                or cut_by_edge(self.calibration, blobs)
                or off_its_images(self.calibration, rec, blobs, self.settings)
                or part_of_body(rec, self.body, self.settings)
                or narrower_than_body(self.calibration, rec, blobs, self.body, self.settings)
                or at_odds_with_track(rec, blobs, self._track.heading if self._track else None,
                                      self._track.length_mm if self._track else None, self.settings))

    def _head_by_clean_view(self, rec: Reconstruction, blobs: dict[str, Blob], feats: dict[str, Features2D],
                            previous: np.ndarray | None) -> Reconstruction:
        """The head as the clean view sees it, where the views' claims disagree and only the other view
        overlaps another structure.

        The head is told by the axial profile: the cone's end ramps, the flat end steps. In a view where
        the body overlaps a vessel (clutter above ``settings.max_clutter``) the background interpolated
        under it slopes along the axis, and the end that meets the vessel runs on into it or is cut by
        it: that view's ramps measure the vessel's edge, not the cone. A clean view's profile has none of
        this, so where the two claims point to opposite 3D ends the clean view's claim is taken. Left
        unidentified, both ends are measured as flat and the cone's apex falls short by ~0.7 of the
        cone's length (robots 2, 3, 5, 7: 2 to 5.5 mm). The reconstruction is redone with the cluttered
        view's claim withdrawn; its own checks (the ends' reprojection when the tips and the axis planes
        disagree) still apply, and the first result stands if the redone one claims no head or leaves
        the axis unresolved.
        """
        if (rec.head_identified or rec.direction is None or self.settings.estimator == "paper"
                or any(feat.head_index is None for feat in feats.values())):
            return rec
        clean = the_one_clean_view(blobs, self.settings.max_clutter)
        if clean is None:
            return rec
        cluttered = "q" if clean == "p" else "p"
        withdrawn = dict(feats)
        withdrawn[cluttered] = replace(feats[cluttered], head_index=None)
        redone = reconstruct(self.calibration, self.F, withdrawn["p"], withdrawn["q"], self.settings, previous)
        if not redone.head_identified or redone.direction is None:
            return rec
        redone.reasons.append(f"the head is view {clean}'s: view {cluttered}, over another structure, "
                              f"saw it at the other end")
        return redone

    def _head_in_doubt(self, rec: Reconstruction, blobs: dict[str, Blob],
                       feats: dict[str, Features2D]) -> Reconstruction:
        """The head claim withheld where it rests on one view over another structure and its confidence
        (:func:`head_claim_confidence`) is below ``settings.head_claim_min_confidence``, or, the body known, the
        ends measured are off the body's length by more than ``settings.head_claim_max_length_error`` (the blob
        ran on into the structure or lost an end: the "ramp" claimed is the structure's, seed 3162277 robot 3
        pose 5, a 53 px ramp at a run-on end, 31.3 mm against the body's 19).

        A wrong claim swaps the tips (a body length of tip error); an unidentified head leaves both
        orders open, and the tips keep what the reconstruction measured (the end claimed keeps its
        cone-model tip, as the reconstruction's own demotion does). Claims by a clean view, or by both
        views, are left alone, so a plain frame (no clutter, :mod:`.steady_state`) never reaches this.
        """
        if not rec.head_identified or self.settings.estimator == "paper" or not rec.view_features:
            return rec
        voters = [name for name in VIEWS if feats[name].head_index is not None]
        if len(voters) != 1 or not blobs[voters[0]].clutter > self.settings.max_clutter:
            return rec
        final = {name: replace(feat, head_index=None) for name, feat in rec.view_features.items()}
        body_length = self.body.length_mm if self.body is not None else None
        if (body_length and rec.length_mm is not None
                and abs(rec.length_mm / body_length - 1.0) > self.settings.head_claim_max_length_error):
            reasons = rec.reasons + [f"the head is not claimed: only view {voters[0]}, over another structure, sees "
                                     f"it, and the ends measured are {rec.length_mm:.1f} mm apart, not the body's "
                                     f"{body_length:g} mm (the blob runs on into the structure or lost an end to it)"]
            return replace(rec, head_identified=False, view_features=final, reasons=reasons)
        confidence = head_claim_confidence(
            {name: (feats[name], blobs[name].clutter, rec.view_features[name].head_index) for name in VIEWS},
            self.settings.head_ramp_floor_px)
        if confidence >= self.settings.head_claim_min_confidence:
            return rec
        reasons = rec.reasons + [f"the head is not claimed: only view {voters[0]}, over another structure, sees it, "
                                 f"and the evidence is weak ({confidence:.2f} of the "
                                 f"{self.settings.head_claim_min_confidence:g} needed, the other view's ramps "
                                 f"included)"]
        return replace(rec, head_identified=False, view_features=final, reasons=reasons)

    # The corrections by the known body (:mod:`.body_corrections`), given what they need explicitly.
    def _head_by_body(self, rec: Reconstruction, blobs: dict[str, Blob], feats: dict[str, Features2D],
                      previous: np.ndarray | None) -> Reconstruction:
        """:func:`.body_corrections.head_by_body` with this tracker's checks (:meth:`_rejection`)."""
        return body_corrections.head_by_body(self.calibration, self.F, self.settings, self.body, rec, blobs, feats,
                                             previous, self._rejection)

    def _mirror_by_body(self, rec: Reconstruction, blobs: dict[str, Blob], feats: dict[str, Features2D],
                        previous: np.ndarray | None) -> Reconstruction:
        """:func:`.body_corrections.mirror_by_body` with this tracker's checks (:meth:`_rejection`)."""
        return body_corrections.mirror_by_body(self.calibration, self.F, self.settings, self.body, rec, blobs, feats,
                                               previous, self._rejection)

    def _centroid_by_body(self, rec: Reconstruction, fits: list) -> Reconstruction:
        """:func:`.body_corrections.centroid_by_body` of this tracker's body."""
        return body_corrections.centroid_by_body(self.body, rec, fits)

    def _axis_by_length(self, rec: Reconstruction, blobs: dict[str, Blob]) -> Reconstruction:
        """:func:`.body_corrections.axis_by_length` with this tracker's calibration, settings and body."""
        return body_corrections.axis_by_length(self.calibration, self._packed, self.settings, self.body, rec, blobs)

    # ------------------------------------------------------------------------------------ results
    def _posture(self, frame: int, t: float, rec: Reconstruction, blobs: dict[str, Blob]) -> Posture:
        observations: dict[str, ViewObservation | None] = {}
        for name in VIEWS:
            feat = rec.view_features[name]
            tips = rec.view_tips[name]
            (u0, v0), (u1, v1) = tips.tolist()
            norm = math.hypot(u0 - u1, v0 - v1)
            axis = np.array([(u0 - u1) / norm, (v0 - v1) / norm]) if norm > 0 else feat.axis
            # ViewObservation(feat.centroid, tips, axis, ...) without the frozen dataclass's __init__ (~2 us).
            observations[name] = _frozen(ViewObservation, {
                "centroid_px": feat.centroid, "tips_px": tips, "axis": axis, "pixel_count": blobs[name].pixel_count,
                "eigenvalues": feat.eigenvalues, "head_index": 0 if rec.head_identified else None})
        reasons = list(rec.reasons)
        ambiguous = rec.ambiguous
        cluttered = [name for name in VIEWS if blobs[name].clutter > self.settings.max_clutter]
        if cluttered:
            # The background under the robot had to be interpolated across another structure; the pose
            # is usually still right, but not to the usual accuracy.
            ambiguous = True
            reasons.append(f"the robot overlaps another structure in view {' and '.join(cluttered)} "
                           f"(background under it varies by {max(blobs[n].clutter for n in cluttered):.0%} of "
                           f"its contrast); reduced accuracy")
        reason = "; ".join(reasons) if reasons else None
        # Posture(...) with every field, in its order, without the generated __init__ (it has no __post_init__).
        return _frozen(Posture, {
            "frame": frame, "t": t, "ok": True, "ambiguous": ambiguous, "centroid_mm": rec.centroid,
            "direction": rec.direction, "tips_mm": rec.tips, "head_identified": rec.head_identified,
            "length_mm": rec.length_mm, "reprojection_px": rec.reprojection_px, "views": observations,
            "reason": reason, "direction_candidates": rec.candidates,
            "pairing_rms_px": (rec.pairing.rms_a_px, rec.pairing.rms_b_px), "plane_angle_deg": rec.plane_angle_deg,
            "timings_us": {}})

    def _placed(self, posture: Posture, rec: Reconstruction, blobs: dict[str, Blob], images: dict[str, np.ndarray]
                ) -> Posture:
        """:func:`.body_prior.place_body` on a posture of the per-view path, in place (``posture`` is the one
        :meth:`_posture` just made): the views' clutter, the axis' sigma, and near each end of a view over
        another structure, how much structure its neighbourhood shows."""
        clutter = {name: blob.clutter for name, blob in blobs.items()}
        ends = {}
        max_clutter = self.settings.max_clutter
        if clutter["p"] > max_clutter or clutter["q"] > max_clutter:
            which = ends_used(posture, self.body, self.settings)  # (the ends whose clutter can change the placement)
            for name, blob in blobs.items():
                view = posture.views.get(name) if which is not None else None
                if blob.clutter > max_clutter and view is not None and name in self._log_bg:
                    ends[name] = end_clutter(images[name], self._log_bg[name], blob, view.centroid_px, view.tips_px,
                                             self.settings, which)
        slide = self._centroid_slide_mm(posture, blobs)
        # (fresh: the posture _posture just made, held by no one else)
        return place_body(self.calibration, posture, self.body, self.settings, clutter, rec.axis_sigma_rad or 0.0,
                          ends, fresh=True, centroid_slide_mm=slide)

    def _centroid_slide_mm(self, posture: Posture, blobs: dict[str, Blob]) -> float:
        """Where one view's blob is heavier than the body (:func:`.body_mass.heavy_view`: another structure merged
        into it), how far that can have moved the moment centroid along the axis (mm,
        :func:`.body_mass.centroid_slide_mm`), the posture flagged with the reason; 0 otherwise (and without the
        body's mass, and for the paper's estimator, kept verbatim)."""
        body = self.body
        rule = self.settings.mass_rule
        if (body is None or body.mass_mm2 is None or posture.centroid_mm is None
                or self.settings.estimator == "paper" or rule == "off"):
            return 0.0
        masses = view_masses_mm2(self.calibration, blobs, posture.centroid_mm)
        heavy = heavy_view(masses, body.mass_mm2, self.settings.max_mass_excess, self.settings.max_mass_deficit)
        if heavy is None:
            return 0.0
        slide = centroid_slide_mm(masses, heavy, body.mass_mm2, body.length_mm)
        posture.ambiguous = True
        other = "q" if heavy == "p" else "p"
        posture.reason = "; ".join(filter(None, [posture.reason, (
            f"view {heavy}'s blob weighs {masses[heavy] / body.mass_mm2:.2f} of the body (view {other}'s "
            f"{masses[other] / body.mass_mm2:.2f}): another structure merged into it, its centroid may have slid "
            f"~{slide:.1f} mm along the axis" + ("; the ends place the body" if rule == "slide" else ""))]))
        return slide if rule == "slide" else 0.0

    def _remember(self, posture: Posture) -> None:
        assert posture.centroid_mm is not None
        old = self._track
        x, y, z = posture.centroid_mm.tolist()
        velocity = (0.0, 0.0, 0.0)
        if old is not None and old.lost_frames == 0 and posture.t > old.t:
            dt = posture.t - old.t
            ox, oy, oz = old.centroid
            velocity = ((x - ox) / dt, (y - oy) / dt, (z - oz) / dt)
        direction = posture.direction
        if direction is None and old is not None:
            direction = old.direction  # unresolved mirror ambiguity: keep the last known axis for the ROI
        heading = old.heading if old is not None else None
        if posture.head_identified and posture.direction is not None:
            heading = posture.direction
        elif heading is not None and posture.direction is not None:
            # The axis carried on, its sign the identified heading's (one frame period turns it little).
            heading = posture.direction if float(posture.direction @ heading) >= 0.0 else -posture.direction
        outline: dict[str, tuple[float, float, float, float, float, float, float]] = {}
        for name, view in posture.views.items():
            if view is not None:
                (cu, cv), ((u0, v0), (u1, v1)) = view.centroid_px.tolist(), view.tips_px.tolist()
                outline[name] = (cu, cv, u0, v0, u1, v1, 2.0 * math.sqrt(max(float(view.eigenvalues[1]), 0.0)))
        self._track = _Track(posture.t, (x, y, z), direction,
                             posture.length_mm if posture.length_mm is not None else (old.length_mm if old else None),
                             velocity, view_outline_px=outline,
                             direction_xyz=None if direction is None else tuple(direction.tolist()),
                             heading=heading)

    def _remember_plain(self, t: float, direction: np.ndarray) -> None:
        """:meth:`_remember` of the steady pair's plain posture at ``t`` (``direction`` its direction), from
        the call's numbers (:attr:`.SteadyPair.plain_track`: the same floats as the posture's fields, the
        centroid the body prior placed included), the track updated in place."""
        track = self._track
        assert track is not None
        centroid, direction_xyz, length, outline_p, outline_q = self._pair.plain_track
        if track.lost_frames == 0 and t > track.t:
            dt = t - track.t
            (x, y, z), (ox, oy, oz) = centroid, track.centroid
            track.velocity = ((x - ox) / dt, (y - oy) / dt, (z - oz) / dt)
        else:
            track.velocity = (0.0, 0.0, 0.0)
        track.t = t
        track.centroid = centroid
        track.direction = direction
        track.direction_xyz = direction_xyz
        track.heading = direction   # (a plain frame's head is identified)
        track.length_mm = length
        track.lost_frames = 0
        track.view_outline_px = {"p": outline_p, "q": outline_q}

    def _lose(self) -> None:
        self._lean_from = None
        if self._track is None:
            return
        self._track.lost_frames += 1
        self._track.velocity = (0.0, 0.0, 0.0)
        if self._track.lost_frames > self.settings.max_lost_frames:
            self._track = None
