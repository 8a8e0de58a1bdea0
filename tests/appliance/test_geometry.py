"""Tests of appliance.geometry / appliance.epipolar: each would fail if a convention or an equation were wrong."""
from __future__ import annotations

import copy
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.errors import CalibrationError
from appliance.geometry import (
    Calibration,
    View,
    epipolar_distance_px,
    epipolar_lines,
    epipolar_plane_angle_deg,
    fundamental_matrix,
    reprojection_error_px,
    triangulate,
)

SIZE = (640, 480)
DIST5 = (-0.12, 0.03, 0.0015, -0.002, -0.004)
DIST8 = (-0.1, 0.02, 0.001, 0.0005, 0.001, 0.01, -0.002, 0.0005)


def biplane(dist_p: Any = (0, 0, 0, 0, 0), dist_q: Any = (0, 0, 0, 0, 0), angle_deg: float = 90.0,
            focal_q: float = 1800.0) -> Calibration:
    """Two views of the isocentre from 500 mm, ``angle_deg`` apart about the vertical, sources slightly raised."""
    a = np.radians(angle_deg)
    p = View.look_at("p", (-500.0, 0.0, 20.0), (0, 0, 0), focal_px=1800.0, image_size=SIZE, dist=dist_p)
    q = View.look_at("q", (-500.0 * np.cos(a), -500.0 * np.sin(a), -10.0), (0, 0, 0), focal_px=focal_q,
                     image_size=SIZE, dist=dist_q, principal_point=(330.0, 231.0))
    return Calibration.from_views(p, q)


@pytest.fixture(scope="module")
def points() -> np.ndarray:
    return np.random.default_rng(7).uniform(-30.0, 30.0, (200, 3))


def image_filling_points(view: View, n: int = 300, seed: int = 5) -> np.ndarray:
    """World points whose ideal images cover the whole image, corners included: where distortion is largest."""
    rng = np.random.default_rng(seed)
    w, h = view.image_size
    uv = rng.uniform((0.0, 0.0), (w - 1.0, h - 1.0), (n, 2))
    uv[:4] = [(0, 0), (w - 1, 0), (0, h - 1), (w - 1, h - 1)]
    rays = np.column_stack([uv, np.ones(n)]) @ np.linalg.inv(view.K).T @ view.R
    depth = rng.uniform(400.0, 600.0, (n, 1))
    return view.source_mm + depth * rays


def _rvec(view: View) -> np.ndarray:
    return cv2.Rodrigues(view.R)[0]


# -- one view -------------------------------------------------------------------------------------
@pytest.mark.parametrize("dist", [(0, 0, 0, 0), DIST5, DIST8])
def test_project_matches_opencv(dist: Any) -> None:
    view = biplane(dist_p=dist).p
    points = image_filling_points(view)
    ours = view.project(points)
    ref = cv2.projectPoints(points, _rvec(view), view.t, view.K, view.dist)[0].reshape(-1, 2)
    np.testing.assert_allclose(ours, ref, atol=1e-9)
    assert np.abs(ours - view.project(points, distort=False)).max() > 1.0 or not any(dist)


def test_project_without_distortion_is_the_contract_K_R_t_with_skew(points: np.ndarray) -> None:
    K = np.array([[1500.0, 3.5, 300.0], [0.0, 1520.0, 250.0], [0.0, 0.0, 1.0]])
    base = biplane().p
    view = View("p", K, np.zeros(5), base.R, base.t, SIZE)
    h = (view.P @ np.column_stack([points, np.ones(len(points))]).T).T
    np.testing.assert_allclose(view.project(points), h[:, :2] / h[:, 2:], atol=1e-9)
    np.testing.assert_allclose(view.source_mm, (-500.0, 0.0, 20.0), atol=1e-9)
    # the source projects nowhere, and a point behind it has no image
    assert np.isnan(view.project([[-600.0, 0.0, 20.0]])).all()


@pytest.mark.parametrize("dist", [DIST5, DIST8])
def test_undistort_inverts_distortion(dist: Any) -> None:
    view = biplane(dist_p=dist).p
    points = image_filling_points(view)
    np.testing.assert_allclose(view.undistort_points(view.project(points)), view.project(points, distort=False),
                               atol=1e-6)


