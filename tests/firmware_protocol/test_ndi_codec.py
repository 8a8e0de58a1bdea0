"""NDI Combined API codec against the facts document's vectors: CRC, both command forms, replies, TX, BX."""
from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_protocol.errors import CrcError, FrameError, TruncatedFrameError
from firmware_protocol.ndi import (
    Command,
    CommSettings,
    LineSplitter,
    PortHandleStatus,
    crc16,
    crc_hex,
    decode_command,
    decode_reply,
    encode_command,
    encode_error,
    encode_phsr,
    encode_reply,
    error_meaning,
    parse_comm,
    parse_error,
    parse_handle,
    parse_phrq,
    parse_phsr,
    pvwr_params,
    rom_chunks,
)
from firmware_protocol.ndi_replies import (
    ToolRecord,
    ToolState,
    TrackingReply,
    bx_total_length,
    decode_bx,
    decode_bx_records,
    decode_tx,
    encode_bx,
    encode_tx,
    parse_reply_option,
    reply_is_binary,
)

WORKED_TX = (b"0101+07071+00000+07071+00000+001234-005678-150000+0123400000031000000D0\n"
             b"000018CA\r")
WORKED_RECORD = ToolRecord(0x01, ToolState.VALID, (0.7071, 0.0, 0.7071, 0.0), (12.34, -56.78, -1500.00), 0.1234,
                           port_status=0x31, frame=208)


@pytest.mark.parametrize("text, crc", [
    (b"123456789", 0xBB3D), (b"INIT:", 0xE3A5), (b"OKAY", 0xA896), (b"RESET", 0xBE6F), (b"VER:0", 0x65EE),
    (b"ERROR01", 0x6BC2), (b"GETINFO:Features.Firmware.Version", 0x0492),
])
def test_crc_check_vectors(text: bytes, crc: int) -> None:
    assert crc16(text) == crc
    assert crc_hex(text) == b"%04X" % crc


def test_crc_runs_over_chunks() -> None:
    assert crc16(b"56789", crc16(b"1234")) == 0xBB3D


def _crc16_by_definition(data: bytes, crc: int = 0) -> int:
    """CRC-16/ARC bit by bit (reflected polynomial 0xA001), as the facts document defines it."""
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300), st.integers(0, 0xFFFF))
def test_table_crc_is_the_bitwise_definition(data: bytes, start: int) -> None:
    assert crc16(data) == _crc16_by_definition(data)
    assert crc16(data, start) == _crc16_by_definition(data, start)


def test_command_forms_on_the_wire() -> None:
    assert encode_command("INIT") == b"INIT:E3A5\r"
    assert encode_command("VER", "0") == b"VER:065EE\r"
    assert encode_command("PINIT", "0A", with_crc=False) == b"PINIT 0A\r"
    assert Command("TSTART", "", has_crc=False).encode() == b"TSTART \r"


@pytest.mark.parametrize("line, expected", [
    (b"INIT:E3A5\r", Command("INIT", "", True)),
    (b"GETINFO:Features.Firmware.Version0492", Command("GETINFO", "Features.Firmware.Version", True)),
    (b"PINIT 0a\r", Command("PINIT", "0a", False)),
    (b"TSTART\r", Command("TSTART", "", False)),
    (b"tstop \r", Command("TSTOP", "", False)),
])
def test_decode_both_command_forms(line: bytes, expected: Command) -> None:
    assert decode_command(line) == expected


def test_bad_command_crc_and_garbage() -> None:
    with pytest.raises(CrcError, match="E3A6 given, E3A5 computed"):
        decode_command(b"INIT:E3A6\r")
    with pytest.raises(CrcError, match="no 4-hex-digit CRC"):
        decode_command(b"INIT:\r")
    with pytest.raises(FrameError):
        decode_command(b"\x01\x02 x\r")
    with pytest.raises(FrameError):
        decode_command(b"\r")
    with pytest.raises(FrameError):
        encode_command("tx")


