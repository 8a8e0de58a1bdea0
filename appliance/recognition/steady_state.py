"""The tracker's steady-state frame pair in one compiled call (:mod:`.steady_kernels`), and its Python side.

:class:`SteadyPair` holds what does not change from frame to frame (the kernels' settings as arrays,
the packed calibration, the plausibility checks' view scalars) and writes the call's per-frame input
in place. After the call, a plain frame (:func:`.steady_kernels._finish`: no ambiguity, no clutter,
the head identified, robot-like, on its images) has its :class:`.Posture` built from the call's
numbers (:meth:`SteadyPair.plain_posture`, with the few checks whose last bit depends on Python's
``math.hypot`` / ``math.degrees`` made here; its tips and views are made when first read, see
:meth:`.Posture.deferred`); any other frame gets the two views' :class:`.Blob` and :class:`.Features2D`
(:meth:`SteadyPair.objects`) and the tracker's decisions on them. Either way the posture is the
per-view path's (:func:`.roi_search.find_in_roi` per view, then :func:`.reconstruction.reconstruct`) to
the last bit; where a view is not plainly found the call says so and the tracker takes that path,
which decides as it always did.

Per pair the Python around the call is a few dozen microseconds after a frame's copy has evicted the
caches (issue 8; ``benchmarks/steady_python.py``): each distinct numpy call then costs several
microseconds, so the plain path makes none but the call itself (the input through a memoryview, the
output's numbers by one ``struct`` read, output arrays and the posture's views of them reused, see
:meth:`SteadyPair._output`).
"""
from __future__ import annotations

import math
import struct
import sys
from typing import Any

import numpy as np

from appliance.geometry import Calibration
from appliance.recognition import body_kernels as bk
from appliance.recognition import reconstruction_kernels as rk
from appliance.recognition import roi_kernels, view_kernels
from appliance.recognition import steady_kernels as sk
from appliance.recognition.body_prior import BodyModel
from appliance.recognition.features import _LEVELS_ARRAY, Features2D, clutter_axis_sigma_rad
from appliance.recognition.plausibility import _view_scalars
from appliance.recognition.posture import Posture, ViewObservation
from appliance.recognition.roi_search import _frozen, _kernel_settings, blob_and_features
from appliance.recognition.segmentation import _SMOOTH_NOISE_GAIN, MAX_CANDIDATES, Blob, LogBackground
from appliance.recognition.settings import RecognitionSettings

#: One view's last 2D outline as the tracker keeps it: centroid u, v, ends u0, v0, u1, v1, half width (px).
Outline = tuple[float, float, float, float, float, float, float]


