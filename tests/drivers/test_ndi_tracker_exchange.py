"""Byte-exact exchanges of the NDI driver with a scripted port that fails on any unexpected byte.

The script is a list of (bytes the driver must write, bytes the tracker answers); ``None`` is silence,
``BREAK`` stands for a serial break, ``DROP`` for a link that dies. The port fails on an unexpected or
extra write, on a reply the driver throws away unread, and (at the end) on steps left over.
"""
from __future__ import annotations

import threading

import time
from collections.abc import Iterator

import numpy as np
import pytest
import serial
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.errors import DeviceError, DeviceTimeoutError, InputDataError, LinkLostError, ProtocolError
from drivers.ndi_tracker import NdiCommandError, NDITracker
from firmware_protocol.ndi import crc_hex, encode_error, encode_reply

BREAK = b"<break>"
DROP = b"<link drop>"

WORKED_TX = (b"0101+07071+00000+07071+00000+001234-005678-150000+0123400000031000000D0\n"
             b"000018CA\r")


def cmd(text: str) -> bytes:
    """A command as ndicapi and our driver send it: text, CRC, CR."""
    raw = text.encode()
    return raw + crc_hex(raw) + b"\r"


OKAY = encode_reply("OKAY")


class ScriptedPort:
    """Just enough of ``serial.SerialBase`` to run a scripted exchange."""

    def __init__(self, script: list[tuple[bytes, bytes | None]], name: str = "/dev/ttyNDI") -> None:
        self.script = list(script)
        self.portstr = name
        self.timeout = 0.01
        self.baudrate = 115200
        self.baud_history: list[int] = []
        self._written = b""
        self._rx = b""
        self._dropped = False
        self.closed = False

    def __setattr__(self, name: str, value: object) -> None:
        if name == "baudrate" and "baud_history" in self.__dict__:
            self.baud_history.append(int(value))  # type: ignore[arg-type]
        super().__setattr__(name, value)

    def _advance(self) -> None:
        while self.script and self._written:
            expected, reply = self.script[0]
            if expected in (BREAK,):
                raise AssertionError(f"driver wrote {self._written!r} where the script expects a serial break")
            if not expected.startswith(self._written[:len(expected)]):
                raise AssertionError(f"driver wrote {self._written!r}, script expects {expected!r}")
            if len(self._written) < len(expected):
                return
            self._written = self._written[len(expected):]
            self.script.pop(0)
            self._reply(reply)
        if self._written:
            raise AssertionError(f"driver wrote {self._written!r} after the end of the script")

    def _reply(self, reply: bytes | None) -> None:
        if reply == DROP:
            self._dropped = True
        elif reply is not None:
            self._rx += reply

    def write(self, data: bytes) -> int:
        if self._dropped:
            raise serial.SerialException("write failed: [Errno 5] Input/output error")
        self._written += data
        self._advance()
        return len(data)

    def send_break(self, duration: float = 0.25) -> None:
        assert self.script and self.script[0][0] == BREAK, "unexpected serial break"
        self._reply(self.script.pop(0)[1])

    @property
    def in_waiting(self) -> int:
        return len(self._rx)

    def read(self, size: int = 1) -> bytes:
        if self._dropped and not self._rx:
            raise serial.SerialException("device reports readiness to read but returned no data")
        if not self._rx:
            time.sleep(self.timeout)
            return b""
        data, self._rx = self._rx[:size], self._rx[size:]
        return data

    def reset_input_buffer(self) -> None:
        assert not self._rx, f"driver discarded an unread reply: {self._rx!r}"

    def close(self) -> None:
        self.closed = True

    def finish(self) -> None:
        assert not self.script, f"script steps left over: {self.script[:3]!r}"
        assert not self._rx, f"reply bytes left unread: {self._rx!r}"


@pytest.fixture
def scripted() -> Iterator[list[ScriptedPort]]:
    ports: list[ScriptedPort] = []
    yield ports
    for port in ports:
        port.finish()


