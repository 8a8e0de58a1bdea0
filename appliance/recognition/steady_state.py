"""The tracker's steady-state frame pair in one compiled call (:mod:`.steady_kernels`), and its Python side.

:class:`SteadyPair` holds what does not change from frame to frame (the kernels' settings as arrays,
the packed calibration, the input array it refills) so that a tracked pair costs one kernel call
and the building of the two views' :class:`.Blob` and :class:`.Features2D` from its output. It gives
what the per-view path (:func:`.roi_search.find_in_roi` per view, then
:func:`.reconstruction.reconstruct`) gives, bit for bit; where a view is not plainly found it
returns None and the tracker takes that path, which decides as it always did.
"""
from __future__ import annotations

import math

import numpy as np

from appliance.geometry import Calibration
from appliance.recognition import steady_kernels as sk
from appliance.recognition import view_kernels
from appliance.recognition.features import _LEVELS_ARRAY, Features2D
from appliance.recognition.roi_search import _kernel_settings, blob_and_features
from appliance.recognition.segmentation import _SMOOTH_NOISE_GAIN, MAX_CANDIDATES, Blob, LogBackground
from appliance.recognition.settings import RecognitionSettings

#: One view's last 2D outline as the tracker keeps it: centroid u, v, ends u0, v0, u1, v1, half width (px).
Outline = tuple[float, float, float, float, float, float, float]


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
               ) -> tuple[tuple[Blob, Blob], tuple[Features2D, Features2D], int, np.ndarray] | None:
        """Both views' blobs and features, the front's status and output (:mod:`.reconstruction_kernels`
        layout), or None where a view is not plainly found (take the per-view path).

        ``centre``, ``direction`` (unit, or zeros) and ``half`` (half length + 1 mm) are the tracker's
        prediction; ``sigma_*`` the noise sigma to reuse (None: measure it); ``previous`` the last
        direction for the reconstruction (None if none). The images must pass :meth:`usable`.
        ``lean_from``: the previous pair's :attr:`out` (its frame remembered by the tracker, whose 3D
        centroid was ``last_centre``) to try the lean pass from (prototype; a view whose noise sigma is
        measured this frame takes the full search), or None.
        """
        inp = self._inp
        inp[sk.IN_CENTRE], inp[sk.IN_CENTRE + 1], inp[sk.IN_CENTRE + 2] = centre
        inp[sk.IN_DIRECTION], inp[sk.IN_DIRECTION + 1], inp[sk.IN_DIRECTION + 2] = direction
        inp[sk.IN_HALF] = half
        for view, (image, bg, outline, sigma) in enumerate(((image_p, bg_p, outline_p, sigma_p),
                                                            (image_q, bg_q, outline_q, sigma_q))):
            v = sk.IN_VIEW + view * sk.IN_VIEW_SIZE
            if outline is None:
                inp[v + sk.V_HAS_OUTLINE] = 0.0
            else:
                inp[v + sk.V_HAS_OUTLINE] = 1.0
                inp[v + sk.V_OUTLINE:v + sk.V_OUTLINE + 7] = outline
            known = float(sigma) if sigma is not None and math.isfinite(sigma) and sigma > 0 else 0.0
            inp[v + sk.V_KNOWN_SIGMA] = known
            inp[v + sk.V_LEAN] = 1.0 if lean_from is not None and known > 0.0 else 0.0
            inp[v + sk.V_FY], inp[v + sk.V_FX] = bg.fy, bg.fx
            inp[v + sk.V_HEIGHT], inp[v + sk.V_WIDTH] = image.shape
        if previous is None:
            inp[sk.IN_PREVIOUS:sk.IN_PREVIOUS + 4] = 0.0
        else:
            inp[sk.IN_PREVIOUS], inp[sk.IN_PREVIOUS + 1], inp[sk.IN_PREVIOUS + 2] = previous
            inp[sk.IN_PREVIOUS + 3] = 1.0
        inp[sk.IN_LAST_CENTRE], inp[sk.IN_LAST_CENTRE + 1], inp[sk.IN_LAST_CENTRE + 2] = last_centre
        out = np.empty(sk.OUT_SIZE)
        status, w_p, m_p, w_q, m_q = sk.search_pair(
            image_p, image_q, bg_p.coarse, bg_q.coarse, self._table, view_kernels.GAUSSIAN_5, self._params,
            self._ring_outer, self._ring_inner, self._near, _LEVELS_ARRAY, self._search_settings, self._G, inp,
            self._no_previous if lean_from is None else lean_from, out)
        if status != sk.PAIR_FOUND:
            return None
        self.out = out
        found = []
        for view, (weights, mask) in enumerate(((w_p, m_p), (w_q, m_q))):
            o = sk.OUT_VIEW + view * sk.OUT_VIEW_SIZE
            x0, y0 = int(out[o + sk.R_ROI]), int(out[o + sk.R_ROI + 1])
            found.append(blob_and_features(out[o:o + sk.SEARCH_SIZE], weights, mask, x0, y0,
                                           float(out[o + sk.R_AXIS_SIGMA])))
        (blob_p, feat_p), (blob_q, feat_q) = found
        return ((blob_p, blob_q), (feat_p, feat_q), int(out[sk.OUT_FRONT_STATUS]),
                out[sk.OUT_FRONT:sk.OUT_FRONT_STATUS])
