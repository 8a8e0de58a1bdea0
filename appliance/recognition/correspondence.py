"""Which tip in view p is which tip in view q: the paper's cases A and B, decided in pixels.

Case A pairs ``p0-q0, p1-q1``; case B pairs ``p0-q1, p1-q0``. Each case is scored by the RMS of the
symmetric geometric epipolar distance (pixels, on undistorted points) of its two pairs, which means
the same thing whatever the focal length or the scaling of ``F`` (unlike the algebraic residual
``x_q^T F x_p``; architecture.md, known traps). The correct case fits to within the tip noise; the
wrong one is off by the robot's extent across the epipolar lines. When the two scores are within
``ambiguity_px`` of each other the robot's axis lies (nearly) in an epipolar plane, and no single frame
can tell the two mirror solutions apart.

Also here: pairing of candidate blobs between the views by the epipolar distance of their centroids.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from appliance.geometry import Calibration, epipolar_distance_px

CASE_A = "A"
CASE_B = "B"


@dataclass(frozen=True)
class Pairing:
    """The outcome of the A/B test."""

    case: str  # "A" or "B": the better-fitting case
    rms_a_px: float
    rms_b_px: float
    separated: bool  # the worse case is worse by at least the ambiguity threshold

    @property
    def separation_px(self) -> float:
        return abs(self.rms_a_px - self.rms_b_px)

    def q_index(self, p_index: int, case: str | None = None) -> int:
        """The tip of q paired with tip ``p_index`` of p under ``case`` (default: the chosen one)."""
        return p_index if (case or self.case) == CASE_A else 1 - p_index


def pairing_rms(F: np.ndarray, tips_p: np.ndarray, tips_q: np.ndarray) -> tuple[float, float]:
    """RMS symmetric epipolar distance (px) of cases A and B, for undistorted tips (2,2) of each view."""
    both_p = np.vstack([tips_p, tips_p])
    both_q = np.vstack([tips_q, tips_q[::-1]])
    d = epipolar_distance_px(F, both_p, both_q)
    return float(np.sqrt(np.mean(d[:2] ** 2))), float(np.sqrt(np.mean(d[2:] ** 2)))


def choose_pairing(F: np.ndarray, tips_p: np.ndarray, tips_q: np.ndarray, ambiguity_px: float) -> Pairing:
    """Cases A/B by the RMS geometric epipolar distance; ``separated`` False when they are too close to call."""
    rms_a, rms_b = pairing_rms(F, tips_p, tips_q)
    case = CASE_A if rms_a <= rms_b else CASE_B
    return Pairing(case, rms_a, rms_b, abs(rms_a - rms_b) >= ambiguity_px)


def pair_candidates(calibration: Calibration, F: np.ndarray, centroids_p: Sequence[tuple[float, float]],
                    centroids_q: Sequence[tuple[float, float]], strengths_p: Sequence[float],
                    strengths_q: Sequence[float], band_px: float, limit: int = 4) -> list[tuple[int, int, float]]:
    """Candidate pairs (index in p, index in q, epipolar distance) that may be the robot, likeliest first.

    Pairs whose centroids are farther than ``band_px`` from each other's epipolar lines cannot be the
    same object; the others are ranked by strength (each view's absorbers relative to its strongest),
    ties going to the smaller epipolar distance. The caller checks the first few in full.
    """
    if not centroids_p or not centroids_q:
        return []
    cp = calibration.p.undistort_points(np.asarray(centroids_p, dtype=np.float64))
    cq = calibration.q.undistort_points(np.asarray(centroids_q, dtype=np.float64))
    i, j = np.meshgrid(np.arange(len(cp)), np.arange(len(cq)), indexing="ij")
    d = epipolar_distance_px(F, cp[i.ravel()], cq[j.ravel()]).reshape(i.shape)
    sp = np.asarray(strengths_p, dtype=np.float64) / max(max(strengths_p), 1e-12)
    sq = np.asarray(strengths_q, dtype=np.float64) / max(max(strengths_q), 1e-12)
    score = sp[:, None] + sq[None, :] - 0.01 * d / band_px
    score[d > band_px] = -np.inf
    order = np.argsort(-score, axis=None)[:limit]
    pairs = [np.unravel_index(int(k), score.shape) for k in order]
    return [(int(a), int(b), float(d[a, b])) for a, b in pairs if np.isfinite(score[a, b])]
