"""Planar method: an asymmetric circle grid of steel balls rendered in several poses calibrates both views."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from appliance.errors import CalibrationError
from appliance.registration import register_points
from appliance.xray_calibration.grid import calibrate_grids, detect_grid, grid_points, grid_symmetries
from drivers.loopback.xray_render import BiplaneRenderer, ImagingSettings, TrueView

PATTERN, COLS, ROWS, PITCH_MM = "circles", 7, 9, 10.0


def _grid_pose(k: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Grid -> world rotation and origin: facing both sources (normal between them), tilted differently each time."""
    normal = np.array([-1.0, -1.0, 0.0]) / np.sqrt(2)
    x_axis = np.array([1.0, -1.0, 0.0]) / np.sqrt(2)
    base = np.column_stack([x_axis, np.cross(normal, x_axis), normal])
    axis = rng.normal(size=3)
    tilt, _ = cv2.Rodrigues(axis / np.linalg.norm(axis) * np.radians(10 + 4 * k))
    R = tilt @ base
    centre = R @ -grid_points(PATTERN, COLS, ROWS, PITCH_MM).mean(axis=0) + rng.uniform(-5, 5, 3)
    return R, centre


@pytest.fixture(scope="module")
def grid_session(true_views: dict[str, TrueView]) -> tuple[list[dict[str, np.ndarray | None]], list, np.ndarray]:
    rng = np.random.default_rng(8)
    obj = grid_points(PATTERN, COLS, ROWS, PITCH_MM)
    observations, poses = [], []
    for k in range(5):
        R, centre = _grid_pose(k, rng)
        world = obj @ R.T + centre
        images = BiplaneRenderer(true_views, None, beads=(world, 1.0, 2.0), settings=ImagingSettings(), seed=k
                                 ).render(None).images
        observations.append({name: detect_grid(images[name], PATTERN, COLS, ROWS) for name in ("p", "q")})
        poses.append((R, centre))
    return observations, poses, obj


def test_grid_is_found_to_sub_pixel_up_to_its_symmetry(grid_session, true_views: dict[str, TrueView]) -> None:
    observations, poses, obj = grid_session
    symmetries = grid_symmetries(obj)
    assert len(symmetries) == 4  # a 7x9 grid: identity, two mirrors, half turn
    for k, (R, centre) in enumerate(poses):
        for name in ("p", "q"):
            uv = observations[k][name]
            if uv is None:
                continue
            truth = true_views[name].project(obj @ R.T + centre)
            error = min(np.max(np.linalg.norm(uv - truth[perm], axis=1)) for perm in symmetries)
            assert error < 0.2  # px
    assert sum(o[n] is not None for o in observations for n in ("p", "q")) >= 8


def test_planar_method_recovers_the_geometry(grid_session, true_views: dict[str, TrueView]) -> None:
    observations, poses, obj = grid_session
    result = calibrate_grids(observations, obj, {n: v.image_size for n, v in true_views.items()})
    # The result's world is grid pose 0 as view p numbered it: our numbering moved by one of the grid's
    # symmetries (a rigid motion of the plate). Map the truth into each candidate frame; one must fit.
    R0, c0 = poses[0]
    frames = []
    for perm in grid_symmetries(obj):
        motion = register_points(obj, obj[perm]).transform  # plate frame -> renumbered plate frame
        frames.append((R0 @ motion.R.T, c0 - R0 @ motion.R.T @ motion.t))
    p_view = result.calibration.views["p"]
    Rw, cw = min(frames, key=lambda f: np.linalg.norm(cv2.Rodrigues(p_view.R @ (true_views["p"].R @ f[0]).T)[0]))
    for name, view in result.calibration.views.items():
        truth = true_views[name]
        np.testing.assert_allclose(np.diag(view.K)[:2], np.diag(truth.K)[:2], rtol=0.01)
        true_R = truth.R @ Rw
        true_source = Rw.T @ (truth.source_mm - cw)
        assert np.degrees(np.linalg.norm(cv2.Rodrigues(view.R @ true_R.T)[0])) < 0.2
        assert np.linalg.norm(view.source_mm - true_source) < 2.0
        assert result.rms_px[name] < 0.3
    assert result.common_poses >= 3


def test_too_few_poses(grid_session, true_views: dict[str, TrueView]) -> None:
    observations, _, obj = grid_session
    with pytest.raises(CalibrationError, match="saw the grid in 1 poses"):
        calibrate_grids(observations[:1], obj, {n: v.image_size for n, v in true_views.items()})


def test_grid_points_layouts() -> None:
    assert grid_points("checkerboard", 3, 2, 10.0)[-1].tolist() == [20.0, 10.0, 0.0]
    assert grid_points("acircles", 2, 2, 10.0)[3].tolist() == [15.0, 5.0, 0.0]
    with pytest.raises(CalibrationError, match="unknown grid pattern"):
        grid_points("hexagons", 3, 3, 1.0)
