"""Independent public NDI clients against the loopback tracker: scikit-surgerynditracker and ndicapi.

Both connect on a real pty (and ndicapi also over TCP, as to a Vega), upload a .rom tool, start tracking
and read the pose we set, in TX and in BX mode. The loopback tracker runs in a child process: ndicapi's
Python binding keeps the GIL during its blocking serial I/O, so a tracker thread in the test process
would never get to answer.
"""
from __future__ import annotations

import importlib.metadata
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from drivers.loopback.ots_fake import synthetic_rom

ndicapy = pytest.importorskip("ndicapy", reason="ndicapi (the public C client's Python binding) is not installed")
sks = pytest.importorskip("sksurgerynditracker.nditracker", reason="scikit-surgerynditracker is not installed")

ROOT = Path(__file__).resolve().parents[3]
SET_T = (25.0, -40.0, -1350.0)
SET_Q = (float(np.cos(np.pi / 12)), float(np.sin(np.pi / 12)), 0.0, 0.0)       # 30° about x
TOLERANCE_MM = 5 * 0.19 / np.sqrt(3)

SERVE = r"""
import sys
from drivers.loopback.ots_fake import SPECTRA_BX_FIRMWARE, FirmwareIdentity, FixedPose, NdiTrackerFake, NoiseModel
from drivers.loopback.serve import PtyServer, TcpServer
firmware = SPECTRA_BX_FIRMWARE if sys.argv[1] == "bx" else FirmwareIdentity()
fake = NdiTrackerFake(FixedPose(%r, %r), noise=NoiseModel(seed=2), firmware=firmware)
server = PtyServer(fake) if sys.argv[2] == "pty" else TcpServer(fake)
with server:
    print(getattr(server, "path", None) or server.address, flush=True)
    sys.stdin.read()                       # serve until the test closes our stdin
    with server.lock:
        print(" ".join(command.name for command in fake.commands), flush=True)
""" % (SET_Q, SET_T)


class Served:
    def __init__(self, address: str) -> None:
        self.address = address
        self.commands: list[str] = []


@contextmanager
def loopback_tracker(firmware: str, transport: str = "pty") -> Iterator[Served]:
    child = subprocess.Popen([sys.executable, "-c", SERVE, firmware, transport], cwd=ROOT, text=True,
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    assert child.stdout is not None and child.stdin is not None
    served = Served(child.stdout.readline().strip())
    if not served.address:
        child.kill()
        raise RuntimeError(f"the loopback tracker process did not start (exit status {child.wait()})")
    try:
        yield served
    finally:
        child.stdin.close()
        served.commands = child.stdout.read().split()
        child.wait(timeout=10)


@pytest.fixture(scope="module")
def rom(tmp_path_factory: pytest.TempPathFactory) -> str:
    path = tmp_path_factory.mktemp("roms") / "loopback_tool.rom"
    path.write_bytes(synthetic_rom("PUBLIC-CLIENT"))
    return str(path)


def client_versions() -> str:
    return ", ".join(f"{name} {importlib.metadata.version(name)}" for name in ("scikit-surgerynditracker", "ndicapi"))


def assert_pose(quaternion: np.ndarray, translation: np.ndarray) -> None:
    np.testing.assert_allclose(translation, SET_T, atol=TOLERANCE_MM)
    q = np.asarray(quaternion, float)
    q = q / np.linalg.norm(q)
    assert 2 * np.degrees(np.linalg.norm(q - np.asarray(SET_Q))) < 0.3


@pytest.mark.parametrize("firmware, data_command", [("tx", "TX"), ("bx", "BX")])
def test_scikit_surgerynditracker_tracks_a_rom_tool(rom: str, firmware: str, data_command: str) -> None:
    with loopback_tracker(firmware) as served:
        tracker = sks.NDITracker({"tracker type": "polaris", "serial port": served.address,
                                  "romfiles": [rom], "use quaternions": True})
        tracker.start_tracking()
        frames = []
        for _ in range(4):
            handles, _, frame_numbers, tracking, quality = tracker.get_frame()
            assert len(handles) == 1 and np.isfinite(quality[0])
            pose = np.asarray(tracking[0]).reshape(7)
            assert_pose(pose[:4], pose[4:])
            frames.append(frame_numbers[0])
        tracker.stop_tracking()
        tracker.close()
    assert frames == sorted(frames), client_versions()
    commands = served.commands
    assert commands[:4] == ["INIT", "GETINFO", "INIT", "COMM"]
    assert commands.count("PVWR") == 16 and "PINIT" in commands and "PENA" in commands
    assert commands.count(data_command) == 4 and commands.count({"TX": "BX", "BX": "TX"}[data_command]) == 0
    assert commands[-1] == "TSTOP"


def _track_with_ndicapi(device: object, rom: str) -> tuple[bytes, object]:
    assert ndicapy.ndiCommand(device, "INIT:") == "OKAY"
    ndicapy.ndiCommand(device, "PHRQ:*********1****")
    handle = ndicapy.ndiGetPHRQHandle(device)
    assert ndicapy.ndiPVWRFromFile(device, handle, rom) == 0
    assert ndicapy.ndiCommand(device, f"PINIT:{handle:02x}") == "OKAY"
    assert ndicapy.ndiCommand(device, f"PENA:{handle:02x}D") == "OKAY"
    return bytes([handle]), device


def test_ndicapi_on_a_pty_tx_bx_and_error_codes(rom: str) -> None:
    with loopback_tracker("tx") as served:
        assert ndicapy.ndiProbe(served.address) == ndicapy.NDI_OKAY
        device = ndicapy.ndiOpen(served.address)
        assert device
        try:
            handle, _ = _track_with_ndicapi(device, rom)
            # Before TSTART the tracker refuses; the binding turns ERROR0C into an OSError with its meaning.
            with pytest.raises(OSError, match="0x0c: Command is invalid while in the current mode"):
                ndicapy.ndiCommand(device, "TX:0801")
            assert ndicapy.ndiGetError(device) == ndicapy.NDI_BAD_MODE
            assert ndicapy.ndiCommand(device, "TSTART:") == "OKAY"
            ndicapy.ndiCommand(device, "TX:0801")
            assert ndicapy.ndiGetError(device) == ndicapy.NDI_OKAY
            tx = ndicapy.ndiGetTXTransform(device, handle)
            assert_pose(np.asarray(tx[:4]), np.asarray(tx[4:7]))
            ndicapy.ndiCommand(device, "BX:0801")
            bx = ndicapy.ndiGetBXTransform(device, handle)
            assert_pose(np.asarray(bx[:4]), np.asarray(bx[4:7]))
            assert ndicapy.ndiGetBXFrame(device, handle) >= ndicapy.ndiGetTXFrame(device, handle)
            assert ndicapy.ndiCommand(device, "TSTOP:") == "OKAY"
        finally:
            ndicapy.ndiClose(device)


def test_ndicapi_over_tcp_like_a_vega(rom: str) -> None:
    with loopback_tracker("bx", "tcp") as served:
        host, port = served.address.rsplit(":", 1)
        device = ndicapy.ndiOpenNetwork(host, int(port))
        assert device
        try:
            handle, _ = _track_with_ndicapi(device, rom)
            assert ndicapy.ndiCommand(device, "TSTART:") == "OKAY"
            ndicapy.ndiCommand(device, "BX:0801")
            bx = ndicapy.ndiGetBXTransform(device, handle)
            assert_pose(np.asarray(bx[:4]), np.asarray(bx[4:7]))
            ndicapy.ndiCommand(device, "TSTOP:")
        finally:
            ndicapy.ndiCloseNetwork(device)
