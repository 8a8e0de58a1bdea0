"""USB grabber byte formats: byte-exact vectors, round trips, and reassembly/resynchronisation properties."""
from __future__ import annotations

import zlib

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_protocol import usb_grabber as proto
from firmware_protocol.errors import CrcError, FrameError, TruncatedFrameError

# A 3x2 mono16 frame, number 7, t = 1.234567 s, exposure 5 ms (also in USB_GRABBER.md).
PAYLOAD = bytes.fromhex("100020003000400050006000")
FRAME_VECTOR = bytes.fromhex(
    "58524631" "01" "70" "02" "00" "07000000" "87d6120000000000" "88130000" "0300" "0200" "0c000000"
    "5715f51c" "260444f0") + PAYLOAD


def test_crc_is_crc32_iso_hdlc() -> None:
    assert zlib.crc32(b"123456789") == 0xCBF43926   # the catalogue's check value


def test_frame_vector_is_byte_exact() -> None:
    wire = proto.encode_frame("p", proto.PixelFormat.MONO16, 7, 1_234_567, 5000, 3, 2, PAYLOAD)
    assert wire == FRAME_VECTOR
    header = proto.FrameHeader.decode(FRAME_VECTOR)
    assert (header.plane, header.number, header.device_time_us, header.exposure_us) == ("p", 7, 1_234_567, 5000)
    assert (header.width, header.height, header.payload_length, header.payload_crc) == (3, 2, 12, 0x1CF51557)


def test_control_vectors_are_byte_exact() -> None:
    identify = proto.IdentifyReply("q", 1024, 1024, (proto.PixelFormat.MONO8, proto.PixelFormat.MONO16), 60.0, 0x0102)
    assert identify.encode() == bytes.fromhex("58524749 01 71 0004 0004 03 00 60ea0000 0201 0000")
    assert proto.IdentifyReply.decode(identify.encode()) == identify
    status = proto.StatusReply(proto.DeviceState.STREAMING, 0, 1000, 3, 30.0)
    assert status.encode() == bytes.fromhex("01 00 0000 e8030000 03000000 30750000")
    assert proto.StatusReply.decode(status.encode()) == status
    assert proto.encode_rate(29.97) == bytes.fromhex("12750000")
    assert proto.encode_exposure(0.005) == bytes.fromhex("88130000")
    assert (proto.REQUEST_TYPE_IN, proto.REQUEST_TYPE_OUT) == (0xC0, 0x40)


@pytest.mark.parametrize("offset", [0, 4, 5, 6, 8, 12, 20, 24, 26, 28, 32, 36])
def test_any_flipped_header_byte_is_rejected(offset: int) -> None:
    bad = bytearray(FRAME_VECTOR)
    bad[offset] ^= 0x01
    with pytest.raises(FrameError):
        proto.FrameHeader.decode(bad)


def test_header_checks_beyond_the_crc() -> None:
    def header(**changes: object) -> bytes:
        fields = dict(plane="p", pixel_format=proto.PixelFormat.MONO16, number=1, device_time_us=0, exposure_us=0,
                      width=3, height=2, payload_length=12, payload_crc=0)
        fields.update(changes)
        return proto.FrameHeader(**fields).encode()  # type: ignore[arg-type]

    with pytest.raises(FrameError, match="does not match 3x2"):
        proto.FrameHeader.decode(header(payload_length=13))
    with pytest.raises(FrameError, match="out of range"):
        proto.FrameHeader.decode(header(width=0, payload_length=0))
    with pytest.raises(TruncatedFrameError):
        proto.FrameHeader.decode(FRAME_VECTOR[:30])
    with pytest.raises(CrcError):
        proto.FrameHeader.decode(FRAME_VECTOR[:36] + b"\0\0\0\0")
    with pytest.raises(FrameError, match="IDENTIFY reply starts"):
        proto.IdentifyReply.decode(b"NOPE" + bytes(16))
    with pytest.raises(TruncatedFrameError):
        proto.StatusReply.decode(bytes(15))


