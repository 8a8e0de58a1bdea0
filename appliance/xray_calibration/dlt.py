"""Direct linear transform (DLT) of a view from 3D-2D bead correspondences, with RANSAC.

The 3x4 projection ``P`` (11 degrees of freedom) is the null vector of the stacked linear equations of
``u ~ P X``; points are normalised first (Hartley: centroid at the origin, mean distance sqrt(2) in
the image, sqrt(3) in space) so the SVD is well conditioned. ``P`` is then split into ``K [R | t]``
by an RQ decomposition. Six points in general position are the minimum; points on one plane (or a
line) leave ``P`` undetermined, and we say so instead of returning an arbitrary matrix.

RANSAC draws minimal 6-point samples, keeps the ``P`` with the most beads reprojecting within a pixel
threshold, refits on those inliers and repeats the inlier search until it stops changing.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from appliance.errors import CalibrationError

log = logging.getLogger(__name__)

MIN_POINTS = 6
#: Smallest singular value of the centred points relative to the largest: below it, "planar".
PLANARITY_RATIO = 1e-3


def _normaliser(points: np.ndarray) -> np.ndarray:
    """Similarity (dim+1 square) that centres ``points`` and scales their mean distance to sqrt(dim)."""
    dim = points.shape[1]
    centre = points.mean(axis=0)
    spread = np.mean(np.linalg.norm(points - centre, axis=1))
    scale = np.sqrt(dim) / spread if spread > 0 else 1.0
    T = np.eye(dim + 1)
    T[:dim, :dim] *= scale
    T[:dim, dim] = -scale * centre
    return T


def check_general_position(points_mm: np.ndarray, what: str = "beads") -> None:
    """Raise :class:`CalibrationError` if 3D points are too few, collinear or coplanar for a DLT."""
    points = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    if len(points) < MIN_POINTS:
        raise CalibrationError(f"{what}: {len(points)} points; the DLT needs at least {MIN_POINTS}")
    s = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    if s[0] <= 0 or s[1] / s[0] < PLANARITY_RATIO:
        raise CalibrationError(f"{what}: the points are collinear; a view cannot be calibrated from them")
    if s[2] / s[0] < PLANARITY_RATIO:
        raise CalibrationError(f"{what}: the points are coplanar; the DLT needs beads on several planes "
                               "(use the planar grid method with several poses for flat targets)")


def _is_degenerate(points: np.ndarray) -> bool:
    s = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return bool(s[0] <= 0 or s[2] / s[0] < 0.05)


def dlt(points_mm: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """The projection matrix ``P`` (3x4, ``P[2, :3]`` of unit norm, positive depth) from >= 6 correspondences."""
    X = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    x = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if len(X) != len(x):
        raise ValueError(f"{len(X)} 3D points but {len(x)} image points")
    check_general_position(X)
    T3, T2 = _normaliser(X), _normaliser(x)
    Xn = (np.column_stack([X, np.ones(len(X))]) @ T3.T)
    xn = (np.column_stack([x, np.ones(len(x))]) @ T2.T)
    rows = np.zeros((2 * len(X), 12))
    rows[0::2, 0:4] = Xn
    rows[0::2, 8:12] = -xn[:, 0:1] * Xn
    rows[1::2, 4:8] = Xn
    rows[1::2, 8:12] = -xn[:, 1:2] * Xn
    _, _, vt = np.linalg.svd(rows)
    Pn = vt[-1].reshape(3, 4)
    P = np.linalg.inv(T2) @ Pn @ T3
    P /= np.linalg.norm(P[2, :3])
    # Orient so that the beads are in front of the source (positive depth).
    if np.median(np.column_stack([X, np.ones(len(X))]) @ P[2]) < 0:
        P = -P
    return P


def project(P: np.ndarray, points_mm: np.ndarray) -> np.ndarray:
    """Pixels (N,2) of world points (N,3) under ``P``."""
    h = np.column_stack([points_mm, np.ones(len(points_mm))]) @ P.T
    return h[:, :2] / h[:, 2:3]


def decompose(P: np.ndarray, what: str = "view") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``P = s K [R | t]`` -> ``K`` (positive diagonal, ``K[2,2] = 1``), rotation ``R`` (det +1), ``t``.

    With ``P`` oriented so that the beads have positive depth (as :func:`dlt` returns it), an improper
    ``R`` means the image is a mirror image of a pinhole view (a flipped detector read-out).
    """
    K, R = scipy.linalg.rq(P[:, :3])
    signs = np.diag(np.sign(np.diag(K)))
    K, R = K @ signs, signs @ R  # signs is its own inverse, so K R is unchanged
    t = np.linalg.solve(K, P[:, 3])
    if np.linalg.det(R) < 0:
        raise CalibrationError(f"{what}: the bead image is a mirror image of a pinhole view (improper rotation); "
                               "the detector read-out is probably flipped -- flip the image before calibrating")
    return K / K[2, 2], R, t


@dataclass(frozen=True)
class RansacResult:
    P: np.ndarray
    inliers: np.ndarray  # bool (N,)
    residual_px: np.ndarray  # (N,) reprojection distance of every correspondence under P
    iterations: int


def ransac_dlt(points_mm: np.ndarray, uv: np.ndarray, *, threshold_px: float = 3.0, confidence: float = 0.999,
               max_iterations: int = 2000, seed: int = 0, what: str = "view") -> RansacResult:
    """Robust DLT: correspondences further than ``threshold_px`` from the consensus ``P`` are outliers."""
    X = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    x = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    check_general_position(X, what=f"{what}: matched beads")
    n = len(X)
    rng = np.random.default_rng(seed)
    best: np.ndarray | None = None
    best_count, iterations, needed = 0, 0, max_iterations
    while iterations < min(needed, max_iterations):
        iterations += 1
        sample = rng.choice(n, MIN_POINTS, replace=False)
        if _is_degenerate(X[sample]):
            continue
        try:
            P = dlt(X[sample], x[sample])
        except (CalibrationError, np.linalg.LinAlgError):
            continue
        with np.errstate(divide="ignore", invalid="ignore"):
            inliers = np.linalg.norm(project(P, X) - x, axis=1) < threshold_px
        count = int(inliers.sum())
        if count > best_count:
            best, best_count = inliers, count
            ratio = count / n
            # Adaptive stop: enough draws that an all-inlier sample was drawn with `confidence`.
            miss = 1.0 - ratio ** MIN_POINTS
            needed = int(np.ceil(np.log(1 - confidence) / np.log(miss))) if 0 < miss < 1 else iterations
    if best is None or best_count < MIN_POINTS + 2:
        raise CalibrationError(f"{what}: RANSAC found no consistent projection ({best_count} of {n} beads agree "
                               f"within {threshold_px:g} px); check the bead correspondences or the initial geometry")
    inliers = best
    for _ in range(10):
        P = dlt(X[inliers], x[inliers])
        residual = np.linalg.norm(project(P, X) - x, axis=1)
        updated = residual < threshold_px
        if updated.sum() < MIN_POINTS or np.array_equal(updated, inliers):
            break
        inliers = updated
    log.debug("%s: RANSAC %d iterations, %d/%d inliers", what, iterations, int(inliers.sum()), n)
    return RansacResult(P, inliers, residual, iterations)
