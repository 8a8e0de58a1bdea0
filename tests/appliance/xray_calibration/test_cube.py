"""Calibration from a rendered bead phantom recovers the simulated world's TRUE geometry.

Margins are looser than the figures measured by benchmarks/calibration_sim.py, which prints them.
"""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from appliance.errors import CalibrationError
from appliance.geometry import Calibration, triangulate
from appliance.xray_calibration.cube import CubeOptions, CubeResult, calibrate_cube, to_calibration
from appliance.xray_calibration.phantom import Phantom, parse_phantom
from drivers.loopback.xray_render import TrueView


def _rotation_error_deg(R: np.ndarray, R_true: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(cv2.Rodrigues(R @ R_true.T)[0])))


@pytest.fixture(scope="module")
def from_initial(cube_images: dict[str, np.ndarray], cube: Phantom, nominal_calibration: Calibration) -> CubeResult:
    return calibrate_cube(cube_images, cube, initial=nominal_calibration)


def _assert_recovers_truth(result: CubeResult, true_views: dict[str, TrueView]) -> None:
    for name, fit in result.fits.items():
        truth = true_views[name]
        np.testing.assert_allclose(np.diag(fit.K)[:2], np.diag(truth.K)[:2], rtol=0.005)  # focal lengths 0.5 %
        assert _rotation_error_deg(fit.R, truth.R) < 0.1
        assert np.linalg.norm(-fit.R.T @ fit.t - truth.source_mm) < 0.5  # source position, mm
        assert np.linalg.norm(fit.t - truth.t) < 1.0  # t also carries the rotation error times ~500 mm
        assert fit.rms_px < 0.3
        assert len(fit.bead_rows) >= 40


def test_from_a_rough_initial_geometry(from_initial: CubeResult, true_views: dict[str, TrueView]) -> None:
    _assert_recovers_truth(from_initial, true_views)


def test_triangulation_with_the_recovered_calibration(from_initial: CubeResult, cube: Phantom,
                                                      true_views: dict[str, TrueView]) -> None:
    rows, errors = from_initial.triangulation_errors_mm()
    assert len(rows) >= 40 and np.sqrt(np.mean(errors ** 2)) < 0.05
    # Points away from the beads too: project true points with the TRUE views, triangulate with ours.
    rng = np.random.default_rng(0)
    points = rng.uniform(-40, 40, (50, 3))
    views = from_initial.views()
    estimate = triangulate(views["p"], views["q"], true_views["p"].project(points), true_views["q"].project(points))
    assert np.max(np.linalg.norm(estimate - points, axis=1)) < 0.1


def test_from_marked_reference_beads(cube_images: dict[str, np.ndarray], cube: Phantom,
                                     true_views: dict[str, TrueView]) -> None:
    # The operator clicks the reference beads to within a pixel or so, as in XMALab.
    rng = np.random.default_rng(1)
    marked = {}
    for name in ("p", "q"):
        ids = list(cube.references)
        uv = true_views[name].project(cube.points_mm[[cube.index(i) for i in ids]]) + rng.normal(0, 0.7, (len(ids), 2))
        marked[name] = {bead: tuple(point) for bead, point in zip(ids, uv)}
    result = calibrate_cube(cube_images, cube, references=marked)
    _assert_recovers_truth(result, true_views)


def test_joint_refinement_keeps_the_geometry(cube_images: dict[str, np.ndarray], cube: Phantom,
                                             nominal_calibration: Calibration, true_views: dict[str, TrueView]) -> None:
    result = calibrate_cube(cube_images, cube, initial=nominal_calibration,
                            options=CubeOptions(bead_tolerance_mm=0.02))
    _assert_recovers_truth(result, true_views)
    assert np.max(np.linalg.norm(result.refined_points_mm - cube.points_mm, axis=1)) < 0.1


def test_calibration_file_carries_rms_inliers_and_date(from_initial: CubeResult, tmp_path) -> None:
    calibration = to_calibration(from_initial)
    loaded = Calibration.load(calibration.save(tmp_path / "calibration.yaml"))
    meta = loaded.metadata
    for name in ("p", "q"):
        assert 0 < meta[f"reprojection_rms_px_{name}"] < 0.3
        assert meta[f"inliers_{name}"] == len(from_initial.fits[name].bead_rows)
    assert meta["date"].startswith("20") and "triangulation_rms_mm" in meta
    np.testing.assert_allclose(loaded.p.K, from_initial.fits["p"].K)


def test_images_without_beads(empty_images: dict[str, np.ndarray], cube: Phantom,
                              nominal_calibration: Calibration) -> None:
    with pytest.raises(CalibrationError, match="view p image: no beads found"):
        calibrate_cube(empty_images, cube, initial=nominal_calibration)


