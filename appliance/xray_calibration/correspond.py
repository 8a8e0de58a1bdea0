"""Which detected blob is which phantom bead: from a rough geometry or from a few marked reference beads.

A rough geometry (nominal source distances and angles, or a DLT of 6+ hand-marked reference beads)
predicts every bead's pixel, but 1-2 degrees of error at 500 mm moves the whole pattern by tens of
pixels -- more than the spacing of the beads. So matching runs coarse to fine:

1. the dominant 2D shift between predictions and detections is found by voting over all pairwise
   differences (the phantom is irregular, so exactly one shift lines most beads up);
2. mutual nearest neighbours within a wide gate fit a 2D affine map (robustly), which absorbs
   in-plane rotation and magnification errors;
3. the matches seed a RANSAC DLT whose projections are matched again within a tight gate, until the
   set of matches stops changing.
"""
from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from appliance.errors import CalibrationError
from appliance.xray_calibration.dlt import MIN_POINTS, dlt, project, ransac_dlt

log = logging.getLogger(__name__)

Projector = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class Matches:
    """Phantom rows (k,) matched to detection rows (k,), and the DLT projection ``P`` they agree on."""

    bead_rows: np.ndarray
    detection_rows: np.ndarray
    P: np.ndarray
    residual_px: np.ndarray  # (k,) distance between detection and DLT projection


def mutual_nearest(predicted: np.ndarray, detected: np.ndarray, gate_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (i, j) where detection j is the nearest to prediction i and vice versa, within ``gate_px``."""
    valid = np.all(np.isfinite(predicted), axis=1)
    if not valid.any() or len(detected) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    rows = np.flatnonzero(valid)
    d_to_p, j_of_p = cKDTree(detected).query(predicted[rows])
    _, i_of_d = cKDTree(predicted[rows]).query(detected)
    keep = (d_to_p < gate_px) & (i_of_d[j_of_p] == np.arange(len(rows)))
    return rows[keep], j_of_p[keep]


def dominant_shift(predicted: np.ndarray, detected: np.ndarray, bin_px: float) -> np.ndarray:
    """The 2D shift that puts the most predictions onto detections (vote over all pairwise differences)."""
    predicted = predicted[np.all(np.isfinite(predicted), axis=1)]
    diffs = (detected[None, :, :] - predicted[:, None, :]).reshape(-1, 2)
    keys = np.floor(diffs / bin_px).astype(np.int64)
    # Vote with 2x2-bin neighbourhoods so a shift on a bin border is not split between bins.
    votes: dict[tuple[int, int], int] = {}
    for kx, ky in keys:
        for ox in (0, -1):
            for oy in (0, -1):
                key = (int(kx + ox), int(ky + oy))
                votes[key] = votes.get(key, 0) + 1
    (bx, by), _ = max(votes.items(), key=lambda item: item[1])
    lo = np.array([bx, by]) * bin_px
    inside = np.all((diffs >= lo) & (diffs < lo + 2 * bin_px), axis=1)
    return diffs[inside].mean(axis=0)


def _spacing(points: np.ndarray) -> float:
    """Median distance of a point to its nearest neighbour."""
    if len(points) < 2:
        return 50.0
    d, _ = cKDTree(points).query(points, k=2)
    return float(np.median(d[:, 1]))


def match_beads(points_mm: np.ndarray, detected_uv: np.ndarray, projector: Projector, *,
                shift_search: bool = True, final_gate_px: float = 3.0, what: str = "view") -> Matches:
    """Match phantom beads to detections starting from ``projector`` (world mm -> predicted pixels)."""
    X = np.asarray(points_mm, dtype=np.float64)
    detected = np.asarray(detected_uv, dtype=np.float64)
    predicted = np.asarray(projector(X), dtype=np.float64)
    spacing = _spacing(detected)
    if shift_search:
        shift = dominant_shift(predicted, detected, bin_px=max(1.0, 0.25 * spacing))
        predicted = predicted + shift
        log.debug("%s: initial geometry off by (%.1f, %.1f) px", what, *shift)
    rows, cols = mutual_nearest(predicted, detected, gate_px=0.45 * spacing)
    if len(rows) >= 4:
        affine, ok = cv2.estimateAffine2D(predicted[rows], detected[cols], ransacReprojThreshold=0.15 * spacing)
        if affine is not None and ok is not None and ok.sum() >= 4:
            predicted = predicted @ affine[:, :2].T + affine[:, 2]
            rows, cols = mutual_nearest(predicted, detected, gate_px=0.35 * spacing)
    if len(rows) < MIN_POINTS + 2:
        raise CalibrationError(
            f"{what}: only {len(rows)} beads could be matched to the {len(detected)} detected blobs from the "
            "initial geometry; give a closer --initial geometry or mark reference beads")
    gate = max(final_gate_px, 0.15 * spacing)
    result = ransac_dlt(X[rows], detected[cols], threshold_px=gate, what=what)
    P = result.P
    previous: set[tuple[int, int]] = set()
    for _ in range(8):
        rows, cols = mutual_nearest(project(P, X), detected, gate_px=gate)
        current = set(zip(rows.tolist(), cols.tolist()))
        if current == previous or len(rows) < MIN_POINTS + 2:
            break
        previous = current
        result = ransac_dlt(X[rows], detected[cols], threshold_px=gate, what=what)
        P = result.P
        keep = result.inliers
        rows, cols = rows[keep], cols[keep]
        # Tighten towards the final gate as the projection improves.
        gate = max(final_gate_px, min(gate, 4.0 * float(np.sqrt(np.mean(result.residual_px[keep] ** 2))) + 0.5))
    if len(rows) < MIN_POINTS + 2:
        raise CalibrationError(f"{what}: only {len(rows)} beads matched consistently; cannot calibrate")
    P = dlt(X[rows], detected[cols])
    residual = np.linalg.norm(project(P, X[rows]) - detected[cols], axis=1)
    log.info("%s: %d beads matched (DLT RMS %.3f px)", what, len(rows), float(np.sqrt(np.mean(residual ** 2))))
    return Matches(rows, cols, P, residual)


def projector_from_references(points_mm: np.ndarray, reference_uv: dict[int, tuple[float, float]],
                              image_size: tuple[int, int], *, focal_guess_px: float | None = None,
                              what: str = "view") -> Projector:
    """A projector from hand-marked beads: phantom row -> (u, v).

    Six or more marked beads give a DLT; four or five need a focal-length guess (pixels) and give a
    pose by ``solvePnP`` with the principal point at the image centre.
    """
    rows = np.array(sorted(reference_uv), dtype=int)
    uv = np.array([reference_uv[r] for r in rows], dtype=np.float64).reshape(-1, 2)
    X = np.asarray(points_mm, dtype=np.float64)
    if len(rows) >= MIN_POINTS:
        P = dlt(X[rows], uv)
        return lambda points: project(P, points)
    if len(rows) >= 4 and focal_guess_px:
        w, h = image_size
        K = np.array([[focal_guess_px, 0, (w - 1) / 2], [0, focal_guess_px, (h - 1) / 2], [0, 0, 1.0]])
        ok, rvec, tvec = cv2.solvePnP(X[rows], uv, K, None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            raise CalibrationError(f"{what}: the marked reference beads give no consistent pose")
        return lambda points: cv2.projectPoints(points, rvec, tvec, K, None)[0].reshape(-1, 2)
    raise CalibrationError(
        f"{what}: {len(rows)} reference beads marked; mark at least {MIN_POINTS} (or 4 with a focal-length guess)")
