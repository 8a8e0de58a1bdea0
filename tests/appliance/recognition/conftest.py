"""Fixtures shared by the recognition tests: small rendered biplane views (384 x 336 px, 90 x 80 mm field) and
their true calibration, built once per session. A module that needs another geometry defines its own ``views``
or ``calibration`` fixture, which takes precedence over these."""
from __future__ import annotations

import pytest

from appliance.geometry import Calibration, View
from drivers.loopback.xray_render import biplane_views


@pytest.fixture(scope="session")
def views() -> dict[str, object]:
    return biplane_views(image_size=(384, 336), fov_mm=(90.0, 80.0))


@pytest.fixture(scope="session")
def calibration(views: dict[str, object]) -> Calibration:
    return Calibration.from_views(*(View(n, v.K, v.dist, v.R, v.t, v.image_size)  # type: ignore[attr-defined]
                                    for n, v in sorted(views.items())))
