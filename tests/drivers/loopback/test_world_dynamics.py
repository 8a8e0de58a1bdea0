"""The simulated world's physics: torque aligns, gradients push at the drag-limited speed, walls stop."""
from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from appliance.config_io import config_path
from drivers.loopback.coils import CoilGeometry, TrueCoils
from drivers.loopback.robot_dynamics import Fluid, MagnetRobot, align, confined_axial_drag, drag_for, free_slender_drag
from drivers.loopback.vessel import Vessel
from drivers.loopback.world import RigidTransform, SimWorld

R_HELM = 300.0   # large coils: uniform field and gradient over the test region


def _bench() -> TrueCoils:
    """Channels 0-5: Helmholtz pairs x, x, y, y, z, z (drive both coils of a pair alike); 6-7: a z Maxwell pair."""
    coils = []
    for axis_index, name in enumerate("xyz"):
        axis = np.eye(3)[axis_index]
        for sign in (-1.0, 1.0):
            coils.append(CoilGeometry(f"h{name}{sign:+.0f}", tuple(sign * R_HELM / 2 * axis), tuple(axis), R_HELM, 500))
    half = math.sqrt(3.0) / 2.0 * R_HELM
    coils.append(CoilGeometry("m-", (0.0, 0.0, -half), (0.0, 0.0, 1.0), R_HELM, 500))
    coils.append(CoilGeometry("m+", (0.0, 0.0, half), (0.0, 0.0, -1.0), R_HELM, 500))
    return TrueCoils(coils)


@pytest.fixture(scope="module")
def bench() -> TrueCoils:
    return _bench()


def _currents(field_axis: int = 2, helmholtz_a: float = 1.0, maxwell_a: float = 0.0) -> np.ndarray:
    currents = np.zeros(8)
    currents[2 * field_axis: 2 * field_axis + 2] = helmholtz_a
    currents[6:8] = maxwell_a
    return currents


def _world(bench: TrueCoils, vessel: Vessel, **kwargs: object) -> SimWorld:
    return SimWorld(bench, MagnetRobot(), vessel, seed=1, **kwargs)  # type: ignore[arg-type]


def test_torque_aligns_the_robot_with_a_uniform_field_at_the_overdamped_rate(bench: TrueCoils) -> None:
    vessel = Vessel([[0, 0, -40], [0, 0, 40]], radius_mm=30.0)
    world = _world(bench, vessel)
    world.set_pose([0, 0, 0], [1.0, 0.0, 0.0])
    currents = _currents(field_axis=2, helmholtz_a=0.5)
    b = float(np.linalg.norm(world.field_at([0, 0, 0], currents)))
    rate = world.moment_am2 * b / world.drag.rotational
    dt = 0.5 / rate                                  # half a time constant: mid-turn, checks the law
    world.step(dt, currents)
    theta = math.acos(float(np.clip(world.pose.direction[2], -1, 1)))
    assert theta == pytest.approx(2.0 * math.atan(math.tan(math.pi / 4) * math.exp(-rate * dt)), rel=1e-6)
    world.step(1.0 / 30.0, currents)
    assert np.allclose(world.pose.direction, [0, 0, 1], atol=1e-9)
    assert np.linalg.norm(world.pose.centroid_mm) < 1e-3   # a uniform field exerts no force


def test_background_field_turns_but_does_not_push(bench: TrueCoils) -> None:
    vessel = Vessel([[0, 0, -40], [0, 0, 40]], radius_mm=30.0)
    earth = np.array([0.0, 20e-6, -45e-6])
    world = _world(bench, vessel, background_field_t=earth)
    world.set_pose([0, 0, 0], [1.0, 0.0, 0.0])
    currents = _currents(field_axis=0, helmholtz_a=0.01)
    total = world.field_at([0, 0, 0], currents)
    assert np.allclose(total - bench.field_at([0, 0, 0], currents), earth)
    world.step(1.0, currents)
    assert np.allclose(world.pose.direction, total / np.linalg.norm(total), atol=1e-9)
    assert np.linalg.norm(world.pose.centroid_mm) < 1e-6


def test_align_is_exact_for_any_step_and_handles_antiparallel() -> None:
    d = align(np.array([0.0, 0.0, -1.0]), np.array([0.0, 0.0, 1e-3]), 0.03, 1e-8, 1.0)
    assert np.allclose(d, [0, 0, 1], atol=1e-6)   # an unstable equilibrium is left, not kept
    same = align(np.array([1.0, 0.0, 0.0]), np.zeros(3), 0.03, 1e-8, 1.0)
    assert np.allclose(same, [1, 0, 0])


def test_gradient_pushes_toward_stronger_field_at_the_drag_limited_speed(bench: TrueCoils) -> None:
    vessel = Vessel([[0, 0, -60], [0, 0, 60]], radius_mm=2.5)
    world = _world(bench, vessel)
    world.set_pose([0, 0, 0], [0.0, 0.0, 1.0])
    currents = _currents(field_axis=2, helmholtz_a=1.0, maxwell_a=-0.05)
    _, grad_per_amp = bench.field_and_gradient_per_amp([0, 0, 0])
    dbz_dz = float((grad_per_amp @ currents)[2, 2])
    expected_mm_s = world.moment_am2 * dbz_dz / world.drag.axial * 1e3
    assert expected_mm_s > 1.0        # the Maxwell pair with negative current raises Bz toward +z
    world.step(0.5, currents)
    assert world.pose.centroid_mm[2] / 0.5 == pytest.approx(expected_mm_s, rel=0.01)
    assert world.pose.velocity_mm_s[2] == pytest.approx(expected_mm_s, rel=0.01)
    assert np.hypot(*world.pose.centroid_mm[:2]) < 1e-3
    # The same gradient pushes a reversed robot (in a reversed field) the other way: F = grad(m . B).
    world.set_pose([0, 0, 0], [0.0, 0.0, -1.0])
    world.step(0.5, _currents(field_axis=2, helmholtz_a=-1.0, maxwell_a=-0.05))
    assert world.pose.centroid_mm[2] == pytest.approx(-0.5 * expected_mm_s, rel=0.01)


