"""X-ray view geometry: the pinhole model of each plane of the biplane fluoroscope, and the calibration file.

An X-ray view is a central projection from the focal spot of the tube (the "source") onto the detector,
which is exactly a pinhole camera. We use the OpenCV convention (architecture.md, calibration file
contract): a world point ``X`` (mm) maps to camera coordinates ``R X + t`` and to pixels through ``K``
with pixel centres at integer coordinates; image-intensifier distortion follows OpenCV's
``k1 k2 p1 p2 [k3 [k4 k5 k6]]`` model applied to normalised coordinates before ``K``.

Unlike ``cv2.projectPoints``/``cv2.undistortPoints``, which ignore the skew term ``K[0, 1]``, the
projection here uses the full ``K`` so the model is exactly the contract's ``K (R X + t)``.

Two-view functions (fundamental matrix, epipolar distances, triangulation, reprojection error) live in
:mod:`appliance.epipolar` and are re-exported here, so ``from appliance.geometry import triangulate``
works.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import cv2
import numpy as np
import yaml
from pydantic import Field, FiniteFloat, PositiveInt, field_validator, model_validator
from pydantic_core import PydanticCustomError

from appliance.config_io import StrictModel, read_yaml, validate_model
from appliance.errors import CalibrationError
from appliance.epipolar import as_points

log = logging.getLogger(__name__)

#: Largest deviation of ``R^T R`` from the identity (any element), and of ``det R`` from +1, accepted as a
#: rotation. YAML files written with ~7 significant digits stay well inside it; a mistyped entry does not.
ROTATION_TOLERANCE = 1e-4
#: The two sources must be at least this far apart (mm) for triangulation to mean anything.
MIN_BASELINE_MM = 1.0
#: ...and their optical axes at least this far from parallel (degrees). A biplane system is ~90 degrees.
MIN_AXIS_ANGLE_DEG = 1.0
#: Iterations / tolerance of the fixed-point undistortion (normalised units, ~1e-9 px at f=1000 px).
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)




def _frozen(array: np.ndarray) -> np.ndarray:
    array = np.array(array, dtype=np.float64)  # a private copy, so the caller's array stays theirs
    array.setflags(write=False)
    return array


@dataclass(frozen=True, eq=False)
class View:
    """One X-ray plane: intrinsics ``K`` (3x3), distortion ``dist``, pose ``R``, ``t`` and image size (w, h)."""

    name: str
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    image_size: tuple[int, int]

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", _frozen(np.reshape(self.K, (3, 3))))
        object.__setattr__(self, "dist", _frozen(np.ravel(self.dist)))
        object.__setattr__(self, "R", _frozen(np.reshape(self.R, (3, 3))))
        object.__setattr__(self, "t", _frozen(np.ravel(self.t)))
        object.__setattr__(self, "image_size", (int(self.image_size[0]), int(self.image_size[1])))
        if self.t.shape != (3,):
            raise ValueError(f"view {self.name}: t must have 3 elements, got {self.t.shape}")
        object.__setattr__(self, "_K_inv", _frozen(np.linalg.inv(self.K)))
        # Views are immutable, so what every projection asks for is computed once here.
        object.__setattr__(self, "_has_distortion", bool(np.any(self.dist != 0.0)))
        object.__setattr__(self, "_P", _frozen(self.K @ np.hstack([self.R, self.t[:, None]])))

    # -- derived quantities -------------------------------------------------------------------------
    @property
    def P(self) -> np.ndarray:
        """The 3x4 projection matrix ``K [R | t]`` (ideal, undistorted pixels); read-only."""
        return self._P  # type: ignore[attr-defined, no-any-return]

    @property
    def source_mm(self) -> np.ndarray:
        """The X-ray focal spot (camera centre) in world mm: ``-R^T t``."""
        return -self.R.T @ self.t

    @property
    def optical_axis(self) -> np.ndarray:
        """Unit world direction from the source through the principal point (towards the detector)."""
        return self.R[2].copy()

    @property
    def has_distortion(self) -> bool:
        return self._has_distortion  # type: ignore[attr-defined, no-any-return]

    @property
    def K_inv(self) -> np.ndarray:
        return self._K_inv  # type: ignore[attr-defined, no-any-return]

    @classmethod
    def look_at(cls, name: str, source_mm: Any, target_mm: Any, *, focal_px: float,
                image_size: tuple[int, int], up: Any = (0.0, 0.0, 1.0), dist: Any = (0, 0, 0, 0, 0),
                principal_point: tuple[float, float] | None = None) -> View:
        """A view whose source sits at ``source_mm`` looking at ``target_mm``; image ``v`` runs against ``up``.

        For building test scenes and simulated benches; real views come from a calibration.
        """
        source = np.asarray(source_mm, dtype=np.float64)
        z = np.asarray(target_mm, dtype=np.float64) - source
        z /= np.linalg.norm(z)
        x = np.cross(z, np.asarray(up, dtype=np.float64))
        if np.linalg.norm(x) < 1e-9:
            raise ValueError(f"view {name}: 'up' is parallel to the viewing direction")
        x /= np.linalg.norm(x)
        y = np.cross(z, x)  # image v grows downwards, i.e. against 'up'
        R = np.vstack([x, y, z])
        w, h = image_size
        cx, cy = principal_point if principal_point is not None else ((w - 1) / 2.0, (h - 1) / 2.0)
        K = np.array([[focal_px, 0.0, cx], [0.0, focal_px, cy], [0.0, 0.0, 1.0]])
        return cls(name, K, np.asarray(dist, dtype=np.float64), R, -R @ source, (w, h))

    # -- point maps ---------------------------------------------------------------------------------
    def to_camera(self, points_mm: Any) -> np.ndarray:
        """World points (N,3) in camera coordinates (N,3); ``z`` is the depth along the optical axis."""
        return as_points(points_mm, 3, "points_mm") @ self.R.T + self.t

    def _distort(self, xy: np.ndarray) -> np.ndarray:
        """OpenCV's radial-tangential(-rational) model on normalised coordinates (N,2)."""
        d = np.zeros(8)
        d[: min(8, self.dist.size)] = self.dist[:8]
        k1, k2, p1, p2, k3, k4, k5, k6 = d
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.column_stack([xd, yd])

    def _normalised_to_pixels(self, xy: np.ndarray) -> np.ndarray:
        K = self.K
        return np.column_stack([K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2], K[1, 1] * xy[:, 1] + K[1, 2]])

    def _pixels_to_normalised(self, uv: np.ndarray) -> np.ndarray:
        Ki = self.K_inv
        return np.column_stack([Ki[0, 0] * uv[:, 0] + Ki[0, 1] * uv[:, 1] + Ki[0, 2], Ki[1, 1] * uv[:, 1] + Ki[1, 2]])

    def project(self, points_mm: Any, *, distort: bool = True) -> np.ndarray:
        """World points (N,3) mm -> observed pixels (N,2), with distortion unless ``distort=False``.

        Points at or behind the source plane have no image: their rows are NaN.
        """
        cam = self.to_camera(points_mm)
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = cam[:, :2] / cam[:, 2:3]
        xy[cam[:, 2] <= 0] = np.nan
        if distort and self.has_distortion:
            xy = self._distort(xy)
        return self._normalised_to_pixels(xy)

    def undistort_points(self, uv: Any) -> np.ndarray:
        """Observed (distorted) pixels (N,2) -> ideal pixels (N,2) of the same ``K``: ``P`` applies to them."""
        uv = as_points(uv, 2, "uv")
        if not self.has_distortion:
            return uv.copy()
        xy = self._pixels_to_normalised(uv)
        ideal = cv2.undistortPoints(xy.reshape(-1, 1, 2), np.eye(3), self.dist, None, None, None,
                                    _UNDISTORT_CRITERIA).reshape(-1, 2)
        return self._normalised_to_pixels(ideal)

    def rays(self, uv: Any) -> tuple[np.ndarray, np.ndarray]:
        """Back-projected rays of observed pixels: world origins (N,3) (the source) and unit directions (N,3)."""
        ideal = self.undistort_points(uv)
        homogeneous = np.column_stack([ideal, np.ones(len(ideal))])
        directions = homogeneous @ self.K_inv.T @ self.R  # R^T (K^-1 x), row-wise
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        return np.repeat(self.source_mm[None, :], len(ideal), axis=0), directions

    def backproject_plane(self, uv_a: Any, uv_b: Any) -> np.ndarray:
        """The world plane ``(n, d)`` with ``n.X + d = 0``, ``|n| = 1``, through the source and two observed pixels.

        The plane of an image line: e.g. the robot's image axis back-projects to a plane holding its 3D axis.
        """
        _, directions = self.rays(np.vstack([as_points(uv_a, 2, "uv_a"), as_points(uv_b, 2, "uv_b")]))
        normal = np.cross(directions[0], directions[1])
        norm = np.linalg.norm(normal)
        if norm < 1e-12:
            raise ValueError(f"view {self.name}: the two pixels coincide; no unique plane through them")
        normal /= norm
        return np.append(normal, -normal @ self.source_mm)

    def contains(self, uv: Any, margin_px: float = 0.0) -> np.ndarray:
        """Which pixels (N,) lie inside the image (pixel centres at integers), ``margin_px`` from its edge."""
        uv = as_points(uv, 2, "uv")
        w, h = self.image_size
        return ((uv[:, 0] >= -0.5 + margin_px) & (uv[:, 0] <= w - 0.5 - margin_px)
                & (uv[:, 1] >= -0.5 + margin_px) & (uv[:, 1] <= h - 0.5 - margin_px))


