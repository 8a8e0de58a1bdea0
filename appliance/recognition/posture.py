"""The result of recognising one biplane frame pair, and its JSON record (architecture.md contract).

A :class:`Posture` is what the tracker knows about the robot at one exposure; :meth:`Posture.to_record`
turns it into the posture record written as JSON Lines. Numbers that are unknown are ``None`` (JSON
``null``), never invented: a lost frame has ``ok: false``, a reason, and no pose.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np


def _vec(value: np.ndarray | None, digits: int) -> list[float] | None:
    if value is None:
        return None
    array = np.asarray(value, dtype=np.float64)
    if not np.all(np.isfinite(array)):
        return None
    return [round(float(x), digits) for x in array.ravel()]


def _num(value: float | None, digits: int) -> float | None:
    if value is None or not math.isfinite(value):
        return None
    return round(float(value), digits)


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
        return {"centroid": _vec(self.centroid_px, 3), "tips": [_vec(tip, 3) for tip in self.tips_px],
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

    def to_record(self) -> dict[str, Any]:
        """The JSON-ready posture record (plain Python types; unknowns are None)."""
        record: dict[str, Any] = {
            "frame": int(self.frame),
            "t": _num(self.t, 6),
            "ok": bool(self.ok),
            "ambiguous": bool(self.ambiguous),
            "centroid_mm": _vec(self.centroid_mm, 4),
            "direction": _vec(self.direction, 6),
            "tips_mm": None if self.tips_mm is None else [_vec(tip, 4) for tip in self.tips_mm],
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
