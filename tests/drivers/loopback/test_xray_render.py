"""The synthetic biplane X-ray renderer: geometry against OpenCV, chords against closed forms, image
formation against Beer-Lambert, and the truth it returns."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.robots import load_robots
from drivers.loopback.xray_render import (
    BiplaneRenderer,
    ImagingSettings,
    RobotBody,
    RobotPose,
    TrueView,
    VesselPhantom,
    biplane_views,
)
from drivers.loopback.xray_scene import robot_chords, sphere_chords, vessel_chords

# Small detector with the default geometry's pixel size (150 mm over 768 px); odd sizes put the
# principal point on a pixel centre.
SMALL = dict(fov_mm=(150.0 * 255 / 768, 130.0 * 223 / 672), image_size=(255, 223))
ROBOT_1 = RobotBody(length_mm=10.0, diameter_mm=2.0, tip_angle_deg=20.0, attenuation_per_mm=1.0)
VERTICAL = np.array([0.0, 0.0, 1.0])


def random_unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def parallel_rays(extent: float, n: int, axis_rng: np.random.Generator | None = None):
    """A source far away (1e4 mm) on -z and rays through an n x n grid of the z=0 plane."""
    source = np.array([0.0, 0.0, -1e4])
    g = np.linspace(-extent, extent, n)
    x, y = np.meshgrid(g, g)
    dirs = np.stack([x, y, np.zeros_like(x)], axis=-1) - source
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    return source, dirs, (g[1] - g[0]) ** 2


# ------------------------------------------------------------------------------------ geometry
def test_projection_matches_opencv() -> None:
    views = biplane_views(elevation_deg=12.0, dist=(-0.08, 0.02, 0.001, -0.0015, 0.003))
    rng = np.random.default_rng(0)
    points = rng.uniform(-40, 40, size=(200, 3))
    for view in views.values():
        rvec, _ = cv2.Rodrigues(view.R)
        expected, _ = cv2.projectPoints(points, rvec, view.t, view.K, view.dist)
        np.testing.assert_allclose(view.project(points), expected.reshape(-1, 2), atol=1e-9)


def test_views_look_at_the_isocentre_from_the_source_distance() -> None:
    views = biplane_views(separation_deg=90.0)
    for view in views.values():
        assert np.linalg.norm(view.source_mm) == pytest.approx(500.0)
        w, h = view.image_size
        np.testing.assert_allclose(view.project(np.zeros((1, 3)))[0], [(w - 1) / 2, (h - 1) / 2])
        # World up is image up.
        assert view.project(np.array([[0.0, 0.0, 10.0]]))[0, 1] < (h - 1) / 2
    cos = views["p"].source_mm @ views["q"].source_mm / 500.0 ** 2
    assert cos == pytest.approx(0.0, abs=1e-12)
    # Field of view at the isocentre: 150 mm across 768 px.
    assert views["p"].K[0, 0] * 75.0 / 500.0 == pytest.approx(768 / 2)


def test_ray_through_projected_centroid_passes_through_it() -> None:
    views = biplane_views(elevation_deg=8.0, dist=(-0.05, 0.01, 0.0005, 0.0, 0.0), **SMALL)
    rng = np.random.default_rng(1)
    for _ in range(10):
        pose = RobotPose(rng.uniform(-20, 20, 3), random_unit(rng))
        for view in views.values():
            pixel = view.project(pose.centroid_mm[None, :])
            ray = view.pixel_rays(pixel)[0]
            offset = pose.centroid_mm - view.source_mm
            miss = np.linalg.norm(offset - (offset @ ray) * ray)
            assert miss < 1e-6


def test_invalid_view_is_rejected() -> None:
    view = biplane_views(**SMALL)["p"]
    with pytest.raises(ValueError, match="not a rotation"):
        TrueView(name="x", K=view.K, dist=view.dist, R=2 * view.R, t=view.t, image_size=(255, 223))


# ----------------------------------------------------------------------------- closed-form chords
@pytest.mark.parametrize("dims", [(10, 2, 20), (3, 1.5, 30), (30, 5, 15), (8, 1, 20)])
def test_chords_integrate_to_the_volume(dims) -> None:
    body = RobotBody(*dims, attenuation_per_mm=1.0)
    rng = np.random.default_rng(2)
    # Random, pointing at the source, away from it, and broadside (off the sampling grid's axes).
    directions = [random_unit(rng), VERTICAL, -VERTICAL, np.array([0.94, 0.34, 0.0])]
    for direction in directions:
        shadow = 0.6 * body.length_mm * math.sqrt(1.0 - direction[2] ** 2) + body.diameter_mm
        source, dirs, cell = parallel_rays(shadow, 400)
        chords = robot_chords(body, RobotPose(np.zeros(3), direction), source, dirs)
        assert np.all(np.isfinite(chords)) and chords.min() >= 0
        assert chords.sum() * cell == pytest.approx(body.volume_mm3, rel=2e-3), direction


unit_vectors = st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda v: 0.1 < np.linalg.norm(v))


@settings(max_examples=200, deadline=None)
@given(axis=unit_vectors, ray=unit_vectors, length=st.floats(1.0, 40.0), diameter=st.floats(0.3, 6.0),
       angle=st.floats(5.0, 89.0))
def test_chord_through_the_centroid_is_inside_and_the_same_both_ways(axis, ray, length, diameter,
                                                                    angle) -> None:
    """The centroid is inside the convex body: any line through it cuts a chord no longer than the
    body's diameter, and the same chord whichever side the source is on."""
    body = RobotBody(length, diameter, angle, attenuation_per_mm=1.0)
    pose = RobotPose(np.zeros(3), np.array(axis))
    d = np.array(ray) / np.linalg.norm(ray)
    there = robot_chords(body, pose, -300.0 * d, d[None, :])[0]
    back = robot_chords(body, pose, 300.0 * d, -d[None, :])[0]
    assert 0.0 < there <= math.hypot(length, diameter) + 1e-6
    # 1 um: a ray along the axis grazes the apex, a double root of the cone's quadric that is
    # known only to sqrt(round-off) x distance / cone slope (sharp cones, ~1e-4 mm at 300 mm).
    assert there == pytest.approx(back, abs=1e-3)