class SteadyPair:
    """One compiled call per tracked pair for a calibration and settings (see the module docstring).

    A plain frame's :class:`.Posture` defers its tips and views (two :class:`.ViewObservation` and their
    arrays) to their first reading (:meth:`.Posture.deferred`): the control reads the pose, the rest is
    for the record, written after the command.
    """

    def __init__(self, calibration: Calibration, settings: RecognitionSettings, body: BodyModel | None = None) -> None:
        self.settings = settings
        self._G = calibration.packed
        (self._table, detect_sigma, floor, min_pixels, self._params, self._ring_outer, self._ring_inner, self._near,
         gate_px, axis_saturation, head_ramp_ratio, head_min_ramp_px) = _kernel_settings(settings)
        self._search_settings = np.array([detect_sigma, _SMOOTH_NOISE_GAIN, floor, min_pixels, MAX_CANDIDATES * 3,
                                          MAX_CANDIDATES, gate_px, axis_saturation, head_ramp_ratio,
                                          head_min_ramp_px], dtype=np.float64)
        s = settings
        self._inp = np.zeros(sk.IN_SIZE)
        self._inp[sk.IN_FRONT:sk.IN_FRONT + sk.FRONT_SETTINGS] = [
            s.ambiguity_px, s.min_plane_angle_deg, s.max_axis_disagreement_deg, s.min_view_elongation,
            s.axis_floor_rad, s.tip_sigma_px, s.tip_rim_fraction]
        self._inp[sk.IN_MARGIN] = float(s.roi_margin_px)
        self._inp[sk.IN_FINISH:sk.IN_FINISH + sk.FINISH_SETTINGS] = [
            s.max_clutter, s.max_length_over_width, s.min_path_attenuation_per_mm, s.max_reprojection_px,
            s.head_foreshortening]
        sources = _view_scalars(calibration)
        self._inp[sk.IN_SOURCES:sk.IN_SOURCES + 8] = [*sources["p"], *sources["q"]]
        #: Whether the call places a plain frame's posture by the robot's body (:func:`.steady_kernels._place_body`,
        #: :func:`.body_prior.place_plain_body`'s numbers; the paper's estimator keeps its postures verbatim).
        self._body = body is not None and s.estimator != "paper"
        if self._body:
            assert body is not None
            self._inp[sk.IN_BODY] = 1.0
            self._inp[sk.IN_BODY + 1:sk.IN_BODY + 1 + bk.B_SIZE] = body.packed
        #: The backgrounds whose factors (and images' shape) the input holds (search writes them when they change).
        self._written: tuple[LogBackground | None, LogBackground | None] = (None, None)
        self._calibration = calibration
        #: The input's per-frame numbers, written in place (search).
        self._frame_input = memoryview(self._inp)
        #: What the call takes between the coarse backgrounds and the previous pair's output, in its order
        #: (the same objects every pair).
        self._fixed = (self._table, view_kernels.GAUSSIAN_5, self._params, self._ring_outer, self._ring_inner,
                       self._near, _LEVELS_ARRAY, self._search_settings, self._G, self._inp)
        self._weighted = s.estimator == "weighted"
        self._lean_allowed = not s.background_along_structure
        self._tight = s.tight_roi
        #: The checks that stay in Python (plain_posture), as plain floats.
        self._max_axis_sigma_deg = float(s.max_axis_sigma_deg)
        self._end_on_flag_elongation = float(s.end_on_flag_elongation)
        self._epipolar_band_px = float(s.epipolar_band_px)
        self._tips_band_px = float(s.tips_band_px)
        #: Output arrays with what a plain posture is made of each (see _new_output), reused where nothing
        #: else holds any of them (see _output).
        self._outputs = [_new_output(self._body) for _ in range(_OUTPUTS)]
        self._next_slot = 0
        self._centroid_mm: np.ndarray | None = None
        self._direction: np.ndarray | None = None
        self._rest: _PlainRest | None = None
        #: The last call's output (a new array per pair: the posture's and the features' arrays are views
        #: of it), and what the tracker remembers of its plain posture (:meth:`plain_posture`).
        self.out = np.empty(0)
        self.plain_track: tuple[tuple[float, float, float], tuple[float, float, float], float, Outline,
                                Outline] | None = None
        self._no_previous = np.zeros(sk.OUT_SIZE)
        #: Where the call writes each view's chosen weights and mask (see objects).
        self._weights_buf = np.zeros((2, sk.WINDOW_CAPACITY), dtype=np.float32)
        self._masks_buf = np.zeros((2, sk.WINDOW_CAPACITY), dtype=np.uint8)
        #: The lean pass's workspace (steady_kernels.lean_view), reused every frame.
        self._work = np.zeros(sk.LEAN_WORK_BYTES, dtype=np.uint8)

    def lean_views(self) -> tuple[bool, bool]:
        """Whether the last call found view p and view q by the lean pass."""
        o = sk.OUT_VIEW_SIZE
        return (bool(self.out[sk.R_FOUND_BY] == sk.FOUND_BY_LEAN),
                bool(self.out[o + sk.R_FOUND_BY] == sk.FOUND_BY_LEAN))

    def usable(self, image_p: np.ndarray, image_q: np.ndarray, bg_p: LogBackground | None,
               bg_q: LogBackground | None) -> bool:
        """Whether the inputs are those of the compiled path (as :func:`.roi_search.find_in_roi` decides)."""
        return (self._weighted and isinstance(bg_p, LogBackground) and isinstance(bg_q, LogBackground)
                and image_p.dtype == _UINT16 and image_q.dtype == _UINT16
                and image_p.flags.c_contiguous and image_q.flags.c_contiguous)

    def search(self, image_p: np.ndarray, image_q: np.ndarray, bg_p: LogBackground, bg_q: LogBackground,
               centre: tuple[float, float, float], direction: tuple[float, float, float], half: float,
               outline_p: Outline | None, outline_q: Outline | None, sigma_p: float | None, sigma_q: float | None,
               previous: tuple[float, float, float] | None, lean_from: np.ndarray | None = None,
               last_centre: tuple[float, float, float] = (0.0, 0.0, 0.0), last_out: np.ndarray | None = None
               ) -> bool:
        """Both views searched and the front run in one call: True if both views were plainly found (then
        :meth:`plain_posture` and :meth:`objects` give the results), False if not (take the per-view path).

        ``centre``, ``direction`` (unit, or zeros) and ``half`` (half length + 1 mm) are the tracker's
        prediction; ``sigma_*`` the noise sigma to reuse (None: measure it); ``previous`` the last
        direction for the reconstruction (None if none). The images must pass :meth:`usable`.
        ``lean_from``: the previous pair's :attr:`out` (its frame remembered by the tracker, whose 3D
        centroid was ``last_centre``) to try the lean pass from (prototype; a view whose noise sigma is
        measured this frame takes the full search), or None. ``last_out``: the previous pair's :attr:`out` where
        the last frame was that pair's (the tight ROI starts from its prediction errors, see
        :data:`.steady_kernels.TIGHT_MARGIN_PX`), or None.
        """
        if not self._lean_allowed:
            lean_from = None  # the lean pass interpolates the background along image columns or rows only
        known_p = float(sigma_p) if sigma_p is not None and math.isfinite(sigma_p) and sigma_p > 0 else 0.0
        known_q = float(sigma_q) if sigma_q is not None and math.isfinite(sigma_q) and sigma_q > 0 else 0.0
        lean = lean_from is not None
        # Every per-frame number into its place of steady_kernels' layout, through a memoryview of the input
        # (a float per store: after a frame's copy, far cheaper than numpy's or struct's conversion of a list).
        m = self._frame_input
        m[0], m[1], m[2] = centre
        m[3], m[4], m[5] = direction
        m[sk.IN_HALF] = half
        if not self._tight:
            last_out = None
        m[sk.IN_TIGHT] = 0.0 if last_out is None else 1.0
        m[7], m[8], m[9] = last_centre
        if previous is None:
            m[10] = m[11] = m[12] = m[13] = 0.0
        else:
            m[10], m[11], m[12] = previous
            m[13] = 1.0
        for v, outline, known in ((_IN_P, outline_p, known_p), (_IN_Q, outline_q, known_q)):
            if outline is None:
                m[v] = m[v + 1] = m[v + 2] = m[v + 3] = m[v + 4] = m[v + 5] = m[v + 6] = m[v + 7] = 0.0
            else:
                m[v] = 1.0
                m[v + 1], m[v + 2], m[v + 3], m[v + 4], m[v + 5], m[v + 6], m[v + 7] = outline
            m[v + 8] = known
            m[v + 9] = 1.0 if lean and known > 0.0 else 0.0
        written = self._written
        if bg_p is not written[0] or bg_q is not written[1]:
            # A new full-frame background (and with it the frames' shape): its factors, kept until the next.
            for v, bg, image in ((_IN_P, bg_p, image_p), (_IN_Q, bg_q, image_q)):
                m[v + 10] = bg.fy
                m[v + 11] = bg.fx
                m[v + 12], m[v + 13] = image.shape
            self._written = (bg_p, bg_q)
        out, self._centroid_mm, self._direction, self._rest = self._output()
        status = sk.search_pair(image_p, image_q, bg_p.coarse, bg_q.coarse, *self._fixed,
                                lean_from if lean_from is not None else
                                last_out if last_out is not None else self._no_previous,
                                self._weights_buf, self._masks_buf, self._work, out)
        if status != sk.PAIR_FOUND:
            return False
        self.out = out
        return True

    def _output(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, _PlainRest]:
        """An output array for the next call and what a plain posture is made of it (:func:`_new_output`):
        one of :data:`_OUTPUTS` made ahead where nothing outside this object holds any of them any more (a
        posture, its features, the tracker's track or lean pass: each holds a reference, which
        ``sys.getrefcount`` counts), else a new one in its slot. A new array and two views would cost
        three numpy calls per pair, ~10 us after a frame's copy has evicted numpy's code."""
        outputs = self._outputs
        for k in range(_OUTPUTS):
            entry = outputs[k]
            # Held only by the list's tuple (and the call's argument); the array also by its two views and
            # the posture's rest.
            if (sys.getrefcount(entry[0]) == 5 and sys.getrefcount(entry[1]) == 2
                    and sys.getrefcount(entry[2]) == 2 and sys.getrefcount(entry[3]) == 2):
                return entry
        entry = outputs[self._next_slot] = _new_output(self._body)
        self._next_slot = (self._next_slot + 1) % _OUTPUTS
        return entry

    def sigmas(self) -> tuple[float, float]:
        """The noise sigma each view of the last call used."""
        return _SIGMAS.unpack_from(self.out)  # type: ignore[return-value]

    def objects(self) -> tuple[tuple[Blob, Blob], tuple[Features2D, Features2D], int | None, np.ndarray]:
        """The last call's blobs and features, the front's status (None where the compiled axis uncertainty
        is not Python's to the last bit: then run the whole reconstruction) and output."""
        out = self.out
        found = []
        for view in range(2):
            # The chosen blob's weights and mask, copied out of the buffers the next call overwrites.
            rows, columns = int(out[sk.OUT_WINDOW_SHAPES + 2 * view]), int(out[sk.OUT_WINDOW_SHAPES + 2 * view + 1])
            weights = self._weights_buf[view, :rows * columns].reshape(rows, columns).copy()
            mask = self._masks_buf[view, :rows * columns].reshape(rows, columns).copy()
            o = sk.OUT_VIEW + view * sk.OUT_VIEW_SIZE
            x0, y0 = int(out[o + sk.R_ROI]), int(out[o + sk.R_ROI + 1])
            found.append(blob_and_features(out[o:o + sk.SEARCH_SIZE], weights, mask, x0, y0, None))
        (blob_p, feat_p), (blob_q, feat_q) = found
        o = sk.OUT_VIEW_SIZE
        # The front ran on the kernel's axis uncertainty (numba's hypot): where that is not Python's in the
        # last bit (a clutter term, ~0.5 % of hypot's arguments), the front is run again from Python.
        same = (feat_p.axis_sigma_rad == out[sk.R_AXIS_SIGMA] and feat_q.axis_sigma_rad == out[o + sk.R_AXIS_SIGMA])
        return ((blob_p, blob_q), (feat_p, feat_q), int(out[sk.OUT_FRONT_STATUS]) if same else None,
                out[sk.OUT_FRONT:sk.OUT_FRONT_STATUS])

    def plain_posture(self, frame: int, t: float, timings_us: dict[str, float] | None = None) -> Posture | None:
        """The last call's posture where its frame is plain (:func:`.steady_kernels._finish`) and passes the
        checks that stay in Python (the centroids' and tips' epipolar bands, the axis uncertainty); None
        otherwise (the tracker then decides on the objects, :meth:`objects`). The same posture as the
        tracker builds, to the last bit, with the robot's body placed where the pair was given one (in the
        call: :func:`.steady_kernels._place_body`; a placement the body prior flags is left to the tracker's
        path too); its tips and views are made when first read (:class:`_PlainRest`). ``timings_us`` becomes
        its :attr:`.Posture.timings_us` (a new dict if None). Where it returns a posture, :attr:`plain_track`
        is what the tracker remembers of it."""
        out = self.out
        # The numbers this needs as Python floats, in one read (the layout's order; see _PLAIN_READ).
        (peak_p, strength_p, clutter_p, count_p, cu_p, cv_p, l1_p, l2_p, axis_p, kernel_axis_p,
         peak_q, strength_q, clutter_q, count_q, cu_q, cv_q, l1_q, l2_q, axis_q, kernel_axis_q,
         rms_a, rms_b, plane_angle, epipolar, sigma, plain, x, y, z, d0, d1, d2, length, reprojection,
         tu0_p, tv0_p, tu1_p, tv1_p, tu0_q, tv0_q, tu1_q, tv1_q,
         placed_x, placed_y, placed_z, placed, flag) = _PLAIN_READ.unpack_from(out)
        if plain != 1.0:
            return None
        if self._body:
            # The body prior's posture: its centroid (which the track follows) and tips, where it placed the
            # body without doubt (a flag's reason is the tracker path's to write).
            if placed != 1.0 or flag != bk.FLAG_NONE:
                return None
            x, y, z = placed_x, placed_y, placed_z
        # The kernel's axis uncertainty must be Python's (see objects: roi_search.blob_and_features' hypot of
        # the pixel noise's and the clutter's terms; the clutter term is 0.0 without clutter), and the
        # front's checks pass.
        if (kernel_axis_p != math.hypot(axis_p, clutter_axis_sigma_rad(
                clutter_p, int(count_p), peak_p, strength_p, l1_p, l2_p) if clutter_p > 0.0 else 0.0)
                or kernel_axis_q != math.hypot(axis_q, clutter_axis_sigma_rad(
                    clutter_q, int(count_q), peak_q, strength_q, l1_q, l2_q) if clutter_q > 0.0 else 0.0)
                or math.degrees(sigma) > self._max_axis_sigma_deg or epipolar > self._epipolar_band_px
                or (rms_b if rms_b < rms_a else rms_a) > self._tips_band_px  # min(rms_a, rms_b)
                # A view seen nearly end-on (elongation in the band below end_on_flag_elongation): whether its
                # axis plane may carry the frame unflagged is reconstruction._flagged_end_on's to decide.
                or l1_p < self._end_on_flag_elongation * l2_p or l1_q < self._end_on_flag_elongation * l2_q):
            return None
        # PostureTracker._remember's numbers of this posture: the same floats as its fields.
        self.plain_track = ((x, y, z), (d0, d1, d2), length,
                            (cu_p, cv_p, tu0_p, tv0_p, tu1_p, tv1_p, 2.0 * math.sqrt(max(l2_p, 0.0))),
                            (cu_q, cv_q, tu0_q, tv0_q, tu1_q, tv1_q, 2.0 * math.sqrt(max(l2_q, 0.0))))
        # Posture(...) with every field but the tips and the views, which are made when first read.
        return Posture.deferred({
            "frame": frame, "t": t, "ok": True, "ambiguous": False,
            "centroid_mm": self._centroid_mm, "direction": self._direction,
            "head_identified": True, "length_mm": length,
            "reprojection_px": reprojection if math.isfinite(reprojection) else None,
            "reason": None, "direction_candidates": None, "pairing_rms_px": (rms_a, rms_b),
            "plane_angle_deg": plane_angle, "timings_us": {} if timings_us is None else timings_us,
        }, self._rest)


