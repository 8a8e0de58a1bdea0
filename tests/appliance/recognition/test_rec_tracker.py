"""End to end on rendered biplane pairs (small images, noise and non-uniform field on): accuracy
within loose bounds, the epipolar-plane pose flagged, a lost robot reported honestly, and ROI
tracking over a short trajectory."""
from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from appliance.errors import InputDataError
from appliance.geometry import Calibration, View
from appliance.recognition import PostureTracker, RecognitionSettings, detect, log_background
from appliance.recognition.body_prior import BodyModel
from appliance.recognition.features import Features2D
from appliance.recognition.head_by_body import axial_rows, axial_rows_reference, chi2_of, chi2_of_reference
from appliance.recognition.reconstruction import Reconstruction, reconstruct
from appliance.recognition.tracker import head_claim_confidence
from appliance.recognition.segmentation import Blob, Roi, the_one_clean_view
from drivers.loopback.xray_render import (
    BiplaneRenderer,
    ImagingSettings,
    RobotBody,
    RobotPose,
    VesselPhantom,
    biplane_views,
)

RECORD_KEYS = {"frame", "t", "ok", "ambiguous", "centroid_mm", "direction", "tips_mm", "head_identified",
               "length_mm", "reprojection_px", "views", "reason"}


@pytest.fixture(scope="module")
def scene() -> tuple[Calibration, BiplaneRenderer]:
    true_views = biplane_views(image_size=(320, 280), fov_mm=(80.0, 70.0))
    calibration = Calibration.from_views(*(View(n, v.K, v.dist, v.R, v.t, v.image_size)
                                           for n, v in sorted(true_views.items())))
    vessel = VesselPhantom(np.array([[-40.0, 25.0, -20.0], [0.0, 20.0, -18.0], [40.0, 30.0, -22.0]]), 2.0, 0.06)
    body = RobotBody(10.0, 2.0, 20.0, 1.0)  # robot 1 of the seed paper
    renderer = BiplaneRenderer(true_views, body, vessel=vessel, settings=ImagingSettings(), seed=7)
    return calibration, renderer


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip(np.dot(a, b), -1.0, 1.0))))


@pytest.mark.parametrize("centroid,direction", [
    ((3.0, -4.0, 5.0), (0.3, 0.5, 0.81)),
    ((-8.0, 6.0, -3.0), (-0.7, 0.2, 0.68)),
    ((5.0, 5.0, 8.0), (0.1, -0.9, -0.42)),
])
def test_rendered_pose_is_recognised(scene: tuple[Calibration, BiplaneRenderer], centroid: tuple[float, ...],
                                     direction: tuple[float, ...]) -> None:
    calibration, renderer = scene
    pose = RobotPose(np.array(centroid), np.array(direction))
    pair = renderer.render(pose)
    posture = PostureTracker(calibration).process(pair.images["p"], pair.images["q"], frame=3, t=0.1)
    assert posture.ok and not posture.ambiguous, posture.reason
    assert np.linalg.norm(posture.centroid_mm - pose.centroid_mm) < 0.2
    assert posture.head_identified
    assert _angle_deg(posture.direction, pose.direction) < 2.0
    assert np.linalg.norm(posture.tips_mm[0] - pair.head_mm) < 0.6
    assert np.linalg.norm(posture.tips_mm[1] - pair.tail_mm) < 0.6
    assert posture.length_mm == pytest.approx(10.0, abs=1.0)
    record = json.loads(json.dumps(posture.to_record()))  # JSON-ready, plain types
    assert RECORD_KEYS <= set(record)
    assert record["frame"] == 3 and record["views"]["p"]["pixel_count"] > 50
    assert set(posture.timings_us) == {"segmentation", "features", "correspondence", "triangulation"}


def test_a_robot_much_shorter_than_the_tracker_s_body_is_lost_not_placed(
        scene: tuple[Calibration, BiplaneRenderer]) -> None:
    # The scene's robot is 10 mm long; a tracker told of a 30 mm body would place that body from a third of
    # it (a body length off) unless it refuses the rod as only part of its robot.
    calibration, renderer = scene
    pair = renderer.render(RobotPose(np.array([3.0, -4.0, 5.0]), np.array([0.3, 0.5, 0.81])))
    right = BodyModel(length_mm=10.0, centroid_from_tail_mm=4.4, cone_length_mm=5.7, diameter_mm=2.0)
    long = replace(right, length_mm=30.0, centroid_from_tail_mm=14.4)
    assert PostureTracker(calibration, body=right).process(pair.images["p"], pair.images["q"]).ok
    posture = PostureTracker(calibration, body=long).process(pair.images["p"], pair.images["q"])
    assert not posture.ok and posture.centroid_mm is None
    assert "against its 30 mm body" in posture.reason and "only part of the robot" in posture.reason


def test_a_robot_much_narrower_than_the_tracker_s_body_is_lost_not_placed(
        scene: tuple[Calibration, BiplaneRenderer]) -> None:
    # The scene's robot is 2 mm across; a tracker told of a 5 mm thick body of the same length must not take
    # the thin rod for it (a vessel stretch as thin was placed 27 mm from robot 6, seed 5266249).
    calibration, renderer = scene
    pair = renderer.render(RobotPose(np.array([3.0, -4.0, 5.0]), np.array([0.3, 0.5, 0.81])))
    right = BodyModel(length_mm=10.0, centroid_from_tail_mm=4.4, cone_length_mm=5.7, diameter_mm=2.0)
    thick = replace(right, diameter_mm=5.0)
    assert PostureTracker(calibration, body=right).process(pair.images["p"], pair.images["q"]).ok
    posture = PostureTracker(calibration, body=thick).process(pair.images["p"], pair.images["q"])
    assert not posture.ok and posture.centroid_mm is None
    assert "against the robot's 5 mm diameter" in posture.reason, posture.reason


