"""Driver of the USB X-ray frame grabber (protocol in ``firmware_protocol.usb_grabber``), through pyusb.

:func:`find_grabber` finds the device (by VID:PID and optionally serial number) with ``usb.core.find``
and translates pyusb's failures into appliance errors; :class:`UsbGrabber` takes that ready
``usb.core.Device`` (tests hand it one found through the fake backend of
``drivers.loopback.usb_backend``; the bench, one found through libusb). Constructing it asks the
grabber who it is (IDENTIFY: plane, size, pixel formats), so a source knows its plane before it is
opened; on open it claims the vendor interface, sets rate and exposure when asked and starts
acquisition (STOP and release on close); ``read``
pulls bulk transfers of any size into a :class:`~firmware_protocol.usb_grabber.FrameAssembler`, which
hands on only frames whose header and payload CRCs check out (the payload CRC runs transfer by transfer, so
after the last one only its own bytes are checked). Transfers land in pooled buffers lent to the assembler:
a frame inside one transfer is handed on as a view on it, and a buffer is read into again only once no
frame or array refers to it. Transfers are 64 KiB unless the URL asks otherwise (``transfer_kib``): a
frame streams in over many of them at the link's rate, and each is checked as it comes, so when the last
byte is in (the frame's host time is stamped when the transfer holding it returns) only that transfer's
bytes are left to check - with one transfer per frame, the whole frame's CRC (~250 us for 1 MB) would come
after the stamp, inside the loop's latency. For the same reason a frame's last transfer is kept small
(``final_transfer``, 4 KiB): when the rest of the frame would fit one transfer, the driver asks for all but
that much, so the frame does not end with a nearly full transfer (768 x 672 mono16 in 64 KiB transfers ends
with 48 KiB, whose copy and CRC, ~25 us, came after the stamp; issue 8). Corrupt headers, bad CRCs and truncated
frames are counted (``counters.corrupt``, details in :attr:`UsbGrabber.link_stats`) and skipped; an
endpoint stall is cleared (CLEAR_FEATURE(HALT)) and the stream resumes at the next frame; a transfer
timeout just means no bytes yet. A vanished device raises :class:`LinkLostError`.

URL: ``usb://VID:PID[?serial=S&plane=p&rate=30&exposure_ms=5&transfer_kib=64]`` (hex VID:PID).
"""
from __future__ import annotations

import array
import errno
import logging
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
import usb.core
import usb.util

from drivers.errors import (
    DeviceBusyError,
    DeviceError,
    DeviceNotFoundError,
    DevicePermissionError,
    DeviceTimeoutError,
    InputDataError,
    LinkLostError,
    ProtocolError,
)
from drivers.frame_source import Frame, FrameSource, SourceUrl, check_known_keys, query_float, query_int
from firmware_protocol import usb_grabber as proto
from firmware_protocol.errors import FrameError

log = logging.getLogger(__name__)

#: Bulk transfer size unless the URL sets ``transfer_kib`` (see the module docstring).
DEFAULT_TRANSFER_BYTES = 64 * 1024
#: At most this many bytes of a frame spanning transfers come in its last transfer (see the module docstring).
FINAL_TRANSFER_BYTES = 4 * 1024

UDEV_HINT = ("install the udev rule config/udev/99-xray-grabber.rules (sudo cp it to /etc/udev/rules.d/, "
             "then `sudo udevadm control --reload && sudo udevadm trigger`) and add your user to group 'plugdev'")


@dataclass(frozen=True)
class GrabberInfo:
    vendor_id: int
    product_id: int
    serial: str | None
    bus: int | None
    address: int | None

    @property
    def url(self) -> str:
        query = f"?serial={self.serial}" if self.serial else ""
        return f"usb://{self.vendor_id:04x}:{self.product_id:04x}{query}"


@dataclass
class UsbLinkStats:
    transfers: int = 0
    bytes: int = 0
    usb_timeouts: int = 0
    stalls: int = 0
    corrupt_headers: int = 0
    bad_crc: int = 0
    truncated: int = 0
    skipped_bytes: int = 0
    buffers_made: int = 0    # transfer and payload buffers allocated; stops growing unless frames are held long


def _serial_of(device: usb.core.Device) -> str | None:
    try:
        return usb.util.get_string(device, device.iSerialNumber) if device.iSerialNumber else None
    except (usb.core.USBError, ValueError, NotImplementedError):
        return None   # no permission to read strings, or none provided