def test_closed_end_stops_the_robot_and_kills_the_normal_velocity(bench: TrueCoils) -> None:
    vessel = Vessel([[0, 0, -20], [0, 0, 5]], radius_mm=2.5)
    world = _world(bench, vessel)
    world.set_pose([0, 0, 0], [0.0, 0.0, 1.0])
    world.step(3.0, _currents(field_axis=2, helmholtz_a=1.0, maxwell_a=-0.05))
    assert world.pose.centroid_mm[2] == pytest.approx(5.0, abs=1e-9)
    assert abs(world.pose.velocity_mm_s[2]) < 1e-9
    assert world.wall_contacts > 0


def test_gravity_flag_sinks_the_robot_onto_the_vessel_floor(bench: TrueCoils) -> None:
    vessel = Vessel([[-30, 0, 0], [30, 0, 0]], radius_mm=2.5)
    floating = _world(bench, vessel)
    sinking = _world(bench, vessel, gravity=True)
    for world in (floating, sinking):
        world.set_pose([0, 0, 0], [1.0, 0.0, 0.0])
        world.step(1.0, _currents(field_axis=0, helmholtz_a=0.5))
    assert np.allclose(floating.pose.centroid_mm, [0, 0, 0], atol=1e-6)
    floor = vessel.radius_mm - sinking.robot.diameter_mm / 2.0
    assert sinking.pose.centroid_mm[2] == pytest.approx(-floor, abs=1e-9)
    assert np.allclose(sinking.pose.velocity_mm_s, 0.0, atol=1e-9)
    assert sinking.robot.net_weight_n(Fluid()) == pytest.approx((7500 - 1060) * math.pi * 1e-9 * 10 * 9.80665, rel=1e-6)


def test_flow_carries_a_free_robot_at_the_poiseuille_centre_speed(bench: TrueCoils) -> None:
    vessel = Vessel([[-30, 0, 0], [30, 0, 0]], radius_mm=2.5, flow_mean_mm_s=2.0)
    world = _world(bench, vessel)
    world.set_pose([0, 0, 0], [1.0, 0.0, 0.0])
    world.step(1.0, np.zeros(8))
    assert world.pose.centroid_mm[0] == pytest.approx(4.0, rel=1e-6)


def test_drag_model_limits_and_confinement() -> None:
    fluid = Fluid()
    free = free_slender_drag(0.01, 0.002, fluid.viscosity_pa_s)
    # Confinement grows fast as the gap closes; in a wide tube the annular model (which ignores the
    # rod's ends) falls below the free value, and the free value is used.
    narrow = confined_axial_drag(0.001, 0.0015, 0.01, fluid.viscosity_pa_s)
    snug = confined_axial_drag(0.001, 0.0025, 0.01, fluid.viscosity_pa_s)
    assert narrow > 5 * snug > 5 * free[0]
    assert drag_for(MagnetRobot(), fluid, 50.0).confinement == 1.0
    drag = drag_for(MagnetRobot(), fluid, 2.5)
    assert drag.axial == pytest.approx(snug) and drag.confinement == pytest.approx(snug / free[0])
    assert drag.lateral / drag.axial == pytest.approx(free[1] / free[0])
    assert drag.axial < drag.lateral
    assert MagnetRobot().moment_am2 == pytest.approx(1.2 * math.pi * 1e-9 * 10 / (4e-7 * math.pi))
    with pytest.raises(ValueError, match="lumen"):
        confined_axial_drag(0.002, 0.001, 0.01, fluid.viscosity_pa_s)


def test_world_from_shipped_config_step_pose_and_tool_pose() -> None:
    coils = yaml.safe_load(config_path("coils.yaml").read_text())
    vessel_file = yaml.safe_load(config_path("vessel.yaml").read_text())
    world = SimWorld.from_config(coils, vessel_file["vessel"], robot={"length_mm": 10, "diameter_mm": 2,
                                 "tip_angle_deg": 20}, world=vessel_file["world"], seed=4)
    start = world.pose
    assert start.t_s == 0.0 and np.linalg.norm(start.direction) == pytest.approx(1.0)
    world.step(1.0 / 30.0, np.zeros(8))
    assert world.pose.t_s == pytest.approx(1.0 / 30.0)
    assert np.allclose(world.pose.centroid_mm, start.centroid_mm)
    tool = world.tool_pose()
    ots = RigidTransform.from_mapping(vessel_file["world"]["ots_from_world"])
    offset = np.asarray(vessel_file["world"]["tool_in_robot"]["translation_mm"], float)
    # The tool offset is along the robot axis here, so its position does not depend on the roll convention.
    assert offset[:2].tolist() == [0.0, 0.0]
    expected = ots.apply(start.centroid_mm + offset[2] * start.direction)
    assert np.allclose(tool.position_mm, expected, atol=1e-9)
    assert np.linalg.norm(tool.quaternion_wxyz) == pytest.approx(1.0) and tool.quaternion_wxyz[0] >= 0.0
    assert np.allclose(tool.rotation[:, 2], ots.rotation @ start.direction)
    with pytest.raises(ValueError, match="currents"):
        world.step(0.1, np.zeros(3))
    with pytest.raises(ValueError, match="dt_s"):
        world.step(-1.0, np.zeros(8))
