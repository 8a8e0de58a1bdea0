"""Framing of the EMA amplifier link: CRC-16/CCITT-FALSE, COBS byte stuffing and a streaming decoder.

A frame on the wire is ``00 | COBS(packet) | 00``. The packet is

    offset  size  field
    0       1     protocol version (``PROTOCOL_VERSION``)
    1       1     message type
    2       2     sequence number, uint16 little-endian
    4       1     payload length N (0..``MAX_PAYLOAD``)
    5       N     payload
    5+N     2     CRC-16/CCITT-FALSE over bytes 0..5+N-1, uint16 little-endian

COBS guarantees that 0x00 appears only as a delimiter, so a receiver that lost bytes resynchronises
at the next 0x00. The leading delimiter terminates any garbage left in a receiver's buffer (for example
a frame whose trailing delimiter was lost), so one corrupt frame never swallows the next good one.
Empty frames (two delimiters in a row) are idle fill and are ignored, not counted.

This module has no I/O: :class:`FrameDecoder` is fed bytes and returns whole frames, and counts every
rejected frame by reason. ``firmware_protocol/AMPLIFIER.md`` is the normative description.
"""
from __future__ import annotations

import binascii
import struct
from collections import Counter
from dataclasses import dataclass

from firmware_protocol.errors import CrcError, FrameError, TruncatedFrameError

PROTOCOL_VERSION = 1
HEADER_SIZE = 5
CRC_SIZE = 2
MAX_PAYLOAD = 255
MAX_PACKET = HEADER_SIZE + MAX_PAYLOAD + CRC_SIZE
# COBS adds one byte per 254 bytes of data plus one; anything longer between delimiters is not a frame.
MAX_ENCODED = MAX_PACKET + MAX_PACKET // 254 + 1
DELIMITER = b"\x00"

_HEADER = struct.Struct("<BBHB")
_CRC = struct.Struct("<H")

# Reasons a receiver rejects a frame; every rejected frame is counted under exactly one of them.
REJECT_REASONS = ("cobs", "truncated", "length", "crc", "version", "oversize")


