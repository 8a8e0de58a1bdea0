"""Shared simulated bench for the X-ray calibration tests: a perturbed biplane geometry and its phantom images.

The world's true geometry is the renderer's views, moved 1.5 degrees and ~3 mm away from the nominal
equipment geometry (which the tests pass as ``--initial``), as on a real bench.
"""
from __future__ import annotations

import numpy as np
import pytest

from appliance.geometry import Calibration, View
from appliance.xray_calibration.phantom import Phantom, make_cube_phantom
from drivers.loopback.xray_render import BiplaneRenderer, ImagingSettings, TrueView, biplane_views
from drivers.loopback.scene_builders import perturb_view

BEAD_RADIUS_MM = 1.0
BEAD_MU_PER_MM = 2.0





def as_view(view: TrueView) -> View:
    return View(view.name, view.K, view.dist, view.R, view.t, view.image_size)


@pytest.fixture(scope="session")
def nominal_views() -> dict[str, TrueView]:
    # A smaller detector than the bench's keeps the tests quick; the field of view is the paper's.
    return biplane_views(image_size=(512, 448))


@pytest.fixture(scope="session")
def true_views(nominal_views: dict[str, TrueView]) -> dict[str, TrueView]:
    rng = np.random.default_rng(11)
    return {name: perturb_view(view, rng) for name, view in nominal_views.items()}


@pytest.fixture(scope="session")
def nominal_calibration(nominal_views: dict[str, TrueView]) -> Calibration:
    return Calibration.from_views(as_view(nominal_views["p"]), as_view(nominal_views["q"]))


@pytest.fixture(scope="session")
def cube() -> Phantom:
    return make_cube_phantom()


@pytest.fixture(scope="session")
def cube_images(true_views: dict[str, TrueView], cube: Phantom) -> dict[str, np.ndarray]:
    renderer = BiplaneRenderer(true_views, None, beads=(cube.points_mm, BEAD_RADIUS_MM, BEAD_MU_PER_MM),
                               settings=ImagingSettings(), seed=5)
    return renderer.render(None).images


@pytest.fixture(scope="session")
def empty_images(true_views: dict[str, TrueView]) -> dict[str, np.ndarray]:
    return BiplaneRenderer(true_views, None, seed=6).render(None).images
