"""No made-up poses: scenes without the robot (contrast-filled vessels, noise, non-uniform field) and a
robot that vanishes or leaves the field of view must give ``ok: false`` with a reason, never a pose on
the vessel. Small images in the simulated bench's geometry (500 mm source-object distance, 150 x 130
mm field, plane q 15 degrees down, both C-arms turned by -45 degrees), where vessels seen
foreshortened or crossing themselves in projection are dense enough to pass a per-width test.
Also the robot against the vessel: a centroid placed by the clean view where the other overlaps the
vessel, and a cone end's tip found from both views' profiles when the head is not identified."""
from __future__ import annotations

import numpy as np
import pytest

from appliance.geometry import Calibration, View
from appliance.recognition import PostureTracker, RecognitionSettings
from drivers.loopback.scene_builders import S_BEND_CENTRELINE_MM, random_vessel, smooth_centreline
from drivers.loopback.xray_render import (
    BiplaneRenderer,
    ImagingSettings,
    RobotBody,
    RobotPose,
    TrueView,
    VesselPhantom,
    biplane_views,
)

IMAGE_SIZE = (256, 224)
SETTINGS = RecognitionSettings(dark_level=ImagingSettings().dark_level)


def _sim_views(image_size: tuple[int, int]) -> dict[str, TrueView]:
    views = biplane_views(sod_mm=500.0, sdd_mm=1000.0, fov_mm=(150.0, 130.0), image_size=image_size,
                          separation_deg=90.0, elevation_deg=15.0)
    a = np.radians(-45.0)  # the C-arms turned about the vertical axis, as config/sim.yaml does
    turn = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    return {n: TrueView(n, v.K, v.dist, v.R @ turn.T, v.t, v.image_size) for n, v in views.items()}


def _calibration(views: dict[str, TrueView]) -> Calibration:
    return Calibration.from_views(*(View(n, v.K, v.dist, v.R, v.t, v.image_size) for n, v in sorted(views.items())))








@pytest.fixture(scope="module")
def views() -> dict[str, TrueView]:
    return _sim_views(IMAGE_SIZE)


def test_twenty_random_empty_scenes_give_no_posture(views: dict[str, TrueView]) -> None:
    calibration = _calibration(views)
    ok = []
    reasons = set()
    for seed in range(20):
        rng = np.random.default_rng(1000 + seed)
        vessel = (VesselPhantom(smooth_centreline(np.asarray(S_BEND_CENTRELINE_MM)), 2.5, 0.06) if seed % 5 == 0
                  else random_vessel(rng))
        renderer = BiplaneRenderer(views, None, vessel=vessel, settings=ImagingSettings(), seed=seed)
        tracker = PostureTracker(calibration, SETTINGS)
        for frame in range(2):  # the second frame has a history of failures, not of a pose
            pair = renderer.render(None)
            posture = tracker.process(pair.images["p"], pair.images["q"], frame=frame, t=0.04 * frame)
            if posture.ok:
                ok.append((seed, frame, posture.centroid_mm.round(1).tolist(), posture.reason))
            else:
                assert posture.reason and posture.centroid_mm is None
                reasons.add(posture.reason.split(":")[0])
    assert not ok, f"made-up postures on empty scenes: {ok}"
    assert any(r.startswith("no robot-like object in view") for r in reasons), reasons


def test_foreshortened_vessel_is_rejected_per_mm_of_path(views: dict[str, TrueView]) -> None:
    """A straight vessel running 20 degrees off p's central ray: dense in p (a long path through
    contrast), side-on in q. Its peak per mm of width in p is metal-like; per mm of path it is not."""
    calibration = _calibration(views)
    ray = -calibration.p.source_mm / np.linalg.norm(calibration.p.source_mm)
    across = np.cross(ray, [0.0, 0.0, 1.0])
    axis = np.cos(np.radians(20.0)) * ray + np.sin(np.radians(20.0)) * across / np.linalg.norm(across)
    vessel = VesselPhantom(smooth_centreline(np.array([-40.0 * axis, 40.0 * axis]) + [5.0, -3.0, 2.0]), 2.5, 0.08)
    renderer = BiplaneRenderer(views, None, vessel=vessel, settings=ImagingSettings(), seed=3)
    pair = renderer.render(None)
    posture = PostureTracker(calibration, SETTINGS).process(pair.images["p"], pair.images["q"])
    assert not posture.ok, f"vessel reported as a robot at {posture.centroid_mm}"
    assert posture.reason


