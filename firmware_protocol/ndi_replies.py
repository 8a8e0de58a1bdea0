"""NDI tracking-data replies: ``TX`` (text) and ``BX`` (binary), encode and decode, reply option 0x0001.

Both carry, per port handle, either a transform (unit quaternion Q0 Qx Qy Qz, translation in mm, RMS
fit error in mm), or ``MISSING`` (tool enabled but not seen), or ``DISABLED``; then the port status and
the 60 Hz frame number; and after all handles the system status.

TX text record: ``hh`` + 4 x (sign + 5 digits, quaternion x 1e4) + 3 x (sign + 6 digits, mm x 100) +
sign + 5 digits (RMS x 1e4) + 8 hex port status + 8 hex frame, then LF. The reply starts with a
2-hex handle count and ends with 4 hex system status, CRC and CR.

BX: ``C4 A5``, uint16 body length, uint16 CRC of those four bytes; the body (little-endian) holds a
uint8 handle count, per handle uint8 handle + uint8 status (1 valid, 2 missing, 4 disabled), valid:
8 float32 + uint32 port status + uint32 frame, missing: port status + frame, disabled: nothing; then
a uint16 system status; then a uint16 CRC of the body.

Not modelled: reply options other than 0x0001 (additional info, single stray, passive stray markers,
3D marker positions); 0x0800 ("report out-of-volume transforms too") changes nothing in the layout.
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import IntEnum

from firmware_protocol.errors import CrcError, FrameError, TruncatedFrameError
from firmware_protocol.ndi import CR, MAX_REPLY_BYTES, crc16, crc_hex, decode_reply

#: Reply option bit for transforms and status: the only one encoded here.
OPTION_TRANSFORMS = 0x0001
#: Reply option bit asking for transforms outside the characterised volume too (no layout change).
OPTION_OUT_OF_VOLUME = 0x0800
SUPPORTED_OPTIONS = OPTION_TRANSFORMS | OPTION_OUT_OF_VOLUME

BX_START = b"\xc4\xa5"
BX_HEADER_BYTES = 6

#: Port status bits (8 hex digits in TX, uint32 in BX).
PORT_OCCUPIED = 0x01
PORT_INITIALISED = 0x10
PORT_ENABLED = 0x20
PORT_OUT_OF_VOLUME = 0x40
PORT_PARTIALLY_OUT_OF_VOLUME = 0x80
#: What a visible, enabled tool reports: occupied, initialised, enabled.
PORT_STATUS_TRACKING = PORT_OCCUPIED | PORT_INITIALISED | PORT_ENABLED


class ToolState(IntEnum):
    """A handle's state in a tracking reply; the values are BX's status bytes."""

    VALID = 0x01
    MISSING = 0x02
    DISABLED = 0x04


@dataclass(frozen=True)
class ToolRecord:
    """One handle's entry in a TX/BX reply. ``quaternion``/``translation_mm``/``rms_mm`` only when VALID."""

    handle: int
    state: ToolState
    quaternion: tuple[float, float, float, float] | None = None   # w, x, y, z
    translation_mm: tuple[float, float, float] | None = None
    rms_mm: float | None = None
    port_status: int = PORT_STATUS_TRACKING
    frame: int = 0

    def __post_init__(self) -> None:
        has_pose = self.quaternion is not None and self.translation_mm is not None and self.rms_mm is not None
        if (self.state == ToolState.VALID) != has_pose:
            raise FrameError(f"handle {self.handle:02X}: a {self.state.name} record "
                             f"{'needs' if self.state == ToolState.VALID else 'has no'} pose, RMS and quaternion")


@dataclass(frozen=True)
class TrackingReply:
    """A whole TX or BX reply."""

    tools: tuple[ToolRecord, ...]
    system_status: int = 0

    def by_handle(self) -> dict[int, ToolRecord]:
        return {tool.handle: tool for tool in self.tools}


def parse_reply_option(params: str) -> int:
    """``TX:0801`` -> 0x0801; no parameter means 0x0001."""
    if not params:
        return OPTION_TRANSFORMS
    if len(params) != 4:
        raise FrameError(f"a reply option is 4 hex digits, got {params!r}")
    try:
        return int(params, 16)
    except ValueError as err:
        raise FrameError(f"reply option {params!r} is not hex") from err


# ------------------------------------------------------------------------------------------------- TX

def _signed(value: float, scale: float, digits: int) -> str:
    scaled = round(value * scale)
    limit = 10 ** digits - 1
    if abs(scaled) > limit:
        raise FrameError(f"{value} does not fit {digits} digits at scale {scale:g}")
    return f"{'-' if scaled < 0 else '+'}{abs(scaled):0{digits}d}"


