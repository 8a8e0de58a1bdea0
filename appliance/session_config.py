"""Typed model of a session file (``config/sim.yaml``, ``config/bench.yaml``): what one closed-loop run uses.

A session names the robot, the configured coils, the operator's path, the X-ray calibration, the
imaging rate, every device (``kind: loopback`` builds the fakes and the simulated world; the other
kinds open real ports), the controller's tuning, the safety thresholds and the recording. It is
validated once at load (unknown keys rejected, every error names the file and the key path) and
never re-read inside the frame loop.

Relative file names inside a session are resolved against the session file's own folder, so a
session copied next to its coils and calibration files keeps working.
"""
from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator, model_validator

from appliance.config_io import StrictModel, config_path, load_model, validate_model
from appliance.control import FollowerSettings, SafetySettings
from appliance.recognition.settings import RecognitionSettings

SCHEMA_VERSION = 1

Link = Literal["pty", "tcp"]


class RobotSection(StrictModel):
    """Which robot of the catalogue (``robots.yaml``, Table 1 of the seed paper) is steered."""

    id: int = 1
    catalogue: str = "robots.yaml"


class CalibrationPerturbation(StrictModel):
    """How far the appliance's belief of the X-ray geometry is from the simulated truth (seeded)."""

    rotation_deg: float = Field(default=0.0, ge=0.0, le=5.0)
    translation_mm: float = Field(default=0.0, ge=0.0, le=20.0)
    seed: int = 0


class CalibrationSection(StrictModel):
    """``source: file`` reads a calibration file (bench); ``nominal`` takes the simulated views as designed,
    optionally perturbed (simulation only: there are no designed views on a bench)."""

    source: Literal["file", "nominal"] = "file"
    file: str | None = None
    perturbation: CalibrationPerturbation = CalibrationPerturbation()

    @model_validator(mode="after")
    def _file_given(self) -> CalibrationSection:
        if self.source == "file" and not self.file:
            raise ValueError("source 'file' needs 'file: PATH' (a calibration YAML)")
        return self


class ImagingSection(StrictModel):
    """The fluoroscope: frame rate, and in simulation the true geometry the frames are rendered with."""

    fps: float = Field(default=30.0, gt=0.0, le=1000.0)
    exposure_ms: float = Field(default=5.0, ge=0.0, le=100.0)
    # Simulated system only (a bench's geometry is its calibration):
    image_size: tuple[int, int] = (768, 672)
    sod_mm: float = Field(default=500.0, gt=0.0)
    sdd_mm: float = Field(default=1000.0, gt=0.0)
    fov_mm: tuple[float, float] = (150.0, 130.0)
    separation_deg: float = Field(default=90.0, gt=0.0, lt=180.0)
    #: Both C-arms turned together about the vertical axis (0: plane p's source on the world's -x axis).
    azimuth_deg: float = Field(default=0.0, ge=-180.0, le=180.0)
    elevation_deg: float = Field(default=0.0, ge=-60.0, le=60.0)
    photons_per_pixel: float = Field(default=2000.0, gt=0.0)
    vessel_attenuation_per_mm: float = Field(default=0.06, ge=0.0)

    @field_validator("image_size")
    @classmethod
    def _size(cls, size: tuple[int, int]) -> tuple[int, int]:
        if min(size) < 32 or max(size) > 4096:
            raise ValueError(f"image_size must be between 32 and 4096 px per side, got {list(size)}")
        return size


class AmplifierDevice(StrictModel):
    """The EMA amplifier: ``serial`` opens ``port`` (a tty, a pty, ``host:port``); ``loopback`` serves the
    fake amplifier on a pty or TCP ``link`` with the coils' electrical values."""

    kind: Literal["serial", "loopback"]
    port: str | None = None
    link: Link = "pty"
    baudrate: int = Field(default=115200, gt=0)
    watchdog_ms: int = Field(default=200, ge=10, le=10_000)
    ack_timeout_ms: float = Field(default=50.0, gt=0.0)
    retries: int = Field(default=2, ge=0, le=10)
    # Limits set on the amplifier at start; default: the coils file's per-coil and slew limits.
    max_current_a: float | None = Field(default=None, gt=0.0)
    slew_a_per_s: float | None = Field(default=None, gt=0.0)
    # Loopback only: the fake's rating and its coils' thermal path.
    rated_current_a: float = Field(default=12.0, gt=0.0)
    thermal_resistance_k_per_w: float = Field(default=0.25, gt=0.0)

    @model_validator(mode="after")
    def _port_given(self) -> AmplifierDevice:
        if self.kind == "serial" and not self.port:
            raise ValueError("kind 'serial' needs 'port' (e.g. /dev/ttyACM0 or 192.168.1.20:7001)")
        return self