def test_paper_estimator_runs_end_to_end(scene: tuple[Calibration, BiplaneRenderer]) -> None:
    calibration, renderer = scene
    pose = RobotPose(np.array([3.0, -4.0, 5.0]), np.array([0.3, 0.5, 0.81]))
    pair = renderer.render(pose)
    tracker = PostureTracker(calibration, RecognitionSettings(estimator="paper"))
    posture = tracker.process(pair.images["p"], pair.images["q"])
    assert posture.ok and not posture.head_identified
    assert np.linalg.norm(posture.centroid_mm - pose.centroid_mm) < 1.0
    assert min(_angle_deg(posture.direction, pose.direction), _angle_deg(-posture.direction, pose.direction)) < 6.0


def test_epipolar_plane_pose_is_flagged_then_resolved_from_history(scene: tuple[Calibration, BiplaneRenderer]) -> None:
    calibration, renderer = scene
    tracker = PostureTracker(calibration)
    # A horizontal robot at the sources' height lies in an epipolar plane; symmetric ends (head not
    # used) would leave the two mirror solutions; the cone may still resolve it, but never silently.
    flat = RobotPose(np.array([2.0, 1.0, 0.0]), np.array([0.6, 0.8, 0.0]))
    pair = renderer.render(flat)
    posture = tracker.process(pair.images["p"], pair.images["q"], frame=0, t=0.0)
    assert posture.ok and posture.ambiguous
    assert "epipolar plane" in posture.reason
    if posture.direction is None:
        assert posture.direction_candidates is not None and posture.tips_mm is None
        assert posture.to_record()["direction"] is None
    else:
        assert _angle_deg(posture.direction, flat.direction) < 5.0
    # Coming from a tilted pose, the tracker resolves the same degenerate view from history.
    tracker.reset()
    tilted = RobotPose(np.array([2.0, 1.0, 0.0]), np.array([0.6, 0.8, 0.25]))
    pair = renderer.render(tilted)
    assert tracker.process(pair.images["p"], pair.images["q"], frame=1, t=0.0).ok
    pair = renderer.render(flat)
    posture = tracker.process(pair.images["p"], pair.images["q"], frame=2, t=0.04)
    assert posture.ok and posture.ambiguous and posture.direction is not None
    assert _angle_deg(posture.direction, flat.direction) < 5.0


def test_empty_frame_is_lost_with_a_reason_and_no_numbers(scene: tuple[Calibration, BiplaneRenderer]) -> None:
    calibration, renderer = scene
    pair = renderer.render(None)
    posture = PostureTracker(calibration).process(pair.images["p"], pair.images["q"], frame=9, t=0.3)
    record = posture.to_record()
    assert record["ok"] is False and record["reason"]
    for key in ("centroid_mm", "direction", "tips_mm", "length_mm", "reprojection_px"):
        assert record[key] is None


def test_roi_tracking_stays_locked_over_a_trajectory(scene: tuple[Calibration, BiplaneRenderer]) -> None:
    calibration, renderer = scene
    tracker = PostureTracker(calibration)
    searches = []
    for n in range(8):
        t = 0.04 * n
        centre = np.array([-5.0 + 12.0 * t, 2.0 - 6.0 * t, 3.0 + 4.0 * t])  # ~15 mm/s
        direction = np.array([math.cos(0.4 + t), math.sin(0.4 + t), 0.5])
        pose = RobotPose(centre, direction)
        pair = renderer.render(pose)
        posture = tracker.process(pair.images["p"], pair.images["q"], frame=n, t=t)
        searches.append(tracker.last_search)
        assert posture.ok, posture.reason
        assert np.linalg.norm(posture.centroid_mm - pose.centroid_mm) < 0.2
        assert _angle_deg(posture.direction, pose.direction) < 2.0
    assert searches[0] == "full" and set(searches[1:]) == {"roi"}


def test_lost_robot_falls_back_to_full_frame_and_recovers(scene: tuple[Calibration, BiplaneRenderer]) -> None:
    calibration, renderer = scene
    tracker = PostureTracker(calibration)
    pose = RobotPose(np.array([0.0, 0.0, 0.0]), np.array([0.2, 0.3, 0.93]))
    pair = renderer.render(pose)
    assert tracker.process(pair.images["p"], pair.images["q"], frame=0, t=0.0).ok
    empty = renderer.render(None)
    lost = tracker.process(empty.images["p"], empty.images["q"], frame=1, t=0.04)
    assert not lost.ok and tracker.last_search == "full"
    jumped = RobotPose(np.array([15.0, -10.0, 6.0]), np.array([0.2, 0.3, 0.93]))
    pair = renderer.render(jumped)
    found = tracker.process(pair.images["p"], pair.images["q"], frame=2, t=0.08)
    assert found.ok and np.linalg.norm(found.centroid_mm - jumped.centroid_mm) < 0.2


def test_wrong_image_size_is_an_input_error(scene: tuple[Calibration, BiplaneRenderer]) -> None:
    calibration, _ = scene
    tracker = PostureTracker(calibration)
    good = np.zeros((280, 320), np.uint16)
    with pytest.raises(InputDataError, match=r"frame 4, view q: image is 300x280 px but the calibration says 320x280"):
        tracker.process(good, np.zeros((280, 300), np.uint16), frame=4)


