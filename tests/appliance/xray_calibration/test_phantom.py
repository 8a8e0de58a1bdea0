"""Bead files: our CSV forms, XMALab's frame-specification CSV and references file, and clear errors."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from appliance.errors import CalibrationError, InputDataError
from appliance.xray_calibration.phantom import (
    MIN_BEADS,
    load_phantom,
    make_cube_phantom,
    parse_phantom,
    write_phantom,
)

CUBE = make_cube_phantom()


def test_plain_xyz_without_header_numbers_beads_from_one() -> None:
    text = "\n".join(f"{x},{y},{z}" for x, y, z in CUBE.points_mm)
    phantom = parse_phantom(text)
    assert phantom.ids[:3] == ("1", "2", "3")
    np.testing.assert_allclose(phantom.points_mm, CUBE.points_mm)


def test_header_and_id_column_with_text_ids_and_other_separators() -> None:
    text = "name; x; y; z\nA; 0; 0; 0\nB\t10\t0\t0\nC 0 10 0\nD,0,0,10\n"
    phantom = parse_phantom(text)
    assert phantom.ids == ("A", "B", "C", "D")
    np.testing.assert_allclose(phantom.points_mm[3], [0, 0, 10])


def test_xmalab_frame_specification_with_scale_header_and_references(tmp_path: Path) -> None:
    spec = tmp_path / "FrameSpec.csv"
    spec.write_text("s2.0,s2.0,s2.0,x y z\n" + "\n".join(f"{x},{y},{z}" for x, y, z in CUBE.points_mm) + "\n")
    refs = tmp_path / "References.csv"
    refs.write_text("1 origin\n5 xaxis\n9 yaxis\n")
    phantom = load_phantom(spec, refs)
    np.testing.assert_allclose(phantom.points_mm, 2.0 * CUBE.points_mm)
    assert phantom.references == {"1": "origin", "5": "xaxis", "9": "yaxis"}
    assert not phantom.bright_beads


def test_xmalab_white_header_marks_bright_beads() -> None:
    assert parse_phantom("white\n0,0,0\n1,0,0\n").bright_beads


def test_round_trip_through_write(tmp_path: Path) -> None:
    again = load_phantom(write_phantom(tmp_path / "beads.csv", CUBE))
    assert again.ids == CUBE.ids
    np.testing.assert_allclose(again.points_mm, CUBE.points_mm, atol=1e-6)


def test_too_few_beads_is_a_clear_error() -> None:
    phantom = parse_phantom("x,y,z\n0,0,0\n10,0,0\n0,10,0\n0,0,10\n")
    with pytest.raises(CalibrationError, match=f"4 beads; a phantom needs at least {MIN_BEADS}"):
        phantom.check_for_dlt()


def test_coplanar_phantom_is_refused_for_the_dlt() -> None:
    grid = "\n".join(f"{x},{y},0" for x in range(0, 50, 10) for y in range(0, 50, 10))
    with pytest.raises(CalibrationError, match="coplanar"):
        parse_phantom(grid, source="plate.csv").check_for_dlt()


@pytest.mark.parametrize("text, message", [
    ("x,y,z\n1,2,3\n4,5\n", "line 3: expected x,y,z or id,x,y,z, got 2 fields"),
    ("1,2,3\n4,five,6\n", "line 2: coordinates are not numbers"),
    ("", "no beads"),
    ("x,y,z\n", "no beads"),
    ("a,1,2,3\na,4,5,6\n", "duplicate bead ids"),
])
def test_malformed_files_name_the_line(text: str, message: str) -> None:
    with pytest.raises((InputDataError, CalibrationError), match=message):
        parse_phantom(text, source="beads.csv")


def test_unknown_bead_id_lists_known_ones() -> None:
    with pytest.raises(InputDataError, match="no bead with id '99'"):
        CUBE.index("99")


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(InputDataError, match="file not found"):
        load_phantom(tmp_path / "nope.csv")
