"""Actuation model: magnetic field and field gradient per ampere of each configured coil at a point.

This is what the appliance *knows* about its coils (``config/coils.yaml``), not the truth: the
simulated world computes its fields independently with magpylib from a possibly perturbed geometry,
and the tests compare the two.

Each coil is a set of coaxial circular current loops. The field of one loop is exact, from the
complete elliptic integrals K(m), E(m) (Smythe / Jackson form, m = k^2 = 4 a rho / ((a + rho)^2 + z^2)):

    B_z   = mu0 I / (2 pi beta) [K + (a^2 - rho^2 - z^2) / alpha^2 E]
    B_rho = mu0 I z / (2 pi rho beta) [-K + (a^2 + rho^2 + z^2) / alpha^2 E]

with alpha^2 = (a - rho)^2 + z^2 and beta^2 = (a + rho)^2 + z^2, in the loop's cylindrical frame.
The gradient is a central finite difference of that exact field (step 20 um; truncation error is
below 1e-8 relative for coils of centimetres).

The per-frame evaluation (field and gradient of every coil at the robot, 7 points x 32 loops) is one
compiled kernel (:mod:`appliance.compiled`): K and E come from the arithmetic-geometric mean (machine
precision, the same values as ``scipy.special.ellipk``/``ellipe`` to ~1e-15), so a frame's actuation
matrix costs microseconds instead of the ~40 numpy calls of the vectorised form, which is kept
(:func:`loop_field`) as the readable reference the kernel is tested against.

Units: positions in mm in and out (the project's convention), fields in T per A, gradients in
T/m per A, forces in N per A.
"""
from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import ellipe, ellipk

from appliance.compiled import kernel, register_warm_up
from appliance.control.coils_config import CoilsConfig

logger = logging.getLogger(__name__)

MU0 = 4e-7 * np.pi  # T m / A; the 2019 SI value differs by 1e-10 relative, far below model error
_FD_STEP_M = 20e-6

FloatArray = NDArray[np.float64]


def loop_field(centres_m: FloatArray, axes: FloatArray, radii_m: FloatArray, currents: FloatArray,
               points_m: FloatArray) -> FloatArray:
    """Field (T) of each loop at each point: array (n_loops, n_points, 3).

    ``centres_m`` (L,3), ``axes`` (L,3) unit, ``radii_m`` (L,), ``currents`` (L,) in A-turns,
    ``points_m`` (P,3).
    """
    d = points_m[None, :, :] - centres_m[:, None, :]                    # (L,P,3)
    z = np.einsum("lpk,lk->lp", d, axes)                                 # (L,P)
    radial = d - z[..., None] * axes[:, None, :]
    rho = np.linalg.norm(radial, axis=-1)
    a = radii_m[:, None]
    alpha2 = (a - rho) ** 2 + z**2
    beta2 = (a + rho) ** 2 + z**2
    beta = np.sqrt(beta2)
    m = np.clip(4.0 * a * rho / beta2, 0.0, 1.0 - 1e-15)
    k_int, e_int = ellipk(m), ellipe(m)
    c = MU0 * currents[:, None] / (2.0 * np.pi)
    bz = c / beta * (k_int + (a**2 - rho**2 - z**2) / alpha2 * e_int)
    on_axis = rho < 1e-12
    safe_rho = np.where(on_axis, 1.0, rho)
    b_rho = np.where(on_axis, 0.0, c * z / (safe_rho * beta) * (-k_int + (a**2 + rho**2 + z**2) / alpha2 * e_int))
    unit_radial = np.where(on_axis[..., None], 0.0, radial / safe_rho[..., None])
    return bz[..., None] * axes[:, None, :] + b_rho[..., None] * unit_radial


@kernel
def _elliptic_k_e(m: float) -> tuple[float, float]:
    """Complete elliptic integrals K(m), E(m) by the arithmetic-geometric mean (0 <= m < 1).

    a_0 = 1, b_0 = sqrt(1 - m), c_0 = sqrt(m); K = pi / (2 a_N), E = K (1 - sum 2^(n-1) c_n^2).
    c_n shrinks quadratically (c_(n+1) ~ c_n^2 / 4a), so once c_n < 1e-10 a the a just computed is
    the limit to ~1e-20 and later terms of the sum are below 1e-40: stop there (a smaller threshold
    would never be met when a and b end one ulp apart, and the doubling weights would add noise).
    """
    a = 1.0
    b = math.sqrt(1.0 - m)
    weight = 0.5
    total = 0.5 * m
    for _ in range(64):
        c = 0.5 * (a - b)
        a, b = 0.5 * (a + b), math.sqrt(a * b)
        weight *= 2.0
        total += weight * c * c
        if abs(c) <= 1e-10 * a:
            break
    k_int = math.pi / (2.0 * a)
    return k_int, k_int * (1.0 - total)


