"""The frame-source interface every X-ray plane is read through, and ``open_source(url)`` to pick one.

A frame source delivers the frames of one X-ray plane (``"p"`` or ``"q"``), in order, each with its
frame number, the device's timestamp and the host's arrival time. The interface is pinned::

    @dataclass(frozen=True)
    class Frame:
        image: np.ndarray          # (height, width) uint8 or uint16, read-only
        plane: str                 # "p" or "q"
        number: int                # the device's frame counter (same number = same exposure in a biplane pair)
        device_time_s: float       # start of exposure on the device's clock (s); files: recorded or nominal time
        host_time_s: float         # time.monotonic() when the host had the whole frame
        exposure_s: float | None   # exposure time, None when the source does not know it
        pixel_format: str          # "mono8" or "mono16"

    class FrameSource(ABC):
        open() -> None; close() -> None (idempotent); context manager (opens on enter)
        read(timeout_s: float) -> Frame      # DeviceTimeoutError at the deadline, EndOfStream after the last file frame
        width, height, pixel_format, plane, name; counters -> SourceCounters(frames, dropped, corrupt, timeouts)

    open_source(url, **options) -> FrameSource
        usb://VID:PID[?serial=...&plane=p&rate=30&exposure_ms=5]     USB frame grabber (pyusb)
        v4l2:///dev/video0 | v4l2://0 [?width=..&height=..&fps=..&bits=16&plane=p]   capture card (OpenCV V4L2)
        file://DIR?plane=p[&rate=max|recorded|30&loop=1]             biplane folder (DIR/p/NNNNNN.png|tif)
        file://stack.tif | file://run.dcm | file://clip.mp4 [?plane=..&rate=..&loop=..]

Loopback sources (``loopback://``) are fakes: production code never imports them, so ``open_source``
refuses them with a pointer to the device factory, which builds them.

``read`` is a template method: subclasses implement ``_read_internal(deadline)`` and return a frame or
``None`` at the deadline; the base class owns the deadline, validation, counters and logging. Counter
meanings: ``frames`` delivered; ``dropped`` frame numbers missing from the delivered sequence, whatever
the cause (lost on the device, discarded as corrupt, overrun on the host); ``corrupt`` frames or byte
runs the source received and rejected (bad header, bad CRC, truncated); ``timeouts`` reads that hit
their deadline. A number lower than the previous one (a device restart, a looped file) is a restart,
not a drop.
"""
from __future__ import annotations

import logging
import threading
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from types import TracebackType
from typing import Any
from urllib.parse import parse_qsl, urlsplit

import numpy as np

from drivers.errors import ApplianceError, DeviceError, DeviceTimeoutError, InputDataError

log = logging.getLogger(__name__)

PLANES = ("p", "q")
PIXEL_FORMATS = {"mono8": np.dtype(np.uint8), "mono16": np.dtype(np.uint16)}


class EndOfStream(ApplianceError, EOFError):
    """A recorded source (files) has delivered its last frame and does not loop."""


@dataclass(frozen=True)
class Frame:
    """One image of one plane, as delivered by a frame source."""

    image: np.ndarray
    plane: str
    number: int
    device_time_s: float
    host_time_s: float
    exposure_s: float | None
    pixel_format: str

    @property
    def width(self) -> int:
        return int(self.image.shape[1])

    @property
    def height(self) -> int:
        return int(self.image.shape[0])


@dataclass(frozen=True)
class SourceCounters:
    """A snapshot of a source's counters (see the module docstring for what each one counts)."""

    frames: int = 0
    dropped: int = 0
    corrupt: int = 0
    timeouts: int = 0


