"""The tracker's steady-state frame pair in one compiled call (:mod:`.steady_kernels`), and its Python side.

:class:`SteadyPair` holds what does not change from frame to frame (the kernels' settings as arrays,
the packed calibration, the plausibility checks' view scalars) and fills the call's per-frame input in
one assignment. After the call, a plain frame (:func:`.steady_kernels._finish`: no ambiguity, no
clutter, the head identified, robot-like, on its images) has its :class:`.Posture` built from the
call's numbers (:meth:`SteadyPair.plain_posture`, with the few checks whose last bit depends on
Python's ``math.hypot`` / ``math.degrees`` made here); any other frame gets the two views'
:class:`.Blob` and :class:`.Features2D` (:meth:`SteadyPair.objects`) and the tracker's decisions on
them. Either way the posture is the per-view path's (:func:`.roi_search.find_in_roi` per view, then
:func:`.reconstruction.reconstruct`) to the last bit; where a view is not plainly found the call
says so and the tracker takes that path, which decides as it always did.
"""
from __future__ import annotations

import math

import numpy as np

from appliance.geometry import Calibration
from appliance.recognition import reconstruction_kernels as rk
from appliance.recognition import roi_kernels, view_kernels
from appliance.recognition import steady_kernels as sk
from appliance.recognition.features import _LEVELS_ARRAY, Features2D, clutter_axis_sigma_rad
from appliance.recognition.plausibility import _view_scalars
from appliance.recognition.posture import Posture, ViewObservation
from appliance.recognition.roi_search import _frozen, _kernel_settings, blob_and_features
from appliance.recognition.segmentation import _SMOOTH_NOISE_GAIN, MAX_CANDIDATES, Blob, LogBackground
from appliance.recognition.settings import RecognitionSettings

#: One view's last 2D outline as the tracker keeps it: centroid u, v, ends u0, v0, u1, v1, half width (px).
Outline = tuple[float, float, float, float, float, float, float]
_NO_OUTLINE = (0.0,) * 7
_NO_DIRECTION = (0.0, 0.0, 0.0)


