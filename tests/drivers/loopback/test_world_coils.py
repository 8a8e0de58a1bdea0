"""The world's true coils (magpylib) against textbook formulas, and the vessel phantom's geometry."""
from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from appliance.config_io import config_path
from drivers.loopback.coils import CoilGeometry, TrueCoils, perturb
from drivers.loopback.vessel import Vessel

MU0 = 4e-7 * math.pi


def _coil(name: str, z_mm: float, axis_z: float, radius_mm: float, turns: int) -> CoilGeometry:
    return CoilGeometry(name, (0.0, 0.0, z_mm), (0.0, 0.0, axis_z), radius_mm, turns)


def test_helmholtz_pair_field_at_centre_matches_formula() -> None:
    radius, turns, current = 150.0, 200, 3.0
    pair = TrueCoils([_coil("a", -radius / 2, 1.0, radius, turns), _coil("b", radius / 2, 1.0, radius, turns)])
    field = pair.field_at([0, 0, 0], [current, current])
    expected = (4.0 / 5.0) ** 1.5 * MU0 * turns * current / (radius * 1e-3)
    assert field[2] == pytest.approx(expected, rel=1e-9)
    assert np.hypot(field[0], field[1]) < 1e-12
    # Helmholtz: uniform to 4th order; 10 mm off-centre along the axis the field changes < 1e-4.
    assert pair.field_at([0, 0, 10], [current, current])[2] == pytest.approx(expected, rel=1e-4)


def test_maxwell_pair_gradient_matches_formula() -> None:
    radius, turns, current = 120.0, 300, 2.0
    half = math.sqrt(3.0) / 2.0 * radius
    # Opposite windings: same positive current, opposite axes.
    pair = TrueCoils([_coil("a", -half, 1.0, radius, turns), _coil("b", half, -1.0, radius, turns)])
    field, grad_per_amp = pair.field_and_gradient_per_amp([0, 0, 0])
    grad = grad_per_amp @ np.array([current, current])
    r_m, a_m = radius * 1e-3, half * 1e-3
    expected = -3.0 * MU0 * turns * current * r_m**2 * a_m / (r_m**2 + a_m**2) ** 2.5   # dBz/dz at centre
    assert abs(expected) / (MU0 * turns * current / r_m**2) == pytest.approx(0.6413, abs=1e-4)
    assert grad[2, 2] == pytest.approx(expected, rel=1e-6)
    assert grad[0, 0] == pytest.approx(-expected / 2, rel=1e-6)
    assert grad[1, 1] == pytest.approx(-expected / 2, rel=1e-6)
    assert np.linalg.norm(field @ np.array([current, current])) < 1e-12
    off_diagonal = grad - np.diag(np.diag(grad))
    assert np.abs(off_diagonal).max() < 1e-6 * abs(expected)


def test_field_is_linear_in_currents_and_curl_and_divergence_free() -> None:
    coils = TrueCoils.from_config(yaml.safe_load(config_path("coils.yaml").read_text()))
    rng = np.random.default_rng(3)
    point = [12.0, -7.0, 4.0]
    i1, i2 = rng.normal(size=coils.n), rng.normal(size=coils.n)
    total = coils.field_at(point, 2.0 * i1 - 0.5 * i2)
    assert np.allclose(total, 2.0 * coils.field_at(point, i1) - 0.5 * coils.field_at(point, i2), rtol=1e-12, atol=1e-18)
    _, grad_per_amp = coils.field_and_gradient_per_amp(point)
    grad = grad_per_amp @ i1
    scale = np.abs(grad).max()
    assert abs(np.trace(grad)) < 1e-6 * scale          # div B = 0
    assert np.abs(grad - grad.T).max() < 1e-6 * scale  # curl B = 0 away from currents
    with pytest.raises(ValueError, match="coil currents"):
        coils.field_at(point, np.zeros(coils.n + 1))


def test_perturbation_changes_gain_exactly_and_geometry_by_seed() -> None:
    base = [_coil("a", -50.0, 1.0, 80.0, 100)]
    gained = TrueCoils(perturb(base, np.random.default_rng(0), gains=[1.01]))
    assert gained.field_at([0, 0, 0], [1.0]) == pytest.approx(1.01 * TrueCoils(base).field_at([0, 0, 0], [1.0]))
    moved_a = perturb(base, np.random.default_rng(5), position_sd_mm=0.5, axis_sd_deg=0.2)
    moved_b = perturb(base, np.random.default_rng(5), position_sd_mm=0.5, axis_sd_deg=0.2)
    assert moved_a == moved_b
    shift = np.subtract(moved_a[0].centre_mm, base[0].centre_mm)
    assert 0.0 < np.linalg.norm(shift) < 3.0
    tilt = math.degrees(math.acos(min(1.0, float(np.dot(moved_a[0].axis, base[0].axis)))))
    assert 0.0 < tilt < 1.5


def test_vessel_nearest_constrain_and_flow_on_a_straight_tube() -> None:
    vessel = Vessel([[0, 0, 0], [50, 0, 0], [100, 0, 0]], radius_mm=2.0, flow_mean_mm_s=3.0)
    assert vessel.length_mm == pytest.approx(100.0)
    near = vessel.nearest([30.0, 1.0, -1.0])
    assert near.s_mm == pytest.approx(30.0) and near.distance_mm == pytest.approx(math.sqrt(2.0))
    inside, normal = vessel.constrain([30.0, 0.5, 0.0], clearance_mm=1.0)
    assert normal is None and np.allclose(inside, [30.0, 0.5, 0.0])
    projected, normal = vessel.constrain([30.0, 0.0, 3.0], clearance_mm=1.0)
    assert np.allclose(projected, [30.0, 0.0, 1.0]) and np.allclose(normal, [0, 0, 1])
    capped, normal = vessel.constrain([104.0, 0.0, 0.0], clearance_mm=1.0)
    assert np.allclose(capped, [100.0, 0.0, 0.0]) and np.allclose(normal, [1, 0, 0])
    assert np.allclose(vessel.flow_velocity_mm_s([10, 0, 0]), [6.0, 0, 0])        # Poiseuille: 2 x mean
    assert np.allclose(vessel.flow_velocity_mm_s([10, 1.0, 0]), [4.5, 0, 0])
    with pytest.raises(ValueError, match="radius_mm"):
        Vessel([[0, 0, 0], [1, 0, 0]], radius_mm=0.0)


def test_default_vessel_is_smooth_and_inside_the_phantom_area() -> None:
    data = yaml.safe_load(config_path("vessel.yaml").read_text())
    vessel = Vessel.from_config(data["vessel"])
    points = vessel.sample(1.0)
    assert np.ptp(points[:, 0]) <= 150.0 and np.ptp(points[:, 1]) <= 100.0
    tangents = np.diff(vessel.points, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1)[:, None]
    curvature = np.linalg.norm(np.diff(tangents, axis=0), axis=1) / np.diff(vessel.s)[:-1]
    assert 1.0 / curvature.max() > 15.0   # bends gentle enough for a 10 mm robot in a 5 mm lumen
    for s in (0.0, 40.0, vessel.length_mm):
        assert vessel.nearest(vessel.point_at(s)).distance_mm < 1e-6
