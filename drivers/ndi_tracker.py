"""Driver for NDI optical trackers (Polaris over serial, Vega over TCP) through the Combined API.

The driver takes a ready pyserial port (``drivers.transport.open_serial``: a device path, a pty, or
``host:port``) and runs the session a tracker expects: INIT (with a serial break and RESET when the
tracker does not answer, e.g. because it is still at the speed a previous session chose), COMM to a
faster line speed and the host switch after OKAY (serial only), passive tools from tool definition
(.rom) files (PHRQ, PVWR in 64-byte chunks, PINIT, PENA), TSTART, TX or BX per frame, TSTOP.

Each tool in a frame becomes a :class:`ToolSample`: 4x4 transform (mm) and quaternion (w, x, y, z),
RMS fit error, the tracker's 60 Hz frame number and the host time of the reply; a tool the tracker does
not see is ``missing`` with no pose (never zeros). A background reader (:meth:`NDITracker.start_streaming`)
polls at the tracker's rate and hands the newest frame to whoever asks (:meth:`NDITracker.latest`).

Errors: an ``ERRORxx`` reply raises :class:`NdiCommandError` naming the command and the code's meaning;
no reply in time raises DeviceTimeoutError; a bad CRC or malformed reply ProtocolError; a dropped link
LinkLostError.
"""
from __future__ import annotations

import logging
import math
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import serial

from drivers.errors import DeviceError, DeviceTimeoutError, InputDataError, LinkLostError, ProtocolError
from firmware_protocol.errors import FrameError
from firmware_protocol.ndi import (
    CR,
    OKAY,
    ROM_MAX_BYTES,
    CommSettings,
    NdiErrorCode,
    decode_reply,
    encode_command,
    error_meaning,
    parse_error,
    parse_phrq,
    parse_phsr,
    pvwr_params,
    rom_chunks,
)
from firmware_protocol.ndi_replies import (
    BX_HEADER_BYTES,
    OPTION_TRANSFORMS,
    ToolState,
    TrackingReply,
    bx_total_length,
    decode_bx_records,
    decode_tx_text,
    reply_is_binary,
)

try:  # POSIX only; elsewhere socket replies are read a byte at a time, which is slower but correct
    import fcntl
    import termios
    _FIONREAD: int | None = termios.FIONREAD
except ImportError:  # pragma: no cover - Windows
    _FIONREAD = None

log = logging.getLogger(__name__)

FRAME_RATE_HZ = 60.0
POWER_ON_BAUD = 9600
#: Any tool type, wireless/passive (``1``), any port: what a passive tool's PHRQ asks for.
PHRQ_PASSIVE = "*********1****"


class NdiCommandError(DeviceError):
    """The tracker answered ``ERRORxx`` to a command; ``code`` and ``meaning`` say why."""

    def __init__(self, command: str, code: int, where: str) -> None:
        self.command, self.code, self.meaning = command, code, error_meaning(code)
        super().__init__(f"tracker at {where} answered ERROR{code:02X} to {command}: {self.meaning}")


@dataclass(frozen=True, eq=False)
class ToolSample:
    """One tool in one tracker frame. Pose fields are None when the tool is missing or disabled."""

    handle: int
    rom: str
    frame: int
    t: float                                   # host clock when the reply arrived, s
    missing: bool
    transform: np.ndarray | None = None        # 4x4, tool to tracker, mm
    quaternion: tuple[float, float, float, float] | None = None   # w, x, y, z
    rms_mm: float | None = None
    port_status: int = 0
    disabled: bool = False

    @property
    def position_mm(self) -> tuple[float, float, float] | None:
        if self.transform is None:
            return None
        return (float(self.transform[0, 3]), float(self.transform[1, 3]), float(self.transform[2, 3]))


