"""NDI Combined API framing: the CRC, commands in both forms, text replies, error codes, COMM, PHRQ/PHSR.

NDI optical trackers (Polaris over serial, Vega over TCP) speak a line protocol: every command and every
reply ends with one carriage return. A command is either ``NAME:params`` followed by a CRC as four
uppercase hex digits (what ndicapi sends), or ``NAME params`` without a CRC (NDI's own sample code).
Every reply carries the CRC of its text before the CR. The CRC is CRC-16/ARC (reflected polynomial
0xA001, initial value 0, no final XOR).

This module is pure: bytes in, values out, or :class:`~firmware_protocol.errors.FrameError` and its
subclasses. The tracking-data replies (TX text, BX binary) live in :mod:`firmware_protocol.ndi_replies`.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from enum import IntEnum

from firmware_protocol.errors import CrcError, FrameError

CR = b"\r"
LF = b"\n"
#: Replies longer than this break ndicapi's fixed 2048-byte buffers; a tracker never sends them.
MAX_REPLY_BYTES = 2047
#: A PVWR writes this many ROM bytes; a passive tool definition is at most 1024 bytes.
PVWR_CHUNK_BYTES = 64
ROM_MAX_BYTES = 1024


def _crc16_table() -> tuple[int, ...]:
    """The CRC-16/ARC register after shifting each byte value through it bit by bit (0xA001 reflected)."""
    table = []
    for value in range(256):
        crc = value
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_CRC16_TABLE = _crc16_table()


def crc16(data: bytes, crc: int = 0) -> int:
    """CRC-16/ARC as NDI computes it over command and reply text (``crc`` continues a running CRC).

    A byte at a time through a 256-entry table: the tracker reader checks a CRC per 60 Hz reply in a
    thread that shares the interpreter with the control loop, and the bit-by-bit form cost ~0.5 us a
    byte there (``binascii.crc_hqx`` is CRC-CCITT, another polynomial, so it cannot stand in).
    """
    table = _CRC16_TABLE
    for byte in data:
        crc = (crc >> 8) ^ table[(crc ^ byte) & 0xFF]
    return crc


def crc_hex(data: bytes) -> bytes:
    """The CRC of ``data`` as the four uppercase hex digits that follow it on the wire."""
    return b"%04X" % crc16(data)


# --------------------------------------------------------------------------------------------- commands

_NAME = re.compile(rb"^[A-Z][A-Z0-9]*$")
_HEX4 = re.compile(rb"^[0-9A-Fa-f]{4}$")


@dataclass(frozen=True)
class Command:
    """One host command. ``has_crc`` records which form it came in (``NAME:params+CRC`` or ``NAME params``)."""

    name: str
    params: str = ""
    has_crc: bool = True

    def encode(self) -> bytes:
        return encode_command(self.name, self.params, with_crc=self.has_crc)


def encode_command(name: str, params: str = "", *, with_crc: bool = True) -> bytes:
    """``TX``, ``0801`` -> ``b"TX:0801" + CRC + CR`` (or ``b"TX 0801\\r"`` without the CRC)."""
    raw_name = name.encode("ascii")
    if not _NAME.match(raw_name):
        raise FrameError(f"invalid NDI command name {name!r}")
    raw_params = params.encode("ascii")
    if CR in raw_params or LF in raw_params:
        raise FrameError(f"NDI command parameters may not contain CR or LF: {params!r}")
    if with_crc:
        text = raw_name + b":" + raw_params
        return text + crc_hex(text) + CR
    return raw_name + b" " + raw_params + CR


def decode_command(line: bytes) -> Command:
    """Parse one command line (with or without its trailing CR).

    A colon marks the CRC form: the last four characters are then the CRC of everything before them.
    Raises :class:`CrcError` for a wrong CRC, :class:`FrameError` for anything that is not a command.
    """
    if line.endswith(CR):
        line = line[:-1]
    if not line:
        raise FrameError("empty command line")
    colon, space = line.find(b":"), line.find(b" ")
    if colon >= 0 and (space < 0 or colon < space):
        if len(line) < colon + 1 + 4 or not _HEX4.match(line[-4:]):
            raise CrcError(f"command {line[:40]!r} has a colon but no 4-hex-digit CRC")
        text, given = line[:-4], int(line[-4:], 16)
        if crc16(text) != given:
            raise CrcError(f"command {text[:40]!r}: CRC {given:04X} given, {crc16(text):04X} computed")
        name, params, has_crc = text[:colon], text[colon + 1:], True
    elif space >= 0:
        name, params, has_crc = line[:space], line[space + 1:], False
    else:
        name, params, has_crc = line, b"", False
    if not _NAME.match(name.upper()):
        raise FrameError(f"not an NDI command: {line[:40]!r}")
    try:
        return Command(name.upper().decode("ascii"), params.decode("ascii"), has_crc)
    except UnicodeDecodeError as err:
        raise FrameError(f"non-ASCII bytes in command {line[:40]!r}") from err


class LineSplitter:
    """Accumulates a byte stream and yields whole CR-terminated lines (the CR stripped).

    Used by the fake for commands; a host reading text replies uses it too. ``max_line`` guards against
    a peer that never sends CR.
    """

    def __init__(self, max_line: int = 4096) -> None:
        self._buffer = bytearray()
        self.max_line = max_line

    def feed(self, data: bytes) -> list[bytes]:
        self._buffer += data
        lines = []
        while True:
            end = self._buffer.find(CR)
            if end < 0:
                break
            lines.append(bytes(self._buffer[:end]))
            del self._buffer[:end + 1]
        if len(self._buffer) > self.max_line:
            overflow = bytes(self._buffer)
            self._buffer.clear()
            raise FrameError(f"{len(overflow)} bytes without a CR: {overflow[:40]!r}...")
        return lines

    @property
    def pending(self) -> bytes:
        return bytes(self._buffer)

    def clear(self) -> None:
        self._buffer.clear()


# ---------------------------------------------------------------------------------------------- replies

def encode_reply(text: str | bytes) -> bytes:
    """Reply text -> text + CRC + CR, as a tracker sends it (the CRC covers any LFs in the text)."""
    raw = text.encode("ascii") if isinstance(text, str) else bytes(text)
    return raw + crc_hex(raw) + CR


def decode_reply(raw: bytes) -> str:
    """A whole text reply (with or without the final CR) -> its text, after checking the CRC."""
    if raw.endswith(CR):
        raw = raw[:-1]
    if len(raw) < 4 or not _HEX4.match(raw[-4:]):
        raise FrameError(f"reply {raw[:40]!r} does not end with a 4-hex-digit CRC")
    text, given = raw[:-4], int(raw[-4:], 16)
    if crc16(text) != given:
        raise CrcError(f"reply {text[:40]!r}: CRC {given:04X} given, {crc16(text):04X} computed")
    try:
        return text.decode("ascii")
    except UnicodeDecodeError as err:
        raise FrameError(f"non-ASCII bytes in reply {text[:40]!r}") from err


OKAY = "OKAY"
RESET = "RESET"


class NdiErrorCode(IntEnum):
    """The ``ERRORxx`` codes this project produces or handles specially (any two-hex code may arrive)."""

    INVALID_COMMAND = 0x01
    COMMAND_TOO_LONG = 0x02
    COMMAND_TOO_SHORT = 0x03
    BAD_COMMAND_CRC = 0x04
    COMMAND_TIMEOUT = 0x05
    BAD_COMM_PARAMETERS = 0x06
    WRONG_PARAMETER_COUNT = 0x07
    INVALID_PORT_HANDLE = 0x08
    INVALID_PRIORITY = 0x09
    INVALID_MODE = 0x0C
    NO_TOOL_ASSIGNED = 0x0D
    HANDLE_NOT_INITIALISED = 0x0E
    HANDLE_NOT_ENABLED = 0x0F
    SYSTEM_NOT_INITIALISED = 0x10
    UNABLE_TO_STOP_TRACKING = 0x11
    UNABLE_TO_START_TRACKING = 0x12
    PARAMETER_OUT_OF_RANGE = 0x24
    HANDLE_NOT_ALLOCATED = 0x2B
    HANDLE_UNOCCUPIED = 0x2C
    NO_MORE_HANDLES = 0x2D


#: What each error code means, in NDI's words where they are public (API guide tables quoted by clients).
ERROR_MEANINGS: dict[int, str] = {
    0x01: "invalid command",
    0x02: "command too long",
    0x03: "command too short",
    0x04: "invalid CRC calculated for command",
    0x05: "time-out on command execution",
    0x06: "unable to set up new communication parameters",
    0x07: "incorrect number of command parameters",
    0x08: "invalid port handle selected",
    0x09: "invalid tracking priority selected (must be S, D or B)",
    0x0A: "invalid LED selected",
    0x0B: "invalid LED state selected (must be B, F or S)",
    0x0C: "command is invalid while in the current mode",
    0x0D: "no tool assigned to the selected port handle",
    0x0E: "selected port handle not initialised",
    0x0F: "selected port handle not enabled",
    0x10: "system not initialised",
    0x11: "unable to stop tracking",
    0x12: "unable to start tracking",
    0x13: "unable to initialise tool-in-port",
    0x14: "invalid position sensor or field generator characterisation parameters",
    0x15: "unable to initialise the measurement system",
    0x16: "unable to start diagnostic mode",
    0x17: "unable to stop diagnostic mode",
    0x19: "unable to read the device's firmware version information",
    0x1A: "internal measurement system error",
    0x23: "unable to find camera parameters for the wavelength of an enabled tool",
    0x24: "command parameter out of range",
    0x25: "unable to select parameters by volume",
    0x26: "unable to determine the supported features list",
    0x29: "main processor firmware corrupt",
    0x2A: "no memory available for dynamic allocation (heap is full)",
    0x2B: "requested port handle has not been allocated",
    0x2C: "requested port handle has become unoccupied",
    0x2D: "all port handles have been allocated",
    0x2E: "invalid port description",
    0x2F: "requested port already assigned to a port handle",
    0x30: "invalid input or output state",
    0xF4: "unable to erase flash EPROM",
    0xF5: "unable to write flash EPROM",
    0xF6: "unable to read flash EPROM",
}


def error_meaning(code: int) -> str:
    return ERROR_MEANINGS.get(code, f"unrecognised error code 0x{code:02X}")


def encode_error(code: int) -> bytes:
    """``ERROR`` + two uppercase hex digits, framed."""
    if not 0 <= code <= 0xFF:
        raise FrameError(f"NDI error code out of range: {code}")
    return encode_reply(f"ERROR{code:02X}")


_ERROR = re.compile(r"^ERROR([0-9A-Fa-f]{2})$")


def parse_error(text: str) -> int | None:
    """``"ERROR0C"`` -> 0x0C; any other reply text -> None."""
    match = _ERROR.match(text)
    return int(match.group(1), 16) if match else None


# ------------------------------------------------------------------------------------------------- COMM

#: COMM baud digit -> line speed (NDI's table; ``A`` was added for 230400).
COMM_BAUD = {"0": 9600, "1": 14400, "2": 19200, "3": 38400, "4": 57600, "5": 115200,
             "6": 921600, "7": 1228739, "A": 230400}


@dataclass(frozen=True)
class CommSettings:
    """Serial parameters a ``COMM`` command selects."""

    baudrate: int = 9600
    data_bits: int = 8
    parity: str = "N"          # N, O or E (pyserial's letters)
    stop_bits: int = 1
    handshake: bool = False

    def encode_params(self) -> str:
        baud = next((digit for digit, rate in COMM_BAUD.items() if rate == self.baudrate), None)
        if baud is None:
            raise FrameError(f"COMM cannot select {self.baudrate} baud; choose one of {sorted(COMM_BAUD.values())}")
        return (f"{baud}{0 if self.data_bits == 8 else 1}{'NOE'.index(self.parity)}"
                f"{self.stop_bits - 1}{int(self.handshake)}")


def parse_comm(params: str) -> CommSettings:
    """``"50000"`` -> 115200 8N1, no handshake. Raises FrameError for anything outside NDI's table."""
    if len(params) != 5:
        raise FrameError(f"COMM wants 5 digits (baud, data bits, parity, stop bits, handshake), got {params!r}")
    baud, data, parity, stop, handshake = params.upper()
    if baud not in COMM_BAUD or data not in "01" or parity not in "012" or stop not in "01" or handshake not in "01":
        raise FrameError(f"COMM parameters {params!r} are outside NDI's table")
    return CommSettings(COMM_BAUD[baud], 8 if data == "0" else 7, "NOE"[int(parity)], int(stop) + 1, handshake == "1")


