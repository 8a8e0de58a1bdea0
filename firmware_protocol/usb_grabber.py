"""Byte formats of the USB X-ray frame grabber: vendor control requests and the bulk-IN frame stream.

The full specification, for firmware authors, is ``firmware_protocol/USB_GRABBER.md``. In short: one
vendor-specific interface (class 0xFF) with one bulk-IN endpoint (0x81) carrying a stream of frames;
each frame is a 40-byte header (magic ``XRF1``, plane, pixel format, frame number, device timestamp,
exposure, width, height, payload length, payload CRC-32, header CRC-32) followed by the pixels.
Transfers may split or join frames anywhere: :class:`FrameAssembler` is fed the bytes of bulk transfers
of any size and yields whole, CRC-checked frames; it resynchronises on the magic after a corrupt
header, a bad payload CRC or a truncated frame, and counts each. No I/O, no threads: the driver and the
fake device both use this module. All integers are little-endian; CRCs are CRC-32/ISO-HDLC (zlib).
"""
from __future__ import annotations

import struct
import sys
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

from firmware_protocol.errors import CrcError, FrameError, TruncatedFrameError

# -- USB identity ---------------------------------------------------------------------------------
#: pid.codes test VID:PID (0x1209:0x0001). A shipped product must use its own allocated pair.
VENDOR_ID = 0x1209
PRODUCT_ID = 0x0001
INTERFACE_NUMBER = 0
INTERFACE_CLASS = 0xFF          # vendor specific
BULK_IN_ENDPOINT = 0x81
PROTOCOL_VERSION = 1

# bmRequestType for vendor requests addressed to the device (USB 2.0 §9.3): IN = 0xC0, OUT = 0x40.
REQUEST_TYPE_IN = 0xC0
REQUEST_TYPE_OUT = 0x40


class Request(IntEnum):
    """bRequest codes of the vendor control requests (see USB_GRABBER.md for data stages)."""

    IDENTIFY = 0x01         # IN, 20 bytes: IdentifyReply
    START = 0x02            # OUT, no data: start streaming frames on the bulk endpoint
    STOP = 0x03             # OUT, no data: stop after the current frame
    SET_FRAME_RATE = 0x04   # OUT, 4 bytes: u32 frame rate in mHz
    SET_EXPOSURE = 0x05     # OUT, 4 bytes: u32 exposure in microseconds
    GET_STATUS = 0x06       # IN, 16 bytes: StatusReply


class PixelFormat(IntEnum):
    MONO8 = 1
    MONO16 = 2              # little-endian u16 per pixel


PIXEL_FORMAT_NAMES = {PixelFormat.MONO8: "mono8", PixelFormat.MONO16: "mono16"}
BYTES_PER_PIXEL = {PixelFormat.MONO8: 1, PixelFormat.MONO16: 2}
PLANE_CODES = {"p": ord("p"), "q": ord("q")}
MAX_SIDE = 16384            # no detector is larger; bounds the payload a header may announce


class DeviceState(IntEnum):
    IDLE = 0
    STREAMING = 1
    FAULT = 2


# -- control request data stages ------------------------------------------------------------------
_IDENTIFY = struct.Struct("<4sBBHHBBIHH")
IDENTIFY_MAGIC = b"XRGI"
IDENTIFY_SIZE = _IDENTIFY.size   # 20


