"""Messages of the EMA coil-current amplifier link: types, states, fault flags, encode and decode.

Every message is a frozen dataclass in wire units (currents in integer milliamps, temperatures in
integer tenths of a degree Celsius, times in milliseconds), so a decode of an encode is exact. The
framing (COBS, header, CRC-16/CCITT-FALSE) lives in :mod:`firmware_protocol.amplifier_framing`;
``firmware_protocol/AMPLIFIER.md`` is the spec a firmware engineer implements from, and
``amplifier_vectors.json`` holds encoded bytes beside decoded messages for both sides' tests.

All multi-byte fields are little-endian. A reply carries the sequence number of the request it answers.
"""
from __future__ import annotations

import enum
import struct
from collections import Counter
from dataclasses import dataclass, field
from typing import ClassVar, Union

from firmware_protocol.amplifier_framing import (
    HEADER_SIZE,
    PROTOCOL_VERSION,
    REJECT_REASONS,
    Frame,
    FrameDecoder,
    encode_frame,
    frame_short_body,
)
from firmware_protocol.errors import FrameError

MAX_CHANNELS = 16


class MsgType(enum.IntEnum):
    """Message type byte. Requests (host to amplifier) are below 0x80; replies have the top bit set."""

    HELLO = 0x01
    ENABLE = 0x02
    DISABLE = 0x03
    SET_CURRENTS = 0x04
    HEARTBEAT = 0x05
    GET_STATUS = 0x06
    CLEAR_FAULT = 0x07
    CONFIGURE_LIMITS = 0x08
    HELLO_REPLY = 0x81
    SET_CURRENTS_REPLY = 0x84
    STATUS = 0x86
    ACK = 0xA0
    NAK = 0xA1


class State(enum.IntEnum):
    """Amplifier output state (see the state machine in AMPLIFIER.md)."""

    DISABLED = 0   # output stage off; power-on state
    ENABLED = 1    # output follows the setpoints
    FAULT = 2      # a fault is latched; output ramping down or off; only CLEAR_FAULT leaves it


class Fault(enum.IntFlag):
    """Fault flags (uint32). Bits 0-7 are latched until CLEAR_FAULT; bits 8-15 report live inputs."""

    NONE = 0
    WATCHDOG = 1 << 0          # no valid request within watchdog_ms while enabled
    ESTOP = 1 << 1             # the emergency-stop input was asserted
    OVER_TEMPERATURE = 1 << 2  # a coil temperature passed over_temperature_dc
    OVER_CURRENT = 1 << 3      # a measured current passed 1.1 x its limit + 100 mA
    INTERNAL = 1 << 7          # firmware self-check failed
    ESTOP_INPUT = 1 << 8       # live: the e-stop input is asserted now
    TEMPERATURE_HIGH = 1 << 9  # live: a coil is still above the restart threshold

    @property
    def latched(self) -> "Fault":
        return Fault(int(self) & 0xFF)


class NakReason(enum.IntEnum):
    """Why a request was refused. A NAKed request changes nothing in the amplifier."""

    BAD_STATE = 1          # not allowed in the current state (e.g. SET_CURRENTS while disabled)
    BAD_PAYLOAD = 2        # payload length or channel count does not fit the message
    OUT_OF_RANGE = 3       # a limit above the amplifier's rating, or a zero watchdog
    FAULT_ACTIVE = 4       # a fault is latched: clear it first
    ESTOP_ACTIVE = 5       # the e-stop input is asserted: software cannot clear it
    CONDITION_PRESENT = 6  # the fault's cause persists (coil still hot)
    UNKNOWN_TYPE = 7       # message type not implemented
    STALE_SEQUENCE = 8     # sequence number older than the last accepted request


# ---- messages --------------------------------------------------------------------------------


@dataclass(frozen=True)
class Hello:
    """Start a session: the amplifier forgets the last sequence number and answers HELLO_REPLY."""

    TYPE: ClassVar[MsgType] = MsgType.HELLO


@dataclass(frozen=True)
class Enable:
    TYPE: ClassVar[MsgType] = MsgType.ENABLE


@dataclass(frozen=True)
class Disable:
    TYPE: ClassVar[MsgType] = MsgType.DISABLE