def _find(backend: Any, vendor_id: int, product_id: int) -> list[usb.core.Device]:
    try:
        return list(usb.core.find(find_all=True, idVendor=vendor_id, idProduct=product_id, backend=backend))
    except usb.core.NoBackendError as err:
        raise DeviceNotFoundError("no USB backend: install libusb-1.0 (apt install libusb-1.0-0)") from err


def list_grabbers(vendor_id: int = proto.VENDOR_ID, product_id: int = proto.PRODUCT_ID,
                  backend: Any = None) -> list[GrabberInfo]:
    """Grabbers present on the USB bus (serial None when the OS denies reading it)."""
    return [GrabberInfo(dev.idVendor, dev.idProduct, _serial_of(dev), dev.bus, dev.address)
            for dev in _find(backend, vendor_id, product_id)]


def find_grabber(vendor_id: int = proto.VENDOR_ID, product_id: int = proto.PRODUCT_ID, serial: str | None = None,
                 backend: Any = None) -> usb.core.Device:
    """The grabber with this VID:PID (and serial, when given), or DeviceNotFoundError naming what exists."""
    devices = _find(backend, vendor_id, product_id)
    name = f"usb://{vendor_id:04x}:{product_id:04x}" + (f"?serial={serial}" if serial else "")
    if serial is not None:
        serials = [_serial_of(dev) for dev in devices]
        matches = [dev for dev, found in zip(devices, serials) if found == serial]
        if not matches:
            seen = ", ".join(s or "(unreadable)" for s in serials) or "none"
            hint = f"; {UDEV_HINT}" if any(s is None for s in serials) else ""
            raise DeviceNotFoundError(f"no USB grabber {name}; grabbers with that VID:PID have serials: {seen}{hint}")
        return matches[0]
    if not devices:
        raise DeviceNotFoundError(f"no USB grabber {name} on the bus (plugged in and powered? `lsusb` lists it?)")
    if len(devices) > 1:
        raise DeviceError(f"{len(devices)} grabbers match {name}; choose one with ?serial=...")
    return devices[0]


def translate_usb_error(err: usb.core.USBError, what: str) -> DeviceError:
    code = getattr(err, "errno", None)
    if isinstance(err, usb.core.USBTimeoutError) or code == errno.ETIMEDOUT:
        return DeviceTimeoutError(f"{what}: USB request timed out")
    if code in (errno.EACCES, errno.EPERM):
        return DevicePermissionError(f"{what}: permission denied; {UDEV_HINT}")
    if code == errno.EBUSY:
        return DeviceBusyError(f"{what}: the grabber is busy (another program has claimed it; close it first)")
    if code in (errno.ENODEV, errno.ENOENT, errno.EIO, errno.ESHUTDOWN):
        return LinkLostError(f"{what}: the grabber is gone ({err})")
    return DeviceError(f"{what}: {err}")


