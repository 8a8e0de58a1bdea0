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
