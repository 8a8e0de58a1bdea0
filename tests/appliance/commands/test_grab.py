"""``appliance grab``: record loopback and file sources into a biplane folder, list devices, clear errors."""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from appliance import cli
from drivers.biplane_folder import BiplaneFolder

LOOP = "loopback://?size=64x56&rate=200&seed=2"


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("grab") / "run"
    import io
    from contextlib import redirect_stdout

    buffer = io.StringIO()
    with redirect_stdout(buffer):
        code = cli.main(["grab", "--source", f"{LOOP}&plane=p", "--source", "loopback+usb://?plane=q",
                         "--frames", "12", "--out", str(out)])
    assert code == 0
    return out, buffer.getvalue()


def test_loopback_pairs_land_in_a_biplane_folder_with_timestamps(recorded: tuple[Path, str]) -> None:
    out, text = recorded
    folder = BiplaneFolder(out)
    assert len(folder) == 12 and folder.unpaired == {"p": [], "q": []}
    assert folder.calibration_path is not None
    image_p, image_q = folder.read_pair(folder.frame_numbers[0])
    assert image_p.shape == image_q.shape == (56, 64) and image_p.dtype == np.uint16
    with (out / "timestamps.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 24 and {row["plane"] for row in rows} == {"p", "q"}
    assert "grabbed 12 pair(s)" in text and "pairs/s" in text
    assert "plane q usb:1209:0001/XRG-Q" in text and "dropped" in text and "p-q skew" in text


def test_a_recorded_folder_replays_through_file_sources(recorded: tuple[Path, str], tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    out, _ = recorded
    copy = tmp_path / "copy"
    code = cli.main(["grab", "--source", f"file://{out}?plane=p", "--source", f"file://{out}?plane=q",
                     "--frames", "100", "--out", str(copy), "--format", "tif"])
    assert code == 0
    assert "stopped early: the recorded sources ended" in capsys.readouterr().out
    original, replay = BiplaneFolder(out), BiplaneFolder(copy)
    assert replay.frame_numbers == original.frame_numbers
    for number in original.frame_numbers:
        assert all(np.array_equal(a, b) for a, b in zip(original.read_pair(number), replay.read_pair(number)))


def test_time_matching_and_no_output(capsys: pytest.CaptureFixture[str]) -> None:
    code = cli.main(["grab", "--source", f"{LOOP}&plane=p&jitter_ms=0.5", "--source", "loopback://?plane=q",
                     "--frames", "5", "--match", "time", "--max-skew-ms", "3"])
    assert code == 0
    out = capsys.readouterr().out
    assert "pairing by time" in out and "written" not in out


@pytest.mark.parametrize("argv, message", [
    (["--source", f"{LOOP}&plane=p"], "exactly two --source"),
    (["--source", f"{LOOP}&plane=p", "--source", f"{LOOP}&plane=p"], "planes p and q"),
    (["--source", "usb://1209:0001", "--source", f"{LOOP}&plane=q"], "no USB"),
    (["--source", "v4l2:///dev/video93?plane=p", "--source", f"{LOOP}&plane=q"], "no such video device"),
    (["--source", "file:///nonexistent?plane=p", "--source", f"{LOOP}&plane=q"], "does not exist"),
])
def test_clear_errors(argv: list[str], message: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["grab", *argv, "--frames", "2"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("appliance grab: error:") and message in err


def test_refuses_a_folder_that_already_holds_frames(recorded: tuple[Path, str],
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    out, _ = recorded
    assert cli.main(["grab", "--source", f"{LOOP}&plane=p", "--source", "loopback://?plane=q", "--out", str(out)]) == 2
    assert "already holds frames" in capsys.readouterr().err


def test_list(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["grab", "--list"]) == 0
    out = capsys.readouterr().out
    assert "USB frame grabbers:" in out and "V4L2 devices:" in out
