"""Physics of the simulated robot: a permanent-magnet rod in a viscous fluid inside a vessel.

Magnet: a uniformly magnetised NdFeB cylinder, point dipole ``m = Br V / mu0`` along its axis
(tail -> head; the head is the north pole). Torque ``m x B``, force ``grad(m . B)``.

Motion is overdamped (at these sizes and speeds inertia settles in well under a millisecond), so
velocity = drag^-1 (force) + flow, and the axis turns toward the field at the rate set by the
rotational drag. Drag coefficients (SI: N s/m, N m s):

* Free slender cylinder, aspect ratio p = L/D (Tirado & Garcia de la Torre 1979/1980):
  axial      xi_par  = 2 pi mu L / (ln p - 0.207 + 0.980/p - 0.133/p^2)
  lateral    xi_perp = 4 pi mu L / (ln p + 0.839 + 0.185/p + 0.233/p^2)
  rotation   xi_rot  = pi mu L^3 / (3 (ln p - 0.662 + 0.917/p - 0.050/p^2))
* Confinement: a rod of radius a in a long closed tube of radius R must push the fluid it displaces
  back through the annular gap. The axial drag then follows from annular Stokes flow (Couette +
  Poiseuille with zero net flux): u(r) = G r^2/(4 mu) + A ln r + B, u(a) = U, u(R) = 0,
  integral of u over the annulus = -U pi a^2; drag = -(2 pi a mu u'(a) - pi a^2 G) L / U.
  For a 2 mm rod in a 5 mm lumen that is 8.3 times the free value. The same ratio is applied to the
  lateral and rotational drag (an approximation: the wall effect on those is of the same order).
  The larger of the confined and free values is used (the annular model ignores the rod's ends and
  falls below the free value in tubes wider than ~10 rod radii).

Fluid defaults: blood-like, viscosity 3.5 mPa s, density 1060 kg/m^3. Magnet: NdFeB N35-like
Br = 1.2 T, density 7500 kg/m^3.

Not modelled: inertia, wall friction and contact torques, the wall's effect on how far the rod can
turn in a narrow vessel, demagnetisation, magnetic interaction with other robots.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
MU0 = 4e-7 * math.pi
G_ACCEL = 9.80665


@dataclass(frozen=True)
class Fluid:
    """A Newtonian fluid (defaults: blood at body temperature, treated as Newtonian)."""

    viscosity_pa_s: float = 3.5e-3
    density_kg_m3: float = 1060.0


@dataclass(frozen=True)
class MagnetRobot:
    """A cylindrical robot with a permanent magnet; geometry in mm (Table 1 robot #1 by default)."""

    length_mm: float = 10.0
    diameter_mm: float = 2.0
    remanence_t: float = 1.2
    magnet_volume_mm3: float | None = None  # default: the whole body is magnet
    density_kg_m3: float = 7500.0

    def __post_init__(self) -> None:
        if self.length_mm <= 0.0 or self.diameter_mm <= 0.0:
            raise ValueError("robot length_mm and diameter_mm must be positive")
        if self.magnet_volume_mm3 is not None and not 0.0 < self.magnet_volume_mm3 <= self.volume_mm3 + 1e-9:
            raise ValueError("magnet_volume_mm3 must be positive and at most the body volume")

    @property
    def volume_mm3(self) -> float:
        return math.pi * (self.diameter_mm / 2.0) ** 2 * self.length_mm

    @property
    def moment_am2(self) -> float:
        """Dipole moment magnitude |m| = Br V / mu0 (A m^2)."""
        volume = (self.magnet_volume_mm3 if self.magnet_volume_mm3 is not None else self.volume_mm3) * 1e-9
        return self.remanence_t * volume / MU0

    def net_weight_n(self, fluid: Fluid) -> float:
        """Weight minus buoyancy (N), positive when it sinks."""
        return (self.density_kg_m3 - fluid.density_kg_m3) * self.volume_mm3 * 1e-9 * G_ACCEL


@dataclass(frozen=True)
class Drag:
    """Drag coefficients: axial and lateral (N s/m), rotational (N m s), and the confinement factor used."""

    axial: float
    lateral: float
    rotational: float
    confinement: float


def free_slender_drag(length_m: float, diameter_m: float, viscosity: float) -> tuple[float, float, float]:
    """Axial, lateral and rotational drag of a free cylinder (Tirado & Garcia de la Torre)."""
    p = max(length_m / diameter_m, 2.0)  # the fits hold for p >= 2; shorter robots use p = 2
    lnp = math.log(p)
    axial = 2.0 * math.pi * viscosity * length_m / (lnp - 0.207 + 0.980 / p - 0.133 / p**2)
    lateral = 4.0 * math.pi * viscosity * length_m / (lnp + 0.839 + 0.185 / p + 0.233 / p**2)
    rotational = math.pi * viscosity * length_m**3 / (3.0 * (lnp - 0.662 + 0.917 / p - 0.050 / p**2))
    return axial, lateral, rotational


def confined_axial_drag(rod_radius_m: float, tube_radius_m: float, length_m: float, viscosity: float) -> float:
    """Axial drag of a long rod moving along a closed tube (annular Stokes flow, zero net flux)."""
    a, r_t, mu = rod_radius_m, tube_radius_m, viscosity
    if r_t <= a:
        raise ValueError("the vessel lumen must be wider than the robot")
    # Flux of each basis function over the annulus: r^2/(4 mu), ln r, 1.
    flux_r2 = math.pi * (r_t**4 - a**4) / (8.0 * mu)
    flux_ln = math.pi * (r_t**2 * (2.0 * math.log(r_t) - 1.0) - a**2 * (2.0 * math.log(a) - 1.0)) / 2.0
    flux_1 = math.pi * (r_t**2 - a**2)
    matrix = np.array([[a**2 / (4.0 * mu), math.log(a), 1.0],
                       [r_t**2 / (4.0 * mu), math.log(r_t), 1.0],
                       [flux_r2, flux_ln, flux_1]])
    g, coef_a, _ = np.linalg.solve(matrix, [1.0, 0.0, -math.pi * a**2])
    shear_gradient = g * a / (2.0 * mu) + coef_a / a
    force = 2.0 * math.pi * a * length_m * mu * shear_gradient - math.pi * a**2 * length_m * g
    return float(-force)


def drag_for(robot: MagnetRobot, fluid: Fluid, lumen_radius_mm: float | None) -> Drag:
    """Drag of ``robot`` in ``fluid``, confined by a lumen of the given radius (None: free)."""
    length, diameter = robot.length_mm * 1e-3, robot.diameter_mm * 1e-3
    axial, lateral, rotational = free_slender_drag(length, diameter, fluid.viscosity_pa_s)
    factor = 1.0
    if lumen_radius_mm is not None:
        confined = confined_axial_drag(diameter / 2.0, lumen_radius_mm * 1e-3, length, fluid.viscosity_pa_s)
        factor = max(confined / axial, 1.0)
    return Drag(float(axial * factor), float(lateral * factor), float(rotational * factor), float(factor))


def align(direction: FloatArray, field_t: FloatArray, moment_am2: float, rotational_drag: float,
          dt_s: float) -> FloatArray:
    """Turn the axis toward the field for ``dt_s``, exactly, for a field constant over the step.

    Overdamped: d(theta)/dt = -(m |B| / xi_rot) sin(theta), whose solution is
    tan(theta/2) = tan(theta0/2) exp(-k t). Exact for any step, so a stiff alignment (time constants
    of microseconds in strong fields) costs nothing and never overshoots.
    """
    b = float(np.linalg.norm(field_t))
    if b == 0.0 or dt_s <= 0.0:
        return direction
    b_hat = field_t / b
    cos0 = float(np.clip(np.dot(direction, b_hat), -1.0, 1.0))
    theta0 = math.acos(cos0)
    if theta0 < 1e-12:
        return direction
    perp = b_hat - cos0 * direction
    norm = float(np.linalg.norm(perp))
    if norm < 1e-12:
        # Exactly anti-aligned: an unstable equilibrium; any disturbance starts the turn.
        perp = np.cross(direction, [1.0, 0.0, 0.0])
        if np.linalg.norm(perp) < 1e-6:
            perp = np.cross(direction, [0.0, 1.0, 0.0])
        norm = float(np.linalg.norm(perp))
        theta0 = min(theta0, math.pi - 1e-9)
    e_perp = perp / norm
    rate = moment_am2 * b / rotational_drag
    theta = 2.0 * math.atan(math.tan(theta0 / 2.0) * math.exp(-min(rate * dt_s, 700.0)))
    turned = theta0 - theta
    new = direction * math.cos(turned) + e_perp * math.sin(turned)
    return new / np.linalg.norm(new)


def velocity_m_s(direction: FloatArray, force_n: FloatArray, drag: Drag) -> FloatArray:
    """Overdamped anisotropic velocity: axial and lateral force components over their drags."""
    axial = float(np.dot(force_n, direction))
    lateral = force_n - axial * direction
    return axial / drag.axial * direction + lateral / drag.lateral