def _new_output(body: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, _PlainRest]:
    """An output array of the pair call, its views that a plain posture's centroid and direction are (the
    centroid the body placed where ``body``), and what makes the rest of that posture (:class:`_PlainRest`)."""
    out = np.empty(sk.OUT_SIZE)
    centroid = _B_CENTROID if body else _P_CENTROID
    return (out, out[centroid:centroid + 3], out[_P_DIRECTION:_P_DIRECTION + 3],
            _PlainRest(out, _B_TIPS if body else _P_TIPS))


def _reader(indices: tuple[int, ...]) -> struct.Struct:
    """A struct that reads the doubles at ``indices`` (ascending) of a float64 array in one call and skips
    the others (pad bytes): a few dozen Python floats without numpy's per-element cost or a whole
    ``tolist``."""
    assert list(indices) == sorted(set(indices)), indices
    fmt, at = ["="], 0
    for i in indices:
        if i > at:
            fmt.append(f"{8 * (i - at)}x")
        fmt.append("d")
        at = i + 1
    return struct.Struct("".join(fmt))


#: Output arrays made ahead (SteadyPair._output): the last pair's is held by the tracker, the one before
#: it usually by nobody any more.
_OUTPUTS = 3
# The per-frame input's layout (steady_kernels), as search writes it.
assert (sk.IN_CENTRE, sk.IN_DIRECTION, sk.IN_HALF, sk.IN_LAST_CENTRE, sk.IN_PREVIOUS, sk.IN_VIEW_SIZE) == (
    0, 3, 6, 7, 10, 14)