def tracker(ports: list[ScriptedPort], script: list[tuple[bytes, bytes | None]], **kwargs: object) -> NDITracker:
    port = ScriptedPort(script)
    ports.append(port)
    return NDITracker(port, reply_timeout_s=0.2, **kwargs)  # type: ignore[arg-type]


def test_connect_switches_speed_after_okay_and_frees_stale_handles(scripted: list[ScriptedPort]) -> None:
    ndi = tracker(scripted, [
        (cmd("INIT:"), OKAY),
        (cmd("COMM:50000"), OKAY),
        (cmd("PHSR:00"), encode_reply("020103120031")),
        (cmd("PHF:01"), OKAY),
        (cmd("PHF:20"), OKAY),
    ])
    ndi.connect(115200)
    assert scripted[0].baud_history == [9600, 115200]


def test_connect_over_tcp_skips_comm(scripted: list[ScriptedPort]) -> None:
    ndi = tracker(scripted, [(cmd("INIT:"), OKAY), (cmd("PHSR:00"), encode_reply("00"))], network=True)
    ndi.connect()
    assert scripted[0].baud_history == []


def test_silent_tracker_gets_a_break_then_reset_then_init(scripted: list[ScriptedPort]) -> None:
    ndi = tracker(scripted, [
        (cmd("INIT:"), None),                    # still at the speed an earlier session chose
        (BREAK, encode_reply("RESET")),
        (cmd("INIT:"), OKAY),
        (cmd("PHSR:01"), encode_reply("00")),
    ])
    ndi.connect(9600, probe_timeout_s=0.05, reset_timeout_s=0.5, free_all_handles=False)


def test_forced_reset_breaks_first_then_switches_speed(scripted: list[ScriptedPort]) -> None:
    ndi = tracker(scripted, [
        (BREAK, encode_reply("RESET")),
        (cmd("INIT:"), OKAY),
        (cmd("COMM:A0000"), OKAY),
        (cmd("PHSR:00"), encode_reply("00")),
    ])
    ndi.connect(230400, reset=True, reset_timeout_s=0.5)
    assert scripted[0].baud_history[-1] == 230400


def test_unsupported_speed_fails_before_any_byte(scripted: list[ScriptedPort]) -> None:
    ndi = tracker(scripted, [])
    with pytest.raises(ValueError, match="COMM cannot select 4800 baud"):
        ndi.connect(4800)


def test_init_while_tracking_stops_tracking_first(scripted: list[ScriptedPort]) -> None:
    ndi = tracker(scripted, [
        (cmd("INIT:"), encode_error(0x0C)),
        (cmd("TSTOP:"), OKAY),
        (cmd("INIT:"), OKAY),
        (cmd("PHSR:00"), encode_reply("00")),
    ], network=True)
    ndi.connect()


def test_break_without_reset_is_a_timeout(scripted: list[ScriptedPort]) -> None:
    ndi = tracker(scripted, [(cmd("INIT:"), None), (BREAK, None)])
    with pytest.raises(DeviceTimeoutError, match="serial break from the tracker at /dev/ttyNDI"):
        ndi.connect(probe_timeout_s=0.05, reset_timeout_s=0.1)


def test_load_tool_uploads_sixteen_chunks(scripted: list[ScriptedPort]) -> None:
    rom = bytes(range(256)) * 2 + b"\xab" * 100          # 612 bytes, zero padded to 1024
    padded = rom.ljust(1024, b"\0")
    script = [(cmd("PHRQ:*********1****"), encode_reply("0A"))]
    script += [(cmd(f"PVWR:0A{addr:04X}{padded[addr:addr + 64].hex().upper()}"), OKAY) for addr in range(0, 1024, 64)]
    script += [(cmd("PINIT:0A"), OKAY), (cmd("PENA:0AD"), OKAY)]
    ndi = tracker(scripted, script)
    assert ndi.load_tool(rom, name="probe") == 0x0A
    assert ndi.tools == {0x0A: "probe"}