def test_head_of_a_cone_heavy_robot_seen_end_on_in_one_view(scene: tuple[Calibration, BiplaneRenderer]) -> None:
    """Robot 6 (30 mm, half of it cone) along q's line of sight: q squeezes the cone's ramp into the
    body's blurred end and may vote for the wrong head; p, seeing it side-on, must decide, and the
    head's tip must then be at the cone's apex (the flat-end model puts it ~10 mm short)."""
    from appliance.robots import load_robots

    calibration, _ = scene
    spec = load_robots()[6]
    true_views = biplane_views(image_size=(320, 280), fov_mm=(80.0, 70.0))
    renderer = BiplaneRenderer(true_views, RobotBody(spec.length_mm, spec.diameter_mm, spec.tip_angle_deg,
                                                     spec.attenuation_per_mm), settings=ImagingSettings(), seed=11)
    ray_q = calibration.q.source_mm / np.linalg.norm(calibration.q.source_mm)
    side = np.cross(ray_q, [0.0, 0.0, 1.0])
    unpreferred_right = 0
    for tilt in (0.1, 0.14):  # 6-8 degrees off q's central ray
        for sign in (1.0, -1.0):
            direction = sign * (ray_q + tilt * side + 0.5 * tilt * np.array([0.0, 0.0, 1.0]))
            pose = RobotPose((2.0, -1.0, 1.0), direction / np.linalg.norm(direction))
            pair = renderer.render(pose)
            results = {}
            for foreshortening in (0.5, 1e-6):  # the default, and the side-on view's vote not preferred
                tracker = PostureTracker(calibration, RecognitionSettings(
                    dark_level=ImagingSettings().dark_level, head_foreshortening=foreshortening))
                posture = tracker.process(pair.images["p"], pair.images["q"], frame=0, t=0.0)
                assert posture.ok
                results[foreshortening] = (posture.head_identified
                                           and float(np.dot(posture.direction, pose.direction)) > 0.99
                                           and float(np.linalg.norm(posture.tips_mm[0] - pair.head_mm)) < 0.6)
            assert results[0.5], f"tilt {tilt}, sign {sign}: head or its tip wrong"
            unpreferred_right += results[1e-6]
    # Without preferring the side-on view, some of these poses lose the head (the test can fail).
    assert unpreferred_right < 4
    # Closer to q's ray (3-4 degrees) q's tips are rims of the end faces: the axis may be a few degrees
    # off, but then the frame must say so (no silent failure).
    for sign in (1.0, -1.0):
        direction = sign * (ray_q + 0.06 * side + 0.03 * np.array([0.0, 0.0, 1.0]))
        pose = RobotPose((2.0, -1.0, 1.0), direction / np.linalg.norm(direction))
        pair = renderer.render(pose)
        posture = PostureTracker(calibration, RecognitionSettings(dark_level=ImagingSettings().dark_level)).process(
            pair.images["p"], pair.images["q"], frame=0, t=0.0)
        assert posture.ok and posture.direction is not None
        error = math.degrees(math.acos(min(1.0, abs(float(np.dot(posture.direction, pose.direction))))))
        assert posture.ambiguous or error <= 5.0, f"silent axis error {error:.1f} deg"


def _blob(width_px: float, clutter: float = 0.0) -> Blob:
    return Blob(window=Roi(0, 0, 4, 4), weights=np.zeros((4, 4), np.float32), mask=np.zeros((4, 4), bool),
                pixel_count=10, peak=1.0, baseline=0.0, sigma=0.01, strength=10.0, centroid_px=(2.0, 2.0),
                touches_border=False, width_px=width_px, clutter=clutter)


def test_pairs_with_a_blob_narrower_than_any_body_are_dropped(scene: tuple[Calibration, BiplaneRenderer]) -> None:
    calibration, _ = scene
    tracker = PostureTracker(calibration)
    floor = tracker.settings.min_body_width_px
    candidates = {"p": [_blob(7.0), _blob(1.0)], "q": [_blob(1.0), _blob(6.5), _blob(floor)]}
    pairs = [(0, 0, 0.3), (0, 1, 0.2), (1, 1, 0.1), (0, 2, 0.4), (1, 0, 0.1)]
    assert tracker._bodies_only(pairs, candidates) == [(0, 1, 0.2), (0, 2, 0.4)]


def test_the_thinnest_robot_at_a_small_image_is_wider_than_the_body_floor() -> None:
    # Robot 7 (1 mm) on the simulated bench's smallest views (256 x 224 px, ~0.4 mm per pixel): its blob's
    # width is still above min_body_width_px, in both views, from several directions.
    true_views = biplane_views(image_size=(256, 224), elevation_deg=15.0)
    calibration = Calibration.from_views(*(View(n, v.K, v.dist, v.R, v.t, v.image_size)
                                           for n, v in sorted(true_views.items())))
    settings = RecognitionSettings(dark_level=ImagingSettings().dark_level)
    renderer = BiplaneRenderer(true_views, RobotBody(8.0, 1.0, 20.0, 1.0), settings=ImagingSettings(), seed=3)
    widths = []
    for direction in ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.6, 0.6, 0.5), (0.3, -0.8, 0.5)):
        pair = renderer.render(RobotPose(np.array([2.0, -3.0, 1.0]), np.array(direction) / np.linalg.norm(direction)))
        for name in ("p", "q"):
            background = log_background(pair.images[name], settings.background_scale_px, settings.dark_level)
            blobs = detect(pair.images[name], background, settings)
            assert blobs, (direction, name)
            widths.append(max(blob.width_px for blob in blobs))
    assert min(widths) >= settings.min_body_width_px, widths