# ------------------------------------------------------------------------------------------- PHRQ, PHSR

class PhsrMode(IntEnum):
    """Which port handles ``PHSR`` lists."""

    ALL = 0
    TO_FREE = 1
    NOT_INITIALISED = 2
    INITIALISED_NOT_ENABLED = 3
    ENABLED = 4


@dataclass(frozen=True)
class PortHandleStatus:
    handle: int
    status: int      # 3 hex digits in PHSR: bit 0 occupied, bit 4 initialised, bit 5 enabled


def encode_phsr(entries: list[PortHandleStatus]) -> str:
    """Reply text (without CRC): count, then per handle 2 hex handle + 3 hex status, no separators."""
    return f"{len(entries):02X}" + "".join(f"{e.handle:02X}{e.status:03X}" for e in entries)


def parse_phsr(text: str) -> list[PortHandleStatus]:
    def hex_at(start: int, end: int) -> int:
        try:
            return int(text[start:end], 16)
        except ValueError as err:
            raise FrameError(f"PHSR reply {text!r} is not hex at {start}") from err

    count = hex_at(0, 2)
    if len(text) < 2 + 5 * count:
        raise FrameError(f"PHSR reply {text!r} announces {count} handles but is {len(text)} characters long")
    return [PortHandleStatus(hex_at(2 + 5 * i, 4 + 5 * i), hex_at(4 + 5 * i, 7 + 5 * i)) for i in range(count)]


