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

Units: positions in mm in and out (the project's convention), fields in T per A, gradients in
T/m per A, forces in N per A.
"""
from __future__ import annotations

import logging

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import ellipe, ellipk

from appliance.control.coils_config import CoilsConfig

logger = logging.getLogger(__name__)

MU0 = 4e-7 * np.pi  # T m / A; the 2019 SI value differs by 1e-10 relative, far below model error
_FD_STEP_M = 20e-6
_OFFSETS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)

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
        # Sums loop contributions into their coil: (n_coils, n_loops).
        self._gather = np.zeros((self.n, len(owner)))
        self._gather[owner, np.arange(len(owner))] = 1.0
        self.max_current_a = np.array([c.max_current_a for c in config.coils])
        self.resistance_ohm = np.array([c.resistance_ohm for c in config.coils])
        self.inductance_h = np.array([c.inductance_h for c in config.coils])

    def _per_amp(self, points_m: FloatArray) -> FloatArray:
        """(P, 3, n): field per ampere of every coil at every point."""
        loops = loop_field(self._centres, self._axes, self._radii, self._turns, points_m)
        coils = np.einsum("cl,lpk->pkc", self._gather, loops)
        return coils

    def field_per_amp(self, point_mm: ArrayLike) -> FloatArray:
        """3 x n matrix: column k is the field (T) at ``point_mm`` for 1 A in coil k."""
        p = np.asarray(point_mm, float).reshape(1, 3) * 1e-3
        return self._per_amp(p)[0]

    def gradient_per_amp(self, point_mm: ArrayLike) -> FloatArray:
        """9 x n matrix: row 3*i + j is dB_i/dx_j (T/m) at ``point_mm`` for 1 A in coil k.

        In a current-free region the 3x3 gradient is symmetric and traceless (5 independent entries).
        """
        p = np.asarray(point_mm, float).reshape(1, 3) * 1e-3
        fields = self._per_amp(p + _FD_STEP_M * _OFFSETS)                # (6,3,n)
        grad = np.empty((3, 3, self.n))
        for j in range(3):
            grad[:, j, :] = (fields[2 * j] - fields[2 * j + 1]) / (2.0 * _FD_STEP_M)
        return grad.reshape(9, self.n)

    def force_per_amp(self, point_mm: ArrayLike, moment_am2: ArrayLike) -> FloatArray:
        """3 x n: force (N) on a dipole ``moment_am2`` per ampere in coil k, F = grad(m . B)."""
        m = np.asarray(moment_am2, float)
        grad = self.gradient_per_amp(point_mm).reshape(3, 3, self.n)
        return np.einsum("i,ijk->jk", m, grad)

    def field(self, point_mm: ArrayLike, currents_a: ArrayLike) -> FloatArray:
        """Field (T) at a point for a currents vector."""
        return self.field_per_amp(point_mm) @ np.asarray(currents_a, float)

    def force(self, point_mm: ArrayLike, moment_am2: ArrayLike, currents_a: ArrayLike) -> FloatArray:
        """Force (N) on a dipole at a point for a currents vector."""
        return self.force_per_amp(point_mm, moment_am2) @ np.asarray(currents_a, float)
