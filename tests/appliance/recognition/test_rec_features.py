"""Features by PCA: the paper's eq. 2-3 on hand-computable clouds, and the weighted estimator on
synthetic attenuation images whose centroid, axis and ends are known exactly."""
from __future__ import annotations

import math

import numpy as np
import pytest

from appliance.recognition import Blob, Roi, axial_profile, paper_features_from_points, weighted_features
from appliance.recognition.features import axis_sigma_rad, clutter_axis_sigma_rad


def test_paper_estimator_on_a_hand_computable_cloud() -> None:
    # Four points on a line along x at -3, -1, 1, 3 (plus offset): mean (10, 5); with 1/(n-1),
    # s11 = (9 + 1 + 1 + 9) / 3 = 20/3, s22 = s12 = 0, so lambda1 = 20/3, v = (1, 0) and the
    # tips are c +- 2 sqrt(20/3) (1, 0).
    points = np.array([[7.0, 5.0], [9.0, 5.0], [11.0, 5.0], [13.0, 5.0]])
    f = paper_features_from_points(points)
    assert f.centroid == pytest.approx([10.0, 5.0])
    assert f.eigenvalues == pytest.approx((20.0 / 3.0, 0.0))
    assert abs(f.axis[0]) == pytest.approx(1.0)
    half = 2.0 * math.sqrt(20.0 / 3.0)
    assert sorted(f.tips[:, 0]) == pytest.approx([10.0 - half, 10.0 + half])
    assert f.tips[:, 1] == pytest.approx([5.0, 5.0])


def test_paper_estimator_eigenvector_formula_on_a_tilted_cloud() -> None:
    # A symmetric cross of 5 points, stretched along (1, 1): s11 = s22 = 1, s12 = 1 (n - 1 = 4).
    points = np.array([[0.0, 0.0], [1.0, 1.0], [-1.0, -1.0], [1.0, 1.0], [-1.0, -1.0]])
    f = paper_features_from_points(points)
    # lambda = (s11 + s22 +- sqrt((s11 - s22)^2 + 4 s12^2)) / 2 = (2 +- 2) / 2
    assert f.eigenvalues == pytest.approx((2.0, 0.0))
    assert f.axis == pytest.approx(np.array([1.0, 1.0]) / math.sqrt(2.0))
    assert f.tips[0] == pytest.approx(2.0 * math.sqrt(2.0) * f.axis)


def test_paper_estimator_overshoots_a_uniform_rod() -> None:
    """The trap of architecture.md: a rod's half-length is sqrt(3 lambda1), not 2 sqrt(lambda1)."""
    xs = np.arange(-50, 51, dtype=float)
    f = paper_features_from_points(np.column_stack([xs, np.zeros_like(xs)]))
    half = abs(f.tips[0, 0] - f.centroid[0])
    assert half == pytest.approx(2.0 * math.sqrt(f.eigenvalues[0]))
    assert half > 1.1 * 50.0


def _rod_image(shape: tuple[int, int], centre: tuple[float, float], angle_deg: float, half_length: float,
               radius: float, cone: float = 0.0, supersample: int = 8) -> np.ndarray:
    """Path length through a rod (cylinder of ``radius``, axis in the image plane) with an optional
    conical head of length ``cone`` at the +axis end, integrated over each pixel by supersampling."""
    h, w = shape
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    ys, xs = np.mgrid[0:h, 0:w].astype(float)
    ang = math.radians(angle_deg)
    ax = np.array([math.cos(ang), math.sin(ang)])
    total = np.zeros(shape)
    for oy in offsets:
        for ox in offsets:
            dx, dy = xs + ox - centre[0], ys + oy - centre[1]
            s = dx * ax[0] + dy * ax[1]
            t = -dx * ax[1] + dy * ax[0]
            r = np.full(shape, radius)
            if cone > 0:
                start = half_length - cone
                r = np.where(s > start, radius * np.clip((half_length - s) / cone, 0, 1), radius)
            inside = (s >= -half_length) & (s <= half_length) & (np.abs(t) < r)
            total += np.where(inside, 2.0 * np.sqrt(np.maximum(r * r - t * t, 0.0)), 0.0)
    return (total / supersample ** 2).astype(np.float32)


def _blob(weights: np.ndarray) -> Blob:
    m = weights > 0.05 * weights.max()
    return Blob(window=Roi(0, 0, weights.shape[1], weights.shape[0]), weights=weights, mask=m,
                pixel_count=int(m.sum()), peak=float(weights.max()), baseline=0.0, sigma=0.01,
                strength=float(weights.sum()), centroid_px=(0.0, 0.0), touches_border=False)


@pytest.mark.parametrize("angle", [0.0, 17.0, 90.0, 133.0])
def test_weighted_features_of_a_flat_ended_rod(angle: float) -> None:
    weights = _rod_image((80, 90), (44.0, 40.5), angle, half_length=20.0, radius=4.0)
    f = weighted_features(_blob(weights))
    assert f.centroid == pytest.approx([44.0, 40.5], abs=0.02)
    expected = np.array([math.cos(math.radians(angle)), math.sin(math.radians(angle))])
    assert abs(float(f.axis @ expected)) == pytest.approx(1.0, abs=1e-5)
    # Flat ends: located at their half-height, within a tenth of a pixel, and no head claimed.
    ends = sorted(float((tip - f.centroid) @ f.axis) for tip in f.tips)
    assert ends == pytest.approx([-20.0, 20.0], abs=0.15)
    assert f.head_index is None