# --------------------------------------------------------------------------------------------------
# The calibration file: schema, validation, load and save.
# --------------------------------------------------------------------------------------------------
_Row3 = Annotated[list[FiniteFloat], Field(min_length=3, max_length=3)]
_Matrix3 = Annotated[list[_Row3], Field(min_length=3, max_length=3)]


class ViewModel(StrictModel):
    """One view of the calibration file (architecture.md: calibration file contract)."""

    K: _Matrix3
    dist: list[FiniteFloat] = Field(default_factory=lambda: [0.0] * 5)
    R: _Matrix3
    t: _Row3
    image_size: tuple[PositiveInt, PositiveInt]

    @field_validator("K")
    @classmethod
    def _intrinsics(cls, K: list[list[float]]) -> list[list[float]]:
        if max(abs(K[1][0]), abs(K[2][0]), abs(K[2][1])) > 1e-9:
            raise PydanticCustomError("intrinsics", "not upper-triangular (K[1][0], K[2][0], K[2][1] must be 0)")
        if abs(K[2][2] - 1.0) > 1e-9:
            raise PydanticCustomError("intrinsics", "K[2][2] must be 1, got {value}", {"value": K[2][2]})
        if K[0][0] <= 0.0 or K[1][1] <= 0.0:
            raise PydanticCustomError("intrinsics", "focal lengths K[0][0], K[1][1] must be positive, got {fx}, {fy}",
                                      {"fx": K[0][0], "fy": K[1][1]})
        return K

    @field_validator("dist")
    @classmethod
    def _distortion(cls, dist: list[float]) -> list[float]:
        if len(dist) not in (4, 5, 8):
            raise PydanticCustomError("distortion", "needs 4, 5 or 8 coefficients (k1 k2 p1 p2 [k3 [k4 k5 k6]]), got {n}",
                                      {"n": len(dist)})
        return dist

    @field_validator("R")
    @classmethod
    def _rotation(cls, R: list[list[float]]) -> list[list[float]]:
        matrix = np.asarray(R, dtype=np.float64)
        det = float(np.linalg.det(matrix))
        off = float(np.max(np.abs(matrix.T @ matrix - np.eye(3))))
        if abs(det - 1.0) > ROTATION_TOLERANCE or off > ROTATION_TOLERANCE:
            raise PydanticCustomError(
                "rotation", "not a rotation (det {det}, max |R^T R - I| {off}; tolerance {tol})",
                {"det": f"{det:.3f}", "off": f"{off:.2g}", "tol": ROTATION_TOLERANCE})
        return R


