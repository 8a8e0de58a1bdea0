"""The axis within an epipolar plane refitted by the known body (appliance.recognition.axis_by_length and
PostureTracker._axis_by_length).

Synthetic features (robot 6's body, its axis in the epipolar plane through its centroid, projected into the small
session views; one view's head end then run on outwards as into a vessel) check that the scan finds the true
direction where the measured one is turned, that a consistent measured direction is left alone, and that the
tracker reports a frame whose ends fit no direction in the plane without an axis."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from appliance.geometry import Calibration
from appliance.recognition import PostureTracker, RecognitionSettings
from appliance.recognition import axis_by_length
from appliance.recognition.axis_by_length import PlaneScan
from appliance.recognition.body_prior import BodyModel
from appliance.recognition.correspondence import CASE_A, Pairing
from appliance.recognition.features import Features2D
from appliance.recognition.reconstruction import Reconstruction, reconstruct
from appliance.robots import load_robots

CAP = RecognitionSettings().head_body_cap


@pytest.fixture(scope="module")
def robot6() -> BodyModel:
    return BodyModel.of(load_robots()[6])


def _in_epipolar_plane(calibration: Calibration, centroid: np.ndarray, turn_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """A direction in the epipolar plane through ``centroid``, ``turn_deg`` from the bisector of the two rays
    (so both views see it obliquely), and the plane's normal."""
    to_p = calibration.p.source_mm - centroid
    to_q = calibration.q.source_mm - centroid
    normal = np.cross(to_p, to_q)
    normal /= np.linalg.norm(normal)
    bisector = to_p / np.linalg.norm(to_p) + to_q / np.linalg.norm(to_q)
    bisector /= np.linalg.norm(bisector)
    side = np.cross(normal, bisector)
    a = math.radians(turn_deg)
    return math.cos(a) * bisector + math.sin(a) * side, normal


def _features(calibration: Calibration, body: BodyModel, centroid: np.ndarray, direction: np.ndarray,
              run_on_px: dict[str, float]) -> dict[str, Features2D]:
    """Each view's features of the body (head at ``+direction``, 2D end 0), the head end moved outwards by
    ``run_on_px[view]`` (no axial profile: the ends are the tips)."""
    tail = centroid - body.centroid_from_tail_mm * direction
    head = tail + body.length_mm * direction
    feats = {}
    for name in ("p", "q"):
        uv_c, uv_h, uv_t = calibration.views[name].project(np.vstack([centroid, head, tail]))
        axis = (uv_h - uv_t) / np.linalg.norm(uv_h - uv_t)
        tips = np.array([uv_h + run_on_px.get(name, 0.0) * axis, uv_t])
        feats[name] = Features2D(uv_c, axis, (100.0, 4.0), tips, 100, head_index=0)
    return feats


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(min(1.0, float(a @ b) / float(np.linalg.norm(a) * np.linalg.norm(b)))))


def _turned(direction: np.ndarray, normal: np.ndarray, deg: float) -> np.ndarray:
    a = math.radians(deg)
    return math.cos(a) * direction + math.sin(a) * np.cross(normal, direction)


def test_scan_finds_the_direction_a_run_on_head_turned(calibration: Calibration, robot6: BodyModel) -> None:
    c = np.array([3.0, -2.0, 1.0])
    truth, normal = _in_epipolar_plane(calibration, c, 20.0)
    feats = _features(calibration, robot6, c, truth, {"p": 50.0})
    measured = _turned(truth, normal, 6.0)   # as triangulated tips with p's head run on would turn it
    scan = PlaneScan(calibration, c, measured, normal, feats, {"p": 0, "q": 0}, {"p": 0.2, "q": 0.0}, robot6, CAP)
    fit = scan.best()
    assert _angle_deg(fit.direction, truth) < 0.3
    assert float(np.linalg.norm(fit.centroid - c)) < 0.1
    # The run-on head is the one capped term; the measured direction fits far worse.
    assert fit.chi2 <= CAP * CAP + 1.0
    assert scan.chi2_at_start - fit.chi2 > RecognitionSettings().plane_refit_chi2
    assert 0.0 < fit.sigma_deg < 2.0