@dataclass(frozen=True)
class Heartbeat:
    TYPE: ClassVar[MsgType] = MsgType.HEARTBEAT


@dataclass(frozen=True)
class GetStatus:
    TYPE: ClassVar[MsgType] = MsgType.GET_STATUS


@dataclass(frozen=True)
class ClearFault:
    TYPE: ClassVar[MsgType] = MsgType.CLEAR_FAULT


@dataclass(frozen=True)
class SetCurrents:
    """Target current of every channel, int32 mA; the amplifier ramps to it within its limits."""

    TYPE: ClassVar[MsgType] = MsgType.SET_CURRENTS
    currents_ma: tuple[int, ...]


@dataclass(frozen=True)
class ConfigureLimits:
    """Per-channel current limit (mA) and slew limit (mA/s), and the link watchdog period (ms)."""

    TYPE: ClassVar[MsgType] = MsgType.CONFIGURE_LIMITS
    watchdog_ms: int
    max_current_ma: tuple[int, ...]
    slew_ma_per_s: tuple[int, ...]


@dataclass(frozen=True)
class HelloReply:
    """Identity, ratings and the limits in force."""

    TYPE: ClassVar[MsgType] = MsgType.HELLO_REPLY
    firmware_version: tuple[int, int, int]
    serial_number: int
    watchdog_ms: int
    over_temperature_dc: int
    rated_current_ma: tuple[int, ...]
    max_current_ma: tuple[int, ...]
    slew_ma_per_s: tuple[int, ...]

    @property
    def channels(self) -> int:
        return len(self.rated_current_ma)


@dataclass(frozen=True)
class SetCurrentsReply:
    """Acknowledges SET_CURRENTS (by sequence number) with the measured currents after applying it."""

    TYPE: ClassVar[MsgType] = MsgType.SET_CURRENTS_REPLY
    state: State
    faults: Fault
    clamped_mask: int              # bit c set: the amplifier scaled the vector because of channel c's limit
    measured_ma: tuple[int, ...]


@dataclass(frozen=True)
class Status:
    TYPE: ClassVar[MsgType] = MsgType.STATUS
    state: State
    faults: Fault
    uptime_ms: int
    last_seq: int                  # sequence number of the last accepted request
    setpoint_ma: tuple[int, ...]   # the slew-limited reference the current loop follows now
    measured_ma: tuple[int, ...]
    temperature_dc: tuple[int, ...]


@dataclass(frozen=True)
class Ack:
    TYPE: ClassVar[MsgType] = MsgType.ACK
    request_type: int
    state: State
    faults: Fault


@dataclass(frozen=True)
class Nak:
    TYPE: ClassVar[MsgType] = MsgType.NAK
    request_type: int
    reason: NakReason
    state: State
    faults: Fault


Message = Union[Hello, Enable, Disable, Heartbeat, GetStatus, ClearFault, SetCurrents, ConfigureLimits,
                HelloReply, SetCurrentsReply, Status, Ack, Nak]
REQUESTS = (Hello, Enable, Disable, Heartbeat, GetStatus, ClearFault, SetCurrents, ConfigureLimits)
REPLIES = (HelloReply, SetCurrentsReply, Status, Ack, Nak)
MESSAGE_CLASSES: dict[MsgType, type] = {cls.TYPE: cls for cls in REQUESTS + REPLIES}
_EMPTY = {cls.TYPE: cls for cls in (Hello, Enable, Disable, Heartbeat, GetStatus, ClearFault)}


class PayloadError(FrameError):
    """A frame with a valid CRC whose payload does not fit its message type."""


class UnknownTypeError(FrameError):
    """A frame with a valid CRC and a message type this codec does not know."""


# ---- payload layouts -------------------------------------------------------------------------