@dataclass(frozen=True)
class IdentifyReply:
    plane: str
    width: int
    height: int
    pixel_formats: tuple[PixelFormat, ...]
    max_rate_hz: float
    firmware_version: int
    protocol_version: int = PROTOCOL_VERSION

    def encode(self) -> bytes:
        mask = 0
        for fmt in self.pixel_formats:
            mask |= 1 << (int(fmt) - 1)
        return _IDENTIFY.pack(IDENTIFY_MAGIC, self.protocol_version, PLANE_CODES[self.plane], self.width,
                              self.height, mask, 0, round(self.max_rate_hz * 1000), self.firmware_version, 0)

    @classmethod
    def decode(cls, data: bytes) -> IdentifyReply:
        if len(data) != IDENTIFY_SIZE:
            raise TruncatedFrameError(f"IDENTIFY reply is {len(data)} bytes, expected {IDENTIFY_SIZE}")
        magic, version, plane, width, height, mask, _, rate_mhz, firmware, _ = _IDENTIFY.unpack(data)
        if magic != IDENTIFY_MAGIC:
            raise FrameError(f"IDENTIFY reply starts with {magic!r}, expected {IDENTIFY_MAGIC!r}")
        planes = {code: name for name, code in PLANE_CODES.items()}
        if plane not in planes:
            raise FrameError(f"IDENTIFY reply names plane code {plane:#04x}, expected 'p' or 'q'")
        formats = tuple(fmt for fmt in PixelFormat if mask & (1 << (int(fmt) - 1)))
        return cls(planes[plane], width, height, formats, rate_mhz / 1000.0, firmware, version)


_STATUS = struct.Struct("<BBHIII")
STATUS_SIZE = _STATUS.size       # 16


@dataclass(frozen=True)
class StatusReply:
    state: DeviceState
    fault_code: int
    frames_sent: int
    frames_overrun: int            # frames the device discarded because the host did not read in time
    rate_hz: float

    def encode(self) -> bytes:
        return _STATUS.pack(int(self.state), self.fault_code, 0, self.frames_sent & 0xFFFFFFFF,
                            self.frames_overrun & 0xFFFFFFFF, round(self.rate_hz * 1000))

    @classmethod
    def decode(cls, data: bytes) -> StatusReply:
        if len(data) != STATUS_SIZE:
            raise TruncatedFrameError(f"GET_STATUS reply is {len(data)} bytes, expected {STATUS_SIZE}")
        state, fault, _, sent, overrun, rate_mhz = _STATUS.unpack(data)
        try:
            state = DeviceState(state)
        except ValueError as err:
            raise FrameError(f"GET_STATUS reply has unknown state {state}") from err
        return cls(state, fault, sent, overrun, rate_mhz / 1000.0)


def encode_rate(rate_hz: float) -> bytes:
    if not 0 < rate_hz < 4_000_000:
        raise ValueError(f"frame rate must be in (0, 4e6) Hz, got {rate_hz}")
    return struct.pack("<I", round(rate_hz * 1000))


def encode_exposure(exposure_s: float) -> bytes:
    if not 0 <= exposure_s < 4000:
        raise ValueError(f"exposure must be in [0, 4000) s, got {exposure_s}")
    return struct.pack("<I", round(exposure_s * 1e6))


def decode_u32(data: bytes, what: str) -> int:
    if len(data) != 4:
        raise TruncatedFrameError(f"{what}: data stage is {len(data)} bytes, expected 4")
    return int(struct.unpack("<I", data)[0])


# -- bulk frame header ----------------------------------------------------------------------------
FRAME_MAGIC = b"XRF1"
_HEADER_BODY = struct.Struct("<4sBBBBIQIHHII")   # everything the header CRC covers
HEADER_SIZE = _HEADER_BODY.size + 4               # 40
HEADER_VERSION = 1