def crc16_ccitt_false(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, not reflected, no final XOR ("123456789" -> 0x29B1).

    That is exactly the CRC of ``binascii.crc_hqx`` (the XMODEM/HQX polynomial, MSB first) started at
    0xFFFF: computed in C, ~30x faster than a table walk in Python for a SET_CURRENTS frame.
    """
    return binascii.crc_hqx(data, crc)


_CODE_BYTES = tuple(bytes((code,)) for code in range(256))


def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing (Cheshire & Baker): the result contains no 0x00.

    Standard form: a block of 254 non-zero bytes has code 0xFF and no implied zero; no empty block
    follows one at the very end (``01..FE`` encodes as ``FF 01..FE``).

    Built from ``bytes.split`` on the zeros (each zero-free run is one or more blocks), not byte by
    byte: a 45-byte SET_CURRENTS packet encodes in 1-6 us (as many zeros, as many runs) instead of ~9.
    """
    runs = data.split(b"\x00")
    if len(data) < 254:   # no run fills a block: one code byte (run length + 1) before each run
        return b"".join([_CODE_BYTES[len(run) + 1] + run for run in runs])
    out = bytearray()
    last = len(runs) - 1
    for index, run in enumerate(runs):
        start = 0
        while len(run) - start >= 254:   # full blocks: code 0xFF, no implied zero
            out.append(0xFF)
            out += run[start:start + 254]
            start += 254
        if index == last and start == len(run) and start > 0:
            break   # data ends with a full block: no empty block after it
        out.append(len(run) - start + 1)
        out += run[start:]
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Inverse of :func:`cobs_encode`; raises :class:`FrameError` on a malformed block."""
    out = bytearray()
    i = 0
    n = len(data)
    while i < n:
        code = data[i]
        if code == 0:
            raise FrameError("COBS: zero byte inside a frame")
        end = i + code
        if end > n:
            raise FrameError("COBS: block runs past the end of the frame")
        block = data[i + 1:end]
        if 0 in block:
            raise FrameError("COBS: zero byte inside a frame")
        out += block
        i = end
        # A code of 0xFF means a full block without an implied zero; the last block never adds one.
        if code != 0xFF and i < n:
            out.append(0)
    return bytes(out)


@dataclass(frozen=True)
class Frame:
    """One packet of the link, before the payload is interpreted."""

    msg_type: int
    seq: int
    payload: bytes = b""
    version: int = PROTOCOL_VERSION


def encode_packet(frame: Frame) -> bytes:
    """Header, payload and CRC, unstuffed (what COBS is applied to)."""
    if not 0 <= frame.seq <= 0xFFFF:
        raise ValueError(f"sequence number {frame.seq} outside 0..65535")
    if not 0 <= frame.msg_type <= 0xFF or not 0 <= frame.version <= 0xFF:
        raise ValueError("message type and version are single bytes")
    if len(frame.payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(frame.payload)} bytes exceeds {MAX_PAYLOAD}")
    body = _HEADER.pack(frame.version, frame.msg_type, frame.seq, len(frame.payload)) + frame.payload
    return body + _CRC.pack(crc16_ccitt_false(body))


def encode_frame(frame: Frame) -> bytes:
    """The bytes on the wire: ``00 | COBS(packet) | 00``."""
    return DELIMITER + cobs_encode(encode_packet(frame)) + DELIMITER


def frame_short_body(body: bytes) -> bytes:
    """``00 | COBS(body + CRC) | 00`` for a header-and-payload ``body`` of at most 251 bytes (so the packet
    has no 254-byte block): :func:`encode_frame`'s bytes in one function, for the per-frame current command
    (issue 8: each call saved on it is ~1-2 us after a frame's recognition has cycled the caches)."""
    runs = (body + _CRC.pack(binascii.crc_hqx(body, 0xFFFF))).split(b"\x00")
    return b"\x00" + b"".join([_CODE_BYTES[len(run) + 1] + run for run in runs]) + b"\x00"


def decode_packet(packet: bytes) -> Frame:
    """Check length, CRC and version of an unstuffed packet; raises a :class:`FrameError` subclass."""
    if len(packet) < HEADER_SIZE + CRC_SIZE:
        raise TruncatedFrameError(f"packet of {len(packet)} bytes is shorter than header and CRC")
    version, msg_type, seq, length = _HEADER.unpack_from(packet)
    if len(packet) < HEADER_SIZE + length + CRC_SIZE:
        raise TruncatedFrameError(f"packet of {len(packet)} bytes is shorter than its declared payload {length}")
    if len(packet) > HEADER_SIZE + length + CRC_SIZE:
        raise LengthError(f"packet of {len(packet)} bytes is longer than its declared payload {length}")
    (crc,) = _CRC.unpack_from(packet, HEADER_SIZE + length)
    expected = crc16_ccitt_false(packet[:HEADER_SIZE + length])
    if crc != expected:
        raise CrcError(f"CRC 0x{crc:04X} does not match contents (0x{expected:04X})")
    if version != PROTOCOL_VERSION:
        raise VersionError(f"protocol version {version}, this codec speaks {PROTOCOL_VERSION}")
    return Frame(msg_type=msg_type, seq=seq, payload=bytes(packet[HEADER_SIZE:HEADER_SIZE + length]),
                 version=version)


class LengthError(FrameError):
    """A packet longer than its declared payload (bytes were inserted or a delimiter was lost)."""


class VersionError(FrameError):
    """A well-formed packet of a protocol version this codec does not speak."""


class CobsError(FrameError):
    """Bytes between two delimiters that are not a valid COBS block sequence."""


def reject_reason(err: FrameError) -> str:
    """The counter name under which a decoder files ``err``."""
    if isinstance(err, CrcError):
        return "crc"
    if isinstance(err, TruncatedFrameError):
        return "truncated"
    if isinstance(err, LengthError):
        return "length"
    if isinstance(err, VersionError):
        return "version"
    return "cobs"


class FrameDecoder:
    """Streaming decoder: ``feed(bytes) -> list[Frame]``; rejected frames are counted in ``rejected``.

    Bytes are collected until a delimiter. A run longer than :data:`MAX_ENCODED` without one is
    dropped as ``oversize`` (once) and the decoder discards input until the next delimiter.
    """

    def __init__(self) -> None:
        self._buffer = bytearray()
        self._overflowed = False
        self.accepted = 0
        self.rejected: Counter[str] = Counter({reason: 0 for reason in REJECT_REASONS})

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())

    def reset(self) -> None:
        """Forget a partial frame (after reopening a port); counters are kept."""
        self._buffer.clear()
        self._overflowed = False

    def feed(self, data: bytes) -> list[Frame]:
        frames: list[Frame] = []
        start = 0
        while True:
            end = data.find(0, start)
            if end < 0:
                self._append(data[start:])
                return frames
            self._append(data[start:end])
            frame = self._finish()
            if frame is not None:
                frames.append(frame)
            start = end + 1

    def _append(self, chunk: bytes) -> None:
        if self._overflowed or not chunk:
            return
        self._buffer += chunk
        if len(self._buffer) > MAX_ENCODED:
            self.rejected["oversize"] += 1
            self._buffer.clear()
            self._overflowed = True

    def _finish(self) -> Frame | None:
        if self._overflowed:
            self._overflowed = False
            return None
        if not self._buffer:
            return None
        encoded = bytes(self._buffer)
        self._buffer.clear()
        try:
            frame = decode_packet(cobs_decode(encoded))
        except FrameError as err:
            if type(err) is FrameError:
                err = CobsError(str(err))
            self.rejected[reject_reason(err)] += 1
            return None
        self.accepted += 1
        return frame
