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
import zlib
from dataclasses import dataclass, field
from enum import IntEnum

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
    payload: bytes


@dataclass
class FrameAssembler:
    """Fed bulk-transfer bytes, yields whole frames whose header and payload CRCs check out."""

    stats: AssemblerStats = field(default_factory=AssemblerStats)

    def __post_init__(self) -> None:
        self._buf = bytearray()
        self._header: FrameHeader | None = None
        self._scan_from = HEADER_SIZE   # where to look for an early next header inside a pending payload

    @property
    def buffered(self) -> int:
        return len(self._buf)

    def reset(self) -> None:
        """Forget a partial frame (after a stall the device restarts at a frame boundary)."""
        if self._buf:
            self.stats.skipped_bytes += len(self._buf)
        self._buf.clear()
        self._header = None
        self._scan_from = HEADER_SIZE

    def feed(self, data: bytes | bytearray | memoryview) -> list[AssembledFrame]:
        self._buf += data
        out: list[AssembledFrame] = []
        buf = self._buf
        while True:
            if self._header is None:
                start = buf.find(FRAME_MAGIC)
                if start < 0:
                    # Keep a tail that may be the first bytes of a magic split across transfers.
                    keep = min(len(buf), len(FRAME_MAGIC) - 1)
                    self._drop(len(buf) - keep)
                    break
                self._drop(start)
                if len(buf) < HEADER_SIZE:
                    break
                try:
                    self._header = FrameHeader.decode(buf)
                except FrameError:
                    self.stats.corrupt_headers += 1
                    self._drop(1)      # resynchronise on the next magic
                    continue
                self._scan_from = HEADER_SIZE
            need = HEADER_SIZE + self._header.payload_length
            inside = self._next_header_inside(min(need, len(buf)))
            if inside == "found":
                continue
            if len(buf) < need or inside == "wait":
                break
            payload = bytes(buf[HEADER_SIZE:need])
            header = self._header
            self._header = None
            if zlib.crc32(payload) != header.payload_crc:
                # A magic inside the payload (its header damaged too) still marks where the frame was cut.
                cut = buf.find(FRAME_MAGIC, HEADER_SIZE, need)
                if cut >= 0:
                    self.stats.truncated += 1
                    self._drop(cut)
                else:
                    self.stats.bad_crc += 1
                    self._drop(need)
                continue
            del buf[:need]
            self.stats.frames += 1
            out.append(AssembledFrame(header, payload))
        return out

    def _next_header_inside(self, end: int) -> str:
        """Look for a valid header starting inside the pending frame's payload before ``end``.

        ``"found"``: the pending frame was truncated; it is dropped and the buffer starts at the new
        header. ``"wait"``: a magic sits there but its header is not complete yet. ``"none"``: nothing.
        """
        buf = self._buf
        pos = self._scan_from
        while True:
            hit = buf.find(FRAME_MAGIC, pos, end)
            if hit < 0:
                self._scan_from = max(HEADER_SIZE, end - len(FRAME_MAGIC) + 1)
                return "none"
            if hit + HEADER_SIZE > len(buf):
                self._scan_from = hit      # look again once the whole candidate header is here
                return "wait"
            try:
                FrameHeader.decode(bytes(buf[hit:hit + HEADER_SIZE]))
            except FrameError:
                pos = hit + 1              # pixel data that happens to contain the magic
                continue
            self.stats.truncated += 1
            self._header = None
            self._drop(hit)
            return "found"

    def _drop(self, n: int) -> None:
        if n > 0:
            self.stats.skipped_bytes += n
            del self._buf[:n]