@dataclass(frozen=True)
class FrameHeader:
    plane: str
    pixel_format: PixelFormat
    number: int                 # u32, wraps
    device_time_us: int         # u64, start of exposure on the device clock
    exposure_us: int            # u32
    width: int
    height: int
    payload_length: int
    payload_crc: int
    flags: int = 0

    def encode(self) -> bytes:
        body = _HEADER_BODY.pack(FRAME_MAGIC, HEADER_VERSION, PLANE_CODES[self.plane], int(self.pixel_format),
                                 self.flags, self.number & 0xFFFFFFFF, self.device_time_us, self.exposure_us,
                                 self.width, self.height, self.payload_length, self.payload_crc)
        return body + struct.pack("<I", zlib.crc32(body))

    @classmethod
    def decode(cls, data: bytes | bytearray | memoryview) -> FrameHeader:
        """Validate and decode the first HEADER_SIZE bytes; FrameError says what is wrong."""
        if len(data) < HEADER_SIZE:
            raise TruncatedFrameError(f"frame header is {len(data)} bytes, expected {HEADER_SIZE}")
        body = bytes(data[:HEADER_SIZE - 4])
        (crc,) = struct.unpack_from("<I", data, HEADER_SIZE - 4)
        if zlib.crc32(body) != crc:
            raise CrcError(f"frame header CRC {crc:#010x} does not match {zlib.crc32(body):#010x}")
        (magic, version, plane, fmt, flags, number, t_us, exposure_us, width, height, length,
         payload_crc) = _HEADER_BODY.unpack(body)
        if magic != FRAME_MAGIC:
            raise FrameError(f"frame header starts with {magic!r}, expected {FRAME_MAGIC!r}")
        if version != HEADER_VERSION:
            raise FrameError(f"frame header version {version}, this host speaks {HEADER_VERSION}")
        planes = {code: name for name, code in PLANE_CODES.items()}
        if plane not in planes:
            raise FrameError(f"frame header plane code {plane:#04x} is not 'p' or 'q'")
        try:
            pixel_format = PixelFormat(fmt)
        except ValueError as err:
            raise FrameError(f"frame header pixel format {fmt} is unknown") from err
        if not (0 < width <= MAX_SIDE and 0 < height <= MAX_SIDE):
            raise FrameError(f"frame header size {width}x{height} is out of range")
        if length != width * height * BYTES_PER_PIXEL[pixel_format]:
            raise FrameError(f"frame header payload length {length} does not match {width}x{height} "
                             f"{PIXEL_FORMAT_NAMES[pixel_format]}")
        return cls(planes[plane], pixel_format, number, t_us, exposure_us, width, height, length, payload_crc, flags)


def encode_frame(plane: str, pixel_format: PixelFormat, number: int, device_time_us: int, exposure_us: int,
                 width: int, height: int, payload: bytes) -> bytes:
    """Header + payload of one frame, as the device puts it on the bulk endpoint."""
    header = FrameHeader(plane, pixel_format, number, device_time_us, exposure_us, width, height,
                         len(payload), zlib.crc32(payload))
    return header.encode() + payload


# -- reassembly -----------------------------------------------------------------------------------
@dataclass
class AssemblerStats:
    frames: int = 0
    corrupt_headers: int = 0     # a magic followed by a header that fails its CRC or its checks
    bad_crc: int = 0             # a whole payload whose CRC does not match
    truncated: int = 0           # a frame cut short: the next header began inside its payload
    skipped_bytes: int = 0       # bytes thrown away while looking for the next header

    @property
    def corrupt(self) -> int:
        return self.corrupt_headers + self.bad_crc + self.truncated


@dataclass(frozen=True)
class AssembledFrame:
    header: FrameHeader
    payload: bytes | bytearray | memoryview   # exactly payload_length bytes, CRC checked; reused once unreferenced