def _rod_features(calibration: Calibration, centre: np.ndarray, direction: np.ndarray, length_mm: float,
                  head_at_head: dict[str, bool]) -> dict[str, Features2D]:
    """Both views' features of a rod (head at ``centre + length/2 direction``), tip 0 its head's image,
    each view claiming the head at the true end or at the other one (``head_at_head``)."""
    feats = {}
    for name in ("p", "q"):
        view = calibration.views[name]
        head, tail, middle = view.project(np.vstack([centre + 0.5 * length_mm * direction,
                                                     centre - 0.5 * length_mm * direction, centre]))
        axis = (head - tail) / np.linalg.norm(head - tail)
        half = 0.5 * float(np.linalg.norm(head - tail))
        feats[name] = Features2D(middle, axis, (half * half / 3.0, 1.0), np.vstack([head, tail]), 200,
                                 0 if head_at_head[name] else 1, axis_sigma_rad=0.002)
    return feats


@pytest.mark.parametrize("clutter_p, clutter_q, expected", [(0.0, 0.3, 1.0), (0.3, 0.0, -1.0), (0.3, 0.3, None),
                                                             (0.0, 0.0, None)])
def test_the_clean_view_tells_the_head_when_a_cluttered_view_disagrees(
        scene: tuple[Calibration, BiplaneRenderer], clutter_p: float, clutter_q: float, expected: float | None) -> None:
    # View p claims the true head, q the other end: where only q is cluttered p's claim is taken (the
    # direction points to the head), where only p is, q's (wrong here, and taken all the same: the rule
    # trusts the clean view); with both views clean or both cluttered the head stays unidentified.
    calibration, _ = scene
    tracker = PostureTracker(calibration)
    direction = np.array([0.6, 0.3, 0.74])
    direction /= np.linalg.norm(direction)
    centre = np.array([2.0, -1.0, 3.0])
    feats = _rod_features(calibration, centre, direction, 10.0, {"p": True, "q": False})
    blobs = {"p": _blob(7.0, clutter_p), "q": _blob(7.0, clutter_q)}
    first = reconstruct(calibration, tracker.F, feats["p"], feats["q"], tracker.settings)
    assert not first.head_identified and first.direction is not None
    rec = tracker._head_by_clean_view(first, blobs, feats, None)
    if expected is None:
        assert rec is first
        return
    assert rec.head_identified
    assert float(np.dot(rec.direction, direction)) == pytest.approx(expected, abs=1e-3)
    assert any("the head is view" in reason for reason in rec.reasons)


def test_head_claim_confidence_counts_both_views_and_is_lowered_by_clutter() -> None:
    def feat(ramps: tuple[float, float]) -> Features2D:
        return Features2D(np.zeros(2), np.array([1.0, 0.0]), (10.0, 1.0), np.zeros((2, 2)), 50, None, ramps)

    claim = {"p": (feat((8.0, 2.0)), 0.0, 0), "q": (feat((3.0, 3.0)), 0.0, 0)}
    clean = head_claim_confidence(claim, 0.5)
    assert clean == pytest.approx(6.0 / 0.5)
    cluttered = head_claim_confidence({**claim, "p": (feat((8.0, 2.0)), 0.3, 0)}, 0.5)
    assert cluttered == pytest.approx(6.0 / (0.5 + 0.3 * 8.0))
    # The other view's profile leaning towards the other end takes confidence away.
    against = head_claim_confidence({**claim, "q": (feat((3.0, 4.0)), 0.0, 0)}, 0.5)
    assert against == pytest.approx(clean - 2.0)


def _assert_head_claim_withheld(rec: Reconstruction, first: Reconstruction, withheld: bool, reason: str) -> None:
    """``rec`` (the doubt rule applied to ``first``) is ``first`` itself, or, when ``withheld``, ``first`` with
    the head unclaimed in every view, the same tips and direction, and ``reason`` among its reasons."""
    if not withheld:
        assert rec is first
        return
    assert not rec.head_identified
    assert all(feat.head_index is None for feat in rec.view_features.values())
    assert np.array_equal(rec.tips, first.tips) and np.array_equal(rec.direction, first.direction)
    assert any(reason in line for line in rec.reasons)


@pytest.mark.parametrize("clutter_p, ramps_p, ramps_q, withheld", [
    (0.3, (8.0, 5.0), (2.7, 3.9), True),     # weak, over a vessel, the clean view leaning the other way
    (0.3, (20.0, 2.5), (3.0, 3.2), False),   # a clear cone and step over the vessel, the other view level
    (0.0, (8.0, 5.0), (2.7, 3.9), False),    # a clean view's claim is not this rule's to withhold
])
def test_a_weak_head_claim_by_one_cluttered_view_is_withheld(
        scene: tuple[Calibration, BiplaneRenderer], clutter_p: float, ramps_p: tuple[float, float],
        ramps_q: tuple[float, float], withheld: bool) -> None:
    calibration, _ = scene
    tracker = PostureTracker(calibration)
    direction = np.array([0.6, 0.3, 0.74])
    direction /= np.linalg.norm(direction)
    feats = _rod_features(calibration, np.array([2.0, -1.0, 3.0]), direction, 10.0, {"p": True, "q": True})
    feats = {"p": replace(feats["p"], ramp_px=ramps_p), "q": replace(feats["q"], ramp_px=ramps_q, head_index=None)}
    blobs = {"p": _blob(7.0, clutter_p), "q": _blob(7.0, 0.0)}
    first = reconstruct(calibration, tracker.F, feats["p"], feats["q"], tracker.settings)
    assert first.head_identified
    _assert_head_claim_withheld(tracker._head_in_doubt(first, blobs, feats), first, withheld,
                                "the head is not claimed: only view p")


