"""The tracker's one-call ROI search gives what segment + gate + features give, bit for bit, on rendered
views of several robots (clean and over a contrast-filled vessel), and the tracker's noise-sigma schedule."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from appliance.geometry import Calibration, View
from appliance.recognition import PostureTracker, RecognitionSettings, roi_search
from appliance.recognition import tracker as tracker_module
from appliance.recognition.segmentation import Blob, Roi, log_background, segment
from appliance.recognition.steady_state import SteadyPair
from appliance.robots import load_robots
from drivers.loopback.scene_builders import S_BEND_CENTRELINE_MM, smooth_centreline
from drivers.loopback.xray_render import (
    BiplaneRenderer,
    ImagingSettings,
    RobotBody,
    RobotPose,
    VesselPhantom,
    biplane_views,
)


def _rendered_views(views: dict[str, object], robot: int, pose: RobotPose, seed: int) -> dict[str, np.ndarray]:
    spec = load_robots()[robot]
    body = RobotBody(spec.length_mm, spec.diameter_mm, spec.tip_angle_deg, spec.attenuation_per_mm)
    vessel = VesselPhantom(smooth_centreline(S_BEND_CENTRELINE_MM), 2.5, 0.06)
    renderer = BiplaneRenderer(views, body, vessel=vessel, settings=ImagingSettings(), seed=seed)
    return renderer.render(pose).images


def _assert_same(a: object, b: object) -> None:
    assert type(a) is type(b)
    for f in dataclasses.fields(a):  # type: ignore[arg-type]
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape, f.name
            np.testing.assert_array_equal(x, y, err_msg=f.name)
        else:
            assert x == y, (f.name, x, y)


def _compare(image: np.ndarray, calibration_view: str, settings: RecognitionSettings, roi: Roi,
             predicted: tuple[float, float], sigma: float | None) -> tuple[Blob, object] | None:
    log_bg = log_background(image, settings.background_scale_px, settings.dark_level)
    general = roi_search._general(image, log_bg, roi, settings, predicted, sigma)
    compiled = roi_search._compiled(image, log_bg, roi, settings, predicted, sigma)
    assert compiled is not False, "the gate test was too close to call"
    if general is None:
        assert compiled is None
        return None
    assert compiled is not None and compiled is not True
    _assert_same(compiled[0], general[0])
    _assert_same(compiled[1], general[1])
    return compiled


@pytest.mark.parametrize("robot,centroid,direction", [
    (1, (3.0, -4.0, 5.0), (0.3, 0.5, 0.81)),
    (3, (0.0, 0.5, 6.0), (0.9, 0.4, 0.2)),      # along the vessel
    (4, (-20.0, -11.0, 4.0), (0.2, 0.9, 0.4)),  # across the vessel
    (6, (1.0, 0.0, 6.0), (0.6, -0.3, 0.74)),    # over the vessel
    (7, (8.0, 6.0, -5.0), (-0.7, 0.2, 0.68)),
])
@pytest.mark.parametrize("along_structure", [False, True])
def test_one_call_equals_segment_gate_and_features(views: dict[str, object], calibration: Calibration, robot: int,
                                                   centroid: tuple[float, ...], direction: tuple[float, ...],
                                                   along_structure: bool) -> None:
    images = _rendered_views(views, robot, RobotPose(np.array(centroid), np.array(direction)), seed=robot)
    # Both backgrounds under the body (along image columns or rows; along the vessel the body crosses).
    settings = RecognitionSettings(background_along_structure=along_structure)
    for name, image in images.items():
        log_bg = log_background(image, settings.background_scale_px, settings.dark_level)
        strongest = next(b for b in segment(image, log_bg, None, settings) if not b.touches_border)
        w = strongest.window
        roi = Roi(max(w.x0 - 20, 0), max(w.y0 - 20, 0), min(w.x1 + 20, image.shape[1]), min(w.y1 + 20, image.shape[0]))
        u, v = strongest.centroid_px
        found = _compare(image, name, settings, roi, (u + 3.0, v - 2.0), None)
        assert found is not None and found[0].centroid_px == pytest.approx(strongest.centroid_px, abs=0.5)
        # A known sigma (the tracker's reuse), another one, a read-only frame, capped weights for the axis.
        _compare(image, name, settings, roi, (u, v), found[0].sigma)
        _compare(image, name, settings, roi, (u, v), 1.3 * found[0].sigma)
        frozen = image.copy()
        frozen.flags.writeable = False
        _compare(frozen, name, settings, roi, (u, v), None)
        _compare(image, name, settings.model_copy(update={"axis_saturation": 0.5}), roi, (u, v), None)
        # Predictions off by more than the gate: nothing, on both paths; a ROI cutting the body: nothing whole.
        assert _compare(image, name, settings, roi, (u + settings.gate_px + 1.0, v), None) is None
        cut = Roi(roi.x0, roi.y0, int(u), roi.y1)
        _compare(image, name, settings, cut, (u, v), None)


def test_the_gate_keeps_the_strongest_near_blob_not_the_strongest(views: dict[str, object],
                                                                   calibration: Calibration) -> None:
    # Two robots' worth of blobs in one ROI: the vessel and the robot; a prediction near either
    # picks that one on both paths.
    images = _rendered_views(views, 6, RobotPose(np.array([1.0, 0.0, 6.0]), np.array([0.6, -0.3, 0.74])), seed=2)
    settings = RecognitionSettings(min_peak_attenuation=0.05)
    image = images["p"]
    log_bg = log_background(image, settings.background_scale_px, settings.dark_level)
    roi = Roi.full(image.shape)
    blobs = segment(image, log_bg, roi, settings)
    for blob in blobs:
        if not blob.touches_border:
            found = _compare(image, "p", settings, roi, blob.centroid_px, None)
            assert found is not None


def test_find_in_roi_takes_the_general_path_for_other_inputs(views: dict[str, object]) -> None:
    images = _rendered_views(views, 1, RobotPose(np.array([3.0, -4.0, 5.0]), np.array([0.3, 0.5, 0.81])), seed=1)
    settings = RecognitionSettings()
    image = images["q"]
    log_bg = log_background(image, settings.background_scale_px, settings.dark_level)
    strongest = next(b for b in segment(image, log_bg, None, settings) if not b.touches_border)
    w = strongest.window
    roi = Roi(max(w.x0 - 15, 0), max(w.y0 - 15, 0), min(w.x1 + 15, image.shape[1]), min(w.y1 + 15, image.shape[0]))
    fast = roi_search.find_in_roi(image, log_bg, roi, settings, strongest.centroid_px)
    # Float frames and a dense log B take segment + features: same blob, same features.
    for other_image, other_bg in ((image.astype(np.float32), log_bg), (image, np.asarray(log_bg))):
        slow = roi_search.find_in_roi(other_image, other_bg, roi, settings, strongest.centroid_px)
        assert fast is not None and slow is not None
        assert slow[0].centroid_px == pytest.approx(fast[0].centroid_px, abs=1e-4)
        np.testing.assert_allclose(slow[1].tips, fast[1].tips, atol=1e-3)
    paper = settings.model_copy(update={"estimator": "paper"})
    found = roi_search.find_in_roi(image, log_bg, roi, paper, strongest.centroid_px)
    assert found is not None and found[1].reach is None


@pytest.mark.parametrize("one_call_per_pair", [True, False])
def test_tracker_reuses_a_views_noise_sigma_and_measures_it_again_periodically(
        monkeypatch: pytest.MonkeyPatch, one_call_per_pair: bool) -> None:
    true_views = biplane_views(image_size=(256, 224), fov_mm=(80.0, 70.0))
    calibration = Calibration.from_views(*(View(n, v.K, v.dist, v.R, v.t, v.image_size)
                                           for n, v in sorted(true_views.items())))
    renderer = BiplaneRenderer(true_views, RobotBody(10.0, 2.0, 20.0, 1.0), settings=ImagingSettings(), seed=5)
    passed: list[tuple[str, float | None, float]] = []
    real = tracker_module.find_in_roi

    def spy(image, log_bg, roi, settings, predicted_px, *, sigma=None):  # type: ignore[no-untyped-def]
        found = real(image, log_bg, roi, settings, predicted_px, sigma=sigma)
        passed.append(("p" if len(passed) % 2 == 0 else "q", sigma, found[0].sigma if found else math.nan))
        return found

    real_pair = SteadyPair.search

    def pair_spy(self, image_p, image_q, bg_p, bg_q, centre, direction, half, outline_p, outline_q,  # type: ignore[no-untyped-def]
                 sigma_p, sigma_q, *rest):
        found = real_pair(self, image_p, image_q, bg_p, bg_q, centre, direction, half, outline_p, outline_q,
                          sigma_p, sigma_q, *rest)
        assert found
        used_p, used_q = self.sigmas()
        passed.extend([("p", sigma_p, used_p), ("q", sigma_q, used_q)])
        return found

    monkeypatch.setattr(tracker_module, "find_in_roi", spy)
    monkeypatch.setattr(SteadyPair, "search", pair_spy)
    monkeypatch.setattr(tracker_module, "NOISE_REMEASURE_FRAMES", 3)
    tracker = PostureTracker(calibration)
    if not one_call_per_pair:
        monkeypatch.setattr(tracker._pair, "usable", lambda *args: False)
    for n in range(8):
        t = 0.04 * n
        pose = RobotPose(np.array([-4.0 + 10.0 * t, 2.0, 3.0]), np.array([1.0, 0.3, 0.4]))
        pair = renderer.render(pose)
        assert tracker.process(pair.images["p"], pair.images["q"], frame=n, t=t).ok
        assert tracker.last_search == ("full" if n == 0 else "roi")
    # Frames 1..7 search ROIs: measured on frames 1, 4, 7, reused (the last measurement) on the others.
    assert len(passed) == 14
    rois = [passed[i:i + 2] for i in range(0, 14, 2)]
    for k, frame_calls in enumerate(rois):
        for view, sigma, used in frame_calls:
            if k % 3 == 0:
                assert sigma is None, (k, view)
            else:
                assert sigma is not None and used == sigma
                measured_on = rois[k - k % 3]
                assert sigma == next(u for v, _, u in measured_on if v == view)
    # A reset (new backgrounds) measures again on the first ROI frame.
    tracker.reset()
    passed.clear()
    for n in range(2):
        pair = renderer.render(RobotPose(np.array([0.0, 2.0, 3.0]), np.array([1.0, 0.3, 0.4])))
        tracker.process(pair.images["p"], pair.images["q"], frame=10 + n, t=0.5 + 0.04 * n)
    assert [s for _, s, _ in passed] == [None, None]


def test_roi_around_coordinates_equals_around_on_points() -> None:
    rng = np.random.default_rng(3)
    shape = (300, 260)
    cases = [rng.uniform(-80.0, 380.0, (3, 2)) for _ in range(300)]
    cases += [np.array([[5.0, 5.0], [np.nan, 7.0], [9.0, 9.0]]), np.array([[1.0, np.inf], [2.0, 3.0], [4.0, 5.0]])]
    boxes = 0
    for points in cases:
        for margin in (0.0, 2.5, 24.0):
            xs, ys = points[:, 0].tolist(), points[:, 1].tolist()
            got = Roi.around_coordinates(tuple(xs), tuple(ys), margin, shape)
            assert got == Roi.around(points, margin, shape)
            boxes += got is not None
    assert boxes > 500
