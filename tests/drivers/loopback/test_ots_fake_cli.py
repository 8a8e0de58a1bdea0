"""End to end on the command line: ``appliance loopback ots`` serves, ``appliance ots stream|info`` reads.

The loopback runs as its own process (as a bench user would start it); the reading side runs in process.
"""
from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from appliance import cli
from drivers.loopback.ots_fake import synthetic_rom

ROOT = Path(__file__).resolve().parents[3]
ROM = ROOT / "tests" / "data" / "synthetic_tool.rom"
KEYS = {"handle", "rom", "position_mm", "quaternion", "rms_mm", "frame", "t", "missing"}


def start_loopback(*args: str) -> tuple[subprocess.Popen[str], str]:
    child = subprocess.Popen([sys.executable, "-m", "appliance", "loopback", "ots", *args], cwd=ROOT, text=True,
                             stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    assert child.stdout is not None
    address = child.stdout.readline().strip()
    if not address:
        child.kill()
        raise RuntimeError("appliance loopback ots printed no address")
    return child, address


@pytest.fixture(scope="module")
def pty_loopback() -> Iterator[str]:
    child, path = start_loopback("--pose", "5,6,-1234,1,0,0,0")
    yield path
    child.terminate()
    child.wait(timeout=10)


@pytest.fixture(scope="module")
def tcp_loopback_out_of_volume() -> Iterator[str]:
    child, address = start_loopback("--tcp", "0", "--pose", "0,0,-100,1,0,0,0")   # too close to see
    yield address
    child.terminate()
    child.wait(timeout=10)


def stream(capsys: pytest.CaptureFixture[str], *args: str) -> list[dict[str, object]]:
    assert cli.main(["ots", "stream", *args]) == 0
    return [json.loads(line) for line in capsys.readouterr().out.splitlines()]


def test_committed_rom_is_the_generated_one() -> None:
    assert ROM.read_bytes() == synthetic_rom() and len(ROM.read_bytes()) <= 1024


def test_stream_prints_one_object_per_tool_and_frame(pty_loopback: str, capsys: pytest.CaptureFixture[str]) -> None:
    records = stream(capsys, "--port", pty_loopback, "--rom", str(ROM), "--rom", str(ROM), "--frames", "3")
    assert len(records) == 6 and all(set(r) == KEYS for r in records)
    assert len({r["handle"] for r in records}) == 2 and {r["rom"] for r in records} == {"synthetic_tool.rom"}
    frames = [r["frame"] for r in records]
    assert frames[0::2] == frames[1::2] and len(set(frames)) == 3 and frames == sorted(frames)
    for r in records:
        assert r["missing"] is False and 0 < r["rms_mm"] < 1 and r["t"] > 1e9     # wall-clock seconds
        np.testing.assert_allclose(r["position_mm"], [5, 6, -1234], atol=5 * 0.19 / np.sqrt(3))
        np.testing.assert_allclose(r["quaternion"], [1, 0, 0, 0], atol=0.005)


def test_stream_in_bx_mode(pty_loopback: str, capsys: pytest.CaptureFixture[str]) -> None:
    records = stream(capsys, "--port", pty_loopback, "--rom", str(ROM), "--frames", "2", "--mode", "bx")
    assert len(records) == 2 and not any(r["missing"] for r in records)


def test_missing_tool_has_null_pose(tcp_loopback_out_of_volume: str, capsys: pytest.CaptureFixture[str]) -> None:
    (record,) = stream(capsys, "--port", tcp_loopback_out_of_volume, "--rom", str(ROM), "--frames", "1")
    assert record["missing"] is True
    assert record["position_mm"] is None and record["quaternion"] is None and record["rms_mm"] is None


def test_info_prints_version_text(pty_loopback: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["ots", "info", "--port", pty_loopback]) == 0
    assert "Freeze Tag: Polaris Spectra Rev 007" in capsys.readouterr().out


def test_clear_errors(pty_loopback: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["ots", "stream", "--port", pty_loopback, "--rom", str(tmp_path / "nope.rom")]) == 2
    err = capsys.readouterr().err
    assert "appliance ots: error: tool definition " in err and "nope.rom does not exist" in err
    assert cli.main(["ots", "stream", "--port", pty_loopback, "--rom", str(ROM), "--rate", "0"]) == 2
    assert "--rate and --timeout must be positive" in capsys.readouterr().err
    assert cli.main(["ots", "info", "--port", "/dev/does-not-exist"]) == 2
    assert "port '/dev/does-not-exist' does not exist" in capsys.readouterr().err
    empty = tmp_path / "empty_tool.rom"
    empty.write_bytes(b"\0" * 64)             # uploads fine, but holds no tool: PINIT fails
    assert cli.main(["ots", "stream", "--port", pty_loopback, "--rom", str(empty), "--frames", "1"]) == 2
    err = capsys.readouterr().err
    assert "appliance ots: error: tracker at" in err
    assert "answered ERROR0D to PINIT:" in err and "no tool assigned to the selected port handle" in err
