"""Which tip in view p is which tip in view q: the paper's cases A and B, decided in pixels.

Case A pairs ``p0-q0, p1-q1``; case B pairs ``p0-q1, p1-q0``. Each case is scored by the RMS of the
symmetric geometric epipolar distance (pixels, on undistorted points) of its two pairs, which means
the same thing whatever the focal length or the scaling of ``F`` (unlike the algebraic residual
``x_q^T F x_p``; architecture.md, known traps). The correct case fits to within the tip noise; the
wrong one is off by the robot's extent across the epipolar lines. When the two scores are within
``ambiguity_px`` of each other the robot's axis lies (nearly) in an epipolar plane, and no single frame
can tell the two mirror solutions apart.

Also here: pairing of candidate blobs between the views by the epipolar distance of their centroids,
once per full-frame detection on a handful of blobs: its distances are one compiled call
(:func:`centroid_distances`), since the numpy version's dozens of small calls cost ~100 us (issue 8).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from appliance.compiled import kernel, register_warm_up
from appliance.geometry import Calibration, epipolar_distance_px
from appliance.geometry_kernels import VIEW_SIZE, ideal_pixel

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


@kernel
def centroid_distances(G: np.ndarray, F: np.ndarray, uv_p: np.ndarray, uv_q: np.ndarray
                       ) -> np.ndarray:  # pragma: no cover - compiled
    """Symmetric geometric epipolar distance (px) of every pair of observed pixels (N,2) of p and (M,2)
    of q, (N, M): each undistorted with the packed views ``G``, against ``F`` (row-major, 9), as
    :func:`~appliance.geometry.epipolar_distance_px` computes it on the ideal pixels."""
    n, m = uv_p.shape[0], uv_q.shape[0]
    ideal_q = np.empty((m, 2))
    for j in range(m):
        ideal_q[j, 0], ideal_q[j, 1] = ideal_pixel(G, VIEW_SIZE, uv_q[j, 0], uv_q[j, 1])
    d = np.empty((n, m))
    for i in range(n):
        up, vp = ideal_pixel(G, 0, uv_p[i, 0], uv_p[i, 1])
        # The line in q of the p pixel, F x_p, normalised so that it gives distances in pixels.
        a, b, c = F[0] * up + F[1] * vp + F[2], F[3] * up + F[4] * vp + F[5], F[6] * up + F[7] * vp + F[8]
        norm = math.hypot(a, b)
        for j in range(m):
            uq, vq = ideal_q[j, 0], ideal_q[j, 1]
            a2, b2, c2 = F[0] * uq + F[3] * vq + F[6], F[1] * uq + F[4] * vq + F[7], F[2] * uq + F[5] * vq + F[8]
            norm2 = math.hypot(a2, b2)
            if norm == 0.0 or norm2 == 0.0:
                d[i, j] = math.nan   # a pixel at its view's epipole: no epipolar line
                continue
            d_q = (a * uq + b * vq + c) / norm
            d_p = (a2 * up + b2 * vp + c2) / norm2
            d[i, j] = math.sqrt((d_p * d_p + d_q * d_q) / 2.0)
    return d


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
    # (F copied: a writable contiguous row, the layout the kernel is warmed up with.)
    d = centroid_distances(calibration.packed, np.array(F, dtype=np.float64).ravel(),
                           np.asarray(centroids_p, dtype=np.float64).reshape(-1, 2),
                           np.asarray(centroids_q, dtype=np.float64).reshape(-1, 2)).tolist()
    top_p, top_q = max(max(strengths_p), 1e-12), max(max(strengths_q), 1e-12)
    sq = [float(s) / top_q for s in strengths_q]
    ranked = []
    for i, (strength_p, row) in enumerate(zip(strengths_p, d)):
        sp = float(strength_p) / top_p
        for j, distance in enumerate(row):
            # (A NaN distance, a centroid at its view's epipole, fails the band test too.)
            if distance <= band_px:
                ranked.append((-(sp + sq[j] - 0.01 * distance / band_px), i * len(row) + j, i, j, distance))
    ranked.sort()
    return [(i, j, distance) for _, _, i, j, distance in ranked[:limit]]


def warm_up() -> None:
    """Compile :func:`centroid_distances` (see :mod:`appliance.compiled`)."""
    G = np.zeros(2 * VIEW_SIZE + 10)
    G.setflags(write=False)   # as Calibration.packed hands it over
    centroid_distances(G, np.eye(3).ravel(), np.ones((1, 2)), np.zeros((2, 2)))


register_warm_up(__name__)
