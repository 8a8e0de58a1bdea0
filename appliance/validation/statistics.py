"""Errors of one recognised posture against a reference, and the summary statistics of a validation session.

Per sample (one biplane pair against one reference pose, both in the X-ray frame, mm):

- position error: distance between the recognised centroid and the reference centroid;
- axis orientation error: angle between the recognised and the reference axis *lines* (0-90 deg). The
  axis is a line; which end is the head is a separate question (a rod's head is identified only from its
  cone's image), reported as ``head_correct`` rather than folded into the angle, where it would turn a
  correct axis with a wrong head into a 180 deg "error";
- tip errors: the recognised tips matched to the reference head (apex) and tail (tail-face centre) -
  by the head identification when the tracker identified the head, else by the assignment with the
  smaller summed distance - and the distance of each.

Summaries follow the paper's Table 1 (mean and standard deviation) and Fig. 4 (median, quartiles,
whiskers); RMS, 95th percentile and maximum are added because a mean hides the tail a clinician cares
about. Missing values (a lost frame has no error) are dropped and counted, never replaced.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np


def _unit(vector: Any, what: str) -> np.ndarray:
    v = np.asarray(vector, dtype=np.float64).reshape(3)
    norm = float(np.linalg.norm(v))
    if not math.isfinite(norm) or norm == 0.0:
        raise ValueError(f"{what} must be a finite non-zero 3-vector, got {v.tolist()}")
    return v / norm


def position_error_mm(centroid_mm: Any, reference_mm: Any) -> float:
    """Euclidean distance between two points (mm)."""
    a = np.asarray(centroid_mm, dtype=np.float64).reshape(3)
    b = np.asarray(reference_mm, dtype=np.float64).reshape(3)
    return float(np.linalg.norm(a - b))


def axis_angle_deg(direction: Any, reference: Any) -> float:
    """Angle between two axis lines (deg, 0-90): the sign of either direction does not matter."""
    a, b = _unit(direction, "direction"), _unit(reference, "reference direction")
    # atan2 of |cross| and |dot| stays accurate near 0 deg, where acos of the dot product loses digits.
    return float(np.degrees(math.atan2(float(np.linalg.norm(np.cross(a, b))), abs(float(np.dot(a, b))))))


def direction_angle_deg(direction: Any, reference: Any) -> float:
    """Angle between two directions (deg, 0-180): tail-to-head vectors compared with their signs."""
    a, b = _unit(direction, "direction"), _unit(reference, "reference direction")
    return float(np.degrees(math.atan2(float(np.linalg.norm(np.cross(a, b))), float(np.dot(a, b)))))


@dataclass(frozen=True)
class TipErrors:
    """Distances (mm) of the recognised tips to the reference head and tail, and how they were matched."""

    head_mm: float
    tail_mm: float
    matched_by_head: bool   # True: the tracker's head identification decided; False: the nearer assignment

    @property
    def mean_mm(self) -> float:
        return 0.5 * (self.head_mm + self.tail_mm)


def tip_errors_mm(tips_mm: Any, reference_head_mm: Any, reference_tail_mm: Any, *,
                  head_identified: bool) -> TipErrors:
    """Match the two recognised tips (head first when ``head_identified``) to the reference ends."""
    tips = np.asarray(tips_mm, dtype=np.float64).reshape(2, 3)
    head = np.asarray(reference_head_mm, dtype=np.float64).reshape(3)
    tail = np.asarray(reference_tail_mm, dtype=np.float64).reshape(3)
    straight = (float(np.linalg.norm(tips[0] - head)), float(np.linalg.norm(tips[1] - tail)))
    if head_identified:
        return TipErrors(straight[0], straight[1], True)
    crossed = (float(np.linalg.norm(tips[1] - head)), float(np.linalg.norm(tips[0] - tail)))
    best = straight if sum(straight) <= sum(crossed) else crossed
    return TipErrors(best[0], best[1], False)


@dataclass(frozen=True)
class Summary:
    """Statistics of one quantity over a set of samples (NaN when there are none)."""

    n: int
    missing: int
    mean: float
    sd: float          # sample standard deviation (n - 1); NaN below two values
    rms: float
    median: float
    q1: float
    q3: float
    p95: float
    min: float
    max: float

    def to_dict(self, digits: int = 4) -> dict[str, Any]:
        return {key: (value if isinstance(value, int) else (None if not math.isfinite(value) else round(value, digits)))
                for key, value in asdict(self).items()}


def summarise(values: Iterable[float | None]) -> Summary:
    """Summary of ``values``; ``None`` and NaN count as missing."""
    raw = list(values)
    kept = np.array([float(v) for v in raw if v is not None and math.isfinite(float(v))], dtype=np.float64)
    missing = len(raw) - len(kept)
    if len(kept) == 0:
        nan = math.nan
        return Summary(0, missing, nan, nan, nan, nan, nan, nan, nan, nan, nan)
    q1, median, q3, p95 = np.percentile(kept, [25, 50, 75, 95])
    sd = float(np.std(kept, ddof=1)) if len(kept) > 1 else math.nan
    return Summary(n=len(kept), missing=missing, mean=float(np.mean(kept)), sd=sd,
                   rms=float(np.sqrt(np.mean(kept ** 2))), median=float(median), q1=float(q1), q3=float(q3),
                   p95=float(p95), min=float(np.min(kept)), max=float(np.max(kept)))


def mean_sd_text(summary: Summary, digits: int = 2) -> str:
    """``mean ± sd`` as the paper's table prints it; ``n/a`` without values."""
    if summary.n == 0:
        return "n/a"
    if not math.isfinite(summary.sd):
        return f"{summary.mean:.{digits}f}"
    return f"{summary.mean:.{digits}f} ± {summary.sd:.{digits}f}"


def fraction(flags: Sequence[bool]) -> float:
    """Share of True among ``flags`` (NaN for none)."""
    return float(np.mean(flags)) if len(flags) else math.nan