def test_load_tool_error_reply_frees_the_handle_and_names_the_meaning(scripted: list[ScriptedPort]) -> None:
    padded = b"\x01".ljust(1024, b"\0")
    script = [(cmd("PHRQ:*********1****"), encode_reply("01"))]
    script += [(cmd(f"PVWR:01{addr:04X}{padded[addr:addr + 64].hex().upper()}"), OKAY) for addr in range(0, 1024, 64)]
    script += [(cmd("PINIT:01"), encode_error(0x0D)), (cmd("PHF:01"), OKAY)]
    ndi = tracker(scripted, script)
    with pytest.raises(NdiCommandError) as info:
        ndi.load_tool(b"\x01")
    assert info.value.code == 0x0D
    assert str(info.value) == ("tracker at /dev/ttyNDI answered ERROR0D to PINIT:01: "
                               "no tool assigned to the selected port handle")
    assert ndi.tools == {}


def test_missing_rom_file_is_input_error_before_any_byte(scripted: list[ScriptedPort], tmp_path) -> None:
    ndi = tracker(scripted, [])
    with pytest.raises(InputDataError, match="nope.rom"):
        ndi.load_tool(tmp_path / "nope.rom")
    with pytest.raises(InputDataError, match="1025 bytes"):
        ndi.load_tool(b"\0" * 1025)


def test_tx_worked_example_becomes_a_sample(scripted: list[ScriptedPort]) -> None:
    ndi = tracker(scripted, [(cmd("TX:0001"), WORKED_TX)], clock=lambda: 42.0)
    ndi.tools[0x01] = "ref.rom"
    (sample,) = ndi.read_frame("tx")
    assert (sample.handle, sample.rom, sample.frame, sample.t, sample.missing) == (1, "ref.rom", 208, 42.0, False)
    assert sample.position_mm == (12.34, -56.78, -1500.0)
    assert sample.quaternion == (0.7071, 0.0, 0.7071, 0.0)
    assert sample.rms_mm == 0.1234 and sample.port_status == 0x31
    assert sample.transform is not None
    # q = (cos 45°, 0, sin 45°, 0): a quarter turn about y sends x to -z.
    np.testing.assert_allclose(sample.transform[:3, :3] @ [1, 0, 0], [0, 0, -1], atol=1e-4)


def test_missing_tool_has_no_pose(scripted: list[ScriptedPort]) -> None:
    ndi = tracker(scripted, [(cmd("TX:0001"), encode_reply("0101MISSING0000003100000100\n0000"))])
    (sample,) = ndi.read_frame()
    assert sample.missing and not sample.disabled and sample.frame == 0x100
    assert sample.transform is None and sample.quaternion is None and sample.rms_mm is None
    assert sample.position_mm is None


def test_bx_reply_read_by_its_declared_length(scripted: list[ScriptedPort]) -> None:
    from firmware_protocol.ndi_replies import ToolRecord, ToolState, TrackingReply, encode_bx

    wire = encode_bx(TrackingReply((ToolRecord(3, ToolState.VALID, (1, 0, 0, 0), (0, 13.0, -1500), 0.1,
                                               frame=0x0D0D0D0D),)))    # CR bytes inside the binary body
    assert b"\r" in wire[6:-2]
    ndi = tracker(scripted, [(cmd("BX:0001"), wire)])
    (sample,) = ndi.read_frame("bx")
    assert sample.frame == 0x0D0D0D0D and sample.position_mm == pytest.approx((0, 13, -1500))


def test_error_reply_to_tx_is_typed(scripted: list[ScriptedPort]) -> None:
    ndi = tracker(scripted, [(cmd("TX:0001"), encode_error(0x0C))])
    with pytest.raises(NdiCommandError, match="ERROR0C to TX:0001: command is invalid while in the current mode"):
        ndi.read_frame()


def test_error_reply_to_bx_is_text_not_binary(scripted: list[ScriptedPort]) -> None:
    ndi = tracker(scripted, [(cmd("BX:0001"), encode_error(0x0C))])
    with pytest.raises(NdiCommandError, match="ERROR0C"):
        ndi.read_frame("bx")