def _tx_record(tool: ToolRecord) -> str:
    head = f"{tool.handle:02X}"
    tail = f"{tool.port_status:08X}{tool.frame & 0xFFFFFFFF:08X}"
    if tool.state == ToolState.MISSING:
        return head + "MISSING" + tail
    if tool.state == ToolState.DISABLED:
        return head + "DISABLED" + tail
    assert tool.quaternion is not None and tool.translation_mm is not None and tool.rms_mm is not None
    return (head + "".join(_signed(q, 1e4, 5) for q in tool.quaternion)
            + "".join(_signed(t, 1e2, 6) for t in tool.translation_mm)
            + _signed(tool.rms_mm, 1e4, 5) + tail)


def encode_tx(reply: TrackingReply) -> bytes:
    """The whole TX reply (text, CRC, CR) for reply option 0x0001."""
    text = (f"{len(reply.tools):02X}" + "".join(_tx_record(tool) + "\n" for tool in reply.tools)
            + f"{reply.system_status & 0xFFFF:04X}")
    raw = text.encode("ascii") + crc_hex(text.encode("ascii")) + CR
    if len(raw) > MAX_REPLY_BYTES:
        raise FrameError(f"TX reply of {len(raw)} bytes exceeds the {MAX_REPLY_BYTES}-byte limit")
    return raw


def _number(text: str, start: int, digits: int, scale: float, what: str) -> float:
    field = text[start:start + digits + 1]
    if len(field) != digits + 1 or field[0] not in "+-" or not field[1:].isdigit():
        raise FrameError(f"TX {what} {field!r} at offset {start} is not a sign and {digits} digits")
    return int(field) / scale


def _hex(text: str, start: int, digits: int, what: str) -> int:
    field = text[start:start + digits]
    try:
        if len(field) != digits:
            raise ValueError
        return int(field, 16)
    except ValueError as err:
        raise FrameError(f"TX {what} {field!r} at offset {start} is not {digits} hex digits") from err


def _parse_tx_record(line: str) -> ToolRecord:
    handle = _hex(line, 0, 2, "handle")
    for word, state in (("MISSING", ToolState.MISSING), ("DISABLED", ToolState.DISABLED)):
        if line.startswith(word, 2):
            at = 2 + len(word)
            return ToolRecord(handle, state, port_status=_hex(line, at, 8, "port status"),
                              frame=_hex(line, at + 8, 8, "frame number"))
    if line.startswith("UNOCCUPIED", 2):
        raise FrameError(f"handle {handle:02X} is UNOCCUPIED (the tool was removed from its port)")
    q = tuple(_number(line, 2 + 6 * i, 5, 1e4, "quaternion") for i in range(4))
    t = tuple(_number(line, 26 + 7 * i, 6, 1e2, "translation") for i in range(3))
    rms = _number(line, 47, 5, 1e4, "RMS error")
    return ToolRecord(handle, ToolState.VALID, q, t, rms,  # type: ignore[arg-type]
                      port_status=_hex(line, 53, 8, "port status"), frame=_hex(line, 61, 8, "frame number"))


def decode_tx_text(text: str) -> TrackingReply:
    """The text of a TX reply (CRC already checked and removed) -> records and system status."""
    lines = text.split("\n")
    count = _hex(lines[0], 0, 2, "handle count")
    # The first record follows the count on the same line; each record ends with LF; the status follows.
    records = [lines[0][2:]] + lines[1:]
    if len(records) != count + 1:
        raise TruncatedFrameError(f"TX reply announces {count} handles but has {len(records) - 1} records")
    tools = tuple(_parse_tx_record(line) for line in records[:count])
    status = _hex(records[count], 0, 4, "system status")
    return TrackingReply(tools, status)


def decode_tx(raw: bytes) -> TrackingReply:
    """A whole TX reply as received (CRC and CR included)."""
    return decode_tx_text(decode_reply(raw))


# ------------------------------------------------------------------------------------------------- BX

_FLOATS = struct.Struct("<8f")
_U32X2 = struct.Struct("<II")


def encode_bx(reply: TrackingReply) -> bytes:
    """The whole BX reply for reply option 0x0001 (send it in one write)."""
    body = bytearray([len(reply.tools)])
    for tool in reply.tools:
        body += bytes([tool.handle, int(tool.state)])
        if tool.state == ToolState.VALID:
            assert tool.quaternion is not None and tool.translation_mm is not None and tool.rms_mm is not None
            body += _FLOATS.pack(*tool.quaternion, *tool.translation_mm, tool.rms_mm)
        if tool.state != ToolState.DISABLED:
            body += _U32X2.pack(tool.port_status, tool.frame & 0xFFFFFFFF)
    body += struct.pack("<H", reply.system_status & 0xFFFF)
    header = BX_START + struct.pack("<H", len(body))
    raw = header + struct.pack("<H", crc16(header)) + bytes(body) + struct.pack("<H", crc16(bytes(body)))
    if len(raw) > MAX_REPLY_BYTES:
        raise FrameError(f"BX reply of {len(raw)} bytes exceeds the {MAX_REPLY_BYTES}-byte limit")
    return raw


