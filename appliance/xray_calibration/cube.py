"""Calibrate both views of the biplane system from one image pair of a 3D bead phantom ("cube").

The steps, as XMALab does them and then some:

1. detect beads in each image (:mod:`.beads`, sub-pixel dark blobs);
2. match them to phantom beads (:mod:`.correspond`) from a rough ``initial`` calibration (nominal
   equipment geometry) or from reference beads marked by hand;
3. a DLT with RANSAC per view (:mod:`.dlt`) drops wrong matches and seeds
4. OpenCV's ``calibrateCamera`` per view with the DLT intrinsics as guess (:mod:`.refine`), then
5. a joint refinement of both views and, within tolerance, of the bead positions.

The result converts to the calibration file of architecture.md (:func:`to_calibration`) with per-view
RMS, inlier counts, the date and the method in its ``metadata``.
"""
from __future__ import annotations

import datetime as _dt
import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from appliance.errors import CalibrationError
from appliance.geometry import Calibration, View, triangulate
from appliance.xray_calibration.beads import BeadDetections, detect_beads
from appliance.xray_calibration.correspond import Matches, match_beads, projector_from_references
from appliance.xray_calibration.distortion import GridCorrection
from appliance.xray_calibration.dlt import decompose
from appliance.xray_calibration.phantom import Phantom
from appliance.xray_calibration.refine import ViewFit, refine_jointly, refine_view

log = logging.getLogger(__name__)

VIEW_NAMES = ("p", "q")
Progress = Callable[[str], None]


@dataclass(frozen=True)
class CubeOptions:
    """Tuning of the phantom calibration; the defaults suit a flat-panel biplane system."""

    distortion: str = "none"  # none | k1 | k1k2 | k1k2p | full
    square_pixels: bool = False
    min_radius_px: float = 1.5
    max_radius_px: float = 15.0
    final_gate_px: float = 3.0
    # Joint refinement of both views and the bead positions, each bead within this tolerance (mm) of
    # its nominal position; 0 takes the phantom as exact and keeps the per-view refinement (with exact
    # beads the joint problem separates, and freeing them only adds noise: benchmarks/calibration_sim.py).
    bead_tolerance_mm: float = 0.0
    focal_guess_px: float | None = None  # needed only with 4-5 marked reference beads
    # Keep the intrinsics (K, dist) of the initial calibration and refine only each view's pose
    # (solvePnP): for re-calibrating after the C-arm moved, with intrinsics known from an earlier run.
    fix_intrinsics: bool = False

    @property
    def joint(self) -> bool:
        return self.bead_tolerance_mm > 0


