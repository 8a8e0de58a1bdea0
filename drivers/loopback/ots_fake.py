"""A loopback NDI optical tracker (Polaris Spectra-like): the tracker's side of the Combined API.

Serve it with :class:`drivers.loopback.serve.PtyServer` or ``TcpServer``; any NDI client (our
:class:`drivers.ndi_tracker.NDITracker`, ndicapi, scikit-surgerynditracker) then talks to it as to a
tracker. It answers every command at once and never speaks unprompted (``tick`` returns nothing), as
clients flush their input before each command.

What it models: INIT (twice is fine), RESET, COMM (recorded; a pty carries no line speed), VER:0 (its
``Freeze Tag`` line decides whether scikit-surgerynditracker uses TX or BX), GETINFO for the firmware
version, BEEP, PHSR, PHRQ, PHF, PVWR (1024-byte tool definitions in 64-byte chunks, stored per handle),
PINIT, PENA, PDIS, TSTART (``80`` resets the frame counter), TSTOP, TX and BX with reply option 0x0001
(0x0800 reports out-of-volume tools with the out-of-volume bit instead of MISSING). Commands in both
forms (``NAME:params``+CRC, ``NAME params``). Errors as a tracker answers them: 01 unknown command,
02 line too long, 04 bad CRC, 06/07 bad COMM or parameter count, 08 unknown handle, 09 bad priority,
0C wrong mode, 0D no tool definition, 0E not initialised, 0F not enabled, 10 system not initialised,
24 parameter out of range, 2D no more handles.

Poses come from a pose provider, ``provider(now) -> {tool_index: (R 3x3 | quaternion wxyz, t_mm) |
None}``; tool index 0 is the first handle a client requested. A tool without a pose, or outside the
measurement volume, is MISSING. Noise per frame: Gaussian position noise (default 0.19 mm RMS, 3D),
small rotation noise, and a reported fit RMS; the same frame number always returns the same sample.
Providers, the volume and the noise model live in :mod:`drivers.loopback.ots_poses`; swap
``fake.provider`` while holding the server's lock (the current frame is then measured again).

Not modelled: the tool definition's contents (markers, geometry), marker-level data (stray markers,
3D markers, reply options 0x0002-0x1000), wired/active tools and tool-in-port events, serial break
(a pty cannot carry one), line speed, illuminator and environment diagnostics, GX/PSTAT/SSTAT.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from drivers.loopback.ots_poses import (  # noqa: F401  (re-exported: the fake's public vocabulary)
    BoxVolume,
    FixedPose,
    NoiseModel,
    Pose,
    PoseProvider,
    ScriptedPoses,
    as_rotation,
)
from firmware_protocol.errors import CrcError, FrameError
from firmware_protocol.ndi import (
    OKAY,
    PVWR_CHUNK_BYTES,
    RESET,
    ROM_MAX_BYTES,
    Command,
    CommSettings,
    LineSplitter,
    NdiErrorCode as E,
    PhsrMode,
    PortHandleStatus,
    decode_command,
    encode_error,
    encode_phsr,
    encode_reply,
    parse_comm,
    parse_handle,
)
from firmware_protocol.ndi_replies import (
    OPTION_OUT_OF_VOLUME,
    PORT_ENABLED,
    PORT_INITIALISED,
    PORT_OCCUPIED,
    PORT_OUT_OF_VOLUME,
    SUPPORTED_OPTIONS,
    ToolRecord,
    ToolState,
    TrackingReply,
    encode_bx,
    encode_tx,
    parse_reply_option,
)

log = logging.getLogger(__name__)

FRAME_RATE_HZ = 60.0


@dataclass(frozen=True)
class FirmwareIdentity:
    """What ``VER:0`` and ``GETINFO`` say. scikit-surgerynditracker picks TX for the Spectra freeze tags."""

    freeze_tag: str = "Polaris Spectra Rev 007"
    product: str = "Polaris Spectra Control Firmware (loopback simulator)"
    serial_number: str = "LOOPBACK-01"
    firmware_version: str = "007.000.012"
    getinfo: bool = True        # older firmware answers GETINFO with ERROR01

    def ver0_text(self) -> str:
        return (f"{self.product}\nNDI S/N: {self.serial_number}\nFreeze Tag: {self.freeze_tag}\n"
                f"Freeze Date: 01/01/2026\n(C) loopback, not Northern Digital Inc.\n")


#: A firmware whose freeze tag scikit-surgerynditracker does not list, so it uses BX.
SPECTRA_BX_FIRMWARE = FirmwareIdentity(freeze_tag="Polaris Spectra Rev 010", firmware_version="010.000.004")


# ------------------------------------------------------------------------------------------------ the fake

@dataclass
class PortHandle:
    handle: int
    tool_index: int
    rom: bytearray = field(default_factory=lambda: bytearray(ROM_MAX_BYTES))
    chunks_written: set[int] = field(default_factory=set)
    initialised: bool = False
    enabled: bool = False
    priority: str = ""

    @property
    def status(self) -> int:
        return PORT_OCCUPIED | (PORT_INITIALISED if self.initialised else 0) | (PORT_ENABLED if self.enabled else 0)


class _Refused(Exception):
    """A command the tracker answers with ERRORxx."""

    def __init__(self, code: int, why: str) -> None:
        super().__init__(why)
        self.code = code


class NdiTrackerFake:
    """The tracker's state machine; feed it host bytes, get reply bytes. Not thread-safe (serve.py locks)."""

    def __init__(self, provider: PoseProvider, *, noise: NoiseModel = NoiseModel(),
                 volume: BoxVolume = BoxVolume(), firmware: FirmwareIdentity = FirmwareIdentity(),
                 first_handle: int = 0x01, max_handles: int = 9) -> None:
        self._provider = provider
        self.noise = noise
        self.volume = volume
        self.firmware = firmware
        self.first_handle = first_handle
        self.max_handles = max_handles
        self._rng = np.random.default_rng(noise.seed)
        self._lines = LineSplitter(max_line=1024)
        self.commands: list[Command] = []     # every command understood, for tests and diagnostics
        self._power_on()

    @property
    def provider(self) -> PoseProvider:
        return self._provider

    @provider.setter
    def provider(self, provider: PoseProvider) -> None:
        """Swap the pose source (hold the server's lock); the current frame is measured again."""
        self._provider = provider
        self._cached = None

    def _power_on(self) -> None:
        self.initialised = False
        self.tracking = False
        self.comm = CommSettings()
        self.ports: dict[int, PortHandle] = {}
        self._clock_origin: float | None = None
        self._frame_offset = 0
        self._cached: tuple[int, dict[int, ToolRecord]] | None = None

    # -- the StreamDevice interface -------------------------------------------------------------------------
    def feed(self, data: bytes, now: float) -> bytes:
        self._touch(now)
        try:
            lines = self._lines.feed(data)
        except FrameError:
            return encode_error(E.COMMAND_TOO_LONG)
        return b"".join(self._answer(line.strip(b"\n"), now) for line in lines)

    def tick(self, now: float) -> bytes:
        self._touch(now)
        return b""       # a tracker never sends unsolicited bytes

    # -- time -----------------------------------------------------------------------------------------------
    def _touch(self, now: float) -> None:
        if self._clock_origin is None:
            self._clock_origin = now

    def frame_number(self, now: float) -> int:
        """The 60 Hz frame counter at ``now`` (it runs from power-on; ``TSTART:80`` sets it to zero)."""
        self._touch(now)
        assert self._clock_origin is not None
        return max(0, int(math.floor((now - self._clock_origin) * FRAME_RATE_HZ)) - self._frame_offset)

    # -- commands -------------------------------------------------------------------------------------------
    def _answer(self, line: bytes, now: float) -> bytes:
        if not line:
            return b""
        try:
            command = decode_command(line)
        except CrcError:
            log.debug("bad CRC on %r", line)
            return encode_error(E.BAD_COMMAND_CRC)
        except FrameError:
            return encode_error(E.INVALID_COMMAND)
        self.commands.append(command)
        handler = getattr(self, f"_cmd_{command.name.lower()}", None)
        if handler is None:
            return encode_error(E.INVALID_COMMAND)
        if command.name not in ("TX", "BX"):
            self._cached = None     # handles may change: measure the current frame again
        try:
            reply = handler(command.params, now)
        except _Refused as refusal:
            log.debug("%s:%s refused with ERROR%02X: %s", command.name, command.params, refusal.code, refusal)
            return encode_error(refusal.code)
        return reply if isinstance(reply, bytes) else encode_reply(reply)

    def _port(self, params: str) -> PortHandle:
        try:
            handle = parse_handle(params[:2])
        except FrameError as err:
            raise _Refused(E.WRONG_PARAMETER_COUNT, str(err)) from err
        if handle not in self.ports:
            raise _Refused(E.INVALID_PORT_HANDLE, f"handle {handle:02X} is not allocated")
        return self.ports[handle]

    def _require(self, *, initialised: bool = True, tracking: bool | None = None) -> None:
        if initialised and not self.initialised:
            raise _Refused(E.SYSTEM_NOT_INITIALISED, "INIT first")
        if tracking is not None and self.tracking != tracking:
            raise _Refused(E.INVALID_MODE, "tracking" if self.tracking else "not tracking")

    def _cmd_init(self, params: str, now: float) -> str:
        self._require(initialised=False, tracking=False)
        self.initialised = True
        return OKAY

    def _cmd_reset(self, params: str, now: float) -> str:
        self._power_on()
        return RESET

    def _cmd_comm(self, params: str, now: float) -> str:
        try:
            self.comm = parse_comm(params)
        except FrameError as err:
            raise _Refused(E.WRONG_PARAMETER_COUNT if len(params) != 5 else E.BAD_COMM_PARAMETERS, str(err)) from err
        return OKAY

    def _cmd_ver(self, params: str, now: float) -> str:
        if params not in ("0", ""):
            raise _Refused(E.PARAMETER_OUT_OF_RANGE, "only VER:0 is modelled")
        return self.firmware.ver0_text()

    def _cmd_getinfo(self, params: str, now: float) -> str:
        if not self.firmware.getinfo:
            raise _Refused(E.INVALID_COMMAND, "this firmware has no GETINFO")
        if params != "Features.Firmware.Version":
            raise _Refused(E.PARAMETER_OUT_OF_RANGE, f"GETINFO {params!r} is not modelled")
        return f"{params}={self.firmware.firmware_version};3;1;0;12;;Current firmware revision number"

    def _cmd_beep(self, params: str, now: float) -> str:
        if not params.isdigit() or not 1 <= int(params) <= 9:
            raise _Refused(E.PARAMETER_OUT_OF_RANGE, "BEEP wants 1-9")
        return "1"

    def _cmd_phsr(self, params: str, now: float) -> str:
        try:
            mode = PhsrMode(int(params or "0", 16))
        except ValueError as err:
            raise _Refused(E.PARAMETER_OUT_OF_RANGE, f"PHSR mode {params!r}") from err
        wanted = {
            PhsrMode.ALL: lambda p: True,
            PhsrMode.TO_FREE: lambda p: False,           # passive tools never become unoccupied
            PhsrMode.NOT_INITIALISED: lambda p: not p.initialised,
            PhsrMode.INITIALISED_NOT_ENABLED: lambda p: p.initialised and not p.enabled,
            PhsrMode.ENABLED: lambda p: p.enabled,
        }[mode]
        return encode_phsr([PortHandleStatus(p.handle, p.status) for p in self.ports.values() if wanted(p)])

    def _cmd_phrq(self, params: str, now: float) -> str:
        self._require(tracking=False)
        if len(params) != 14:
            raise _Refused(E.WRONG_PARAMETER_COUNT, f"PHRQ wants 14 characters, got {len(params)}")
        free = [h for h in range(self.first_handle, self.first_handle + self.max_handles) if h not in self.ports]
        if not free:
            raise _Refused(E.NO_MORE_HANDLES, "all handles allocated")
        used = {p.tool_index for p in self.ports.values()}
        index = next(i for i in range(len(used) + 1) if i not in used)
        self.ports[free[0]] = PortHandle(free[0], index)
        return f"{free[0]:02X}"

    def _cmd_phf(self, params: str, now: float) -> str:
        port = self._port(params)
        if port.enabled and self.tracking:
            raise _Refused(E.INVALID_MODE, "disable the handle before freeing it while tracking")
        del self.ports[port.handle]
        return OKAY

    def _cmd_pvwr(self, params: str, now: float) -> str:
        self._require(tracking=False)
        port = self._port(params)
        if len(params) != 2 + 4 + 2 * PVWR_CHUNK_BYTES:
            raise _Refused(E.WRONG_PARAMETER_COUNT, f"PVWR wants 134 characters, got {len(params)}")
        try:
            address, data = int(params[2:6], 16), bytes.fromhex(params[6:])
        except ValueError as err:
            raise _Refused(E.PARAMETER_OUT_OF_RANGE, "PVWR data is not hex") from err
        if address % PVWR_CHUNK_BYTES or address >= ROM_MAX_BYTES:
            raise _Refused(E.PARAMETER_OUT_OF_RANGE, f"PVWR address {address:04X}")
        port.rom[address:address + PVWR_CHUNK_BYTES] = data
        port.chunks_written.add(address)
        return OKAY

    def _cmd_pinit(self, params: str, now: float) -> str:
        self._require(tracking=False)
        port = self._port(params)
        if not port.chunks_written or not any(port.rom):
            raise _Refused(E.NO_TOOL_ASSIGNED, f"no tool definition written to handle {port.handle:02X}")
        port.initialised = True
        return OKAY

    def _cmd_pena(self, params: str, now: float) -> str:
        port = self._port(params)
        if len(params) != 3:
            raise _Refused(E.WRONG_PARAMETER_COUNT, "PENA wants handle and priority")
        if params[2].upper() not in "SDB":
            raise _Refused(E.INVALID_PRIORITY, f"priority {params[2]!r}")
        if not port.initialised:
            raise _Refused(E.HANDLE_NOT_INITIALISED, f"handle {port.handle:02X}")
        port.enabled, port.priority = True, params[2].upper()
        return OKAY

    def _cmd_pdis(self, params: str, now: float) -> str:
        port = self._port(params)
        if not port.enabled:
            raise _Refused(E.HANDLE_NOT_ENABLED, f"handle {port.handle:02X}")
        port.enabled = False
        return OKAY

    def _cmd_tstart(self, params: str, now: float) -> str:
        self._require(tracking=False)
        if params not in ("", "80"):
            raise _Refused(E.PARAMETER_OUT_OF_RANGE, f"TSTART option {params!r}")
        if params == "80":
            self._frame_offset = 0
            self._frame_offset = self.frame_number(now)
        self.tracking = True
        return OKAY

    def _cmd_tstop(self, params: str, now: float) -> str:
        self._require(tracking=True)
        self.tracking = False
        return OKAY

    def _cmd_tx(self, params: str, now: float) -> bytes:
        return encode_tx(self._tracking_reply(params, now))

    def _cmd_bx(self, params: str, now: float) -> bytes:
        return encode_bx(self._tracking_reply(params, now))

    # -- tracking data -------------------------------------------------------------------------------------
    def _tracking_reply(self, params: str, now: float) -> TrackingReply:
        self._require(tracking=True)
        try:
            option = parse_reply_option(params)
        except FrameError as err:
            raise _Refused(E.PARAMETER_OUT_OF_RANGE, str(err)) from err
        if option & ~SUPPORTED_OPTIONS:
            raise _Refused(E.PARAMETER_OUT_OF_RANGE, f"reply option {option:04X} is not modelled")
        frame = self.frame_number(now)
        if self._cached is None or self._cached[0] != frame:
            self._cached = (frame, self._measure(frame, now))
        records = []
        for port in sorted(self.ports.values(), key=lambda p: p.handle):
            if not port.initialised:
                continue
            if not port.enabled:
                records.append(ToolRecord(port.handle, ToolState.DISABLED, port_status=port.status, frame=frame))
                continue
            record = self._cached[1].get(port.handle) or ToolRecord(port.handle, ToolState.MISSING,
                                                                    port_status=port.status, frame=frame)
            if record.port_status & PORT_OUT_OF_VOLUME and not option & OPTION_OUT_OF_VOLUME:
                record = ToolRecord(port.handle, ToolState.MISSING, port_status=port.status, frame=frame)
            records.append(record)
        return TrackingReply(tuple(records))

    def _measure(self, frame: int, now: float) -> dict[int, ToolRecord]:
        """One frame's noisy measurement of every enabled tool the provider places (out-of-volume flagged)."""
        poses = self._provider(now)
        measured: dict[int, ToolRecord] = {}
        for port in self.ports.values():
            pose = poses.get(port.tool_index) if port.enabled else None
            if pose is None:
                continue
            rotation = as_rotation(pose[0])
            t_true = np.asarray(pose[1], float).reshape(3)
            sigma_t = self.noise.position_rms_mm / math.sqrt(3.0)
            sigma_r = math.radians(self.noise.rotation_rms_deg) / math.sqrt(3.0)
            t = t_true + self._rng.normal(0.0, sigma_t, 3)
            q = (Rotation.from_rotvec(self._rng.normal(0.0, sigma_r, 3)) * rotation).as_quat(scalar_first=True)
            q = -q if q[0] < 0 else q            # a tracker reports the quaternion with q0 >= 0
            rms = abs(self._rng.normal(self.noise.fit_rms_mm, 0.1 * self.noise.fit_rms_mm))
            status = port.status | (0 if self.volume.contains(t_true) else PORT_OUT_OF_VOLUME)
            measured[port.handle] = ToolRecord(port.handle, ToolState.VALID, tuple(float(v) for v in q),
                                               tuple(float(v) for v in t), float(rms), status, frame)
        return measured


