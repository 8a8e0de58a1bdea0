"""The steady state's one compiled call per pair (steady_state / steady_kernels) gives what the per-view path
(find_in_roi per view, then reconstruct) gives, bit for bit: every posture record, every Blob and Features2D field,
and the noise-sigma schedule, over short trajectories of several robots (clean and over a contrast-filled vessel)
(with the tight ROI off: the per-view path has none); and the tight ROI follows such tracks as the ROI does."""
from __future__ import annotations

import dataclasses
import math
import pickle

import numpy as np
import pytest

from appliance.geometry import Calibration
from appliance.recognition import PostureTracker, RecognitionSettings
from appliance.recognition import tracker as tracker_module
from appliance.recognition.steady_kernels import FOUND_BY_TIGHT, OUT_VIEW_SIZE, R_FOUND_BY, clutter_axis_sigma
from appliance.recognition.features import clutter_axis_sigma_rad
from appliance.recognition.steady_state import SteadyPair
from appliance.robots import load_robots
from drivers.loopback.scene_builders import S_BEND_CENTRELINE_MM, smooth_centreline
from drivers.loopback.xray_render import (
    BiplaneRenderer,
    ImagingSettings,
    RobotBody,
    RobotPose,
    VesselPhantom,
)


def _same(a: object, b: object, skip: tuple[str, ...] = ()) -> None:
    """Every field equal, arrays in dtype, shape and every bit (dataclasses compared field by field)."""
    assert type(a) is type(b)
    for f in dataclasses.fields(a):  # type: ignore[arg-type]
        if f.name in skip:
            continue
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape, f.name
            np.testing.assert_array_equal(x, y, err_msg=f.name)
        elif isinstance(x, dict) and any(dataclasses.is_dataclass(v) for v in x.values()):
            assert x.keys() == y.keys()
            for k in x:
                _same(x[k], y[k])
        elif isinstance(x, list) and x and isinstance(x[0], np.ndarray):
            assert len(x) == len(y) and all(np.array_equal(u, v) for u, v in zip(x, y)), f.name
        else:
            assert x == y or (isinstance(x, float) and math.isnan(x) and math.isnan(y)), (f.name, x, y)