@pytest.fixture(scope="module")
def robot_scene(views: dict[str, TrueView]) -> tuple[Calibration, BiplaneRenderer]:
    vessel = VesselPhantom(smooth_centreline(np.asarray(S_BEND_CENTRELINE_MM)), 2.5, 0.06)
    body = RobotBody(10.0, 2.0, 20.0, 2.5)  # robot 1 of the seed paper
    return _calibration(views), BiplaneRenderer(views, body, vessel=vessel, settings=ImagingSettings(), seed=5)


def test_robot_that_disappears_becomes_lost_not_the_vessel(robot_scene: tuple[Calibration, BiplaneRenderer]) -> None:
    calibration, renderer = robot_scene
    tracker = PostureTracker(calibration, SETTINGS)
    # In the vessel, along its centreline near the origin (direction of the (0,0,6)->(20,12,2) segment).
    direction = np.array([20.0, 12.0, -4.0]) / np.linalg.norm([20.0, 12.0, -4.0])
    for frame in range(3):
        pose = RobotPose(np.array([0.0, 0.0, 6.0]) + 0.5 * frame * direction, direction)
        pair = renderer.render(pose)
        posture = tracker.process(pair.images["p"], pair.images["q"], frame=frame, t=0.04 * frame)
        # Over the vessel the robot is seen with reduced accuracy: frames whose rod does not reproject
        # onto its images (here 7 px, 1.2-1.7 mm off) may be reported lost; the first one is ok and
        # starts the track, which must be there when the robot vanishes.
        assert posture.ok or frame > 0, posture.reason
        assert posture.ok or "reproject" in (posture.reason or ""), posture.reason
    assert tracker.tracking
    for frame in range(3, 9):
        pair = renderer.render(None)
        posture = tracker.process(pair.images["p"], pair.images["q"], frame=frame, t=0.04 * frame)
        assert not posture.ok, f"frame {frame}: pose {posture.centroid_mm} made up after the robot vanished"
        assert posture.reason and posture.centroid_mm is None


def test_robot_leaving_the_field_is_tracked_then_lost_never_misplaced(
        robot_scene: tuple[Calibration, BiplaneRenderer]) -> None:
    calibration, renderer = robot_scene
    tracker = PostureTracker(calibration, SETTINGS)
    direction = np.array([1.0, 0.3, 0.1]) / np.linalg.norm([1.0, 0.3, 0.1])
    # Upwards, away from the vessel (which lies near z = 0): out of both fields at the end.
    motion = np.array([0.2, -0.3, 1.0]) / np.linalg.norm([0.2, -0.3, 1.0])
    outcomes = []
    for frame in range(16):
        pose = RobotPose(np.array([10.0, -10.0, -15.0]) + 6.0 * frame * motion, direction)
        pair = renderer.render(pose)
        posture = tracker.process(pair.images["p"], pair.images["q"], frame=frame, t=0.04 * frame)
        if posture.ok:
            error = float(np.linalg.norm(posture.centroid_mm - pose.centroid_mm))
            # A robot partly off the detector may be flagged, but never placed elsewhere.
            assert error < (2.0 if posture.ambiguous else 0.5), f"frame {frame}: {error:.2f} mm off"
        outcomes.append(posture.ok)
    assert outcomes[0] and not outcomes[-1]  # seen at first, reported lost once far outside the field


