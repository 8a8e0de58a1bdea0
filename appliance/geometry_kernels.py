"""Compiled two-view geometry for the per-frame path: projection, rays, optimal triangulation, epipolar distance.

A steady-state frame pair has tens of microseconds for everything (issue 8), while one numpy call on a
3-vector costs one or two. So the arithmetic of a frame's few points runs here, on plain float64 arrays,
and :mod:`appliance.geometry` / :mod:`appliance.epipolar` keep the readable numpy definitions (the
tests compare the two).

Both views of a calibration travel as one packed array (:func:`pack_views`), so a kernel call unboxes
one array instead of a dozen: per view ``K``, ``K^-1``, ``R`` (row-major), ``t``, the source
``-R^T t``, eight distortion coefficients (OpenCV's ``k1 k2 p1 p2 k3 k4 k5 k6``), a distortion flag;
then ``F`` (``x_q^T F x_p = 0``) and the DLT's world scale.

The optimal (Hartley-Sturm) correction is computed by Lindstrom's iteration ("Triangulation made
easy", CVPR 2010): the pixel moves ``dx = l (n - E~ dx')``, ``dx' = l (n' - E~^T dx)``, with ``l``
the root of the (quadratic) epipolar constraint, repeated to a fixed point, which is where the
Lagrange conditions of the least-squares problem hold and the constraint is met exactly. Two rounds
reach machine precision at any realistic noise; the loop runs until the step vanishes.
"""
from __future__ import annotations

import math

import numpy as np

from appliance.compiled import kernel, register_warm_up

# Layout of a packed view (offsets into the packed array).
_K = 0
_KI = 9
_R = 18
_T = 27
_SRC = 30
_DIST = 33
_HAS_DIST = 41
VIEW_SIZE = 42
#: Offset of F (row-major) and of the DLT's world scale in the packed array; its length.
F_OFFSET = 2 * VIEW_SIZE
SCALE_OFFSET = F_OFFSET + 9
PACKED_SIZE = SCALE_OFFSET + 1
#: Iterations and tolerance of the fixed-point undistortion, as the numpy path asks of cv2.undistortPoints.
_UNDISTORT_ITERATIONS = 100
_UNDISTORT_EPS = 1e-12
_CORRECTION_ITERATIONS = 20


