"""Frames from a V4L2 video capture card (a fluoroscope's video output) through OpenCV's V4L2 backend.

URL: ``v4l2:///dev/video0`` or ``v4l2://0`` (index), with ``?width=..&height=..&fps=..&bits=8|16&plane=p``.
``bits=16`` asks the card for 16-bit grayscale (V4L2 ``Y16``) with OpenCV's RGB conversion off; 8-bit
asks for ``GREY``. What the card actually delivers wins: colour frames are converted to 8-bit gray, a raw
Y16 buffer is reinterpreted as little-endian uint16, and a mismatch with the request is logged once.

Frame numbers are counted by this driver (OpenCV does not expose the V4L2 buffer sequence), so drops
inside the kernel's queue are not visible; the device time is the V4L2 buffer timestamp OpenCV reports
(``CAP_PROP_POS_MSEC``) when it has one, else the host time. Opening checks what OpenCV cannot tell apart:
a missing node (DeviceNotFoundError), no access (DevicePermissionError: group ``video``), OpenCV built
without V4L2 (DeviceNotFoundError), and a node that exists but will not capture (DeviceBusyError: most
often another program is streaming from it).
"""
from __future__ import annotations

import glob
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from drivers.errors import DeviceBusyError, DeviceNotFoundError, DevicePermissionError, InputDataError
from drivers.frame_source import Frame, FrameSource, SourceUrl, check_known_keys, query_float, query_int

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class V4l2Device:
    path: str
    name: str | None     # the driver's card name from sysfs

    @property
    def url(self) -> str:
        return f"v4l2://{self.path}"


def list_v4l2_devices(pattern: str = "/dev/video*") -> list[V4l2Device]:
    """Video device nodes present, with their sysfs names (capture and metadata nodes alike)."""
    found = []
    for path in sorted(glob.glob(pattern), key=lambda p: (len(p), p)):
        name_file = Path("/sys/class/video4linux") / Path(path).name / "name"
        try:
            name = name_file.read_text(encoding="utf-8").strip()
        except OSError:
            name = None
        found.append(V4l2Device(path, name))
    return found


def v4l2_backend_available() -> bool:
    import cv2

    return bool(cv2.videoio_registry.hasBackend(cv2.CAP_V4L2))


def device_path(device: str | int) -> str:
    if isinstance(device, int) or (isinstance(device, str) and device.isdigit()):
        return f"/dev/video{int(device)}"
    return str(device)


def open_v4l2_capture(device: str | int, *, width: int | None = None, height: int | None = None,
                      fps: float | None = None, bits: int = 16, read_timeout_ms: int = 100) -> Any:
    """A ready ``cv2.VideoCapture`` on the V4L2 node, or a DeviceError saying why not."""
    import cv2

    path = device_path(device)
    if not v4l2_backend_available():
        raise DeviceNotFoundError(f"{path}: this OpenCV build has no V4L2 backend "
                                  f"(backends: {[cv2.videoio_registry.getBackendName(b) for b in cv2.videoio_registry.getCameraBackends()]})")
    if not os.path.exists(path):
        present = ", ".join(d.path for d in list_v4l2_devices()) or "none"
        raise DeviceNotFoundError(f"{path}: no such video device (present: {present}); is the capture card plugged in?")
    if not os.access(path, os.R_OK | os.W_OK):
        raise DevicePermissionError(f"{path}: permission denied; add your user to group 'video' "
                                    f"(sudo usermod -aG video $USER, then log in again)")
    capture = cv2.VideoCapture(path, cv2.CAP_V4L2)
    if not capture.isOpened():
        capture.release()
        raise DeviceBusyError(f"{path}: V4L2 will not capture from it: another program is probably streaming "
                              f"from it (`fuser {path}`), or it is not a capture node")
    fourcc = "Y16 " if bits == 16 else "GREY"
    capture.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*fourcc))
    if bits == 16:
        capture.set(cv2.CAP_PROP_CONVERT_RGB, 0)
    if width:
        capture.set(cv2.CAP_PROP_FRAME_WIDTH, width)
    if height:
        capture.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
    if fps:
        capture.set(cv2.CAP_PROP_FPS, fps)
    # Short backend timeouts keep read() close to its own deadline (it retries until then).
    capture.set(cv2.CAP_PROP_READ_TIMEOUT_MSEC, read_timeout_ms)
    return capture


