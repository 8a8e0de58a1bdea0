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

The follower only uses what the appliance knows (posture, time, path); it never sees the
simulated truth.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field, model_validator
from scipy.interpolate import CubicSpline

from appliance.config_io import StrictModel, config_path, read_yaml, validate_model
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


@dataclass(frozen=True)
class Command:
    """What the follower asks of the coils this frame, and where it thinks the robot is on the path."""

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


class PathFollower:
    """Aligns the robot with the path tangent and pushes it along, correcting cross-track error."""

    def __init__(self, path_points_mm: ArrayLike, settings: FollowerSettings | None = None) -> None:
        self.settings = settings or FollowerSettings()
        self.points, self.s = smooth_path(path_points_mm)
        segments = np.diff(self.points, axis=0)
        self._tangents = segments / np.linalg.norm(segments, axis=1)[:, None]
        self.length_mm = float(self.s[-1])
        self.reset()

    def reset(self) -> None:
        """Forget the previous frame (after a hold, or to start again)."""
        self._s_hint: float | None = None
        self._t_last: float | None = None
        self._integral = np.zeros(3)
        self._velocity = np.zeros(3)
        self._carrot_s: float | None = None
        self._t_start: float | None = None
        self._field_dir: FloatArray | None = None

    def tangent_at(self, s_mm: float) -> FloatArray:
        index = int(np.clip(np.searchsorted(self.s, s_mm) - 1, 0, len(self._tangents) - 1))
        return self._tangents[index].copy()

    def nearest(self, point_mm: ArrayLike) -> tuple[float, FloatArray]:
        """(arc length, point) of the nearest path point, near the previous one when known."""
        p = np.asarray(point_mm, float)
        if self._s_hint is None:
            lo, hi = 0, len(self._tangents)
        else:
            lo = max(int(np.searchsorted(self.s, self._s_hint - _SEARCH_WINDOW_MM)) - 1, 0)
            hi = min(int(np.searchsorted(self.s, self._s_hint + _SEARCH_WINDOW_MM)) + 1, len(self._tangents))
        a = self.points[lo:hi]
        t = self._tangents[lo:hi]
        lengths = np.diff(self.s)[lo:hi]
        along = np.clip(np.einsum("ij,ij->i", p - a, t), 0.0, lengths)
        q = a + along[:, None] * t
        best = int(np.argmin(np.linalg.norm(p - q, axis=1)))
        return float(self.s[lo + best] + along[best]), q[best]

    def command(self, posture_centroid_mm: ArrayLike, direction: ArrayLike, t_s: float) -> Command:
        """Field and force for this frame from the tracked centroid and axis at time ``t_s``."""
        cfg = self.settings
        p = np.asarray(posture_centroid_mm, float)
        axis = np.asarray(direction, float)
        axis = axis / np.linalg.norm(axis)
        dt = 0.0 if self._t_last is None else float(np.clip(t_s - self._t_last, 0.0, 0.2))
        self._t_last = t_s
        if self._t_start is None:
            self._t_start = t_s
        s, nearest = self.nearest(p)
        self._s_hint = s
        tangent = self.tangent_at(s)
        offset = p - nearest
        cross_track = float(np.linalg.norm(offset - np.dot(offset, tangent) * tangent))
        done = self.length_mm - s <= cfg.goal_tolerance_mm

        # The carrot: a target point moving along the path at the cruise speed, never more than
        # max_lead_mm ahead of the robot (so it waits when the robot is held back).
        if self._carrot_s is None:
            self._carrot_s = s
        cruise = self._cruise(self._carrot_s)
        self._carrot_s = min(self._carrot_s + cruise * dt, s + cfg.max_lead_mm, self.length_mm)
        carrot_tangent = self.tangent_at(self._carrot_s)
        error = p - self.point_at(self._carrot_s)
        if done:
            wanted = np.zeros(3)
            self._integral[:] = 0.0
        else:
            self._integral += error * dt
            if cfg.cross_track_integral_per_s2 > 0.0:   # anti-windup: bounded integral velocity
                bound = cfg.integral_limit_mm_s / cfg.cross_track_integral_per_s2
                norm = float(np.linalg.norm(self._integral))
                if norm > bound:
                    self._integral *= bound / norm
            wanted = (self._cruise(self._carrot_s) * carrot_tangent - cfg.cross_track_gain_per_s * error
                      - cfg.cross_track_integral_per_s2 * self._integral)
        speed = float(np.linalg.norm(wanted))
        if speed > cfg.max_speed_mm_s:
            wanted *= cfg.max_speed_mm_s / speed
        change = wanted - self._velocity
        max_change = cfg.max_accel_mm_s2 * dt if dt > 0.0 else np.inf
        if float(np.linalg.norm(change)) > max_change:
            change *= max_change / float(np.linalg.norm(change))
        self._velocity = self._velocity + change

        v_m_s = self._velocity * 1e-3
        axial = float(np.dot(v_m_s, axis))
        force = cfg.drag_axial_n_s_per_m * axial * axis + cfg.drag_lateral_n_s_per_m * (v_m_s - axial * axis)

        ahead = self.tangent_at(min(s + cfg.lookahead_mm, self.length_mm))
        self._field_dir = ahead if self._field_dir is None or dt == 0.0 else _turn_toward(
            self._field_dir, ahead, math.radians(cfg.max_turn_deg_s) * dt)
        progress = float(np.clip(s / self.length_mm, 0.0, 1.0))
        # The field (and with it the model-mismatch force) comes up over field_ramp_s, so the
        # integral action builds up with the disturbance instead of after it hit the wall.
        ramp = 1.0 if cfg.field_ramp_s == 0.0 else min(1.0, 0.1 + (t_s - self._t_start) / cfg.field_ramp_s)
        return Command(cfg.field_t * ramp * self._field_dir, force, cross_track, progress, done,
                       self._velocity.copy(), s, nearest)

    def _cruise(self, s_mm: float) -> float:
        """Cruise speed at arc length ``s_mm``: slows over the last ``slow_down_mm`` (to 15 %)."""
        cfg = self.settings
        if cfg.slow_down_mm <= 0.0:
            return cfg.speed_mm_s
        return cfg.speed_mm_s * min(1.0, max((self.length_mm - s_mm) / cfg.slow_down_mm, 0.15))

    def point_at(self, s_mm: float) -> FloatArray:
        """Path point at arc length ``s_mm`` (clamped to the ends)."""
        s = float(np.clip(s_mm, 0.0, self.length_mm))
        return np.array([np.interp(s, self.s, self.points[:, k]) for k in range(3)])


def _turn_toward(current: FloatArray, goal: FloatArray, max_angle: float) -> FloatArray:
    """Rotate unit ``current`` toward unit ``goal`` by at most ``max_angle`` radians."""
    cos = float(np.clip(np.dot(current, goal), -1.0, 1.0))
    angle = math.acos(cos)
    if angle <= max_angle:
        return goal.copy()
    perp = goal - cos * current
    norm = float(np.linalg.norm(perp))
    if norm < 1e-12:
        perp = np.cross(current, [1.0, 0.0, 0.0] if abs(current[0]) < 0.9 else [0.0, 1.0, 0.0])
        norm = float(np.linalg.norm(perp))
    return current * math.cos(max_angle) + perp / norm * math.sin(max_angle)