def _body_features(calibration: Calibration, centre: np.ndarray, direction: np.ndarray, body: BodyModel,
                   cone_at_plus: dict[str, bool]) -> dict[str, Features2D]:
    """Both views' features of the known body (head at ``centre + (L - c) direction``, ``centre`` its volume
    centroid), no head claimed: per view its ends' reaches at the levels as the profile has them, the
    cone's where the profile of a cone falls (``sqrt`` of the level times the cone from the apex), the
    tail's a blurred step (the 0.2 level 0.3 px beyond its half height, the 0.8 level 0.3 px inside).
    ``cone_at_plus``: the cone's reaches at the +direction end (the truth), or the tail's at both ends."""
    to_head, to_tail, cone = body.length_mm - body.centroid_from_tail_mm, body.centroid_from_tail_mm, body.cone_length_mm
    levels = (0.2, 0.25, 0.5, 0.64, 0.8)
    feats = {}
    for name in ("p", "q"):
        view = calibration.views[name]
        points = [centre, centre + to_head * direction, centre - to_tail * direction]
        points += [centre + (to_head - math.sqrt(level) * cone) * direction for level in levels]
        uv = view.project(np.vstack(points))
        middle, axis = uv[0], (uv[1] - uv[2]) / np.linalg.norm(uv[1] - uv[2])
        tail = float(np.dot(uv[2] - middle, -axis))
        step = {level: tail + 0.3 * (0.5 - level) / 0.3 for level in levels}
        cone_reach = {level: float(np.dot(uv[3 + k] - middle, axis)) for k, level in enumerate(levels)}
        reach = (cone_reach if cone_at_plus[name] else dict(step), step)
        ramps = (reach[0][0.2] - reach[0][0.8], reach[1][0.2] - reach[1][0.8])
        feat = Features2D(middle, axis, (100.0, 1.0), np.vstack([uv[1], uv[2]]), 200, None, ramps, reach,
                          axis_sigma_rad=0.002)
        feats[name] = feat.with_head(None)
    return feats


@pytest.fixture(scope="module")
def robot3() -> BodyModel:
    from appliance.robots import load_robots

    return BodyModel.of(load_robots()[3])


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_the_known_body_tells_the_head_the_ramps_left_unidentified(
        scene: tuple[Calibration, BiplaneRenderer], robot3: BodyModel, sign: float) -> None:
    # Robot 3's cone seen in both views, but neither view claims it (foreshortened, or its ramp over a
    # vessel): measured as the apex, the cone's end puts the body where its centroid and tail do, the
    # other end (a step) a cone's worth off; the head is claimed and its tip placed at the apex.
    calibration, _ = scene
    tracker = PostureTracker(calibration, body=robot3)
    direction = sign * np.array([0.6, 0.3, 0.74]) / np.linalg.norm([0.6, 0.3, 0.74])
    centre = np.array([2.0, -1.0, 3.0])
    feats = _body_features(calibration, centre, direction, robot3, {"p": True, "q": True})
    blobs = {"p": _blob(8.0), "q": _blob(8.0)}
    first = reconstruct(calibration, tracker.F, feats["p"], feats["q"], tracker.settings)
    assert not first.head_identified and first.direction is not None
    rec = tracker._head_by_body(first, blobs, feats, None)
    assert rec.head_identified
    assert float(np.dot(rec.direction, direction)) > 0.999
    apex = centre + (robot3.length_mm - robot3.centroid_from_tail_mm) * direction
    assert np.linalg.norm(rec.tips[0] - apex) < 0.3
    assert any("told by the body's shape" in reason for reason in rec.reasons)


@pytest.mark.parametrize("sign", [1.0, -1.0])
@pytest.mark.parametrize("orients", [True, False])
def test_a_head_the_body_tells_is_kept_where_the_claimed_redo_fails_its_checks(
        scene: tuple[Calibration, BiplaneRenderer], robot3: BodyModel, sign: float, orients: bool) -> None:
    # The body's fit decides the head the ramps left unidentified, but the reconstruction redone with both views
    # claiming it fails the tracker's checks (here every head-claimed frame is refused; on J seed 2302585 robot 6
    # pose 26 view p's cone was cut by a vessel ending under it, its extrapolated apex reprojected 5.1 px off):
    # the first reconstruction is kept with the head where the fit put it, its ends as measured, the reason
    # given. Without that (the setting off) the head stays unidentified and the body prior puts the tips half
    # the body either side of its place, each off by the body's offset asymmetry.
    calibration, _ = scene
    tracker = PostureTracker(calibration, RecognitionSettings(head_body_orients_unclaimed=orients), body=robot3)
    tracker._rejection = lambda rec, *_: "refused" if rec.head_identified else None  # type: ignore[method-assign]
    direction = sign * np.array([0.6, 0.3, 0.74]) / np.linalg.norm([0.6, 0.3, 0.74])
    feats = _body_features(calibration, np.array([2.0, -1.0, 3.0]), direction, robot3, {"p": True, "q": True})
    first = reconstruct(calibration, tracker.F, feats["p"], feats["q"], tracker.settings)
    assert not first.head_identified and first.direction is not None
    rec = tracker._head_by_body(first, {"p": _blob(8.0), "q": _blob(8.0)}, feats, None)
    if not orients:
        assert rec is first
        return
    assert rec.head_identified and float(np.dot(rec.direction, direction)) > 0.999
    flipped = float(np.dot(first.direction, direction)) < 0
    assert np.array_equal(rec.tips, first.tips[::-1] if flipped else first.tips)   # the ends as measured
    for name in ("p", "q"):
        head_px = rec.view_tips[name][0]
        assert np.array_equal(rec.view_features[name].tips[rec.view_features[name].head_index], head_px)
    assert any("its ends kept as measured" in reason for reason in rec.reasons)