def test_bad_reply_crc_is_protocol_error(scripted: list[ScriptedPort]) -> None:
    ndi = tracker(scripted, [(cmd("TX:0001"), WORKED_TX.replace(b"18CA", b"18CB"))])
    with pytest.raises(ProtocolError, match="CRC 18CB given, 18CA computed"):
        ndi.read_frame()


def test_bad_bx_header_crc_is_protocol_error(scripted: list[ScriptedPort]) -> None:
    ndi = tracker(scripted, [(cmd("BX:0001"), b"\xc4\xa5\x10\x00\x00\x00")])
    with pytest.raises(ProtocolError, match="bad BX header"):
        ndi.read_frame("bx")


def test_silence_is_a_timeout_naming_the_command(scripted: list[ScriptedPort]) -> None:
    ndi = tracker(scripted, [(cmd("VER:0"), None)])
    with pytest.raises(DeviceTimeoutError, match="no complete reply to VER:0 from the tracker at /dev/ttyNDI"):
        ndi.version()


def test_half_a_reply_is_a_timeout_that_shows_it(scripted: list[ScriptedPort]) -> None:
    ndi = tracker(scripted, [(cmd("TSTART:"), b"OKA")])
    with pytest.raises(DeviceTimeoutError, match=r"got only b'OKA'"):
        ndi.start()


def test_dropped_link_is_link_lost(scripted: list[ScriptedPort]) -> None:
    ndi = tracker(scripted, [(cmd("TX:0001"), DROP)])
    with pytest.raises(LinkLostError, match="link to the tracker at /dev/ttyNDI lost"):
        ndi.read_frame()


def test_unexpected_reply_text_is_protocol_error(scripted: list[ScriptedPort]) -> None:
    ndi = tracker(scripted, [(cmd("TSTART:"), encode_reply("RESET"))])
    with pytest.raises(ProtocolError, match="instead of OKAY"):
        ndi.start()


def test_close_stops_tracking_and_closes_once(scripted: list[ScriptedPort]) -> None:
    ndi = tracker(scripted, [(cmd("TSTART:"), OKAY), (cmd("TSTOP:"), OKAY)])
    with ndi:
        ndi.start()
    ndi.close()
    assert scripted[0].closed


def test_background_reader_hands_over_newest_frame_then_its_error(scripted: list[ScriptedPort]) -> None:
    frames = [encode_reply(f"0101MISSING00000031{n:08X}\n0000") for n in (1, 2, 3)]
    error = encode_error(0x0C)
    ndi = tracker(scripted, [(cmd("TSTART:"), OKAY)] + [(cmd("TX:0001"), f) for f in frames]
                  + [(cmd("TX:0001"), error)])
    port = scripted[-1]
    seen_frame_3 = threading.Event()
    plain_reply = port._reply

    def reply_after_frame_3_was_seen(reply: bytes | None) -> None:
        # Hold the error back until the test has taken frame 3: otherwise a fast reader can pass
        # frame 3 and reach the error before the test thread looks, and the test would race.
        if reply == error:
            seen_frame_3.wait(timeout=5.0)
        plain_reply(reply)

    port._reply = reply_after_frame_3_was_seen  # type: ignore[method-assign]
    ndi.start()
    ndi.start_streaming(rate_hz=200)
    assert ndi.wait_for_frame(2, timeout_s=2.0)[0].frame == 3
    seen_frame_3.set()
    with pytest.raises(NdiCommandError, match="ERROR0C"):
        ndi.wait_for_frame(3, timeout_s=2.0)
    with pytest.raises(NdiCommandError):
        ndi.latest()
    ndi.stop_streaming()


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(mode=st.sampled_from(["tx", "bx"]), junk=st.one_of(
    st.binary(max_size=120).map(lambda raw: raw.replace(b"\r", b"") + b"\r"),
    st.binary(max_size=120).map(lambda raw: b"\xc4\xa5" + raw),
    st.text("0123456789ABCDEF+-MISNGDABLE\n", max_size=120).map(lambda text: encode_reply(text))))
