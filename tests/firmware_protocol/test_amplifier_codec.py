"""Amplifier codec: CRC check value, COBS, round trips of every message (hypothesis), the vector file,
and the streaming decoder's rejection counting and resynchronisation."""
from __future__ import annotations

import json
import random
import struct
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_protocol.amplifier import (
    MAX_CHANNELS,
    MESSAGE_CLASSES,
    Ack,
    ClearFault,
    ConfigureLimits,
    Disable,
    Enable,
    Fault,
    GetStatus,
    Heartbeat,
    Hello,
    HelloReply,
    MessageDecoder,
    MsgType,
    Nak,
    NakReason,
    SetCurrents,
    SetCurrentsReply,
    State,
    Status,
    decode_payload,
    encode_message,
    encode_set_currents,
    seq_newer,
)
from firmware_protocol.amplifier_framing import (
    MAX_ENCODED,
    FrameDecoder,
    cobs_decode,
    cobs_encode,
    crc16_ccitt_false,
)
from firmware_protocol.errors import FrameError

VECTORS = json.loads((Path(__file__).parents[2] / "firmware_protocol" / "amplifier_vectors.json").read_text())

i32 = st.integers(-(2 ** 31), 2 ** 31 - 1)
u32 = st.integers(0, 2 ** 32 - 1)
u16 = st.integers(0, 2 ** 16 - 1)
i16 = st.integers(-(2 ** 15), 2 ** 15 - 1)
u8 = st.integers(0, 255)
states = st.sampled_from(list(State))
faults = u32.map(Fault)
channels = st.integers(1, MAX_CHANNELS)


def vec(n: int, elements: st.SearchStrategy[int]) -> st.SearchStrategy[tuple[int, ...]]:
    return st.lists(elements, min_size=n, max_size=n).map(tuple)


@st.composite
def messages(draw: st.DrawFn):
    n = draw(channels)
    kind = draw(st.sampled_from(list(MsgType)))
    if kind in (MsgType.HELLO, MsgType.ENABLE, MsgType.DISABLE, MsgType.HEARTBEAT, MsgType.GET_STATUS,
                MsgType.CLEAR_FAULT):
        return MESSAGE_CLASSES[kind]()
    if kind is MsgType.SET_CURRENTS:
        return SetCurrents(draw(vec(n, i32)))
    if kind is MsgType.CONFIGURE_LIMITS:
        return ConfigureLimits(draw(u16), draw(vec(n, u32)), draw(vec(n, u32)))
    if kind is MsgType.HELLO_REPLY:
        return HelloReply((draw(u8), draw(u8), draw(u8)), draw(u32), draw(u16), draw(i16), draw(vec(n, u32)),
                          draw(vec(n, u32)), draw(vec(n, u32)))
    if kind is MsgType.SET_CURRENTS_REPLY:
        return SetCurrentsReply(draw(states), draw(faults), draw(u16), draw(vec(n, i32)))
    if kind is MsgType.STATUS:
        return Status(draw(states), draw(faults), draw(u32), draw(u16), draw(vec(n, i32)), draw(vec(n, i32)),
                      draw(vec(n, i16)))
    if kind is MsgType.ACK:
        return Ack(draw(u8), draw(states), draw(faults))
    return Nak(draw(u8), draw(st.sampled_from(list(NakReason))), draw(states), draw(faults))


def test_crc_check_value() -> None:
    assert crc16_ccitt_false(b"123456789") == 0x29B1 == int(VECTORS["crc"]["check"], 16)