def _rotation_rows(w: float, x: float, y: float, z: float) -> tuple[tuple[float, float, float], ...]:
    """Unit quaternion (w, x, y, z) -> the rows of its rotation matrix, normalised first (TX carries 4
    decimals, BX float32). Plain floats: the reader builds one per tool per 60 Hz frame in a thread that
    shares the interpreter with the control loop, and a handful of small numpy calls cost it ~10 us there.
    A zero quaternion gives NaN everywhere, as numpy's 0/0 did before (BX can carry one; nothing raises)."""
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    if norm == 0.0:
        return ((math.nan,) * 3,) * 3
    w, x, y, z = w / norm, x / norm, y / norm, z / norm
    return ((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
            (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
            (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)))


def quaternion_to_matrix(q: tuple[float, float, float, float]) -> np.ndarray:
    """Unit quaternion (w, x, y, z) -> 3x3 rotation matrix (normalised first: TX carries 4 decimals)."""
    return np.array(_rotation_rows(*(float(v) for v in q)))


def pose_transform(q: tuple[float, float, float, float], translation_mm: tuple[float, float, float]) -> np.ndarray:
    """Quaternion (w, x, y, z) and translation (mm) -> the read-only 4x4 tool-to-tracker transform."""
    (r0, r1, r2) = _rotation_rows(float(q[0]), float(q[1]), float(q[2]), float(q[3]))
    tx, ty, tz = translation_mm
    transform = np.array(((r0[0], r0[1], r0[2], tx), (r1[0], r1[1], r1[2], ty), (r2[0], r2[1], r2[2], tz),
                          (0.0, 0.0, 0.0, 1.0)))
    transform.setflags(write=False)     # samples are shared between threads
    return transform


@dataclass(frozen=True)
class _Poll:
    """A tracking-data command encoded once (the reader sends it 60 times a second)."""

    wire: bytes
    label: str
    binary: bool


_POLLS = {mode: _Poll(encode_command(mode.upper(), f"{OPTION_TRANSFORMS:04X}"),
                      f"{mode.upper()}:{OPTION_TRANSFORMS:04X}", mode == "bx") for mode in ("tx", "bx")}


class NDITracker:
    """An NDI tracker on a ready port. Use as a context manager; ``close()`` stops tracking and closes."""

    def __init__(self, port: serial.SerialBase, *, network: bool | None = None, reply_timeout_s: float = 2.0,
                 clock: Callable[[], float] = time.monotonic, own_port: bool = True) -> None:
        self.port = port
        self.where = str(getattr(port, "portstr", None) or getattr(port, "port", None) or "?")
        self.network = network if network is not None else self.where.startswith("socket://")
        self.reply_timeout_s = reply_timeout_s
        self.clock = clock
        self.own_port = own_port
        self.tools: dict[int, str] = {}         # handle -> ROM name
        self.tracking = False
        self._io = threading.RLock()             # one command/reply exchange at a time
        self._latest: list[ToolSample] | None = None
        self._latest_changed = threading.Condition()
        self._reader: threading.Thread | None = None
        self._reader_stop = threading.Event()
        self._reader_error: BaseException | None = None
        self._closed = False

    # -- lifecycle ------------------------------------------------------------------------------------------
    def __enter__(self) -> NDITracker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def connect(self, baudrate: int = 115200, *, reset: bool = False, probe_timeout_s: float = 0.5,
                reset_timeout_s: float = 10.0, free_all_handles: bool = True) -> None:
        """INIT the tracker (break and RESET it if it does not answer), then COMM to ``baudrate`` on serial.

        ``reset`` sends the serial break first, whatever state the tracker is in (serial only). With
        ``free_all_handles`` the port handles a previous session left allocated are freed, so that
        frames hold only the tools this session loads; otherwise only those the tracker marks to free.
        """
        if self.network:
            self._init(self.reply_timeout_s)     # no break over TCP: the tracker must answer
        else:
            CommSettings(baudrate).encode_params()      # an unsupported speed fails before any byte is sent
            self._set_baud(POWER_ON_BAUD)
            if reset:
                self._break_and_reset(reset_timeout_s)
            try:
                # Short: a tracker left at another speed by an earlier session hears only noise.
                self._init(probe_timeout_s if not reset else self.reply_timeout_s)
            except (DeviceTimeoutError, ProtocolError) as first:
                if reset:
                    raise
                log.info("%s: no answer to INIT (%s); sending a serial break", self.where, first)
                self._break_and_reset(reset_timeout_s)
                self._init(self.reply_timeout_s)
            if baudrate != POWER_ON_BAUD:
                self.command("COMM", CommSettings(baudrate).encode_params())
                time.sleep(0.1)    # the tracker switches 100 ms after OKAY has left it
                self._set_baud(baudrate)
        self.free_handles(all_allocated=free_all_handles)
        log.info("%s: tracker initialised%s", self.where, "" if self.network else f" at {self.port.baudrate} baud")

    def _break_and_reset(self, timeout_s: float) -> None:
        """A serial break resets the tracker to 9600 baud; it answers RESET when it is ready again."""
        if not hasattr(self.port, "send_break"):
            raise DeviceError(f"port {self.where} cannot send a serial break")
        with self._io:
            self._flush_input()
            self._io_call(self.port.send_break, 0.25)
            self._set_baud(POWER_ON_BAUD)
            reply = self._read_text(time.monotonic() + timeout_s, "serial break")
        if reply != "RESET":
            raise ProtocolError(f"tracker at {self.where} answered {reply!r} to a serial break instead of RESET")
        self.tools.clear()
        self.tracking = False

    def _init(self, timeout_s: float) -> None:
        try:
            self.command("INIT", timeout_s=timeout_s)
        except NdiCommandError as err:
            if err.code != NdiErrorCode.INVALID_MODE:
                raise
            # A previous session left the tracker tracking: stop it and initialise again.
            self.command("TSTOP", timeout_s=timeout_s)
            self.command("INIT", timeout_s=timeout_s)

    def close(self) -> None:
        """Stop the reader, stop tracking (best effort) and close the port; safe to call twice."""
        if self._closed:
            return
        self.stop_streaming()
        if self.tracking:
            try:
                self.stop()
            except DeviceError as err:
                log.warning("%s: TSTOP on close failed: %s", self.where, err)
        self._closed = True
        if self.own_port:
            try:
                self.port.close()
            except (OSError, serial.SerialException) as err:
                log.warning("%s: closing the port failed: %s", self.where, err)

    # -- commands -------------------------------------------------------------------------------------------
    def version(self) -> str:
        """The tracker's ``VER:0`` text (product, serial number, freeze tag...)."""
        return str(self.command("VER", "0"))

    def free_handles(self, *, all_allocated: bool = False) -> None:
        """Free the handles the tracker marks to be freed (PHSR 01), or every allocated handle (PHSR 00)."""
        for handle in parse_phsr_text(str(self.command("PHSR", "00" if all_allocated else "01"))):
            self.command("PHF", f"{handle:02X}")
            self.tools.pop(handle, None)

    def load_tool(self, rom: str | Path | bytes, name: str | None = None) -> int:
        """Upload a passive tool definition (a .rom path or its bytes), initialise and enable it; returns the handle."""
        if isinstance(rom, (str, Path)):
            path = Path(rom)
            try:
                data = path.read_bytes()
            except OSError as err:
                raise InputDataError(f"cannot read tool definition {path}: {err.strerror or err}") from err
            name = name or path.name
        else:
            data = bytes(rom)
        if not data or len(data) > ROM_MAX_BYTES:
            raise InputDataError(f"tool definition {name or '(bytes)'} is {len(data)} bytes; NDI tools are 1-1024 bytes")
        handle = parse_phrq(str(self.command("PHRQ", PHRQ_PASSIVE)))
        try:
            for address, chunk in rom_chunks(data):
                self.command("PVWR", pvwr_params(handle, address, chunk))
            self.command("PINIT", f"{handle:02X}")
            self.command("PENA", f"{handle:02X}D")
        except DeviceError:
            try:
                self.command("PHF", f"{handle:02X}")
            except DeviceError as cleanup:
                log.warning("%s: freeing handle %02X after a failed load failed too: %s", self.where, handle, cleanup)
            raise
        self.tools[handle] = name or f"tool-{handle:02x}"
        log.info("%s: tool %s loaded on handle %02X", self.where, self.tools[handle], handle)
        return handle

    def start(self) -> None:
        self.command("TSTART")
        self.tracking = True

    def stop(self) -> None:
        self.stop_streaming()
        self.command("TSTOP")
        self.tracking = False

    def read_frame(self, mode: str = "tx") -> list[ToolSample]:
        """One frame of every enabled tool, with TX (text) or BX (binary) replies.

        The sample time ``t`` is the host clock right after the whole reply is in (before it is parsed).
        """
        poll = _POLLS.get(mode)
        if poll is None:
            raise ValueError(f"mode is 'tx' or 'bx', not {mode!r}")
        with self._io:
            raw = self._exchange(poll.wire, poll.label, self.reply_timeout_s, poll.binary)
            t = self.clock()
        if isinstance(raw, str):
            raw = self._checked_text(raw, poll.label)
        try:
            if isinstance(raw, bytes):
                return self._bx_samples(decode_bx_records(raw)[0], t)
            return self._samples(decode_tx_text(raw), t)
        except FrameError as err:
            raise ProtocolError(f"tracker at {self.where}: malformed {mode.upper()} reply: {err}") from err

    def _rom(self, handle: int) -> str:
        rom = self.tools.get(handle)
        return rom if rom is not None else f"handle-{handle:02x}"

    def _samples(self, reply: TrackingReply, t: float) -> list[ToolSample]:
        samples = []
        for record in reply.tools:
            rom = self._rom(record.handle)
            if record.state != ToolState.VALID:
                samples.append(ToolSample(record.handle, rom, record.frame, t, missing=True,
                                          port_status=record.port_status,
                                          disabled=record.state == ToolState.DISABLED))
                continue
            assert record.quaternion is not None and record.translation_mm is not None
            samples.append(ToolSample(record.handle, rom, record.frame, t, missing=False,
                                      transform=pose_transform(record.quaternion, record.translation_mm),
                                      quaternion=tuple(float(v) for v in record.quaternion),  # type: ignore[arg-type]
                                      rms_mm=float(record.rms_mm or 0.0), port_status=record.port_status))
        return samples

    def _bx_samples(self, records: list[tuple], t: float) -> list[ToolSample]:
        """The samples of :func:`decode_bx_records`'s flat records (the same as :meth:`_samples` of decode_bx)."""
        samples = []
        for record in records:
            handle, status = record[0], record[1]
            if status == ToolState.VALID:
                q = record[2:6]
                samples.append(ToolSample(handle, self._rom(handle), record[11], t, missing=False,
                                          transform=pose_transform(q, record[6:9]), quaternion=q,
                                          rms_mm=record[9], port_status=record[10]))
            elif status == ToolState.MISSING:
                samples.append(ToolSample(handle, self._rom(handle), record[3], t, missing=True,
                                          port_status=record[2]))
            else:
                samples.append(ToolSample(handle, self._rom(handle), 0, t, missing=True, disabled=True))
        return samples

    def command(self, name: str, params: str = "", *, timeout_s: float | None = None,
                binary: bool = False) -> str | bytes:
        """Send one command (CRC form); return the reply text without CRC, or a BX reply's bytes."""
        label = f"{name}:{params[:24]}{'...' if len(params) > 24 else ''}"
        wire = encode_command(name, params)
        log.debug("%s <- %r", self.where, wire)
        raw = self._exchange(wire, label, timeout_s if timeout_s is not None else self.reply_timeout_s, binary)
        if isinstance(raw, bytes):
            log.debug("%s -> %d BX bytes", self.where, len(raw))
            return raw
        log.debug("%s -> %r", self.where, raw)
        text = self._checked_text(raw, label)
        if name in ("INIT", "COMM", "PVWR", "PINIT", "PENA", "PHF", "TSTART", "TSTOP") and text != OKAY:
            raise ProtocolError(f"tracker at {self.where} answered {text[:40]!r} to {label} instead of OKAY")
        return text

    def _exchange(self, wire: bytes, label: str, timeout_s: float, binary: bool) -> str | bytes:
        """Write one encoded command and read its whole reply: a BX reply's bytes (by its declared length,
        header CRC checked), or a text reply's text (CRC checked). ``label`` names the command in errors."""
        deadline = time.monotonic() + timeout_s
        with self._io:
            if self._closed:
                raise DeviceError(f"tracker at {self.where} is closed")
            self._flush_input()
            self._io_call(self.port.write, wire)
            first = self._read_exact(1, deadline, label)
            if binary and reply_is_binary(first):
                header = first + self._read_exact(BX_HEADER_BYTES - 1, deadline, label)
                try:
                    total = bx_total_length(header)
                except FrameError as err:
                    raise ProtocolError(f"tracker at {self.where}: bad BX header for {label}: {err}") from err
                return header + self._read_exact(total - BX_HEADER_BYTES, deadline, label)
            return self._read_text(deadline, label, first)

    def _checked_text(self, text: str, label: str) -> str:
        """A text reply's text, unless it is ``ERRORxx`` (NdiCommandError); a WARNING is logged."""
        if text.startswith("ERROR"):
            code = parse_error(text)
            if code is not None:
                raise NdiCommandError(label, code, self.where)
        elif text.startswith("WARNING"):
            log.warning("%s: %s answered %s", self.where, label, text)
        return text

    # -- bytes ----------------------------------------------------------------------------------------------
    def _io_call(self, fn: Callable[..., object], *args: object) -> object:
        try:
            return fn(*args)
        except serial.SerialTimeoutException as err:
            raise DeviceTimeoutError(f"writing to the tracker at {self.where} timed out") from err
        except (serial.SerialException, OSError) as err:
            raise LinkLostError(f"link to the tracker at {self.where} lost: {err}") from err

    def _set_baud(self, baudrate: int) -> None:
        self._io_call(setattr, self.port, "baudrate", baudrate)

    def _flush_input(self) -> None:
        # A tracker never speaks unprompted; anything waiting is the tail of an abandoned reply. With
        # nothing waiting there is nothing to discard, and the flush's system call is saved (every poll).
        waiting = self._io_call(lambda: self.port.in_waiting)
        if waiting:
            log.warning("%s: discarding %s stale bytes", self.where, waiting)
            self._io_call(self.port.reset_input_buffer)

    def _read_exact(self, count: int, deadline: float, label: str) -> bytes:
        first = self._io_call(self.port.read, count)
        if len(first) == count:         # the usual case: the port's own timeout waited for all of it
            return first                # type: ignore[return-value]
        data = bytearray(first)         # type: ignore[arg-type]
        while len(data) < count:
            if time.monotonic() > deadline:
                raise DeviceTimeoutError(self._silence(label, data))
            data += self._io_call(self.port.read, count - len(data))  # type: ignore[operator]
        return bytes(data)

    def _read_text(self, deadline: float, label: str, first: bytes = b"") -> str:
        data = bytearray(first)
        while not data.endswith(CR):
            if time.monotonic() > deadline:
                raise DeviceTimeoutError(self._silence(label, data))
            data += self._io_call(self.port.read, max(1, self._available()))  # type: ignore[operator]
            if len(data) > 4096:
                raise ProtocolError(f"tracker at {self.where}: {len(data)} bytes without CR after {label}")
        try:
            return decode_reply(bytes(data))
        except FrameError as err:
            raise ProtocolError(f"tracker at {self.where}: bad reply to {label}: {err}") from err

    def _available(self) -> int:
        """Bytes ready to read. pyserial's ``socket://`` port says only 0 or 1, which would make a TX reply
        arrive one byte per system call; ask the socket itself for the count (FIONREAD) instead."""
        waiting = int(self._io_call(lambda: self.port.in_waiting))  # type: ignore[call-overload]
        sock = getattr(self.port, "_socket", None)
        if waiting and sock is not None and _FIONREAD is not None:
            try:
                count = fcntl.ioctl(sock.fileno(), _FIONREAD, b"\0\0\0\0")
                return max(waiting, struct.unpack("i", count)[0])
            except (OSError, ValueError):
                pass
        return waiting

    def _silence(self, label: str, partial: bytearray) -> str:
        got = f" (got only {bytes(partial)[:40]!r})" if partial else ""
        return f"no complete reply to {label} from the tracker at {self.where}{got}"

    # -- background reader ----------------------------------------------------------------------------------
    def start_streaming(self, mode: str = "tx", rate_hz: float = FRAME_RATE_HZ) -> None:
        """Poll frames in a thread at ``rate_hz``; :meth:`latest` returns the newest. Needs :meth:`start` first."""
        if self._reader is not None:
            return
        if not self.tracking:
            raise DeviceError(f"tracker at {self.where}: start() tracking before streaming")
        self._reader_stop.clear()
        self._reader_error = None
        self._reader = threading.Thread(target=self._read_loop, args=(mode, 1.0 / rate_hz),
                                        name=f"ndi-reader-{self.where}", daemon=True)
        self._reader.start()

    def stop_streaming(self) -> None:
        if self._reader is None:
            return
        self._reader_stop.set()
        if self._reader is not threading.current_thread():
            self._reader.join(timeout=2.0 + self.reply_timeout_s)
        self._reader = None

    def _read_loop(self, mode: str, period_s: float) -> None:
        next_at = time.monotonic()
        while not self._reader_stop.is_set():
            try:
                samples = self.read_frame(mode)
            except BaseException as err:   # handed to the next caller of latest(), never swallowed
                self._reader_error = err
                log.error("%s: background reader stopped: %s", self.where, err)
                with self._latest_changed:
                    self._latest_changed.notify_all()
                return
            with self._latest_changed:
                self._latest = samples
                self._latest_changed.notify_all()
            next_at = max(next_at + period_s, time.monotonic() - period_s)
            self._reader_stop.wait(max(0.0, next_at - time.monotonic()))

    def latest(self) -> list[ToolSample] | None:
        """The newest frame the reader got (None before the first); re-raises the error that stopped it."""
        if self._reader_error is not None:
            raise self._reader_error
        return list(self._latest) if self._latest is not None else None

    def wait_for_frame(self, newer_than: int = -1, timeout_s: float = 1.0) -> list[ToolSample]:
        """Block until the reader has a frame numbered above ``newer_than``; DeviceTimeoutError otherwise."""
        deadline = time.monotonic() + timeout_s
        with self._latest_changed:
            while True:
                samples = self.latest()
                if samples and samples[0].frame > newer_than:
                    return samples
                remaining = deadline - time.monotonic()
                if remaining <= 0 or (self._reader is None and self._reader_error is None):
                    raise DeviceTimeoutError(f"no frame after {newer_than} from the tracker at {self.where}")
                self._latest_changed.wait(remaining)


def parse_phsr_text(text: str) -> list[int]:
    """Handles listed in a PHSR reply."""
    try:
        return [entry.handle for entry in parse_phsr(text)]
    except FrameError as err:
        raise ProtocolError(f"malformed PHSR reply {text!r}: {err}") from err
