"""The calibration report: per-bead residuals (CSV), a summary (text), and a PNG of both views.

The PNG shows each X-ray image (contrast-stretched to 8 bits) with every detected blob (green circle),
the reprojection of every matched phantom bead under the final calibration (red cross, with its id),
blobs rejected as not round (orange), and the residual vectors magnified so sub-pixel errors are
visible. The CSV has one row per view and matched bead: detected and reprojected pixel, residual,
and, for beads seen in both views, the triangulation error against the phantom coordinates.
"""
from __future__ import annotations

import csv
import logging
from pathlib import Path

import cv2
import numpy as np

from appliance.errors import CalibrationError
from appliance.xray_calibration.cube import CubeResult

log = logging.getLogger(__name__)

#: Residual vectors are drawn this many times longer than they are.
RESIDUAL_GAIN = 50.0


def residual_rows(result: CubeResult) -> list[dict[str, object]]:
    """One dict per (view, matched bead) with ids, pixels, residual and triangulation error."""
    common, tri = result.triangulation_errors_mm()
    tri_of = dict(zip(common.tolist(), tri.tolist()))
    rows: list[dict[str, object]] = []
    for name, fit in sorted(result.fits.items()):
        projected = fit.project(result.refined_points_mm[fit.bead_rows])
        for k, bead in enumerate(fit.bead_rows.tolist()):
            rows.append({
                "view": name, "bead": result.phantom.ids[bead],
                "u_detected": round(float(fit.uv[k, 0]), 4), "v_detected": round(float(fit.uv[k, 1]), 4),
                "u_reprojected": round(float(projected[k, 0]), 4), "v_reprojected": round(float(projected[k, 1]), 4),
                "residual_px": round(float(fit.residual_px[k]), 4),
                "triangulation_error_mm": round(tri_of[bead], 4) if bead in tri_of else "",
            })
        for bead in fit.rejected_rows.tolist():
            rows.append({"view": name, "bead": result.phantom.ids[bead], "u_detected": "", "v_detected": "",
                         "u_reprojected": "", "v_reprojected": "", "residual_px": "outlier",
                         "triangulation_error_mm": ""})
    return rows


def write_residuals_csv(path: str | Path, result: CubeResult) -> Path:
    path = Path(path)
    rows = residual_rows(result)
    try:
        with path.open("w", newline="", encoding="utf-8") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    except OSError as err:
        raise CalibrationError(f"{path}: cannot write ({err.strerror or err})") from err
    return path


def summary_text(result: CubeResult) -> str:
    """A short human-readable summary (what the CLI prints)."""
    lines = [f"phantom {result.phantom.source}: {len(result.phantom)} beads"]
    lines.append(f"{'view':<5}{'detected':>9}{'matched':>9}{'outliers':>9}{'RMS px':>9}{'max px':>9}"
                 f"{'fx px':>10}{'fy px':>10}{'cx':>9}{'cy':>9}  source mm")
    for name, fit in sorted(result.fits.items()):
        source = -fit.R.T @ fit.t
        lines.append(f"{name:<5}{len(result.detections[name]):>9}{len(fit.bead_rows):>9}{len(fit.rejected_rows):>9}"
                     f"{fit.rms_px:>9.3f}{fit.residual_px.max():>9.3f}{fit.K[0, 0]:>10.1f}{fit.K[1, 1]:>10.1f}"
                     f"{fit.K[0, 2]:>9.1f}{fit.K[1, 2]:>9.1f}  [{source[0]:.1f}, {source[1]:.1f}, {source[2]:.1f}]")
    common, tri = result.triangulation_errors_mm()
    if len(tri):
        lines.append(f"beads triangulated from both views: {len(tri)}, error RMS {np.sqrt(np.mean(tri ** 2)):.3f} mm, "
                     f"max {tri.max():.3f} mm (bead {result.phantom.ids[int(common[np.argmax(tri)])]})")
    return "\n".join(lines)


def _to_8bit(image: np.ndarray) -> np.ndarray:
    values = np.asarray(image, dtype=np.float64)
    lo, hi = np.percentile(values, [0.5, 99.5])
    scaled = np.clip((values - lo) / max(hi - lo, 1e-9), 0, 1) * 255
    return cv2.cvtColor(scaled.astype(np.uint8), cv2.COLOR_GRAY2BGR)


def draw_view(image: np.ndarray, result: CubeResult, name: str) -> np.ndarray:
    """One annotated view (BGR, 8 bit)."""
    canvas = _to_8bit(image)
    found, fit = result.detections[name], result.fits[name]
    for (u, v), r in zip(found.uv, found.radius_px):
        cv2.circle(canvas, (int(round(u)), int(round(v))), int(round(r)) + 3, (0, 200, 0), 1, cv2.LINE_AA)
    for u, v in found.rejected_uv:
        cv2.circle(canvas, (int(round(u)), int(round(v))), 6, (0, 140, 255), 1, cv2.LINE_AA)
    projected = fit.project(result.refined_points_mm[fit.bead_rows])
    for k, bead in enumerate(fit.bead_rows.tolist()):
        pu, pv = projected[k]
        du, dv = fit.uv[k] - projected[k]
        centre = (int(round(pu)), int(round(pv)))
        cv2.drawMarker(canvas, centre, (0, 0, 255), cv2.MARKER_CROSS, 8, 1, cv2.LINE_AA)
        tip = (int(round(pu + RESIDUAL_GAIN * du)), int(round(pv + RESIDUAL_GAIN * dv)))
        cv2.line(canvas, centre, tip, (255, 0, 255), 1, cv2.LINE_AA)
        cv2.putText(canvas, result.phantom.ids[bead], (centre[0] + 6, centre[1] - 6), cv2.FONT_HERSHEY_SIMPLEX,
                    0.35, (0, 255, 255), 1, cv2.LINE_AA)
    title = f"view {name}: {len(fit.bead_rows)} beads, RMS {fit.rms_px:.3f} px (residuals x{RESIDUAL_GAIN:g})"
    cv2.putText(canvas, title, (8, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return canvas


def write_report_png(path: str | Path, images: dict[str, np.ndarray], result: CubeResult) -> Path:
    """Both annotated views side by side."""
    path = Path(path)
    panels = [draw_view(images[name], result, name) for name in sorted(result.fits)]
    height = max(p.shape[0] for p in panels)
    panels = [cv2.copyMakeBorder(p, 0, height - p.shape[0], 0, 4, cv2.BORDER_CONSTANT) for p in panels]
    if not cv2.imwrite(str(path), np.hstack(panels)):
        raise CalibrationError(f"{path}: cannot write the report image")
    return path


def write_report(directory: str | Path, images: dict[str, np.ndarray], result: CubeResult,
                 stem: str = "calibration") -> dict[str, Path]:
    """Write ``<stem>_residuals.csv``, ``<stem>_report.png`` and ``<stem>_report.txt`` into ``directory``."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths = {"csv": write_residuals_csv(directory / f"{stem}_residuals.csv", result),
             "png": write_report_png(directory / f"{stem}_report.png", images, result)}
    text = directory / f"{stem}_report.txt"
    text.write_text(summary_text(result) + "\n", encoding="utf-8")
    paths["txt"] = text
    log.info("calibration report written to %s", directory)
    return paths