@pytest.mark.parametrize("clean_view_chi2, clean_claims_head, told",
                         [(9.0, True, True), (1e6, True, False), (9.0, False, False)])
def test_a_clean_view_s_claim_the_body_leans_to_decides_between_disagreeing_views(
        scene: tuple[Calibration, BiplaneRenderer], robot3: BodyModel, clean_view_chi2: float,
        clean_claims_head: bool, told: bool) -> None:
    # The views' claims disagree, one view over a vessel; the body's fit leans to the head's end, here short of
    # decisive (head_body_chi2 out of reach). Where the clean view claims that end, the two agree and the head is
    # taken there (study seed 110 robot 6 pose 1: the fit 6.9 against 22.5, the clean view q with it; tips 5.6 mm
    # off with the head unidentified); where the clean view claims the other end, or the margin is below
    # head_body_clean_view_chi2, the head stays unidentified.
    calibration, _ = scene
    settings = RecognitionSettings(head_body_chi2=1e6, head_body_clean_view_chi2=clean_view_chi2)
    tracker = PostureTracker(calibration, settings, body=robot3)
    direction = np.array([0.6, 0.3, 0.74]) / np.linalg.norm([0.6, 0.3, 0.74])
    feats = _body_features(calibration, np.array([2.0, -1.0, 3.0]), direction, robot3, {"p": True, "q": True})
    claim = 0 if clean_claims_head else 1   # tips[0] is the +direction end, the head
    feats["q"] = feats["q"].with_head(claim)   # q clean, p over a vessel claiming the other end
    feats["p"] = feats["p"].with_head(1 - claim)
    first = reconstruct(calibration, tracker.F, feats["p"], feats["q"], tracker.settings)
    assert not first.head_identified and first.direction is not None
    blobs = {"q": _blob(8.0), "p": _blob(8.0, 0.2)}
    rec = tracker._head_by_body(first, blobs, feats, None)
    if not told:
        assert rec is first
        return
    assert rec.head_identified and float(np.dot(rec.direction, direction)) > 0.999
    assert any("told by the body's shape" in reason for reason in rec.reasons)


def test_ends_that_do_not_tell_the_cone_leave_the_head_unidentified(
        scene: tuple[Calibration, BiplaneRenderer], robot3: BodyModel) -> None:
    # Both ends steps (the cone's ramp lost in one view and the other view foreshortened, say): neither
    # order fits decisively better, and the head is not guessed.
    calibration, _ = scene
    tracker = PostureTracker(calibration, body=robot3)
    direction = np.array([0.6, 0.3, 0.74]) / np.linalg.norm([0.6, 0.3, 0.74])
    feats = _body_features(calibration, np.array([2.0, -1.0, 3.0]), direction, robot3, {"p": False, "q": False})
    first = reconstruct(calibration, tracker.F, feats["p"], feats["q"], tracker.settings)
    assert not first.head_identified
    assert tracker._head_by_body(first, {"p": _blob(8.0), "q": _blob(8.0)}, feats, None) is first


@pytest.mark.parametrize("clutter_p, both_claim, overruled",
                         [(0.2, False, True), (0.0, False, True), (0.2, True, True), (0.0, True, False)])
def test_a_claim_at_the_wrong_end_over_a_vessel_is_overruled_by_the_known_body(
        scene: tuple[Calibration, BiplaneRenderer], robot3: BodyModel, clutter_p: float, both_claim: bool,
        overruled: bool) -> None:
    # View p claims the tail (a vessel there made its profile sag into a long "ramp"); the ends measured
    # by the body's shape put the head at the other end, decisively: over the vessel the claim is
    # replaced, and so is a claim by view p alone below max_clutter (a vessel alongside the tail does not
    # always raise the clutter: study seed 4040404, robot 2, pose 26, clutter 0.12); a claim by both views,
    # both clean, is not this rule's to overrule.
    calibration, _ = scene
    tracker = PostureTracker(calibration, body=robot3)
    direction = np.array([0.6, 0.3, 0.74]) / np.linalg.norm([0.6, 0.3, 0.74])
    feats = _body_features(calibration, np.array([2.0, -1.0, 3.0]), direction, robot3, {"p": True, "q": True})
    feats["p"] = feats["p"].with_head(1)
    if both_claim:
        feats["q"] = feats["q"].with_head(1)
    first = reconstruct(calibration, tracker.F, feats["p"], feats["q"], tracker.settings)
    assert first.head_identified and float(np.dot(first.direction, direction)) < -0.999
    rec = tracker._head_by_body(first, {"p": _blob(8.0, clutter_p), "q": _blob(8.0)}, feats, None)
    if not overruled:
        assert rec is first
        return
    assert rec.head_identified and float(np.dot(rec.direction, direction)) > 0.999


