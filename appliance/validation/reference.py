"""The optical tracker's reference pose of the robot, mapped into the X-ray frame.

The tracker follows a marker tool on the robot's holder, not the robot. The holder calibration says
where that tool sits in the robot's own frame (``tool_in_robot``: robot frame with its origin at the
robot's volume centroid and z along the axis, tail to head), so a tool pose ``T_ots<-tool`` gives the
robot in tracker coordinates as ``T_ots<-tool * inverse(tool_in_robot)``; the registration's X-ray <- OTS
transform then carries it into the frame the appliance reports postures in. The reference tips are the
robot's ends along that axis: the cone's apex (head) and the tail face's centre, at the distances the
robot's geometry (``appliance.robots.RobotSpec``) gives from the centroid.

A holder file (``--holder``) is YAML: ``tool_in_robot: {R: 3x3, t: [x, y, z]}`` or
``tool_in_robot: {rotation_deg_xyz: [rx, ry, rz], translation_mm: [x, y, z]}`` (extrinsic x, y, z).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from appliance.config_io import read_yaml
from appliance.errors import CalibrationError, ConfigError
from appliance.registration import RigidTransform
from appliance.robots import RobotSpec


@dataclass(frozen=True)
class RobotPose:
    """Centroid, unit axis (tail to head) and the two ends of a robot, in one frame (mm)."""

    centroid_mm: np.ndarray
    direction: np.ndarray
    head_mm: np.ndarray
    tail_mm: np.ndarray

    @classmethod
    def from_axis(cls, centroid_mm: Any, direction: Any, robot: RobotSpec) -> RobotPose:
        c = np.asarray(centroid_mm, dtype=np.float64).reshape(3)
        d = np.asarray(direction, dtype=np.float64).reshape(3)
        d = d / np.linalg.norm(d)
        behind = robot.centroid_from_tail_mm
        return cls(c, d, c + (robot.length_mm - behind) * d, c - behind * d)


class ReferenceMapper:
    """Turns tracker samples of the holder tool into the robot's reference pose in the X-ray frame."""

    def __init__(self, xray_to_ots: RigidTransform, tool_in_robot: RigidTransform, robot: RobotSpec) -> None:
        self.ots_to_xray = xray_to_ots.inverse()
        self.robot_from_tool = tool_in_robot.inverse()
        self.robot = robot

    def from_tool(self, tool_to_ots: Any) -> RobotPose:
        """``tool_to_ots``: the tracker's 4x4 tool pose (mm), as :class:`drivers.ndi_tracker.ToolSample` has it."""
        matrix = np.asarray(tool_to_ots, dtype=np.float64)
        if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
            raise ValueError(f"a tool pose is a finite 4x4 matrix, got shape {matrix.shape}")
        tool = RigidTransform(matrix[:3, :3], matrix[:3, 3])
        robot_in_xray = self.ots_to_xray.compose(tool.compose(self.robot_from_tool))
        return RobotPose.from_axis(robot_in_xray.t, robot_in_xray.R[:, 2], self.robot)


def transform_from_mapping(data: Any, source: str) -> RigidTransform:
    """``{R, t}`` or ``{rotation_deg_xyz, translation_mm}`` -> a rigid transform; errors name ``source``."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping with R and t (or rotation_deg_xyz and translation_mm)")
    if "R" in data or "t" in data:
        try:
            return RigidTransform.from_dict(data, source=source)
        except CalibrationError as err:
            raise ConfigError(str(err)) from err
    unknown = sorted(set(data) - {"rotation_deg_xyz", "translation_mm"})
    if unknown:
        raise ConfigError(f"{source}: unknown keys {unknown}; expected R and t, or rotation_deg_xyz and translation_mm")
    try:
        angles = np.asarray(data.get("rotation_deg_xyz", (0.0, 0.0, 0.0)), dtype=np.float64).reshape(3)
        shift = np.asarray(data.get("translation_mm", (0.0, 0.0, 0.0)), dtype=np.float64).reshape(3)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{source}: rotation_deg_xyz and translation_mm are three numbers each ({err})") from err
    if not (np.all(np.isfinite(angles)) and np.all(np.isfinite(shift))):
        raise ConfigError(f"{source}: rotation_deg_xyz and translation_mm must be finite")
    return RigidTransform(Rotation.from_euler("xyz", angles, degrees=True).as_matrix(), shift)


def load_holder(path: str | Path) -> RigidTransform:
    """The holder calibration (``tool_in_robot``) from a YAML file."""
    data = read_yaml(Path(path))
    name = Path(path).name
    if not isinstance(data, dict) or "tool_in_robot" not in data:
        raise ConfigError(f"{name}: needs a 'tool_in_robot' section (the tracked tool in the robot frame)")
    return transform_from_mapping(data["tool_in_robot"], f"{name}: tool_in_robot")