class FrameSource(ABC):
    """One plane's frames. Subclasses implement ``_open_internal``, ``_close_internal``, ``_read_internal``."""

    def __init__(self, *, plane: str, name: str, width: int = 0, height: int = 0,
                 pixel_format: str = "mono16") -> None:
        if plane not in PLANES:
            raise InputDataError(f"{name}: plane must be one of {PLANES}, got {plane!r}")
        if pixel_format not in PIXEL_FORMATS:
            raise InputDataError(f"{name}: pixel format must be one of {sorted(PIXEL_FORMATS)}, got {pixel_format!r}")
        self.plane = plane
        self.name = name
        # Subclasses learn the size on open (the device or the file says); 0 means "not known yet".
        self.width = width
        self.height = height
        self.pixel_format = pixel_format
        self._is_open = False
        self._lock = threading.Lock()
        self._c_frames = 0
        self._c_dropped = 0
        self._c_corrupt = 0
        self._c_timeouts = 0
        self._last_number: int | None = None

    # -- lifecycle -------------------------------------------------------------------------------
    @property
    def is_open(self) -> bool:
        return self._is_open

    def open(self) -> None:
        if self._is_open:
            return
        self._open_internal()
        self._is_open = True
        log.info("%s: open (%dx%d %s, plane %s)", self.name, self.width, self.height, self.pixel_format, self.plane)

    def close(self) -> None:
        if not self._is_open:
            return
        self._is_open = False
        try:
            self._close_internal()
        finally:
            log.info("%s: closed after %s", self.name, self.counters)

    def __enter__(self) -> FrameSource:
        self.open()
        return self

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None,
                 trace: TracebackType | None) -> None:
        self.close()

    # -- reading ---------------------------------------------------------------------------------
    def read(self, timeout_s: float) -> Frame:
        """The next frame, or DeviceTimeoutError when none is complete within ``timeout_s`` seconds."""
        if not self._is_open:
            raise DeviceError(f"{self.name}: read() on a source that is not open")
        if timeout_s < 0:
            raise ValueError(f"timeout_s must be >= 0, got {timeout_s}")
        deadline = time.monotonic() + timeout_s
        frame = self._read_internal(deadline)
        if frame is None:
            with self._lock:
                self._c_timeouts += 1
            raise DeviceTimeoutError(f"{self.name}: no frame within {timeout_s * 1000:.0f} ms")
        self._check(frame)
        frame.image.setflags(write=False)  # frames are shared by pairer, tracker and recorder
        with self._lock:
            self._c_frames += 1
            if self._last_number is not None:
                gap = frame.number - self._last_number - 1
                if gap > 0:
                    self._c_dropped += gap
                    log.debug("%s: %d frame(s) missing before %d", self.name, gap, frame.number)
                elif gap < -1 or frame.number == self._last_number:
                    log.info("%s: frame number went from %d to %d (restart)", self.name, self._last_number,
                             frame.number)
            self._last_number = frame.number
        log.debug("%s: frame %d t_dev=%.6f", self.name, frame.number, frame.device_time_s)
        return frame

    def _check(self, frame: Frame) -> None:
        # A subclass bug here would hand the tracker a wrong image; fail loudly instead.
        image = frame.image
        expected = PIXEL_FORMATS.get(frame.pixel_format)
        if image.ndim != 2 or image.dtype != expected:
            raise DeviceError(f"{self.name}: frame {frame.number} is {image.dtype}{image.shape}, "
                              f"expected 2-D {expected} for {frame.pixel_format}")
        if frame.plane != self.plane:
            raise DeviceError(f"{self.name}: frame {frame.number} is from plane {frame.plane!r}, source is {self.plane!r}")
        if self.width and self.height and (image.shape[1], image.shape[0]) != (self.width, self.height):
            raise DeviceError(f"{self.name}: frame {frame.number} is {image.shape[1]}x{image.shape[0]}, "
                              f"source announced {self.width}x{self.height}")

    # -- counters --------------------------------------------------------------------------------
    @property
    def counters(self) -> SourceCounters:
        with self._lock:
            return SourceCounters(self._c_frames, self._c_dropped, self._c_corrupt, self._c_timeouts)

    def _count_corrupt(self, n: int = 1) -> None:
        with self._lock:
            self._c_corrupt += n

    def _count_dropped(self, n: int = 1) -> None:
        """For drops a subclass knows about that do not show as a number gap (frames it discarded itself
        after a restart); number gaps are counted by ``read``."""
        with self._lock:
            self._c_dropped += n

    # -- subclass hooks --------------------------------------------------------------------------
    @abstractmethod
    def _open_internal(self) -> None:
        """Acquire the device or file and set width/height/pixel_format."""

    @abstractmethod
    def _close_internal(self) -> None:
        """Release what ``_open_internal`` acquired; must not raise for a device that vanished."""

    @abstractmethod
    def _read_internal(self, deadline: float) -> Frame | None:
        """The next frame, or None once ``time.monotonic()`` passes ``deadline``."""

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name} plane={self.plane} {self.width}x{self.height} {self.pixel_format}>"


