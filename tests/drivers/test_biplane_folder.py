"""Tests of the biplane frame folder contract: listing, pairing, 16-bit reading, and its errors."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from drivers.biplane_folder import PLANES, BiplaneFolder, frame_name, write_frame
from drivers.errors import InputDataError


def _frame(seed: int, shape: tuple[int, int] = (24, 32)) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 65536, shape, dtype=np.uint16)


@pytest.fixture()
def folder(tmp_path: Path) -> Path:
    for number in (0, 1, 2, 5):
        write_frame(tmp_path, "p", number, _frame(number))
    for number in (1, 2, 5, 7):
        write_frame(tmp_path, "q", number, _frame(100 + number), fmt="tif")
    return tmp_path


def test_lists_pairs_and_unpaired(folder: Path) -> None:
    frames = BiplaneFolder(folder)
    assert frames.frame_numbers == [1, 2, 5]
    assert frames.unpaired == {"p": [0], "q": [7]}
    assert frames.calibration_path is None
    assert len(frames) == 3
    (folder / "calibration.yaml").write_text("views: {}\n")
    assert BiplaneFolder(folder).calibration_path == folder / "calibration.yaml"


def test_reads_16_bit_png_and_tiff_exactly(folder: Path) -> None:
    frames = BiplaneFolder(folder)
    image_p, image_q = frames.read_pair(5)
    assert image_p.dtype == np.uint16 and image_q.dtype == np.uint16
    np.testing.assert_array_equal(image_p, _frame(5))
    np.testing.assert_array_equal(image_q, _frame(105))
    assert [number for number, _, _ in frames.pairs()] == [1, 2, 5]


def test_write_frame_names_and_checks(tmp_path: Path) -> None:
    assert frame_name(12) == "000012.png"
    assert frame_name(1234567, "tif") == "1234567.tif"
    assert write_frame(tmp_path, "q", 3, _frame(3), fmt="tiff") == tmp_path / "q" / "000003.tif"
    with pytest.raises(ValueError, match="uint16"):
        write_frame(tmp_path, "p", 0, _frame(0).astype(np.float32))
    with pytest.raises(ValueError, match="plane"):
        write_frame(tmp_path, "x", 0, _frame(0))
    with pytest.raises(ValueError, match="format"):
        write_frame(tmp_path, "p", 0, _frame(0), fmt="jpg")


def test_missing_folder_or_plane(tmp_path: Path) -> None:
    with pytest.raises(InputDataError, match="no such folder"):
        BiplaneFolder(tmp_path / "nowhere")
    (tmp_path / "p").mkdir()
    with pytest.raises(InputDataError, match=r"no q/ subfolder"):
        BiplaneFolder(tmp_path)


def test_unpaired_and_absent_frames_are_named(folder: Path) -> None:
    frames = BiplaneFolder(folder)
    with pytest.raises(InputDataError, match=r"frame 0 is only in plane p"):
        frames.read_pair(0)
    with pytest.raises(InputDataError, match=r"frame 9 is in neither plane"):
        frames.read_pair(9)
    with pytest.raises(InputDataError, match=r"no frame 7 \(expected .*p/000007.png\)"):
        frames.read("p", 7)


def test_8_bit_and_colour_are_rejected(tmp_path: Path) -> None:
    for plane in PLANES:
        write_frame(tmp_path, plane, 1, _frame(1))
        write_frame(tmp_path, plane, 2, _frame(2))
    cv2.imwrite(str(tmp_path / "p" / "000001.png"), (_frame(1) >> 8).astype(np.uint8))
    cv2.imwrite(str(tmp_path / "q" / "000002.png"), np.dstack([_frame(2)] * 3))
    frames = BiplaneFolder(tmp_path)
    with pytest.raises(InputDataError, match=r"p/000001.png: frame 1: is uint8 \(8-bit\).*rejected, not converted"):
        frames.read_pair(1)
    with pytest.raises(InputDataError, match=r"q/000002.png: frame 2: has 3 channels"):
        frames.read("q", 2)


def test_unreadable_and_vanished_files(folder: Path) -> None:
    frames = BiplaneFolder(folder)
    (folder / "q" / "000002.tif").write_bytes(b"II*\x00 truncated")
    with pytest.raises(InputDataError, match=r"q/000002.tif: frame 2: not a readable PNG or TIFF"):
        frames.read("q", 2)
    (folder / "p" / "000001.png").unlink()
    with pytest.raises(InputDataError, match=r"p/000001.png: frame 1: cannot read"):
        frames.read_pair(1)


def test_sizes_must_agree_within_a_plane(folder: Path) -> None:
    write_frame(folder, "p", 2, _frame(2, shape=(20, 32)))
    frames = BiplaneFolder(folder)
    frames.read_pair(1)
    with pytest.raises(InputDataError, match=r"p/000002.png: frame 2 is 32x20 pixels but plane p is 32x24 \(from frame 1\)"):
        frames.read_pair(2)
    strict = BiplaneFolder(folder, expected_sizes={"p": (32, 24), "q": (64, 48)})
    with pytest.raises(InputDataError, match=r"q/000001.tif: frame 1 is 32x24 pixels but plane q is 64x48 \(from the calibration\)"):
        strict.read_pair(1)


def test_duplicate_numbers_and_stray_files(tmp_path: Path) -> None:
    for plane in PLANES:
        write_frame(tmp_path, plane, 4, _frame(4))
    (tmp_path / "p" / "notes.txt").write_text("ignored")
    (tmp_path / "p" / "frame4.png").write_bytes(b"")
    assert BiplaneFolder(tmp_path).frame_numbers == [4]
    write_frame(tmp_path, "p", 4, _frame(4), fmt="tif")
    with pytest.raises(InputDataError, match=r"frame 4 exists twice: 000004.png and 000004.tif"):
        BiplaneFolder(tmp_path)