_U8 = struct.Struct("<B")
# Per-channel int32 vectors (SET_CURRENTS, SET_CURRENTS_REPLY) by channel count, compiled once.
_I32_VECTORS = {n: struct.Struct(f"<{n}i") for n in range(1, MAX_CHANNELS + 1)}
_I32 = struct.Struct("<i")
_MSG_TYPES = {int(kind): kind for kind in MsgType}
_SET_CURRENTS_TYPE = int(MsgType.SET_CURRENTS)
_STATE_FAULTS = struct.Struct("<BI")
_HELLO_HEAD = struct.Struct("<BBBBIHh")       # channels, fw major/minor/patch, serial, watchdog_ms, over_temp_dc
_HELLO_CHANNEL = struct.Struct("<III")        # rated_ma, max_ma, slew_ma_per_s
_LIMITS_HEAD = struct.Struct("<HB")           # watchdog_ms, channels
_LIMITS_CHANNEL = struct.Struct("<II")
_SET_REPLY_HEAD = struct.Struct("<BIHB")      # state, faults, clamped_mask, channels
_STATUS_HEAD = struct.Struct("<BIIHB")        # state, faults, uptime_ms, last_seq, channels
_STATUS_CHANNEL = struct.Struct("<iih")       # setpoint_ma, measured_ma, temperature_dc
_ACK = struct.Struct("<BBI")                  # request_type, state, faults
_NAK = struct.Struct("<BBBI")                 # request_type, reason, state, faults


def _check_channels(n: int) -> None:
    if not 1 <= n <= MAX_CHANNELS:
        raise ValueError(f"{n} channels; the protocol carries 1..{MAX_CHANNELS}")


def _same_length(*vectors: tuple[int, ...]) -> int:
    lengths = {len(v) for v in vectors}
    if len(lengths) != 1:
        raise ValueError(f"per-channel vectors of different lengths {sorted(lengths)}")
    n = lengths.pop()
    _check_channels(n)
    return n


def encode_payload(msg: Message) -> bytes:
    """The payload bytes of ``msg`` (raises ValueError / struct.error for values that do not fit)."""
    if isinstance(msg, (Hello, Enable, Disable, Heartbeat, GetStatus, ClearFault)):
        return b""
    if isinstance(msg, SetCurrents):
        n = _same_length(msg.currents_ma)
        return _U8.pack(n) + _I32_VECTORS[n].pack(*msg.currents_ma)
    if isinstance(msg, ConfigureLimits):
        n = _same_length(msg.max_current_ma, msg.slew_ma_per_s)
        body = b"".join(_LIMITS_CHANNEL.pack(m, s) for m, s in zip(msg.max_current_ma, msg.slew_ma_per_s))
        return _LIMITS_HEAD.pack(msg.watchdog_ms, n) + body
    if isinstance(msg, HelloReply):
        n = _same_length(msg.rated_current_ma, msg.max_current_ma, msg.slew_ma_per_s)
        head = _HELLO_HEAD.pack(n, *msg.firmware_version, msg.serial_number, msg.watchdog_ms,
                                msg.over_temperature_dc)
        return head + b"".join(_HELLO_CHANNEL.pack(*c) for c in
                               zip(msg.rated_current_ma, msg.max_current_ma, msg.slew_ma_per_s))
    if isinstance(msg, SetCurrentsReply):
        n = _same_length(msg.measured_ma)
        return (_SET_REPLY_HEAD.pack(msg.state, msg.faults, msg.clamped_mask, n)
                + _I32_VECTORS[n].pack(*msg.measured_ma))
    if isinstance(msg, Status):
        n = _same_length(msg.setpoint_ma, msg.measured_ma, msg.temperature_dc)
        head = _STATUS_HEAD.pack(msg.state, msg.faults, msg.uptime_ms, msg.last_seq, n)
        return head + b"".join(_STATUS_CHANNEL.pack(*c) for c in
                               zip(msg.setpoint_ma, msg.measured_ma, msg.temperature_dc))
    if isinstance(msg, Ack):
        return _ACK.pack(msg.request_type, msg.state, msg.faults)
    if isinstance(msg, Nak):
        return _NAK.pack(msg.request_type, msg.reason, msg.state, msg.faults)
    raise TypeError(f"not an amplifier message: {msg!r}")


def encode_message(msg: Message, seq: int) -> bytes:
    """The complete frame on the wire for ``msg`` with sequence number ``seq``."""
    return encode_frame(Frame(msg_type=msg.TYPE, seq=seq, payload=encode_payload(msg)))


# SET_CURRENTS packets without the CRC, by channel count: header (version, type, seq, payload length),
# then the payload (channel count, int32 currents), packed by one compiled struct.
_SET_CURRENTS_PACKETS = {n: struct.Struct(f"<BBHBB{n}i") for n in range(1, MAX_CHANNELS + 1)}