def make_default_fake(pose: Sequence[float] | None = None, *, seed: int | None = None) -> NdiTrackerFake:
    """The tracker ``appliance loopback ots`` serves: every loaded tool at ``pose`` = (x, y, z, qw, qx, qy, qz).

    Without a pose, tools sit 1.5 m in front of the camera, unrotated (inside the Polaris volume).
    """
    values = tuple(pose) if pose is not None else (0.0, 0.0, -1500.0, 1.0, 0.0, 0.0, 0.0)
    if len(values) != 7:
        raise ValueError(f"a pose is x,y,z,qw,qx,qy,qz (7 numbers), got {len(values)}")
    quaternion = np.asarray(values[3:], float)
    norm = float(np.linalg.norm(quaternion))
    if not norm > 0:
        raise ValueError("the pose quaternion is zero")
    return NdiTrackerFake(FixedPose(quaternion / norm, values[:3]), noise=NoiseModel(seed=seed))


def synthetic_rom(name: str = "LOOPBACK-TOOL", markers_mm: Sequence[Sequence[float]] | None = None) -> bytes:
    """A plausible passive tool definition for tests and demos (not NDI's format, which is proprietary).

    752 bytes: an ASCII header naming the tool, the marker count and float32 marker coordinates, padded;
    the fake stores such bytes exactly as a client uploads them and never interprets them.
    """
    markers = np.asarray(markers_mm if markers_mm is not None else
                         [[0, 0, 0], [0, 50, 0], [0, 0, 88], [-40, 0, 60]], np.float32)
    header = f"NDI-LIKE SROM (synthetic)\0{name}\0".encode("ascii").ljust(64, b"\0")
    body = bytes([len(markers)]) + markers.tobytes()
    return (header + body).ljust(752, b"\xff")
