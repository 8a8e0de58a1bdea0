"""The simulated world: the physical truth that the loopback fakes share, on an injected clock.

``SimWorld`` ties together the TRUE coils (:mod:`drivers.loopback.coils`, magpylib), the magnet
robot's overdamped dynamics (:mod:`drivers.loopback.robot_dynamics`) and the vessel phantom
(:mod:`drivers.loopback.vessel`). The orchestrator feeds it the amplifier fake's MEASURED currents
with ``world.step(dt_s, currents_a)``; the X-ray renderer reads ``world.pose``; the OTS fake reads
``world.tool_pose()``. Nothing here knows about the appliance's configured models.

Integration: currents are held over a step (zero-order hold, like a sampled amplifier). The step is
split into substeps so that the robot moves at most ``max_substep_mm`` per substep; in each, field
and gradient are evaluated at the robot by magpylib, the axis turns toward the field by the exact
overdamped solution, the centroid moves by the drag-limited velocity (plus flow, plus net weight
when ``gravity`` is on), and the vessel wall projects it back and cancels the outward velocity.

Thread safety: one lock guards the state, so device fakes on server threads may read the pose
while the owner loop steps the world.
"""
from __future__ import annotations

import logging
import math
import threading
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from drivers.loopback.coils import TrueCoils
from drivers.loopback.robot_dynamics import Fluid, MagnetRobot, align, drag_for, velocity_m_s
from drivers.loopback.vessel import Vessel

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
_ROBOT_KEYS = ("length_mm", "diameter_mm", "remanence_t", "magnet_volume_mm3", "density_kg_m3")


@dataclass(frozen=True)
class RobotState:
    """True robot pose: centroid (mm), unit axis tail -> head, velocity (mm/s), world time (s)."""

    centroid_mm: FloatArray
    direction: FloatArray
    velocity_mm_s: FloatArray
    t_s: float


@dataclass(frozen=True)
class RigidTransform:
    """x' = rotation @ x + translation_mm."""

    rotation: FloatArray = field(default_factory=lambda: np.eye(3))
    translation_mm: FloatArray = field(default_factory=lambda: np.zeros(3))

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any] | None) -> RigidTransform:
        """``{rotation_deg_xyz: [rx, ry, rz] (extrinsic x, y, z), translation_mm: [x, y, z]}``."""
        if not data:
            return cls()
        rotation = Rotation.from_euler("xyz", data.get("rotation_deg_xyz", (0.0, 0.0, 0.0)), degrees=True)
        return cls(rotation.as_matrix(), np.asarray(data.get("translation_mm", (0.0, 0.0, 0.0)), float))

    def apply(self, point: ArrayLike) -> FloatArray:
        return self.rotation @ np.asarray(point, float) + self.translation_mm

    def compose(self, inner: RigidTransform) -> RigidTransform:
        """self after inner."""
        return RigidTransform(self.rotation @ inner.rotation, self.apply(inner.translation_mm))


@dataclass(frozen=True)
class ToolPose:
    """Pose of the tracked tool in the OTS frame: position (mm) and unit quaternion (w, x, y, z)."""

    position_mm: FloatArray
    quaternion_wxyz: FloatArray
    rotation: FloatArray


def robot_frame(direction: FloatArray) -> FloatArray:
    """A right-handed frame whose z axis is the robot axis; x is world x made perpendicular.

    The rod is axisymmetric so its roll is not physical; this fixes it by convention.
    """
    z = direction / np.linalg.norm(direction)
    ref = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = ref - np.dot(ref, z) * z
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


