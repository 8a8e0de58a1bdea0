"""Path following: from the tracked posture to the field (to orient) and force (to push) to request.

The operator's path is a polyline of waypoints (mm, X-ray world frame), smoothed by a natural cubic
spline in chord length (the same construction as the vessel phantom's centreline) and resampled
every 0.25 mm. Each frame the follower:

1. finds the nearest path point, searching a window around the previous one so a path that comes
   back near itself is not short-cut;
2. moves a target point (the "carrot") along the path at the cruise speed (slowing down over the
   last ``slow_down_mm``, never more than ``max_lead_mm`` ahead of the robot) and commands a
   velocity: the cruise speed along the carrot's tangent minus a proportional-integral correction
   of the robot's offset from the carrot (cross-track and along-track; the integral rejects steady
   force errors, such as the coil model's mismatch with the real coils);
3. limits the speed and the change of commanded velocity per second (rate limit);
4. converts velocity to force with the configured drag of the robot (overdamped motion: F = xi v,
   axial and lateral drags about the tracked axis);
5. asks for a field of ``field_t`` (ramped up from 10 % over ``field_ramp_s`` after a start or
   :meth:`PathFollower.reset`) along the tangent ``lookahead_mm`` ahead, turning at most
   ``max_turn_deg_s``.

The robot's axis follows the field within microseconds (see the world's rotational drag), so the
best estimate of the moment's direction for the allocator is the commanded field direction, not a
noisy tracked axis: a 1 degree axis error times the aligning field's own gradient (~7 mT/m at
0.5 mT) is a force error of ~3.5 uN, as much as the push. ``Command.moment_direction`` gives it.

Each frame's step is one compiled kernel (:mod:`appliance.compiled`; ``_follow``) on the follower's
state kept in a small array (the ``_S_HINT`` ... ``_FIELD_DIR`` offsets), the same arithmetic as the step-by-step list above
in ~10 us instead of ~60 numpy calls (issue 8: control and allocation within 300 us at p99).

The follower only uses what the appliance knows (posture, time, path); it never sees the
simulated truth.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field, model_validator
from scipy.interpolate import CubicSpline

from appliance.compiled import kernel, register_warm_up
from appliance.config_io import StrictModel, config_path, read_yaml, validate_model
from appliance.control.kernel_args import float_vector
from appliance.errors import ConfigError

FloatArray = NDArray[np.float64]
_SPACING_MM = 0.25
_SEARCH_WINDOW_MM = 15.0


class FollowerSettings(StrictModel):
    """Tuning of the path follower (a config section; defaults suit robot #1 in a 5 mm lumen)."""

    speed_mm_s: float = Field(default=4.0, gt=0.0)
    max_speed_mm_s: float = Field(default=8.0, gt=0.0)
    # Weak on purpose: it aligns the robot in milliseconds, and the force error from the coil
    # model's mismatch grows with the currents that make it (see the benchmark).
    field_t: float = Field(default=0.5e-3, gt=0.0)
    field_ramp_s: float = Field(default=1.0, ge=0.0)
    cross_track_gain_per_s: float = Field(default=6.0, ge=0.0)
    cross_track_integral_per_s2: float = Field(default=12.0, ge=0.0)
    integral_limit_mm_s: float = Field(default=6.0, ge=0.0)
    max_accel_mm_s2: float = Field(default=40.0, gt=0.0)
    max_turn_deg_s: float = Field(default=180.0, gt=0.0)
    lookahead_mm: float = Field(default=1.0, ge=0.0)
    max_lead_mm: float = Field(default=2.0, gt=0.0)
    slow_down_mm: float = Field(default=8.0, ge=0.0)
    goal_tolerance_mm: float = Field(default=0.5, gt=0.0)
    drag_axial_n_s_per_m: float = Field(default=1.1e-3, gt=0.0)
    drag_lateral_n_s_per_m: float = Field(default=1.5e-3, gt=0.0)

    @model_validator(mode="after")
    def _speeds(self) -> FollowerSettings:
        if self.speed_mm_s > self.max_speed_mm_s:
            raise ValueError("speed_mm_s must not exceed max_speed_mm_s")
        return self


class Command(NamedTuple):
    """What the follower asks of the coils this frame, and where it thinks the robot is on the path.

    An immutable named tuple rather than a frozen dataclass: built once per frame, and a frozen
    dataclass's ``__init__`` (one ``object.__setattr__`` per field) costs several times a tuple's.
    """

    field_T: FloatArray
    force_N: FloatArray
    cross_track_mm: float
    progress: float            # 0 at the path start, 1 at its end
    done: bool
    velocity_mm_s: FloatArray  # commanded velocity (before conversion to force)
    s_mm: float                # arc length of the nearest path point
    target_mm: FloatArray      # nearest path point

    @property
    def moment_direction(self) -> FloatArray:
        """Unit direction to use for the robot's moment in allocation (the commanded field's)."""
        return self.field_T / np.linalg.norm(self.field_T)


def smooth_path(waypoints_mm: ArrayLike, spacing_mm: float = _SPACING_MM) -> tuple[FloatArray, FloatArray]:
    """(points (M,3), arc lengths (M,)) of the spline through ``waypoints_mm`` resampled every ``spacing_mm``."""
    control = np.asarray(waypoints_mm, float)
    if control.ndim != 2 or control.shape[1] != 3 or len(control) < 2:
        raise ValueError(f"a path needs at least 2 waypoints of 3 coordinates, got shape {control.shape}")
    chords = np.linalg.norm(np.diff(control, axis=0), axis=1)
    if np.any(chords < 1e-9):
        raise ValueError("path has repeated consecutive waypoints")
    u = np.concatenate([[0.0], np.cumsum(chords)])
    if len(control) >= 3:
        dense = CubicSpline(u, control, bc_type="natural")(np.linspace(0.0, u[-1], max(int(u[-1] / (spacing_mm / 2)), 8) + 1))
    else:
        dense = control
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
    s = np.linspace(0.0, arc[-1], max(int(np.ceil(arc[-1] / spacing_mm)), 1) + 1)
    return np.column_stack([np.interp(s, arc, dense[:, k]) for k in range(3)]), s


def cut_path(points: FloatArray, s: FloatArray, start_s_mm: float, end_s_mm: float) -> FloatArray:
    """The stretch [start, end] of a resampled path; a negative ``end_s_mm`` counts from the far end."""
    end = s[-1] + end_s_mm if end_s_mm < 0 else end_s_mm
    if not 0.0 <= start_s_mm < end <= s[-1] + 1e-9:
        raise ValueError(f"path stretch {start_s_mm}..{end_s_mm} mm is not inside 0..{s[-1]:.1f} mm")
    keep = (s > start_s_mm) & (s < end)
    ends = [np.array([np.interp(v, s, points[:, k]) for k in range(3)]) for v in (start_s_mm, end)]
    return np.vstack([ends[0], points[keep], ends[1]])


class _PathSection(StrictModel):
    start_s_mm: float = 0.0
    end_s_mm: float = -0.0
    waypoints_mm: list[tuple[float, float, float]] | None = None


def load_path(path: str | Path | None = None) -> FloatArray:
    """The operator's default path from ``vessel.yaml``: its ``path`` section (explicit ``waypoints_mm``,
    or a ``start_s_mm``/``end_s_mm`` stretch of ``vessel.centreline_mm``), as dense points (M,3)."""
    file = Path(path) if path is not None else config_path("vessel.yaml")
    data = read_yaml(file)
    if not isinstance(data, dict):
        raise ConfigError(f"{file}: expected a mapping with 'vessel' and 'path' sections")
    section = validate_model(_PathSection, data.get("path") or {}, str(file), key_prefix="path")
    if section.waypoints_mm is not None:
        return smooth_path(section.waypoints_mm)[0]
    try:
        centreline = data["vessel"]["centreline_mm"]
        points, s = smooth_path(centreline)
        return cut_path(points, s, section.start_s_mm, section.end_s_mm)
    except (KeyError, TypeError) as err:
        raise ConfigError(f"{file}: vessel.centreline_mm: missing (needed by path)") from err
    except ValueError as err:
        raise ConfigError(f"{file}: path: {err}") from err


# The follower's state between frames, one float array (NaN: not known yet, before the first frame):
# arc length of the last nearest point, time of the last frame, carrot's arc length, time of the start,
# then three 3-vectors from these offsets: integral of the error, commanded velocity, field direction.
_S_HINT, _T_LAST, _CARROT_S, _T_START, _INTEGRAL, _VELOCITY, _FIELD_DIR = 0, 1, 2, 3, 4, 7, 10
_STATE_SIZE = 13
# The settings as the kernel reads them, in this order.
_SETTINGS = ("speed_mm_s", "max_speed_mm_s", "field_t", "field_ramp_s", "cross_track_gain_per_s",
             "cross_track_integral_per_s2", "integral_limit_mm_s", "max_accel_mm_s2", "max_turn_deg_s",
             "lookahead_mm", "max_lead_mm", "slow_down_mm", "goal_tolerance_mm", "drag_axial_n_s_per_m",
             "drag_lateral_n_s_per_m")


class PathFollower:
    """Aligns the robot with the path tangent and pushes it along, correcting cross-track error."""

    def __init__(self, path_points_mm: ArrayLike, settings: FollowerSettings | None = None) -> None:
        self.settings = settings or FollowerSettings()
        self.points, self.s = smooth_path(path_points_mm)
        segments = np.diff(self.points, axis=0)
        self._tangents = segments / np.linalg.norm(segments, axis=1)[:, None]
        self.length_mm = float(self.s[-1])
        self._settings = np.array([float(getattr(self.settings, name)) for name in _SETTINGS])
        self._state = np.empty(_STATE_SIZE)
        self.reset()

    def reset(self) -> None:
        """Forget the previous frame (after a hold, or to start again)."""
        self._state[:] = np.nan
        self._state[_INTEGRAL:_INTEGRAL + 3] = 0.0
        self._state[_VELOCITY:_VELOCITY + 3] = 0.0

    def tangent_at(self, s_mm: float) -> FloatArray:
        return _tangent_at(self.s, self._tangents, float(s_mm)).copy()

    def nearest(self, point_mm: ArrayLike) -> tuple[float, FloatArray]:
        """(arc length, point) of the nearest path point, near the previous one when known."""
        p = np.array(point_mm, dtype=np.float64).reshape(3)
        s, q = _nearest(self.points, self.s, self._tangents, p, self._state[_S_HINT])
        return s, q

    def command(self, posture_centroid_mm: ArrayLike, direction: ArrayLike, t_s: float) -> Command:
        """Field and force for this frame from the tracked centroid and axis at time ``t_s``."""
        # Copies only of what the kernel was not compiled for (a read-only or strided view into a posture).
        p = float_vector(posture_centroid_mm, 3, "posture_centroid_mm")
        axis = float_vector(direction, 3, "direction")
        field, force, velocity, nearest, cross_track, progress, done, s = _follow(
            self.points, self.s, self._tangents, self._settings, self._state, p, axis, float(t_s))
        return Command(field, force, cross_track, progress, done, velocity, s, nearest)

    def point_at(self, s_mm: float) -> FloatArray:
        """Path point at arc length ``s_mm`` (clamped to the ends)."""
        return _point_at(self.points, self.s, float(s_mm))


@kernel
def _tangent_at(s: FloatArray, tangents: FloatArray, s_mm: float) -> FloatArray:
    index = min(max(np.searchsorted(s, s_mm) - 1, 0), tangents.shape[0] - 1)
    return tangents[index]


@kernel
def _point_at(points: FloatArray, s: FloatArray, s_mm: float) -> FloatArray:
    at = min(max(s_mm, 0.0), s[-1])
    out = np.empty(3)
    for k in range(3):
        out[k] = np.interp(at, s, points[:, k])
    return out


@kernel
def _nearest(points: FloatArray, s: FloatArray, tangents: FloatArray, p: FloatArray,
             s_hint: float) -> tuple[float, FloatArray]:
    """Nearest point of the segments within ``_SEARCH_WINDOW_MM`` of ``s_hint`` (all when NaN)."""
    n = tangents.shape[0]
    if math.isnan(s_hint):
        lo, hi = 0, n
    else:
        lo = max(np.searchsorted(s, s_hint - _SEARCH_WINDOW_MM) - 1, 0)
        hi = min(np.searchsorted(s, s_hint + _SEARCH_WINDOW_MM) + 1, n)
    best, best_d2, best_along = lo, math.inf, 0.0
    for i in range(lo, hi):
        along = ((p[0] - points[i, 0]) * tangents[i, 0] + (p[1] - points[i, 1]) * tangents[i, 1]
                 + (p[2] - points[i, 2]) * tangents[i, 2])
        along = min(max(along, 0.0), s[i + 1] - s[i])
        d2 = 0.0
        for k in range(3):
            d = p[k] - (points[i, k] + along * tangents[i, k])
            d2 += d * d
        if d2 < best_d2:
            best, best_d2, best_along = i, d2, along
    return s[best] + best_along, points[best] + best_along * tangents[best]


@kernel
def _norm3(v: FloatArray) -> float:
    return math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


@kernel
def _cruise(settings: FloatArray, length_mm: float, s_mm: float) -> float:
    """Cruise speed at arc length ``s_mm``: slows over the last ``slow_down_mm`` (to 15 %)."""
    speed, slow_down = settings[0], settings[11]
    if slow_down <= 0.0:
        return speed
    return speed * min(1.0, max((length_mm - s_mm) / slow_down, 0.15))


@kernel
def _turn_toward(current: FloatArray, goal: FloatArray, max_angle: float) -> FloatArray:
    """Rotate unit ``current`` toward unit ``goal`` by at most ``max_angle`` radians."""
    cos = min(max(current[0] * goal[0] + current[1] * goal[1] + current[2] * goal[2], -1.0), 1.0)
    angle = math.acos(cos)
    if angle <= max_angle:
        return goal.copy()
    perp = goal - cos * current
    norm = _norm3(perp)
    if norm < 1e-12:
        other = np.array([1.0, 0.0, 0.0]) if abs(current[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        perp = np.cross(current, other)
        norm = _norm3(perp)
    return current * math.cos(max_angle) + perp / norm * math.sin(max_angle)


@kernel
def _follow(points: FloatArray, s_path: FloatArray, tangents: FloatArray, settings: FloatArray, state: FloatArray,
            p: FloatArray, direction: FloatArray, t_s: float
            ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, float, float, bool, float]:
    """One frame of :meth:`PathFollower.command` (steps 1-5 of the module docstring); updates ``state``.

    Returns (field, force, velocity, nearest point, cross-track, progress, done, arc length)."""
    (_speed, max_speed, field_t, field_ramp_s, gain, integral_gain, integral_limit, max_accel, max_turn_deg_s,
     lookahead, max_lead, _slow_down, goal_tolerance, drag_axial, drag_lateral) = (
        settings[0], settings[1], settings[2], settings[3], settings[4], settings[5], settings[6], settings[7],
        settings[8], settings[9], settings[10], settings[11], settings[12], settings[13], settings[14])
    length = s_path[-1]
    axis = direction / _norm3(direction)
    t_last = state[_T_LAST]
    dt = 0.0 if math.isnan(t_last) else min(max(t_s - t_last, 0.0), 0.2)
    state[_T_LAST] = t_s
    if math.isnan(state[_T_START]):
        state[_T_START] = t_s
    s, nearest = _nearest(points, s_path, tangents, p, state[_S_HINT])
    state[_S_HINT] = s
    tangent = _tangent_at(s_path, tangents, s)
    offset = p - nearest
    lateral = offset - (offset[0] * tangent[0] + offset[1] * tangent[1] + offset[2] * tangent[2]) * tangent
    cross_track = _norm3(lateral)
    done = length - s <= goal_tolerance

    # The carrot: a target point moving along the path at the cruise speed, never more than
    # max_lead_mm ahead of the robot (so it waits when the robot is held back).
    if math.isnan(state[_CARROT_S]):
        state[_CARROT_S] = s
    cruise = _cruise(settings, length, state[_CARROT_S])
    carrot = min(state[_CARROT_S] + cruise * dt, s + max_lead, length)
    state[_CARROT_S] = carrot
    carrot_tangent = _tangent_at(s_path, tangents, carrot)
    error = p - _point_at(points, s_path, carrot)
    integral = state[_INTEGRAL:_INTEGRAL + 3]   # views: updated in place
    if done:
        wanted = np.zeros(3)
        integral[:] = 0.0
    else:
        integral += error * dt
        if integral_gain > 0.0:   # anti-windup: bounded integral velocity
            bound = integral_limit / integral_gain
            norm = _norm3(integral)
            if norm > bound:
                integral *= bound / norm
        wanted = _cruise(settings, length, carrot) * carrot_tangent - gain * error - integral_gain * integral
    wanted_speed = _norm3(wanted)
    if wanted_speed > max_speed:
        wanted *= max_speed / wanted_speed
    velocity = state[_VELOCITY:_VELOCITY + 3]
    change = wanted - velocity
    max_change = max_accel * dt if dt > 0.0 else math.inf
    change_norm = _norm3(change)
    if change_norm > max_change:
        change *= max_change / change_norm
    velocity += change

    v_m_s = velocity * 1e-3
    axial = v_m_s[0] * axis[0] + v_m_s[1] * axis[1] + v_m_s[2] * axis[2]
    force = drag_axial * axial * axis + drag_lateral * (v_m_s - axial * axis)

    ahead = _tangent_at(s_path, tangents, min(s + lookahead, length))
    field_dir = state[_FIELD_DIR:_FIELD_DIR + 3]
    if math.isnan(field_dir[0]) or dt == 0.0:
        field_dir[:] = ahead
    else:
        field_dir[:] = _turn_toward(field_dir.copy(), ahead, math.radians(max_turn_deg_s) * dt)
    progress = min(max(s / length, 0.0), 1.0)
    # The field (and with it the model-mismatch force) comes up over field_ramp_s, so the
    # integral action builds up with the disturbance instead of after it hit the wall.
    ramp = 1.0 if field_ramp_s == 0.0 else min(1.0, 0.1 + (t_s - state[_T_START]) / field_ramp_s)
    return field_t * ramp * field_dir, force, velocity.copy(), nearest, cross_track, progress, done, s


def warm_up() -> None:
    """Compile the kernels of this module on a two-segment path (see :mod:`appliance.compiled`)."""
    follower = PathFollower([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [10.0, 1.0, 0.0]])
    for t in (0.0, 0.1):
        follower.command([1.0, 0.1, 0.0], [1.0, 0.0, 0.0], t)
    follower.point_at(1.0)
    _turn_toward(np.array([1.0, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0]), 0.1)


register_warm_up(__name__)