class V4l2Source(FrameSource):
    """One capture card as a frame source; ``opener`` returns a ready capture (``open_v4l2_capture``)."""

    def __init__(self, opener: Callable[[], Any], *, plane: str = "p", name: str = "v4l2", bits: int = 16,
                 width: int = 0, height: int = 0) -> None:
        if bits not in (8, 16):
            raise InputDataError(f"{name}: bits must be 8 or 16, got {bits}")
        super().__init__(plane=plane, name=name, pixel_format="mono16" if bits == 16 else "mono8")
        self._opener = opener
        self._capture: Any = None
        self._requested = (width, height)
        self._number = 0
        self._warned = False

    def _open_internal(self) -> None:
        import cv2

        self._capture = self._opener()
        self.width = int(self._capture.get(cv2.CAP_PROP_FRAME_WIDTH)) or self._requested[0]
        self.height = int(self._capture.get(cv2.CAP_PROP_FRAME_HEIGHT)) or self._requested[1]
        self._number = 0

    def _close_internal(self) -> None:
        if self._capture is not None:
            self._capture.release()
            self._capture = None

    def _read_internal(self, deadline: float) -> Frame | None:
        import cv2

        while time.monotonic() < deadline:
            ok, raw = self._capture.read()
            if not ok or raw is None:
                continue        # the backend's own read timeout expired; try again until our deadline
            host = time.monotonic()
            image = self._convert(raw)
            stamp_ms = float(self._capture.get(cv2.CAP_PROP_POS_MSEC) or 0.0)
            number = self._number
            self._number += 1
            return Frame(image=image, plane=self.plane, number=number,
                         device_time_s=stamp_ms / 1000.0 if stamp_ms > 0 else host, host_time_s=host,
                         exposure_s=None, pixel_format=self.pixel_format)
        return None

    def _convert(self, raw: np.ndarray) -> np.ndarray:
        import cv2

        if raw.dtype == np.uint8 and raw.ndim == 2 and raw.shape[0] == 1 and raw.size == self.width * self.height * 2:
            image = raw.view("<u2").reshape(self.height, self.width)     # raw Y16 buffer
        elif raw.ndim == 3:
            image = cv2.cvtColor(raw, cv2.COLOR_BGR2GRAY)
        else:
            image = raw
        fmt = "mono16" if image.dtype == np.uint16 else "mono8"
        if fmt != self.pixel_format:
            if not self._warned:
                log.warning("%s: asked for %s, the card delivers %s; using %s", self.name, self.pixel_format, fmt, fmt)
                self._warned = True
            self.pixel_format = fmt
        if (image.shape[1], image.shape[0]) != (self.width, self.height):
            self.height, self.width = image.shape     # the driver negotiated another size than it reported
        return np.ascontiguousarray(image)


def v4l2_source_from_url(url: SourceUrl, **options: Any) -> V4l2Source:
    """``v4l2:///dev/video0`` / ``v4l2://0`` [``?width=&height=&fps=&bits=&plane=``] -> a V4l2Source (not open)."""
    check_known_keys(url, {"width", "height", "fps", "bits", "plane"})
    device = (url.netloc + url.path) if url.netloc else url.path
    if not device:
        raise InputDataError(f"frame source {url.text!r}: name a device, e.g. v4l2:///dev/video0 or v4l2://0")
    bits = query_int(url, "bits", 16) or 16
    width, height = query_int(url, "width", None), query_int(url, "height", None)
    fps = query_float(url, "fps", None)
    path = device_path(device)

    def opener() -> Any:
        return open_v4l2_capture(path, width=width, height=height, fps=fps, bits=bits)

    kwargs: dict[str, Any] = {"plane": url.take("plane", "p"), "name": f"v4l2:{path}", "bits": bits,
                              "width": width or 0, "height": height or 0}
    kwargs.update(options)
    return V4l2Source(opener, **kwargs)
