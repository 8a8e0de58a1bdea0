"""The NDI driver against the loopback tracker on a real pty and a real TCP socket (and, opt-in, hardware).

One contract suite, several targets: ``pty`` and ``tcp`` serve the loopback tracker; ``hardware`` runs
against ``--device-url ots=URL`` with ``--ots-rom``-free checks only (no pose is known there).
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from drivers.errors import DeviceTimeoutError, LinkLostError, ProtocolError
from drivers.loopback.ots_fake import FixedPose, NdiTrackerFake, NoiseModel, synthetic_rom
from drivers.loopback.serve import PtyServer, TcpServer
from drivers.ndi_tracker import NDITracker, ToolSample
from drivers.transport import open_serial

SET_POSITION = np.array([12.5, -30.0, -1400.0])
SET_QUATERNION = np.array([np.cos(np.pi / 8), 0.0, np.sin(np.pi / 8), 0.0])   # 45° about y
SIGMA_AXIS_MM = 0.19 / np.sqrt(3)


@dataclass
class Target:
    url: str
    server: PtyServer | TcpServer | None
    fake: NdiTrackerFake | None


@pytest.fixture(scope="module", params=["pty", "tcp"])
def loopback(request: pytest.FixtureRequest) -> Iterator[Target]:
    fake = NdiTrackerFake(FixedPose(SET_QUATERNION, SET_POSITION), noise=NoiseModel(seed=5))
    server = PtyServer(fake) if request.param == "pty" else TcpServer(fake)
    with server:
        yield Target(getattr(server, "path", None) or server.address, server, fake)


@pytest.fixture(scope="module")
def rom_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("roms") / "reference_tool.rom"
    path.write_bytes(synthetic_rom("REFERENCE"))
    return path


def open_tracker(url: str) -> NDITracker:
    return NDITracker(open_serial(url, baudrate=9600, timeout=0.05), reply_timeout_s=1.0)


def test_reported_pose_is_the_pose_set_within_noise(loopback: Target, rom_file: Path) -> None:
    by_frame: dict[int, dict[str, ToolSample]] = {}
    with open_tracker(loopback.url) as ndi:
        ndi.connect(115200)
        assert "Freeze Tag:" in ndi.version()
        handle = ndi.load_tool(rom_file)
        ndi.start()
        while len(by_frame) < 30:       # 30 distinct 60 Hz frames: independent noise draws
            for mode in ("tx", "bx"):
                (sample,) = ndi.read_frame(mode)
                by_frame.setdefault(sample.frame, {})[mode] = sample
    samples = [s for pair in by_frame.values() for s in pair.values()]
    assert {s.handle for s in samples} == {handle} and {s.rom for s in samples} == {"reference_tool.rom"}
    assert not any(s.missing for s in samples)
    for pair in by_frame.values():      # one frame read both ways: TX is BX rounded to its digits
        if len(pair) == 2:
            np.testing.assert_allclose(pair["tx"].position_mm, pair["bx"].position_mm, atol=0.0051)
            np.testing.assert_allclose(pair["tx"].quaternion, pair["bx"].quaternion, atol=0.000051)
    positions = np.array([next(iter(pair.values())).position_mm for pair in by_frame.values()])
    # Each frame is within 5 sigma of the pose set; the mean of 30 frames within 5 sigma of the mean.
    assert np.all(np.abs(positions - SET_POSITION) < 5 * SIGMA_AXIS_MM)
    assert np.all(np.abs(positions.mean(axis=0) - SET_POSITION) < 5 * SIGMA_AXIS_MM / np.sqrt(len(positions)))
    for s in samples:
        q = np.asarray(s.quaternion) / np.linalg.norm(s.quaternion)
        # |q - q_set| is half the rotation angle between them for small angles (arccos is ill-conditioned).
        assert 2 * np.degrees(np.linalg.norm(q - SET_QUATERNION)) < 0.3
        np.testing.assert_allclose(s.transform[:3, :3] @ s.transform[:3, :3].T, np.eye(3), atol=1e-3)
        assert 0 < s.rms_mm < 1
    assert sorted(by_frame) == list(by_frame)    # frame numbers only grow
    if loopback.fake is not None:
        with loopback.server.lock:
            assert loopback.fake.comm.baudrate == (9600 if isinstance(loopback.server, TcpServer) else 115200)


def test_tool_outside_the_volume_is_missing_then_back(loopback: Target, rom_file: Path) -> None:
    with open_tracker(loopback.url) as ndi:
        ndi.connect()
        ndi.load_tool(rom_file)
        ndi.start()
        with loopback.server.lock:
            loopback.fake.provider = FixedPose(np.eye(3), (0.0, 0.0, -500.0))   # too close to the camera
        try:
            gone = ndi.read_frame()[0]
            assert gone.missing and gone.position_mm is None
        finally:
            with loopback.server.lock:
                loopback.fake.provider = FixedPose(SET_QUATERNION, SET_POSITION)
        back = ndi.read_frame()[0]
        while back.frame == gone.frame:     # a pose change shows from the next 60 Hz frame on
            back = ndi.read_frame()[0]
        assert not back.missing


def test_reconnect_frees_the_previous_session_handles(loopback: Target, rom_file: Path) -> None:
    for _ in range(2):
        with open_tracker(loopback.url) as ndi:
            ndi.connect()
            ndi.load_tool(rom_file)
            ndi.start()
            assert len(ndi.read_frame()) == 1           # only this session's tool


def test_background_reader_at_tracker_rate(loopback: Target, rom_file: Path) -> None:
    with open_tracker(loopback.url) as ndi:
        ndi.connect()
        ndi.load_tool(rom_file)
        ndi.start()
        ndi.start_streaming("bx")
        first = ndi.wait_for_frame(timeout_s=2.0)
        later = ndi.wait_for_frame(first[0].frame + 3, timeout_s=2.0)
        assert later[0].frame > first[0].frame + 3 and ndi.latest() is not None


def test_unplugged_link_is_a_timeout(loopback: Target, rom_file: Path) -> None:
    with open_tracker(loopback.url) as ndi:
        ndi.connect()
        ndi.reply_timeout_s = 0.2
        loopback.server.unplugged.set()
        try:
            with pytest.raises(DeviceTimeoutError, match="no complete reply to VER:0"):
                ndi.version()
        finally:
            loopback.server.unplugged.clear()


def test_corrupted_reply_is_a_protocol_error_and_the_next_frame_reads(loopback: Target, rom_file: Path) -> None:
    damaged = []

    def flip_one_digit(data: bytes, direction: str) -> bytes:
        if direction == "to_host" and data[:1] != b"\xc4" and len(data) > 40 and not damaged:
            damaged.append(data)
            return data[:10] + bytes([data[10] ^ 0x01]) + data[11:]     # a TX digit changes, the CRC does not
        return data

    with open_tracker(loopback.url) as ndi:
        ndi.connect()
        ndi.load_tool(rom_file)
        ndi.start()
        loopback.server.link_filter = flip_one_digit
        try:
            with pytest.raises(ProtocolError, match="CRC .* given, .* computed"):
                ndi.read_frame("tx")
        finally:
            loopback.server.link_filter = None
        assert damaged and not ndi.read_frame("tx")[0].missing


def test_peer_closing_the_connection_is_link_lost(rom_file: Path) -> None:
    server = TcpServer(NdiTrackerFake(FixedPose(SET_QUATERNION, SET_POSITION)))
    ndi = open_tracker(server.address)
    try:
        ndi.connect()
        server.close()              # the tracker goes away: its end of the connection closes
        with pytest.raises(LinkLostError, match="link to the tracker at socket://127.0.0.1:"):
            ndi.version()
    finally:
        ndi.close()


@pytest.mark.hardware
def test_real_tracker_contract(device_urls: dict[str, str]) -> None:
    if "ots" not in device_urls:
        pytest.skip("pass --device-url ots=/dev/ttyUSB0 (Polaris) or ots=HOST:8765 (Vega)")
    with open_tracker(device_urls["ots"]) as ndi:
        ndi.connect()
        assert ndi.version().strip()
        ndi.start()
        assert ndi.read_frame("tx") == [] and ndi.read_frame("bx") == []    # no tools loaded
        ndi.stop()