def test_axis_pointing_at_the_source_gives_the_whole_length() -> None:
    source = np.array([-500.0, 0.0, 0.0])
    rng = np.random.default_rng(12)
    for _ in range(5):
        centroid = rng.uniform(-20, 20, 3)
        for sign in (1.0, -1.0):   # head toward the source, then tail toward it
            axis = sign * (centroid - source) / np.linalg.norm(centroid - source)
            pose = RobotPose(centroid, axis)
            ray = (centroid - source) / np.linalg.norm(centroid - source)
            # (to 0.1 um: the ray grazes the apex, where the cone's discriminant is round-off)
            assert robot_chords(ROBOT_1, pose, source, ray[None, :])[0] == \
                pytest.approx(ROBOT_1.length_mm, abs=1e-4)


def test_broadside_chords_through_cylinder_and_cone() -> None:
    body = ROBOT_1
    # Axis along world z, centroid at the origin, rays along +x through points on the axis.
    pose = RobotPose(np.zeros(3), VERTICAL)
    tail_z = body.tail_offset_mm
    heights = np.array([tail_z + 0.5 * (body.length_mm - body.cone_length_mm),   # cylinder middle
                        body.head_offset_mm - 0.5 * body.cone_length_mm])         # cone middle
    source = np.array([-500.0, 0.0, 0.0])
    targets = np.stack([np.zeros(2), np.zeros(2), heights], axis=1)
    dirs = targets - source
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    chords = robot_chords(body, pose, source, dirs)
    slope = math.tan(math.radians(body.tip_angle_deg / 2))
    # Rays are tilted by atan(z / 500) from the perpendicular: chord grows by 1/cos of that tilt.
    tilt = np.cos(np.arctan2(heights, 500.0))
    assert chords[0] == pytest.approx(body.diameter_mm / tilt[0], rel=1e-9)
    assert chords[1] == pytest.approx(2 * slope * 0.5 * body.cone_length_mm / tilt[1], rel=2e-3)


def test_sphere_and_mitred_vessel_volumes() -> None:
    source, dirs, cell = parallel_rays(30.0, 500)
    assert sphere_chords(np.zeros(3), 2.0, source, dirs).sum() * cell == \
        pytest.approx(4 / 3 * math.pi * 8.0, rel=3e-3)
    # A bent vessel: mitred joints make the tube's volume pi r^2 times the centreline's length.
    t = np.linspace(0, math.pi, 25)
    centreline = np.stack([20 * np.cos(t), 12 * np.sin(t) - 6, 4 * np.sin(2 * t)], axis=1)
    vessel = VesselPhantom(centreline, radius_mm=1.5, attenuation_per_mm=0.05)
    length = np.linalg.norm(np.diff(centreline, axis=0), axis=1).sum()
    assert vessel_chords(vessel, source, dirs).sum() * cell == \
        pytest.approx(math.pi * 1.5 ** 2 * length, rel=3e-3)


