"""body_prior.end_clutter's compiled pixel work (body_kernels.end_spread) against the numpy formulation it
replaced, written out here: a tilted body's weights over a background with a vessel-like band and noise, tips
anywhere (near the image's edge too), must give the same number to the bit; and ends_used names only the ends
place_body reads."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from appliance.recognition import RecognitionSettings
from appliance.recognition.body_prior import BodyModel, end_clutter, ends_used
from appliance.recognition.posture import Posture
from appliance.recognition.segmentation import Blob, Roi, attenuation
from appliance.robots import load_robots

SETTINGS = RecognitionSettings()


def _reference(image, log_bg, blob, centroid_px, tips_px, settings):
    """The numpy end_clutter (masks from mgrid, cv2.dilate of the support, np.percentile)."""
    half = 0.5 * blob.width_px
    reach = half + 7
    cu, cv = float(centroid_px[0]), float(centroid_px[1])
    out = []
    h, w = image.shape
    for tip in np.asarray(tips_px, dtype=np.float64):
        tu, tv = float(tip[0]), float(tip[1])
        au, av = tu - cu, tv - cv
        norm = math.hypot(au, av)
        if not norm > 0:
            out.append(math.inf)
            continue
        au, av = au / norm, av / norm
        x0, x1 = max(0, math.floor(tu - reach - 1)), min(w, math.ceil(tu + reach + 2))
        y0, y1 = max(0, math.floor(tv - reach - 1)), min(h, math.ceil(tv + reach + 2))
        if x1 - x0 < 4 or y1 - y0 < 4:
            out.append(math.inf)
            continue
        a = cv2.blur(attenuation(image, log_bg, Roi(x0, y0, x1, y1), settings.dark_level), (3, 3))[1:-1, 1:-1]
        ys, xs = np.mgrid[y0 + 1:y1 - 1, x0 + 1:x1 - 1]
        gs = (xs - tu) * au + (ys - tv) * av
        gt = np.abs(-(xs - tu) * av + (ys - tv) * au)
        # the body's support grown by 3 px (elliptic element)
        bx0, by0, bx1, by1 = x0 + 1 - 3, y0 + 1 - 3, x1 - 1 + 3, y1 - 1 + 3
        inside = np.zeros((by1 - by0, bx1 - bx0), dtype=np.uint8)
        win = blob.window
        for r in range(blob.weights.shape[0]):
            for c in range(blob.weights.shape[1]):
                y, x = win.y0 + r, win.x0 + c
                if blob.weights[r, c] != 0 and by0 <= y < by1 and bx0 <= x < bx1:
                    inside[y - by0, x - bx0] = 1
        grown = cv2.dilate(inside, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (7, 7)))[3:-3, 3:-3].astype(bool)
        near = ~grown & (gs >= -(2.0 * half + 7)) & (gs <= reach) & (gt <= reach)
        values = a[near]
        if values.size < 16:
            out.append(math.inf)
            continue
        lo, hi = np.percentile(values, (5.0, 95.0))
        out.append(max(float(hi - lo) - 3.29 * blob.sigma / 3.0, 0.0) / max(blob.peak, 1e-6))
    return out[0], out[1]


def _scene(rng: np.random.Generator, size: int = 160):
    """An image (uint16), its dense log background, a body blob (weights on a window) and its centroid and tips."""
    yy, xx = np.mgrid[0:size, 0:size]
    log_bg = np.full((size, size), math.log(30000.0), dtype=np.float32)
    angle = rng.uniform(0, math.pi)
    band = np.abs((xx - rng.uniform(0, size)) * math.sin(angle) - (yy - rng.uniform(0, size)) * math.cos(angle))
    atten = 0.3 * np.exp(-(band / rng.uniform(3, 12)) ** 2)   # a vessel-like band
    cu, cv = rng.uniform(-10, size + 10, size=2)
    theta, half_len, radius = rng.uniform(0, 2 * math.pi), rng.uniform(8, 30), rng.uniform(2, 6)
    du, dv = math.cos(theta), math.sin(theta)
    along = (xx - cu) * du + (yy - cv) * dv
    across = np.abs(-(xx - cu) * dv + (yy - cv) * du)
    body = (np.abs(along) <= half_len) & (across <= radius)
    atten = atten + 0.8 * body
    image = np.clip(30000.0 * np.exp(-atten) + rng.normal(0, 60, atten.shape), 0, 65535).astype(np.uint16)
    x0, y0 = max(0, int(cu - half_len - 12)), max(0, int(cv - half_len - 12))
    x1, y1 = min(size, int(cu + half_len + 12)), min(size, int(cv + half_len + 12))
    if x1 - x0 < 2 or y1 - y0 < 2:
        return None
    support = cv2.dilate(body.astype(np.uint8), np.ones((5, 5), np.uint8))[y0:y1, x0:x1]
    weights = np.where(support != 0, atten[y0:y1, x0:x1], 0.0).astype(np.float32)
    blob = Blob(window=Roi(x0, y0, x1, y1), weights=weights, mask=support != 0, pixel_count=int(body.sum()),
                peak=0.8, baseline=0.0, sigma=float(rng.uniform(0.001, 0.01)), strength=1.0,
                centroid_px=(cu, cv), touches_border=False, width_px=2 * radius, clutter=0.5)
    tips = np.array([[cu + half_len * du, cv + half_len * dv], [cu - half_len * du, cv - half_len * dv]])
    return image, log_bg, blob, np.array([cu, cv]), tips


def test_compiled_end_clutter_is_the_numpy_one_to_the_bit() -> None:
    rng = np.random.default_rng(8)
    compared = finite = 0
    for _ in range(60):
        scene = _scene(rng)
        if scene is None:
            continue
        image, log_bg, blob, centroid, tips = scene
        expected = _reference(image, log_bg, blob, centroid, tips, SETTINGS)
        assert end_clutter(image, log_bg, blob, centroid, tips, SETTINGS) == expected
        compared += 1
        finite += sum(math.isfinite(v) for v in expected)
    assert compared >= 40 and finite >= 40   # the numbers compared, not only the edge cases


def test_an_end_not_asked_for_is_not_measured() -> None:
    image, log_bg, blob, centroid, tips = _scene(np.random.default_rng(3), 200)
    both = end_clutter(image, log_bg, blob, centroid, tips, SETTINGS)
    head_only = end_clutter(image, log_bg, blob, centroid, tips, SETTINGS, (True, False))
    assert head_only[0] == both[0] and math.isnan(head_only[1])


@pytest.mark.parametrize("robot_id, tail_used", [(4, False), (6, True)])
def test_ends_used_are_those_place_body_reads(robot_id: int, tail_used: bool) -> None:
    body = BodyModel.of(load_robots()[robot_id])
    posture = Posture(frame=0, t=0.0, ok=True, centroid_mm=np.zeros(3), direction=np.array([1.0, 0.0, 0.0]),
                      tips_mm=np.zeros((2, 3)), head_identified=True, length_mm=body.length_mm, views={})
    assert ends_used(posture, body, SETTINGS) == (True, tail_used)
    posture.head_identified = False   # each end is the tail under one order of the tips
    assert ends_used(posture, body, SETTINGS) == (True, True)
    assert ends_used(Posture.lost(0, 0.0, "gone"), body, SETTINGS) is None