def test_rays_pass_through_the_points() -> None:
    view = biplane(dist_p=DIST5).p
    points = image_filling_points(view)
    origins, directions = view.rays(view.project(points))
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0)
    np.testing.assert_allclose(origins, np.broadcast_to(view.source_mm, origins.shape))
    offset = points - origins
    miss = np.linalg.norm(offset - np.sum(offset * directions, axis=1, keepdims=True) * directions, axis=1)
    assert miss.max() < 1e-6
    assert np.all(np.sum(offset * directions, axis=1) > 0)  # towards the points, not away


def test_backprojected_plane_holds_the_segment(points: np.ndarray) -> None:
    view = biplane(dist_p=DIST5).p
    a, b = points[0], points[1]
    plane = view.backproject_plane(view.project(a)[0], view.project(b)[0])
    np.testing.assert_allclose(np.linalg.norm(plane[:3]), 1.0)
    midpoint = (a + b) / 2
    for X in (a, b, midpoint, view.source_mm):
        assert abs(plane[:3] @ X + plane[3]) < 1e-6
    assert abs(plane[:3] @ points[2] + plane[3]) > 0.01  # an unrelated point is off it
    with pytest.raises(ValueError, match="coincide"):
        view.backproject_plane((10.0, 10.0), (10.0, 10.0))


# -- two views ------------------------------------------------------------------------------------
def test_fundamental_matrix_on_projected_points(points: np.ndarray) -> None:
    cal = biplane()
    F = cal.F
    assert np.linalg.matrix_rank(F, tol=1e-9) == 2
    up, uq = cal.p.project(points), cal.q.project(points)
    # normalised algebraic residual and geometric distance both vanish for true pairs...
    xp, xq = np.column_stack([up, np.ones(len(up))]), np.column_stack([uq, np.ones(len(uq))])
    algebraic = np.einsum("ij,jk,ik->i", xq, F, xp) / (np.linalg.norm(xp, axis=1) * np.linalg.norm(xq, axis=1))
    assert np.abs(algebraic).max() < 1e-12
    assert epipolar_distance_px(F, up, uq).max() < 1e-6
    # ...and not for wrong pairings
    wrong = epipolar_distance_px(F, up, np.roll(uq, 1, axis=0))
    assert np.median(wrong) > 20.0
    # epipoles: the image of the other source
    e_q = cal.q.project(cal.p.source_mm)[0]
    assert np.abs(epipolar_lines(F, up, from_view="p") @ np.append(e_q, 1.0)).max() < 1e-6


def test_fundamental_matrix_order_matters(points: np.ndarray) -> None:
    cal = biplane()
    up, uq = cal.p.project(points), cal.q.project(points)
    assert np.median(epipolar_distance_px(fundamental_matrix(cal.q, cal.p), up, uq)) > 1.0


def test_fundamental_matrix_agrees_with_opencv_estimate(points: np.ndarray) -> None:
    cal = biplane()
    up, uq = cal.p.project(points), cal.q.project(points)
    estimated, _ = cv2.findFundamentalMat(up, uq, cv2.FM_8POINT)
    estimated /= np.linalg.norm(estimated)
    assert min(np.abs(estimated - cal.F).max(), np.abs(estimated + cal.F).max()) < 1e-5


@pytest.mark.parametrize("distorted", [False, True])
def test_triangulation_round_trip(distorted: bool, points: np.ndarray) -> None:
    cal = biplane(DIST5, DIST8) if distorted else biplane()
    up, uq = cal.p.project(points), cal.q.project(points)
    for optimal in (False, True):
        X = triangulate(cal.p, cal.q, up, uq, optimal=optimal)
        np.testing.assert_allclose(X, points, atol=1e-6)
        assert reprojection_error_px(cal.p, cal.q, X, up, uq).max() < 1e-6


@settings(max_examples=60, deadline=None)
@given(azimuth=st.floats(20.0, 160.0), elevation=st.floats(-30.0, 30.0), sod=st.floats(300.0, 900.0),
       focal=st.floats(500.0, 4000.0), k1=st.floats(-0.2, 0.2), seed=st.integers(0, 2**16))