def encode_set_currents(currents_ma: tuple[int, ...] | list[int], seq: int) -> bytes:
    """``encode_message(SetCurrents(currents_ma=tuple(currents_ma)), seq)``, byte for byte, without the
    message object, the Frame and the generic payload dispatch: the driver's path from the allocated
    currents to the write (issue 8). Raises ValueError (channel count) or struct.error (a value or
    ``seq`` that does not fit its field)."""
    n = len(currents_ma)
    layout = _SET_CURRENTS_PACKETS.get(n)
    if layout is None:
        raise ValueError(f"{n} channels; the protocol carries 1..{MAX_CHANNELS}")
    # At most 16 channels: a 71-byte body, well within frame_short_body's 251.
    return frame_short_body(layout.pack(PROTOCOL_VERSION, _SET_CURRENTS_TYPE, seq, layout.size - HEADER_SIZE, n,
                                        *currents_ma))


def _unpack_channels(payload: bytes, offset: int, n: int, layout: struct.Struct) -> list[tuple[int, ...]]:
    if n < 1 or n > MAX_CHANNELS:
        raise PayloadError(f"channel count {n} outside 1..{MAX_CHANNELS}")
    if len(payload) != offset + n * layout.size:
        raise PayloadError(f"payload of {len(payload)} bytes does not hold {n} channels")
    columns = list(zip(*(layout.unpack_from(payload, offset + i * layout.size) for i in range(n))))
    return columns


def _state(value: int) -> State:
    try:
        return State(value)
    except ValueError as err:
        raise PayloadError(f"unknown state {value}") from err


def decode_payload(msg_type: int, payload: bytes) -> Message:
    """The message of type ``msg_type``; raises :class:`UnknownTypeError` or :class:`PayloadError`."""
    kind = _MSG_TYPES.get(msg_type)
    if kind is None:
        raise UnknownTypeError(f"unknown message type 0x{msg_type:02X}")
    try:
        return _decode(kind, payload)
    except struct.error as err:
        raise PayloadError(f"{kind.name}: payload of {len(payload)} bytes: {err}") from err


def _fixed(layout: struct.Struct, payload: bytes, kind: MsgType) -> tuple[int, ...]:
    if len(payload) != layout.size:
        raise PayloadError(f"{kind.name}: payload of {len(payload)} bytes, expected {layout.size}")
    return layout.unpack(payload)


def _decode(kind: MsgType, payload: bytes) -> Message:
    if kind in _EMPTY:
        if payload:
            raise PayloadError(f"{kind.name} carries no payload, got {len(payload)} bytes")
        return _EMPTY[kind]()
    if kind is MsgType.SET_CURRENTS:
        if not payload:
            raise PayloadError("SET_CURRENTS without a channel count")
        n = payload[0]
        (currents,) = _unpack_channels(payload, 1, n, _I32)
        return SetCurrents(currents_ma=tuple(currents))
    if kind is MsgType.CONFIGURE_LIMITS:
        watchdog_ms, n = _LIMITS_HEAD.unpack_from(payload)
        max_ma, slew = _unpack_channels(payload, _LIMITS_HEAD.size, n, _LIMITS_CHANNEL)
        return ConfigureLimits(watchdog_ms=watchdog_ms, max_current_ma=tuple(max_ma), slew_ma_per_s=tuple(slew))
    if kind is MsgType.HELLO_REPLY:
        n, major, minor, patch, serial, watchdog_ms, over_dc = _HELLO_HEAD.unpack_from(payload)
        rated, max_ma, slew = _unpack_channels(payload, _HELLO_HEAD.size, n, _HELLO_CHANNEL)
        return HelloReply(firmware_version=(major, minor, patch), serial_number=serial, watchdog_ms=watchdog_ms,
                          over_temperature_dc=over_dc, rated_current_ma=tuple(rated),
                          max_current_ma=tuple(max_ma), slew_ma_per_s=tuple(slew))
    if kind is MsgType.SET_CURRENTS_REPLY:
        state, faults, mask, n = _SET_REPLY_HEAD.unpack_from(payload)
        (measured,) = _unpack_channels(payload, _SET_REPLY_HEAD.size, n, _I32)
        return SetCurrentsReply(state=_state(state), faults=Fault(faults), clamped_mask=mask,
                                measured_ma=tuple(measured))
    if kind is MsgType.STATUS:
        state, faults, uptime, last_seq, n = _STATUS_HEAD.unpack_from(payload)
        setpoint, measured, temps = _unpack_channels(payload, _STATUS_HEAD.size, n, _STATUS_CHANNEL)
        return Status(state=_state(state), faults=Fault(faults), uptime_ms=uptime, last_seq=last_seq,
                      setpoint_ma=tuple(setpoint), measured_ma=tuple(measured), temperature_dc=tuple(temps))
    if kind is MsgType.ACK:
        request_type, state, faults = _fixed(_ACK, payload, kind)
        return Ack(request_type=request_type, state=_state(state), faults=Fault(faults))
    if kind is MsgType.NAK:
        request_type, reason, state, faults = _fixed(_NAK, payload, kind)
        try:
            nak_reason = NakReason(reason)
        except ValueError as err:
            raise PayloadError(f"NAK: unknown reason {reason}") from err
        return Nak(request_type=request_type, reason=nak_reason, state=_state(state), faults=Fault(faults))
    raise UnknownTypeError(f"message type {kind.name} has no decoder")  # pragma: no cover