def parse_phrq(text: str) -> int:
    """PHRQ reply: the new handle as two hex digits."""
    if len(text) < 2:
        raise FrameError(f"PHRQ reply {text!r} is shorter than a handle")
    try:
        return int(text[:2], 16)
    except ValueError as err:
        raise FrameError(f"PHRQ reply {text!r} is not a hex handle") from err


def parse_handle(text: str) -> int:
    """Two hex digits, either case (ndicapi sends ``0a``, NDI's sample ``0A``)."""
    if len(text) != 2:
        raise FrameError(f"a port handle is two hex digits, got {text!r}")
    try:
        return int(text, 16)
    except ValueError as err:
        raise FrameError(f"port handle {text!r} is not hex") from err


def pvwr_params(handle: int, address: int, chunk: bytes) -> str:
    """Parameters of one PVWR: handle, 4-hex address, 64 bytes as 128 uppercase hex digits."""
    if len(chunk) != PVWR_CHUNK_BYTES:
        raise FrameError(f"PVWR writes {PVWR_CHUNK_BYTES} bytes at a time, got {len(chunk)}")
    if address % PVWR_CHUNK_BYTES or not 0 <= address < ROM_MAX_BYTES:
        raise FrameError(f"PVWR address 0x{address:04X} is not a 64-byte boundary below 0x0400")
    return f"{handle:02X}{address:04X}{chunk.hex().upper()}"


def rom_chunks(rom: bytes) -> list[tuple[int, bytes]]:
    """A tool definition padded with zeros to 1024 bytes, as (address, 64 bytes) pairs."""
    if len(rom) > ROM_MAX_BYTES:
        raise FrameError(f"a tool definition is at most {ROM_MAX_BYTES} bytes, got {len(rom)}")
    padded = rom.ljust(ROM_MAX_BYTES, b"\x00")
    return [(addr, padded[addr:addr + PVWR_CHUNK_BYTES]) for addr in range(0, ROM_MAX_BYTES, PVWR_CHUNK_BYTES)]
