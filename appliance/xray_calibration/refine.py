"""Non-linear refinement of each view, then of both views together.

Per view, the DLT's ``K [R | t]`` seeds OpenCV's ``calibrateCamera`` (which requires an intrinsic guess
for a non-planar rig) minimising reprojection error over focal lengths, principal point, pose and the
chosen distortion terms; with intrinsics already known (``fix_intrinsics``), ``solvePnP`` refines the
pose alone. Correspondences whose residual is far above the robust noise level are dropped and the
fit repeated once.

The joint refinement adjusts both views and, within the phantom's manufacturing tolerance, the bead
positions themselves (a bundle adjustment with a prior that keeps beads near their nominal
coordinates and so fixes the world frame). With a perfect phantom it changes little; with a phantom
whose beads are off by tens of microns it keeps the two views consistent with each other, which is
what triangulation needs.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy.optimize import least_squares

from appliance.errors import CalibrationError

log = logging.getLogger(__name__)

#: Which OpenCV distortion terms are estimated (the others stay zero).
DISTORTION_MODELS = ("none", "k1", "k1k2", "k1k2p", "full")
_FIXED_FLAGS = {
    "none": cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "k1": cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "k1k2": cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "k1k2p": cv2.CALIB_FIX_K3,
    "full": 0,
}
_FREE_DIST = {"none": [], "k1": [0], "k1k2": [0, 1], "k1k2p": [0, 1, 2, 3], "full": [0, 1, 2, 3, 4]}


@dataclass(frozen=True)
class ViewFit:
    """A calibrated view and the correspondences it was fitted to."""

    name: str
    K: np.ndarray
    dist: np.ndarray  # (5,) k1 k2 p1 p2 k3
    R: np.ndarray
    t: np.ndarray
    image_size: tuple[int, int]
    bead_rows: np.ndarray  # phantom rows of the inlier correspondences
    uv: np.ndarray  # (k,2) detected pixels of those beads
    residual_px: np.ndarray  # (k,) reprojection distances
    rejected_rows: np.ndarray  # phantom rows dropped as outliers in refinement

    @property
    def rms_px(self) -> float:
        return float(np.sqrt(np.mean(self.residual_px ** 2)))

    def project(self, points_mm: np.ndarray) -> np.ndarray:
        rvec, _ = cv2.Rodrigues(self.R)
        return cv2.projectPoints(np.asarray(points_mm, np.float64).reshape(-1, 1, 3), rvec, self.t,
                                 self.K, self.dist)[0].reshape(-1, 2)


def _residuals(fit: ViewFit, points_mm: np.ndarray) -> np.ndarray:
    return np.linalg.norm(fit.project(points_mm[fit.bead_rows]) - fit.uv, axis=1)


def _calibrate_once(name: str, X: np.ndarray, uv: np.ndarray, K0: np.ndarray, dist0: np.ndarray, R0: np.ndarray,
                    t0: np.ndarray, image_size: tuple[int, int], distortion: str, square_pixels: bool,
                    fix_intrinsics: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    obj = X.reshape(-1, 1, 3).astype(np.float32)
    img = uv.reshape(-1, 1, 2).astype(np.float32)
    if fix_intrinsics:
        rvec, _ = cv2.Rodrigues(R0)
        ok, rvec, tvec = cv2.solvePnP(X, uv, K0, dist0, rvec.copy(), np.asarray(t0, np.float64).reshape(3, 1).copy(),
                                      useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            raise CalibrationError(f"view {name}: solvePnP failed")
        rvec, tvec = cv2.solvePnPRefineLM(X, uv, K0, dist0, rvec, tvec)
        R, _ = cv2.Rodrigues(rvec)
        return K0.copy(), dist0.copy(), R, tvec.ravel()
    K = K0.copy()
    K[0, 1] = 0.0  # OpenCV's model has no skew; the DLT's is noise around zero for a real detector
    if square_pixels:
        K[0, 0] = K[1, 1] = 0.5 * (K0[0, 0] + K0[1, 1])
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | _FIXED_FLAGS[distortion]
    if square_pixels:
        flags |= cv2.CALIB_FIX_ASPECT_RATIO
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    _, K, dist, rvecs, tvecs = cv2.calibrateCamera([obj], [img], image_size, K, dist0.reshape(1, -1).copy(),
                                                   flags=flags, criteria=criteria)
    R, _ = cv2.Rodrigues(rvecs[0])
    d = np.zeros(5)
    d[: min(5, dist.size)] = dist.ravel()[:5]
    return K, d, R, tvecs[0].ravel()


def refine_view(name: str, points_mm: np.ndarray, bead_rows: np.ndarray, uv: np.ndarray, K0: np.ndarray,
                R0: np.ndarray, t0: np.ndarray, image_size: tuple[int, int], *, distortion: str = "none",
                square_pixels: bool = False, fix_intrinsics: bool = False, dist0: np.ndarray | None = None,
                outlier_sigma: float = 4.0, max_rounds: int = 4) -> ViewFit:
    """Refine one view from matched beads; drops correspondences above ``outlier_sigma`` robust sigmas.

    ``K0`` (and ``dist0``) seed ``calibrateCamera``; with ``fix_intrinsics`` they are kept and only the
    pose is refined by ``solvePnP``, starting from ``R0``, ``t0``.
    """
    if distortion not in DISTORTION_MODELS:
        raise CalibrationError(f"view {name}: unknown distortion model {distortion!r}; use one of {DISTORTION_MODELS}")
    X = np.asarray(points_mm, dtype=np.float64)
    rows = np.asarray(bead_rows, dtype=int)
    uv = np.asarray(uv, dtype=np.float64)
    dist = np.zeros(5) if dist0 is None else np.asarray(dist0, dtype=np.float64).ravel()[:5]
    K, R, t = np.asarray(K0, dtype=np.float64), np.asarray(R0, dtype=np.float64), np.asarray(t0, dtype=np.float64)
    rejected = np.zeros(0, dtype=int)
    for round_number in range(max_rounds):
        K, dist_fit, R, t = _calibrate_once(name, X[rows], uv, K, dist, R, t, image_size, distortion,
                                            square_pixels, fix_intrinsics)
        fit = ViewFit(name, K, dist_fit, R, t, image_size, rows, uv, np.zeros(len(rows)), rejected)
        residual = _residuals(fit, X)
        fit = replace(fit, residual_px=residual)
        # Robust scale (MAD), floored so that a near-perfect fit does not reject good beads for 0.05 px.
        sigma = max(1.4826 * float(np.median(residual)), 0.05)
        bad = residual > outlier_sigma * sigma + 0.25
        if not bad.any() or len(rows) - bad.sum() < 8 or round_number == max_rounds - 1:
            break
        rejected = np.concatenate([rejected, rows[bad]])
        rows, uv = rows[~bad], uv[~bad]
    log.info("view %s: refined on %d beads, RMS %.3f px, f = %.1f px, %d outliers", name, len(fit.bead_rows),
             fit.rms_px, fit.K[0, 0], len(fit.rejected_rows))
    return fit


def _unpack(params: np.ndarray, free_dist: list[int], square: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                           np.ndarray]:
    i = 0
    fx = params[i]
    fy = params[i] if square else params[i + 1]
    i += 1 if square else 2
    cx, cy = params[i], params[i + 1]
    i += 2
    rvec, tvec = params[i:i + 3], params[i + 3:i + 6]
    i += 6
    dist = np.zeros(5)
    dist[free_dist] = params[i:i + len(free_dist)]
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    return K, dist, rvec, tvec


def _pack(fit: ViewFit, free_dist: list[int], square: bool) -> np.ndarray:
    rvec, _ = cv2.Rodrigues(fit.R)
    focal = [0.5 * (fit.K[0, 0] + fit.K[1, 1])] if square else [fit.K[0, 0], fit.K[1, 1]]
    return np.concatenate([focal, [fit.K[0, 2], fit.K[1, 2]], rvec.ravel(), fit.t, fit.dist[free_dist]])


def refine_jointly(fits: dict[str, ViewFit], points_mm: np.ndarray, *, bead_tolerance_mm: float = 0.05,
                   detection_sigma_px: float = 0.1, distortion: str = "none",
                   square_pixels: bool = False) -> tuple[dict[str, ViewFit], np.ndarray]:
    """Bundle-adjust both views and the beads (prior: each bead within ``bead_tolerance_mm`` of nominal).

    Returns the refined fits and the refined bead positions (N,3). ``bead_tolerance_mm = 0`` keeps the
    beads fixed, which makes the two views independent (the result equals the per-view refinement).
    """
    X0 = np.asarray(points_mm, dtype=np.float64)
    names = sorted(fits)
    free_dist = _FREE_DIST[distortion]
    view_params = [_pack(fits[n], free_dist, square_pixels) for n in names]
    sizes = [len(p) for p in view_params]
    move_beads = bead_tolerance_mm > 0
    seen = np.unique(np.concatenate([fits[n].bead_rows for n in names]))
    x0 = np.concatenate(view_params + ([np.zeros(3 * len(seen))] if move_beads else []))
    slot = {int(row): k for k, row in enumerate(seen)}
    offsets = np.cumsum([0] + sizes)
    bead_base = offsets[-1]

    def beads_of(params: np.ndarray) -> np.ndarray:
        X = X0.copy()
        if move_beads:
            X[seen] += params[bead_base:].reshape(-1, 3)
        return X

    def residuals(params: np.ndarray) -> np.ndarray:
        X = beads_of(params)
        parts = []
        for k, name in enumerate(names):
            K, dist, rvec, tvec = _unpack(params[offsets[k]:offsets[k + 1]], free_dist, square_pixels)
            fit = fits[name]
            uv = cv2.projectPoints(X[fit.bead_rows].reshape(-1, 1, 3), rvec, tvec, K, dist)[0].reshape(-1, 2)
            parts.append(((uv - fit.uv) / detection_sigma_px).ravel())
        if move_beads:
            parts.append(params[bead_base:] / bead_tolerance_mm)
        return np.concatenate(parts)

    def jacobian(params: np.ndarray) -> np.ndarray:
        # OpenCV's projectPoints gives d(uv)/d(rvec, tvec, fx, fy, cx, cy, dist); d(uv)/dX = d(uv)/dt R.
        X = beads_of(params)
        J = np.zeros((n_res, len(params)))
        r = 0
        for k, name in enumerate(names):
            K, dist, rvec, tvec = _unpack(params[offsets[k]:offsets[k + 1]], free_dist, square_pixels)
            fit = fits[name]
            _, jac = cv2.projectPoints(X[fit.bead_rows].reshape(-1, 1, 3), rvec, tvec, K, dist)
            jac = jac / detection_sigma_px
            n = 2 * len(fit.bead_rows)
            focal = [jac[:, 6] + jac[:, 7]] if square_pixels else [jac[:, 6], jac[:, 7]]
            block = np.column_stack(focal + [jac[:, 8], jac[:, 9], jac[:, 0:3], jac[:, 3:6]]
                                    + [jac[:, 10 + i] for i in free_dist])
            J[r:r + n, offsets[k]:offsets[k + 1]] = block
            if move_beads:
                R, _ = cv2.Rodrigues(rvec)
                d_point = jac[:, 3:6] @ R
                for m, row in enumerate(fit.bead_rows):
                    c = bead_base + 3 * slot[int(row)]
                    J[r + 2 * m:r + 2 * m + 2, c:c + 3] = d_point[2 * m:2 * m + 2]
            r += n
        if move_beads:
            J[r:, bead_base:] = np.eye(3 * len(seen)) / bead_tolerance_mm
        return J

    n_res = sum(2 * len(fits[n].bead_rows) for n in names) + (3 * len(seen) if move_beads else 0)
    solution = least_squares(residuals, x0, jac=jacobian, method="lm", x_scale="jac",
                             xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200)
    X = beads_of(solution.x)
    refined: dict[str, ViewFit] = {}
    for k, name in enumerate(names):
        K, dist, rvec, tvec = _unpack(solution.x[offsets[k]:offsets[k + 1]], free_dist, square_pixels)
        R, _ = cv2.Rodrigues(rvec)
        fit = replace(fits[name], K=K, dist=dist, R=R, t=np.asarray(tvec, dtype=np.float64))
        refined[name] = replace(fit, residual_px=_residuals(fit, X))
    shift = np.linalg.norm(X - X0, axis=1)
    log.info("joint refinement: RMS %s px; beads moved up to %.3f mm", ", ".join(
        f"{n} {refined[n].rms_px:.3f}" for n in names), float(shift.max()) if len(shift) else 0.0)
    return refined, X