class UsbGrabber(FrameSource):
    """One USB grabber as a frame source (see the module docstring)."""

    def __init__(self, device: usb.core.Device, *, plane: str | None = None, rate_hz: float | None = None,
                 exposure_s: float | None = None, transfer_size: int = DEFAULT_TRANSFER_BYTES, poll_s: float = 0.05,
                 max_queued: int = 4, name: str | None = None, final_transfer: int = FINAL_TRANSFER_BYTES) -> None:
        serial = _serial_of(device)
        label = name or f"usb:{device.idVendor:04x}:{device.idProduct:04x}" + (f"/{serial}" if serial else "")
        self.device = device
        self.identity = self._identify(device, label)
        if plane is not None and plane != self.identity.plane:
            raise DeviceError(f"{label}: the grabber identifies as plane {self.identity.plane!r} but plane={plane!r} "
                              f"was asked for; swap the cables/URLs or reconfigure the grabber")
        formats = self.identity.pixel_formats
        fmt = proto.PixelFormat.MONO16 if proto.PixelFormat.MONO16 in formats else proto.PixelFormat.MONO8
        super().__init__(plane=self.identity.plane, name=label, width=self.identity.width,
                         height=self.identity.height, pixel_format=proto.PIXEL_FORMAT_NAMES[fmt])
        self.rate_hz = rate_hz
        self.exposure_s = exposure_s
        self.transfer_size = transfer_size
        self.final_transfer = final_transfer
        self.poll_s = poll_s
        self.max_queued = max_queued
        # Transfers are read into pooled buffers lent to the assembler: a frame that fits one transfer is
        # handed on as a view on it (no copy), and that buffer is read into again only once nothing holds it.
        self._transfers = proto.PayloadBuffers(keep=max_queued + 6, make=lambda n: array.array("B", [0]) * n)
        self._assembler = proto.FrameAssembler(buffers=proto.PayloadBuffers(keep=max_queued + 6))
        self._queue: deque[tuple[proto.AssembledFrame, float]] = deque()
        self._stats = UsbLinkStats()
        self._corrupt_seen = 0
        self._number_base = 0
        self._last_raw: int | None = None

    @staticmethod
    def _identify(device: usb.core.Device, label: str) -> proto.IdentifyReply:
        try:
            data = device.ctrl_transfer(proto.REQUEST_TYPE_IN, proto.Request.IDENTIFY, 0, 0, proto.IDENTIFY_SIZE,
                                        timeout=1000)
            return proto.IdentifyReply.decode(bytes(data))
        except usb.core.USBError as err:
            raise translate_usb_error(err, f"{label}: IDENTIFY") from err
        except FrameError as err:
            raise ProtocolError(f"{label}: IDENTIFY reply is invalid: {err}") from err

    def _control_out(self, request: proto.Request, data: bytes = b"") -> None:
        try:
            self.device.ctrl_transfer(proto.REQUEST_TYPE_OUT, request, 0, 0, data, timeout=1000)
        except usb.core.USBError as err:
            raise translate_usb_error(err, f"{self.name}: {request.name}") from err

    def status(self) -> proto.StatusReply:
        try:
            data = self.device.ctrl_transfer(proto.REQUEST_TYPE_IN, proto.Request.GET_STATUS, 0, 0,
                                             proto.STATUS_SIZE, timeout=1000)
            return proto.StatusReply.decode(bytes(data))
        except usb.core.USBError as err:
            raise translate_usb_error(err, f"{self.name}: GET_STATUS") from err
        except FrameError as err:
            raise ProtocolError(f"{self.name}: GET_STATUS reply is invalid: {err}") from err

    @property
    def link_stats(self) -> UsbLinkStats:
        a = self._assembler.stats
        s = self._stats
        return UsbLinkStats(s.transfers, s.bytes, s.usb_timeouts, s.stalls, a.corrupt_headers, a.bad_crc,
                            a.truncated, a.skipped_bytes, self._transfers.made + self._assembler.buffers.made)

    def _open_internal(self) -> None:
        try:
            # Setting the configuration again would reset the device; only do it when none is active.
            try:
                active = self.device.get_active_configuration().bConfigurationValue
            except usb.core.USBError as err:
                if getattr(err, "errno", None) in (errno.EACCES, errno.EPERM, errno.ENODEV, errno.EBUSY):
                    raise
                active = None
            if active != 1:
                self.device.set_configuration(1)
            usb.util.claim_interface(self.device, proto.INTERFACE_NUMBER)
        except usb.core.USBError as err:
            raise translate_usb_error(err, f"{self.name}: open") from err
        try:
            if self.rate_hz is not None:
                self._control_out(proto.Request.SET_FRAME_RATE, proto.encode_rate(self.rate_hz))
            if self.exposure_s is not None:
                self._control_out(proto.Request.SET_EXPOSURE, proto.encode_exposure(self.exposure_s))
            self._assembler.reset()
            self._queue.clear()
            self._control_out(proto.Request.START)
        except BaseException:
            self._release()
            raise

    def _close_internal(self) -> None:
        try:
            self._control_out(proto.Request.STOP)
        except DeviceError as err:
            log.info("%s: STOP on close failed (%s)", self.name, err)
        self._release()

    def _release(self) -> None:
        try:
            usb.util.release_interface(self.device, proto.INTERFACE_NUMBER)
        except usb.core.USBError:
            pass   # the device may be gone; nothing left to release then
        usb.util.dispose_resources(self.device)

    def _read_internal(self, deadline: float) -> Frame | None:
        while True:
            if self._queue:
                assembled, host_time = self._queue.popleft()
                return self._to_frame(assembled, host_time)
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            timeout_ms = max(1, int(min(remaining, self.poll_s) * 1000))
            if not self._transfer(timeout_ms):
                continue
            # Whatever the assembler rejected is counted once, as corrupt.
            corrupt = self._assembler.stats.corrupt
            if corrupt > self._corrupt_seen:
                self._count_corrupt(corrupt - self._corrupt_seen)
                log.warning("%s: rejected %d corrupt frame(s) (%s)", self.name, corrupt - self._corrupt_seen,
                            self._assembler.stats)
                self._corrupt_seen = corrupt
            while len(self._queue) > self.max_queued:
                # The host fell behind: the oldest frames go (they show as a number gap, i.e. dropped).
                self._queue.popleft()

    def _transfer(self, timeout_ms: int) -> bool:
        """One bulk transfer into a free pooled buffer, fed to the assembler; the frames it completes are
        queued, stamped with the time it returned. False when there was none (timeout, cleared stall).
        A method of its own so that no local name outlives it and keeps the buffer looking in use."""
        size = self.transfer_size
        left = self._assembler.payload_left
        if self.final_transfer < left <= size:
            size = left - self.final_transfer   # the frame's last transfer is then a small one
        buffer = self._transfers.take(size)
        try:
            n = self.device.read(proto.BULK_IN_ENDPOINT, buffer, timeout=timeout_ms)
        except usb.core.USBTimeoutError:
            self._stats.usb_timeouts += 1
            return False
        except usb.core.USBError as err:
            if getattr(err, "errno", None) == errno.EPIPE:
                self._recover_stall()
                return False
            raise translate_usb_error(err, f"{self.name}: bulk read") from err
        now = time.monotonic()
        self._stats.transfers += 1
        self._stats.bytes += n
        for assembled in self._assembler.feed(memoryview(buffer)[:n], lent=True):
            self._queue.append((assembled, now))
        return True

    def _recover_stall(self) -> None:
        self._stats.stalls += 1
        log.warning("%s: bulk endpoint stalled; clearing the halt and resynchronising", self.name)
        try:
            self.device.clear_halt(proto.BULK_IN_ENDPOINT)
        except usb.core.USBError as err:
            raise translate_usb_error(err, f"{self.name}: clearing a stall") from err
        # The frame in flight was aborted by the device; its partial bytes are worthless.
        self._assembler.reset()

    def _to_frame(self, assembled: proto.AssembledFrame, host_time: float) -> Frame:
        header = assembled.header
        if header.plane != self.plane:
            raise ProtocolError(f"{self.name}: frame {header.number} is labelled plane {header.plane!r}, "
                                f"the grabber identified as {self.plane!r}")
        # The device counter is 32 bits; unwrap it so numbers keep increasing over long sessions.
        if self._last_raw is not None and header.number < self._last_raw and self._last_raw - header.number > 1 << 31:
            self._number_base += 1 << 32
        self._last_raw = header.number
        dtype = "<u2" if header.pixel_format == proto.PixelFormat.MONO16 else "u1"
        image = np.frombuffer(assembled.payload, dtype=dtype).reshape(header.height, header.width)
        return Frame(image=image, plane=self.plane, number=self._number_base + header.number,
                     device_time_s=header.device_time_us / 1e6, host_time_s=host_time,
                     exposure_s=header.exposure_us / 1e6, pixel_format=proto.PIXEL_FORMAT_NAMES[header.pixel_format])


