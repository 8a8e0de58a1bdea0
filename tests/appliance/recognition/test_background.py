"""The open-field background: what the cold path's coarse estimate keeps (the smooth field) and removes
(anything narrower than its scale), and the shape of what it hands to segmentation."""
from __future__ import annotations

import cv2
import numpy as np

from appliance.recognition import log_background


def _field(h: int, w: int) -> np.ndarray:
    """A heel-effect and vignetting-like open field in gray levels above a dark level of 1000."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    r2 = ((x - 0.45 * w) ** 2 + (y - 0.55 * h) ** 2) / (0.8 * max(h, w)) ** 2
    return 20000.0 * (1.0 - 0.3 * x / w) * (1.0 - 0.5 * r2)


def test_the_field_is_kept_and_a_robot_and_a_vessel_are_closed_over() -> None:
    h, w = 384, 320
    field = _field(h, w)
    rng = np.random.default_rng(5)
    attenuation = np.zeros((h, w))
    attenuation[150:162, 80:200] = 1.2          # a robot, 12 px wide
    yy, xx = np.mgrid[0:h, 0:w]
    attenuation += 0.3 * (np.abs(xx - 0.6 * yy - 60) < 12)   # a vessel, 24 px wide, crossing it
    image = (1000 + field * np.exp(-attenuation) + rng.normal(0, 40, (h, w))).clip(0, 65535).astype(np.uint16)
    bg = log_background(image, 48, 1000.0)
    truth = np.log(field)
    inner = (slice(24, h - 24), slice(24, w - 24))   # the closing's border rows follow the frame's edge
    error = np.asarray(bg)[inner] - truth[inner]
    # Within 3.5 % of the field everywhere, curvature included (measured: 2.8 %; the closing at the
    # detection grid, before issue 8, 2.0 %): far below the robot's 1.2, and smooth, so the local
    # baseline that segmentation measures around the body takes it out.
    assert np.abs(error).max() < 0.035, np.abs(error).max()
    # Under the robot and the vessel the estimate is the open field, not their attenuation (a 2 % bias).
    assert np.abs(bg[140:172, 70:210] - truth[140:172, 70:210]).max() < 0.03
    # The coarse attenuation sees the robot at its (block-averaged) strength and the vessel weaker.
    a = bg.coarse_attenuation
    assert 1.0 < float(a[38:40, 25:45].mean()) < 1.3
    assert float(a[10, 40]) < 0.4


def test_the_pinned_shape_of_the_background() -> None:
    image = np.full((200, 152), 21000, dtype=np.uint16)
    bg = log_background(image, 48, 1000.0)
    for grid in (bg.coarse, bg.coarse_log, bg.coarse_attenuation):
        assert grid.dtype == np.float32 and grid.flags.c_contiguous and grid.shape == (50, 38)
    assert (bg.fx, bg.fy, bg.shape) == (4.0, 4.0, (200, 152))
    full = cv2.resize(bg.coarse, (152, 200), interpolation=cv2.INTER_LINEAR)
    np.testing.assert_allclose(bg[10:60, 100:152], full[10:60, 100:152], atol=2e-5)
    np.testing.assert_allclose(np.asarray(bg), np.log(20000.0), atol=1e-5)