class PayloadBuffers:
    """Payload buffers reused from frame to frame; a buffer is handed out again only once nothing but this
    pool refers to it, so a frame (or any numpy view on it) that a consumer still holds is never overwritten.

    "Refers to" is CPython's reference count: every holder of the payload (the frame, ``np.frombuffer`` on it
    and views of that array, a ``memoryview``) keeps a reference to the buffer. At most ``keep`` buffers
    are pooled; when all are in use a new one is made and the oldest leaves the pool (it is freed as usual
    once its last holder lets go).
    """

    def __init__(self, keep: int = 8, make: Callable[[int], Any] = bytearray) -> None:
        self.keep = keep
        self.make = make   # length -> a new zeroed buffer (the driver's transfers need array.array("B"))
        self._buffers: list[Any] = []
        self.made = 0      # buffers allocated (a steady stream reuses them: this stops growing)

    def take(self, length: int) -> Any:
        buffers = self._buffers
        for i in range(len(buffers)):
            # 2 = the pool's list + getrefcount's argument (indexing, not a loop variable that would add one).
            if len(buffers[i]) == length and sys.getrefcount(buffers[i]) == 2:
                return buffers[i]
        buffer = self.make(length)
        self.made += 1
        if len(buffers) >= self.keep:
            del buffers[0]
        buffers.append(buffer)
        return buffer