@kernel
def _coil_fields(centres: FloatArray, axes: FloatArray, radii: FloatArray, turns: FloatArray,
                 owner: NDArray[np.int64], n_coils: int, points_m: FloatArray) -> FloatArray:
    """(P, 3, n_coils): field (T) per ampere of every coil at every point; :func:`loop_field`, loop by loop."""
    n_points = points_m.shape[0]
    out = np.zeros((n_points, 3, n_coils))
    c0 = MU0 / (2.0 * math.pi)
    for p in range(n_points):
        for l in range(radii.shape[0]):
            dx = points_m[p, 0] - centres[l, 0]
            dy = points_m[p, 1] - centres[l, 1]
            dz = points_m[p, 2] - centres[l, 2]
            ax, ay, az = axes[l, 0], axes[l, 1], axes[l, 2]
            z = dx * ax + dy * ay + dz * az
            rx, ry, rz = dx - z * ax, dy - z * ay, dz - z * az
            rho = math.sqrt(rx * rx + ry * ry + rz * rz)
            a = radii[l]
            alpha2 = (a - rho) ** 2 + z * z
            beta2 = (a + rho) ** 2 + z * z
            beta = math.sqrt(beta2)
            m = min(max(4.0 * a * rho / beta2, 0.0), 1.0 - 1e-15)
            k_int, e_int = _elliptic_k_e(m)
            c = c0 * turns[l]
            bz = c / beta * (k_int + (a * a - rho * rho - z * z) / alpha2 * e_int)
            coil = owner[l]
            out[p, 0, coil] += bz * ax
            out[p, 1, coil] += bz * ay
            out[p, 2, coil] += bz * az
            if rho >= 1e-12:   # off the axis: the radial component
                b_rho = c * z / (rho * beta) * (-k_int + (a * a + rho * rho + z * z) / alpha2 * e_int)
                out[p, 0, coil] += b_rho * rx / rho
                out[p, 1, coil] += b_rho * ry / rho
                out[p, 2, coil] += b_rho * rz / rho
    return out


@kernel
def _field_and_gradient(centres: FloatArray, axes: FloatArray, radii: FloatArray, turns: FloatArray,
                        owner: NDArray[np.int64], n_coils: int, point_m: FloatArray,
                        step_m: float) -> tuple[FloatArray, FloatArray]:
    """(3 x n field per ampere, 9 x n gradient per ampere) at one point: the field there and the
    central difference of the fields at the six points ``step_m`` away along each axis."""
    points = np.empty((7, 3))
    for i in range(7):
        for k in range(3):
            points[i, k] = point_m[k]
    for j in range(3):
        points[1 + 2 * j, j] += step_m
        points[2 + 2 * j, j] -= step_m
    fields = _coil_fields(centres, axes, radii, turns, owner, n_coils, points)
    gradient = np.empty((9, n_coils))
    for i in range(3):
        for j in range(3):
            for c in range(n_coils):
                gradient[3 * i + j, c] = (fields[1 + 2 * j, i, c] - fields[2 + 2 * j, i, c]) / (2.0 * step_m)
    return fields[0].copy(), gradient


@kernel
def _force_rows(gradient: FloatArray, moment: FloatArray) -> FloatArray:
    """3 x n: F_j = sum_i m_i dB_i/dx_j per ampere, from the 9 x n gradient."""
    n = gradient.shape[1]
    force = np.zeros((3, n))
    for i in range(3):
        for j in range(3):
            for c in range(n):
                force[j, c] += moment[i] * gradient[3 * i + j, c]
    return force


