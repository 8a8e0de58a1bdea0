"""Image-intensifier distortion: a correction map from an image of a perforated plate, applied to points.

An image intensifier's curved input screen gives pincushion distortion, and the earth's (or the EMA
coils'!) magnetic field bends its electrons into an S-shaped, position-dependent rotation. Neither is
the radial-tangential model of OpenCV, so, as XMALab and the bi-plane literature do, we measure it:
a flat plate with a regular lattice of holes is fixed on the intensifier's input face, its image
shows the holes as bright spots, and the map that puts every hole back on a regular lattice is the
correction.

Steps: holes are detected with sub-pixel centres (:func:`.beads.detect_beads` on bright blobs); the
lattice is numbered by growing from the hole nearest the image centre, predicting each neighbour
from the local lattice vectors (robust to strong distortion at the edges); the ideal lattice is the
affine fit of the lattice numbers to the holes near the centre, where distortion is smallest; then
either a 2D polynomial (``"polynomial"``, global, smooth, default degree 5) or a thin-plate spline
(``"local"``, follows local defects of the tube) maps distorted to ideal pixels. The map is applied to
detected points (bead centres, robot features) before any pinhole geometry; the calibration is then
done with ``dist = 0`` on corrected points, and the correction is saved next to the calibration.
"""
from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy.interpolate import RBFInterpolator
from scipy.spatial import cKDTree

from appliance.errors import CalibrationError
from appliance.xray_calibration.beads import detect_beads

log = logging.getLogger(__name__)

METHODS = ("polynomial", "local")
MIN_HOLES = 25


def _exponents(degree: int) -> list[tuple[int, int]]:
    return [(i, total - i) for total in range(degree + 1) for i in range(total + 1)]


def _design(xy: np.ndarray, degree: int) -> np.ndarray:
    return np.column_stack([xy[:, 0] ** i * xy[:, 1] ** j for i, j in _exponents(degree)])


