"""DLT, its decomposition and RANSAC: exact recovery, outlier rejection, degenerate layouts refused."""
from __future__ import annotations

import numpy as np
import pytest

from appliance.errors import CalibrationError
from appliance.xray_calibration.dlt import decompose, dlt, project, ransac_dlt
from appliance.xray_calibration.phantom import Phantom
from drivers.loopback.xray_render import TrueView


def _pixels(view: TrueView, points: np.ndarray) -> np.ndarray:
    return view.project(points)


def test_noiseless_dlt_recovers_K_R_t(true_views: dict[str, TrueView], cube: Phantom) -> None:
    for view in true_views.values():
        K, R, t = decompose(dlt(cube.points_mm, _pixels(view, cube.points_mm)))
        np.testing.assert_allclose(K, view.K, rtol=1e-7, atol=1e-5)
        np.testing.assert_allclose(R, view.R, atol=1e-9)
        np.testing.assert_allclose(t, view.t, atol=1e-6)


def test_ransac_finds_wrong_matches(true_views: dict[str, TrueView], cube: Phantom) -> None:
    view = true_views["q"]
    rng = np.random.default_rng(3)
    uv = _pixels(view, cube.points_mm) + rng.normal(0, 0.05, (len(cube), 2))
    wrong = rng.choice(len(cube), 8, replace=False)
    uv[wrong] = uv[np.roll(wrong, 1)]  # swapped correspondences, as a bad match would give
    result = ransac_dlt(cube.points_mm, uv, threshold_px=1.0)
    assert set(np.flatnonzero(~result.inliers)) == set(wrong)
    K, _, _ = decompose(result.P)
    np.testing.assert_allclose(np.diag(K)[:2], np.diag(view.K)[:2], rtol=2e-3)


@pytest.mark.parametrize("points, message", [
    (np.column_stack([np.arange(10.0), 2 * np.arange(10.0), np.zeros(10)]), "collinear"),
    (np.column_stack([np.arange(10.0) % 4, np.arange(10.0) // 4, np.zeros(10)]) * 10, "coplanar"),
    (np.eye(3)[:5 % 3].repeat(2, axis=0), "at least 6"),
])
def test_degenerate_layouts_are_refused(points: np.ndarray, message: str, true_views: dict[str, TrueView]) -> None:
    uv = _pixels(true_views["p"], points)
    with pytest.raises(CalibrationError, match=message):
        dlt(points, uv)


def test_mirror_image_is_named(true_views: dict[str, TrueView], cube: Phantom) -> None:
    view = true_views["p"]
    uv = _pixels(view, cube.points_mm)
    uv[:, 0] = view.image_size[0] - 1 - uv[:, 0]  # a detector read out right to left
    with pytest.raises(CalibrationError, match="mirror image"):
        decompose(dlt(cube.points_mm, uv))


def test_project_matches_the_view(true_views: dict[str, TrueView], cube: Phantom) -> None:
    view = true_views["p"]
    P = view.K @ np.hstack([view.R, view.t[:, None]])
    np.testing.assert_allclose(project(P, cube.points_mm), _pixels(view, cube.points_mm), atol=1e-9)