class ActuationModel:
    """Field and gradient per ampere at a point, for the configured coils (one coil per channel)."""

    def __init__(self, config: CoilsConfig) -> None:
        self.config = config
        self.names = [c.name for c in config.coils]
        self.n = len(config.coils)
        centres, axes, radii, turns, owner = [], [], [], [], []
        for index, coil in enumerate(config.coils):
            axis = np.asarray(coil.axis, float)
            centre = np.asarray(coil.centre_mm, float) * 1e-3
            winding = coil.winding
            n_ax = winding.loops_axial if winding else 1
            n_rad = winding.loops_radial if winding else 1
            length = (winding.length_mm if winding else 0.0) * 1e-3
            depth = (winding.depth_mm if winding else 0.0) * 1e-3
            for i in range(n_ax):
                offset = (-0.5 + (i + 0.5) / n_ax) * length
                for j in range(n_rad):
                    centres.append(centre + offset * axis)
                    axes.append(axis)
                    radii.append(coil.radius_mm * 1e-3 + (-0.5 + (j + 0.5) / n_rad) * depth)
                    turns.append(coil.turns / (n_ax * n_rad))
                    owner.append(index)
        self._centres = np.array(centres)
        self._axes = np.array(axes)
        self._radii = np.array(radii)
        self._turns = np.array(turns)
        self._owner = np.array(owner, dtype=np.int64)
        #: The loops as the kernels take them: centres (m), unit axes, radii (m), turns, owning coil.
        self.loops = (self._centres, self._axes, self._radii, self._turns, self._owner)
        # Sums loop contributions into their coil: (n_coils, n_loops).
        self._gather = np.zeros((self.n, len(owner)))
        self._gather[owner, np.arange(len(owner))] = 1.0
        self.max_current_a = np.array([c.max_current_a for c in config.coils])
        self.resistance_ohm = np.array([c.resistance_ohm for c in config.coils])
        self.inductance_h = np.array([c.inductance_h for c in config.coils])

    def _per_amp(self, points_m: FloatArray) -> FloatArray:
        """(P, 3, n): field per ampere of every coil at every point."""
        points = np.ascontiguousarray(points_m, dtype=np.float64).reshape(-1, 3)
        return _coil_fields(self._centres, self._axes, self._radii, self._turns, self._owner, self.n, points)

    def field_and_gradient_per_amp(self, point_mm: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """(3 x n field, 9 x n gradient) per ampere at ``point_mm``, in one kernel call (see below)."""
        p = np.asarray(point_mm, dtype=np.float64).reshape(3) * 1e-3
        return _field_and_gradient(self._centres, self._axes, self._radii, self._turns, self._owner, self.n, p,
                                   _FD_STEP_M)

    def field_per_amp(self, point_mm: ArrayLike) -> FloatArray:
        """3 x n matrix: column k is the field (T) at ``point_mm`` for 1 A in coil k."""
        p = np.asarray(point_mm, float).reshape(1, 3) * 1e-3
        return self._per_amp(p)[0]

    def gradient_per_amp(self, point_mm: ArrayLike) -> FloatArray:
        """9 x n matrix: row 3*i + j is dB_i/dx_j (T/m) at ``point_mm`` for 1 A in coil k.

        In a current-free region the 3x3 gradient is symmetric and traceless (5 independent entries).
        """
        return self.field_and_gradient_per_amp(point_mm)[1]

    def force_per_amp(self, point_mm: ArrayLike, moment_am2: ArrayLike) -> FloatArray:
        """3 x n: force (N) on a dipole ``moment_am2`` per ampere in coil k, F = grad(m . B)."""
        return self.force_from_gradient(self.gradient_per_amp(point_mm), moment_am2)

    @staticmethod
    def force_from_gradient(gradient: FloatArray, moment_am2: ArrayLike) -> FloatArray:
        """3 x n force per ampere on a dipole ``moment_am2`` from a 9 x n gradient per ampere."""
        return _force_rows(gradient, np.asarray(moment_am2, dtype=np.float64).reshape(3))

    def field(self, point_mm: ArrayLike, currents_a: ArrayLike) -> FloatArray:
        """Field (T) at a point for a currents vector."""
        return self.field_per_amp(point_mm) @ np.asarray(currents_a, float)

    def force(self, point_mm: ArrayLike, moment_am2: ArrayLike, currents_a: ArrayLike) -> FloatArray:
        """Force (N) on a dipole at a point for a currents vector."""
        return self.force_per_amp(point_mm, moment_am2) @ np.asarray(currents_a, float)


def warm_up() -> None:
    """Compile the kernels of this module on a one-loop coil (see :mod:`appliance.compiled`)."""
    centres, axes = np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]])
    radii, turns, owner = np.array([0.05]), np.array([1.0]), np.zeros(1, dtype=np.int64)
    _, gradient = _field_and_gradient(centres, axes, radii, turns, owner, 1, np.array([0.01, 0.0, 0.0]), _FD_STEP_M)
    _coil_fields(centres, axes, radii, turns, owner, 1, np.zeros((1, 3)))
    _force_rows(gradient, np.array([0.0, 0.0, 1.0]))


register_warm_up(__name__)
