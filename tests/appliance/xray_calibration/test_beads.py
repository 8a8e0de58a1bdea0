"""Bead detection: sub-pixel centres on rendered X-ray images, rejection of overlaps, clear errors."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from appliance.errors import CalibrationError, InputDataError
from appliance.xray_calibration.beads import detect_beads
from appliance.xray_calibration.phantom import Phantom
from drivers.loopback.xray_render import BiplaneRenderer, TrueView


@pytest.mark.parametrize("name", ["p", "q"])
def test_every_bead_found_to_a_small_fraction_of_a_pixel(name: str, cube_images: dict[str, np.ndarray],
                                                         true_views: dict[str, TrueView], cube: Phantom) -> None:
    found = detect_beads(cube_images[name])
    truth = true_views[name].project(cube.points_mm)
    w, h = true_views[name].image_size
    margin = 8.0  # px: a bead cut by the image border is rejected, not measured
    inside = truth[(truth[:, 0] > margin) & (truth[:, 0] < w - 1 - margin)
                   & (truth[:, 1] > margin) & (truth[:, 1] < h - 1 - margin)]
    assert len(inside) > 40
    distance, _ = cKDTree(found.uv).query(inside)
    # The simulated cube is designed so no two beads overlap in either view: every one is found.
    assert len(found) == len(inside)
    assert np.sqrt(np.mean(distance ** 2)) < 0.05  # px; noise, blur and the heel gradient included
    assert np.abs(found.radius_px - found.radius_px.mean()).max() < 1.5


def test_overlapping_beads_are_rejected_not_averaged(true_views: dict[str, TrueView]) -> None:
    view = true_views["p"]
    # Two beads whose shadows overlap in view p (same ray direction, 1.2 mm apart sideways) and one alone.
    centres = np.array([[0.0, 0.0, 0.0], [0.0, 1.5, 0.4], [0.0, -25.0, 10.0]])
    images = BiplaneRenderer({"p": view}, None, beads=(centres, 1.0, 2.0), seed=1).render(None).images
    found = detect_beads(images["p"])
    assert len(found) == 1
    np.testing.assert_allclose(found.uv[0], view.project(centres[2:])[0], atol=0.1)
    assert len(found.rejected_uv) == 1


def test_bright_beads_on_a_dark_plate() -> None:
    image = np.full((120, 160), 1000.0)
    yy, xx = np.mgrid[:120, :160]
    for u, v in [(40.3, 30.7), (100.0, 80.25)]:
        image += 3000.0 * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * 2.0 ** 2))
    found = detect_beads(image.astype(np.uint16), bright=True)
    order = np.argsort(found.uv[:, 0])
    np.testing.assert_allclose(found.uv[order], [[40.3, 30.7], [100.0, 80.25]], atol=0.05)


def test_image_without_beads_is_a_clear_error(empty_images: dict[str, np.ndarray]) -> None:
    with pytest.raises(CalibrationError, match="view p image: no beads found"):
        detect_beads(empty_images["p"], what="view p image")


def test_uniform_and_malformed_images() -> None:
    with pytest.raises(CalibrationError, match="uniform"):
        detect_beads(np.full((64, 64), 500, np.uint16))
    with pytest.raises(InputDataError, match="2D grey image"):
        detect_beads(np.zeros((4, 4)))
