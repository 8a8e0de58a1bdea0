"""The result of recognising one biplane frame pair, and its JSON record (architecture.md contract).

A :class:`Posture` is what the tracker knows about the robot at one exposure; :meth:`Posture.to_record`
turns it into the posture record written as JSON Lines. Numbers that are unknown are ``None`` (JSON
``null``), never invented: a lost frame has ``ok: false``, a reason, and no pose.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np


def _vec(value: np.ndarray | None, digits: int) -> list[float] | None:
    """The numbers of ``value`` rounded to ``digits``, or None if it is None or any is not finite."""
    if value is None:
        return None
    if type(value) is not np.ndarray or value.dtype != _FLOAT64:
        value = np.asarray(value, dtype=np.float64)
    # As Python floats (float64 -> float is exact), so the test and the rounding are per number without
    # numpy's per-call overhead (a record has ~10 small arrays).
    numbers = value.ravel().tolist()
    for x in numbers:
        if not math.isfinite(x):
            return None
    return [round(x, digits) for x in numbers]


def _rows(value: np.ndarray, digits: int) -> list[list[float] | None]:
    """``[_vec(row, digits) for row in value]`` for a 2D array (tips), from one conversion to floats."""
    if type(value) is not np.ndarray or value.dtype != _FLOAT64:
        value = np.asarray(value, dtype=np.float64)
    if value.ndim != 2:
        return [_vec(row, digits) for row in value]
    return [None if not all(math.isfinite(x) for x in row) else [round(x, digits) for x in row]
            for row in value.tolist()]


def _num(value: float | None, digits: int) -> float | None:
    if value is None or not math.isfinite(value):
        return None
    return round(float(value), digits)


_FLOAT64 = np.dtype(np.float64)


@dataclass(frozen=True)
class ViewObservation:
    """What one view showed: the robot's image centroid, tips (head first when identified) and axis, in pixels."""

    centroid_px: np.ndarray
    tips_px: np.ndarray  # (2, 2)
    axis: np.ndarray  # unit 2D direction of the major axis (towards tips_px[0])
    pixel_count: int
    eigenvalues: tuple[float, float]
    head_index: int | None = None  # which tip the asymmetry says is the conical head, if any

    def to_record(self) -> dict[str, Any]:
        return {"centroid": _vec(self.centroid_px, 3), "tips": _rows(self.tips_px, 3),
                "axis": _vec(self.axis, 5), "pixel_count": int(self.pixel_count)}


@dataclass
class Posture:
    """The robot's 3D pose at one frame pair; fields are ``None`` where not known."""

    frame: int
    t: float
    ok: bool
    ambiguous: bool = False
    centroid_mm: np.ndarray | None = None
    direction: np.ndarray | None = None  # unit, tail -> head when head_identified
    tips_mm: np.ndarray | None = None  # (2, 3), head first when head_identified
    head_identified: bool = False
    #: The length between the ends as measured. Where the tracker knows the robot (body prior) the tips are
    #: its body's, the catalogue length apart, and this stays the measurement (a plausibility signal).
    length_mm: float | None = None
    reprojection_px: float | None = None
    views: dict[str, ViewObservation | None] = field(default_factory=lambda: {"p": None, "q": None})
    reason: str | None = None
    #: Both mirror directions when an epipolar-plane ambiguity could not be resolved (direction is None then).
    direction_candidates: list[np.ndarray] | None = None
    #: Diagnostics: RMS epipolar distance (px) of pairings A and B, angle between the axis planes (deg).
    pairing_rms_px: tuple[float, float] | None = None
    plane_angle_deg: float | None = None
    #: Per-stage wall time of this frame pair (microseconds): segmentation, features, correspondence, triangulation.
    timings_us: dict[str, float] = field(default_factory=dict)

    @classmethod
    def lost(cls, frame: int, t: float, reason: str, views: dict[str, ViewObservation | None] | None = None) -> Posture:
        """A frame where the robot was not recognised; ``reason`` is one sentence for the operator."""
        return cls(frame=frame, t=t, ok=False, reason=reason, views=views or {"p": None, "q": None})

    @classmethod
    def deferred(cls, fields: dict[str, Any], rest: Callable[[], dict[str, Any]]) -> Posture:
        """A posture holding ``fields`` (every field by name, but any of :data:`DEFERRABLE`) whose other
        fields are made by ``rest()`` when one of them is first read (then kept). The tracker's steady
        state builds its plain frames so (issue 8): the loop's control reads the pose at once, the tips
        and the views are for the record, written after the command. Made without the dataclass's
        ``__init__`` (it has no ``__post_init__``); every field reads as the ``__init__``-built
        posture's would (the tests compare them)."""
        posture = object.__new__(cls)
        fields["_rest"] = rest
        posture.__dict__ = fields
        return posture

    def __getattr__(self, name: str) -> Any:
        # Called only for what the instance does not hold: the fields a deferred posture has not made yet.
        if name in DEFERRABLE:
            held = self.__dict__
            rest = held.pop("_rest", None)
            if rest is not None:
                for key, value in rest().items():
                    held.setdefault(key, value)  # a field assigned meanwhile keeps its new value
                return held[name]
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def to_record(self) -> dict[str, Any]:
        """The JSON-ready posture record (plain Python types; unknowns are None)."""
        record: dict[str, Any] = {
            "frame": int(self.frame),
            "t": _num(self.t, 6),
            "ok": bool(self.ok),
            "ambiguous": bool(self.ambiguous),
            "centroid_mm": _vec(self.centroid_mm, 4),
            "direction": _vec(self.direction, 6),
            "tips_mm": None if self.tips_mm is None else _rows(self.tips_mm, 4),
            "head_identified": bool(self.head_identified),
            "length_mm": _num(self.length_mm, 4),
            "reprojection_px": _num(self.reprojection_px, 3),
            "views": {name: (obs.to_record() if obs is not None else None) for name, obs in self.views.items()},
            "reason": self.reason,
        }
        if self.direction_candidates is not None:
            record["direction_candidates"] = [_vec(d, 6) for d in self.direction_candidates]
        if self.pairing_rms_px is not None:
            record["pairing_rms_px"] = [_num(v, 3) for v in self.pairing_rms_px]
        if self.plane_angle_deg is not None:
            record["plane_angle_deg"] = _num(self.plane_angle_deg, 3)
        return record


#: The fields :meth:`Posture.deferred` may leave to their first reading. None of them may be a class
#: attribute (an instance's lookup would find it before ``__getattr__``): ``tips_mm``'s default None is
#: its ``__init__``'s alone.
DEFERRABLE = frozenset({"tips_mm", "views"})
del Posture.tips_mm