def parse_vid_pid(text: str, url: str) -> tuple[int, int]:
    try:
        vid, pid = (int(part, 16) for part in text.split(":"))
    except ValueError as err:
        raise InputDataError(f"frame source {url!r}: expected usb://VID:PID in hex, e.g. usb://1209:0001") from err
    if not (0 <= vid <= 0xFFFF and 0 <= pid <= 0xFFFF):
        raise InputDataError(f"frame source {url!r}: VID and PID are 16-bit hex numbers")
    return vid, pid


def usb_source_from_url(url: SourceUrl, *, backend: Any = None, **options: Any) -> UsbGrabber:
    """``usb://VID:PID[?serial=..&plane=..&rate=..&exposure_ms=..&transfer_kib=..]`` -> a UsbGrabber (not open)."""
    check_known_keys(url, {"serial", "plane", "rate", "exposure_ms", "transfer_kib"})
    vid, pid = parse_vid_pid(url.netloc or url.path.strip("/") or f"{proto.VENDOR_ID:04x}:{proto.PRODUCT_ID:04x}",
                             url.text)
    device = find_grabber(vid, pid, url.take("serial"), backend=backend)
    exposure_ms = query_float(url, "exposure_ms", None)
    kwargs: dict[str, Any] = {
        "plane": url.take("plane"), "rate_hz": query_float(url, "rate", None),
        "exposure_s": None if exposure_ms is None else exposure_ms / 1000.0,
        "transfer_size": (query_int(url, "transfer_kib", DEFAULT_TRANSFER_BYTES // 1024)
                          or DEFAULT_TRANSFER_BYTES // 1024) * 1024,
    }
    kwargs.update(options)
    return UsbGrabber(device, **kwargs)
