"""Second calibration method: a planar grid (checkerboard, or a circle grid of metal balls) in several poses.

Zhang's method: each view is calibrated from several images of the plane (OpenCV ``calibrateCamera``;
a plane alone fixes intrinsics only through the variety of its poses), then the pose of view q
relative to view p comes from the grid poses both views saw at the same time (``stereoCalibrate``
with the intrinsics fixed). The world frame is the grid's own frame in one chosen pose (``world_pose``,
default the first), so the result is a complete biplane calibration; to express it in another frame
(the bead phantom's, the OTS's) register afterwards.

For X-ray, a circle grid of steel balls in an acrylic plate images like the bead phantom; the
asymmetric layout (``"acircles"``) has no 180-degree ambiguity, so both views order the balls alike.
Detected grids are refined to the attenuation-weighted bead centres of :mod:`.beads`.
"""
from __future__ import annotations

import datetime as _dt
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from appliance.errors import CalibrationError
from appliance.geometry import Calibration, View
from appliance.xray_calibration.beads import detect_beads

log = logging.getLogger(__name__)

PATTERNS = ("checkerboard", "circles", "acircles")
MIN_POSES = 3


def grid_points(pattern: str, cols: int, rows: int, pitch_mm: float) -> np.ndarray:
    """Grid points (cols*rows, 3) in the grid frame (z = 0), in OpenCV's detection order.

    ``cols`` x ``rows`` counts inner corners for a checkerboard and balls for circle grids; for the
    asymmetric grid ``pitch_mm`` is the distance between neighbouring balls of one row over two.
    """
    if pattern not in PATTERNS:
        raise CalibrationError(f"unknown grid pattern {pattern!r}; use one of {', '.join(PATTERNS)}")
    if cols < 2 or rows < 2 or pitch_mm <= 0:
        raise CalibrationError(f"grid needs at least 2x2 points and a positive pitch, got {cols}x{rows}, {pitch_mm}")
    points = []
    for i in range(rows):
        for j in range(cols):
            if pattern == "acircles":
                points.append(((2 * j + i % 2) * pitch_mm / 2, i * pitch_mm / 2, 0.0))
            else:
                points.append((j * pitch_mm, i * pitch_mm, 0.0))
    return np.asarray(points)


def _to_8bit(image: np.ndarray) -> np.ndarray:
    values = np.asarray(image, dtype=np.float64)
    lo, hi = np.percentile(values, [0.5, 99.5])
    return (np.clip((values - lo) / max(hi - lo, 1e-9), 0, 1) * 255).astype(np.uint8)


def detect_grid(image: np.ndarray, pattern: str, cols: int, rows: int, *, max_radius_px: float = 15.0) -> np.ndarray | None:
    """Pixel positions (cols*rows, 2) of the grid points in OpenCV order, or None if the grid is not found."""
    gray = _to_8bit(image)
    if pattern == "checkerboard":
        found, corners = cv2.findChessboardCornersSB(gray, (cols, rows), flags=cv2.CALIB_CB_ACCURACY)
        return corners.reshape(-1, 2).astype(np.float64) if found else None
    flags = cv2.CALIB_CB_ASYMMETRIC_GRID if pattern == "acircles" else cv2.CALIB_CB_SYMMETRIC_GRID
    params = cv2.SimpleBlobDetector_Params()
    params.filterByColor, params.blobColor = True, 0  # metal balls are dark in a raw X-ray image
    params.minArea, params.maxArea = 6.0, float(np.pi * max_radius_px ** 2 * 2)
    detector = cv2.SimpleBlobDetector_create(params)
    found, centres = cv2.findCirclesGrid(gray, (cols, rows), flags=flags, blobDetector=detector)
    if not found:
        return None
    coarse = centres.reshape(-1, 2).astype(np.float64)
    # The blob detector's centres are binary centroids; snap them to attenuation-weighted bead centres.
    try:
        beads = detect_beads(image, max_radius_px=max_radius_px)
    except CalibrationError:
        return coarse
    distance, index = cKDTree(beads.uv).query(coarse)
    spacing = float(np.median(np.linalg.norm(np.diff(coarse, axis=0), axis=1)))
    refined = coarse.copy()
    close = distance < 0.25 * spacing
    refined[close] = beads.uv[index[close]]
    return refined