# ---------------------------------------------------------------------------- image formation
def attenuation_image(renderer: BiplaneRenderer, pair, name: str) -> np.ndarray:
    """-log(I / I0) from a noise-free, blur-free rendering."""
    flat = renderer.expected_photons(name)
    return -np.log(np.maximum(renderer.to_photons(pair.images[name]), 1e-9) / flat)


@pytest.mark.parametrize("supersample, mu, rel", [
    (1, 1.0, 0.02),     # pixel-centre sampling: a Riemann sum of the line integral
    (4, 0.05, 0.01),    # faint: -log(mean T) ~ mean(mu L), so anti-aliasing must preserve the sum
    (4, 1.0, 0.06),     # dense: edge pixels average T, not mu L (partial-volume effect): sum is low
])
def test_attenuation_integral_matches_volume(supersample: int, mu: float, rel: float) -> None:
    views = biplane_views(elevation_deg=10.0, **SMALL)
    body = RobotBody(10.0, 2.0, 20.0, attenuation_per_mm=mu)
    renderer = BiplaneRenderer(views, body, settings=ImagingSettings.exact(supersample))
    rng = np.random.default_rng(3)
    for _ in range(3):
        pose = RobotPose(rng.uniform(-8, 8, 3), random_unit(rng))
        pair = renderer.render(pose)
        for name, view in views.items():
            cam = view.to_camera(pose.centroid_mm[None, :])[0]
            x, y = cam[0] / cam[2], cam[1] / cam[2]
            # Sum over pixels of the line integral = fx fy * integral of sqrt(1+x^2+y^2)/Z^2 dV.
            expected = (mu * body.volume_mm3 * view.K[0, 0] * view.K[1, 1]
                        * math.sqrt(1 + x * x + y * y) / cam[2] ** 2)
            measured = attenuation_image(renderer, pair, name).sum()
            assert measured == pytest.approx(expected, rel=rel)
            if rel > 0.05:
                assert measured < expected


def test_attenuation_weighted_centroid_is_the_projected_volume_centroid() -> None:
    """What the recognition relies on: moments of -log(I/I0) land on the projected 3D centroid
    (a binary silhouette's centroid would not, for a cone-tipped body), with lens distortion."""
    views = biplane_views(dist=(-0.3, 0.1, 0.002, -0.002, 0.0), **SMALL)
    renderer = BiplaneRenderer(views, ROBOT_1, settings=ImagingSettings.exact())
    rng = np.random.default_rng(13)
    poses = [RobotPose(rng.uniform(-12, 12, 3), random_unit(rng)) for _ in range(4)]
    poses.append(RobotPose(np.array([2.0, -1.0, 1.0]), np.array([0.3, 0.3, 1.0])))  # broadside
    # Broadside, the silhouette's centroid lies this far (mm) headward of the volume's.
    cyl, cone, d = ROBOT_1.length_mm - ROBOT_1.cone_length_mm, ROBOT_1.cone_length_mm, 2.0
    area_centroid = (d * cyl * cyl / 2 + d * cone / 2 * (cyl + cone / 3)) / (d * cyl + d * cone / 2)
    shift_mm = area_centroid - ROBOT_1.centroid_from_tail_mm
    px_per_mm = views["p"].K[0, 0] / 500.0
    broadside_seen = 0
    for pose in poses:
        pair = renderer.render(pose)
        for name in views:
            truth = pair.truth[name]
            weight = attenuation_image(renderer, pair, name)
            weight[weight < 1e-3] = 0.0            # quantisation of the 16-bit background
            v, u = np.mgrid[0:weight.shape[0], 0:weight.shape[1]]
            centroid = np.array([(weight * u).sum(), (weight * v).sum()]) / weight.sum()
            assert np.linalg.norm(centroid - truth.centroid_px) < 0.1
            seen = np.linalg.norm(truth.head_px - truth.tail_px) / (ROBOT_1.length_mm * px_per_mm)
            if seen > 0.9:                          # nearly broadside: the cone's effect shows
                x0, y0, x1, y1 = truth.bbox
                silhouette = np.zeros_like(weight)
                silhouette[y0:y1, x0:x1] = truth.coverage
                binary = np.array([(silhouette * u).sum(), (silhouette * v).sum()]) / silhouette.sum()
                axis = (truth.head_px - truth.tail_px) / np.linalg.norm(truth.head_px - truth.tail_px)
                # Tilted out of the image plane the end faces add to the silhouette: half is safe.
                assert (binary - truth.centroid_px) @ axis > 0.5 * shift_mm * seen * px_per_mm
                broadside_seen += 1
    assert broadside_seen >= 2