def frames(count: int, width: int = 5, height: int = 3) -> list[bytes]:
    out = []
    for n in range(count):
        payload = bytes((n * 31 + i) % 256 for i in range(width * height * 2))
        out.append(proto.encode_frame("q", proto.PixelFormat.MONO16, n, n * 1000, 100, width, height, payload))
    return out


@pytest.mark.parametrize("lent", [False, True])
@settings(max_examples=60, deadline=None)
@given(cuts=st.lists(st.integers(min_value=0, max_value=20 * 70), max_size=40))
def test_frames_survive_any_split_into_transfers(lent: bool, cuts: list[int]) -> None:
    stream = b"".join(frames(20))
    bounds = sorted({0, len(stream), *[min(c, len(stream)) for c in cuts]})
    assembler = proto.FrameAssembler()
    got = []
    for a, b in zip(bounds, bounds[1:]):
        got += assembler.feed(stream[a:b], lent=lent)
    assert [f.header.number for f in got] == list(range(20))
    assert [f.payload for f in got] == [w[proto.HEADER_SIZE:] for w in frames(20)]
    assert assembler.stats.corrupt == 0 and assembler.stats.skipped_bytes == 0


@pytest.mark.parametrize("lent", [False, True])
@settings(max_examples=60, deadline=None)
@given(damage=st.dictionaries(st.integers(min_value=1, max_value=18),
                              st.sampled_from(["header", "payload", "truncate", "garbage"]), max_size=6),
       chunk=st.integers(min_value=1, max_value=200))
def test_damage_is_counted_and_the_rest_arrives_intact(lent: bool, damage: dict[int, str], chunk: int) -> None:
    clean = frames(20)
    stream = bytearray()
    for n, wire in enumerate(clean):
        kind = damage.get(n)
        wire = bytearray(wire)
        if kind == "header":
            wire[10] ^= 0xFF
        elif kind == "payload":
            wire[proto.HEADER_SIZE + 3] ^= 0x01
        elif kind == "truncate":
            del wire[proto.HEADER_SIZE + 7:]
        elif kind == "garbage":
            wire[:0] = b"\x00XRF\x17" * 9
        stream += wire
    assembler = proto.FrameAssembler()
    got = []
    for start in range(0, len(stream), chunk):
        got += assembler.feed(bytes(stream[start:start + chunk]), lent=lent)
    lost = {n for n, kind in damage.items() if kind != "garbage"}
    assert [f.header.number for f in got] == [n for n in range(20) if n not in lost]
    assert all(f.payload == clean[f.header.number][proto.HEADER_SIZE:] for f in got)
    stats = assembler.stats
    assert stats.corrupt_headers == sum(kind == "header" for kind in damage.values())
    # A cut frame whose claimed length holds only garbage cannot be told from a bad CRC; together they add up.
    assert stats.bad_crc + stats.truncated == sum(kind in ("payload", "truncate") for kind in damage.values())
    assert stats.truncated <= sum(kind == "truncate" for kind in damage.values())


def test_reset_forgets_a_partial_frame() -> None:
    one, two = frames(2)
    assembler = proto.FrameAssembler()
    assert assembler.feed(one[:50]) == []
    assembler.reset()
    got = assembler.feed(two)
    assert [f.header.number for f in got] == [1] and assembler.stats.skipped_bytes == 50


def test_a_cut_frame_is_counted_as_truncated_and_the_next_one_arrives_early() -> None:
    zero, one, two = frames(3, width=40, height=30)
    assembler = proto.FrameAssembler()
    got = assembler.feed(zero + one[:proto.HEADER_SIZE + 100] + two)
    assert [f.header.number for f in got] == [0, 2]
    assert assembler.stats.truncated == 1 and assembler.stats.bad_crc == 0
    # Early: frame 2 is handed on as soon as it is complete, without waiting for frame 1's claimed length.
    assembler = proto.FrameAssembler()
    assert [f.header.number for f in assembler.feed(one[:proto.HEADER_SIZE + 100] + two)] == [2]