def test_wrong_phantom_file_cannot_be_matched(cube_images: dict[str, np.ndarray],
                                              nominal_calibration: Calibration) -> None:
    rng = np.random.default_rng(4)
    other = parse_phantom("\n".join(",".join(f"{c:.3f}" for c in row) for row in rng.uniform(-50, 50, (40, 3))))
    with pytest.raises(CalibrationError, match="view p: "):
        calibrate_cube(cube_images, other, initial=nominal_calibration)


def test_needs_initial_geometry_or_marked_beads(cube_images: dict[str, np.ndarray], cube: Phantom) -> None:
    with pytest.raises(CalibrationError, match="no initial geometry and no marked reference beads"):
        calibrate_cube(cube_images, cube)


def test_too_few_marked_beads(cube_images: dict[str, np.ndarray], cube: Phantom) -> None:
    with pytest.raises(CalibrationError, match="3 reference beads marked"):
        calibrate_cube(cube_images, cube, references={"p": {"1": (1.0, 2.0), "2": (3.0, 4.0), "3": (5.0, 9.0)}})


def test_detector_distortion_is_estimated(true_views: dict[str, TrueView], cube: Phantom,
                                          nominal_calibration: Calibration) -> None:
    from drivers.loopback.xray_render import BiplaneRenderer

    dist = np.array([0.6, 0.0, 0.0, 0.0, 0.0])  # ~5 px of pincushion at the image corners
    distorted = {n: TrueView(v.name, v.K, dist, v.R, v.t, v.image_size) for n, v in true_views.items()}
    images = BiplaneRenderer(distorted, None, beads=(cube.points_mm, 1.0, 2.0), seed=9).render(None).images
    plain = calibrate_cube(images, cube, initial=nominal_calibration)
    modelled = calibrate_cube(images, cube, initial=nominal_calibration, options=CubeOptions(distortion="k1"))
    assert min(f.rms_px for f in plain.fits.values()) > 0.2  # ignoring it shows in the residuals
    _assert_recovers_truth(modelled, distorted)
    for fit in modelled.fits.values():
        assert fit.dist[0] == pytest.approx(0.6, abs=0.1)


def test_pose_only_recalibration_with_known_intrinsics(cube_images: dict[str, np.ndarray], cube: Phantom,
                                                      true_views: dict[str, TrueView],
                                                      nominal_calibration: Calibration) -> None:
    # The nominal calibration has the true intrinsics (only the poses were perturbed): solvePnP path.
    result = calibrate_cube(cube_images, cube, initial=nominal_calibration, options=CubeOptions(fix_intrinsics=True))
    _assert_recovers_truth(result, true_views)
    for name, fit in result.fits.items():
        np.testing.assert_array_equal(fit.K, nominal_calibration.views[name].K)
    assert to_calibration(result).metadata["intrinsics"] == "kept from the initial calibration"


def test_recognition_with_the_recovered_calibration_matches_the_true_one(
        from_initial: CubeResult, true_views: dict[str, TrueView]) -> None:
    from appliance.geometry import View
    from appliance.recognition import PostureTracker
    from drivers.loopback.xray_render import BiplaneRenderer, RobotBody, RobotPose

    exact = Calibration.from_views(*(View(n, v.K, v.dist, v.R, v.t, v.image_size) for n, v in sorted(true_views.items())))
    recovered = to_calibration(from_initial)
    renderer = BiplaneRenderer(true_views, RobotBody(10.0, 2.0, 20.0, 1.0), seed=2)  # robot 1 of the paper
    pose = RobotPose(np.array([6.0, -9.0, 4.0]), np.array([0.3, 0.5, 0.81]) / np.linalg.norm([0.3, 0.5, 0.81]))
    pair = renderer.render(pose)
    with_truth = PostureTracker(exact).process(pair.images["p"], pair.images["q"])
    with_ours = PostureTracker(recovered).process(pair.images["p"], pair.images["q"])
    assert with_truth.ok and with_ours.ok, (with_truth.reason, with_ours.reason)
    assert np.linalg.norm(with_ours.centroid_mm - with_truth.centroid_mm) < 0.02
    assert np.linalg.norm(with_ours.centroid_mm - pose.centroid_mm) < 0.2
    assert np.degrees(np.arccos(min(1.0, float(with_ours.direction @ with_truth.direction)))) < 0.2


def test_four_marked_beads_with_a_focal_guess(cube_images: dict[str, np.ndarray], cube: Phantom,
                                             true_views: dict[str, TrueView]) -> None:
    ids = list(cube.references)[:4]
    marked = {name: {bead: tuple(true_views[name].project(cube.points_mm[cube.index(bead)][None])[0] + 0.5)
                     for bead in ids} for name in ("p", "q")}
    guess = 1.1 * true_views["p"].K[0, 0]  # 10 % off, as a nominal source-detector distance would be
    result = calibrate_cube(cube_images, cube, references=marked, options=CubeOptions(focal_guess_px=guess))
    _assert_recovers_truth(result, true_views)
