"""The configured actuation model: validated coils.yaml, and fields equal to the world's magpylib coils."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from appliance.config_io import config_path
from appliance.control import ActuationModel, load_coils
from appliance.errors import ConfigError
from drivers.loopback.coils import TrueCoils


@pytest.fixture(scope="module")
def model() -> ActuationModel:
    return ActuationModel(load_coils())


@pytest.fixture(scope="module")
def true_coils() -> TrueCoils:
    return TrueCoils.from_config(yaml.safe_load(config_path("coils.yaml").read_text()))


@pytest.mark.parametrize("point", [[0, 0, 0], [45, -20, 8], [-55, 25, -10], [0, 0, 120]])
def test_elliptic_integral_model_equals_magpylib(model: ActuationModel, true_coils: TrueCoils, point: list[float]) -> None:
    field = model.field_per_amp(point)
    true_field, true_grad = true_coils.field_and_gradient_per_amp(point)
    assert field.shape == (3, 8)
    assert np.abs(field - true_field).max() < 1e-8 * np.abs(true_field).max()
    grad = model.gradient_per_amp(point)
    assert grad.shape == (9, 8)
    assert np.abs(grad - true_grad.reshape(9, 8)).max() < 1e-6 * np.abs(true_grad).max()


def test_gradient_is_symmetric_traceless_and_force_is_grad_m_dot_b(model: ActuationModel) -> None:
    point = np.array([20.0, 10.0, -5.0])
    grad = model.gradient_per_amp(point).reshape(3, 3, 8)
    for k in range(8):
        g = grad[:, :, k]
        assert abs(np.trace(g)) < 1e-6 * np.abs(g).max()
        assert np.abs(g - g.T).max() < 1e-6 * np.abs(g).max()
    moment = np.array([0.01, -0.02, 0.015])
    currents = np.linspace(-3, 4, 8)
    # Central difference of the energy-like m . B(p) must equal the model's force.
    h = 1e-3
    numeric = [(moment @ model.field(point + h * e, currents) - moment @ model.field(point - h * e, currents)) / (2 * h * 1e-3)
               for e in np.eye(3)]
    assert np.allclose(model.force(point, moment, currents), numeric, rtol=1e-5)


def test_centre_has_full_eight_degrees_of_freedom(model: ActuationModel) -> None:
    matrix = np.vstack([model.field_per_amp([0, 0, 0]), model.gradient_per_amp([0, 0, 0])[[0, 1, 2, 4, 5]] * 0.1])
    singular = np.linalg.svd(matrix, compute_uv=False)
    assert singular[0] / singular[-1] < 5.0


def _write(tmp_path: Path, mutate: object) -> Path:
    data = yaml.safe_load(config_path("coils.yaml").read_text())
    mutate(data)  # type: ignore[operator]
    path = tmp_path / "coils.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize(("mutate", "message"), [
    (lambda d: d["coils"][2].update(max_current_a=-1), "coils[2].max_current_a"),
    (lambda d: d["coils"][5].update(axis=[0, 0, 0]), "coils[5].axis"),
    (lambda d: d["coils"][1].update(colour="red"), "coils[1].colour"),
    (lambda d: d.update(schema_version=7), "schema_version"),
    (lambda d: d["coils"][3].update(name=d["coils"][0]["name"]), "used twice"),
    (lambda d: d["limits"].pop("max_power_w"), "limits.max_power_w"),
])
def test_bad_coils_file_names_the_key(tmp_path: Path, mutate: object, message: str) -> None:
    path = _write(tmp_path, mutate)
    with pytest.raises(ConfigError) as info:
        load_coils(path)
    assert str(path) in str(info.value) and message in str(info.value)


def test_compiled_fields_equal_the_vectorised_scipy_reference(model: ActuationModel) -> None:
    """The kernel (AGM elliptic integrals, loop by loop) against loop_field (scipy's ellipk/ellipe),
    in the workspace (50 mm around the centre), on and near coil axes: equal to rounding, so the 20 um
    gradient difference is too."""
    from scipy.special import ellipe, ellipk

    from appliance.control.actuation import _elliptic_k_e, loop_field

    m = np.concatenate([np.linspace(0.0, 1.0 - 1e-15, 4001), [0.5, 0.9685152576288143]])
    k_e = np.array([_elliptic_k_e(v) for v in m])
    assert np.abs(k_e[:, 0] / ellipk(m) - 1.0).max() < 1e-14
    assert np.abs(k_e[:, 1] / ellipe(m) - 1.0).max() < 1e-14
    workspace = np.vstack([np.random.default_rng(3).uniform(-0.05, 0.05, (40, 3)), np.zeros((1, 3)),
                           [[0.0, 0.0, 0.03]]])
    # 20 um off an axis the radial term is a difference of nearly equal K and E terms (both forms
    # lose ~7 digits of it there; it is ~1e-4 of the field).
    near_axis = np.array([[2e-5, 0.0, 0.0], [0.0, -2e-5, 0.0]])
    for points, tolerance in ((workspace, 1e-13), (near_axis, 1e-10)):
        loops = loop_field(model._centres, model._axes, model._radii, model._turns, points)
        reference = np.einsum("cl,lpk->pkc", model._gather, loops)
        assert np.abs(model._per_amp(points) - reference).max() < tolerance * np.abs(reference).max()
    field, gradient = model.field_and_gradient_per_amp([12.0, -7.0, 4.0])
    assert np.array_equal(field, model.field_per_amp([12.0, -7.0, 4.0]))
    assert np.array_equal(gradient, model.gradient_per_amp([12.0, -7.0, 4.0]))


def _richardson_gradient(model: ActuationModel, point_m: np.ndarray, step_m: float = 10e-6) -> np.ndarray:
    """9 x n: central differences of the compiled field at steps h and 2h, combined (4 g_h - g_2h) / 3 so
    the h^2 truncation cancels (what is left is ~1e-11 of the gradient in the workspace)."""
    from appliance.control.actuation import _coil_fields

    def central(h: float) -> np.ndarray:
        offsets = np.array([s * h * e for e in np.eye(3) for s in (1.0, -1.0)])
        fields = _coil_fields(*model.loops[:4], model.loops[4], model.n, point_m + offsets)
        return np.vstack([(fields[2 * j, i] - fields[2 * j + 1, i]) / (2.0 * h) for i in range(3) for j in range(3)])

    return (4.0 * central(step_m) - central(2.0 * step_m)) / 3.0


def test_analytic_gradient_equals_a_fine_difference_of_the_field(model: ActuationModel) -> None:
    """The closed-form gradient against the field's Richardson-extrapolated central difference, off the
    coils' axes in the workspace: 1e-9 of the largest entry (the 20 um difference used before was 1.3e-8
    off; a wrong sign or a missing term is off by tens of percent)."""
    points = np.vstack([np.random.default_rng(5).uniform(-0.06, 0.06, (25, 3)), [[0.03, 0.0, 0.0], [0.0, 0.02, 0.04]]])
    for point in points:
        field, gradient = model.field_and_gradient_per_amp(point * 1e3)
        assert np.array_equal(field, model.field_per_amp(point * 1e3))
        reference = _richardson_gradient(model, point)
        assert np.abs(gradient - reference).max() < 1e-9 * np.abs(reference).max()


def test_analytic_gradient_on_and_near_a_loop_axis() -> None:
    """One loop (radius 90 mm): on its axis the gradient is f'(z) (n n^T - (I - n n^T) / 2) with f the
    textbook axial field; near the axis (series branch) and off it (closed form) the two branches agree
    where they meet, and the gradient stays symmetric and traceless (curl- and divergence-free)."""
    from appliance.control.actuation import AXIS_SERIES_RHO, MU0, _field_and_gradient

    axis = np.array([0.6, 0.0, 0.8])
    across = np.array([0.8, 0.0, -0.6])
    loops = (np.array([[0.01, -0.02, 0.03]]), axis[None, :], np.array([0.09]), np.array([500.0]),
             np.zeros(1, dtype=np.int64))
    a = 0.09
    for z in (0.0, 0.04, -0.15, 0.22):
        _, on_axis = _field_and_gradient(*loops, 1, loops[0][0] + z * axis)
        s = a * a + z * z
        f1 = -3.0 * MU0 * 500.0 * a * a * z / (2.0 * s**2.5)    # d/dz of mu0 N I a^2 / (2 s^1.5)
        expected = f1 * (1.5 * np.outer(axis, axis) - 0.5 * np.eye(3))
        assert np.abs(on_axis[:, 0].reshape(3, 3) - expected).max() < 1e-12 * np.abs(expected).max() + 1e-18
        edge = AXIS_SERIES_RHO * a
        below = _field_and_gradient(*loops, 1, loops[0][0] + z * axis + edge * (1 - 1e-11) * across)[1][:, 0]
        above = _field_and_gradient(*loops, 1, loops[0][0] + z * axis + edge * (1 + 1e-11) * across)[1][:, 0]
        assert np.abs(below - above).max() < 1e-9 * np.abs(above).max()
        for rho in (1e-9, 1e-6, 1e-4, 0.02, 0.08):
            g = _field_and_gradient(*loops, 1, loops[0][0] + z * axis + rho * across)[1][:, 0].reshape(3, 3)
            assert abs(np.trace(g)) < 1e-12 * np.abs(g).max()
            assert np.abs(g - g.T).max() < 1e-11 * np.abs(g).max()


def test_analytic_gradient_equals_magpylib_difference(true_coils: TrueCoils, model: ActuationModel) -> None:
    """Against the simulation's own coils (magpylib, unperturbed), differenced at 10 and 20 um and
    extrapolated: the configured model's gradient is the world's to 1e-9 of its largest entry."""
    for point_mm in ([45.0, -20.0, 8.0], [-55.0, 25.0, -10.0], [12.0, 30.0, 40.0]):
        p = np.asarray(point_mm) * 1e-3

        def central(h: float) -> np.ndarray:
            fields = [true_coils._per_amp_m(np.array([p + s * h * e for s in (1.0, -1.0)])) for e in np.eye(3)]
            return np.vstack([(f[0, i] - f[1, i]) / (2.0 * h) for i in range(3) for f in fields])

        reference = (4.0 * central(10e-6) - central(20e-6)) / 3.0
        gradient = model.gradient_per_amp(point_mm)
        assert np.abs(gradient - reference).max() < 1e-9 * np.abs(reference).max()