def pack_view(K: np.ndarray, K_inv: np.ndarray, R: np.ndarray, t: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """One view's numbers in the packed layout (see the module docstring)."""
    packed = np.zeros(VIEW_SIZE)
    packed[_K:_K + 9] = np.ravel(K)
    packed[_KI:_KI + 9] = np.ravel(K_inv)
    packed[_R:_R + 9] = np.ravel(R)
    packed[_T:_T + 3] = t
    packed[_SRC:_SRC + 3] = -np.asarray(R).T @ np.asarray(t)
    d = np.ravel(dist)[:8]
    packed[_DIST:_DIST + d.size] = d
    packed[_HAS_DIST] = 1.0 if np.any(d != 0.0) else 0.0
    return packed


def pack_views(view_p: np.ndarray, view_q: np.ndarray, F: np.ndarray, world_scale: float) -> np.ndarray:
    """Both packed views, ``F`` and the DLT's world scale in one read-only array."""
    packed = np.concatenate([view_p, view_q, np.ravel(F), [world_scale]])
    packed.setflags(write=False)
    return packed


# ------------------------------------------------------------------------------------------------------
# Single-point building blocks (inlined into the public kernels).
# ------------------------------------------------------------------------------------------------------
@kernel
def _distort(G: np.ndarray, o: int, x: float, y: float) -> tuple[float, float]:
    """OpenCV's radial-tangential(-rational) model on normalised coordinates."""
    k1, k2, p1, p2 = G[o + _DIST], G[o + _DIST + 1], G[o + _DIST + 2], G[o + _DIST + 3]
    k3, k4, k5, k6 = G[o + _DIST + 4], G[o + _DIST + 5], G[o + _DIST + 6], G[o + _DIST + 7]
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


@kernel
def ideal_pixel(G: np.ndarray, o: int, u: float, v: float) -> tuple[float, float]:
    """Observed pixel -> ideal (undistorted) pixel of the same ``K``: OpenCV's fixed-point iteration
    (as ``cv2.undistortPoints`` runs it with the numpy path's criteria); the identity without distortion."""
    if G[o + _HAS_DIST] == 0.0:
        return u, v
    x0 = G[o + _KI] * u + G[o + _KI + 1] * v + G[o + _KI + 2]
    y0 = G[o + _KI + 4] * v + G[o + _KI + 5]
    k1, k2, p1, p2 = G[o + _DIST], G[o + _DIST + 1], G[o + _DIST + 2], G[o + _DIST + 3]
    k3, k4, k5, k6 = G[o + _DIST + 4], G[o + _DIST + 5], G[o + _DIST + 6], G[o + _DIST + 7]
    x, y = x0, y0
    error = math.inf
    for _ in range(_UNDISTORT_ITERATIONS):
        if error < _UNDISTORT_EPS:
            break
        r2 = x * x + y * y
        icdist = (1 + ((k6 * r2 + k5) * r2 + k4) * r2) / (1 + ((k3 * r2 + k2) * r2 + k1) * r2)
        if icdist < 0:
            x, y = x0, y0
            break
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x = (x0 - dx) * icdist
        y = (y0 - dy) * icdist
        xd, yd = _distort(G, o, x, y)
        error = math.sqrt((xd - x0) ** 2 + (yd - y0) ** 2)
    K = G[o + _K:o + _K + 9]
    return K[0] * x + K[1] * y + K[2], K[4] * y + K[5]


@kernel
def project_point(G: np.ndarray, o: int, X0: float, X1: float, X2: float) -> tuple[float, float]:
    """World point (mm) -> observed pixel (with distortion); NaN at or behind the source plane."""
    R = G[o + _R:o + _R + 9]
    cz = R[6] * X0 + R[7] * X1 + R[8] * X2 + G[o + _T + 2]
    if not cz > 0.0:
        return math.nan, math.nan
    x = (R[0] * X0 + R[1] * X1 + R[2] * X2 + G[o + _T]) / cz
    y = (R[3] * X0 + R[4] * X1 + R[5] * X2 + G[o + _T + 1]) / cz
    if G[o + _HAS_DIST] != 0.0:
        x, y = _distort(G, o, x, y)
    K = G[o + _K:o + _K + 9]
    return K[0] * x + K[1] * y + K[2], K[4] * y + K[5]


@kernel
def ray_direction(G: np.ndarray, o: int, u: float, v: float) -> tuple[float, float, float]:
    """Unit world direction of the ray from the source through an *ideal* pixel: ``R^T K^-1 x``, normalised."""
    Ki = G[o + _KI:o + _KI + 9]
    R = G[o + _R:o + _R + 9]
    x = Ki[0] * u + Ki[1] * v + Ki[2]
    y = Ki[3] * u + Ki[4] * v + Ki[5]
    z = Ki[6] * u + Ki[7] * v + Ki[8]
    d0 = R[0] * x + R[3] * y + R[6] * z
    d1 = R[1] * x + R[4] * y + R[7] * z
    d2 = R[2] * x + R[5] * y + R[8] * z
    n = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    return d0 / n, d1 / n, d2 / n


@kernel
def epipolar_distance(G: np.ndarray, up: float, vp: float, uq: float, vq: float) -> float:
    """Symmetric geometric epipolar distance (px) of one pair of ideal pixels (as ``epipolar_distance_px``)."""
    F = G[F_OFFSET:F_OFFSET + 9]
    # Line in q of the p pixel: F x_p; line in p of the q pixel: F^T x_q.
    a = F[0] * up + F[1] * vp + F[2]
    b = F[3] * up + F[4] * vp + F[5]
    c = F[6] * up + F[7] * vp + F[8]
    a2 = F[0] * uq + F[3] * vq + F[6]
    b2 = F[1] * uq + F[4] * vq + F[7]
    c2 = F[2] * uq + F[5] * vq + F[8]
    if a == 0.0 and b == 0.0 or a2 == 0.0 and b2 == 0.0:
        return math.nan  # a pixel at its view's epipole: no epipolar line
    d_q = (a * uq + b * vq + c) / math.hypot(a, b)
    d_p = (a2 * up + b2 * vp + c2) / math.hypot(a2, b2)
    return math.sqrt((d_p * d_p + d_q * d_q) / 2.0)


@kernel
def optimal_correction(G: np.ndarray, up: float, vp: float, uq: float, vq: float
                       ) -> tuple[float, float, float, float]:
    """The smallest move of two ideal pixels onto the epipolar constraint (Lindstrom's iteration, see the
    module docstring); a pair it cannot handle keeps its pixels (as the numpy path does)."""
    F = G[F_OFFSET:F_OFFSET + 9]
    # Constraint x_q^T F x_p = 0 with x_p = (up, vp, 1) - S^T dp, x_q = (uq, vq, 1) - S^T dq.
    # n: gradient w.r.t. x_p's first two coordinates (F^T x_q), m: w.r.t. x_q's (F x_p); E~ = S F^T S^T.
    n0 = F[0] * uq + F[3] * vq + F[6]
    n1 = F[1] * uq + F[4] * vq + F[7]
    m0 = F[0] * up + F[1] * vp + F[2]
    m1 = F[3] * up + F[4] * vp + F[5]
    c = uq * m0 + vq * m1 + (F[6] * up + F[7] * vp + F[8])
    # x_q^T F x_p after the moves: c - dp.n - dq.m + dq^T F2 dp with F2 the upper-left 2x2 of F.
    f00, f01, f10, f11 = F[0], F[1], F[3], F[4]
    dp0 = dp1 = dq0 = dq1 = 0.0
    lam = 0.0
    for _ in range(_CORRECTION_ITERATIONS):
        gp0 = n0 - (dq0 * f00 + dq1 * f10)
        gp1 = n1 - (dq0 * f01 + dq1 * f11)
        gq0 = m0 - (f00 * dp0 + f01 * dp1)
        gq1 = m1 - (f10 * dp0 + f11 * dp1)
        a = gq0 * (f00 * gp0 + f01 * gp1) + gq1 * (f10 * gp0 + f11 * gp1)
        b = gp0 * n0 + gp1 * n1 + gq0 * m0 + gq1 * m1
        disc = b * b - 4.0 * a * c
        if not disc >= 0.0:
            return up, vp, uq, vq
        root = math.sqrt(disc)
        denominator = b + root if b >= 0.0 else b - root
        if denominator == 0.0:
            return up, vp, uq, vq
        new = 2.0 * c / denominator
        dp0, dp1, dq0, dq1 = new * gp0, new * gp1, new * gq0, new * gq1
        if abs(new - lam) <= 1e-15 * abs(new):
            break
        lam = new
    out_p0, out_p1, out_q0, out_q1 = up - dp0, vp - dp1, uq - dq0, vq - dq1
    if not (math.isfinite(out_p0) and math.isfinite(out_p1) and math.isfinite(out_q0) and math.isfinite(out_q1)):
        return up, vp, uq, vq
    return out_p0, out_p1, out_q0, out_q1


@kernel
def symmetric_eigen(M: np.ndarray, values: np.ndarray, vectors: np.ndarray) -> None:
    """Eigenvalues (ascending) and unit eigenvectors (columns) of a small symmetric matrix, by cyclic Jacobi
    rotations (``M`` is overwritten)."""
    n = M.shape[0]
    for i in range(n):
        for j in range(n):
            vectors[i, j] = 1.0 if i == j else 0.0
    for _ in range(50):
        rotated = False
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = M[p, q]
                if apq == 0.0:
                    continue
                # An element too small to change either diagonal entry is zero (Jacobi converges
                # quadratically, so this is reached in a few sweeps; a relative test on the whole
                # matrix would stall on rounding).
                small = 100.0 * abs(apq)
                if abs(M[p, p]) + small == abs(M[p, p]) and abs(M[q, q]) + small == abs(M[q, q]):
                    M[p, q] = M[q, p] = 0.0
                    continue
                rotated = True
                theta = (M[q, q] - M[p, p]) / (2.0 * apq)
                t = (1.0 if theta >= 0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for k in range(n):
                    mkp, mkq = M[k, p], M[k, q]
                    M[k, p] = c * mkp - s * mkq
                    M[k, q] = s * mkp + c * mkq
                for k in range(n):
                    mpk, mqk = M[p, k], M[q, k]
                    M[p, k] = c * mpk - s * mqk
                    M[q, k] = s * mpk + c * mqk
                for k in range(n):
                    vkp, vkq = vectors[k, p], vectors[k, q]
                    vectors[k, p] = c * vkp - s * vkq
                    vectors[k, q] = s * vkp + c * vkq
        if not rotated:
            break
    for i in range(n):
        values[i] = M[i, i]
    # Sort ascending (insertion sort on a handful of values), columns along.
    for i in range(1, n):
        j = i
        while j > 0 and values[j - 1] > values[j]:
            values[j - 1], values[j] = values[j], values[j - 1]
            for k in range(n):
                vectors[k, j - 1], vectors[k, j] = vectors[k, j], vectors[k, j - 1]
            j -= 1


@kernel
def _camera_depth(G: np.ndarray, o: int, X0: float, X1: float, X2: float) -> float:
    return G[o + _R + 6] * X0 + G[o + _R + 7] * X1 + G[o + _R + 8] * X2 + G[o + _T + 2]


@kernel
def _intersect_rays(G: np.ndarray, up: float, vp: float, uq: float, vq: float) -> tuple[float, float, float]:
    """Where the rays of two ideal pixels on each other's epipolar lines meet: the DLT's exact solution
    for such a pair (its four equations then have a null vector), at a tenth of the cost. Computed as
    the midpoint of the rays' closest points, so rounding in the correction does not matter."""
    o = VIEW_SIZE
    a0, a1, a2 = ray_direction(G, 0, up, vp)
    b0, b1, b2 = ray_direction(G, o, uq, vq)
    w0, w1, w2 = G[_SRC] - G[o + _SRC], G[_SRC + 1] - G[o + _SRC + 1], G[_SRC + 2] - G[o + _SRC + 2]
    k = a0 * b0 + a1 * b1 + a2 * b2
    denominator = 1.0 - k * k
    if not denominator > 1e-15:  # parallel rays: a point at infinity
        return math.nan, math.nan, math.nan
    wa = w0 * a0 + w1 * a1 + w2 * a2
    wb = w0 * b0 + w1 * b1 + w2 * b2
    s = (k * wb - wa) / denominator  # along p's ray
    t = (wb - k * wa) / denominator  # along q's ray
    X0 = 0.5 * (G[_SRC] + s * a0 + G[o + _SRC] + t * b0)
    X1 = 0.5 * (G[_SRC + 1] + s * a1 + G[o + _SRC + 1] + t * b1)
    X2 = 0.5 * (G[_SRC + 2] + s * a2 + G[o + _SRC + 2] + t * b2)
    if _camera_depth(G, 0, X0, X1, X2) <= 0.0 or _camera_depth(G, o, X0, X1, X2) <= 0.0:
        return math.nan, math.nan, math.nan
    return X0, X1, X2


@kernel
def triangulate_ideal(G: np.ndarray, up: float, vp: float, uq: float, vq: float, optimal: bool
                      ) -> tuple[float, float, float]:
    """World point (mm) of a pair of ideal pixels: optionally corrected onto the epipolar constraint (then the
    rays meet), else the linear DLT in normalised coordinates with the world scaled (as
    :func:`appliance.epipolar.triangulate`); NaN at infinity or at or behind either source."""
    if optimal:
        up, vp, uq, vq = optimal_correction(G, up, vp, uq, vq)
        if not (up == up and uq == uq):  # NaN pixels: no point
            return math.nan, math.nan, math.nan
        return _intersect_rays(G, up, vp, uq, vq)
    s = G[SCALE_OFFSET]
    A = np.empty((4, 4))
    row = 0
    for view in range(2):
        o = view * VIEW_SIZE
        u, v = (up, vp) if view == 0 else (uq, vq)
        Ki = G[o + _KI:o + _KI + 9]
        xn0 = Ki[0] * u + Ki[1] * v + Ki[2]
        xn1 = Ki[3] * u + Ki[4] * v + Ki[5]
        for axis in range(2):
            x = xn0 if axis == 0 else xn1
            norm = 0.0
            for k in range(4):
                third = G[o + _R + 6 + k] if k < 3 else G[o + _T + 2] / s
                this = G[o + _R + 3 * axis + k] if k < 3 else G[o + _T + axis] / s
                A[row, k] = x * third - this
                norm += A[row, k] * A[row, k]
            norm = math.sqrt(norm)
            for k in range(4):
                A[row, k] /= norm
            row += 1
    M = np.empty((4, 4))
    for i in range(4):
        for j in range(4):
            total = 0.0
            for k in range(4):
                total += A[k, i] * A[k, j]
            M[i, j] = total
    values = np.empty(4)
    vectors = np.empty((4, 4))
    symmetric_eigen(M, values, vectors)
    w = vectors[3, 0]
    if w == 0.0:  # a point at infinity (parallel rays)
        return math.nan, math.nan, math.nan
    X0, X1, X2 = vectors[0, 0] / w * s, vectors[1, 0] / w * s, vectors[2, 0] / w * s
    if not (math.isfinite(X0) and math.isfinite(X1) and math.isfinite(X2)):
        return math.nan, math.nan, math.nan
    if _camera_depth(G, 0, X0, X1, X2) <= 0.0 or _camera_depth(G, VIEW_SIZE, X0, X1, X2) <= 0.0:
        return math.nan, math.nan, math.nan
    return X0, X1, X2


# ------------------------------------------------------------------------------------------------------
# Array kernels behind the public functions of appliance.geometry / appliance.epipolar.
# ------------------------------------------------------------------------------------------------------
@kernel
def triangulate_points(G: np.ndarray, uv_p: np.ndarray, uv_q: np.ndarray, optimal: bool) -> np.ndarray:
    """World points (N,3) of observed (distorted) pixel pairs (N,2) and (N,2)."""
    n = uv_p.shape[0]
    out = np.empty((n, 3))
    for i in range(n):
        up, vp = ideal_pixel(G, 0, uv_p[i, 0], uv_p[i, 1])
        uq, vq = ideal_pixel(G, VIEW_SIZE, uv_q[i, 0], uv_q[i, 1])
        out[i, 0], out[i, 1], out[i, 2] = triangulate_ideal(G, up, vp, uq, vq, optimal)
    return out


@kernel
def correct_points(G: np.ndarray, uv_p: np.ndarray, uv_q: np.ndarray) -> np.ndarray:
    """Ideal pixel pairs (N,2), (N,2) moved onto the epipolar constraint: (N,4) ``up vp uq vq``."""
    n = uv_p.shape[0]
    out = np.empty((n, 4))
    for i in range(n):
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = optimal_correction(G, uv_p[i, 0], uv_p[i, 1],
                                                                         uv_q[i, 0], uv_q[i, 1])
    return out


@kernel
def project_into_both(G: np.ndarray, points: np.ndarray) -> np.ndarray:
    """World points (N,3) -> observed pixels in view p and q, (2, N, 2); NaN rows where not imaged."""
    n = points.shape[0]
    out = np.empty((2, n, 2))
    for view in range(2):
        for i in range(n):
            out[view, i, 0], out[view, i, 1] = project_point(G, view * VIEW_SIZE, points[i, 0], points[i, 1],
                                                             points[i, 2])
    return out


@kernel
def project_segment(G: np.ndarray, c0: float, c1: float, c2: float, d0: float, d1: float, d2: float,
                    half: float) -> np.ndarray:
    """The centre and both ends ``c +- half d`` of a 3D segment in view p and q, (2, 3, 2) (the tracker's
    prediction of the robot's image)."""
    out = np.empty((2, 3, 2))
    for view in range(2):
        o = view * VIEW_SIZE
        out[view, 0, 0], out[view, 0, 1] = project_point(G, o, c0, c1, c2)
        out[view, 1, 0], out[view, 1, 1] = project_point(G, o, c0 + half * d0, c1 + half * d1, c2 + half * d2)
        out[view, 2, 0], out[view, 2, 1] = project_point(G, o, c0 - half * d0, c1 - half * d1, c2 - half * d2)
    return out


def warm_up() -> None:
    """Compile every kernel of this module on a tiny two-view geometry."""
    eye = np.eye(3)
    view_p = pack_view(np.diag([1000.0, 1000.0, 1.0]), np.diag([1e-3, 1e-3, 1.0]), eye, np.array([0.0, 0.0, 500.0]),
                       np.array([1e-3, 0.0, 0.0, 0.0, 0.0]))
    turn = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    view_q = pack_view(np.diag([1000.0, 1000.0, 1.0]), np.diag([1e-3, 1e-3, 1.0]), turn, np.array([0.0, 0.0, 500.0]),
                       np.zeros(5))
    G = pack_views(view_p, view_q, np.ones((3, 3)) / 3.0, 500.0)
    pixels = np.zeros((1, 2))
    triangulate_points(G, pixels, pixels, True)
    triangulate_points(G, pixels, pixels, False)
    correct_points(G, pixels, pixels)
    project_into_both(G, np.zeros((1, 3)))
    project_segment(G, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0)


register_warm_up(__name__)