def test_line_splitter_reassembles_and_bounds() -> None:
    splitter = LineSplitter(max_line=16)
    assert splitter.feed(b"INIT:E3") == []
    assert splitter.feed(b"A5\rVER:065EE\rTX") == [b"INIT:E3A5", b"VER:065EE"]
    assert splitter.pending == b"TX"
    with pytest.raises(FrameError, match="without a CR"):
        splitter.feed(b"x" * 20)


def test_replies_carry_crc_over_text_and_lfs() -> None:
    assert encode_reply("OKAY") == b"OKAYA896\r"
    assert encode_error(0x01) == b"ERROR016BC2\r"
    assert encode_reply("RESET") == b"RESETBE6F\r"
    text = "Polaris\nFreeze Tag: x\n"
    assert decode_reply(encode_reply(text)) == text
    with pytest.raises(CrcError):
        decode_reply(b"OKAYA897\r")
    with pytest.raises(FrameError, match="does not end with"):
        decode_reply(b"OK\r")


def test_error_codes_and_meanings() -> None:
    assert parse_error("ERROR0C") == 0x0C
    assert parse_error("ERROR0c") == 0x0C
    assert parse_error("OKAY") is None and parse_error("WARNING01") is None
    assert error_meaning(0x04) == "invalid CRC calculated for command"
    assert error_meaning(0x0C) == "command is invalid while in the current mode"
    assert "0x99" in error_meaning(0x99)


def test_comm_table() -> None:
    assert parse_comm("50000") == CommSettings(115200, 8, "N", 1, False)
    assert parse_comm("A1211") == CommSettings(230400, 7, "E", 2, True)
    assert CommSettings(115200).encode_params() == "50000"
    assert CommSettings(921600, parity="O").encode_params() == "60100"
    for bad in ("5000", "90000", "50300"):
        with pytest.raises(FrameError):
            parse_comm(bad)
    with pytest.raises(FrameError, match="cannot select"):
        CommSettings(4800).encode_params()


def test_phsr_phrq_and_handles() -> None:
    assert encode_phsr([PortHandleStatus(1, 0x001), PortHandleStatus(2, 0x001)]) == "020100102001"
    assert parse_phsr("020100102001") == [PortHandleStatus(1, 1), PortHandleStatus(2, 1)]
    assert parse_phsr("00") == []
    with pytest.raises(FrameError, match="announces 2 handles"):
        parse_phsr("0201001")
    assert parse_phrq("0A") == 10
    assert parse_handle("0a") == parse_handle("0A") == 10
    with pytest.raises(FrameError):
        parse_handle("g1")


def test_rom_is_padded_to_sixteen_pvwr_chunks() -> None:
    chunks = rom_chunks(b"\x01" * 100)
    assert [addr for addr, _ in chunks] == list(range(0, 1024, 64))
    assert chunks[1][1] == b"\x01" * 36 + b"\x00" * 28
    params = pvwr_params(0x0A, 0x40, chunks[1][1])
    assert params.startswith("0A0040" + "01" * 36) and len(params) == 134
    with pytest.raises(FrameError):
        rom_chunks(b"\0" * 1025)
    with pytest.raises(FrameError):
        pvwr_params(1, 0x20, b"\0" * 64)


def test_tx_worked_example_both_ways() -> None:
    assert encode_tx(TrackingReply((WORKED_RECORD,), 0)) == WORKED_TX
    assert decode_tx(WORKED_TX) == TrackingReply((WORKED_RECORD,), 0)


def test_tx_missing_and_disabled_records() -> None:
    reply = TrackingReply((ToolRecord(0x0A, ToolState.MISSING, port_status=0x31, frame=0x1234),
                           ToolRecord(0x0B, ToolState.DISABLED, port_status=0x11, frame=0x1234)), 0x0002)
    wire = encode_tx(reply)
    assert wire.startswith(b"020AMISSING0000003100001234\n0BDISABLED0000001100001234\n0002")
    assert decode_tx(wire) == reply


