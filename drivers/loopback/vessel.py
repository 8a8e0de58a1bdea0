"""The vessel phantom of the simulated world: a tube of constant radius around a smooth 3D centreline.

The centreline is given as control points (mm, X-ray world frame) and interpolated by a cubic
spline in chord length, then resampled densely (0.25 mm) so that nearest-point queries are a small
search over a polyline. The robot's centroid must stay ``radius_mm - clearance`` from the centreline
(the robot's own radius is the clearance): :meth:`Vessel.constrain` projects a point that left the
lumen back onto that surface and returns the outward normal so the caller can cancel the normal
velocity. Optional steady Poiseuille flow along the tangent: ``v(r) = 2 v_mean (1 - r^2/R^2)``.

Not modelled: branches, varying radius, wall compliance, pulsatile flow, the rod's ends touching
the wall in bends (only the centroid is constrained).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import CubicSpline
from scipy.spatial import cKDTree

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Nearest:
    """The centreline point nearest to a query point."""

    s_mm: float              # arc length of the nearest point
    point_mm: FloatArray     # nearest centreline point
    tangent: FloatArray      # unit tangent there (direction of increasing s)
    offset_mm: FloatArray    # query point minus nearest point (perpendicular to the tangent)
    distance_mm: float


class Vessel:
    """A tube of ``radius_mm`` along a smoothed centreline, with optional mean flow speed."""

    def __init__(self, centreline_mm: ArrayLike, radius_mm: float, flow_mean_mm_s: float = 0.0,
                 spacing_mm: float = 0.25) -> None:
        control = np.asarray(centreline_mm, float)
        if control.ndim != 2 or control.shape[1] != 3 or len(control) < 2:
            raise ValueError(f"centreline_mm must be N x 3 with N >= 2, got shape {control.shape}")
        if radius_mm <= 0.0:
            raise ValueError(f"radius_mm must be positive, got {radius_mm}")
        chords = np.linalg.norm(np.diff(control, axis=0), axis=1)
        if np.any(chords < 1e-9):
            raise ValueError("centreline_mm has repeated consecutive points")
        u = np.concatenate([[0.0], np.cumsum(chords)])
        if len(control) >= 3:
            spline = CubicSpline(u, control, bc_type="natural")
            dense_u = np.linspace(0.0, u[-1], max(int(u[-1] / (spacing_mm / 2.0)), 8) + 1)
            dense = spline(dense_u)
        else:
            dense = control
        # Resample at uniform arc length: spline parameter (chord length) is not arc length.
        seg = np.linalg.norm(np.diff(dense, axis=0), axis=1)
        arc = np.concatenate([[0.0], np.cumsum(seg)])
        n = max(int(np.ceil(arc[-1] / spacing_mm)), 1) + 1
        self.s = np.linspace(0.0, arc[-1], n)
        self.points = np.column_stack([np.interp(self.s, arc, dense[:, k]) for k in range(3)])
        diffs = np.diff(self.points, axis=0)
        self._seg_tangent = diffs / np.linalg.norm(diffs, axis=1)[:, None]
        self.radius_mm = float(radius_mm)
        self.flow_mean_mm_s = float(flow_mean_mm_s)
        self.length_mm = float(self.s[-1])
        self._tree = cKDTree(self.points)

    @classmethod
    def from_config(cls, data: Mapping[str, Any]) -> Vessel:
        """From the plain ``vessel.yaml`` mapping (``centreline_mm``, ``radius_mm``, optional ``flow_mean_mm_s``)."""
        return cls(data["centreline_mm"], float(data["radius_mm"]), float(data.get("flow_mean_mm_s", 0.0)))

    def point_at(self, s_mm: float) -> FloatArray:
        """Centreline point at arc length ``s_mm`` (clamped to the ends)."""
        s = float(np.clip(s_mm, 0.0, self.length_mm))
        return np.array([np.interp(s, self.s, self.points[:, k]) for k in range(3)])

    def tangent_at(self, s_mm: float) -> FloatArray:
        """Unit tangent at arc length ``s_mm``."""
        index = int(np.clip(np.searchsorted(self.s, s_mm) - 1, 0, len(self._seg_tangent) - 1))
        return self._seg_tangent[index].copy()

    def nearest(self, point_mm: ArrayLike) -> Nearest:
        """Nearest centreline point (exact on the resampled polyline)."""
        p = np.asarray(point_mm, float)
        _, index = self._tree.query(p)
        best: tuple[float, FloatArray, int] | None = None
        for seg in (index - 1, index):
            if 0 <= seg < len(self._seg_tangent):
                a = self.points[seg]
                t = np.clip(np.dot(p - a, self._seg_tangent[seg]), 0.0, self.s[seg + 1] - self.s[seg])
                q = a + t * self._seg_tangent[seg]
                d = float(np.linalg.norm(p - q))
                if best is None or d < best[0]:
                    best = (d, q, seg)
                    s_best = self.s[seg] + t
        assert best is not None
        distance, q, seg = best
        return Nearest(float(s_best), q, self._seg_tangent[seg].copy(), p - q, distance)

    def constrain(self, point_mm: ArrayLike, clearance_mm: float) -> tuple[FloatArray, FloatArray | None]:
        """Keep ``point_mm`` within ``radius_mm - clearance_mm`` of the centreline and inside the ends.

        Returns the (possibly projected) point and the outward unit normal of the surface it was
        projected onto, or None when it was inside.
        """
        p = np.asarray(point_mm, float)
        near = self.nearest(p)
        normal: FloatArray | None = None
        allowed = max(self.radius_mm - clearance_mm, 0.0)
        if near.distance_mm > allowed:
            radial = near.offset_mm - np.dot(near.offset_mm, near.tangent) * near.tangent
            r = float(np.linalg.norm(radial))
            if r > 1e-12:
                normal = radial / r
                p = near.point_mm + np.dot(near.offset_mm, near.tangent) * near.tangent + allowed * normal
        # The tube is closed at both ends (a phantom with end caps).
        for s_end, sign in ((0.0, -1.0), (self.length_mm, 1.0)):
            if sign * (near.s_mm - s_end) >= 0.0:
                end_t = self.tangent_at(s_end) * sign
                beyond = float(np.dot(p - self.point_at(s_end), end_t))
                if beyond > 0.0:
                    p = p - beyond * end_t
                    normal = end_t if normal is None else normal
        return p, normal

    def flow_velocity_mm_s(self, point_mm: ArrayLike) -> FloatArray:
        """Steady Poiseuille flow along the tangent at ``point_mm`` (zero outside the lumen)."""
        if self.flow_mean_mm_s == 0.0:
            return np.zeros(3)
        near = self.nearest(point_mm)
        r = near.distance_mm / self.radius_mm
        return 2.0 * self.flow_mean_mm_s * max(1.0 - r * r, 0.0) * near.tangent

    def sample(self, step_mm: float = 1.0) -> FloatArray:
        """Centreline points every ``step_mm`` (for plots and default paths)."""
        s = np.arange(0.0, self.length_mm + 1e-9, step_mm)
        if s[-1] < self.length_mm:
            s = np.append(s, self.length_mm)
        return np.column_stack([np.interp(s, self.s, self.points[:, k]) for k in range(3)])
