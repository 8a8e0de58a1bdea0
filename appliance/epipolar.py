"""Two-view geometry of the biplane system: fundamental matrix, epipolar distances, triangulation.

Conventions: view ``p`` is the first image and ``q`` the second, ``x_q^T F x_p = 0`` for ideal
(undistorted) pixels of one world point. Distances are geometric, in pixels: the algebraic residual
``x_q^T F x_p`` depends on how points and ``F`` are scaled (architecture.md, known traps), so no
threshold in the appliance is ever put on it.

Triangulation undistorts first, optionally moves the pair onto the epipolar constraint with the
optimal (Hartley-Sturm) correction - the smallest pixel move that makes the two rays intersect - and
then solves the linear DLT in normalised camera coordinates, which is well conditioned whatever the
focal length. It runs compiled (:mod:`appliance.geometry_kernels`; the correction is Lindstrom's
iteration, which the tests check against ``cv2.correctMatches``): the tracker and the full-frame
candidate checks call it every frame on a handful of points.
"""
from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Any

import numpy as np

from appliance import geometry_kernels

if TYPE_CHECKING:
    from appliance.geometry import View


def as_points(values: Any, dim: int, what: str) -> np.ndarray:
    """Accept one point ``(dim,)`` or many ``(N, dim)``; return float64 ``(N, dim)``."""
    array = np.asarray(values, dtype=np.float64)
    if array.ndim == 1:
        array = array[None, :]
    if array.ndim != 2 or array.shape[1] != dim:
        raise ValueError(f"{what}: expected shape (N, {dim}) or ({dim},), got {np.shape(values)}")
    return array


def _pair(uv_p: Any, uv_q: Any) -> tuple[np.ndarray, np.ndarray]:
    a, b = as_points(uv_p, 2, "uv_p"), as_points(uv_q, 2, "uv_q")
    if len(a) != len(b):
        raise ValueError(f"uv_p and uv_q must pair up: {len(a)} vs {len(b)} points")
    return a, b


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _homogeneous(uv: np.ndarray) -> np.ndarray:
    return np.column_stack([uv, np.ones(len(uv))])


def fundamental_matrix(p: View, q: View) -> np.ndarray:
    """``F`` (3x3, unit Frobenius norm) with ``x_q^T F x_p = 0`` for ideal pixels of the same world point.

    From the relative pose ``X_q = R X_p + t`` (camera frames): ``E = [t]_x R``, ``F = K_q^-T E K_p^-1``.
    """
    R = q.R @ p.R.T
    t = q.t - R @ p.t
    F = q.K_inv.T @ _skew(t) @ R @ p.K_inv
    return F / np.linalg.norm(F)


@functools.lru_cache(maxsize=32)
def _fundamental_cached(p: View, q: View) -> np.ndarray:
    """``fundamental_matrix`` per pair of (immutable, identity-hashed) views, for the per-frame path."""
    F = fundamental_matrix(p, q)
    F.flags.writeable = False
    return F


def packed_views(p: View, q: View) -> np.ndarray:
    """Both views, ``F`` and the DLT's world scale packed for the compiled kernels (cached per view pair)."""
    return _packed_cached(p, q)


@functools.lru_cache(maxsize=32)
def _packed_cached(p: View, q: View) -> np.ndarray:
    views = [geometry_kernels.pack_view(v.K, v.K_inv, v.R, v.t, v.dist) for v in (p, q)]
    # The DLT scales the world by s so that the homogeneous column is as large as the rotation part.
    scale = max(float(np.linalg.norm(p.t)), float(np.linalg.norm(q.t)), 1.0)
    return geometry_kernels.pack_views(views[0], views[1], _fundamental_cached(p, q), scale)