@pytest.mark.parametrize("doubt_chi2, withdrawn", [(9.0, True), (1e6, False)])
def test_a_claim_the_body_leans_against_not_decisively_is_withdrawn_not_flipped(
        scene: tuple[Calibration, BiplaneRenderer], robot3: BodyModel, doubt_chi2: float, withdrawn: bool) -> None:
    # View p, over a vessel, claims the tail; the body's fit puts the head at the other end, here made short of
    # decisive (head_body_chi2 out of reach): the claim is not flipped, but it is withdrawn, the frame redone with
    # neither view claiming the head and the reason given (seed 7757247 robot 7 pose 17: a wrong claim, the fit
    # 16.5 against it, tips 9.9 and 6.1 mm off; withdrawn, 0.73). Below head_body_doubt_chi2 the claim stands.
    calibration, _ = scene
    settings = RecognitionSettings(head_body_chi2=1e6, head_body_doubt_chi2=doubt_chi2)
    tracker = PostureTracker(calibration, settings, body=robot3)
    direction = np.array([0.6, 0.3, 0.74]) / np.linalg.norm([0.6, 0.3, 0.74])
    feats = _body_features(calibration, np.array([2.0, -1.0, 3.0]), direction, robot3, {"p": True, "q": True})
    feats["p"] = feats["p"].with_head(1)
    first = reconstruct(calibration, tracker.F, feats["p"], feats["q"], tracker.settings)
    assert first.head_identified and float(np.dot(first.direction, direction)) < -0.999
    rec = tracker._head_by_body(first, {"p": _blob(8.0, 0.2), "q": _blob(8.0)}, feats, None)
    if not withdrawn:
        assert rec is first
        return
    assert not rec.head_identified and rec.direction is not None
    assert all(feat.head_index is None for feat in rec.view_features.values())
    assert any("the head is not claimed: the body's shape puts it at the other end" in r for r in rec.reasons)


def test_a_measurement_far_off_counts_no_more_than_the_cap() -> None:
    # Two measurements agree, one is 10 sigmas off: the place is where the two are, and the outlier adds
    # the cap squared, not 100 (nor does it pull the place towards itself).
    rows = [(0.0, 1.0, 0.0), (0.0, 1.0, 0.0), (10.0, 1.0, 0.0)]
    for chi2 in (chi2_of, chi2_of_reference):
        assert chi2(rows, 4.0) == pytest.approx(16.0)
        assert chi2(rows, 100.0) == pytest.approx(2 * (10.0 / 3) ** 2 + (20.0 / 3) ** 2)