def test_the_compiled_fits_are_the_numpy_definition(calibration: Calibration, robot6: BodyModel) -> None:
    # The scan's compiled fits (the tracker's path) against the numpy definition, over the directions a scan
    # tries (the run-on head trimmed in some, not in others): the same chi-squares and centroids to rounding
    # (another summation order and a 3x3 elimination for LAPACK's); the warm-ups compiled the calls.
    from appliance.compiled import warm_up_all
    from appliance.recognition import axis_kernels

    warm_up_all()
    compiled = (len(axis_kernels.ray_directions.signatures), len(axis_kernels.fit_centroids.signatures))
    c = np.array([3.0, -2.0, 1.0])
    truth, normal = _in_epipolar_plane(calibration, c, 20.0)
    feats = _features(calibration, robot6, c, truth, {"p": 50.0})
    measured = axis_by_length._measurements(calibration, c, feats, {"p": 0, "q": 0}, {"p": 0.2, "q": 0.0}, robot6)
    origins, rays = measured[0], measured[1]
    for k, name in enumerate(("p", "q")):
        view_origins, view_rays = calibration.views[name].rays(np.vstack([feats[name].tips, feats[name].centroid]))
        np.testing.assert_allclose(rays[3 * k:3 * k + 3], view_rays, rtol=0, atol=1e-14)
        np.testing.assert_array_equal(origins[3 * k:3 * k + 3], view_origins)
    directions = np.array([_turned(truth, normal, a) for a in np.arange(-30.0, 30.1, 0.5)])
    centroids, chi2 = axis_by_length._fit_centroids(directions, *measured, CAP)
    ref_centroids, ref_chi2 = axis_by_length._fit_centroids_reference(directions, *measured, CAP)
    np.testing.assert_allclose(chi2, ref_chi2, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(centroids, ref_centroids, rtol=0, atol=1e-9)
    assert int(np.argmin(chi2)) == int(np.argmin(ref_chi2))
    assert (len(axis_kernels.ray_directions.signatures), len(axis_kernels.fit_centroids.signatures)) == compiled


def test_consistent_direction_fits_at_the_start(calibration: Calibration, robot6: BodyModel) -> None:
    c = np.array([-4.0, 5.0, -2.0])
    truth, normal = _in_epipolar_plane(calibration, c, -15.0)
    feats = _features(calibration, robot6, c, truth, {})
    scan = PlaneScan(calibration, c, truth, normal, feats, {"p": 0, "q": 0}, {"p": 0.0, "q": 0.0}, robot6, CAP)
    assert scan.chi2_at_start < 1.0


def _reconstruction(calibration: Calibration, body: BodyModel, feats: dict[str, Features2D], centroid: np.ndarray,
                    direction: np.ndarray, length_mm: float) -> Reconstruction:
    tail = centroid - body.centroid_from_tail_mm * direction
    pairing = Pairing(CASE_A, 1.0, 1.2, False)
    return Reconstruction(centroid, direction, np.array([tail + length_mm * direction, tail]), True, length_mm, 1.0,
                          pairing, 1.0, True, [], None, {name: f.tips for name, f in feats.items()}, feats, 0.1, 0.01)


def test_tracker_turns_the_axis_or_reports_none(calibration: Calibration, robot6: BodyModel) -> None:
    tracker = PostureTracker(calibration, RecognitionSettings(), body=load_robots()[6])
    c = np.array([3.0, -2.0, 1.0])
    truth, normal = _in_epipolar_plane(calibration, c, 20.0)
    blobs = {"p": SimpleNamespace(clutter=0.2), "q": SimpleNamespace(clutter=0.0)}
    feats = _features(calibration, robot6, c, truth, {"p": 50.0})
    rec = tracker._axis_by_length(_reconstruction(calibration, robot6, feats, c, _turned(truth, normal, 6.0), 36.0),
                                  blobs)  # type: ignore[arg-type]
    assert rec.direction is not None and _angle_deg(rec.direction, truth) < 0.3
    assert rec.ambiguous and "turned" in rec.reasons[-1]
    # A length within the tolerance is not examined.
    kept = _reconstruction(calibration, robot6, feats, c, _turned(truth, normal, 6.0), 30.2)
    assert tracker._axis_by_length(kept, blobs) is kept  # type: ignore[arg-type]
    # Every end moved, each its own way: no direction in the plane fits the body.
    wild = _features(calibration, robot6, c, truth, {"p": 60.0, "q": -40.0})
    wild = {name: Features2D(f.centroid + 30.0 * f.axis * (1 if name == "p" else -1), f.axis, f.eigenvalues,
                             f.tips + np.array([[0.0, 0.0], [-35.0 * f.axis[0], -35.0 * f.axis[1]]]), 100, head_index=0)
            for name, f in wild.items()}
    clean = {"p": SimpleNamespace(clutter=0.0), "q": SimpleNamespace(clutter=0.0)}
    lost = tracker._axis_by_length(_reconstruction(calibration, robot6, wild, c, truth, 45.0), clean)  # type: ignore[arg-type]
    assert lost.direction is None and lost.tips is None and not lost.head_identified
    assert "no axis" in lost.reasons[-1]


def _profiled(feat: Features2D, cone_px: float) -> Features2D:
    """``feat`` with an axial profile (``reach``) whose end 0 is the cone (apex at the tip) and end 1 a blurred
    step, and no head claimed: what a view that cannot tell the ends' ramps apart leaves."""
    apex = float((feat.tips[0] - feat.centroid) @ feat.axis)
    tail = float((feat.centroid - feat.tips[1]) @ feat.axis)
    cone = {level: apex - cone_px * math.sqrt(level) for level in (0.2, 0.25, 0.5, 0.64, 0.8)}
    step = {0.2: tail + 1.0, 0.25: tail + 0.8, 0.5: tail, 0.64: tail - 0.5, 0.8: tail - 1.0}
    return Features2D(feat.centroid, feat.axis, feat.eigenvalues, np.array([feat.centroid + cone[0.5] * feat.axis,
                      feat.centroid - tail * feat.axis]), 100, None, (1.0, 1.0), (cone, step))


def _unresolved_mirror(calibration: Calibration, robot6: BodyModel, tracker: PostureTracker
                       ) -> tuple[np.ndarray, dict[str, Features2D], Reconstruction]:
    """The true axis in an epipolar plane, profiled features that claim no head, and their reconstruction."""
    c = np.array([2.0, 3.0, -1.0])
    truth, _ = _in_epipolar_plane(calibration, c, 25.0)
    feats = _features(calibration, robot6, c, truth, {})
    feats = {name: _profiled(f, robot6.cone_length_mm / robot6.length_mm * float(np.linalg.norm(f.tips[0] - f.tips[1])))
             for name, f in feats.items()}
    return truth, feats, reconstruct(calibration, tracker.F, feats["p"], feats["q"], tracker.settings, None)


def test_mirror_resolved_by_the_body(calibration: Calibration, robot6: BodyModel,
                                     monkeypatch: pytest.MonkeyPatch) -> None:
    tracker = PostureTracker(calibration, RecognitionSettings(), body=load_robots()[6])
    monkeypatch.setattr(tracker, "_rejection", lambda *args: None)   # (no blobs: the checks have nothing to test)
    truth, feats, rec = _unresolved_mirror(calibration, robot6, tracker)
    assert rec.direction is None and rec.candidates is not None   # the mirror ambiguity, unresolved
    blobs = {"p": SimpleNamespace(clutter=0.0), "q": SimpleNamespace(clutter=0.0)}
    resolved = tracker._mirror_by_body(rec, blobs, feats, None)  # type: ignore[arg-type]
    assert resolved.direction is not None and resolved.head_identified
    assert _angle_deg(resolved.direction, truth) < 1.0
    assert "mirror ambiguity is resolved" in resolved.reasons[-1]


def test_an_unresolved_mirror_takes_the_centroid_the_body_fits_agree_on(calibration: Calibration,
                                                                       robot6: BodyModel) -> None:
    tracker = PostureTracker(calibration, RecognitionSettings(), body=load_robots()[6])
    truth, feats, rec = _unresolved_mirror(calibration, robot6, tracker)
    assert rec.direction is None
    body_centre = rec.centroid + 1.5 * truth   # the images' centroid 1.5 mm along the axis from the body's
    close = [SimpleNamespace(centroid=body_centre + offset) for offset in
             (np.array([0.3, 0, 0]), np.array([-0.3, 0, 0]), np.array([0, 0.2, 0]), np.array([0, -0.2, 0]))]
    placed = tracker._centroid_by_body(rec, close)  # type: ignore[arg-type]
    np.testing.assert_allclose(placed.centroid, body_centre, atol=1e-9)
    assert placed.direction is None and "the centroid is the body's" in placed.reasons[-1]
    # Fits farther apart than a quarter of the diameter (5 mm): the measured centroid stands.
    apart = close[:3] + [SimpleNamespace(centroid=body_centre + np.array([0, 0, 1.5]))]
    assert tracker._centroid_by_body(rec, apart) is rec  # type: ignore[arg-type]
