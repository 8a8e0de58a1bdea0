"""The compiled arithmetic of :mod:`.axis_by_length`: the rays of a view's measured points, and the body's best
centroid with its axis along each of a set of directions (the plane scan's fits).

A frame whose axis lies near an epipolar plane with its length off the body's (one not plain, :mod:`.steady_state`)
spent ~0.5-1 ms in numpy's per-call overhead on these few points (issue 8: the steady state's p99).
:func:`.axis_by_length._fit_centroids_reference` keeps the readable numpy definition (the tests compare the two);
here each direction is fitted on its own, with the same trimming, and the 3x3 normal equations are solved by
Gaussian elimination with partial pivoting (LAPACK's method, summed in another order: the centroids may differ
from numpy's in the last bits).
"""
from __future__ import annotations

import math

import numpy as np

from appliance.compiled import kernel, register_warm_up
from appliance.geometry_kernels import VIEW_SIZE, ideal_pixel, ray_direction
from appliance.recognition.head_kernels import warm_up_calibration


@kernel
def ray_directions(G: np.ndarray, o: int, pixels: np.ndarray, out: np.ndarray) -> None:
    """Unit world directions (N, 3) into ``out`` of the rays through observed pixels (N, 2) of the view at
    offset ``o`` of the packed calibration (as :meth:`appliance.geometry.View.rays`)."""
    for k in range(pixels.shape[0]):
        u, v = ideal_pixel(G, o, pixels[k, 0], pixels[k, 1])
        out[k, 0], out[k, 1], out[k, 2] = ray_direction(G, o, u, v)


@kernel
def _solve3(A: np.ndarray, b: np.ndarray, x: np.ndarray) -> None:
    """``x`` with ``A x = b`` (3x3) by Gaussian elimination with partial pivoting (``A``, ``b`` overwritten);
    NaN where ``A`` is singular."""
    for col in range(3):
        pivot = col
        for row in range(col + 1, 3):
            if abs(A[row, col]) > abs(A[pivot, col]):
                pivot = row
        if A[pivot, col] == 0.0:
            x[:] = math.nan
            return
        if pivot != col:
            for k in range(3):
                A[col, k], A[pivot, k] = A[pivot, k], A[col, k]
            b[col], b[pivot] = b[pivot], b[col]
        for row in range(col + 1, 3):
            f = A[row, col] / A[col, col]
            for k in range(col, 3):
                A[row, k] -= f * A[col, k]
            b[row] -= f * b[col]
    for row in range(2, -1, -1):
        s = b[row]
        for k in range(row + 1, 3):
            s -= A[row, k] * x[k]
        x[row] = s / A[row, row]


@kernel
def fit_centroids(directions: np.ndarray, origins: np.ndarray, rays: np.ndarray, offsets: np.ndarray,
                  weights: np.ndarray, cap: float, trim_rounds: int, centroids: np.ndarray,
                  chi2: np.ndarray) -> None:
    """:func:`.axis_by_length._fit_centroids_reference` into ``centroids`` (n, 3) and ``chi2`` (n,): per direction
    (rows of ``directions``) the moment centroid that best puts the body's points (``offsets`` along the axis
    from it) on their rays (``origins``, unit ``rays``; ``weights`` 1 / sigma^2), refitted up to
    ``trim_rounds`` times without the measurements beyond ``cap`` sigma (at least four kept), and the least
    capped chi-square of its rounds."""
    m = weights.shape[0]
    cap2 = cap * cap
    across = np.empty((m, 3, 3))
    for i in range(m):
        for j in range(3):
            for k in range(3):
                across[i, j, k] = (1.0 if j == k else 0.0) - rays[i, j] * rays[i, k]
    targets = np.empty((m, 3))
    use = np.empty(m)
    keep = np.empty(m)
    z2 = np.empty(m)
    A = np.empty((3, 3))
    b = np.empty(3)
    c = np.empty(3)
    for n in range(directions.shape[0]):
        for i in range(m):
            for j in range(3):
                targets[i, j] = origins[i, j] - offsets[i] * directions[n, j]
        use[:] = 1.0
        best = math.inf
        centroids[n, :] = 0.0
        for _ in range(trim_rounds + 1):
            A[:, :] = 0.0
            b[:] = 0.0
            for i in range(m):
                w = weights[i] * use[i]
                for j in range(3):
                    for k in range(3):
                        A[j, k] += w * across[i, j, k]
                        b[j] += w * across[i, j, k] * targets[i, k]
            _solve3(A, b, c)
            total = 0.0
            kept = 0.0
            for i in range(m):
                r2 = 0.0
                for j in range(3):
                    r = 0.0
                    for k in range(3):
                        r += across[i, j, k] * (c[k] - targets[i, k])
                    r2 += r * r
                z2[i] = weights[i] * r2
                total += min(z2[i], cap2)
                keep[i] = 1.0 if z2[i] <= cap2 else 0.0
                kept += keep[i]
            if total < best:
                best = total
                centroids[n, 0], centroids[n, 1], centroids[n, 2] = c[0], c[1], c[2]
            if kept < 4:
                keep[:] = use   # (at least four points on their rays: a direction's centroid stays fixed)
            same = True
            for i in range(m):
                if keep[i] != use[i]:
                    same = False
            if same:
                break
            use[:] = keep
        chi2[n] = best


def warm_up() -> None:
    """Compile both kernels for the calls :mod:`.axis_by_length` makes (the read-only packed calibration)."""
    G = warm_up_calibration()
    rays = np.empty((6, 3))
    pixels = np.array([[10.0, 0.0], [-10.0, 0.0], [0.0, 0.0]])
    ray_directions(G, 0, pixels, rays[:3])
    ray_directions(G, VIEW_SIZE, pixels, rays[3:])
    origins = np.zeros((6, 3))
    origins[3:, 0] = 100.0
    directions = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    fit_centroids(directions, origins, rays, np.array([1.0, -1.0, 0.0, 1.0, -1.0, 0.0]), np.ones(6), 4.0, 3,
                  np.empty((2, 3)), np.empty(2))


register_warm_up(__name__)