def test_measured_path_length_at_the_cylinder_middle_is_the_diameter() -> None:
    views = biplane_views(**SMALL)
    renderer = BiplaneRenderer(views, ROBOT_1, settings=ImagingSettings.exact(1))
    cylinder_middle = ROBOT_1.tail_offset_mm + 0.5 * (ROBOT_1.length_mm - ROBOT_1.cone_length_mm)
    pair = renderer.render(RobotPose(np.array([0.0, 0.0, -cylinder_middle]), VERTICAL))
    for name in views:
        mu_l = attenuation_image(renderer, pair, name)[111, 127]   # the principal point's pixel
        assert mu_l / ROBOT_1.attenuation_per_mm == pytest.approx(ROBOT_1.diameter_mm, rel=2e-3)


def test_rendered_vessel_attenuation_matches_its_volume() -> None:
    """The whole bent tube is traced (no segment's box cut short at a mitred joint)."""
    views = biplane_views(**SMALL)
    t = np.linspace(0, math.pi, 13)        # 15 degree bends
    centreline = np.stack([20 * np.cos(t), 12 * np.sin(t) - 6, 4 * np.sin(2 * t)], axis=1)
    vessel = VesselPhantom(centreline, radius_mm=1.5, attenuation_per_mm=0.05)
    exact = ImagingSettings.exact()
    renderer = BiplaneRenderer(views, None, vessel=vessel, settings=exact)
    flat = BiplaneRenderer(views, None, settings=exact)
    mids = 0.5 * (centreline[1:] + centreline[:-1])
    lengths = np.linalg.norm(np.diff(centreline, axis=0), axis=1)
    for name, view in views.items():
        cam = view.to_camera(mids)
        # Per segment: fx fy * mu * volume * sqrt(1 + x^2 + y^2) / Z^2 at its middle.
        oblique = np.sqrt(1 + (cam[:, 0] / cam[:, 2]) ** 2 + (cam[:, 1] / cam[:, 2]) ** 2)
        expected = (view.K[0, 0] * view.K[1, 1] * 0.05 * math.pi * 1.5 ** 2
                    * np.sum(lengths * oblique / cam[:, 2] ** 2))
        measured = -np.log(renderer.expected_photons(name) / flat.expected_photons(name)).sum()
        assert measured == pytest.approx(expected, rel=0.01)


def test_robot_in_a_vessel_displaces_the_contrast() -> None:
    views = biplane_views(**SMALL)
    vessel = VesselPhantom(np.array([[0.0, 0.0, -30.0], [0.0, 0.0, 30.0]]), 3.0, 0.05)
    renderer = BiplaneRenderer(views, ROBOT_1, vessel=vessel, settings=ImagingSettings.exact(1))
    empty = BiplaneRenderer(views, None, settings=ImagingSettings.exact(1))
    cylinder_middle = ROBOT_1.tail_offset_mm + 0.5 * (ROBOT_1.length_mm - ROBOT_1.cone_length_mm)
    pair = renderer.render(RobotPose(np.array([0.0, 0.0, -cylinder_middle]), VERTICAL))
    for name in views:
        flat = empty.expected_photons(name)[111, 127]
        mu_l = -math.log(renderer.to_photons(pair.images[name])[111, 127] / flat)
        # Through the axis: 2 mm of robot and the 6 mm lumen minus the robot's 2 mm of contrast.
        assert mu_l == pytest.approx(1.0 * 2.0 + 0.05 * (6.0 - 2.0), rel=2e-3)