class ViewsModel(StrictModel):
    p: ViewModel
    q: ViewModel

    @model_validator(mode="after")
    def _distinct(self) -> ViewsModel:
        sources, axes = [], []
        for view in (self.p, self.q):
            R, t = np.asarray(view.R), np.asarray(view.t)
            sources.append(-R.T @ t)
            axes.append(R[2])
        baseline = float(np.linalg.norm(sources[0] - sources[1]))
        if baseline < MIN_BASELINE_MM:
            raise PydanticCustomError("coincident", "the two sources coincide (baseline {b} mm < {m} mm)",
                                      {"b": f"{baseline:.3g}", "m": MIN_BASELINE_MM})
        angle = math.degrees(math.acos(min(1.0, abs(float(axes[0] @ axes[1])))))
        if angle < MIN_AXIS_ANGLE_DEG:
            raise PydanticCustomError("parallel", "the optical axes are parallel ({a} deg apart < {m} deg)",
                                      {"a": f"{angle:.3g}", "m": MIN_AXIS_ANGLE_DEG})
        return self


class CalibrationModel(StrictModel):
    views: ViewsModel
    #: Free-form provenance: date, reprojection RMS per view, inliers, source, method...
    metadata: dict[str, Any] = Field(default_factory=dict)


def _nearest_rotation(R: Any) -> np.ndarray:
    """Project a validated near-rotation onto SO(3) so that later algebra sees an exact one.

    One already orthonormal to rounding is kept bit for bit, so that save/load round trips are exact.
    """
    matrix = np.asarray(R, dtype=np.float64)
    if np.max(np.abs(matrix.T @ matrix - np.eye(3))) < 1e-12:
        return matrix
    u, _, vt = np.linalg.svd(matrix)
    return u @ vt