def test_centroid_over_a_vessel_in_one_view_comes_from_the_clean_view(views: dict[str, TrueView]) -> None:
    """Robot 6 (30 x 5 mm, polymer around a magnet: weak contrast against the vessel) at random poses
    around the default vessel: where one view's blob merges with the vessel, the clean view's ray places
    the centroid. Without it (clutter never detected) the same frames are several times worse."""
    calibration = _calibration(_sim_views((384, 336)))
    centreline = smooth_centreline(np.asarray(S_BEND_CENTRELINE_MM))
    renderer = BiplaneRenderer(_sim_views((384, 336)), RobotBody(30.0, 5.0, 15.0, 0.15 * 2.5 + 0.85 * 0.025),
                               vessel=VesselPhantom(centreline, 2.5, 0.06), settings=ImagingSettings(), seed=2)
    blind = SETTINGS.model_copy(update={"max_clutter": 1e6})
    rng = np.random.default_rng(4)
    errors: dict[str, list[float]] = {"ours": [], "blind": []}
    kept_only_by_ours = 0
    for _ in range(16):
        centre = centreline[rng.integers(20, len(centreline) - 20)] + rng.normal(0.0, 3.0, 3)
        direction = rng.normal(size=3)
        pair = renderer.render(RobotPose(centre, direction / np.linalg.norm(direction)))
        ours = PostureTracker(calibration, SETTINGS).process(pair.images["p"], pair.images["q"])
        if not (ours.ok and ours.reason and "overlaps another structure in view" in ours.reason
                and " and " not in ours.reason.split("overlaps another structure in view")[1][:8]):
            continue  # not a one-view overlap
        other = PostureTracker(calibration, blind).process(pair.images["p"], pair.images["q"])
        if not other.ok:
            # Without the placement the rod reprojects off its images and the frame is lost: ours gives
            # a position (within 0.3 mm here) where the blind tracker gives none.
            assert "reproject" in (other.reason or ""), other.reason
            assert float(np.linalg.norm(ours.centroid_mm - centre)) < 0.3
            kept_only_by_ours += 1
            continue
        errors["ours"].append(float(np.linalg.norm(ours.centroid_mm - centre)))
        errors["blind"].append(float(np.linalg.norm(other.centroid_mm - centre)))
    assert len(errors["ours"]) + kept_only_by_ours >= 6, "too few one-view overlaps to compare"
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in errors.items()}
    # Frames both report: 0.38 vs 0.49 mm RMS since the body stands on the attenuation beside it slice by
    # slice (the blind tracker's blobs lose less to the vessel; before: 0.43 vs 0.70 with the reprojection
    # rule, 0.6x before it took the two frames only ours reports out of the comparison); without clutter
    # detection they are still worse, and ours is no worse than before.
    assert rms["ours"] < 0.85 * rms["blind"], rms
    assert rms["ours"] < 0.43, rms


def test_cone_end_is_found_from_both_views_profiles_when_the_head_is_not_identified() -> None:
    """Each view's ramp ratio (1.4) is below head identification's 1.6, but both views ramp longer at
    the same 3D end: that end is measured as a cone (apex beyond the half-height point)."""
    from appliance.recognition.features import Features2D
    from appliance.recognition.reconstruction import _likely_cone_end

    calibration = _calibration(_sim_views(IMAGE_SIZE))
    reach = {0.2: 10.0, 0.25: 9.6, 0.5: 8.0, 0.64: 7.2, 0.8: 6.0}
    flat = {0.2: 8.6, 0.25: 8.5, 0.5: 8.0, 0.64: 7.8, 0.8: 7.4}

    def feat(ramps: tuple[float, float]) -> Features2D:
        reaches = (reach, flat) if ramps[0] > ramps[1] else (flat, reach)
        return Features2D(np.zeros(2), np.array([1.0, 0.0]), (30.0, 1.0), np.zeros((2, 2)), 50, None, ramps,
                          reaches, 0.01)

    views = {"p": (calibration.p, feat((4.0, 1.2))), "q": (calibration.q, feat((1.2, 4.0)))}
    # q's +axis end is the 3D -d end, so both views point at the 3D +d end.
    assert _likely_cone_end(views, {"p": 0, "q": 1}, SETTINGS) == 0
    # The views disagree in 3D: no end is called a cone.
    assert _likely_cone_end(views, {"p": 0, "q": 0}, SETTINGS) is None
    # A weak ratio in one view: no cone either.
    weak = {"p": views["p"], "q": (calibration.q, feat((1.2, 1.4)))}
    assert _likely_cone_end(weak, {"p": 0, "q": 1}, SETTINGS) is None
    # The cone model puts the tip beyond the half-height point.
    f = views["p"][1]
    assert f.tip_distance(0, conical=True) > f.tip_distance(0, conical=False) + 1.0