def _crc_bitwise(data: bytes) -> int:
    """CRC-16/CCITT-FALSE from its definition, one bit at a time (the reference for the C one)."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


def _cobs_bytewise(data: bytes) -> bytes:
    """COBS from its definition, one byte at a time (the reference for the split-based encoder)."""
    out, code_at, code = bytearray([0]), 0, 1
    for i, byte in enumerate(data):
        if byte:
            out.append(byte)
            code += 1
        if not byte or code == 0xFF:
            out[code_at] = code
            if code == 0xFF and i == len(data) - 1:
                return bytes(out)
            code_at, code = len(out), 1
            out.append(0)
    out[code_at] = code
    return bytes(out)


# Runs of non-zero bytes around the 254-byte block length, and zeros between them.
_cobs_edge_cases = st.lists(st.sampled_from([0, 1, 253, 254, 255, 508]), max_size=4).map(
    lambda lengths: b"\x00".join(bytes([7]) * n for n in lengths))


@given(st.binary(max_size=700) | _cobs_edge_cases)
def test_fast_crc_and_cobs_equal_their_definitions(data: bytes) -> None:
    assert crc16_ccitt_false(data) == _crc_bitwise(data)
    assert cobs_encode(data) == _cobs_bytewise(data)


@given(st.binary(max_size=700))
def test_cobs_round_trip_and_no_zero(data: bytes) -> None:
    encoded = cobs_encode(data)
    assert 0 not in encoded
    assert len(encoded) <= len(data) + len(data) // 254 + 1
    assert cobs_decode(encoded) == data


@given(messages(), u16)
@settings(max_examples=200)
def test_every_message_round_trips_through_the_stream_decoder(message, seq: int) -> None:
    wire = encode_message(message, seq)
    assert wire[0] == 0 and wire[-1] == 0 and 0 not in wire[1:-1]
    assert len(wire) <= MAX_ENCODED + 2
    decoder = MessageDecoder()
    (env,) = decoder.feed(wire)
    assert (env.seq, env.msg_type, env.message) == (seq, message.TYPE, message)
    assert decoder.rejected_total == 0


@given(st.lists(st.tuples(messages(), u16), min_size=1, max_size=6), st.integers(1, 64))
def test_decoder_is_independent_of_how_bytes_are_chunked(items, chunk: int) -> None:
    wire = b"".join(encode_message(m, s) for m, s in items)
    decoder = MessageDecoder()
    got = []
    for i in range(0, len(wire), chunk):
        got += decoder.feed(wire[i:i + chunk])
    assert [(e.message, e.seq) for e in got] == list(items)


@pytest.mark.parametrize("vector", VECTORS["messages"], ids=lambda v: v["name"])
def test_message_vectors_both_ways(vector: dict) -> None:
    cls = MESSAGE_CLASSES[MsgType(vector["type_code"])]
    assert cls.TYPE.name == vector["type"]
    kwargs = {k: tuple(v) if isinstance(v, list) else v for k, v in vector["fields"].items()}
    if "state" in kwargs:
        kwargs["state"] = State(kwargs["state"])
    if "faults" in kwargs:
        kwargs["faults"] = Fault(kwargs["faults"])
    if "reason" in kwargs:
        kwargs["reason"] = NakReason(kwargs["reason"])
    message = cls(**kwargs)
    wire = bytes.fromhex(vector["wire_hex"])
    assert encode_message(message, vector["seq"]) == wire
    assert cobs_decode(wire[1:-1]) == bytes.fromhex(vector["packet_hex"])
    (env,) = MessageDecoder().feed(wire)
    assert (env.message, env.seq) == (message, vector["seq"])


@given(channels.flatmap(lambda n: vec(n, i32)), u16)
@settings(max_examples=300)
def test_the_drivers_set_currents_encoder_writes_the_same_bytes(currents: tuple[int, ...], seq: int) -> None:
    expected = encode_message(SetCurrents(currents_ma=currents), seq)
    assert encode_set_currents(currents, seq) == expected
    assert encode_set_currents(list(currents), seq) == expected


def test_the_set_currents_encoder_matches_the_vector_file_and_refuses_what_does_not_fit() -> None:
    vectors = [v for v in VECTORS["messages"] if v["type"] == "SET_CURRENTS"]
    assert vectors
    for vector in vectors:
        assert encode_set_currents(vector["fields"]["currents_ma"], vector["seq"]) == bytes.fromhex(vector["wire_hex"])
    with pytest.raises(ValueError, match="channels"):
        encode_set_currents((), 1)
    with pytest.raises(ValueError, match="channels"):
        encode_set_currents((0,) * (MAX_CHANNELS + 1), 1)
    with pytest.raises(struct.error):
        encode_set_currents((2 ** 31,), 1)
    with pytest.raises(struct.error):
        encode_set_currents((0,), 0x10000)


@pytest.mark.parametrize("case", VECTORS["cobs"], ids=lambda c: c["encoded_hex"][:20])
def test_cobs_vectors(case: dict) -> None:
    decoded, encoded = bytes.fromhex(case["decoded_hex"]), bytes.fromhex(case["encoded_hex"])
    assert cobs_encode(decoded) == encoded
    assert cobs_decode(encoded) == decoded


@pytest.mark.parametrize("case", VECTORS["rejects"], ids=lambda c: c["name"])
def test_reject_vectors_are_counted_by_reason_and_the_next_frame_survives(case: dict) -> None:
    decoder = MessageDecoder()
    follow = encode_message(Heartbeat(), 99)
    got = decoder.feed(bytes.fromhex(case["wire_hex"]) + follow)
    assert decoder.rejected[case["reason"]] == 1
    assert decoder.rejected_total == 1
    assert [e.message for e in got if e.message is not None] == [Heartbeat()]


def test_leading_delimiters_limit_the_damage_of_garbage_and_lost_delimiters() -> None:
    decoder = FrameDecoder()
    first = encode_message(SetCurrents((1, 2, 3)), 1)
    second = encode_message(SetCurrents((4, 5, 6)), 2)
    # Line noise ends at the first frame's leading delimiter (one rejection); the first frame lost its
    # trailing delimiter, but the second frame's leading one ends it, so both frames survive.
    frames = decoder.feed(b"\x13\x37" + first[:-1] + second)
    assert [f.seq for f in frames] == [1, 2]
    assert decoder.rejected_total == 1 and decoder.rejected["cobs"] + decoder.rejected["truncated"] == 1


def test_oversize_run_is_dropped_once_then_decoding_resumes() -> None:
    decoder = FrameDecoder()
    frames = decoder.feed(b"\x00" + b"\x05" * (3 * MAX_ENCODED))
    frames += decoder.feed(b"\x05\x05" + encode_message(Enable(), 3))
    assert [f.seq for f in frames] == [3]
    assert decoder.rejected["oversize"] == 1 and decoder.rejected_total == 1


def test_single_bit_flips_are_always_rejected() -> None:
    wire = encode_message(SetCurrents((10000, -10000, 2500, -1, 0, 123, 4567, -8900)), 0x1234)
    rng = random.Random(3)
    for _ in range(2000):
        corrupt = bytearray(wire)
        i = rng.randrange(1, len(wire) - 1)
        corrupt[i] ^= 1 << rng.randrange(8)
        decoder = MessageDecoder()
        got = [e for e in decoder.feed(bytes(corrupt) + b"\x00") if e.message is not None]
        assert got == [], f"flip at byte {i} accepted"
        assert decoder.rejected_total >= 1


@pytest.mark.parametrize("message, error", [
    (SetCurrents(()), ValueError),
    (SetCurrents((0,) * (MAX_CHANNELS + 1)), ValueError),
    (ConfigureLimits(100, (1, 2), (1,)), ValueError),
    (SetCurrents((2 ** 31,)), Exception),
])
def test_encoder_refuses_messages_that_do_not_fit(message, error) -> None:
    with pytest.raises(error):
        encode_message(message, 1)


def test_payload_errors_are_frame_errors() -> None:
    with pytest.raises(FrameError):
        decode_payload(MsgType.SET_CURRENTS, b"\x02\x00\x00\x00\x00")
    with pytest.raises(FrameError):
        decode_payload(0x55, b"")
    with pytest.raises(FrameError):
        decode_payload(MsgType.ACK, b"\x02\x09\x00\x00\x00\x00")   # state 9 does not exist


@pytest.mark.parametrize("seq, than, newer", [(1, 0, True), (0, 0xFFFF, True), (0x8000, 0, False),
                                               (0x7FFF, 0, True), (5, 5, False), (4, 5, False)])
def test_sequence_numbers_wrap(seq: int, than: int, newer: bool) -> None:
    assert seq_newer(seq, than) is newer


def test_disable_and_clear_are_distinct_types() -> None:
    assert {Disable.TYPE, ClearFault.TYPE, GetStatus.TYPE, Hello.TYPE} == {
        MsgType.DISABLE, MsgType.CLEAR_FAULT, MsgType.GET_STATUS, MsgType.HELLO}


@given(st.binary(max_size=251) | st.lists(st.sampled_from([0, 0, 1, 0xFF]), max_size=251).map(bytes))
def test_the_short_framing_is_the_general_one(body: bytes) -> None:
    """frame_short_body (the current command's framing in one function) gives encode_frame's bytes for every
    body it takes: zero-free, all zeros, runs of every length up to 251 bytes."""
    from firmware_protocol.amplifier_framing import frame_short_body

    assert frame_short_body(body) == b"\x00" + cobs_encode(body + struct.pack("<H", crc16_ccitt_false(body))) + b"\x00"