class SimWorld:
    """The true coils, robot and vessel, advanced by :meth:`step` on the caller's clock."""

    def __init__(self, coils: TrueCoils, robot: MagnetRobot, vessel: Vessel, seed: int | None = 0, *,
                 fluid: Fluid | None = None, gravity: bool = False, up: ArrayLike = (0.0, 0.0, 1.0),
                 start_s_mm: float | None = None, ots_from_world: RigidTransform | None = None,
                 tool_in_robot: RigidTransform | None = None, max_substep_mm: float = 0.05,
                 max_substeps: int = 64, reevaluate_mm: float = 0.25,
                 background_field_t: ArrayLike = (0.0, 0.0, 0.0)) -> None:
        self.coils = coils
        self.robot = robot
        self.vessel = vessel
        self.fluid = fluid or Fluid()
        self.gravity = gravity
        self.up = np.asarray(up, float) / np.linalg.norm(up)
        self.rng = np.random.default_rng(seed)
        self.drag = drag_for(robot, self.fluid, vessel.radius_mm)
        self.moment_am2 = robot.moment_am2
        self.clearance_mm = robot.diameter_mm / 2.0
        self.ots_from_world = ots_from_world or RigidTransform()
        self.tool_in_robot = tool_in_robot or RigidTransform()
        self.max_substep_mm = max_substep_mm
        # Uniform field not made by the coils (the Earth's ~50 uT, a nearby magnet): torque, no force.
        self.background_field_t = np.asarray(background_field_t, float).reshape(3)
        self.max_substeps = max_substeps
        self.reevaluate_mm = reevaluate_mm
        self._cache: tuple[FloatArray, FloatArray] | None = None
        self._cache_point = np.zeros(3)
        self.wall_contacts = 0          # substeps that ended on the wall (diagnostic)
        self.last_substeps = 0          # substeps used by the last step (diagnostic)
        self.last_field_t = np.zeros(3)
        self.last_force_n = np.zeros(3)
        self._lock = threading.Lock()
        s0 = start_s_mm if start_s_mm is not None else min(robot.length_mm / 2.0, vessel.length_mm / 2.0)
        self._position = vessel.point_at(s0)
        self._direction = vessel.tangent_at(s0)
        self._velocity = np.zeros(3)
        self._t = 0.0
        logger.info("world: robot |m| %.4f A m^2, drag axial %.3g N s/m (confinement x%.1f), vessel %.1f mm long",
                    self.moment_am2, self.drag.axial, self.drag.confinement, vessel.length_mm)

    @classmethod
    def from_config(cls, coils: Mapping[str, Any], vessel: Mapping[str, Any],
                    robot: Mapping[str, Any] | None = None, world: Mapping[str, Any] | None = None,
                    seed: int | None = 0) -> SimWorld:
        """Build from plain mappings: ``coils.yaml``, the ``vessel`` section of ``vessel.yaml``, a robot
        entry (extra keys such as tip angles are ignored) and the ``world`` section of ``vessel.yaml``
        (``gravity``, ``fluid``, ``coil_perturbation``, ``start_s_mm``, ``ots_from_world``, ``tool_in_robot``,
        ``background_field_t``)."""
        world = dict(world or {})
        robot_args = {k: robot[k] for k in _ROBOT_KEYS if robot and k in robot}
        fluid = Fluid(**world["fluid"]) if world.get("fluid") else None
        return cls(TrueCoils.from_config(coils, world.get("coil_perturbation"), seed), MagnetRobot(**robot_args),
                   Vessel.from_config(vessel), seed, fluid=fluid, gravity=bool(world.get("gravity", False)),
                   start_s_mm=world.get("start_s_mm"),
                   ots_from_world=RigidTransform.from_mapping(world.get("ots_from_world")),
                   tool_in_robot=RigidTransform.from_mapping(world.get("tool_in_robot")),
                   background_field_t=world.get("background_field_t", (0.0, 0.0, 0.0)))

    def __getstate__(self) -> dict[str, Any]:
        """Pickled without its lock (the simulated lab's child process gets the world whole)."""
        state = self.__dict__.copy()
        del state["_lock"]
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()

    # -- state -----------------------------------------------------------------------------------
    @property
    def pose(self) -> RobotState:
        with self._lock:
            return RobotState(self._position.copy(), self._direction.copy(), self._velocity.copy(), self._t)

    @property
    def t_s(self) -> float:
        return self._t

    def set_pose(self, centroid_mm: ArrayLike, direction: ArrayLike) -> None:
        """Place the robot (tests, scenario set-up); the centroid is kept inside the vessel."""
        d = np.asarray(direction, float)
        with self._lock:
            self._position, _ = self.vessel.constrain(np.asarray(centroid_mm, float), self.clearance_mm)
            self._direction = d / np.linalg.norm(d)
            self._velocity = np.zeros(3)
            self._cache = None

    def tool_pose(self) -> ToolPose:
        """Pose of the tool rigidly attached to the robot, in the OTS frame."""
        with self._lock:
            robot_in_world = RigidTransform(robot_frame(self._direction), self._position.copy())
        pose = self.ots_from_world.compose(robot_in_world).compose(self.tool_in_robot)
        quat_xyzw = Rotation.from_matrix(pose.rotation).as_quat()
        quat = np.roll(quat_xyzw, 1)
        return ToolPose(pose.translation_mm, quat if quat[0] >= 0.0 else -quat, pose.rotation)

    # -- physics ---------------------------------------------------------------------------------
    def field_at(self, point_mm: ArrayLike, currents_a: ArrayLike) -> FloatArray:
        """True field (T) at a point for the given coil currents (background field included)."""
        return self.coils.field_at(point_mm, currents_a) + self.background_field_t

    def _per_amp_here(self) -> tuple[FloatArray, FloatArray]:
        """Per-ampere field and gradient at the robot; magpylib is re-evaluated after each
        ``reevaluate_mm`` of travel and the field is extrapolated linearly in between (the gradient
        changes by ~0.3 % per 0.25 mm at 200 mm from the coils)."""
        offset_m = (self._position - self._cache_point) * 1e-3
        if self._cache is None or float(np.linalg.norm(offset_m)) * 1e3 > self.reevaluate_mm:
            self._cache_point = self._position.copy()
            self._cache = self.coils.field_and_gradient_per_amp(self._position)
            offset_m = np.zeros(3)
        b0, g0 = self._cache
        return b0 + np.einsum("ijk,j->ik", g0, offset_m), g0

    def _forces(self, currents: FloatArray) -> tuple[FloatArray, FloatArray]:
        b_per_amp, g_per_amp = self._per_amp_here()
        b = b_per_amp @ currents + self.background_field_t
        grad = g_per_amp @ currents                      # grad[i, j] = dB_i / dx_j
        force = grad.T @ (self.moment_am2 * self._direction)   # F_j = sum_i m_i dB_i/dx_j
        if self.gravity:
            force = force - self.robot.net_weight_n(self.fluid) * self.up
        return b, force

    def step(self, dt_s: float, currents_a: ArrayLike) -> None:
        """Advance ``dt_s`` seconds with the coil currents (A, the amplifier's measured values) held."""
        currents = np.asarray(currents_a, float)
        if currents.shape != (self.coils.n,):
            raise ValueError(f"expected {self.coils.n} coil currents, got shape {currents.shape}")
        if not np.all(np.isfinite(currents)):
            raise ValueError("coil currents must be finite")
        if not dt_s >= 0.0 or not math.isfinite(dt_s):
            raise ValueError(f"dt_s must be a finite non-negative number, got {dt_s}")
        with self._lock:
            remaining = dt_s
            substeps = 0  # kept for diagnostics (last_substeps)
            while remaining > 1e-12:
                b, force = self._forces(currents)
                velocity = velocity_m_s(self._direction, force, self.drag) * 1e3
                velocity = velocity + self.vessel.flow_velocity_mm_s(self._position)
                speed = float(np.linalg.norm(velocity))
                h = remaining
                if speed * h > self.max_substep_mm:
                    h = max(self.max_substep_mm / speed, dt_s / self.max_substeps)
                h = min(h, remaining)
                self._direction = align(self._direction, b, self.moment_am2, self.drag.rotational, h)
                target = self._position + velocity * h
                self._position, normal = self.vessel.constrain(target, self.clearance_mm)
                if normal is not None:
                    outward = float(np.dot(velocity, normal))
                    if outward > 0.0:
                        velocity = velocity - outward * normal
                    self.wall_contacts += 1
                self._velocity = velocity
                self.last_field_t, self.last_force_n = b, force
                remaining -= h
                substeps += 1
            self._t += dt_s
            self.last_substeps = substeps