def test_round_trip_over_random_biplane_geometries(azimuth: float, elevation: float, sod: float, focal: float,
                                                   k1: float, seed: int) -> None:
    a, e = np.radians(azimuth), np.radians(elevation)
    p = View.look_at("p", (-sod, 0.0, 0.0), (0, 0, 0), focal_px=focal, image_size=SIZE, dist=(k1, 0, 0, 0, 0))
    q = View.look_at("q", (-sod * np.cos(a) * np.cos(e), -sod * np.sin(a) * np.cos(e), sod * np.sin(e)), (0, 0, 0),
                     focal_px=focal * 1.3, image_size=SIZE, dist=(-k1 / 2, 0, 0, 0, 0))
    cal = Calibration.from_views(p, q)
    X = np.random.default_rng(seed).uniform(-20.0, 20.0, (20, 3))
    up, uq = cal.p.project(X), cal.q.project(X)
    assert epipolar_distance_px(cal.F, cal.p.undistort_points(up), cal.q.undistort_points(uq)).max() < 1e-5
    np.testing.assert_allclose(triangulate(cal.p, cal.q, up, uq), X, atol=1e-5)


def test_triangulation_matches_opencv(points: np.ndarray) -> None:
    cal = biplane(DIST5, (0, 0, 0, 0, 0))
    rng = np.random.default_rng(3)
    up = cal.p.project(points) + rng.normal(0.0, 0.3, (len(points), 2))
    uq = cal.q.project(points) + rng.normal(0.0, 0.3, (len(points), 2))
    a, b = cal.p.undistort_points(up), cal.q.undistort_points(uq)
    h = cv2.triangulatePoints(cal.p.P, cal.q.P, a.T, b.T)
    reference = (h[:3] / h[3]).T
    # both are linear solutions; they differ only in how the algebraic rows are weighted
    assert np.abs(triangulate(cal.p, cal.q, up, uq, optimal=False) - reference).max() < 0.05


def test_optimal_correction_reduces_error_under_noise() -> None:
    # unequal pixel scales in the two views are where the linear solution's algebraic error differs
    # most from the pixel error, and where Hartley-Sturm pays
    cal = biplane(DIST5, (0, 0, 0, 0, 0), focal_q=5000.0)
    rng = np.random.default_rng(11)
    X = rng.uniform(-30.0, 30.0, (2000, 3))
    up = cal.p.project(X) + rng.normal(0.0, 1.0, (len(X), 2))
    uq = cal.q.project(X) + rng.normal(0.0, 1.0, (len(X), 2))
    rms, reproj = {}, {}
    for optimal in (False, True):
        Y = triangulate(cal.p, cal.q, up, uq, optimal=optimal)
        rms[optimal] = float(np.sqrt(np.mean(np.sum((Y - X) ** 2, axis=1))))
        reproj[optimal] = float(np.mean(reprojection_error_px(cal.p, cal.q, Y, up, uq) ** 2))
    assert rms[True] < 0.97 * rms[False]
    assert reproj[True] < 0.5 * reproj[False]
    # one residual degree of freedom of unit variance, spread over the two views' four coordinates
    assert reproj[True] == pytest.approx(0.5, rel=0.1)