# ---- streaming -------------------------------------------------------------------------------


@dataclass(frozen=True)
class Envelope:
    """A frame that passed framing and CRC. ``message`` is None when its payload could not be decoded
    (``error`` says why); the sequence number and type are still trustworthy, so a device can NAK it."""

    seq: int
    msg_type: int
    message: Message | None
    error: str | None = None


MESSAGE_REJECT_REASONS = REJECT_REASONS + ("type", "payload")


@dataclass
class MessageDecoder:
    """``feed(bytes) -> list[Envelope]`` for driver and fake alike; every rejected frame is counted.

    ``rejected`` counts framing rejections (see :data:`REJECT_REASONS`) plus ``type`` (unknown message
    type) and ``payload`` (payload does not fit its type); ``accepted`` counts decoded messages.
    """

    frames: FrameDecoder = field(default_factory=FrameDecoder)
    accepted: int = 0
    _payload_rejects: Counter[str] = field(default_factory=lambda: Counter({"type": 0, "payload": 0}))

    @property
    def rejected(self) -> Counter[str]:
        counts: Counter[str] = Counter({reason: 0 for reason in MESSAGE_REJECT_REASONS})
        counts.update(self.frames.rejected)
        counts.update(self._payload_rejects)
        return counts

    @property
    def rejected_total(self) -> int:
        return self.frames.rejected_total + sum(self._payload_rejects.values())

    def reset(self) -> None:
        self.frames.reset()

    def feed(self, data: bytes) -> list[Envelope]:
        out = []
        for frame in self.frames.feed(data):
            try:
                message = decode_payload(frame.msg_type, frame.payload)
            except UnknownTypeError as err:
                self._payload_rejects["type"] += 1
                out.append(Envelope(frame.seq, frame.msg_type, None, str(err)))
                continue
            except PayloadError as err:
                self._payload_rejects["payload"] += 1
                out.append(Envelope(frame.seq, frame.msg_type, None, str(err)))
                continue
            self.accepted += 1
            out.append(Envelope(frame.seq, frame.msg_type, message))
        return out


def seq_newer(seq: int, than: int) -> bool:
    """Serial-number arithmetic on uint16: ``seq`` is newer than ``than`` (RFC 1982 style)."""
    diff = (seq - than) & 0xFFFF
    return 0 < diff < 0x8000


__all__ = [
    "PROTOCOL_VERSION", "MAX_CHANNELS", "MsgType", "State", "Fault", "NakReason", "Hello", "Enable", "Disable",
    "Heartbeat", "GetStatus", "ClearFault", "SetCurrents", "ConfigureLimits", "HelloReply", "SetCurrentsReply",
    "Status", "Ack", "Nak", "Message", "REQUESTS", "REPLIES", "MESSAGE_CLASSES", "PayloadError",
    "UnknownTypeError", "encode_payload", "encode_message", "encode_set_currents", "decode_payload", "Envelope",
    "MessageDecoder", "seq_newer", "MESSAGE_REJECT_REASONS",
]