def test_any_reply_is_a_sample_list_or_a_device_error(mode: str, junk: bytes) -> None:
    port = ScriptedPort([(cmd(f"{mode.upper()}:0001"), junk)])
    ndi = NDITracker(port, reply_timeout_s=0.05)  # type: ignore[arg-type]
    try:
        samples = ndi.read_frame(mode)
    except DeviceError:
        return          # ProtocolError, NdiCommandError or a timeout on a short binary reply: all typed
    assert all(s.missing == (s.transform is None) for s in samples)


# -- the samples of a reply: the reader's precompiled path against the definition ---------------------------

def _reference_transform(q: tuple[float, ...], t: tuple[float, ...]) -> np.ndarray:
    """The 4x4 as the driver defined it before its per-poll path was made lean (numpy, normalised q)."""
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    transform = np.eye(4)
    transform[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
    transform[:3, 3] = t
    return transform


def _assert_samples_match(samples: list, tools: list, rom_of: dict[int, str], t: float, mode: str = "bx") -> None:
    from firmware_protocol.ndi_replies import ToolState

    assert len(samples) == len(tools)
    for sample, tool in zip(samples, tools):
        rom = rom_of.get(tool.handle, f"handle-{tool.handle:02x}")
        assert (sample.handle, sample.rom, sample.t) == (tool.handle, rom, t)
        assert sample.missing == (tool.state != ToolState.VALID)
        assert sample.disabled == (tool.state == ToolState.DISABLED)
        if tool.state == ToolState.DISABLED and mode == "bx":   # BX sends neither for a disabled handle
            assert (sample.frame, sample.port_status) == (0, 0)
        else:
            assert (sample.frame, sample.port_status) == (tool.frame, tool.port_status)
        if tool.state != ToolState.VALID:
            assert sample.transform is None and sample.quaternion is None and sample.rms_mm is None
            continue
        assert sample.quaternion == pytest.approx(tool.quaternion, abs=1e-6)      # float32 on BX
        assert all(type(v) is float for v in sample.quaternion) and type(sample.rms_mm) is float
        assert sample.rms_mm == pytest.approx(tool.rms_mm, abs=1e-6)
        assert sample.transform.shape == (4, 4) and not sample.transform.flags.writeable
        np.testing.assert_allclose(sample.transform, _reference_transform(sample.quaternion, sample.position_mm),
                                   rtol=0, atol=1e-12)
        assert sample.position_mm == pytest.approx(tool.translation_mm, abs=1e-3)


def _tool_records():
    from firmware_protocol.ndi_replies import ToolRecord, ToolState

    unit = st.floats(-1, 1, allow_nan=False).map(lambda v: round(v, 4))
    mm = st.floats(-9999, 9999, allow_nan=False).map(lambda v: round(v, 2))
    quaternion = st.tuples(unit, unit, unit, unit).filter(lambda q: sum(v * v for v in q) > 1e-3)
    return st.builds(
        lambda handle, state, q, t, rms, status, frame: ToolRecord(
            handle, state, *((q, t, rms) if state == ToolState.VALID else (None, None, None)),
            port_status=status, frame=frame),
        st.integers(1, 255), st.sampled_from(list(ToolState)), quaternion, st.tuples(mm, mm, mm),
        st.floats(0, 9, allow_nan=False).map(lambda v: round(v, 4)),
        st.integers(0, 0xFFFFFFFF), st.integers(0, 0xFFFFFFFF))


@settings(max_examples=150, deadline=None)
@given(mode=st.sampled_from(["tx", "bx"]), tools=st.lists(_tool_records(), max_size=6))
def test_frame_samples_are_the_reference_transforms(mode: str, tools: list) -> None:
    from firmware_protocol.ndi_replies import TrackingReply, encode_bx, encode_tx

    wire = (encode_bx if mode == "bx" else encode_tx)(TrackingReply(tuple(tools), 0))
    port = ScriptedPort([(cmd(f"{mode.upper()}:0001"), wire)])
    ndi = NDITracker(port, reply_timeout_s=0.2, clock=lambda: 7.5)  # type: ignore[arg-type]
    rom_of = {tool.handle: f"tool-{tool.handle}.rom" for tool in tools[::2]}
    ndi.tools.update(rom_of)
    _assert_samples_match(ndi.read_frame(mode), tools, rom_of, 7.5, mode)
    port.finish()


def test_bx_missing_tool_beside_a_tracked_one(scripted: list[ScriptedPort]) -> None:
    from firmware_protocol.ndi_replies import ToolRecord, ToolState, TrackingReply, encode_bx

    tools = [ToolRecord(1, ToolState.VALID, (0.7071, 0.0, 0.7071, 0.0), (12.34, -56.78, -1500.0), 0.1234,
                        port_status=0x31, frame=208),
             ToolRecord(2, ToolState.MISSING, port_status=0x31, frame=208)]
    ndi = tracker(scripted, [(cmd("BX:0001"), encode_bx(TrackingReply(tuple(tools))))], clock=lambda: 1.0)
    ndi.tools[1] = "ref.rom"
    samples = ndi.read_frame("bx")
    _assert_samples_match(samples, tools, {1: "ref.rom"}, 1.0)
    np.testing.assert_allclose(samples[0].transform[:3, :3] @ [1, 0, 0], [0, 0, -1], atol=1e-4)


def test_bx_body_crc_error_is_protocol_error_and_the_next_frame_reads(scripted: list[ScriptedPort]) -> None:
    from firmware_protocol.ndi_replies import ToolRecord, ToolState, TrackingReply, encode_bx

    good = encode_bx(TrackingReply((ToolRecord(1, ToolState.VALID, (1, 0, 0, 0), (1.0, 2.0, 3.0), 0.1, frame=5),)))
    bad = good[:-1] + bytes([good[-1] ^ 0x01])
    ndi = tracker(scripted, [(cmd("BX:0001"), bad), (cmd("BX:0001"), good)])
    with pytest.raises(ProtocolError, match="malformed BX reply: BX body CRC"):
        ndi.read_frame("bx")
    (sample,) = ndi.read_frame("bx")
    assert sample.frame == 5 and sample.position_mm == pytest.approx((1.0, 2.0, 3.0))


def test_zero_quaternion_gives_a_nan_transform_not_an_exception(scripted: list[ScriptedPort]) -> None:
    from firmware_protocol.ndi_replies import ToolRecord, ToolState, TrackingReply, encode_bx

    wire = encode_bx(TrackingReply((ToolRecord(1, ToolState.VALID, (0, 0, 0, 0), (1.0, 2.0, 3.0), 0.1),)))
    ndi = tracker(scripted, [(cmd("BX:0001"), wire)])
    (sample,) = ndi.read_frame("bx")
    assert not sample.missing and np.isnan(sample.transform[:3, :3]).all()
    assert sample.position_mm == pytest.approx((1.0, 2.0, 3.0))


class FlushCountingPort(ScriptedPort):
    """A scripted port that may hold stale bytes (an abandoned reply's tail) and counts its flushes."""

    flushes = 0

    def reset_input_buffer(self) -> None:
        self.flushes += 1
        self._rx = b""


def test_stale_bytes_are_discarded_before_a_command_and_only_then_flushed(caplog) -> None:
    port = FlushCountingPort([(cmd("TX:0001"), WORKED_TX), (cmd("TX:0001"), WORKED_TX)])
    ndi = NDITracker(port, reply_timeout_s=0.2)  # type: ignore[arg-type]
    (sample,) = ndi.read_frame("tx")
    assert sample.frame == 208 and port.flushes == 0      # nothing waiting: no flush
    port._rx = b"0000\r+0123400000031"                    # the tail of a reply given up on
    with caplog.at_level("WARNING", logger="drivers.ndi_tracker"):
        (sample,) = ndi.read_frame("tx")
    assert sample.frame == 208 and port.flushes == 1
    assert "discarding 19 stale bytes" in caplog.text
    port.finish()
