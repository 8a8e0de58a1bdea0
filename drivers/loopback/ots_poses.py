"""What the loopback NDI tracker sees: pose providers, the measurement volume and the noise model.

A pose provider is any callable ``provider(now) -> {tool_index: pose | None}`` where a pose is
``(R, t_mm)``: a 3x3 rotation matrix or a unit quaternion (w, x, y, z), and a translation in mm, both in
tracker coordinates; tool index 0 is the first handle a client requested. A tool with no entry or
``None`` is not seen (MISSING). The simulated world plugs in here with its own callable.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

Pose = tuple[ArrayLike, ArrayLike]           # (3x3 rotation or unit quaternion w,x,y,z; translation mm)
PoseProvider = Callable[[float], Mapping[int, Pose | None]]


class _EveryTool(Mapping[int, Pose]):
    """The same pose for whichever tool index is asked for."""

    def __init__(self, pose: Pose) -> None:
        self._pose = pose

    def __getitem__(self, index: int) -> Pose:
        return self._pose

    def __contains__(self, index: object) -> bool:
        return isinstance(index, int)

    def __iter__(self) -> Iterator[int]:
        return iter(())

    def __len__(self) -> int:
        return 0


class FixedPose:
    """Every tool (or only the listed tool indices) at one pose, for ever."""

    def __init__(self, rotation: ArrayLike, translation_mm: ArrayLike, tools: Sequence[int] | None = None) -> None:
        pose: Pose = (np.asarray(rotation, float), np.asarray(translation_mm, float))
        self._poses: Mapping[int, Pose | None] = _EveryTool(pose) if tools is None else {i: pose for i in tools}

    def __call__(self, now: float) -> Mapping[int, Pose | None]:
        return self._poses


class ScriptedPoses:
    """Keyframes ``(t_s, {tool_index: pose | None})`` held until the next one; ``t_s`` counts from the first call."""

    def __init__(self, keyframes: Sequence[tuple[float, Mapping[int, Pose | None]]]) -> None:
        if not keyframes:
            raise ValueError("ScriptedPoses needs at least one keyframe")
        self._keyframes = sorted(keyframes, key=lambda item: item[0])
        self._t0: float | None = None

    def __call__(self, now: float) -> Mapping[int, Pose | None]:
        if self._t0 is None:
            self._t0 = now
        elapsed = now - self._t0
        current = self._keyframes[0][1]
        for t_s, poses in self._keyframes:
            if t_s > elapsed:
                break
            current = poses
        return current


@dataclass(frozen=True)
class BoxVolume:
    """An axis-aligned measurement volume in tracker coordinates (mm); the default is Polaris-like."""

    min_mm: tuple[float, float, float] = (-900.0, -900.0, -2400.0)
    max_mm: tuple[float, float, float] = (900.0, 900.0, -950.0)

    def contains(self, point_mm: np.ndarray) -> bool:
        return bool(np.all(point_mm >= self.min_mm) and np.all(point_mm <= self.max_mm))


@dataclass(frozen=True)
class NoiseModel:
    """Per-frame measurement noise. ``position_rms_mm`` is the 3D RMS (Polaris Spectra: 0.19 mm)."""

    position_rms_mm: float = 0.19
    rotation_rms_deg: float = 0.05
    fit_rms_mm: float = 0.12
    seed: int | None = None


def as_rotation(rotation: ArrayLike) -> Rotation:
    """A 3x3 rotation matrix or a quaternion (w, x, y, z) -> scipy Rotation."""
    array = np.asarray(rotation, float)
    if array.shape == (3, 3):
        return Rotation.from_matrix(array)
    if array.shape == (4,):
        return Rotation.from_quat(array, scalar_first=True)
    raise ValueError(f"a tool rotation is a 3x3 matrix or a quaternion w,x,y,z, got shape {array.shape}")


class HeldPose:
    """One tool held still at ``(rotation, translation_mm)``: ``pose(now)`` (picklable, for a lab in another
    process)."""

    def __init__(self, rotation: ArrayLike, translation_mm: ArrayLike) -> None:
        self.rotation = np.asarray(rotation, float)
        self.translation_mm = np.asarray(translation_mm, float)

    def __call__(self, now: float) -> Pose:
        return self.rotation, self.translation_mm


class PivotingPose:
    """A pointer pivoted about its tip, held in a divot at ``pivot_mm``: two incommensurate swings of
    ``swing_rad`` about the x and y axes of ``base_rotation`` (0.9 and 0.55 turns per second), so the
    pointer cones about its tip in every direction; ``tip_mm`` is the tip in the pointer's frame."""

    def __init__(self, pivot_mm: ArrayLike, base_rotation: ArrayLike, swing_rad: float, tip_mm: ArrayLike,
                 start_s: float) -> None:
        self.pivot_mm = np.asarray(pivot_mm, float)
        self.base_rotation = np.asarray(base_rotation, float)
        self.swing_rad = float(swing_rad)
        self.tip_mm = np.asarray(tip_mm, float)
        self.start_s = float(start_s)

    def __call__(self, now: float) -> Pose:
        phase = 2.0 * math.pi * (now - self.start_s)
        turn = Rotation.from_rotvec([self.swing_rad * math.sin(0.9 * phase), self.swing_rad * math.cos(0.55 * phase),
                                     0.0])
        rotation = self.base_rotation @ turn.as_matrix()
        return rotation, self.pivot_mm - rotation @ self.tip_mm
