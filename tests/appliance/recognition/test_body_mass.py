"""Each view's blob weighed against the robot's body (appliance.recognition.body_mass) and its use by the body prior.

A rendered clean robot-6 frame (no vessel) weighs its attenuation times its volume in both views; the heavy-view
rule takes one view over the body with the other clean, and nothing else; the slide a view's excess can make,
given to the body prior, leaves the body's place to its clean ends; the tracker flags a frame whose view is heavy."""
from __future__ import annotations

import dataclasses
import math
import re

import numpy as np
import pytest

from appliance.geometry import Calibration
from appliance.recognition import PostureTracker, RecognitionSettings
from appliance.recognition.body_mass import centroid_slide_mm, heavy_view, view_masses_mm2
from appliance.recognition.body_prior import BodyModel, place_body
from appliance.recognition.posture import Posture, ViewObservation
from appliance.robots import load_robots
from drivers.loopback.xray_render import BiplaneRenderer, ImagingSettings, RobotBody, RobotPose

SETTINGS = RecognitionSettings()


@pytest.fixture(scope="module")
def spec6():
    return load_robots()[6]


@pytest.fixture(scope="module")
def clean_frame(views: dict[str, object], spec6):
    """Robot 6 rendered without a vessel on the small session views, side-on to neither view."""
    body = RobotBody(spec6.length_mm, spec6.diameter_mm, spec6.tip_angle_deg, spec6.attenuation_per_mm)
    renderer = BiplaneRenderer(views, body, settings=ImagingSettings(), seed=3)
    pose = RobotPose(np.array([1.0, -2.0, 1.5]), np.array([0.6, -0.3, 0.74]) / np.linalg.norm([0.6, -0.3, 0.74]))
    return pose, renderer.render(pose)


def test_the_body_model_carries_the_robots_attenuation_times_volume(spec6) -> None:
    model = BodyModel.of(spec6)
    assert model.mass_mm2 == pytest.approx(spec6.attenuation_per_mm * spec6.volume_mm3)
    # Robot 6: 0.396 /mm (15 % NdFeB in VeroWhite) x 340 mm^3 (a 5 mm cylinder with a 19 mm cone on 30 mm).
    assert model.mass_mm2 == pytest.approx(134.8, abs=0.2)
    # A body given without its material has no mass to weigh views against.
    bare = type("Bare", (), {"length_mm": 12.0, "centroid_from_tail_mm": 6.0, "cone_length_mm": 0.0,
                             "diameter_mm": 2.0})()
    assert BodyModel.of(bare).mass_mm2 is None


def test_a_clean_view_weighs_the_body(calibration: Calibration, clean_frame, spec6) -> None:
    pose, pair = clean_frame
    tracker = PostureTracker(calibration, RecognitionSettings(dark_level=ImagingSettings().dark_level), body=spec6)
    seen = {}
    made = tracker._posture

    def keep(frame, t, rec, blobs):
        seen["blobs"] = blobs
        return made(frame, t, rec, blobs)
    tracker._posture = keep
    posture = tracker.process(pair.images["p"], pair.images["q"])
    assert posture.ok
    expected = BodyModel.of(spec6).mass_mm2
    masses = view_masses_mm2(calibration, seen["blobs"], pose.centroid_mm)
    # Both views within a few % of attenuation x volume: the pixel's area at the object, not its side (a
    # ratio ~0.2 mm/px off), nor the magnification of the wrong view (the two views' sources are at different
    # distances from this point).
    for name in ("p", "q"):
        assert masses[name] / expected == pytest.approx(1.0, abs=0.04), name
    # The default point (the blobs' centroids triangulated) is the robot's, to a fraction of a %.
    at_blobs = view_masses_mm2(calibration, seen["blobs"])
    for name in ("p", "q"):
        assert at_blobs[name] == pytest.approx(masses[name], rel=0.005)
    # A clean frame is not flagged by its mass.
    assert not (posture.reason or "").count("weighs")


def test_only_one_view_over_the_body_with_the_other_clean_is_heavy() -> None:
    m = 100.0
    assert heavy_view({"p": 114.0, "q": 98.0}, m, 0.04, 0.08) == "p"
    assert heavy_view({"p": 99.0, "q": 109.0}, m, 0.04, 0.08) == "q"
    assert heavy_view({"p": 103.0, "q": 98.0}, m, 0.04, 0.08) is None     # within the clean spread
    assert heavy_view({"p": 110.0, "q": 109.0}, m, 0.04, 0.08) is None    # both heavy: no clean view
    assert heavy_view({"p": 110.0, "q": 90.0}, m, 0.04, 0.08) is None     # the other lost part of the body
    assert heavy_view({"p": math.nan, "q": math.nan}, m, 0.04, 0.08) is None


