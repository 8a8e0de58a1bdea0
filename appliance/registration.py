"""Point-based rigid registration between the X-ray frame and the optical tracker (OTS), and pivot calibration.

Registration: fiducials known in both frames (bead centres triangulated in X-ray, the same beads
touched with a tracked pointer) give the rotation and translation that minimise the summed squared
distances -- the closed form of Arun, Huang & Blostein (SVD of the cross-covariance), equivalent to
Horn's unit-quaternion solution, with the reflection case excluded so the result is a rotation.

Errors, after Fitzpatrick, West & Maurer (IEEE TMI 17(5), 1998):

- fiducial registration error (FRE): per fiducial, the distance between the mapped source point and
  its target; its expected square is ``(1 - 2/N) FLE^2`` for N fiducials, which gives an estimate of
  the fiducial localisation error FLE from the observed FRE;
- target registration error (TRE) at a point ``r``:
  ``<TRE^2(r)> ~ FLE^2 / N * (1 + 1/3 * sum_k d_k^2 / f_k^2)``, where ``d_k`` is the distance of ``r``
  from the k-th principal axis of the fiducial configuration and ``f_k`` the RMS distance of the
  fiducials from that axis. FRE itself says little about TRE; the formula is what to report.

Pivot calibration: a pointer pivoting about its fixed tip gives tracker poses ``(R_i, t_i)`` with
``R_i p_tip + t_i = p_pivot`` for all i; stacking ``[R_i  -I] [p_tip; p_pivot] = -t_i`` and solving in
least squares gives the tip offset in the tool frame and the pivot point in the tracker frame.

A registration is saved with the calibration as ``metadata["ots_registration"]`` (see
:func:`attach_registration`).
"""
from __future__ import annotations

import datetime as _dt
import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from appliance.errors import CalibrationError

log = logging.getLogger(__name__)

MIN_FIDUCIALS = 3
#: Second singular value of the centred fiducials (mm) below which they are called collinear.
COLLINEAR_MM = 1e-3