assert (sk.V_HAS_OUTLINE, sk.V_OUTLINE, sk.V_KNOWN_SIGMA, sk.V_LEAN, sk.V_FY, sk.V_FX, sk.V_HEIGHT, sk.V_WIDTH) == (
    0, 1, 8, 9, 10, 11, 12, 13)
_IN_P, _IN_Q = sk.IN_VIEW, sk.IN_VIEW + sk.IN_VIEW_SIZE
_UINT16 = np.dtype(np.uint16)
_R, _E, _C = roi_kernels.REFINED, roi_kernels.EIGENVALUES, roi_kernels.CENTROID
_P_CENTROID = sk.OUT_POSTURE + sk.P_CENTROID
_P_DIRECTION = sk.OUT_POSTURE + sk.P_DIRECTION
_P_TIPS = sk.OUT_POSTURE + sk.P_TIPS
_P_VIEW_TIPS = sk.OUT_POSTURE + sk.P_VIEW_TIPS
_B_CENTROID = sk.OUT_BODY + bk.OUT_CENTROID
_B_TIPS = sk.OUT_BODY + bk.OUT_TIPS
#: The noise sigma of each view.
_SIGMAS = _reader((roi_kernels.SIGMA, sk.OUT_VIEW_SIZE + roi_kernels.SIGMA))
#: What plain_posture reads, in the order it unpacks it: per view the clutter term's inputs, the centroid,
#: the eigenvalues, the noise's axis term and the kernel's axis uncertainty; the front's pairing RMS,
#: plane angle, centroid epipolar distance and axis sigma; the posture's plain flag, centroid, direction,
#: length, reprojection and each view's tips; the body's placed centroid, whether it placed it and its flag.
_PLAIN_READ = _reader(tuple(
    [o + i for o in (0, sk.OUT_VIEW_SIZE) for i in (_R + 4, _R + 6, _R + 11, _R + 12, _C, _C + 1, _E, _E + 1,
                                                   roi_kernels.AXIS_SIGMA, sk.R_AXIS_SIGMA)]
    + [sk.OUT_FRONT + i for i in (rk.OUT_RMS_A, rk.OUT_RMS_B, rk.OUT_PLANE_ANGLE, rk.OUT_CENTROID_EPIPOLAR,
                                  rk.OUT_SIGMA)]
    + [sk.OUT_POSTURE + sk.P_PLAIN, *range(_P_CENTROID, _P_CENTROID + 3), *range(_P_DIRECTION, _P_DIRECTION + 3),
       sk.OUT_POSTURE + sk.P_LENGTH, sk.OUT_POSTURE + sk.P_REPROJECTION, *range(_P_VIEW_TIPS, _P_VIEW_TIPS + 8)]
    + [*range(_B_CENTROID, _B_CENTROID + 3), sk.OUT_BODY + bk.OUT_PLACED, sk.OUT_BODY + bk.OUT_FLAG]))