# -- URLs ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SourceUrl:
    """A parsed source URL: ``scheme://netloc/path?query``; query values stay strings."""

    scheme: str
    netloc: str
    path: str
    query: dict[str, str]
    text: str

    def take(self, key: str, default: str | None = None) -> str | None:
        return self.query.get(key, default)


def parse_source_url(url: str) -> SourceUrl:
    """Split a source URL, refusing repeated query keys (a typo there would silently win or lose)."""
    parts = urlsplit(url.strip())
    if not parts.scheme:
        raise InputDataError(f"frame source {url!r} has no scheme: use usb://VID:PID, v4l2:///dev/videoN, "
                             f"file://DIR or loopback://")
    query: dict[str, str] = {}
    for key, value in parse_qsl(parts.query, keep_blank_values=True):
        if key in query:
            raise InputDataError(f"frame source {url!r}: query key {key!r} given twice")
        query[key] = value
    return SourceUrl(parts.scheme.lower(), parts.netloc, parts.path, query, url)


def query_float(url: SourceUrl, key: str, default: float | None) -> float | None:
    raw = url.query.get(key)
    if raw is None or raw == "":
        return default
    try:
        return float(raw)
    except ValueError as err:
        raise InputDataError(f"frame source {url.text!r}: {key}={raw!r} is not a number") from err


def query_int(url: SourceUrl, key: str, default: int | None) -> int | None:
    value = query_float(url, key, None)
    if value is None:
        return default
    if value != int(value):
        raise InputDataError(f"frame source {url.text!r}: {key} must be a whole number, got {value}")
    return int(value)


def query_bool(url: SourceUrl, key: str, default: bool) -> bool:
    raw = url.query.get(key)
    if raw is None:
        return default
    if raw.lower() in ("1", "true", "yes", "on", ""):
        return True
    if raw.lower() in ("0", "false", "no", "off"):
        return False
    raise InputDataError(f"frame source {url.text!r}: {key}={raw!r} is not a yes/no value")


def check_known_keys(url: SourceUrl, known: set[str]) -> None:
    unknown = sorted(set(url.query) - known)
    if unknown:
        raise InputDataError(f"frame source {url.text!r}: unknown option(s) {', '.join(unknown)}; "
                             f"known: {', '.join(sorted(known))}")


def open_source(url: str, **options: Any) -> FrameSource:
    """Build (not open) the frame source a URL names; ``options`` go to the source's constructor
    (for example ``backend=`` for a USB source, ``plane=`` to override the URL)."""
    parsed = parse_source_url(url)
    if parsed.scheme == "usb":
        from drivers.usb_grabber import usb_source_from_url
        return usb_source_from_url(parsed, **options)
    if parsed.scheme == "v4l2":
        from drivers.v4l2_source import v4l2_source_from_url
        return v4l2_source_from_url(parsed, **options)
    if parsed.scheme == "file":
        from drivers.file_sources import file_source_from_url
        return file_source_from_url(parsed, **options)
    if parsed.scheme.startswith("loopback"):
        raise DeviceError(f"frame source {url!r} is a loopback fake: it is built by the appliance's device factory "
                          f"(or `appliance grab`), never by production drivers")
    raise InputDataError(f"frame source {url!r}: unknown scheme {parsed.scheme!r}; "
                         f"use usb://VID:PID, v4l2:///dev/videoN, v4l2://N or file://PATH")
