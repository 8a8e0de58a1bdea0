"""Actuation model: magnetic field and field gradient per ampere of each configured coil at a point.

This is what the appliance *knows* about its coils (``config/coils.yaml``), not the truth: the
simulated world computes its fields independently with magpylib from a possibly perturbed geometry,
and the tests compare the two.

Each coil is a set of coaxial circular current loops. The field of one loop is exact, from the
complete elliptic integrals K(m), E(m) (Smythe / Jackson form, m = k^2 = 4 a rho / ((a + rho)^2 + z^2)):

    B_z   = mu0 I / (2 pi beta) [K + (a^2 - rho^2 - z^2) / alpha^2 E]
    B_rho = mu0 I z / (2 pi rho beta) [-K + (a^2 + rho^2 + z^2) / alpha^2 E]

with alpha^2 = (a - rho)^2 + z^2 and beta^2 = (a + rho)^2 + z^2, in the loop's cylindrical frame.
The gradient is analytic: the derivatives of that form in rho and z (dK/dm and dE/dm are closed forms in K
and E), and near a loop's axis, where the form is a difference of nearly equal terms, the off-axis expansion
of the axial field (:func:`_loop_derivatives`). It replaced a 7-point central difference (step 20 um, 1.3e-8
relative truncation error), at under half the cost (issue 8, round 14).

The per-frame evaluation (field and gradient of every coil at the robot, 32 loops) is one
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
#: Below this distance from a loop's axis (in loop radii) the gradient comes from the axial field's
#: expansion, above it from the closed form (see :func:`_loop_derivatives`).
AXIS_SERIES_RHO = 3e-3

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
def _loop_frame_and_axial_field(dx: float, dy: float, dz: float, ax: float, ay: float, az: float, a: float,
                                c: float) -> tuple[float, float, float, float, float, float, float, float, float,
                                                   float, float]:
    """One loop of radius ``a`` (unit axis ``ax, ay, az``, ``c`` = mu0 N / (2 pi) per ampere) seen from a point
    at ``dx, dy, dz`` (m) from its centre: the radial vector ``rx, ry, rz`` and its length ``rho``, the axial
    coordinate ``z``, ``alpha2`` and ``beta`` of the Smythe form, the modulus ``m``, K(m), E(m), and the axial
    field ``bz`` (module docstring). Shared by :func:`_coil_fields` and :func:`_field_and_gradient`."""
    z = dx * ax + dy * ay + dz * az
    rx, ry, rz = dx - z * ax, dy - z * ay, dz - z * az
    rho = math.sqrt(rx * rx + ry * ry + rz * rz)
    alpha2 = (a - rho) ** 2 + z * z
    beta2 = (a + rho) ** 2 + z * z
    beta = math.sqrt(beta2)
    m = min(max(4.0 * a * rho / beta2, 0.0), 1.0 - 1e-15)
    k_int, e_int = _elliptic_k_e(m)
    bz = c / beta * (k_int + (a * a - rho * rho - z * z) / alpha2 * e_int)
    return rx, ry, rz, rho, z, alpha2, beta, m, k_int, e_int, bz


@kernel
def _coil_fields(centres: FloatArray, axes: FloatArray, radii: FloatArray, turns: FloatArray,
                 owner: NDArray[np.int64], n_coils: int, points_m: FloatArray) -> FloatArray:
    """(P, 3, n_coils): field (T) per ampere of every coil at every point; :func:`loop_field`, loop by loop."""
    n_points = points_m.shape[0]
    out = np.zeros((n_points, 3, n_coils))
    c0 = MU0 / (2.0 * math.pi)
    for p in range(n_points):
        for l in range(radii.shape[0]):
            ax, ay, az = axes[l, 0], axes[l, 1], axes[l, 2]
            a = radii[l]
            c = c0 * turns[l]
            rx, ry, rz, rho, z, alpha2, beta, m, k_int, e_int, bz = _loop_frame_and_axial_field(
                points_m[p, 0] - centres[l, 0], points_m[p, 1] - centres[l, 1], points_m[p, 2] - centres[l, 2],
                ax, ay, az, a, c)
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
                        owner: NDArray[np.int64], n_coils: int, point_m: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(3 x n field per ampere, 9 x n gradient per ampere) at one point, loop by loop in one pass.

    The field is :func:`_coil_fields`' arithmetic (the same numbers). The gradient is analytic: in a loop's
    frame (axis n, radial unit e = r / rho, P = I - n n^T)

        dB_i/dx_j = n_i (dBz/drho e_j + dBz/dz n_j) + e_i (dBrho/drho e_j + dBrho/dz n_j) + Brho/rho (P_ij - e_i e_j)

    with the cylindrical derivatives from :func:`_loop_derivatives`.
    """
    field = np.zeros((3, n_coils))
    gradient = np.zeros((9, n_coils))
    normal = np.empty(3)
    radial = np.empty(3)
    c0 = MU0 / (2.0 * math.pi)
    for l in range(radii.shape[0]):
        ax, ay, az = axes[l, 0], axes[l, 1], axes[l, 2]
        a = radii[l]
        c = c0 * turns[l]
        rx, ry, rz, rho, z, alpha2, beta, m, k_int, e_int, bz = _loop_frame_and_axial_field(
            point_m[0] - centres[l, 0], point_m[1] - centres[l, 1], point_m[2] - centres[l, 2], ax, ay, az, a, c)
        coil = owner[l]
        field[0, coil] += bz * ax
        field[1, coil] += bz * ay
        field[2, coil] += bz * az
        normal[0], normal[1], normal[2] = ax, ay, az
        radial[0], radial[1], radial[2] = 0.0, 0.0, 0.0
        if rho >= 1e-12:   # off the axis: the radial component
            b_rho = c * z / (rho * beta) * (-k_int + (a * a + rho * rho + z * z) / alpha2 * e_int)
            field[0, coil] += b_rho * rx / rho
            field[1, coil] += b_rho * ry / rho
            field[2, coil] += b_rho * rz / rho
        if rho > 0.0:
            radial[0], radial[1], radial[2] = rx / rho, ry / rho, rz / rho
        bz_rho, bz_z, br_rho, br_z, br_over_rho = _loop_derivatives(a, rho, z, c, m, k_int, e_int)
        for i in range(3):
            for j in range(3):
                value = (normal[i] * (bz_rho * radial[j] + bz_z * normal[j])
                         + radial[i] * (br_rho * radial[j] + br_z * normal[j])
                         - br_over_rho * (normal[i] * normal[j] + radial[i] * radial[j]))
                if i == j:
                    value += br_over_rho
                gradient[3 * i + j, coil] += value
    return field, gradient