def grid_symmetries(object_points: np.ndarray) -> list[np.ndarray]:
    """Permutations of the grid points under which the grid looks the same (identity first).

    A detector orders a symmetric grid from the image alone, so two views (or two poses) may number
    it differently by one of these; each is a rigid motion of the plate, so a single view cannot tell,
    but the two views' relative pose can.
    """
    xy = np.asarray(object_points, dtype=np.float64)[:, :2]
    centre = xy.mean(axis=0)
    tree = cKDTree(xy)
    tolerance = 1e-6 * max(1.0, float(np.abs(xy - centre).max()))
    found: list[np.ndarray] = []
    for angle in (0, 90, 180, 270):
        c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
        for mirror in (1.0, -1.0):
            A = np.array([[c, -s], [s, c]]) @ np.diag([1.0, mirror])
            mapped = (xy - centre) @ A.T + centre
            distance, index = tree.query(mapped)
            if np.all(distance < tolerance) and len(set(index.tolist())) == len(xy):
                if not any(np.array_equal(index, f) for f in found):
                    found.append(index)
    return found


def _relative_pose(obj: np.ndarray, uv_p: np.ndarray, uv_q: np.ndarray, Kp: np.ndarray, dp: np.ndarray,
                   Kq: np.ndarray, dq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    poses = []
    for uv, K, d in ((uv_p, Kp, dp), (uv_q, Kq, dq)):
        _, rvec, tvec = cv2.solvePnP(obj, uv.reshape(-1, 1, 2), K, d, flags=cv2.SOLVEPNP_ITERATIVE)
        poses.append((cv2.Rodrigues(rvec)[0], tvec.ravel()))
    (Rp, tp), (Rq, tq) = poses
    R = Rq @ Rp.T
    return R, tq - R @ tp


def _consistent_labels(obj: np.ndarray, pairs: list[tuple[np.ndarray, np.ndarray]], Kp: np.ndarray, dp: np.ndarray,
                       Kq: np.ndarray, dq: np.ndarray) -> list[np.ndarray]:
    """Renumber view q's grid in each pose so that all poses agree on one relative pose of q to p."""
    symmetries = grid_symmetries(obj)
    if len(symmetries) == 1:
        return [q for _, q in pairs]
    candidates = [[(_relative_pose(obj, p, q[perm], Kp, dp, Kq, dq), perm) for perm in symmetries] for p, q in pairs]

    def agree(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> bool:
        angle = np.degrees(np.linalg.norm(cv2.Rodrigues(a[0] @ b[0].T)[0]))
        return bool(angle < 2.0 and np.linalg.norm(a[1] - b[1]) < 0.02 * np.linalg.norm(a[1]) + 1.0)

    best: list[np.ndarray] | None = None
    best_votes = -1
    for reference, _ in candidates[0]:
        chosen, votes = [], 0
        for options in candidates:
            match = next((perm for pose, perm in options if agree(pose, reference)), None)
            votes += match is not None
            chosen.append(match if match is not None else options[0][1])
        if votes > best_votes:
            best, best_votes = chosen, votes
    assert best is not None
    if best_votes < len(pairs):
        log.warning("grid: %d of %d poses disagree with the others on the relative pose of q", len(pairs) - best_votes,
                    len(pairs))
    return [q[perm] for (_, q), perm in zip(pairs, best)]


@dataclass(frozen=True)
class GridResult:
    calibration: Calibration
    rms_px: dict[str, float]  # per view, from calibrateCamera
    stereo_rms_px: float
    poses_used: dict[str, int]  # per view
    common_poses: int


def calibrate_grids(observations: Sequence[Mapping[str, np.ndarray | None]], object_points: np.ndarray,
                    image_sizes: Mapping[str, tuple[int, int]], *, world_pose: int = 0,
                    distortion: str = "none") -> GridResult:
    """Both views from grid detections: ``observations[k][view]`` is the (N,2) grid seen in pose k, or None."""
    obj = np.asarray(object_points, dtype=np.float32).reshape(-1, 1, 3)
    flags = {"none": cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
             "k1k2": cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST, "full": 0}.get(distortion)
    if flags is None:
        raise CalibrationError(f"grid calibration: distortion model must be none, k1k2 or full, got {distortion!r}")
    intrinsics: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    rms: dict[str, float] = {}
    used: dict[str, int] = {}
    for name in ("p", "q"):
        seen = [np.asarray(o[name], np.float32).reshape(-1, 1, 2) for o in observations if o.get(name) is not None]
        if len(seen) < MIN_POSES:
            raise CalibrationError(f"grid calibration: view {name} saw the grid in {len(seen)} poses; "
                                   f"at least {MIN_POSES} differently tilted poses are needed")
        error, K, dist, _, _ = cv2.calibrateCamera([obj] * len(seen), seen, tuple(image_sizes[name]), None, None,
                                                   flags=flags)
        intrinsics[name], rms[name], used[name] = (K, dist.ravel()), float(error), len(seen)
        log.info("grid: view %s from %d poses, RMS %.3f px", name, len(seen), error)
    both = [k for k, o in enumerate(observations) if o.get("p") is not None and o.get("q") is not None]
    if world_pose not in both:
        raise CalibrationError(f"grid calibration: the world pose {world_pose} must be seen by both views "
                               f"(poses seen by both: {both})")
    (Kp, dp), (Kq, dq) = intrinsics["p"], intrinsics["q"]
    pairs = [(np.asarray(observations[k]["p"], np.float64).reshape(-1, 2),
              np.asarray(observations[k]["q"], np.float64).reshape(-1, 2)) for k in both]
    relabelled = _consistent_labels(np.asarray(object_points, np.float64), pairs, Kp, dp, Kq, dq)
    pts_p = [p.astype(np.float32).reshape(-1, 1, 2) for p, _ in pairs]
    pts_q = [q.astype(np.float32).reshape(-1, 1, 2) for q in relabelled]
    stereo_rms, _, _, _, _, R_pq, T_pq, _, _ = cv2.stereoCalibrate(
        [obj] * len(both), pts_p, pts_q, Kp, dp, Kq, dq, tuple(image_sizes["p"]), flags=cv2.CALIB_FIX_INTRINSIC)
    ok, rvec, tvec = cv2.solvePnP(obj, pts_p[both.index(world_pose)], Kp, dp, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise CalibrationError("grid calibration: no pose for the world grid in view p")
    R_p, _ = cv2.Rodrigues(rvec)
    t_p = tvec.ravel()
    R_q = R_pq @ R_p
    t_q = R_pq @ t_p + T_pq.ravel()

    def five(d: np.ndarray) -> np.ndarray:
        out = np.zeros(5)
        out[: min(5, d.size)] = d[:5]
        return out

    views = (View("p", Kp, five(dp), R_p, t_p, tuple(image_sizes["p"])),
             View("q", Kq, five(dq), R_q, t_q, tuple(image_sizes["q"])))
    metadata = {"date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                "method": f"planar grid, {len(observations)} poses (Zhang + stereoCalibrate); world = grid pose "
                          f"{world_pose}", "reprojection_rms_px_p": round(rms["p"], 4),
                "reprojection_rms_px_q": round(rms["q"], 4), "stereo_rms_px": round(float(stereo_rms), 4),
                "inliers_p": used["p"] * len(object_points), "inliers_q": used["q"] * len(object_points)}
    return GridResult(Calibration.from_views(*views, metadata), rms, float(stereo_rms), used, len(both))