def _svd_dlt(cal: Calibration, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The linear DLT by numpy's SVD, as the compiled kernel defines it (normalised coordinates, world / s)."""
    s = max(float(np.linalg.norm(cal.p.t)), float(np.linalg.norm(cal.q.t)), 1.0)
    rows = []
    for view, uv in ((cal.p, a), (cal.q, b)):
        xn = np.column_stack([uv, np.ones(len(uv))]) @ view.K_inv.T
        Pn = np.hstack([view.R, view.t[:, None] / s])
        rows += [xn[:, 0, None] * Pn[2] - Pn[0], xn[:, 1, None] * Pn[2] - Pn[1]]
    A = np.stack(rows, axis=1)
    A /= np.linalg.norm(A, axis=2, keepdims=True)
    Xh = np.linalg.svd(A)[2][:, -1, :]
    return Xh[:, :3] / Xh[:, 3:4] * s


def test_compiled_optimal_correction_matches_opencv_correct_matches(points: np.ndarray) -> None:
    # Lindstrom's iteration must land where Hartley-Sturm's polynomial does (cv2.correctMatches), and
    # the DLT of the moved pixels where numpy's SVD puts it. Noise of 2 px and unequal pixel scales.
    from appliance.epipolar import optimal_correction

    cal = biplane(DIST5, DIST8, focal_q=4000.0)
    rng = np.random.default_rng(19)
    up = cal.p.project(points) + rng.normal(0.0, 2.0, (len(points), 2))
    uq = cal.q.project(points) + rng.normal(0.0, 2.0, (len(points), 2))
    a, b = cal.p.undistort_points(up), cal.q.undistort_points(uq)
    ref_a, ref_b = cv2.correctMatches(cal.F, a.reshape(1, -1, 2), b.reshape(1, -1, 2))
    new_a, new_b = optimal_correction(cal.p, cal.q, a, b)
    assert np.abs(new_a - ref_a.reshape(-1, 2)).max() < 1e-6
    assert np.abs(new_b - ref_b.reshape(-1, 2)).max() < 1e-6
    assert np.abs(new_a - a).max() > 0.5  # the pixels did move
    np.testing.assert_allclose(triangulate(cal.p, cal.q, up, uq), _svd_dlt(cal, new_a, new_b), atol=1e-9)
    np.testing.assert_allclose(triangulate(cal.p, cal.q, up, uq, optimal=False), _svd_dlt(cal, a, b), atol=1e-9)


def test_compiled_projection_and_undistortion_match_the_numpy_views() -> None:
    from appliance import geometry_kernels

    cal = biplane(DIST5, DIST8)
    G = cal.packed
    for index, view in enumerate((cal.p, cal.q)):
        X = image_filling_points(view, 50)
        X[7] = view.source_mm - 10.0 * view.optical_axis  # behind the source: no image
        projected = geometry_kernels.project_into_both(G, X)[index]
        np.testing.assert_allclose(projected, view.project(X), atol=1e-9)
        observed = view.project(X[:5])
        ideal = [geometry_kernels.ideal_pixel(G, index * geometry_kernels.VIEW_SIZE, u, v) for u, v in observed]
        np.testing.assert_allclose(ideal, view.undistort_points(observed), atol=1e-9)
    c, d, half = np.array([3.0, -2.0, 5.0]), np.array([0.6, 0.0, 0.8]), 7.0
    segment = geometry_kernels.project_segment(G, *c, *d, half)
    for index, view in enumerate((cal.p, cal.q)):
        np.testing.assert_allclose(segment[index], view.project(np.vstack([c, c + half * d, c - half * d])),
                                   atol=1e-9)


def test_triangulation_input_checks() -> None:
    cal = biplane()
    with pytest.raises(ValueError, match="pair up"):
        triangulate(cal.p, cal.q, np.zeros((3, 2)), np.zeros((2, 2)))
    assert triangulate(cal.p, cal.q, np.zeros((0, 2)), np.zeros((0, 2))).shape == (0, 3)
    single = triangulate(cal.p, cal.q, cal.p.project([1.0, 2.0, 3.0])[0], cal.q.project([1.0, 2.0, 3.0])[0])
    np.testing.assert_allclose(single, [[1.0, 2.0, 3.0]], atol=1e-6)


def test_epipolar_plane_angle_finds_the_degenerate_axis() -> None:
    cal = biplane()
    centre = np.zeros((1, 3))
    in_plane = np.cross(cal.p.source_mm, cal.q.source_mm)  # normal of the epipolar plane through the origin
    in_plane = np.cross(in_plane, [[1.0, 1.0, 0.0]])        # a direction lying in it
    assert epipolar_plane_angle_deg(cal.p, cal.q, centre, in_plane)[0] < 1e-6
    assert epipolar_plane_angle_deg(cal.p, cal.q, centre, [[0.0, 0.0, 1.0]])[0] > 80.0
    # and it is the pose whose two tip pairings both satisfy the epipolar constraint
    tips = np.vstack([centre - 5 * in_plane / np.linalg.norm(in_plane), centre + 5 * in_plane / np.linalg.norm(in_plane)])
    up, uq = cal.p.project(tips), cal.q.project(tips)
    assert epipolar_distance_px(cal.F, up, uq[::-1]).max() < 1e-6


# -- calibration file -----------------------------------------------------------------------------
def _set(path: str, value: Any) -> Callable[[dict[str, Any]], None]:
    def apply(data: dict[str, Any]) -> None:
        node: Any = data
        keys = path.split(".")
        for key in keys[:-1]:
            node = node[int(key)] if key.isdigit() else node[key]
        last = keys[-1]
        if value is _DELETE:
            del node[last]
        else:
            node[int(last) if last.isdigit() else last] = value
    return apply


_DELETE = object()
_MIRROR = [[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]]  # p's R with the last row negated


@pytest.mark.parametrize("mutation, expected", [
    (_set("views.q.R", _MIRROR), "views.q.R: not a rotation (det -1.000"),
    (_set("views.p.R.0.0", 0.1), "views.p.R: not a rotation"),
    (_set("views.p.K.0.0", float("nan")), "views.p.K[0][0]: Input should be a finite number"),
    (_set("views.p.t.2", float("inf")), "views.p.t[2]: Input should be a finite number"),
    (_set("views.p.K.0.0", -1800.0), "views.p.K: focal lengths"),
    (_set("views.q.K.1.0", 2.0), "views.q.K: not upper-triangular"),
    (_set("views.q.K.2.2", 2.0), "views.q.K: K[2][2] must be 1"),
    (_set("views.p.K", [[1.0, 0.0, 1.0], [0.0, 1.0, 1.0]]), "views.p.K: List should have at least 3 items"),
    (_set("views.p.dist", [0.0, 0.0, 0.0]), "views.p.dist: needs 4, 5 or 8 coefficients"),
    (_set("views.p.t", [0.0, 0.0]), "views.p.t: List should have at least 3 items"),
    (_set("views.p.image_size", [640, 0]), "views.p.image_size[1]: Input should be greater than 0"),
    (_set("views.p.image_size", [640.5, 480]), "views.p.image_size[0]"),
    (_set("views.q", _DELETE), "views.q: Field required"),
    (_set("views.r", {}), "views.r: Extra inputs are not permitted"),
    (_set("views.p.skew", 0.0), "views.p.skew: Extra inputs are not permitted"),
    (_set("views.q.R.1.1", "x"), "views.q.R[1][1]: Input should be a valid number"),
])
def test_calibration_validation_names_key_path(mutation: Callable[[dict[str, Any]], None], expected: str) -> None:
    data = copy.deepcopy(biplane().to_dict())
    mutation(data)
    with pytest.raises(CalibrationError) as info:
        Calibration.from_dict(data, source="cal.yaml")
    assert f"cal.yaml: {expected}" in str(info.value)


def test_calibration_rejects_coincident_and_parallel_views() -> None:
    data = biplane().to_dict()
    same = copy.deepcopy(data)
    same["views"]["q"] = copy.deepcopy(same["views"]["p"])
    with pytest.raises(CalibrationError, match=r"cal.yaml: views: the two sources coincide"):
        Calibration.from_dict(same, source="cal.yaml")
    parallel = copy.deepcopy(same)
    parallel["views"]["q"]["t"][0] += 50.0  # a sideways shift: a baseline, but the same viewing direction
    with pytest.raises(CalibrationError, match=r"cal.yaml: views: the optical axes are parallel"):
        Calibration.from_dict(parallel, source="cal.yaml")


def test_calibration_accepts_rounded_rotations() -> None:
    data = biplane().to_dict()
    data["views"]["q"]["R"] = [[round(v, 6) for v in row] for row in data["views"]["q"]["R"]]
    cal = Calibration.from_dict(data)
    np.testing.assert_allclose(cal.q.R @ cal.q.R.T, np.eye(3), atol=1e-12)


def test_calibration_save_load_round_trip(tmp_path: Path, points: np.ndarray) -> None:
    cal = biplane(DIST5, DIST8)
    cal = Calibration(cal.views, {"reprojection_rms_px": {"p": np.float64(0.21), "q": 0.18}, "inliers": np.int64(57)})
    path = cal.save(tmp_path / "calibration.yaml")
    loaded = Calibration.load(path)
    for name in ("p", "q"):
        a, b = cal.views[name], loaded.views[name]
        for attr in ("K", "dist", "R", "t"):
            np.testing.assert_array_equal(getattr(a, attr), getattr(b, attr))
        assert a.image_size == b.image_size
    np.testing.assert_array_equal(loaded.p.project(points), cal.p.project(points))
    assert loaded.metadata["reprojection_rms_px"] == {"p": 0.21, "q": 0.18}
    assert loaded.metadata["inliers"] == 57
    assert loaded.metadata["loaded_from"] == str(path)


def test_calibration_file_errors(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="missing.yaml: file not found"):
        Calibration.load(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("views: {p: [1, 2\n")
    with pytest.raises(CalibrationError, match="bad.yaml: not valid YAML"):
        Calibration.load(bad)
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    with pytest.raises(CalibrationError, match="empty.yaml: file is empty"):
        Calibration.load(empty)
    listing = tmp_path / "list.yaml"
    listing.write_text("- 1\n- 2\n")
    with pytest.raises(CalibrationError, match="list.yaml"):
        Calibration.load(listing)