def _points(values: Any, what: str) -> np.ndarray:
    array = np.asarray(values, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise CalibrationError(f"{what}: expected an (N, 3) array of points, got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        bad = np.flatnonzero(~np.all(np.isfinite(array), axis=1)).tolist()
        raise CalibrationError(f"{what}: rows {bad} are not finite")
    return array


@dataclass(frozen=True)
class RigidTransform:
    """``y = R x + t`` (mm)."""

    R: np.ndarray
    t: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "R", np.asarray(self.R, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "t", np.asarray(self.t, dtype=np.float64).reshape(3))

    def apply(self, points: Any) -> np.ndarray:
        return np.asarray(points, dtype=np.float64) @ self.R.T + self.t

    def inverse(self) -> RigidTransform:
        return RigidTransform(self.R.T, -self.R.T @ self.t)

    def compose(self, other: RigidTransform) -> RigidTransform:
        """``self`` after ``other``."""
        return RigidTransform(self.R @ other.R, self.R @ other.t + self.t)

    def matrix(self) -> np.ndarray:
        """The 4x4 homogeneous matrix."""
        out = np.eye(4)
        out[:3, :3], out[:3, 3] = self.R, self.t
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"R": self.R.tolist(), "t": self.t.tolist()}

    @classmethod
    def from_dict(cls, data: Any, source: str = "transform") -> RigidTransform:
        try:
            R = np.asarray(data["R"], dtype=np.float64).reshape(3, 3)
            t = np.asarray(data["t"], dtype=np.float64).reshape(3)
        except (KeyError, TypeError, ValueError) as err:
            raise CalibrationError(f"{source}: needs R (3x3) and t (3): {err}") from err
        if abs(np.linalg.det(R) - 1) > 1e-4 or np.max(np.abs(R.T @ R - np.eye(3))) > 1e-4:
            raise CalibrationError(f"{source}: R is not a rotation")
        u, _, vt = np.linalg.svd(R)
        return cls(u @ vt, t)


@dataclass(frozen=True)
class Registration:
    """A fitted registration with its error figures (mm)."""

    transform: RigidTransform  # source frame -> target frame
    fre_mm: np.ndarray  # (N,) per fiducial
    source_points: np.ndarray
    target_points: np.ndarray

    @property
    def fre_rms_mm(self) -> float:
        return float(np.sqrt(np.mean(self.fre_mm ** 2)))

    @property
    def fle_estimate_mm(self) -> float:
        """FLE estimated from FRE: ``<FRE^2> = (1 - 2/N) <FLE^2>`` (needs N > 2)."""
        n = len(self.fre_mm)
        return self.fre_rms_mm / np.sqrt(1.0 - 2.0 / n) if n > 2 else float("nan")

    def tre_mm(self, targets: Any, fle_mm: float | None = None) -> np.ndarray:
        """Expected RMS TRE (N,) at target points given in the *source* frame (Fitzpatrick 1998)."""
        return expected_tre_mm(self.source_points, targets, self.fle_estimate_mm if fle_mm is None else fle_mm)

    def to_dict(self, targets: Any | None = None) -> dict[str, Any]:
        data: dict[str, Any] = {
            **self.transform.to_dict(),
            "fiducials": int(len(self.fre_mm)),
            "fre_rms_mm": round(self.fre_rms_mm, 4),
            "fre_max_mm": round(float(self.fre_mm.max()), 4),
            "fle_estimate_mm": round(self.fle_estimate_mm, 4),
            "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        }
        if targets is not None:
            data["tre_rms_mm_at_targets"] = np.round(self.tre_mm(targets), 4).tolist()
        else:
            data["tre_rms_mm_at_centroid"] = round(float(self.tre_mm(self.source_points.mean(axis=0)[None])[0]), 4)
        return data


def register_points(source: Any, target: Any, weights: Any | None = None) -> Registration:
    """The rigid transform taking ``source`` points (N,3) onto ``target`` (N,3) in least squares."""
    a = _points(source, "registration source points")
    b = _points(target, "registration target points")
    if a.shape != b.shape:
        raise CalibrationError(f"registration: {len(a)} source points but {len(b)} target points")
    if len(a) < MIN_FIDUCIALS:
        raise CalibrationError(f"registration: {len(a)} fiducials; at least {MIN_FIDUCIALS} non-collinear are needed")
    w = np.ones(len(a)) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.shape != (len(a),) or np.any(w < 0) or w.sum() <= 0:
        raise CalibrationError("registration: weights must be N non-negative numbers, not all zero")
    w = w / w.sum()
    ca, cb = w @ a, w @ b
    spread = np.linalg.svd(a - ca, compute_uv=False)
    if spread[1] < COLLINEAR_MM * np.sqrt(len(a)):
        raise CalibrationError("registration: the fiducials are collinear (or coincide); the rotation about their "
                               "line is undetermined -- use at least 3 fiducials not on one line")
    H = (a - ca).T @ ((b - cb) * w[:, None])
    u, _, vt = np.linalg.svd(H)
    # Force a proper rotation: flip the axis of the smallest singular value when the best orthogonal
    # matrix would be a reflection (noisy near-planar fiducials).
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    R = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    transform = RigidTransform(R, cb - R @ ca)
    fre = np.linalg.norm(transform.apply(a) - b, axis=1)
    result = Registration(transform, fre, a, b)
    log.info("registration of %d fiducials: FRE RMS %.3f mm (max %.3f)", len(a), result.fre_rms_mm, fre.max())
    return result


def expected_tre_mm(fiducials: Any, targets: Any, fle_mm: float) -> np.ndarray:
    """RMS TRE expected at ``targets`` (M,3) for fiducials (N,3) with isotropic RMS error ``fle_mm``."""
    f = _points(fiducials, "fiducials")
    r = _points(np.atleast_2d(targets), "targets")
    centre = f.mean(axis=0)
    _, _, axes = np.linalg.svd(f - centre)  # rows: principal axes of the configuration
    fc, rc = (f - centre) @ axes.T, (r - centre) @ axes.T
    ratio = np.zeros(len(r))
    for k in range(3):
        others = [j for j in range(3) if j != k]
        f_k2 = np.mean(np.sum(fc[:, others] ** 2, axis=1))  # mean squared distance of fiducials from axis k
        d_k2 = np.sum(rc[:, others] ** 2, axis=1)
        ratio += d_k2 / f_k2
    return fle_mm * np.sqrt((1.0 + ratio / 3.0) / len(f))


@dataclass(frozen=True)
class PivotCalibration:
    tip_offset_mm: np.ndarray  # tip in the tool's own frame
    pivot_point_mm: np.ndarray  # the fixed pivot in the tracker frame
    residual_mm: np.ndarray  # (N,) distance of each pose's tip from the pivot point

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(np.mean(self.residual_mm ** 2)))


def pivot_calibration(rotations: Any, translations: Any, *, min_spread_deg: float = 10.0) -> PivotCalibration:
    """Tip offset and pivot point from N tool poses ``(R_i, t_i)`` (tool -> tracker) pivoting about the tip."""
    Rs = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    ts = np.asarray(translations, dtype=np.float64).reshape(-1, 3)
    if len(Rs) != len(ts) or len(Rs) < 3:
        raise CalibrationError(f"pivot calibration: needs at least 3 poses with rotations and translations "
                               f"(got {len(Rs)} rotations, {len(ts)} translations)")
    # The tip is found only if the tool turned about at least two axes by a useful amount.
    angles = [np.degrees(np.arccos(np.clip((np.trace(R @ Rs[0].T) - 1) / 2, -1, 1))) for R in Rs]
    if max(angles) < min_spread_deg:
        raise CalibrationError(f"pivot calibration: the tool turned only {max(angles):.1f} deg; pivot it through "
                               f"at least {min_spread_deg:g} deg in several directions")
    A = np.zeros((3 * len(Rs), 6))
    A[:, :3] = Rs.reshape(-1, 3)
    A[:, 3:] = -np.tile(np.eye(3), (len(Rs), 1))
    solution, _, rank, singular = np.linalg.lstsq(A, -ts.reshape(-1), rcond=None)
    if rank < 6 or singular[-1] / singular[0] < 1e-6:
        raise CalibrationError("pivot calibration: poses turn about a single axis only; the tip position along "
                               "that axis is undetermined -- pivot in two directions")
    tip, pivot = solution[:3], solution[3:]
    residual = np.linalg.norm(np.einsum("nij,j->ni", Rs, tip) + ts - pivot, axis=1)
    result = PivotCalibration(tip, pivot, residual)
    log.info("pivot calibration from %d poses: tip %s mm, RMS %.3f mm", len(Rs), np.round(tip, 2), result.rms_mm)
    return result


def attach_registration(calibration: Any, registration: Registration, *, direction: str = "xray_to_ots",
                        targets: Any | None = None) -> Any:
    """A copy of ``calibration`` (an ``appliance.geometry.Calibration``) with the registration in its metadata.

    ``direction`` names what the transform maps (``xray_to_ots``: X-ray world mm -> tracker mm).
    """
    metadata = dict(calibration.metadata)
    metadata["ots_registration"] = {"direction": direction, **registration.to_dict(targets)}
    return type(calibration)(dict(calibration.views), metadata)


def registration_from_calibration(calibration: Any) -> RigidTransform | None:
    """The X-ray -> OTS transform saved with a calibration, or None if it has none."""
    data = calibration.metadata.get("ots_registration")
    if data is None:
        return None
    transform = RigidTransform.from_dict(data, source="calibration metadata.ots_registration")
    return transform if data.get("direction", "xray_to_ots") == "xray_to_ots" else transform.inverse()
