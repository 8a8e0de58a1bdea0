"""``appliance track``: its error paths (exit status 2, a message naming the file/frame) and its output."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from appliance.cli import main
from appliance.geometry import Calibration, View
from drivers.biplane_folder import PLANES, write_frame

SIZE = (64, 48)


def _have_tracker() -> bool:
    try:
        from appliance.recognition import PostureTracker  # noqa: F401
    except ImportError:
        return False
    return True


# TEMPORARY while appliance.recognition lands: these paths construct the tracker.
needs_tracker = pytest.mark.skipif(not _have_tracker(), reason="appliance.recognition.PostureTracker not there yet")


def _calibration() -> Calibration:
    p = View.look_at("p", (-500.0, 0.0, 0.0), (0, 0, 0), focal_px=200.0, image_size=SIZE)
    q = View.look_at("q", (0.0, -500.0, 0.0), (0, 0, 0), focal_px=200.0, image_size=SIZE)
    return Calibration.from_views(p, q, {"source": "test"})


def _blank(shape: tuple[int, int] = (SIZE[1], SIZE[0])) -> np.ndarray:
    return np.random.default_rng(0).integers(30000, 30100, shape, dtype=np.uint16)


@pytest.fixture()
def folder(tmp_path: Path) -> Path:
    root = tmp_path / "scene"
    for number in (1, 2):
        for plane in PLANES:
            write_frame(root, plane, number, _blank())
    _calibration().save(root / "calibration.yaml")
    return root


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(["track", *argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_missing_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = _run(capsys, str(tmp_path / "nowhere"))
    assert code == 2 and out == ""
    assert f"appliance track: error: {tmp_path / 'nowhere'}: no such folder" in err


def test_folder_without_planes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = _run(capsys, str(tmp_path))
    assert code == 2 and "no p/ or q/ subfolder" in err


def test_missing_calibration(folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (folder / "calibration.yaml").unlink()
    code, out, err = _run(capsys, str(folder))
    assert code == 2 and out == ""
    assert "calibration.yaml: file not found" in err and "--calibration FILE" in err
    code, _, err = _run(capsys, str(folder), "--calibration", str(folder / "other.yaml"))
    assert code == 2 and f"{folder / 'other.yaml'}: file not found" in err


def test_bad_calibration_names_key_path(folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = _calibration().to_dict()
    data["views"]["q"]["R"][2] = [-v for v in data["views"]["q"]["R"][2]]  # a mirror, det -1
    path = folder / "calibration.yaml"
    path.write_text(yaml.safe_dump(data))
    code, out, err = _run(capsys, str(folder))
    assert code == 2 and out == ""
    assert f"{path}: views.q.R: not a rotation (det -1.000" in err


def test_empty_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for plane in PLANES:
        (tmp_path / plane).mkdir()
    write_frame(tmp_path, "p", 3, _blank())
    _calibration().save(tmp_path / "calibration.yaml")
    code, _, err = _run(capsys, str(tmp_path))
    assert code == 2 and "no frame pairs to track (p/: 1 unpaired, q/: 0 unpaired" in err


@needs_tracker
def test_frame_size_not_the_calibrations(folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_frame(folder, "q", 1, _blank((24, 32)))
    code, out, err = _run(capsys, str(folder))
    assert code == 2 and out == ""
    assert f"{folder / 'q' / '000001.png'}: frame 1 is 32x24 pixels but plane q is 64x48 (from the calibration)" in err


@needs_tracker
def test_unreadable_frame_keeps_earlier_records(folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (folder / "p" / "000002.png").write_bytes(b"\x89PNG\r\n\x1a\n broken")
    out_file = folder / "postures.jsonl"
    code, out, err = _run(capsys, str(folder), "--out", str(out_file))
    assert code == 2 and out == ""
    assert f"{folder / 'p' / '000002.png'}: frame 2: not a readable PNG or TIFF image" in err
    records = [json.loads(line) for line in out_file.read_text().splitlines()]
    assert [r["frame"] for r in records] == [1]


@needs_tracker
def test_blank_frames_are_reported_lost_not_invented(folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = _run(capsys, str(folder), "--fps", "10")
    assert code == 0 and err == ""  # stderr is not a terminal here: no progress line
    records = [json.loads(line) for line in out.splitlines()]
    assert [r["frame"] for r in records] == [1, 2]
    assert [r["t"] for r in records] == [0.1, 0.2]
    for record in records:
        assert record["ok"] is False and record["reason"]
        assert record["centroid_mm"] is None and record["direction"] is None and record["tips_mm"] is None


def test_bad_arguments(folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["track", str(folder), "--fps", "0"])
    assert info.value.code == 2
    assert "--fps: must be positive" in capsys.readouterr().err