class _PlainRest:
    """A plain posture's tips and two :class:`.ViewObservation`, made from the call's output when first
    read (:meth:`.Posture.deferred`): the tips as the call placed them (at ``tips``: the reconstruction's, or
    the body prior's), the views as the tracker's ``_posture`` makes them from the reconstruction."""

    __slots__ = ("out", "tips")

    def __init__(self, out: np.ndarray, tips: int) -> None:
        self.out = out
        self.tips = tips

    def __call__(self) -> dict[str, Any]:
        out = self.out
        numbers = out.tolist()
        views: dict[str, ViewObservation | None] = {}
        for name, v, k in (("p", 0, _P_VIEW_TIPS), ("q", sk.OUT_VIEW_SIZE, _P_VIEW_TIPS + 4)):
            u0, v0, u1, v1 = numbers[k:k + 4]
            tips = np.array([[u0, v0], [u1, v1]])
            norm = math.hypot(u0 - u1, v0 - v1)
            c = v + roi_kernels.CENTROID
            axis = (np.array([(u0 - u1) / norm, (v0 - v1) / norm]) if norm > 0
                    else out[v + roi_kernels.AXIS:v + roi_kernels.AXIS + 2])
            e = v + roi_kernels.EIGENVALUES
            views[name] = _frozen(ViewObservation, {
                "centroid_px": out[c:c + 2], "tips_px": tips, "axis": axis,
                "pixel_count": int(numbers[v + roi_kernels.REFINED + 12]), "eigenvalues": (numbers[e], numbers[e + 1]),
                "head_index": 0})
        return {"tips_mm": out[self.tips:self.tips + 6].reshape(2, 3), "views": views}
