"""Path follower: field along the tangent, push along and back toward the path, rate limits, the end."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from appliance.config_io import config_path
from appliance.control import FollowerSettings, PathFollower, load_path
from appliance.errors import ConfigError

STRAIGHT = np.array([[0.0, 0.0, 0.0], [25.0, 0.0, 0.0], [50.0, 0.0, 0.0]])


def test_on_path_it_aligns_and_pushes_along_the_tangent() -> None:
    cfg = FollowerSettings(field_ramp_s=0.0)
    follower = PathFollower(STRAIGHT, cfg)
    command = follower.command([10.0, 0.0, 0.0], [1.0, 0.0, 0.0], 0.0)
    assert np.allclose(command.field_T, [cfg.field_t, 0, 0])
    assert command.force_N[0] == pytest.approx(cfg.drag_axial_n_s_per_m * cfg.speed_mm_s * 1e-3)
    assert np.allclose(command.force_N[1:], 0.0)
    assert command.cross_track_mm == pytest.approx(0.0) and command.progress == pytest.approx(0.2)
    assert not command.done and np.allclose(command.moment_direction, [1, 0, 0])


def test_field_ramps_up_after_start_and_reset() -> None:
    cfg = FollowerSettings(field_ramp_s=1.0)
    follower = PathFollower(STRAIGHT, cfg)
    magnitudes = [np.linalg.norm(follower.command([10.0, 0, 0], [1, 0, 0], t).field_T) for t in (5.0, 5.5, 6.0, 7.0)]
    assert np.allclose(magnitudes, np.array([0.1, 0.6, 1.0, 1.0]) * cfg.field_t)
    follower.reset()
    assert np.linalg.norm(follower.command([10.0, 0, 0], [1, 0, 0], 9.0).field_T) == pytest.approx(0.1 * cfg.field_t)


def test_cross_track_error_is_pushed_back_with_lateral_drag() -> None:
    cfg = FollowerSettings(cross_track_integral_per_s2=0.0)
    follower = PathFollower(STRAIGHT, cfg)
    command = follower.command([10.0, 0.5, -0.2], [1.0, 0.0, 0.0], 0.0)
    assert command.cross_track_mm == pytest.approx(math.hypot(0.5, 0.2))
    expected_v = -cfg.cross_track_gain_per_s * np.array([0.5, -0.2])
    assert np.allclose(command.force_N[1:], cfg.drag_lateral_n_s_per_m * expected_v * 1e-3)
    assert command.force_N[0] > 0.0


def test_integral_action_grows_while_an_error_persists() -> None:
    follower = PathFollower(STRAIGHT, FollowerSettings(max_accel_mm_s2=1e6))
    forces = [follower.command([5.0 + 0.1 * i, 0.3, 0.0], [1, 0, 0], i / 30).force_N[1] for i in range(30)]
    assert forces[-1] < forces[1] < 0.0


def test_speed_and_acceleration_limits() -> None:
    cfg = FollowerSettings(max_speed_mm_s=5.0, max_accel_mm_s2=30.0)
    follower = PathFollower(STRAIGHT, cfg)
    follower.command([10.0, 0.0, 0.0], [1, 0, 0], 0.0)
    command = follower.command([10.0, 2.0, 0.0], [1, 0, 0], 1 / 30)   # a jump sideways
    previous = np.array([cfg.speed_mm_s, 0.0, 0.0])
    assert np.linalg.norm(command.velocity_mm_s - previous) == pytest.approx(30.0 / 30, rel=1e-9)
    for i in range(2, 60):
        command = follower.command([10.0, 2.0, 0.0], [1, 0, 0], i / 30)
        assert np.linalg.norm(command.velocity_mm_s) <= cfg.max_speed_mm_s + 1e-9


def test_field_turns_at_most_the_rate_limit_at_a_corner() -> None:
    corner = np.array([[0.0, 0.0, 0.0], [20.0, 0.0, 0.0], [20.0, 20.0, 0.0]])
    cfg = FollowerSettings(max_turn_deg_s=90.0)
    follower = PathFollower(corner, cfg)
    follower.command([0.0, 0.0, 0.0], [1, 0, 0], 0.0)
    previous = None
    for i, x in enumerate(np.linspace(0.0, 20.0, 40)):
        command = follower.command(follower.point_at(x * 1.4), [1, 0, 0], (i + 1) / 30)
        direction = command.field_T / np.linalg.norm(command.field_T)
        if previous is not None:
            angle = math.degrees(math.acos(np.clip(np.dot(direction, previous), -1, 1)))
            assert angle <= 90.0 / 30 + 1e-6
        previous = direction


def test_nearest_point_does_not_jump_to_a_nearby_return_leg() -> None:
    hairpin = np.array([[0, 0, 0], [20, 0, 0], [40, 0, 0], [45, 3, 0], [40, 6, 0], [20, 6, 0], [0, 6, 0]], float)
    follower = PathFollower(hairpin)
    follower.command([3.0, 0.0, 0.0], [1, 0, 0], 0.0)
    command = follower.command([5.0, 3.2, 0.0], [1, 0, 0], 1 / 30)
    assert command.s_mm == pytest.approx(5.0, abs=0.2)
    assert follower.nearest([5.0, 3.2, 0.0])[0] < 10.0   # the return leg is at s > 80 mm


def test_done_at_the_end_with_no_push() -> None:
    follower = PathFollower(STRAIGHT, FollowerSettings(goal_tolerance_mm=0.5, max_accel_mm_s2=1e6))
    follower.command([49.0, 0.0, 0.0], [1, 0, 0], 0.0)
    command = follower.command([49.7, 0.0, 0.0], [1, 0, 0], 0.1)
    assert command.done and command.progress == pytest.approx(49.7 / 50.0)
    assert np.allclose(command.force_N, 0.0) and np.linalg.norm(command.field_T) > 0.0


def test_default_path_and_bad_path_sections(tmp_path: Path) -> None:
    path = load_path()
    data = yaml.safe_load(config_path("vessel.yaml").read_text())
    assert np.linalg.norm(path[0] - path[1]) == pytest.approx(0.25, abs=0.01)
    assert len(path) > 100 and np.all(np.abs(path[:, 0]) < 75.0)
    waypoints = tmp_path / "vessel.yaml"
    waypoints.write_text(yaml.safe_dump({"vessel": data["vessel"], "path": {"waypoints_mm": [[0, 0, 0], [0, 10, 0]]}}))
    assert np.allclose(load_path(waypoints)[-1], [0, 10, 0])
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"vessel": data["vessel"], "path": {"start_s_mm": 500.0}}))
    with pytest.raises(ConfigError, match=f"{bad}: path: "):
        load_path(bad)
    typo = tmp_path / "typo.yaml"
    typo.write_text(yaml.safe_dump({"vessel": data["vessel"], "path": {"start_mm": 5.0}}))
    with pytest.raises(ConfigError, match="path.start_mm"):
        load_path(typo)
    with pytest.raises(ValueError, match="speed_mm_s"):
        FollowerSettings(speed_mm_s=10.0, max_speed_mm_s=5.0)


def test_reset_forgets_the_whole_state_and_commands_do_not_share_it() -> None:
    """The compiled step keeps its state in one array: after a reset the follower acts as a new one
    (integral, velocity, carrot, field direction, search window), and two followers never interfere."""
    path = load_path()
    used, other = PathFollower(path), PathFollower(path)
    for i in range(40):
        used.command(path[60 + i] + [0.3, -0.2, 0.1], [0.0, 1.0, 0.0], i / 30)
        other.command(path[10] + [0.5, 0.0, 0.0], [1.0, 0.0, 0.0], i / 30)
    used.reset()
    fresh = PathFollower(path)
    for i in range(5):
        point, t = path[300] + [0.4, 0.1, -0.2], 10.0 + i / 30
        a, b = used.command(point, [0.0, 0.0, 1.0], t), fresh.command(point, [0.0, 0.0, 1.0], t)
        for name in ("field_T", "force_N", "velocity_mm_s", "target_mm"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
        assert (a.s_mm, a.cross_track_mm, a.progress, a.done) == (b.s_mm, b.cross_track_mm, b.progress, b.done)
    # A returned command is a copy: changing it changes nothing in the follower.
    a.velocity_mm_s[:] = 1e6
    a.field_T[:] = 0.0
    assert np.array_equal(used.command(point, [0.0, 0.0, 1.0], 11.0).field_T,
                          fresh.command(point, [0.0, 0.0, 1.0], 11.0).field_T)
