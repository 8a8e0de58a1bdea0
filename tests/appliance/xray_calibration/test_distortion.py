"""Image-intensifier distortion (pincushion + S-distortion) measured from a perforated plate and undone."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from appliance.errors import CalibrationError
from appliance.xray_calibration.distortion import GridCorrection, correction_from_image, fit_correction

SIZE = (400, 360)
CENTRE = np.array([(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2])


def distort(uv: np.ndarray) -> np.ndarray:
    """A plausible intensifier: 6 % pincushion at the corner and a swirl growing with radius (S-distortion)."""
    d = (uv - CENTRE) / 200.0
    r2 = np.sum(d * d, axis=1, keepdims=True)
    d = d * (1 + 0.05 * r2)
    angle = 0.03 * r2[:, 0]
    c, s = np.cos(angle), np.sin(angle)
    d = np.column_stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1]])
    return CENTRE + 200.0 * d + np.array([0.7, -0.4])


def _plate_image(pitch_px: float = 20.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Noisy image of a hole lattice seen through the distortion; returns image and ideal hole positions."""
    ii, jj = np.meshgrid(np.arange(-12, 13), np.arange(-11, 12))
    ideal = CENTRE + pitch_px * np.column_stack([ii.ravel(), jj.ravel()]) @ np.array([[1.0, 0.02], [-0.02, 1.0]])
    observed = distort(ideal)
    keep = np.all((observed > 6) & (observed < np.array(SIZE) - 7), axis=1)
    yy, xx = np.mgrid[:SIZE[1], :SIZE[0]]
    image = np.full((SIZE[1], SIZE[0]), 4000.0)
    for u, v in observed[keep]:
        near = (np.abs(xx - u) < 8) & (np.abs(yy - v) < 8)
        image[near] += 20000.0 * np.exp(-((xx[near] - u) ** 2 + (yy[near] - v) ** 2) / (2 * 2.2 ** 2))
    image += np.random.default_rng(seed).normal(0, 60, image.shape)
    return np.clip(image, 0, 65535).astype(np.uint16), ideal[keep]


def _straightness_px(corrected: np.ndarray, ideal: np.ndarray) -> float:
    """Largest deviation of corrected points from the best affine image of the ideal lattice."""
    design = np.column_stack([ideal, np.ones(len(ideal))])
    affine, *_ = np.linalg.lstsq(design, corrected, rcond=None)
    return float(np.max(np.linalg.norm(design @ affine - corrected, axis=1)))


@pytest.fixture(scope="module")
def plate() -> tuple[np.ndarray, np.ndarray]:
    return _plate_image()


@pytest.mark.parametrize("method", ["polynomial", "local"])
def test_correction_restores_a_regular_lattice(plate: tuple[np.ndarray, np.ndarray], method: str) -> None:
    image, _ = plate
    correction = correction_from_image(image, method=method)
    assert np.sqrt(np.mean(correction.residual_px() ** 2)) < 0.1
    # Points that are not holes: a grid between the holes, through the same distortion.
    rng = np.random.default_rng(1)
    ideal = CENTRE + rng.uniform(-150, 150, (200, 2)) * np.array([1.0, 0.85])
    observed = distort(ideal)
    before = _straightness_px(observed, ideal)
    after = _straightness_px(correction.apply(observed), ideal)
    assert before > 5.0  # the distortion is large...
    assert after < 0.25  # ...and what is left is sub-pixel


def test_save_and_load_give_the_same_map(plate: tuple[np.ndarray, np.ndarray], tmp_path: Path) -> None:
    for method in ("polynomial", "local"):
        correction = correction_from_image(plate[0], method=method)
        again = GridCorrection.load(correction.save(tmp_path / f"{method}.yaml"))
        points = np.array([[10.0, 20.0], [200.0, 180.0], [390.0, 350.0]])
        np.testing.assert_allclose(again.apply(points), correction.apply(points), atol=1e-9)


def test_too_few_holes_and_bad_files(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="holes"):
        fit_correction(np.array([[0.0, 0.0], [20.0, 0.0], [0.0, 20.0], [20.0, 20.0], [40.0, 0.0]]), (64, 64))
    (tmp_path / "bad.yaml").write_text("method: magic\n")
    with pytest.raises(CalibrationError, match="bad.yaml: not a valid distortion map"):
        GridCorrection.load(tmp_path / "bad.yaml")