@pytest.mark.parametrize("robot,start,velocity,direction", [
    (1, (3.0, -4.0, 5.0), (20.0, 10.0, -5.0), (0.3, 0.5, 0.81)),
    (3, (-4.0, 0.5, 6.0), (30.0, 0.0, 0.0), (0.9, 0.4, 0.2)),       # along the vessel
    (4, (-20.0, -11.0, 4.0), (0.0, 25.0, 5.0), (0.2, 0.9, 0.4)),    # across the vessel
    (6, (1.0, 0.0, 6.0), (10.0, -10.0, 0.0), (0.6, -0.3, 0.74)),    # over the vessel
    (7, (8.0, 6.0, -5.0), (-15.0, 5.0, 10.0), (-0.7, 0.2, 0.68)),
])
def test_one_call_per_pair_equals_the_per_view_path(views: dict[str, object], calibration: Calibration, robot: int,
                                                    start: tuple[float, ...], velocity: tuple[float, ...],
                                                    direction: tuple[float, ...],
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    _track_both_ways(views, calibration, robot, start, velocity, direction, monkeypatch)


@pytest.mark.parametrize("robot,start,velocity,direction", [
    (1, (3.0, -4.0, 5.0), (20.0, 10.0, -5.0), (0.3, 0.5, 0.81)),
    (6, (1.0, 0.0, 6.0), (10.0, -10.0, 0.0), (0.6, -0.3, 0.74)),    # over the vessel
])
def test_both_paths_place_the_known_body_alike(views: dict[str, object], calibration: Calibration, robot: int,
                                               start: tuple[float, ...], velocity: tuple[float, ...],
                                               direction: tuple[float, ...], monkeypatch: pytest.MonkeyPatch) -> None:
    # With the robot's body given (body_prior), the plain frames' postures and the per-view path's stay the same.
    _track_both_ways(views, calibration, robot, start, velocity, direction, monkeypatch, body=True)


def _track_both_ways(views: dict[str, object], calibration: Calibration, robot: int, start: tuple[float, ...],
                     velocity: tuple[float, ...], direction: tuple[float, ...], monkeypatch: pytest.MonkeyPatch,
                     body: bool = False) -> int:
    """Six frames through a tracker with the one call per pair and one without (both given the robot's body if
    ``body``); asserts they are the same in every bit; returns how many frames the first built from the call's
    numbers (plain frames)."""
    spec = load_robots()[robot]
    body = RobotBody(spec.length_mm, spec.diameter_mm, spec.tip_angle_deg, spec.attenuation_per_mm)
    vessel = VesselPhantom(smooth_centreline(S_BEND_CENTRELINE_MM), 2.5, 0.06)
    renderer = BiplaneRenderer(views, body, vessel=vessel, settings=ImagingSettings(), seed=robot)
    # The tight ROI and the lean pass (which the per-view path does not have) off: the pair's ROI is the
    # per-view path's.
    settings = RecognitionSettings(dark_level=ImagingSettings().dark_level, tight_roi=False, lean_steady_state=False)
    known = spec if body else None
    paired, per_view = PostureTracker(calibration, settings, body=known), PostureTracker(calibration, settings, body=known)
    monkeypatch.setattr(per_view._pair, "usable", lambda *args: False)
    # What each tracker searched and found (the blobs and features behind its postures).
    calls = {"pair": 0}
    real_pair = tracker_module.PostureTracker._search_pair

    def counted(self, *args):  # type: ignore[no-untyped-def]
        found = real_pair(self, *args)
        calls["pair"] += bool(found)
        return found

    monkeypatch.setattr(tracker_module.PostureTracker, "_search_pair", counted)
    kept = {}
    real_posture = tracker_module.PostureTracker._posture

    def keep(self, frame, t, rec, blobs):  # type: ignore[no-untyped-def]
        kept[(id(self), frame)] = (blobs, rec.view_features)
        return real_posture(self, frame, t, rec, blobs)

    monkeypatch.setattr(tracker_module.PostureTracker, "_posture", keep)
    roi_frames = plain = 0
    for n in range(6):
        t = n / 30.0
        pose = RobotPose(np.array(start) + t * np.array(velocity), np.array(direction))
        pair = renderer.render(pose)
        a = paired.process(pair.images["p"], pair.images["q"], frame=n, t=t)
        b = per_view.process(pair.images["p"], pair.images["q"], frame=n, t=t)
        assert paired.last_search == per_view.last_search
        assert a.to_record() == b.to_record()
        _same(a, b, skip=("timings_us",))
        # The next frame's prediction too (the body prior moves a plain posture's centroid).
        for field in ("t", "centroid", "length_mm", "velocity", "lost_frames", "view_outline_px", "direction_xyz"):
            assert getattr(paired._track, field) == getattr(per_view._track, field), field
        plain += (id(paired), n) not in kept and paired.last_search == "roi"
        if (id(paired), n) in kept:
            (blobs_a, feats_a), (blobs_b, feats_b) = kept[(id(paired), n)], kept[(id(per_view), n)]
            for name in ("p", "q"):
                _same(blobs_a[name], blobs_b[name])
                _same(feats_a[name], feats_b[name])
        roi_frames += paired.last_search == "roi"
        assert [v[1:] for v in paired._roi_noise.values()] == [v[1:] for v in per_view._roi_noise.values()]
    assert roi_frames >= 3 and calls["pair"] == roi_frames
    return plain


def test_most_tracked_frames_are_plain(views: dict[str, object], calibration: Calibration,
                                       monkeypatch: pytest.MonkeyPatch) -> None:
    # The posture of a plain frame is built from the call's numbers (no Blob, Features2D or Reconstruction):
    # on a clean track (robot 1 away from the vessel) that is every tracked frame after the first.
    plain = _track_both_ways(views, calibration, 1, (3.0, -4.0, 5.0), (20.0, 10.0, -5.0), (0.3, 0.5, 0.81),
                             monkeypatch)
    assert plain >= 3


def test_a_plain_frame_is_placed_without_making_its_deferred_tips_and_views(views: dict[str, object],
                                                                             calibration: Calibration,
                                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    # The body prior places a plain frame's posture within the pair's compiled call (steady_kernels._place_body):
    # its tips and views stay for the record to make, and when made they are the placed tips.
    spec = load_robots()[1]
    body = RobotBody(spec.length_mm, spec.diameter_mm, spec.tip_angle_deg, spec.attenuation_per_mm)
    renderer = BiplaneRenderer(views, body, settings=ImagingSettings(), seed=1)
    tracker = PostureTracker(calibration, RecognitionSettings(dark_level=ImagingSettings().dark_level), body=spec)
    objects = SteadyPair.objects
    called = []
    monkeypatch.setattr(SteadyPair, "objects", lambda self: called.append(1) or objects(self))
    plain = 0
    for n in range(6):
        t = n / 30.0
        pose = RobotPose(np.array((3.0, -4.0, 5.0)) + t * np.array((20.0, 10.0, -5.0)), np.array((0.3, 0.5, 0.81)))
        pair = renderer.render(pose)
        called.clear()
        posture = tracker.process(pair.images["p"], pair.images["q"], frame=n, t=t)
        if tracker.last_search != "roi" or called:
            continue
        plain += 1
        assert "_rest" in posture.__dict__ and "views" not in posture.__dict__
        placed = posture.tips_mm.copy()
        assert posture.views["p"] is not None          # the rest made now ...
        assert np.array_equal(posture.tips_mm, placed)  # ... keeps the placed tips
        assert math.isclose(float(np.linalg.norm(placed[0] - placed[1])), spec.length_mm, rel_tol=1e-9)
        assert not math.isclose(posture.length_mm, spec.length_mm, rel_tol=1e-9)   # the measured length stays
    assert plain >= 3


def test_pair_path_is_not_used_for_other_inputs(calibration: Calibration) -> None:
    pair = SteadyPair(calibration, RecognitionSettings())
    image = np.zeros((336, 384), dtype=np.uint16)
    from appliance.recognition.segmentation import log_background
    bg = log_background(image + 1000, 48, 0.0)
    assert pair.usable(image, image, bg, bg)
    assert not pair.usable(image.astype(np.float32), image, bg, bg)
    assert not pair.usable(image, image[:, ::2], bg, bg)
    assert not pair.usable(image, image, bg, None)
    assert not SteadyPair(calibration, RecognitionSettings(estimator="paper")).usable(image, image, bg, bg)


def test_compiled_clutter_term_equals_the_python_one() -> None:
    rng = np.random.default_rng(4)
    cases = [(0.0, 10, 1.0, 5.0, 3.0, 1.0), (0.3, 50, 1.0, -1.0, 3.0, 1.0), (0.3, 50, 1.0, 5.0, 1.0, 3.0),
             (0.2, 40, 1.2, 30.0, 4.0, -0.5), (math.nan, 40, 1.2, 30.0, 4.0, 1.0), (0.2, 40, 1.2, 30.0, math.nan, 1.0)]
    cases += [(float(rng.uniform(0, 1)), int(rng.integers(1, 3000)), float(rng.uniform(0.1, 3)),
               float(rng.uniform(1, 900)), float(rng.uniform(1, 400)), float(rng.uniform(0, 20))) for _ in range(300)]
    for case in cases:
        a, b = clutter_axis_sigma(*case), clutter_axis_sigma_rad(*case)
        assert a == b or (math.isnan(a) and math.isnan(b)), case


def _two_trackers(views: dict[str, object], calibration: Calibration, robot: int, centres: list[np.ndarray],
                  direction: tuple[float, ...], first: RecognitionSettings, second: RecognitionSettings,
                  used: object, body: bool = False) -> list[tuple[object, object, tuple[bool, bool]]]:
    """Per frame of the robot at ``centres``: the posture of a tracker with settings ``first``, of one with
    ``second`` (both given the robot's body if ``body``), and ``used(first tracker)``."""
    spec = load_robots()[robot]
    shape = RobotBody(spec.length_mm, spec.diameter_mm, spec.tip_angle_deg, spec.attenuation_per_mm)
    vessel = VesselPhantom(smooth_centreline(S_BEND_CENTRELINE_MM), 2.5, 0.06)
    renderer = BiplaneRenderer(views, shape, vessel=vessel, settings=ImagingSettings(), seed=robot)
    known = spec if body else None
    a_tracker = PostureTracker(calibration, first, body=known)
    b_tracker = PostureTracker(calibration, second, body=known)
    frames = []
    for n, centre in enumerate(centres):
        pair = renderer.render(RobotPose(centre, np.array(direction)))
        a = a_tracker.process(pair.images["p"], pair.images["q"], frame=n, t=n / 30.0)
        b = b_tracker.process(pair.images["p"], pair.images["q"], frame=n, t=n / 30.0)
        frames.append((a, b, used(a_tracker)))  # type: ignore[operator]
    return frames


def _tight_views(tracker: PostureTracker) -> tuple[bool, bool]:
    """Which views the tracker's last steady pair found in the tight ROI."""
    out = tracker._pair.out
    if tracker.last_search != "roi" or not out.size:
        return False, False
    return bool(out[R_FOUND_BY] == FOUND_BY_TIGHT), bool(out[OUT_VIEW_SIZE + R_FOUND_BY] == FOUND_BY_TIGHT)


def _tight_track(views: dict[str, object], calibration: Calibration, robot: int, centres: list[np.ndarray],
                 direction: tuple[float, ...]) -> list[tuple[object, object, tuple[bool, bool]]]:
    """Per frame: the posture with the tight ROI on, with it off, and which views the tight ROI found (the lean
    pass off in both: it is tried before the tight ROI)."""
    dark = ImagingSettings().dark_level
    return _two_trackers(views, calibration, robot, centres, direction,
                         RecognitionSettings(dark_level=dark, lean_steady_state=False),
                         RecognitionSettings(dark_level=dark, tight_roi=False, lean_steady_state=False), _tight_views,
                         body=True)


@pytest.mark.parametrize("robot,start,velocity,direction", [
    (1, (3.0, -4.0, 5.0), (20.0, 10.0, -5.0), (0.3, 0.5, 0.81)),
    (3, (-4.0, 0.5, 6.0), (30.0, 0.0, 0.0), (0.9, 0.4, 0.2)),       # along the vessel
    (6, (1.0, 0.0, 6.0), (10.0, -10.0, 0.0), (0.6, -0.3, 0.74)),    # over the vessel
])
def test_tight_roi_follows_a_steady_track_as_the_roi_does(views: dict[str, object], calibration: Calibration,
                                                          robot: int, start: tuple[float, ...],
                                                          velocity: tuple[float, ...],
                                                          direction: tuple[float, ...]) -> None:
    centres = [np.array(start) + n / 30.0 * np.array(velocity) for n in range(7)]
    frames = _tight_track(views, calibration, robot, centres, direction)
    # Frame 0 is detected, frame 1 searched in the ROI (no previous pair); then the tight ROI, both views.
    assert [used for _, _, used in frames[:2]] == [(False, False), (False, False)]
    assert sum(used == (True, True) for _, _, used in frames[2:]) >= 4
    for tight, wide, _ in frames:
        assert tight.ok == wide.ok and tight.ambiguous == wide.ambiguous
        assert tight.head_identified == wide.head_identified
        if tight.ok:
            assert np.linalg.norm(tight.centroid_mm - wide.centroid_mm) < 0.01
            if tight.tips_mm is not None:
                assert np.abs(tight.tips_mm - wide.tips_mm).max() < 0.05


def test_tight_roi_widens_where_the_body_moved_unexpectedly(views: dict[str, object],
                                                             calibration: Calibration) -> None:
    # Frames 0-4 at constant velocity, then a 1.5 mm jump across the axis (~10 px, beyond the tight ROI's
    # allowance): that view is searched in the ROI, which finds the body as without the tight ROI.
    direction = np.array([-0.7, 0.2, 0.68]) / np.linalg.norm([-0.7, 0.2, 0.68])
    across = np.cross(direction, [0.0, 0.0, 1.0])
    centres = [np.array([-8.0, 6.0, -3.0]) + n / 30.0 * np.array([9.0, 3.0, -2.0]) for n in range(5)]
    centres.append(centres[-1] + 1.5 * across / np.linalg.norm(across))
    frames = _tight_track(views, calibration, 1, centres, tuple(direction))
    assert frames[4][2] == (True, True)
    tight, wide, used = frames[5]
    assert used != (True, True)
    assert tight.ok and wide.ok
    assert np.array_equal(tight.centroid_mm, wide.centroid_mm) or np.linalg.norm(
        tight.centroid_mm - wide.centroid_mm) < 0.01


def _lean_track(views: dict[str, object], calibration: Calibration, robot: int, centres: list[np.ndarray],
                direction: tuple[float, ...]) -> list[tuple[object, object, tuple[bool, bool]]]:
    """Per frame: the posture with the lean pass on, with it off, and which views the lean pass found."""
    dark = ImagingSettings().dark_level

    def used(tracker: PostureTracker) -> tuple[bool, bool]:
        return (tracker._pair.lean_views() if tracker.last_search == "roi" and tracker._lean_from is not None
                else (False, False))

    return _two_trackers(views, calibration, robot, centres, direction, RecognitionSettings(dark_level=dark),
                         RecognitionSettings(dark_level=dark, lean_steady_state=False), used)


def test_lean_pass_follows_a_clean_track_as_the_roi_search_does(views: dict[str, object],
                                                                 calibration: Calibration) -> None:
    # Robot 1 clear of the vessel in both views.
    centres = [np.array([-8.0, 6.0, -3.0]) + n / 30.0 * np.array([9.0, 3.0, -2.0]) for n in range(7)]
    frames = _lean_track(views, calibration, 1, centres, (-0.7, 0.2, 0.68))
    # Frame 0 is detected, frame 1 searched in ROIs (no previous pair to start from); then the lean pass.
    assert [used for _, _, used in frames[:2]] == [(False, False), (False, False)]
    assert all(used == (True, True) for _, _, used in frames[2:])
    for lean, full, _ in frames:
        assert lean.ok and full.ok and lean.ambiguous == full.ambiguous and lean.head_identified == full.head_identified
        assert np.linalg.norm(lean.centroid_mm - full.centroid_mm) < 0.01
        assert np.abs(lean.tips_mm - full.tips_mm).max() < 0.05


def test_lean_pass_is_the_default_and_not_taken_with_the_background_along_structure(
        views: dict[str, object], calibration: Calibration) -> None:
    # The default tracker takes the lean pass on a clean track (the test above); with the background
    # interpolated along the structure (which the lean pass does not do) every view takes the ROI search.
    assert RecognitionSettings().lean_steady_state
    dark = ImagingSettings().dark_level
    centres = [np.array([-8.0, 6.0, -3.0]) + n / 30.0 * np.array([9.0, 3.0, -2.0]) for n in range(4)]

    def used(tracker: PostureTracker) -> tuple[bool, bool]:
        return tracker._pair.lean_views() if tracker.last_search == "roi" else (False, False)

    frames = _two_trackers(views, calibration, 1, centres, (-0.7, 0.2, 0.68),
                           RecognitionSettings(dark_level=dark, background_along_structure=True),
                           RecognitionSettings(dark_level=dark), used)
    assert all(used == (False, False) for _, _, used in frames)
    assert all(a.ok for a, _, _ in frames)


def test_lean_pass_falls_back_to_the_roi_search_where_the_body_moved_unexpectedly(
        views: dict[str, object], calibration: Calibration) -> None:
    # Frames 0-3 at constant velocity, then a 2.5 mm jump along the axis (~10 px): the body leaves the
    # lean pass's capsule (4 px beyond the last body), which must not follow it.
    direction = np.array([-0.7, 0.2, 0.68]) / np.linalg.norm([-0.7, 0.2, 0.68])
    centres = [np.array([-8.0, 6.0, -3.0]) + n / 30.0 * np.array([9.0, 3.0, -2.0]) for n in range(4)]
    centres.append(centres[-1] + 2.5 * direction)
    frames = _lean_track(views, calibration, 1, centres, tuple(direction))
    assert frames[3][2] == (True, True)
    lean, full, used = frames[4]
    assert used == (False, False)
    assert lean.ok and full.ok
    assert np.linalg.norm(lean.centroid_mm - full.centroid_mm) < 0.01


def test_lean_pass_leaves_a_view_over_the_vessel_to_the_roi_search(views: dict[str, object],
                                                                   calibration: Calibration) -> None:
    # Robot 6 over the contrast-filled vessel: the background interpolated under it varies (clutter), which
    # the lean pass (the last baseline, no end stops) does not handle; such a view takes the ROI search.
    centres = [np.array([1.0, 0.0, 6.0]) + n / 30.0 * np.array([3.0, -3.0, 0.0]) for n in range(5)]
    frames = _lean_track(views, calibration, 6, centres, (0.6, -0.3, 0.74))
    over = [name for name in ("p", "q") if frames[-1][1].reason and f"view {name}" in frames[-1][1].reason]
    assert over, "the pose is meant to put the robot over the vessel in a view"
    for lean, full, used in frames[2:]:
        for name, lean_view in zip(("p", "q"), used):
            if name in over:
                assert not lean_view
        assert lean.ok == full.ok


def test_a_compiled_axis_uncertainty_off_by_a_bit_sends_the_frame_to_python(views: dict[str, object],
                                                                            calibration: Calibration) -> None:
    # numba's hypot differs from Python's in the last bit for ~0.5 % of arguments: where the kernel's axis
    # uncertainty (which its front used) is not Python's, the frame is neither plain nor finished from the
    # kernel's front, and the features carry Python's value.
    from appliance.recognition import steady_kernels as sk

    spec = load_robots()[1]
    body = RobotBody(spec.length_mm, spec.diameter_mm, spec.tip_angle_deg, spec.attenuation_per_mm)
    renderer = BiplaneRenderer(views, body, settings=ImagingSettings(), seed=3)
    tracker = PostureTracker(calibration, RecognitionSettings(dark_level=ImagingSettings().dark_level))
    for n in range(2):
        pair = renderer.render(RobotPose(np.array([-8.0, 6.0, -3.0 + 0.2 * n]), np.array([-0.7, 0.2, 0.68])))
        tracker.process(pair.images["p"], pair.images["q"], frame=n, t=n / 30.0)
    assert tracker.last_search == "roi"
    steady = tracker._pair
    assert steady.plain_posture(1, 1 / 30.0) is not None and steady.objects()[2] is not None
    python_value = steady.objects()[1][1].axis_sigma_rad
    steady.out[sk.OUT_VIEW_SIZE + sk.R_AXIS_SIGMA] = np.nextafter(python_value, np.inf)
    assert steady.plain_posture(1, 1 / 30.0) is None
    blobs, feats, status, _ = steady.objects()
    assert status is None and feats[1].axis_sigma_rad == python_value


def test_output_arrays_are_reused_only_where_nothing_holds_them(views: dict[str, object],
                                                                calibration: Calibration) -> None:
    # A plain posture's arrays are views of its pair call's output, which the next calls reuse (SteadyPair._output)
    # only where no posture, feature or track holds it: kept postures keep their numbers, dropped ones free them.
    spec = load_robots()[1]
    body = RobotBody(spec.length_mm, spec.diameter_mm, spec.tip_angle_deg, spec.attenuation_per_mm)
    renderer = BiplaneRenderer(views, body, settings=ImagingSettings(), seed=5)
    tracker = PostureTracker(calibration, RecognitionSettings(dark_level=ImagingSettings().dark_level))
    pairs = [renderer.render(RobotPose(np.array([3.0 + 0.3 * n, -4.0, 5.0]), np.array([0.3, 0.5, 0.81])))
             for n in range(16)]
    kept = []
    for n, pair in enumerate(pairs[:8]):
        posture = tracker.process(pair.images["p"], pair.images["q"], frame=n, t=n / 30.0)
        kept.append((posture, posture.to_record(), pickle.dumps(posture)))
    plain = [p for p, _, _ in kept if p.frame > 0]
    assert tracker.last_search == "roi"
    assert len({id(p.centroid_mm) for p in plain}) == len(plain)
    for posture, record, pickled in kept:
        assert posture.to_record() == record == pickle.loads(pickled).to_record()
    # Dropped postures free their arrays for the next calls.
    seen = set()
    del kept, plain, posture
    for n, pair in enumerate(pairs[8:], start=8):
        posture = tracker.process(pair.images["p"], pair.images["q"], frame=n, t=n / 30.0)
        assert posture.ok and tracker.last_search == "roi"
        seen.add(id(posture.centroid_mm))
    assert len(seen) <= 3


def test_lean_pass_reads_nothing_of_its_workspace_it_did_not_write(views: dict[str, object], calibration: Calibration,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    # The lean pass's arrays are parts of a workspace the pair reuses every frame, some of them not cleared
    # (steady_kernels.lean_view). With the workspace and the weights' buffers filled with NaN bytes before every
    # call, every posture must still be the one of a tracker whose buffers hold what the last call left.
    centres = [np.array([-8.0, 6.0, -3.0]) + n / 30.0 * np.array([9.0, 3.0, -2.0]) for n in range(6)]
    dark = ImagingSettings().dark_level
    search = SteadyPair.search
    dirtied, pairs = [], []

    def dirty_search(self: SteadyPair, *args: object, **kwargs: object) -> bool:
        if not any(p is self for p in pairs):
            pairs.append(self)
        if self is pairs[-1] and len(pairs) == 2:  # (the second tracker's pair only)
            for buffer in (self._work, self._weights_buf, self._masks_buf):
                buffer.view(np.uint8)[:] = 0xFF
            dirtied.append(True)
        return search(self, *args, **kwargs)

    monkeypatch.setattr(SteadyPair, "search", dirty_search)
    frames = _two_trackers(views, calibration, 1, centres, (-0.7, 0.2, 0.68), RecognitionSettings(dark_level=dark),
                           RecognitionSettings(dark_level=dark),
                           lambda t: t._pair.lean_views() if t.last_search == "roi" else (False, False))
    assert dirtied and all(used == (True, True) for _, _, used in frames[2:])
    for clean, dirty, _ in frames:
        _same(clean, dirty, skip=("timings_us",))