def _plain(value: Any) -> Any:
    """numpy scalars/arrays and tuples -> plain Python, so YAML and JSON can write them."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return value


@dataclass(frozen=True, eq=False)
class Calibration:
    """Both views of the biplane system (``"p"`` and ``"q"``) and where the numbers came from."""

    views: dict[str, View]
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        missing = {"p", "q"} - set(self.views)
        if missing:
            raise CalibrationError(f"calibration needs views p and q; missing {sorted(missing)}")

    @property
    def p(self) -> View:
        return self.views["p"]

    @property
    def q(self) -> View:
        return self.views["q"]

    @property
    def F(self) -> np.ndarray:
        """Fundamental matrix with ``x_q^T F x_p = 0`` on ideal pixels."""
        return fundamental_matrix(self.p, self.q)

    @property
    def packed(self) -> np.ndarray:
        """Both views and ``F`` in the read-only layout of :mod:`appliance.geometry_kernels` (computed once)."""
        return packed_views(self.views["p"], self.views["q"])

    @classmethod
    def from_views(cls, p: View, q: View, metadata: dict[str, Any] | None = None) -> Calibration:
        """Build from two views, running the same checks as a file load."""
        calibration = cls({"p": p, "q": q}, dict(metadata or {}))
        return cls.from_dict(calibration.to_dict(), source=f"views {p.name}/{q.name}")

    @classmethod
    def from_dict(cls, data: Any, source: str = "calibration") -> Calibration:
        """Validate parsed data; a :class:`CalibrationError` names ``source`` and the key path."""
        model = validate_model(CalibrationModel, data, source, error=CalibrationError)
        views = {}
        for name in ("p", "q"):
            v: ViewModel = getattr(model.views, name)
            views[name] = View(name, np.asarray(v.K), np.asarray(v.dist), _nearest_rotation(v.R),
                               np.asarray(v.t), tuple(v.image_size))  # type: ignore[arg-type]
        return cls(views, dict(model.metadata))

    @classmethod
    def load(cls, path: str | Path) -> Calibration:
        """Read and validate a calibration YAML file."""
        path = Path(path)
        calibration = cls.from_dict(read_yaml(path, error=CalibrationError), source=str(path))
        calibration.metadata.setdefault("loaded_from", str(path))
        log.debug("loaded calibration %s", path)
        return calibration

    def to_dict(self) -> dict[str, Any]:
        views = {name: {"K": view.K.tolist(), "dist": view.dist.tolist(), "R": view.R.tolist(),
                        "t": view.t.tolist(), "image_size": list(view.image_size)}
                 for name, view in sorted(self.views.items())}
        metadata = {k: v for k, v in self.metadata.items() if k != "loaded_from"}
        return {"views": views, "metadata": _plain(metadata)}

    def save(self, path: str | Path) -> Path:
        """Write the calibration file (full float precision, so a load gives back the same views)."""
        path = Path(path)
        text = "# Biplane X-ray calibration (mm, OpenCV pinhole convention; see architecture.md)\n"
        text += yaml.safe_dump(self.to_dict(), sort_keys=False, default_flow_style=None, width=120)
        try:
            path.write_text(text, encoding="utf-8")
        except OSError as err:
            raise CalibrationError(f"{path}: cannot write ({err.strerror or err})") from err
        return path


# Re-exported two-view geometry (kept in its own module for size); imported last because it only
# refers to View for type checking.
from appliance.epipolar import (  # noqa: E402
    epipolar_distance_px,
    epipolar_lines,
    epipolar_plane_angle_deg,
    fundamental_matrix,
    packed_views,
    reprojection_error_px,
    triangulate,
)

__all__ = [
    "Calibration", "CalibrationModel", "View", "ViewModel", "dark_level_of", "epipolar_distance_px", "epipolar_lines",
    "epipolar_plane_angle_deg", "fundamental_matrix", "packed_views", "reprojection_error_px", "triangulate",
]


def dark_level_of(calibration: Calibration, override: float | None = None) -> float:
    """The detector's dark level (gray levels): ``override`` if given, else the calibration file's
    ``metadata.detector.dark_level``, else 0. A present but invalid value is a CalibrationError."""
    if override is not None:
        return float(override)
    detector = calibration.metadata.get("detector")
    if detector is None:
        return 0.0
    where = calibration.metadata.get("loaded_from", "calibration")
    value = detector.get("dark_level") if isinstance(detector, dict) else None
    if not isinstance(detector, dict):
        raise CalibrationError(f"{where}: metadata.detector: expected a mapping, got {detector!r}")
    if value is None:
        return 0.0
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= float(value) < float("inf"):
        raise CalibrationError(f"{where}: metadata.detector.dark_level: expected a finite number >= 0 "
                               f"(gray levels), got {value!r}")
    return float(value)