@settings(max_examples=40, deadline=None)
@given(damage=st.dictionaries(st.integers(min_value=0, max_value=11),
                              st.sampled_from(["header", "payload", "truncate", "garbage"]), max_size=5),
       chunk=st.integers(min_value=1, max_value=400))
def test_lending_the_transfers_changes_nothing_but_the_copy(damage: dict[int, str], chunk: int) -> None:
    stream = bytearray()
    for n, wire in enumerate(frames(12)):
        wire = bytearray(wire)
        kind = damage.get(n)
        if kind == "header":
            wire[12] ^= 0x40
        elif kind == "payload":
            wire[-1] ^= 0x80
        elif kind == "truncate":
            del wire[proto.HEADER_SIZE + 11:]
        elif kind == "garbage":
            wire[:0] = b"XRF1" + bytes(50)
        stream += wire
    results = []
    for lent in (False, True):
        assembler = proto.FrameAssembler()
        got = []
        for start in range(0, len(stream), chunk):
            got += [(f.header, bytes(f.payload)) for f in assembler.feed(bytes(stream[start:start + chunk]), lent=lent)]
        results.append((got, assembler.stats, assembler.buffered))
    assert results[0] == results[1]


def test_a_frame_inside_a_lent_transfer_is_a_view_on_it_and_otherwise_a_copy() -> None:
    wire = frames(1, width=40, height=30)[0]
    transfer = bytearray(wire)
    (lent,) = proto.FrameAssembler().feed(transfer, lent=True)
    (copied,) = proto.FrameAssembler().feed(transfer)
    assert isinstance(lent.payload, memoryview) and lent.payload.obj is transfer
    assert bytes(lent.payload) == bytes(copied.payload) == wire[proto.HEADER_SIZE:]
    transfer[proto.HEADER_SIZE] ^= 0xFF        # the caller breaking its promise shows in the view only
    assert bytes(lent.payload) != bytes(copied.payload) == wire[proto.HEADER_SIZE:]


def test_a_bad_payload_in_a_lent_transfer_is_counted_as_in_a_copied_one() -> None:
    zero, one = frames(2, width=40, height=30)
    bad = bytearray(zero)
    bad[-5] ^= 0x10
    assembler = proto.FrameAssembler()
    assert assembler.feed(bad, lent=True) == [] and assembler.stats.bad_crc == 1
    assert [f.header.number for f in assembler.feed(bytearray(one), lent=True)] == [1]
    assert assembler.stats.skipped_bytes == len(zero)


def test_payload_buffers_are_reused_only_once_nothing_refers_to_them() -> None:
    import numpy as np

    wires = frames(30, width=40, height=30)
    assembler = proto.FrameAssembler(buffers=proto.PayloadBuffers(keep=4))
    held = {}
    for n, wire in enumerate(wires):
        # Three transfers per frame: the payload is collected into a pooled buffer.
        (frame,) = assembler.feed(wire[:17]) + assembler.feed(wire[17:900]) + assembler.feed(wire[900:])
        if n in (0, 1, 2, 9):
            held[n] = np.frombuffer(frame.payload, dtype="<u2")[5:]   # a view on a view, as the tracker's ROIs are
        del frame
        assert all(bytes(image) == wires[k][proto.HEADER_SIZE + 10:] for k, image in held.items())
    # Frames let go give their buffer back; each held one keeps its own out of use.
    assert assembler.buffers.made <= len(held) + 1


def test_payload_buffers_of_a_full_pool_are_made_afresh() -> None:
    pool = proto.PayloadBuffers(keep=2)
    taken = [pool.take(64) for _ in range(5)]
    assert len({id(buffer) for buffer in taken}) == 5 and pool.made == 5
    del taken
    again = pool.take(64)
    assert pool.made == 5 and len(again) == 64 and pool.take(32) is not again and pool.made == 6