class SteadyPair:
    """One compiled call per tracked pair for a calibration and settings (see the module docstring)."""

    def __init__(self, calibration: Calibration, settings: RecognitionSettings) -> None:
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
        self._calibration = calibration
        #: The last call's output (a new array per pair: the features' arrays are views of it).
        self.out = np.empty(0)
        self._no_previous = np.zeros(sk.OUT_SIZE)

    def lean_views(self) -> tuple[bool, bool]:
        """Whether the last call found view p and view q by the lean pass."""
        o = sk.OUT_VIEW_SIZE
        return bool(self.out[sk.R_LEAN] == 1.0), bool(self.out[o + sk.R_LEAN] == 1.0)

    def usable(self, image_p: np.ndarray, image_q: np.ndarray, bg_p: LogBackground | None,
               bg_q: LogBackground | None) -> bool:
        """Whether the inputs are those of the compiled path (as :func:`.roi_search.find_in_roi` decides)."""
        return (self.settings.estimator == "weighted" and isinstance(bg_p, LogBackground)
                and isinstance(bg_q, LogBackground) and image_p.dtype == np.uint16 and image_q.dtype == np.uint16
                and image_p.flags.c_contiguous and image_q.flags.c_contiguous)

    def search(self, image_p: np.ndarray, image_q: np.ndarray, bg_p: LogBackground, bg_q: LogBackground,
               centre: tuple[float, float, float], direction: tuple[float, float, float], half: float,
               outline_p: Outline | None, outline_q: Outline | None, sigma_p: float | None, sigma_q: float | None,
               previous: tuple[float, float, float] | None, lean_from: np.ndarray | None = None,
               last_centre: tuple[float, float, float] = (0.0, 0.0, 0.0)
               ) -> bool:
        """Both views searched and the front run in one call: True if both views were plainly found (then
        :meth:`plain_posture` and :meth:`objects` give the results), False if not (take the per-view path).

        ``centre``, ``direction`` (unit, or zeros) and ``half`` (half length + 1 mm) are the tracker's
        prediction; ``sigma_*`` the noise sigma to reuse (None: measure it); ``previous`` the last
        direction for the reconstruction (None if none). The images must pass :meth:`usable`.
        ``lean_from``: the previous pair's :attr:`out` (its frame remembered by the tracker, whose 3D
        centroid was ``last_centre``) to try the lean pass from (prototype; a view whose noise sigma is
        measured this frame takes the full search), or None.
        """
        if self.settings.background_along_structure:
            lean_from = None  # the lean pass interpolates the background along image columns or rows only
        # Every per-frame number in the order of steady_kernels' layout, written in one assignment.
        numbers = [*centre, *direction, half, *last_centre, *(previous or _NO_DIRECTION), float(previous is not None)]
        for image, bg, outline, sigma in ((image_p, bg_p, outline_p, sigma_p), (image_q, bg_q, outline_q, sigma_q)):
            known = float(sigma) if sigma is not None and math.isfinite(sigma) and sigma > 0 else 0.0
            numbers += (0.0, *_NO_OUTLINE) if outline is None else (1.0, *outline)
            numbers += (known, 1.0 if lean_from is not None and known > 0.0 else 0.0, bg.fy, bg.fx, *image.shape)
        inp = self._inp
        inp[:sk.IN_FRAME_SIZE] = numbers
        out = np.empty(sk.OUT_SIZE)
        status, w_p, m_p, w_q, m_q = sk.search_pair(
            image_p, image_q, bg_p.coarse, bg_q.coarse, self._table, view_kernels.GAUSSIAN_5, self._params,
            self._ring_outer, self._ring_inner, self._near, _LEVELS_ARRAY, self._search_settings, self._G, inp,
            self._no_previous if lean_from is None else lean_from, out)
        if status != sk.PAIR_FOUND:
            return False
        self.out = out
        self._found = ((w_p, m_p), (w_q, m_q))
        return True

    def sigmas(self) -> tuple[float, float]:
        """The noise sigma each view of the last call used."""
        o = sk.OUT_VIEW_SIZE
        return float(self.out[roi_kernels.SIGMA]), float(self.out[o + roi_kernels.SIGMA])

    def body_inputs(self) -> tuple[dict[str, float], float]:
        """What :func:`.body_prior.place_body` takes of the last call: each view's :attr:`.Blob.clutter` (what
        its blob would carry) and the 3D axis' sigma (rad, the front's, as the reconstruction keeps it)."""
        o, r = sk.OUT_VIEW_SIZE, roi_kernels.REFINED + 11
        return ({"p": float(self.out[r]), "q": float(self.out[o + r])},
                float(self.out[sk.OUT_FRONT + rk.OUT_SIGMA]))

    def objects(self) -> tuple[tuple[Blob, Blob], tuple[Features2D, Features2D], int | None, np.ndarray]:
        """The last call's blobs and features, the front's status (None where the compiled axis uncertainty
        is not Python's to the last bit: then run the whole reconstruction) and output."""
        out = self.out
        found = []
        for view, (weights, mask) in enumerate(self._found):
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

    def plain_posture(self, frame: int, t: float) -> Posture | None:
        """The last call's posture where its frame is plain (:func:`.steady_kernels._finish`) and passes the
        checks that stay in Python (the centroids' and tips' epipolar bands, the axis uncertainty); None
        otherwise (the tracker then decides on the objects, :meth:`objects`). The same posture as the
        tracker builds, to the last bit."""
        out = self.out
        P = sk.OUT_POSTURE
        if out[P + sk.P_PLAIN] != 1.0:
            return None
        s = self.settings
        f = sk.OUT_FRONT
        o = sk.OUT_VIEW_SIZE
        axis_p, axis_q = float(out[sk.R_AXIS_SIGMA]), float(out[o + sk.R_AXIS_SIGMA])
        numbers = out.tolist()
        # The kernel's axis uncertainty must be Python's (see objects), and the front's checks pass.
        if (axis_p != _axis_sigma(numbers, 0) or axis_q != _axis_sigma(numbers, o)
                or math.degrees(numbers[f + rk.OUT_SIGMA]) > s.max_axis_sigma_deg
                or numbers[f + rk.OUT_CENTROID_EPIPOLAR] > s.epipolar_band_px
                or min(numbers[f + rk.OUT_RMS_A], numbers[f + rk.OUT_RMS_B]) > s.tips_band_px):
            return None
        views: dict[str, ViewObservation | None] = {}
        for name, v in (("p", 0), ("q", o)):
            k = P + sk.P_VIEW_TIPS + (0 if v == 0 else 4)
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
        reprojection = numbers[P + sk.P_REPROJECTION]
        return Posture(frame=frame, t=t, ok=True, ambiguous=False,
                       centroid_mm=out[P + sk.P_CENTROID:P + sk.P_CENTROID + 3],
                       direction=out[P + sk.P_DIRECTION:P + sk.P_DIRECTION + 3],
                       tips_mm=out[P + sk.P_TIPS:P + sk.P_TIPS + 6].reshape(2, 3), head_identified=True,
                       length_mm=numbers[P + sk.P_LENGTH],
                       reprojection_px=reprojection if math.isfinite(reprojection) else None, views=views,
                       reason=None, direction_candidates=None,
                       pairing_rms_px=(numbers[f + rk.OUT_RMS_A], numbers[f + rk.OUT_RMS_B]),
                       plane_angle_deg=numbers[f + rk.OUT_PLANE_ANGLE])


def _axis_sigma(numbers: list[float], o: int) -> float:
    """A found view's axis uncertainty with the clutter term, as roi_search.blob_and_features computes it."""
    r = o + roi_kernels.REFINED
    e = o + roi_kernels.EIGENVALUES
    return math.hypot(numbers[o + roi_kernels.AXIS_SIGMA], clutter_axis_sigma_rad(
        numbers[r + 11], int(numbers[r + 12]), numbers[r + 4], numbers[r + 6], numbers[e], numbers[e + 1]))