_BX_HEADER = struct.Struct("<HH")
_U16 = struct.Struct("<H")
#: One BX record, unpacked in one call: handle, status, Q0 Qx Qy Qz, Tx Ty Tz (mm), RMS (mm), port status, frame.
BX_VALID_RECORD = struct.Struct("<BB8fII")
#: A MISSING record: handle, status, port status, frame.
BX_MISSING_RECORD = struct.Struct("<BBII")
_VALID, _MISSING, _DISABLED = int(ToolState.VALID), int(ToolState.MISSING), int(ToolState.DISABLED)


def bx_total_length(header: bytes) -> int:
    """From the first six bytes of a BX reply, the length of the whole reply (header CRC checked)."""
    if len(header) < BX_HEADER_BYTES:
        raise TruncatedFrameError(f"BX header is {BX_HEADER_BYTES} bytes, got {len(header)}")
    if header[:2] != BX_START:
        raise FrameError(f"BX reply starts {header[:2].hex()} instead of c4a5")
    length, given = _BX_HEADER.unpack_from(header, 2)
    if crc16(header[:4]) != given:
        raise CrcError(f"BX header CRC {given:04X} given, {crc16(header[:4]):04X} computed")
    return BX_HEADER_BYTES + length + 2


def decode_bx_records(raw: bytes) -> tuple[list[tuple], int]:
    """A whole BX reply -> (records as flat tuples, system status); the checks of :func:`decode_bx`.

    Each record is what one ``struct`` call unpacks: a VALID handle ``(handle, 1, q0, qx, qy, qz, tx, ty,
    tz, rms, port_status, frame)`` (:data:`BX_VALID_RECORD`), a MISSING one ``(handle, 2, port_status,
    frame)``, a DISABLED one ``(handle, 4)``; ``record[1]`` is the :class:`ToolState` value. This is the
    form a 60 Hz reader wants (no object per field); :func:`decode_bx` builds :class:`ToolRecord` from it.
    """
    total = bx_total_length(raw[:BX_HEADER_BYTES])
    if len(raw) < total:
        raise TruncatedFrameError(f"BX reply declares {total} bytes, got {len(raw)}")
    if len(raw) > total:
        raise FrameError(f"BX reply declares {total} bytes, got {len(raw)} (trailing bytes)")
    body = raw[BX_HEADER_BYTES:total - 2]
    (given,) = _U16.unpack_from(raw, total - 2)
    if crc16(body) != given:
        raise CrcError(f"BX body CRC {given:04X} given, {crc16(body):04X} computed")
    records: list[tuple] = []
    try:
        at = 1
        for _ in range(body[0]):
            status = body[at + 1]
            if status == _VALID:
                record = BX_VALID_RECORD.unpack_from(body, at)
                at += BX_VALID_RECORD.size
                if not math.isfinite(sum(record[2:10])):     # a NaN or an infinity anywhere stays one
                    raise FrameError(f"BX handle {record[0]:02X} carries a non-finite number")
            elif status == _MISSING:
                record = BX_MISSING_RECORD.unpack_from(body, at)
                at += BX_MISSING_RECORD.size
            elif status == _DISABLED:
                record = (body[at], status)
                at += 2
            else:
                raise FrameError(f"BX handle {body[at]:02X} has unknown status 0x{status:02X}")
            records.append(record)
        (system_status,) = _U16.unpack_from(body, at)
        at += 2
    except (IndexError, struct.error) as err:
        raise TruncatedFrameError(f"BX body of {len(body)} bytes ends inside a record") from err
    if at != len(body):
        raise FrameError(f"BX body has {len(body) - at} bytes after the system status")
    return records, system_status


def decode_bx(raw: bytes) -> TrackingReply:
    """A whole BX reply -> records and system status; checks both CRCs and every length."""
    records, system_status = decode_bx_records(raw)
    tools = []
    for record in records:
        handle, status = record[0], record[1]
        if status == _VALID:
            tools.append(ToolRecord(handle, ToolState.VALID, record[2:6],  # type: ignore[arg-type]
                                    record[6:9], record[9], port_status=record[10], frame=record[11]))
        elif status == _MISSING:
            tools.append(ToolRecord(handle, ToolState.MISSING, port_status=record[2], frame=record[3]))
        else:
            tools.append(ToolRecord(handle, ToolState.DISABLED, port_status=0, frame=0))
    return TrackingReply(tuple(tools), system_status)


def reply_is_binary(first_byte: bytes) -> bool:
    """Whether a reply starting with this byte is BX binary; text replies (``ERRORxx``) are ASCII."""
    return first_byte[:1] == BX_START[:1]