@dataclass
class CubeResult:
    """Everything the calibration found, for the calibration file and the report."""

    phantom: Phantom
    detections: dict[str, BeadDetections]
    matches: dict[str, Matches]
    dlt_fits: dict[str, ViewFit]
    fits: dict[str, ViewFit]
    refined_points_mm: np.ndarray
    options: CubeOptions
    started: str = field(default_factory=lambda: _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"))

    def views(self) -> dict[str, View]:
        return {name: View(name, f.K, f.dist, f.R, f.t, f.image_size) for name, f in self.fits.items()}

    def triangulation_errors_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """Beads seen in both views: phantom rows (k,) and distance (k,) of the triangulated bead from nominal."""
        p, q = self.fits["p"], self.fits["q"]
        common, ip, iq = np.intersect1d(p.bead_rows, q.bead_rows, return_indices=True)
        if len(common) == 0:
            return common, np.zeros(0)
        views = self.views()
        points = np.asarray(triangulate(views["p"], views["q"], p.uv[ip], q.uv[iq]))
        points = points.reshape(len(common), -1)[:, :3]
        return common, np.linalg.norm(points - self.phantom.points_mm[common], axis=1)

    def metadata(self) -> dict[str, Any]:
        rows, tri = self.triangulation_errors_mm()
        meta: dict[str, Any] = {
            "date": self.started,
            "method": "bead phantom: DLT + RANSAC, calibrateCamera per view"
                      + (f", joint refinement (bead tolerance {self.options.bead_tolerance_mm:g} mm)"
                         if self.options.joint else ""),
            "phantom": self.phantom.source,
            "phantom_beads": len(self.phantom),
            "distortion_model": self.options.distortion,
            "intrinsics": "kept from the initial calibration" if self.options.fix_intrinsics else "estimated",
        }
        for name, fit in self.fits.items():
            meta[f"reprojection_rms_px_{name}"] = round(fit.rms_px, 4)
            meta[f"inliers_{name}"] = int(len(fit.bead_rows))
            meta[f"detected_{name}"] = int(len(self.detections[name]))
        if len(tri):
            meta["triangulation_rms_mm"] = round(float(np.sqrt(np.mean(tri ** 2))), 4)
            meta["triangulation_max_mm"] = round(float(tri.max()), 4)
        return meta


def to_calibration(result: CubeResult, extra_metadata: Mapping[str, Any] | None = None) -> Calibration:
    """The validated calibration (architecture.md contract) with provenance in ``metadata``."""
    views = result.views()
    metadata = result.metadata() | dict(extra_metadata or {})
    return Calibration.from_views(views["p"], views["q"], metadata)


def _dlt_fit(name: str, detections: BeadDetections, matches: Matches, image_size: tuple[int, int]) -> ViewFit:
    K, R, t = decompose(matches.P, what=f"view {name}")
    return ViewFit(name, K, np.zeros(5), R, t, image_size, matches.bead_rows,
                   detections.uv[matches.detection_rows], matches.residual_px, np.zeros(0, dtype=int))


def calibrate_cube(images: Mapping[str, np.ndarray], phantom: Phantom, *,
                   initial: Calibration | None = None,
                   references: Mapping[str, Mapping[str, tuple[float, float]]] | None = None,
                   options: CubeOptions = CubeOptions(), progress: Progress | None = None,
                   corrections: Mapping[str, GridCorrection] | None = None) -> CubeResult:
    """Calibrate views ``p`` and ``q`` from phantom images.

    ``initial`` (a rough calibration) or ``references`` (per view: bead id -> marked pixel) provides the
    correspondence; one of them is needed for each view (``references`` wins where both are given).
    ``corrections`` (per view, an image-intensifier map from a perforated plate) are applied to the
    detected bead centres first; the views are then pinhole views of corrected pixels, and the same
    map must be applied to every point measured in that view's images later.
    """
    say = progress or (lambda message: log.info("%s", message))
    phantom.check_for_dlt()
    references = references or {}
    detections: dict[str, BeadDetections] = {}
    matches: dict[str, Matches] = {}
    dlt_fits: dict[str, ViewFit] = {}
    fits: dict[str, ViewFit] = {}
    for name in VIEW_NAMES:
        if name not in images:
            raise CalibrationError(f"no image for view {name}")
        image = np.asarray(images[name])
        image_size = (int(image.shape[1]), int(image.shape[0]))
        say(f"view {name}: detecting beads in {image_size[0]}x{image_size[1]} image")
        found = detect_beads(image, min_radius_px=options.min_radius_px, max_radius_px=options.max_radius_px,
                             bright=phantom.bright_beads, what=f"view {name} image")
        if corrections and name in corrections:
            found = replace(found, uv=corrections[name].apply(found.uv),
                            rejected_uv=corrections[name].apply(found.rejected_uv))
        detections[name] = found
        marked = references.get(name) or {}
        if marked:
            rows = {phantom.index(bead_id): tuple(uv) for bead_id, uv in marked.items()}
            projector = projector_from_references(phantom.points_mm, rows, image_size,
                                                  focal_guess_px=options.focal_guess_px, what=f"view {name}")
            shift_search = False  # marked beads are where the operator clicked: no global shift to find
        elif initial is not None:
            view = initial.views[name]
            if tuple(view.image_size) != image_size:
                raise CalibrationError(f"view {name}: the initial geometry is for {view.image_size[0]}x"
                                       f"{view.image_size[1]} images, this image is {image_size[0]}x{image_size[1]}")
            projector = view.project
            shift_search = True
        else:
            raise CalibrationError(f"view {name}: no initial geometry and no marked reference beads; give "
                                   "--initial or mark reference beads (--ref-{name} ID:u,v)")
        say(f"view {name}: {len(found)} beads detected; matching to {len(phantom)} phantom beads")
        matches[name] = match_beads(phantom.points_mm, found.uv, projector, shift_search=shift_search,
                                    final_gate_px=options.final_gate_px, what=f"view {name}")
        dlt_fits[name] = _dlt_fit(name, found, matches[name], image_size)
        d = dlt_fits[name]
        say(f"view {name}: DLT on {len(d.bead_rows)} beads, RMS {d.rms_px:.3f} px; refining")
        K0, dist0 = d.K, None
        if options.fix_intrinsics:
            if initial is None:
                raise CalibrationError("fixed intrinsics need an initial calibration that holds them (--initial)")
            K0, dist0 = initial.views[name].K, initial.views[name].dist
        fits[name] = refine_view(name, phantom.points_mm, d.bead_rows, d.uv, K0, d.R, d.t, image_size,
                                 distortion=options.distortion, square_pixels=options.square_pixels,
                                 fix_intrinsics=options.fix_intrinsics, dist0=dist0)
    points = phantom.points_mm
    if options.joint:
        say("joint refinement of both views")
        fits, points = refine_jointly(fits, phantom.points_mm, bead_tolerance_mm=options.bead_tolerance_mm,
                                      distortion=options.distortion, square_pixels=options.square_pixels)
    result = CubeResult(phantom, detections, matches, dlt_fits, fits, points, options)
    for name, fit in fits.items():
        say(f"view {name}: {len(fit.bead_rows)} beads, reprojection RMS {fit.rms_px:.3f} px, "
            f"source at {np.round(-fit.R.T @ fit.t, 1).tolist()} mm")
    return result
