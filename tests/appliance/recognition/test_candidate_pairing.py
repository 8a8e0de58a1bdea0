"""Pairing of full-frame candidates between the views: the compiled distances and ranking give what
the numpy formulation (undistort, epipolar distance, strength score) gives, distortion included."""
from __future__ import annotations

import numpy as np
import pytest

from appliance.geometry import (
    Calibration,
    View,
    epipolar_distance_px,
    fundamental_matrix,
)
from appliance.recognition.correspondence import pair_candidates

SIZE = (640, 480)


def _calibration(dist_p: tuple[float, ...], dist_q: tuple[float, ...]) -> Calibration:
    p = View.look_at("p", (-500.0, 0.0, 20.0), (0, 0, 0), focal_px=1800.0, image_size=SIZE, dist=dist_p)
    q = View.look_at("q", (0.0, -500.0, -10.0), (0, 0, 0), focal_px=1700.0, image_size=SIZE, dist=dist_q,
                     principal_point=(330.0, 231.0))
    return Calibration.from_views(p, q)


def _numpy_pairs(calibration: Calibration, F: np.ndarray, cp: np.ndarray, cq: np.ndarray, sp: np.ndarray,
                 sq: np.ndarray, band_px: float, limit: int = 4) -> list[tuple[int, int, float]]:
    """The ranking written with numpy arrays (what pair_candidates computed before it was compiled)."""
    ip, iq = calibration.p.undistort_points(cp), calibration.q.undistort_points(cq)
    i, j = np.meshgrid(np.arange(len(ip)), np.arange(len(iq)), indexing="ij")
    d = epipolar_distance_px(F, ip[i.ravel()], iq[j.ravel()]).reshape(i.shape)
    score = (sp / sp.max())[:, None] + (sq / sq.max())[None, :] - 0.01 * d / band_px
    score[d > band_px] = -np.inf
    order = np.argsort(-score, axis=None, kind="stable")[:limit]
    pairs = [np.unravel_index(int(k), score.shape) for k in order]
    return [(int(a), int(b), float(d[a, b])) for a, b in pairs if np.isfinite(score[a, b])]


@pytest.mark.parametrize("dist_p, dist_q", [((0, 0, 0, 0, 0), (0, 0, 0, 0, 0)),
                                            ((-0.12, 0.03, 0.0015, -0.002, -0.004),
                                             (-0.1, 0.02, 0.001, 0.0005, 0.001, 0.01, -0.002, 0.0005))])
def test_pairs_and_distances_equal_the_numpy_formulation(dist_p: tuple[float, ...], dist_q: tuple[float, ...]) -> None:
    calibration = _calibration(dist_p, dist_q)
    F = fundamental_matrix(calibration.p, calibration.q)
    rng = np.random.default_rng(3)
    found = 0
    for _ in range(300):
        n, m = (int(v) for v in rng.integers(1, 9, 2))
        # Objects near the isocentre seen in both views, their centroids a few pixels off (some out of
        # the band), strengths rounded so that ties occur.
        X = rng.normal(0.0, 15.0, (max(n, m), 3))
        cp = calibration.p.project(X)[:n] + rng.normal(0.0, 4.0, (n, 2))
        cq = calibration.q.project(X)[:m] + rng.normal(0.0, 4.0, (m, 2))
        sp, sq = rng.integers(1, 4, n).astype(float), rng.integers(1, 4, m).astype(float)
        expected = _numpy_pairs(calibration, F, cp, cq, sp, sq, 6.0)
        got = pair_candidates(calibration, F, [tuple(c) for c in cp.tolist()], [tuple(c) for c in cq.tolist()],
                              sp.tolist(), sq.tolist(), 6.0)
        assert [pair[:2] for pair in got] == [pair[:2] for pair in expected]
        np.testing.assert_allclose([pair[2] for pair in got], [pair[2] for pair in expected], rtol=0, atol=1e-9)
        found += bool(got)
    assert found > 200   # most trials pair something: the comparison is not vacuous


def test_no_candidates_or_none_in_the_band_give_no_pair() -> None:
    calibration = _calibration((0, 0, 0, 0, 0), (0, 0, 0, 0, 0))
    F = fundamental_matrix(calibration.p, calibration.q)
    assert pair_candidates(calibration, F, [], [(320.0, 240.0)], [], [1.0], 6.0) == []
    c_p = tuple(calibration.p.project(np.zeros((1, 3)))[0].tolist())
    c_q = calibration.q.project(np.zeros((1, 3)))[0]
    assert pair_candidates(calibration, F, [c_p], [tuple(c_q.tolist())], [1.0], [1.0], 6.0)[0][:2] == (0, 0)
    # 50 px across the epipolar line (the line through c_q is far from vertical here).
    lines_off = (float(c_q[0]), float(c_q[1]) + 50.0)
    assert pair_candidates(calibration, F, [c_p], [lines_off], [1.0], [1.0], 6.0) == []


def test_the_kernel_warms_up_and_a_centroid_at_the_epipole_pairs_with_nothing() -> None:
    from appliance.recognition import correspondence

    correspondence.warm_up()   # what warm_up_all runs before the first frame
    calibration = _calibration((0, 0, 0, 0, 0), (0, 0, 0, 0, 0))
    # F's own right null vector is p's epipole: its line in q is undefined, its distance NaN.
    F = np.eye(3)
    assert np.isnan(correspondence.centroid_distances(calibration.packed, F.ravel(), np.zeros((1, 2)),
                                                      np.ones((1, 2)))).all()
    assert pair_candidates(calibration, F, [(0.0, 0.0)], [(1.0, 1.0)], [1.0], [1.0], 6.0) == []


def test_a_pair_whose_integrated_attenuations_differ_in_mm2_is_a_mismatch() -> None:
    """The robot's two images hold the same attenuation volume (strength x pixel area at the object):
    equal in mm^2, the pair's strength mismatch is 0 however the views magnify; a quarter, ``log 4``."""
    from types import SimpleNamespace

    from appliance.recognition.tracker import PostureTracker

    calibration = _calibration((0, 0, 0, 0, 0), (0, 0, 0, 0, 0))
    tracker = PostureTracker(calibration)
    X = np.array([12.0, -7.0, 5.0])

    def blob(name: str, strength_mm2: float, width_mm: float) -> SimpleNamespace:
        view = calibration.views[name]
        mm_per_px = float(np.linalg.norm(X - view.source_mm)) / float(view.K[0, 0])
        return SimpleNamespace(centroid_px=tuple(view.project(X[None])[0].tolist()), width_px=width_mm / mm_per_px,
                               strength=strength_mm2 / mm_per_px ** 2)

    width, strength = tracker._size_mismatch({"p": blob("p", 3.0, 1.0), "q": blob("q", 3.0, 1.0)})
    assert width == pytest.approx(0.0, abs=1e-6) and strength == pytest.approx(0.0, abs=1e-6)
    width, strength = tracker._size_mismatch({"p": blob("p", 0.75, 1.0), "q": blob("q", 3.0, 1.0)})
    assert width == pytest.approx(0.0, abs=1e-6) and strength == pytest.approx(np.log(4.0), abs=1e-6)