@kernel
def _loop_derivatives(a: float, rho: float, z: float, c: float, m: float, k_int: float,
                      e_int: float) -> tuple[float, float, float, float, float]:
    """dBz/drho, dBz/dz, dBrho/drho, dBrho/dz and Brho/rho (T/m) of one loop of radius ``a`` carrying
    ``c`` = mu0 I / (2 pi), at (``rho``, ``z``) in its frame; ``m``, K(m), E(m) as the field used them.

    Off the axis: the derivatives of the Smythe form (module docstring), with dK/dm = (E - (1 - m) K) /
    (2 m (1 - m)) and dE/dm = (E - K) / (2 m). Near the axis (rho < AXIS_SERIES_RHO a) that form is a
    difference of nearly equal terms (Brho/rho loses ~(a/rho)^2 eps), and the workspace centre lies on
    every coil's axis; there the off-axis expansion of the axial field f(z) = pi c a^2 / (a^2 + z^2)^1.5
    is used: Bz = f - rho^2/4 f2 + rho^4/64 f4, Brho = -rho/2 f1 + rho^3/16 f3 (fk the k-th derivative;
    the terms left out are below ~(rho/a)^4 of the gradient).
    """
    if rho < AXIS_SERIES_RHO * a:
        s = a * a + z * z
        f_scale = math.pi * c * a * a / (s * s * math.sqrt(s))         # pi c a^2 s^-5/2
        f1 = -3.0 * f_scale * z
        f2 = 3.0 * f_scale * (4.0 * z * z - a * a) / s
        f3 = 15.0 * f_scale * z * (3.0 * a * a - 4.0 * z * z) / (s * s)
        f4 = 45.0 * f_scale * (a ** 4 - 12.0 * a * a * z * z + 8.0 * z ** 4) / (s * s * s)
        rho2 = rho * rho
        bz_rho = -0.5 * rho * f2 + rho * rho2 / 16.0 * f4
        bz_z = f1 - 0.25 * rho2 * f3
        br_over_rho = -0.5 * f1 + rho2 / 16.0 * f3
        br_rho = -0.5 * f1 + 3.0 * rho2 / 16.0 * f3
        return bz_rho, bz_z, br_rho, bz_rho, br_over_rho   # curl-free: dBrho/dz = dBz/drho
    alpha2 = (a - rho) ** 2 + z * z
    beta2 = (a + rho) ** 2 + z * z
    beta = math.sqrt(beta2)
    dk = (e_int - (1.0 - m) * k_int) / (2.0 * m * (1.0 - m))
    de = (e_int - k_int) / (2.0 * m)
    m_rho = 4.0 * a / beta2 * (1.0 - 2.0 * rho * (a + rho) / beta2)
    m_z = -2.0 * z * m / beta2
    alpha2_rho = -2.0 * (a - rho)
    alpha2_z = 2.0 * z
    beta_rho = (a + rho) / beta
    beta_z = z / beta
    u = (a * a - rho * rho - z * z) / alpha2
    v = (a * a + rho * rho + z * z) / alpha2
    u_rho = (-2.0 * rho - u * alpha2_rho) / alpha2
    u_z = (-2.0 * z - u * alpha2_z) / alpha2
    v_rho = (2.0 * rho - v * alpha2_rho) / alpha2
    v_z = (2.0 * z - v * alpha2_z) / alpha2
    s_z = k_int + u * e_int                      # Bz = c s_z / beta
    s_r = -k_int + v * e_int                     # Brho = c z s_r / (rho beta)
    s_z_rho = (dk + u * de) * m_rho + u_rho * e_int
    s_z_z = (dk + u * de) * m_z + u_z * e_int
    s_r_rho = (-dk + v * de) * m_rho + v_rho * e_int
    s_r_z = (-dk + v * de) * m_z + v_z * e_int
    bz_rho = c / beta * (s_z_rho - s_z * beta_rho / beta)
    bz_z = c / beta * (s_z_z - s_z * beta_z / beta)
    g = c / (rho * beta)
    br_over_rho = g * z * s_r / rho
    br_rho = g * z * (s_r_rho - s_r * (1.0 / rho + beta_rho / beta))
    br_z = g * (s_r + z * s_r_z - z * s_r * beta_z / beta)
    return bz_rho, bz_z, br_rho, br_z, br_over_rho


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
        return _field_and_gradient(self._centres, self._axes, self._radii, self._turns, self._owner, self.n, p)

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
    _, gradient = _field_and_gradient(centres, axes, radii, turns, owner, 1, np.array([0.01, 0.0, 0.0]))
    _field_and_gradient(centres, axes, radii, turns, owner, 1, np.array([0.0, 0.0, 0.01]))   # the axis branch
    _coil_fields(centres, axes, radii, turns, owner, 1, np.zeros((1, 3)))
    _force_rows(gradient, np.array([0.0, 0.0, 1.0]))


register_warm_up(__name__)