def number_lattice(holes: np.ndarray, start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Integer lattice indices (k,2) for the holes (k rows of ``holes``) reachable from the hole nearest ``start``."""
    tree = cKDTree(holes)
    _, origin = tree.query(start)
    d, nn = tree.query(holes[origin], k=min(9, len(holes)))
    vectors = holes[nn[1:]] - holes[origin]
    a = vectors[0]
    b = next((v for v in vectors[1:] if abs(np.dot(v, a)) / (np.linalg.norm(v) * np.linalg.norm(a)) < 0.5), None)
    if b is None:
        raise CalibrationError("perforated plate: the holes do not form a 2D lattice near the image centre")
    pitch = min(np.linalg.norm(a), np.linalg.norm(b))
    index_of: dict[tuple[int, int], int] = {(0, 0): int(origin)}
    position: dict[tuple[int, int], np.ndarray] = {(0, 0): holes[origin]}
    queue = deque([(0, 0)])
    taken = {int(origin)}
    while queue:
        i, j = queue.popleft()
        here = position[(i, j)]
        for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            key = (i + di, j + dj)
            if key in index_of:
                continue
            # Local lattice vector: from the hole on the far side if known, else the central one.
            back = position.get((i - di, j - dj))
            step = (here - back) if back is not None else (di * a if di else dj * b)
            guess = here + step
            dist, k = tree.query(guess)
            if dist < 0.3 * pitch and int(k) not in taken:
                index_of[key], position[key] = int(k), holes[k]
                taken.add(int(k))
                queue.append(key)
    keys = np.array(list(index_of.keys()))
    rows = np.array(list(index_of.values()))
    return rows, keys


@dataclass(frozen=True)
class GridCorrection:
    """A distorted -> ideal pixel map for one view, from a perforated-plate image."""

    method: str
    image_size: tuple[int, int]
    centre: np.ndarray  # normalisation of pixel coordinates
    scale: float
    degree: int
    coefficients: np.ndarray | None  # polynomial: (terms, 2)
    control_px: np.ndarray  # distorted hole centres used for the fit (k,2)
    ideal_px: np.ndarray  # their ideal positions (k,2)
    smoothing: float = 1e-3

    def __post_init__(self) -> None:
        if self.method == "local":
            object.__setattr__(self, "_rbf", RBFInterpolator(self._normalise(self.control_px),
                                                             self.ideal_px - self.control_px,
                                                             kernel="thin_plate_spline", smoothing=self.smoothing))

    def _normalise(self, uv: np.ndarray) -> np.ndarray:
        return (np.asarray(uv, dtype=np.float64).reshape(-1, 2) - self.centre) / self.scale

    def apply(self, uv: Any) -> np.ndarray:
        """Ideal pixels (N,2) of distorted (observed) pixels (N,2)."""
        points = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        if self.method == "polynomial":
            assert self.coefficients is not None
            return _design(self._normalise(points), self.degree) @ self.coefficients
        return points + self._rbf(self._normalise(points))  # type: ignore[attr-defined]

    def residual_px(self) -> np.ndarray:
        """Distance of each corrected control hole from its ideal lattice position."""
        return np.linalg.norm(self.apply(self.control_px) - self.ideal_px, axis=1)

    def to_dict(self) -> dict[str, Any]:
        data: dict[str, Any] = {"method": self.method, "image_size": list(self.image_size),
                                "centre": self.centre.tolist(), "scale": self.scale, "degree": self.degree,
                                "control_px": self.control_px.tolist(), "ideal_px": self.ideal_px.tolist(),
                                "smoothing": self.smoothing}
        if self.coefficients is not None:
            data["coefficients"] = self.coefficients.tolist()
        return data

    @classmethod
    def from_dict(cls, data: Any, source: str = "distortion map") -> GridCorrection:
        try:
            method = str(data["method"])
            if method not in METHODS:
                raise ValueError(f"method must be one of {METHODS}")
            coefficients = np.asarray(data["coefficients"], dtype=np.float64) if "coefficients" in data else None
            return cls(method, tuple(int(v) for v in data["image_size"]), np.asarray(data["centre"], np.float64),
                       float(data["scale"]), int(data["degree"]), coefficients,
                       np.asarray(data["control_px"], np.float64).reshape(-1, 2),
                       np.asarray(data["ideal_px"], np.float64).reshape(-1, 2), float(data.get("smoothing", 1e-3)))
        except (KeyError, TypeError, ValueError) as err:
            raise CalibrationError(f"{source}: not a valid distortion map: {err}") from err

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.write_text(yaml.safe_dump(self.to_dict(), default_flow_style=None, width=120), encoding="utf-8")
        return path

    @classmethod
    def load(cls, path: str | Path) -> GridCorrection:
        from appliance.config_io import read_yaml

        return cls.from_dict(read_yaml(path, error=CalibrationError), source=str(path))


def fit_correction(holes_px: np.ndarray, image_size: tuple[int, int], *, method: str = "polynomial",
                   degree: int = 5, central_rings: int = 2, smoothing: float = 1e-3) -> GridCorrection:
    """Fit the correction from detected hole centres (any order) of a regular perforated plate."""
    if method not in METHODS:
        raise CalibrationError(f"unknown distortion correction method {method!r}; use one of {METHODS}")
    holes = np.asarray(holes_px, dtype=np.float64).reshape(-1, 2)
    w, h = image_size
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    rows, keys = number_lattice(holes, centre)
    if len(rows) < MIN_HOLES:
        raise CalibrationError(f"perforated plate: only {len(rows)} holes could be placed on the lattice; "
                               f"need at least {MIN_HOLES}")
    central = np.all(np.abs(keys) <= central_rings, axis=1)
    if central.sum() < 6:
        raise CalibrationError("perforated plate: too few holes near the image centre to define the ideal lattice")
    design = np.column_stack([keys[central], np.ones(central.sum())])
    affine, *_ = np.linalg.lstsq(design, holes[rows[central]], rcond=None)
    ideal = np.column_stack([keys, np.ones(len(keys))]) @ affine
    control = holes[rows]
    scale = float(max(w, h)) / 2.0
    coefficients = None
    if method == "polynomial":
        terms = len(_exponents(degree))
        if len(rows) < 2 * terms:
            raise CalibrationError(f"perforated plate: {len(rows)} holes are too few for a degree-{degree} polynomial")
        coefficients, *_ = np.linalg.lstsq(_design((control - centre) / scale, degree), ideal, rcond=None)
    correction = GridCorrection(method, (int(w), int(h)), centre, scale, degree, coefficients, control, ideal,
                                smoothing)
    residual = correction.residual_px()
    log.info("distortion map (%s) from %d holes: residual RMS %.3f px, max %.3f px; largest correction %.1f px",
             method, len(rows), float(np.sqrt(np.mean(residual ** 2))), float(residual.max()),
             float(np.linalg.norm(ideal - control, axis=1).max()))
    return correction


def correction_from_image(image: np.ndarray, *, method: str = "polynomial", degree: int = 5,
                          max_radius_px: float = 10.0) -> GridCorrection:
    """Detect the holes (bright spots) of a perforated-plate image and fit the correction."""
    holes = detect_beads(image, bright=True, max_radius_px=max_radius_px, what="perforated plate image")
    return fit_correction(holes.uv, (int(image.shape[1]), int(image.shape[0])), method=method, degree=degree)