@dataclass
class FrameAssembler:
    """Fed bulk-transfer bytes, yields whole frames whose header and payload CRCs check out.

    Two states. *Looking*: bytes gather in a small buffer until a magic and a valid header are found
    (garbage before it is skipped, a header failing its checks is counted and the search goes on one
    byte later). *Collecting*: the payload is copied straight from the transfers into a buffer of the
    announced length, which becomes the frame: one copy per byte on the common path. The payload CRC
    runs over each piece as it is copied (zlib's running value), so once the last transfer is in only
    its own bytes remain to check; buffers come from :class:`PayloadBuffers`, which reuses one only when
    nothing outside it still refers to it (a fresh 1-2 MB buffer per frame is zero-filled and faulted
    in page by page, inside the frame's latency when the frame is a single transfer). A caller that
    lends its transfer buffers (``feed(..., lent=True)``) gets a frame that lies wholly in one transfer
    as a view on that transfer, with no copy at all. The device ends a
    transfer at the end of each frame, so a transfer that begins with a valid header while a payload
    is being collected means the frame was cut short: it is counted as truncated and the new frame
    starts at once. A complete payload whose CRC fails is counted as a bad CRC, or as truncated when a
    magic inside it shows where the next frame began (a cut that did not end its transfer), and looking
    resumes at that magic. Scanning every payload for the magic instead would cost more than the CRC.
    """

    stats: AssemblerStats = field(default_factory=AssemblerStats)
    buffers: PayloadBuffers = field(default_factory=PayloadBuffers)

    def __post_init__(self) -> None:
        self._buf = bytearray()                  # looking: bytes not yet known to belong to a frame
        self._header: FrameHeader | None = None  # collecting: the valid header ...
        self._payload = bytearray()              # ... its payload buffer ...
        self._filled = 0                         # ... how much of it has arrived ...
        self._crc = 0                            # ... and the CRC-32 of what has

    @property
    def buffered(self) -> int:
        return len(self._buf) + (HEADER_SIZE + self._filled if self._header is not None else 0)

    @property
    def payload_left(self) -> int:
        """Payload bytes of the frame being collected still to come (0 while looking for a header)."""
        return self._header.payload_length - self._filled if self._header is not None else 0

    def reset(self) -> None:
        """Forget a partial frame (after a stall the device restarts at a frame boundary)."""
        self.stats.skipped_bytes += self.buffered
        self._buf.clear()
        self._header = None
        self._payload = bytearray()
        self._filled = 0
        self._crc = 0

    def feed(self, data: bytes | bytearray | memoryview, *, lent: bool = False) -> list[AssembledFrame]:
        """The frames completed by these bytes. ``lent``: the caller will not write into ``data``'s buffer
        while anything refers to it (it takes its transfer buffers from a :class:`PayloadBuffers`), so a
        good frame wholly inside ``data`` is handed on as a view on it, without copying its payload."""
        out: list[AssembledFrame] = []
        view = memoryview(data).cast("B") if isinstance(data, memoryview) else memoryview(data)
        while True:
            if self._header is not None:
                view = self._collect(view, out)
                if self._header is not None:
                    return out               # all bytes went into the payload; wait for more
                continue
            if not self._buf and len(view) >= HEADER_SIZE and view[:4] == FRAME_MAGIC:
                # Common path: a transfer starts with a header; no copy through the looking buffer.
                try:
                    header: FrameHeader | None = FrameHeader.decode(view[:HEADER_SIZE])
                except FrameError:
                    header = None
                if header is not None:
                    end = HEADER_SIZE + header.payload_length
                    if lent and len(view) >= end:
                        payload = view[HEADER_SIZE:end]
                        if zlib.crc32(payload) == header.payload_crc:
                            self.stats.frames += 1
                            out.append(AssembledFrame(header, payload))
                            view = view[end:]
                            continue
                        # A bad payload takes the copying path, which counts and resynchronises as always.
                    self._start(header)
                    view = view[HEADER_SIZE:]
                    continue
            if len(view):
                self._buf += view
                view = view[len(view):]
            if not self._look():
                return out
            # A valid header was found at the start of the looking buffer: its bytes feed the payload.
            pending = bytes(self._buf[HEADER_SIZE:])
            header = FrameHeader.decode(self._buf)
            self._buf.clear()
            self._start(header)
            view = memoryview(pending)

    # -- looking ---------------------------------------------------------------------------------
    def _look(self) -> bool:
        """Find a valid header at the start of the looking buffer (dropping what precedes it)."""
        buf = self._buf
        while True:
            start = buf.find(FRAME_MAGIC)
            if start < 0:
                # Keep a tail that may be the first bytes of a magic split across transfers.
                self._drop(len(buf) - min(len(buf), len(FRAME_MAGIC) - 1))
                return False
            self._drop(start)
            if len(buf) < HEADER_SIZE:
                return False
            try:
                FrameHeader.decode(buf)
                return True
            except FrameError:
                self.stats.corrupt_headers += 1
                self._drop(1)

    def _drop(self, n: int) -> None:
        if n > 0:
            self.stats.skipped_bytes += n
            del self._buf[:n]

    # -- collecting ------------------------------------------------------------------------------
    def _start(self, header: FrameHeader) -> None:
        self._header = header
        self._payload = self.buffers.take(header.payload_length)
        self._filled = 0
        self._crc = 0

    def _collect(self, view: memoryview, out: list[AssembledFrame]) -> memoryview:
        """Copy payload bytes from ``view``; returns what is left of it."""
        header = self._header
        assert header is not None
        if self._filled and self._valid_header_at_start(view):
            self.stats.truncated += 1
            self.stats.skipped_bytes += HEADER_SIZE + self._filled
            self._header = None
            self._payload = bytearray()
            return view
        take = min(len(view), header.payload_length - self._filled)
        piece = view[:take]
        self._payload[self._filled:self._filled + take] = piece
        self._crc = zlib.crc32(piece, self._crc)
        self._filled += take
        rest = view[take:]
        if self._filled < header.payload_length:
            return rest
        payload = self._payload
        self._header = None
        self._payload = bytearray()
        if self._crc == header.payload_crc:
            self.stats.frames += 1
            out.append(AssembledFrame(header, payload))
            return rest
        # A magic inside the payload (its header damaged too) still marks where the frame was cut.
        cut = payload.find(FRAME_MAGIC)
        if cut >= 0:
            self.stats.truncated += 1
            self.stats.skipped_bytes += HEADER_SIZE + cut
            self._buf = bytearray(payload[cut:])
            self._buf += rest
            return memoryview(b"")
        self.stats.bad_crc += 1
        self.stats.skipped_bytes += HEADER_SIZE + len(payload)
        return rest

    @staticmethod
    def _valid_header_at_start(view: memoryview) -> bool:
        if len(view) < HEADER_SIZE or view[:4] != FRAME_MAGIC:
            return False
        try:
            FrameHeader.decode(view[:HEADER_SIZE])
            return True
        except FrameError:
            return False
