"""MayaCam 2.0: write then read gives the same view; XMALab's text reads; malformed files are named."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from appliance.errors import CalibrationError
from appliance.geometry import Calibration, View
from appliance.xray_calibration.mayacam import (
    export_calibration,
    format_mayacam,
    import_calibration,
    parse_mayacam,
    read_mayacam,
    write_mayacam,
)

# As XMALab exports it (layout from its documentation; numbers ours).
XMALAB_TEXT = """image size
1024,768

camera matrix
5120.5,0,511.25
0,5121.75,383.5
0,0,1

rotation
0,1,0
0,0,-1
-1,0,0

translation
0.5
-1.25
500

"""


def _view(dist: tuple[float, ...] = (0, 0, 0, 0, 0)) -> View:
    return View.look_at("p", [-498.7, 3.1, 2.2], [0.4, -0.3, 0.2], focal_px=2561.234567891,
                        image_size=(768, 672), dist=dist, principal_point=(383.77, 335.12))


@pytest.mark.parametrize("dist", [(0, 0, 0, 0, 0), (-0.21, 0.034, 1e-4, -2e-4, 0.002)])
def test_round_trip_gives_the_same_view(tmp_path: Path, dist: tuple[float, ...]) -> None:
    view = _view(dist)
    again = read_mayacam(write_mayacam(tmp_path / "cam.txt", view), "p")
    assert again.image_size == view.image_size
    for key in ("K", "dist", "R", "t"):
        np.testing.assert_array_equal(getattr(again, key), getattr(view, key))
    uv = view.project(np.array([[10.0, -20.0, 30.0]]))
    np.testing.assert_array_equal(again.project(np.array([[10.0, -20.0, 30.0]])), uv)


def test_layout_sections_and_order() -> None:
    lines = format_mayacam(_view((-0.2, 0, 0, 0, 0))).splitlines()
    assert lines[0] == "image size" and lines[1] == "768,672"
    assert [lines[i] for i in (3, 8, 13, 18)] == ["camera matrix", "rotation", "translation", "undistortion"]
    assert len(lines[19].split(",")) == 8  # XMALab's eight OpenCV coefficients
    assert "undistortion" not in format_mayacam(_view())


def test_reads_xmalab_export() -> None:
    view = parse_mayacam(XMALAB_TEXT, "q")
    assert view.image_size == (1024, 768)
    assert view.K[0, 0] == 5120.5 and view.K[1, 2] == 383.5
    np.testing.assert_allclose(view.source_mm, -view.R.T @ np.array([0.5, -1.25, 500]))
    assert not view.has_distortion


def test_calibration_export_import(tmp_path: Path) -> None:
    q = View.look_at("q", [2.0, -501.0, 0.0], [0, 0, 0], focal_px=2550.0, image_size=(768, 672))
    calibration = Calibration.from_views(_view(), q)
    paths = export_calibration(calibration, tmp_path / "mayacam")
    again = import_calibration(paths["p"], paths["q"])
    for name in ("p", "q"):
        np.testing.assert_array_equal(again.views[name].P, calibration.views[name].P)


@pytest.mark.parametrize("text, message", [
    (XMALAB_TEXT.replace("rotation", "rotatio"), "outside any section"),
    (XMALAB_TEXT.replace("translation\n0.5\n-1.25\n500\n", ""), "missing section.*translation"),
    (XMALAB_TEXT.replace("0,0,-1", "0,0"), "section 'rotation': expected 3 line"),
    (XMALAB_TEXT.replace("5120.5", "fx"), "line 5: section 'camera matrix': not numbers"),
    (XMALAB_TEXT.replace("0,0,-1", "0,0,1"), "not a rotation"),
    (XMALAB_TEXT + "undistortion\n0.1,0,0,0,0,0.5,0,0\n", "k4 k5 k6"),
    (XMALAB_TEXT.replace("1024,768", "1024.5,768"), "two positive integers"),
])
def test_malformed_files(text: str, message: str) -> None:
    with pytest.raises(CalibrationError, match=message):
        parse_mayacam(text, "p", source="cam.txt")