def test_the_slide_is_the_excess_share_of_the_blob_times_the_bodys_rms_lever_arm() -> None:
    # Robot 6, seed 1357911 pose 12: view q 153.6 mm^2 against 134.8: 12 % of q's blob, 30 mm / sqrt(12).
    assert centroid_slide_mm({"p": 129.9, "q": 153.6}, "q", 134.8, 30.0) == pytest.approx(
        (153.6 - 134.8) / 153.6 * 30.0 / math.sqrt(12.0))
    assert centroid_slide_mm({"p": 129.9, "q": 130.0}, "q", 134.8, 30.0) == 0.0


def _posture(calibration: Calibration, body: BodyModel, centroid_shift_mm: float) -> tuple[Posture, np.ndarray]:
    """The true body's posture (its centroid slid along the axis by ``centroid_shift_mm``) and its centroid."""
    c, u = np.array([2.0, -3.0, 4.0]), np.array([0.6, -0.3, 0.74]) / np.linalg.norm([0.6, -0.3, 0.74])
    tail = c - body.centroid_from_tail_mm * u
    head = tail + body.length_mm * u
    views = {}
    for name in ("p", "q"):
        uv_c, uv_h, uv_t = calibration.views[name].project(np.vstack([c, head, tail]))
        tips = np.array([uv_h, uv_t])
        views[name] = ViewObservation(uv_c, tips, (tips[0] - tips[1]) / np.linalg.norm(tips[0] - tips[1]), 100,
                                      (100.0, 4.0), 0)
    return Posture(frame=0, t=0.0, ok=True, centroid_mm=c + centroid_shift_mm * u, direction=u,
                   tips_mm=np.array([head, tail]), head_identified=True, length_mm=body.length_mm,
                   views=views), c


def test_a_heavy_views_slide_leaves_the_place_to_the_clean_ends(calibration: Calibration, spec6) -> None:
    body = BodyModel.of(spec6)
    posture, c = _posture(calibration, body, 0.6)
    # The moment centroid slid 0.6 mm (a vessel piece merged into view q at the head), the tails stayed put.
    clutter = {"p": 0.07, "q": 0.14}
    believed = place_body(calibration, dataclasses.replace(posture), body, SETTINGS, clutter)
    weighed = place_body(calibration, dataclasses.replace(posture), body, SETTINGS, clutter, centroid_slide_mm=1.8)
    assert np.linalg.norm(believed.centroid_mm - c) > 0.15
    assert np.linalg.norm(weighed.centroid_mm - c) < 0.05
    assert np.linalg.norm(weighed.tips_mm[1] - (c - body.centroid_from_tail_mm * posture.direction)) < 0.05
    # A slide of 0 is the placement without it, to the last bit.
    zero = place_body(calibration, dataclasses.replace(posture), body, SETTINGS, clutter, centroid_slide_mm=0.0)
    np.testing.assert_array_equal(zero.centroid_mm, believed.centroid_mm)


def _heavier_q(tracker: PostureTracker) -> None:
    """Have ``tracker`` see view q's blob 12 % heavier than found (as a merged vessel piece would make it)."""
    found = tracker._search_full

    def heavier(images, timings):
        (blobs, feats), failure = found(images, timings)
        blobs = dict(blobs, q=dataclasses.replace(blobs["q"], strength=blobs["q"].strength * 1.12))
        return (blobs, feats), failure
    tracker._search_full = heavier


@pytest.mark.parametrize("rule", ["slide", "flag", "off"])
def test_the_mass_rule_flags_and_weighs_a_heavy_view_as_set(calibration: Calibration, clean_frame, spec6,
                                                            rule: str) -> None:
    pose, pair = clean_frame
    settings = RecognitionSettings(dark_level=ImagingSettings().dark_level, mass_rule=rule)
    tracker = PostureTracker(calibration, settings, body=spec6)
    plain = tracker.process(pair.images["p"], pair.images["q"])
    # The same frame with view q's blob made 12 % heavier: "slide" and "flag" flag it, the reason naming the
    # view; "slide" then rests the placement on the ends (this clean frame's: the centroid stays close), the
    # others place it as the plain frame; "off" does not weigh the views.
    tracker.reset()
    _heavier_q(tracker)
    heavy = tracker.process(pair.images["p"], pair.images["q"])
    assert heavy.ok and not plain.ambiguous
    weighs = re.search(r"view q's blob weighs ([0-9.]+) of the body \(view p's ([0-9.]+)\)", heavy.reason or "")
    if rule == "off":
        assert not heavy.ambiguous and weighs is None
    else:
        assert heavy.ambiguous
        assert weighs and float(weighs.group(1)) > 1.04 and 0.92 <= float(weighs.group(2)) <= 1.04
    assert np.linalg.norm(heavy.centroid_mm - pose.centroid_mm) < 0.1
    if rule == "slide":
        assert not np.array_equal(heavy.centroid_mm, plain.centroid_mm)
        assert "the ends place the body" in heavy.reason
    else:
        np.testing.assert_array_equal(heavy.centroid_mm, plain.centroid_mm)
