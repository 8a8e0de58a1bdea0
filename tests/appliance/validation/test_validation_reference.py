"""The tracker's holder pose -> the robot's reference in the X-ray frame; holder files; fiducial correspondence."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from appliance.errors import CalibrationError, ConfigError
from appliance.geometry import Calibration, View
from appliance.registration import RigidTransform
from appliance.robots import load_robots
from appliance.validation.fiducials import match_across_views, match_by_distances
from appliance.validation.reference import (
    ReferenceMapper,
    RobotPose,
    load_holder,
    transform_from_mapping,
)

LAYOUT = np.array([[0.0, 0.0, 0.0], [31.0, 6.0, -9.0], [-24.0, 13.0, 7.0], [9.0, -27.0, 14.0],
                   [-13.0, -21.0, -23.0], [19.0, 26.0, 21.0], [-33.0, -4.0, 26.0], [23.0, -14.0, -28.0]])


def _transform(seed: int, spread_mm: float = 500.0) -> RigidTransform:
    rng = np.random.default_rng(seed)
    return RigidTransform(Rotation.random(random_state=seed).as_matrix(), rng.uniform(-spread_mm, spread_mm, 3))


def test_robot_ends_sit_on_the_axis_at_the_geometry_distances() -> None:
    robot = load_robots()[1]
    pose = RobotPose.from_axis([1.0, 2.0, 3.0], [0.0, 0.0, 2.0], robot)
    assert np.linalg.norm(pose.head_mm - pose.tail_mm) == pytest.approx(robot.length_mm)
    assert pose.centroid_mm[2] - pose.tail_mm[2] == pytest.approx(robot.centroid_from_tail_mm)
    np.testing.assert_allclose(pose.direction, [0.0, 0.0, 1.0])


def test_mapper_inverts_the_chain_tool_holder_registration() -> None:
    robot = load_robots()[3]
    xray_to_ots, tool_in_robot = _transform(1), _transform(2, 80.0)
    centroid, direction = np.array([5.0, -12.0, 30.0]), np.array([0.6, 0.0, 0.8])
    # Any robot frame whose z is the axis: the roll is the holder's business, not the reference's.
    z = direction
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    robot_in_xray = RigidTransform(np.column_stack([x, np.cross(z, x), z]), centroid)
    tool_in_ots = xray_to_ots.compose(robot_in_xray).compose(tool_in_robot)
    pose = ReferenceMapper(xray_to_ots, tool_in_robot, robot).from_tool(tool_in_ots.matrix())
    np.testing.assert_allclose(pose.centroid_mm, centroid, atol=1e-9)
    np.testing.assert_allclose(pose.direction, direction, atol=1e-12)
    np.testing.assert_allclose(pose.head_mm, centroid + (robot.length_mm - robot.centroid_from_tail_mm) * direction,
                               atol=1e-9)


def test_mapper_refuses_a_malformed_pose() -> None:
    mapper = ReferenceMapper(_transform(1), _transform(2), load_robots()[1])
    with pytest.raises(ValueError, match="4x4"):
        mapper.from_tool(np.eye(3))


def test_holder_files(tmp_path: Path) -> None:
    path = tmp_path / "holder.yaml"
    path.write_text("tool_in_robot: {rotation_deg_xyz: [0, 0, 90], translation_mm: [0, 0, -60]}\n")
    holder = load_holder(path)
    np.testing.assert_allclose(holder.apply([1.0, 0.0, 0.0]), [0.0, 1.0, -60.0], atol=1e-12)
    path.write_text("tool_in_robot: {R: [[1, 0, 0], [0, 1, 0], [0, 0, 1]], t: [1, 2, 3]}\n")
    np.testing.assert_allclose(load_holder(path).t, [1.0, 2.0, 3.0])
    path.write_text("holder: {}\n")
    with pytest.raises(ConfigError, match="holder.yaml: needs a 'tool_in_robot'"):
        load_holder(path)
    with pytest.raises(ConfigError, match=r"x: unknown keys \['rotation_deg'\]"):
        transform_from_mapping({"rotation_deg": [0, 0, 0]}, "x")
    with pytest.raises(ConfigError, match="not a rotation"):
        transform_from_mapping({"R": [[2, 0, 0], [0, 1, 0], [0, 0, 1]], "t": [0, 0, 0]}, "x")


def test_distance_signatures_put_moved_fiducials_in_correspondence() -> None:
    rng = np.random.default_rng(3)
    order = rng.permutation(len(LAYOUT))
    moved = _transform(4).apply(LAYOUT[order]) + rng.normal(0.0, 0.1, LAYOUT.shape)
    perm = match_by_distances(LAYOUT, moved)          # LAYOUT[i] <-> moved[perm[i]]
    np.testing.assert_array_equal(order[perm], np.arange(len(LAYOUT)))
    with pytest.raises(CalibrationError, match="8 seen in X-ray but 7"):
        match_by_distances(LAYOUT, moved[:7])


def test_beads_are_matched_across_the_views_by_epipolar_distance() -> None:
    views = {name: View.look_at(name, source, [0.0, 0.0, 0.0], focal_px=2000.0, image_size=(768, 672))
             for name, source in (("p", [-500.0, 0.0, 0.0]), ("q", [0.0, -500.0, 130.0]))}
    calibration = Calibration.from_views(views["p"], views["q"])
    uv_p, uv_q = views["p"].project(LAYOUT), views["q"].project(LAYOUT)
    order = np.random.default_rng(5).permutation(len(LAYOUT))
    matches = match_across_views(calibration, uv_p, uv_q[order])
    assert sorted(i for i, _ in matches) == list(range(len(LAYOUT)))
    assert all(order[j] == i for i, j in matches)
    # A bead seen in one view only has no partner within the band.
    assert len(match_across_views(calibration, uv_p, uv_q[order][1:])) == len(LAYOUT) - 1