def test_several_vessels_attenuate_together() -> None:
    views = biplane_views(**SMALL)
    a = VesselPhantom(np.array([[-30.0, 0.0, -5.0], [30.0, 0.0, 5.0]]), 2.0, 0.05)
    b = VesselPhantom(np.array([[0.0, -30.0, 8.0], [2.0, 0.0, 0.0], [0.0, 30.0, -8.0]]), 2.5, 0.04)
    exact = ImagingSettings.exact(1)
    both = BiplaneRenderer(views, None, vessel=[a, b], settings=exact)
    only = [BiplaneRenderer(views, None, vessel=v, settings=exact) for v in (a, b)]
    flat = BiplaneRenderer(views, None, settings=exact)
    for name in views:
        t_a, t_b = (r.expected_photons(name) / flat.expected_photons(name) for r in only)
        assert t_a.min() < 0.9 and t_b.min() < 0.9                    # both are visible
        np.testing.assert_allclose(both.expected_photons(name) / flat.expected_photons(name),
                                   t_a * t_b, rtol=1e-6)


def test_robot_is_darker_than_its_surroundings_in_a_vessel() -> None:
    views = biplane_views(**SMALL)
    t = np.linspace(-1, 1, 12)
    vessel = VesselPhantom(np.stack([12 * t, 6 * t, 15 * t * t], axis=1), 3.0, 0.04)
    noisy = BiplaneRenderer(views, ROBOT_1, vessel=vessel, seed=4)
    exact = BiplaneRenderer(views, ROBOT_1, vessel=vessel, settings=ImagingSettings.exact())
    pose = RobotPose(np.array([0.0, 0.0, 0.0]), np.array([0.6, 0.3, 0.2]))
    image_pair, exact_pair = noisy.render(pose), exact.render(pose)
    for name in views:
        x0, y0, x1, y1 = image_pair.truth[name].bbox
        robot = attenuation_image(exact, exact_pair, name) > 0.5 + 0.04 * 6.0   # beyond the vessel
        image = image_pair.images[name].astype(float)
        ring = np.zeros_like(robot)
        ring[max(y0 - 6, 0):y1 + 6, max(x0 - 6, 0):x1 + 6] = True
        ring[y0 - 1:y1 + 1, x0 - 1:x1 + 1] = False
        assert robot.sum() > 50
        assert image[robot].mean() < 0.7 * image[ring].mean()


def test_field_is_not_uniform_and_noise_is_poisson() -> None:
    views = biplane_views(**SMALL)
    settings = ImagingSettings(blur_sigma_px=0.0)
    renderer = BiplaneRenderer(views, None, settings=settings, seed=5)
    flat = renderer.expected_photons("p")
    assert flat.max() / flat.min() > 1.3      # heel + vignette: no global threshold fits
    photons = renderer.to_photons(renderer.render(None).images["p"])
    residual = (photons - flat) / np.sqrt(flat)
    assert abs(residual.mean()) < 0.02 and residual.var() == pytest.approx(1.0, rel=0.05)


def test_low_counts_are_exact_poisson() -> None:
    views = biplane_views(**SMALL)
    # Full scale at 5x the mean count so no Poisson draw saturates.
    settings = ImagingSettings(photons_per_pixel=5.0, blur_sigma_px=0.0, dark_level=100,
                               full_scale_fraction=0.2)
    renderer = BiplaneRenderer(views, None, settings=settings, seed=6)
    photons = renderer.to_photons(renderer.render(None).images["q"])
    assert photons.min() >= 0
    # Integer photon counts survive the 16-bit conversion (gain >> 1 grey level per photon).
    np.testing.assert_allclose(photons, np.round(photons), atol=0.5 / renderer.gain + 1e-9)


def test_few_photons_behind_a_dense_magnet_are_exact_poisson() -> None:
    views = biplane_views(**SMALL)
    dense = RobotBody(10.0, 2.0, 20.0, attenuation_per_mm=2.5)   # NdFeB: <1 % gets through 2 mm
    pose = RobotPose(np.zeros(3), np.array([0.2, 0.3, 1.0]))
    expected = BiplaneRenderer(views, dense, settings=ImagingSettings(
        noise=False, blur_sigma_px=0.0)).render(pose)
    noisy = BiplaneRenderer(views, dense, settings=ImagingSettings(blur_sigma_px=0.0), seed=14)
    core_means, core_counts = [], []
    for _ in range(4):
        pair = noisy.render(pose)
        for name in views:
            mean = noisy.to_photons(expected.images[name])
            photons = noisy.to_photons(pair.images[name])
            core = mean < 30
            assert core.sum() > 30
            np.testing.assert_allclose(photons[core], np.round(photons[core]), atol=0.02)
            core_means.append(mean[core])
            core_counts.append(photons[core])
    means, counts = np.concatenate(core_means), np.concatenate(core_counts)
    assert counts.min() >= 0
    # Unbiased and with Poisson variance: the standardised residuals average 0 and have variance 1.
    z = (counts - means) / np.sqrt(np.maximum(means, 1e-9))
    assert abs(z.mean()) < 4 / math.sqrt(len(z)) and z.var() == pytest.approx(1.0, rel=0.15)