class XrayDevice(StrictModel):
    """The two X-ray planes: ``sources`` are frame-source URLs (``usb://``, ``v4l2://``, ``file://``);
    ``loopback`` renders the simulated world and serves it through the fake USB grabbers (``link: usb``,
    the real pyusb driver on a fake backend) or the in-process loopback grabber (``link: grabber``)."""

    kind: Literal["sources", "loopback"]
    sources: dict[str, str] | None = None
    link: Literal["usb", "grabber"] = "usb"
    match: Literal["number", "time"] = "number"
    max_skew_ms: float = Field(default=5.0, gt=0.0)
    startup_timeout_ms: float = Field(default=3000.0, gt=0.0)

    @model_validator(mode="after")
    def _sources_given(self) -> XrayDevice:
        if self.kind == "sources" and (not self.sources or sorted(self.sources) != ["p", "q"]):
            raise ValueError("kind 'sources' needs 'sources: {p: URL, q: URL}'")
        return self


class OtsDevice(StrictModel):
    """The optical tracker (validation only, never in the control path): ``none``, ``serial`` (NDI Polaris on
    a tty, Vega on ``host:port``) with a tool definition ``rom``, or ``loopback`` (the fake, tracking a tool
    rigidly attached to the simulated robot's holder)."""

    kind: Literal["none", "serial", "loopback"] = "none"
    port: str | None = None
    link: Link = "pty"
    rom: str | None = None
    mode: Literal["tx", "bx"] = "bx"
    rate_hz: float = Field(default=60.0, gt=0.0, le=250.0)
    baudrate: int = Field(default=115200, gt=0)

    @model_validator(mode="after")
    def _port_given(self) -> OtsDevice:
        if self.kind == "serial" and not (self.port and self.rom):
            raise ValueError("kind 'serial' needs 'port' and 'rom' (the tool definition file)")
        return self


class DevicesSection(StrictModel):
    amplifier: AmplifierDevice
    xray: XrayDevice
    ots: OtsDevice = OtsDevice()


class LoopSection(StrictModel):
    """The frame loop's own timing and safety beyond the supervisor's thresholds."""

    #: How long one step waits for a new biplane pair before it counts a missing frame.
    pair_timeout_ms: float = Field(default=500.0, gt=0.0)
    #: No new pair for this long (on the loop's clock) means the imaging chain stopped: latched stop.
    frame_timeout_ms: float = Field(default=250.0, gt=0.0)
    #: Device status (temperatures, state) is read and recorded every this many frames.
    status_every_frames: int = Field(default=30, ge=1)
    #: Stop the run when the robot reaches the end of the path.
    stop_at_end: bool = True


class SimulationSection(StrictModel):
    """The simulated world's settings (``kind: loopback`` devices only)."""

    seed: int = 0
    #: Time from the start of an exposure to the command reaching the amplifier, modelled on the
    #: simulated clock (exposure + read-out + recognition + control). The wall-clock latency is measured.
    loop_latency_ms: float = Field(default=25.0, ge=0.0, le=1000.0)
    #: The world is stepped in pieces of at most this much, each with the amplifier's measured currents.
    substep_ms: float = Field(default=5.0, gt=0.0, le=100.0)
    #: Simulated time limit of ``appliance sim`` (the robot normally reaches the path's end first).
    max_seconds: float = Field(default=60.0, gt=0.0)
    #: After the loop has stopped the world keeps running this long (simulated) to watch the coils settle.
    settle_ms: float = Field(default=500.0, ge=0.0)
    #: With two or more CPU cores, the simulated lab's process (world, device fakes, renderer) runs on a core
    #: of its own and the appliance's threads on the others, as a bench's devices are other machines
    #: (:mod:`appliance.core_placement`: on 2 cores the sim loop's p99 1.43 -> 1.00 ms). False: the
    #: scheduler's placement.
    lab_own_core: bool = True