@pytest.mark.parametrize("sign, cone_at_plus, clutter_p", [(1.0, True, 0.0), (-1.0, True, 0.3), (1.0, False, 0.1)])
def test_the_compiled_axial_rows_are_the_numpy_definitions(
        scene: tuple[Calibration, BiplaneRenderer], robot3: BodyModel, sign: float, cone_at_plus: bool,
        clutter_p: float) -> None:
    # The compiled rows and chi-squares (the tracker's path) against head_by_body's numpy definitions: the same
    # rows to rounding (the rays summed in another order), the same +direction ends, the same chi-squares; and
    # the warm-ups compiled the calls the tracker makes (none compiles inside the loop's window).
    from appliance.compiled import warm_up_all
    from appliance.recognition import head_kernels

    warm_up_all()
    compiled = (len(head_kernels.axial_rows.signatures), len(head_kernels.chi2_of.signatures))
    calibration, _ = scene
    direction = sign * np.array([0.6, 0.3, 0.74]) / np.linalg.norm([0.6, 0.3, 0.74])
    centre = np.array([2.0, -1.0, 3.0])
    feats = _body_features(calibration, centre, direction, robot3, {"p": cone_at_plus, "q": True})
    clutter = {"p": clutter_p, "q": 0.05}
    # (an axis a little off the truth, as a reconstruction's: the rows are not all at their offsets)
    off = direction + np.array([0.01, -0.02, 0.0])
    off /= np.linalg.norm(off)
    plus, minus, plus_index = axial_rows(calibration, centre + 0.1, off, feats, clutter, robot3)
    ref_plus, ref_minus, ref_index = axial_rows_reference(calibration, centre + 0.1, off, feats, clutter, robot3)
    assert plus_index == ref_index
    np.testing.assert_allclose(plus, np.asarray(ref_plus), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(minus, np.asarray(ref_minus), rtol=1e-12, atol=1e-12)
    for rows, ref in ((plus, ref_plus), (minus, ref_minus)):
        for cap in (2.0, 4.0, 100.0):
            assert chi2_of(ref, cap) == chi2_of_reference(ref, cap)
            assert chi2_of(rows, cap) == pytest.approx(chi2_of_reference(ref, cap), rel=1e-10)
    assert (len(head_kernels.axial_rows.signatures), len(head_kernels.chi2_of.signatures)) == compiled


@pytest.mark.parametrize("robot_id,along", [(6, True), (3, False), (1, False), (4, False)])
def test_wide_robot_has_its_background_interpolated_along_structure(scene: tuple[Calibration, BiplaneRenderer],
                                                                    robot_id: int, along: bool) -> None:
    """Robot 6 (5 mm) is as wide as the vessels it crosses: its tracker turns the along-structure fill on;
    the thinner robots keep the default, and so do the paper's estimator, a tracker without a robot and one
    with the body prior off (the model-free pipeline)."""
    from appliance.robots import load_robots

    calibration, _ = scene
    spec = load_robots()[robot_id]
    given = RecognitionSettings()
    tracker = PostureTracker(calibration, given, body=spec)
    assert tracker.settings.background_along_structure is along
    # Nothing else changes (but a stubby body's end-on planes, test_nearly_end_on_view.py), and the caller's
    # settings are left as they were.
    assert tracker.settings.model_copy(update={"background_along_structure": False,
                                               "end_on_plane_max_sigma_deg": None}) == given
    assert not given.background_along_structure
    assert not PostureTracker(calibration, RecognitionSettings(estimator="paper"),
                              body=spec).settings.background_along_structure
    assert not PostureTracker(calibration, given).settings.background_along_structure
    assert not PostureTracker(calibration, RecognitionSettings(body_prior=False),
                              body=spec).settings.background_along_structure
    narrow = RecognitionSettings(along_structure_min_diameter_mm=spec.diameter_mm + 0.5)
    assert not PostureTracker(calibration, narrow, body=spec).settings.background_along_structure


def test_the_heading_a_claim_is_checked_against_comes_from_frames_whose_head_was_identified(
        scene: tuple[Calibration, BiplaneRenderer]) -> None:
    # A frame whose head is not identified has a direction of arbitrary sign (a cold frame's, a withdrawn
    # claim's): remembered as the heading, it had the next frame's head claim over a vessel rejected as "180 deg
    # away from the tracked heading" (seed 7757247 robot 7 pose 17, tracked). The heading is the last identified
    # one, carried through unclaimed frames with its sign, and there is none before a head is identified.
    calibration, _ = scene
    tracker = PostureTracker(calibration)
    direction = np.array([0.6, 0.3, 0.74]) / np.linalg.norm([0.6, 0.3, 0.74])
    centre = np.array([2.0, -1.0, 3.0])
    blobs = {"p": _blob(7.0, 0.3), "q": _blob(7.0)}   # view p over another structure: the frame is in doubt

    def claimed(at_head: bool):
        feats = _rod_features(calibration, centre, direction, 10.0, {"p": at_head, "q": True})
        feats["q"] = replace(feats["q"], head_index=None)
        rec = reconstruct(calibration, tracker.F, feats["p"], feats["q"], tracker.settings)
        assert rec.head_identified and float(np.dot(rec.direction, direction)) == pytest.approx(
            1.0 if at_head else -1.0, abs=1e-3)
        return rec, feats

    right, feats = claimed(True)
    wrong, _ = claimed(False)
    # The same frame, its head not identified, the direction's sign the other way.
    unclaimed = replace(right, head_identified=False, direction=-right.direction, tips=right.tips[::-1].copy())

    def remember(rec) -> None:
        tracker._remember(tracker._posture(0, 0.0, rec, blobs))

    def heading_rejects(rec) -> bool:
        reason = tracker._rejection(rec, blobs, feats, tracker._track.direction)
        return reason is not None and "tracked heading" in reason

    remember(unclaimed)
    assert not heading_rejects(right) and not heading_rejects(wrong)
    assert tracker._track.heading is None
    remember(right)
    assert not heading_rejects(right) and heading_rejects(wrong)
    remember(unclaimed)   # carried through with the identified heading's sign
    assert float(np.dot(tracker._track.heading, direction)) > 0.999
    assert not heading_rejects(right) and heading_rejects(wrong)


@pytest.mark.parametrize("length_mm, withheld", [(31.3, True), (19.0, False), (12.0, True), (21.0, False)])
def test_a_claim_by_one_cluttered_view_whose_ends_are_not_the_body_s_length_apart_is_withheld(
        scene: tuple[Calibration, BiplaneRenderer], robot3: BodyModel, length_mm: float, withheld: bool) -> None:
    # View p, over a vessel, claims the head with a clear ramp (it would stand on its confidence), but its blob
    # ran on into the vessel: the ends are 31.3 mm apart against robot 3's 19 mm, and the "ramp" is the vessel's
    # (seed 3162277 robot 3 pose 5: a wrong claim, axis 176 deg off, tips 23 and 15 mm). Within
    # head_claim_max_length_error of the body's length the claim stands.
    calibration, _ = scene
    tracker = PostureTracker(calibration, body=robot3)
    direction = np.array([0.6, 0.3, 0.74]) / np.linalg.norm([0.6, 0.3, 0.74])
    feats = _rod_features(calibration, np.array([2.0, -1.0, 3.0]), direction, length_mm, {"p": True, "q": True})
    feats = {"p": replace(feats["p"], ramp_px=(20.0, 2.5)), "q": replace(feats["q"], ramp_px=(3.0, 3.2), head_index=None)}
    blobs = {"p": _blob(7.0, 0.3), "q": _blob(7.0, 0.0)}
    first = reconstruct(calibration, tracker.F, feats["p"], feats["q"], tracker.settings)
    assert first.head_identified and first.length_mm == pytest.approx(length_mm, rel=1e-3)
    _assert_head_claim_withheld(tracker._head_in_doubt(first, blobs, feats), first, withheld,
                                "not the body's 19 mm")


@pytest.mark.parametrize("clutter_p, clutter_q, expected", [
    (0.3, 0.0, "q"), (0.0, 0.3, "p"), (0.0, 0.0, None), (0.3, 0.3, None), (float("nan"), 0.3, "p")])
def test_the_one_clean_view_is_named_only_where_the_other_is_over_a_structure(
        clutter_p: float, clutter_q: float, expected: str | None) -> None:
    blobs = {"p": _blob(7.0, clutter_p), "q": _blob(7.0, clutter_q)}
    assert the_one_clean_view(blobs, 0.1) == expected
    assert the_one_clean_view({"p": blobs["p"]}, 0.1) is None   # one view: no other to be over a structure