def test_weighted_features_find_the_conical_head_and_its_apex() -> None:
    weights = _rod_image((70, 110), (50.0, 35.0), 0.0, half_length=30.0, radius=4.0, cone=20.0)
    f = weighted_features(_blob(weights))
    head = f.tips[f.head_index]
    tail = f.tips[1 - f.head_index]
    assert head[0] > tail[0], "the conical end is at +x"
    assert head[0] == pytest.approx(80.0, abs=1.0)  # the apex, not the half-height of the cone
    assert tail[0] == pytest.approx(20.0, abs=0.15)


def _cut_cone(angle: float, cut: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A rod shaped like robot 6 (cone 55 % of the length) whose weights lost the apex's last ``cut`` of
    the cone, as the segmentation's support loses a faint tip; with the uncut body's weighted centroid
    and the unit axis (towards the head)."""
    ax = np.array([math.cos(math.radians(angle)), math.sin(math.radians(angle))])
    whole = _rod_image((130, 140), (70.0, 65.0), angle, half_length=50.0, radius=8.0, cone=62.0, supersample=4)
    ys, xs = np.mgrid[0:whole.shape[0], 0:whole.shape[1]]
    ideal = np.array([(xs * whole).sum(), (ys * whole).sum()]) / whole.sum()
    s = (xs - 70.0) * ax[0] + (ys - 65.0) * ax[1]
    return np.where(s <= 50.0 - cut * 62.0, whole, 0.0).astype(np.float32), ideal, ax


@pytest.mark.parametrize("angle", [0.0, 17.0, 133.0])
def test_weighted_centroid_counts_the_cone_tip_the_weights_lost(angle: float) -> None:
    weights, ideal, ax = _cut_cone(angle, 0.22)
    ys, xs = np.mgrid[0:weights.shape[0], 0:weights.shape[1]]
    moment = np.array([(xs * weights).sum(), (ys * weights).sum()]) / weights.sum()
    f = weighted_features(_blob(weights))
    # The weights' own centroid is a fifth of a pixel towards the tail; the completed one is on the body's.
    assert float((moment - ideal) @ ax) < -0.18
    assert abs(float((f.centroid - ideal) @ ax)) < 0.06
    assert float(np.linalg.norm(f.centroid - ideal)) < 0.06
    # The ends did not move with the centroid: the distances are measured from it.
    assert f.head_index == 0
    assert f.with_head(f.head_index).tips == pytest.approx(f.tips, abs=1e-9)
    assert f.tips[0] == pytest.approx(np.array([70.0, 65.0]) + 50.0 * ax, abs=1.0)


def test_cone_completion_adds_no_more_than_a_cut_tip_can_lose() -> None:
    # Two fifths of the cone missing (more than the support loses): the centroid moves towards the body's,
    # by no more than the largest lost tip allows, never past it.
    weights, ideal, ax = _cut_cone(17.0, 0.4)
    ys, xs = np.mgrid[0:weights.shape[0], 0:weights.shape[1]]
    moment = float((np.array([(xs * weights).sum(), (ys * weights).sum()]) / weights.sum() - ideal) @ ax)
    completed = float((weighted_features(_blob(weights)).centroid - ideal) @ ax)
    assert moment < completed < 0.0
    assert completed - moment < 0.5 * abs(moment)


def test_axial_profile_keeps_the_total_weight() -> None:
    weights = _rod_image((40, 60), (30.0, 20.0), 30.0, half_length=12.0, radius=3.0)
    profile, _ = axial_profile(weights, np.array([30.0, 20.0]), np.array([math.cos(0.5236), math.sin(0.5236)]))
    assert profile.sum() == pytest.approx(float(weights.sum()), rel=1e-6)


def test_axis_noise_estimate_matches_monte_carlo() -> None:
    rng = np.random.default_rng(3)
    clean = 0.4 * _rod_image((40, 60), (30.0, 20.0), 0.0, half_length=15.0, radius=2.5)
    support = clean > 0
    angles = []
    for _ in range(120):
        # Quantum noise in attenuation space: standard deviation grows as exp(A / 2).
        noise = rng.normal(0.0, 0.2, clean.shape) * np.exp(clean / 2.0)
        noisy = np.where(support, clean + noise, 0.0).astype(np.float32)
        angles.append(math.atan2(*weighted_features(_blob(noisy)).axis[::-1]))
    angles = np.unwrap(np.array(angles) * 2) / 2
    f = weighted_features(_blob(clean))
    predicted = axis_sigma_rad(np.where(support, clean, 0), f.centroid, f.axis,
                               f.eigenvalues[0] - f.eigenvalues[1], 0.2)
    assert float(np.std(angles)) == pytest.approx(predicted, rel=0.3)


def test_background_clutter_widens_the_axis_uncertainty_of_a_stubby_body_most() -> None:
    # A blob over another structure (background known to 12 % of the peak): a stubby body's axis (robot 4,
    # elongation ~1.5) becomes uncertain by degrees, a long one's (robot 1, ~9) by a few tenths.
    stubby = clutter_axis_sigma_rad(0.12, 65, 3.75, 0.5 * 65 * 3.75, 6.9, 3.2)
    long_ = clutter_axis_sigma_rad(0.12, 800, 3.75, 0.5 * 800 * 3.75, 300.0, 4.0)
    assert math.degrees(stubby) > 2.5 > 0.5 > math.degrees(long_) > 0.0
    # It grows with the clutter, and a clean background adds nothing.
    assert clutter_axis_sigma_rad(0.24, 65, 3.75, 0.5 * 65 * 3.75, 6.9, 3.2) == pytest.approx(2 * stubby)
    assert clutter_axis_sigma_rad(0.0, 65, 3.75, 0.5 * 65 * 3.75, 6.9, 3.2) == 0.0
    # A round blob: nothing added (its noise term already says the axis is unknown), no division by zero.
    assert clutter_axis_sigma_rad(0.12, 65, 3.75, 100.0, 5.0, 5.0) == 0.0