class RecordingSection(StrictModel):
    enabled: bool = True
    #: Folder for recordings (relative: to the working directory); one MCAP file per session.
    folder: str = "runs"
    #: Keep every n-th biplane pair's images (1: all); postures, commands and currents are always kept.
    frames_every: int = Field(default=10, ge=1)


class SessionConfig(StrictModel):
    """The whole session file."""

    schema_version: int
    name: str = "session"
    robot: RobotSection = RobotSection()
    coils: str = "coils.yaml"
    #: The operator's path (``path`` section) and, in simulation, the vessel phantom and world settings.
    vessel: str = "vessel.yaml"
    calibration: CalibrationSection
    imaging: ImagingSection = ImagingSection()
    devices: DevicesSection
    #: Posture recognition tuning; ``dark_level`` 0 means "the calibration's metadata.detector.dark_level".
    recognition: RecognitionSettings = RecognitionSettings()
    control: FollowerSettings = FollowerSettings()
    safety: SafetySettings = SafetySettings()
    loop: LoopSection = LoopSection()
    simulation: SimulationSection = SimulationSection()
    recording: RecordingSection = RecordingSection()

    @field_validator("schema_version")
    @classmethod
    def _known_version(cls, version: int) -> int:
        if version != SCHEMA_VERSION:
            raise ValueError(f"unsupported schema_version {version}; this appliance reads {SCHEMA_VERSION}")
        return version

    @model_validator(mode="after")
    def _consistent(self) -> SessionConfig:
        loopback = self.is_simulation
        kinds = {"amplifier": self.devices.amplifier.kind, "xray": self.devices.xray.kind,
                 "ots": self.devices.ots.kind}
        mixed = [name for name, kind in kinds.items() if kind not in ("loopback", "none")] if loopback else \
            [name for name, kind in kinds.items() if kind == "loopback"]
        if mixed:
            # The fakes share one simulated world; a real device cannot sit in it (and vice versa).
            raise ValueError(f"devices: either every device is loopback (simulation) or none is; "
                             f"{', '.join(mixed)} differ from the X-ray kind {self.devices.xray.kind!r}")
        if self.calibration.source == "nominal" and not loopback:
            raise ValueError("calibration.source 'nominal' exists only in simulation (a bench needs a calibration file)")
        return self

    @property
    def is_simulation(self) -> bool:
        return self.devices.xray.kind == "loopback"


class Session:
    """A validated session file and where its relative file names point."""

    def __init__(self, config: SessionConfig, source: Path) -> None:
        self.config = config
        self.source = source
        self.folder = source.parent

    def resolve(self, name: str) -> Path:
        """A file named in the session: absolute as given, else next to the session file, else in ``config/``."""
        path = Path(name).expanduser()
        if path.is_absolute():
            return path
        beside = self.folder / path
        return beside if beside.exists() else config_path(name)

    @property
    def coils_path(self) -> Path:
        return self.resolve(self.config.coils)

    @property
    def vessel_path(self) -> Path:
        return self.resolve(self.config.vessel)

    @property
    def robots_path(self) -> Path:
        return self.resolve(self.config.robot.catalogue)


def load_session(path: str | Path | None = None) -> Session:
    """Read and validate a session file (default: the shipped ``config/sim.yaml``)."""
    source = Path(path) if path is not None else config_path("sim.yaml")
    return Session(load_model(source, SessionConfig), source.resolve())


def session_from_mapping(data: object, source: str | Path) -> Session:
    """Validate an already-parsed session (tests, tools that derive a session from another); relative file
    names resolve as if the session were the file ``source``."""
    source = Path(source)
    return Session(validate_model(SessionConfig, data, str(source)), source.resolve())