def test_same_seed_same_frames() -> None:
    views = biplane_views(**SMALL)
    pose = RobotPose(np.array([1.0, 2.0, 3.0]), np.array([0.2, 0.9, 0.1]))
    a = BiplaneRenderer(views, ROBOT_1, seed=7).render(pose)
    b = BiplaneRenderer(views, ROBOT_1, seed=7).render(pose)
    c = BiplaneRenderer(views, ROBOT_1, seed=8).render(pose)
    for name in views:
        assert a.images[name].dtype == np.uint16 and a.images[name].shape == (223, 255)
        np.testing.assert_array_equal(a.images[name], b.images[name])
        assert np.any(a.images[name] != c.images[name])


def test_pose_outside_the_field_of_view() -> None:
    views = biplane_views(**SMALL)
    renderer = BiplaneRenderer(views, ROBOT_1, seed=9)
    gone = renderer.render(RobotPose(np.array([0.0, 0.0, 150.0]), VERTICAL))
    for name in views:
        truth = gone.truth[name]
        assert not truth.in_view and truth.pixel_count == 0 and truth.bbox == (0, 0, 0, 0)
        assert truth.centroid_px[1] < 0                       # above the image, still the truth
    half = renderer.render(RobotPose(np.array([0.0, 0.0, 18.0]), VERTICAL))   # cut by the top edge
    for name in views:
        truth = half.truth[name]
        assert truth.in_view and not truth.fully_in_view and truth.bbox[1] == 0
    whole = renderer.render(RobotPose(np.zeros(3), VERTICAL))
    assert all(t.in_view and t.fully_in_view for t in whole.truth.values())
    # Behind the source of plane p: no crash, nothing in view there.
    behind = renderer.render(RobotPose(np.array([-600.0, 0.0, 0.0]), VERTICAL))
    assert not behind.truth["p"].in_view


def test_table_1_pixel_counts_at_the_default_geometry() -> None:
    """A robot broadside to a view covers its silhouette's area in pixels; over Table 1 the counts
    span about the paper's 200-3750 px (robot 4, 3 mm long, is below: it covers ~90 px)."""
    views = biplane_views()
    sin, cos = math.sin(math.radians(12.0)), math.cos(math.radians(12.0))
    # Perpendicular to p's optical axis (world x) and q's (world y), tilted off the pixel grid.
    broadside = {"p": np.array([0.0, sin, cos]), "q": np.array([sin, 0.0, cos])}
    counts = {}
    for rid, spec in load_robots().items():
        body = RobotBody(spec.length_mm, spec.diameter_mm, spec.tip_angle_deg, spec.attenuation_per_mm)
        renderer = BiplaneRenderer(views, body, settings=ImagingSettings.exact())
        for name, view in views.items():
            truth = renderer.render(RobotPose(np.array([0.3, -0.2, 0.1]), broadside[name])).truth[name]
            cyl = body.length_mm - body.cone_length_mm
            area_px = (body.diameter_mm * (cyl + body.cone_length_mm / 2)
                       * view.K[0, 0] * view.K[1, 1] / 500.0 ** 2)
            perimeter_px = 2 * (body.length_mm + body.diameter_mm) * view.K[0, 0] / 500.0
            assert abs(truth.pixel_count - area_px) < 0.05 * perimeter_px + 2, (rid, name)
            assert truth.area_px == pytest.approx(area_px, rel=0.01, abs=1.0)
            counts[rid, name] = truth.pixel_count
    assert 60 <= min(counts.values()) and max(counts.values()) <= 4500
    assert max(counts, key=counts.get)[0] == 6 and min(counts, key=counts.get)[0] == 4