def test_tx_malformed() -> None:
    with pytest.raises(CrcError):
        decode_tx(WORKED_TX.replace(b"18CA", b"18CB"))
    with pytest.raises(TruncatedFrameError, match="announces 2 handles"):
        decode_tx(encode_reply(WORKED_TX[:-5].decode().replace("0101", "0201", 1)))
    with pytest.raises(FrameError, match="UNOCCUPIED"):
        decode_tx(encode_reply("0101UNOCCUPIED0000000000000000\n0000"))
    with pytest.raises(FrameError, match="sign and 5 digits"):
        decode_tx(encode_reply(WORKED_TX[:-5].decode().replace("+07071", " 07071", 1)))
    with pytest.raises(FrameError, match="does not fit"):
        encode_tx(TrackingReply((ToolRecord(1, ToolState.VALID, (1, 0, 0, 0), (1e5, 0, 0), 0.1),)))


def test_bx_layout_by_hand() -> None:
    wire = encode_bx(TrackingReply((WORKED_RECORD,), 0))
    body = bytes([1, 0x01, 0x01]) + struct.pack("<8f", 0.7071, 0, 0.7071, 0, 12.34, -56.78, -1500.0, 0.1234) \
        + struct.pack("<IIH", 0x31, 208, 0)
    header = b"\xc4\xa5" + struct.pack("<H", len(body))
    assert wire == header + struct.pack("<H", crc16(header)) + body + struct.pack("<H", crc16(body))
    assert bx_total_length(wire[:6]) == len(wire)
    decoded = decode_bx(wire).tools[0]
    assert decoded.handle == 1 and decoded.frame == 208 and decoded.port_status == 0x31
    assert decoded.translation_mm == pytest.approx((12.34, -56.78, -1500.0), abs=1e-4)
    assert reply_is_binary(wire[:1]) and not reply_is_binary(b"E")


def test_bx_missing_disabled_and_damage() -> None:
    reply = TrackingReply((ToolRecord(2, ToolState.MISSING, port_status=0x31, frame=9),
                           ToolRecord(3, ToolState.DISABLED, port_status=0, frame=0)), 0)
    wire = encode_bx(reply)
    assert len(wire) == 6 + (1 + 2 + 8 + 2 + 2) + 2
    assert decode_bx(wire) == reply
    with pytest.raises(CrcError, match="header"):
        decode_bx(wire[:4] + b"\0\0" + wire[6:])
    with pytest.raises(CrcError, match="body"):
        decode_bx(wire[:-1] + bytes([wire[-1] ^ 0xFF]))
    with pytest.raises(TruncatedFrameError):
        decode_bx(wire[:-3])
    with pytest.raises(FrameError, match="trailing"):
        decode_bx(wire + b"\0")
    with pytest.raises(FrameError, match="c4a5"):
        bx_total_length(b"ERROR0")


def test_reply_options() -> None:
    assert parse_reply_option("") == 0x0001
    assert parse_reply_option("0801") == 0x0801
    with pytest.raises(FrameError):
        parse_reply_option("08")


_unit = st.floats(-1, 1, allow_nan=False).map(lambda v: round(v, 4))
_mm = st.floats(-9999, 9999, allow_nan=False).map(lambda v: round(v, 2))
_record = st.builds(
    lambda handle, state, q, t, rms, status, frame: ToolRecord(
        handle, state, *((q, t, rms) if state == ToolState.VALID else (None, None, None)),
        port_status=status, frame=frame),
    st.integers(0, 255), st.sampled_from(list(ToolState)), st.tuples(_unit, _unit, _unit, _unit),
    st.tuples(_mm, _mm, _mm), st.floats(0, 9, allow_nan=False).map(lambda v: round(v, 4)),
    st.integers(0, 0xFFFFFFFF), st.integers(0, 0xFFFFFFFF))