def epipolar_lines(F: np.ndarray, uv: Any, *, from_view: str = "p") -> np.ndarray:
    """Epipolar lines (N,3) ``(a, b, c)`` with ``a^2 + b^2 = 1`` in the *other* view for ideal pixels of ``from_view``.

    With unit ``(a, b)``, ``a u + b v + c`` is the signed distance in pixels from ``(u, v)`` to the line.
    """
    if from_view not in ("p", "q"):
        raise ValueError(f"from_view must be 'p' or 'q', got {from_view!r}")
    x = _homogeneous(as_points(uv, 2, "uv"))
    lines = x @ F.T if from_view == "p" else x @ F  # F x_p, or F^T x_q, row-wise
    norm = np.hypot(lines[:, 0], lines[:, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        return lines / norm[:, None]


def epipolar_distance_px(F: np.ndarray, uv_p: Any, uv_q: Any) -> np.ndarray:
    """Symmetric geometric epipolar distance per pair (N,), pixels, of ideal pixels.

    The root mean square of the distance from ``x_q`` to the epipolar line of ``x_p`` and from ``x_p``
    to the epipolar line of ``x_q``: 0 for a true correspondence, growing with the mismatch, in the
    units the image noise is in.
    """
    a, b = _pair(uv_p, uv_q)
    d_q = np.einsum("ij,ij->i", epipolar_lines(F, a, from_view="p"), _homogeneous(b))
    d_p = np.einsum("ij,ij->i", epipolar_lines(F, b, from_view="q"), _homogeneous(a))
    return np.sqrt((d_p * d_p + d_q * d_q) / 2.0)


def optimal_correction(p: View, q: View, ideal_p: Any, ideal_q: Any) -> tuple[np.ndarray, np.ndarray]:
    """Hartley-Sturm optimal correction of ideal pixel pairs (N,2), (N,2): the smallest squared pixel move
    onto ``x_q^T F x_p = 0``. Pairs it cannot handle keep their pixels."""
    a, b = _pair(ideal_p, ideal_q)
    moved = geometry_kernels.correct_points(packed_views(p, q), np.ascontiguousarray(a), np.ascontiguousarray(b))
    return moved[:, :2], moved[:, 2:]


def triangulate(p: View, q: View, uv_p: Any, uv_q: Any, *, optimal: bool = True) -> np.ndarray:
    """World points (N,3) mm from observed (distorted) pixel pairs.

    ``optimal=True`` first corrects each pair onto the epipolar constraint (Hartley-Sturm, minimising
    the squared pixel move), then solves the linear DLT (the smallest right singular vector of the four
    row-normalised equations, in normalised camera coordinates with the world scaled by the larger
    ``|t|``). Rows whose solution lies at or behind either source (no image could show it) or at
    infinity are NaN.
    """
    a, b = _pair(uv_p, uv_q)
    # Contiguous arrays: the layout the kernel was compiled for at warm-up.
    return geometry_kernels.triangulate_points(packed_views(p, q), np.ascontiguousarray(a), np.ascontiguousarray(b),
                                               bool(optimal))


def reprojection_error_px(p: View, q: View, X: Any, uv_p: Any, uv_q: Any) -> np.ndarray:
    """Per point (N,): RMS over both views of the distance between the projection of ``X`` and the observed pixel."""
    a, b = _pair(uv_p, uv_q)
    points = np.asarray(X, dtype=np.float64).reshape(-1, 3)
    if len(points) != len(a):
        raise ValueError(f"X has {len(points)} points but there are {len(a)} pixel pairs")
    e_p = np.sum((p.project(points) - a) ** 2, axis=1)
    e_q = np.sum((q.project(points) - b) ** 2, axis=1)
    return np.sqrt((e_p + e_q) / 2.0)


def epipolar_plane_angle_deg(p: View, q: View, points_mm: Any, directions: Any) -> np.ndarray:
    """Angle (N,) in degrees between each 3D direction and the epipolar plane through its point.

    A segment lying in an epipolar plane (angle ~ 0) projects onto corresponding epipolar lines in both
    views, so its two end-point pairings fit equally well: the mirror ambiguity of architecture.md.
    Recognition compares this angle with what its pixel noise can resolve.
    """
    X = as_points(points_mm, 3, "points_mm")
    d = as_points(directions, 3, "directions")
    normal = np.cross(p.source_mm - X, q.source_mm - X)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    return np.degrees(np.arcsin(np.clip(np.abs(np.einsum("ij,ij->i", normal, d)), 0.0, 1.0)))