@settings(max_examples=150, deadline=None)
@given(st.lists(_record, max_size=12), st.integers(0, 0xFFFF))
def test_tx_round_trip_property(records: list[ToolRecord], status: int) -> None:
    reply = TrackingReply(tuple(records), status)
    assert decode_tx(encode_tx(reply)) == reply


@settings(max_examples=150, deadline=None)
@given(st.lists(_record, max_size=12), st.integers(0, 0xFFFF))
def test_bx_round_trip_property(records: list[ToolRecord], status: int) -> None:
    reply = TrackingReply(tuple(records), status)
    decoded = decode_bx(encode_bx(reply))
    assert decoded.system_status == status and len(decoded.tools) == len(records)
    for got, sent in zip(decoded.tools, records):
        assert (got.handle, got.state) == (sent.handle, sent.state)
        if sent.state != ToolState.DISABLED:
            assert (got.port_status, got.frame) == (sent.port_status, sent.frame)
        if sent.state == ToolState.VALID:
            assert got.translation_mm == pytest.approx(sent.translation_mm, rel=1e-6, abs=1e-3)


def _record_tuple(tool: ToolRecord) -> tuple:
    """What decode_bx_records promises for one record, built from the record's fields."""
    if tool.state == ToolState.VALID:
        assert tool.quaternion is not None and tool.translation_mm is not None and tool.rms_mm is not None
        pose = struct.unpack("<8f", struct.pack("<8f", *tool.quaternion, *tool.translation_mm, tool.rms_mm))
        return (tool.handle, 1, *pose, tool.port_status, tool.frame)
    if tool.state == ToolState.MISSING:
        return (tool.handle, 2, tool.port_status, tool.frame)
    return (tool.handle, 4)


@settings(max_examples=150, deadline=None)
@given(st.lists(_record, max_size=12), st.integers(0, 0xFFFF))
def test_bx_flat_records_carry_every_field(records: list[ToolRecord], status: int) -> None:
    wire = encode_bx(TrackingReply(tuple(records), status))
    flat, system_status = decode_bx_records(wire)
    assert system_status == status
    assert flat == [_record_tuple(tool) for tool in records]
    # decode_bx is built from them: the same fields in ToolRecords
    for got, want in zip(decode_bx(wire).tools, flat):
        assert _record_tuple(got) == want


def test_bx_flat_records_reject_what_decode_bx_rejects() -> None:
    wire = encode_bx(TrackingReply((WORKED_RECORD, ToolRecord(2, ToolState.MISSING, port_status=0x31, frame=9)), 0))
    body = bytearray(wire[6:-2])
    with pytest.raises(CrcError, match="body"):
        decode_bx_records(wire[:-1] + bytes([wire[-1] ^ 0x01]))
    with pytest.raises(TruncatedFrameError):
        decode_bx_records(wire[:-5])

    def reframed(new_body: bytes) -> bytes:
        header = b"\xc4\xa5" + struct.pack("<H", len(new_body))
        return header + struct.pack("<H", crc16(header)) + new_body + struct.pack("<H", crc16(new_body))

    unknown = bytearray(body)
    unknown[2] = 0x08                                       # the first record's status byte
    with pytest.raises(FrameError, match="unknown status 0x08"):
        decode_bx_records(reframed(bytes(unknown)))
    nan = bytearray(body)
    nan[3 + 4 * 5:3 + 4 * 6] = struct.pack("<f", float("nan"))   # Ty
    with pytest.raises(FrameError, match="non-finite"):
        decode_bx_records(reframed(bytes(nan)))
    infinite = bytearray(body)
    infinite[3:7] = struct.pack("<f", float("inf"))              # Q0
    with pytest.raises(FrameError, match="non-finite"):
        decode_bx(reframed(bytes(infinite)))
    with pytest.raises(TruncatedFrameError):
        decode_bx_records(reframed(bytes(body[:20])))
