"""A fake pyusb backend presenting USB X-ray frame grabbers, so the real ``usb.core`` path runs in tests.

:class:`FakeGrabberBackend` implements ``usb.backend.IBackend``: ``usb.core.find(backend=fake)``
enumerates its :class:`FakeGrabberDevice` objects through their descriptors (device, configuration,
one vendor interface, one bulk-IN endpoint 0x81, string descriptors with the serial number), and the
driver opens, configures, claims, sends vendor control requests and reads bulk transfers exactly as
with libusb. Each device streams the frames of a :class:`FrameFeed` (a :class:`PatternFeed` here, or the
rendered scene of ``loopback_grabber.SceneFeed``) in the byte format of ``firmware_protocol.usb_grabber``.

Device behaviour modelled: frames become available at their exposure time plus exposure on an injected
clock (``realtime=True``) or at once (``realtime=False``, for throughput); a bulk-IN transfer ends at the
end of a frame (the short packet that ends a USB transfer) or when the host's buffer is full, so frames
span transfers; with ``link_bytes_per_s`` the bytes cross the link at that rate on the wall clock (a
transfer returns once its last byte could have arrived: the link carries a frame's bytes only from the
moment the frame is read out and a transfer is pending, and one transfer after the other), so the host
checks a frame's earlier transfers while its later ones are still on the wire, as with a real link;
without it (the default) a transfer returns as soon as the host asks (throughput bound by the host); a
small on-device buffer overruns when the host does not read (counted in GET_STATUS);
STOP discards the frame in flight. Injected faults, per frame number (:meth:`FakeGrabberDevice.schedule`)
or at random (``fault_rates``): a corrupt header, a bad payload CRC, a truncated frame, random short
transfers, garbage between frames, an endpoint stall (EPIPE until CLEAR_FEATURE(HALT), then the device
resumes at the next frame) and a transfer timeout. Host-side conditions: permission denied on open,
the interface already claimed (busy), and unplugging (ENODEV from then on).

Not modelled: zero-length packets at frame ends that fill a whole number of packets, the bus's packet
scheduling (``link_bytes_per_s`` is one steady rate per device), alternate settings, hot-plug events,
interrupt endpoints.
"""
from __future__ import annotations

import errno
import logging
import math
import threading
import time
import zlib
from collections import OrderedDict
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from enum import Enum
from types import SimpleNamespace
from typing import Any, Protocol

import numpy as np
import usb.backend
import usb.core

from firmware_protocol import usb_grabber as proto

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DeviceFrame:
    number: int
    device_time_s: float      # start of exposure on the device clock (0 = START)
    exposure_s: float
    image: np.ndarray         # (h, w) uint8 or uint16


class FrameFeed(Protocol):
    plane: str
    width: int
    height: int
    pixel_format: str
    rate_hz: float
    exposure_s: float

    def frame(self, number: int) -> DeviceFrame: ...


class PatternFeed:
    """Deterministic test frames: frame ``n`` is ``pool[n % len(pool)]`` of seeded random images
    (so a test can compare delivered pixels with :meth:`frame`), on a fixed-rate schedule."""

    def __init__(self, plane: str = "p", width: int = 64, height: int = 48, *, rate_hz: float = 1000.0,
                 exposure_s: float = 0.0005, pixel_format: str = "mono16", pool: int = 4, seed: int = 0) -> None:
        self.plane, self.width, self.height, self.pixel_format = plane, width, height, pixel_format
        self.rate_hz, self.exposure_s = rate_hz, exposure_s
        rng = np.random.default_rng(seed)
        dtype, top = (np.uint16, 65536) if pixel_format == "mono16" else (np.uint8, 256)
        self.pool = [rng.integers(0, top, size=(height, width), dtype=dtype) for _ in range(pool)]

    def frame(self, number: int) -> DeviceFrame:
        return DeviceFrame(number, number / self.rate_hz, self.exposure_s, self.pool[number % len(self.pool)])


class Fault(Enum):
    CORRUPT_HEADER = "corrupt_header"   # one header byte flipped: header CRC fails
    BAD_CRC = "bad_crc"                 # one payload byte flipped: payload CRC fails
    TRUNCATE = "truncate"               # the frame ends halfway through its payload
    SHORT_TRANSFERS = "short_transfers" # the frame is delivered in many small, odd-sized transfers (valid)
    GARBAGE = "garbage"                 # random bytes before the frame
    STALL = "stall"                     # the endpoint halts halfway through the frame (frame lost)
    TIMEOUT = "timeout"                 # one transfer times out halfway through the frame (frame intact)


_LOST = {Fault.CORRUPT_HEADER, Fault.BAD_CRC, Fault.TRUNCATE, Fault.STALL}


def lost_by(fault: Fault | None) -> bool:
    """Whether a frame with this fault never reaches the host intact."""
    return fault in _LOST


def _usb_error(code: int, text: str) -> usb.core.USBError:
    if code == errno.ETIMEDOUT:
        return usb.core.USBTimeoutError(text, -7, code)
    return usb.core.USBError(text, None, code)


class FakeGrabberDevice:
    """The device side of one USB grabber (see the module docstring)."""

    def __init__(self, feed: FrameFeed, *, serial: str = "XRG-0001", vendor_id: int = proto.VENDOR_ID,
                 product_id: int = proto.PRODUCT_ID, realtime: bool = True, buffer_frames: int = 4,
                 fault_rates: dict[Fault, float] | None = None, seed: int | None = None,
                 clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep,
                 bus: int = 1, address: int = 5, link_bytes_per_s: float | None = None,
                 link_clock: Callable[[], float] = time.monotonic,
                 link_sleep: Callable[[float], None] = time.sleep) -> None:
        if link_bytes_per_s is not None and not link_bytes_per_s > 0:
            raise ValueError(f"link_bytes_per_s must be > 0 (or None: unpaced), got {link_bytes_per_s}")
        self.feed = feed
        self.serial = serial
        self.realtime = realtime
        self.link_bytes_per_s = link_bytes_per_s
        # The link's time is the wall clock (injectable for tests): it is about the host's CPU keeping up.
        self._link_clock, self._link_sleep = link_clock, link_sleep
        self._link_free = -math.inf      # link clock reading when the link has carried all it was given
        self.buffer_frames = buffer_frames
        self.fault_rates = dict(fault_rates or {})
        self._rng = np.random.default_rng(seed)
        self._clock, self._sleep = clock, sleep
        self._lock = threading.RLock()
        self._scheduled: dict[int, Fault] = {}
        self.faults_injected: dict[int, Fault] = {}   # frame number -> fault actually applied
        # Every control transfer as seen on the wire: (bmRequestType, bRequest, wValue, wIndex, data stage).
        self.control_log: list[tuple[int, int, int, int, bytes]] = []
        self.strings = {1: "Microrobot Lab", 2: "X-ray frame grabber", 3: serial}
        self.device_descriptor = SimpleNamespace(
            bLength=18, bDescriptorType=1, bcdUSB=0x0200, bDeviceClass=0, bDeviceSubClass=0, bDeviceProtocol=0,
            bMaxPacketSize0=64, idVendor=vendor_id, idProduct=product_id, bcdDevice=0x0100, iManufacturer=1,
            iProduct=2, iSerialNumber=3, bNumConfigurations=1, address=address, bus=bus, port_number=address,
            port_numbers=(address,), speed=3)
        self.configuration_descriptor = SimpleNamespace(
            bLength=9, bDescriptorType=2, wTotalLength=25, bNumInterfaces=1, bConfigurationValue=1,
            iConfiguration=0, bmAttributes=0x80, bMaxPower=250, extra_descriptors=[])
        self.interface_descriptor = SimpleNamespace(
            bLength=9, bDescriptorType=4, bInterfaceNumber=proto.INTERFACE_NUMBER, bAlternateSetting=0,
            bNumEndpoints=1, bInterfaceClass=proto.INTERFACE_CLASS, bInterfaceSubClass=0, bInterfaceProtocol=0,
            iInterface=0, extra_descriptors=[])
        self.endpoint_descriptor = SimpleNamespace(
            bLength=7, bDescriptorType=5, bEndpointAddress=proto.BULK_IN_ENDPOINT, bmAttributes=0x02,
            wMaxPacketSize=512, bInterval=0, bRefresh=0, bSynchAddress=0, extra_descriptors=[])
        # Host-visible state.
        self.configuration = 1          # the OS configures a device on enumeration, as Linux does
        self.claimed_by: object | None = None
        self.permission_denied = False
        self.unplugged = False
        # Stream state.
        self.streaming = False
        self.halted = False
        self.frames_sent = 0
        self.frames_overrun = 0
        self._t0 = 0.0
        self._next_number = 0
        self._segments: list[memoryview] = []   # the frame on the wire: header, payload (no copy of the pixels)
        self._length = 0
        self._offset = 0
        self._fault: Fault | None = None
        self._fault_at = -1              # byte offset where a stall/timeout fires
        self._payloads: OrderedDict[int, tuple[np.ndarray, bytes, int]] = OrderedDict()

    # -- fault injection -------------------------------------------------------------------------
    def schedule(self, number: int, fault: Fault) -> None:
        """Apply ``fault`` to frame ``number`` when it is sent."""
        with self._lock:
            self._scheduled[number] = fault

    def unplug(self) -> None:
        with self._lock:
            self.unplugged = True

    # -- control requests ------------------------------------------------------------------------
    def identify(self) -> bytes:
        fmt = proto.PixelFormat.MONO16 if self.feed.pixel_format == "mono16" else proto.PixelFormat.MONO8
        return proto.IdentifyReply(self.feed.plane, self.feed.width, self.feed.height, (fmt,),
                                   max_rate_hz=1000.0, firmware_version=0x0102).encode()

    def vendor_request(self, request: int, value: int, data: bytes | None) -> bytes | None:
        """Handle a vendor request; returns the IN data stage, or None for OUT. USBError EPIPE on an unknown
        request (a control-endpoint stall, as real devices answer)."""
        with self._lock:
            if request == proto.Request.IDENTIFY:
                return self.identify()
            if request == proto.Request.GET_STATUS:
                state = proto.DeviceState.STREAMING if self.streaming else proto.DeviceState.IDLE
                return proto.StatusReply(state, 0, self.frames_sent, self.frames_overrun, self.feed.rate_hz).encode()
            if request == proto.Request.START:
                self.streaming = True
                self.halted = False
                # A feed driven by a shared trigger (both planes of one scene) sets the time origin.
                origin = getattr(self.feed, "origin", None)
                self._t0 = origin(self._clock) if origin is not None else self._clock()
                first = getattr(self.feed, "first_frame_after", None)
                self._next_number = first(self._clock() - self._t0) if first is not None and self.realtime else 0
                self._put_on_wire([])
                return None
            if request == proto.Request.STOP:
                self.streaming = False
                self._put_on_wire([])
                return None
            if request == proto.Request.SET_FRAME_RATE:
                rate = proto.decode_u32(bytes(data or b""), "SET_FRAME_RATE") / 1000.0
                if rate <= 0:
                    raise _usb_error(errno.EPIPE, "frame rate 0 refused")
                self.feed.rate_hz = rate
                return None
            if request == proto.Request.SET_EXPOSURE:
                self.feed.exposure_s = proto.decode_u32(bytes(data or b""), "SET_EXPOSURE") / 1e6
                return None
        raise _usb_error(errno.EPIPE, f"unknown vendor request {request:#04x}")

    # -- bulk IN ---------------------------------------------------------------------------------
    def bulk_read(self, buffer: memoryview, timeout_ms: int) -> int:
        """Fill ``buffer`` with the next transfer (at most to the end of the current frame); returns its length.
        With ``link_bytes_per_s`` it returns once the transfer's bytes could have crossed the link."""
        deadline = time.monotonic() + (timeout_ms / 1000.0 if timeout_ms else 3600.0)
        submitted = self._link_clock()
        while True:
            on_wire = False
            with self._lock:
                if self.unplugged:
                    raise _usb_error(errno.ENODEV, "No such device (it may have been disconnected)")
                if self.halted:
                    raise _usb_error(errno.EPIPE, "Pipe error")
                if self.streaming:
                    if self._offset >= self._length:
                        wait = self._load_next_frame()
                        if wait <= 0:
                            # The frame's bytes start on the link now (it was just read out), not before.
                            self._link_free = max(self._link_free, self._link_clock())
                    else:
                        wait = 0.0
                    if wait <= 0 and self.link_bytes_per_s is not None:
                        size = min(len(buffer), self._length - self._offset)
                        done = max(submitted, self._link_free) + size / self.link_bytes_per_s
                        wait = done - self._link_clock()
                        on_wire = wait > 0
                        if not on_wire:
                            self._link_free = done
                    if wait <= 0:
                        return self._send(buffer)
                else:
                    wait = 0.01
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise _usb_error(errno.ETIMEDOUT, "Operation timed out")
            # Bytes on the wire take real time; waiting for an exposure follows the injected clock.
            (self._link_sleep if on_wire else self._sleep)(min(wait, remaining, 0.05))

    def clear_halt(self) -> None:
        with self._lock:
            if self.halted:
                # The aborted frame is gone; the device resumes at the next frame boundary.
                self.halted = False
                self._put_on_wire([])

    def _put_on_wire(self, segments: list[bytes | memoryview]) -> None:
        self._segments = [memoryview(segment) for segment in segments]
        self._length = sum(len(segment) for segment in self._segments)
        self._offset = 0

    def _load_next_frame(self) -> float:
        """Put the next due frame on the wire; returns 0, or the seconds until one is due."""
        elapsed = self._clock() - self._t0
        if self.realtime:
            period = 1.0 / self.feed.rate_hz
            # Frames that finished exposing: the newest is the one the device just read out.
            newest = int(np.floor((elapsed - self.feed.exposure_s) / period + 1e-9))
            if newest < self._next_number:
                due = self._next_number * period + self.feed.exposure_s
                return max(due - elapsed, 1e-4)
            oldest_kept = newest - self.buffer_frames + 1
            if oldest_kept > self._next_number:
                self.frames_overrun += oldest_kept - self._next_number
                self._next_number = oldest_kept
        number = self._next_number
        self._next_number += 1
        frame = self.feed.frame(number)
        fault = self._scheduled.pop(number, None)
        if fault is None and self.fault_rates:
            roll = float(self._rng.random())
            for kind, rate in self.fault_rates.items():
                if roll < rate:
                    fault = kind
                    break
                roll -= rate
        header, payload = self._encode(frame)
        self._fault, self._fault_at = fault, -1
        if fault is not None:
            self.faults_injected[number] = fault
            self._put_on_wire([self._apply(fault, header + payload)])
        else:
            self._put_on_wire([header, payload])
        self.frames_sent += 1
        return 0.0

    def _encode(self, frame: DeviceFrame) -> tuple[bytes, bytes]:
        image = frame.image
        cached = self._payloads.get(id(image))
        if cached is None or cached[0] is not image:
            payload = np.ascontiguousarray(image, dtype="<u2" if image.dtype == np.uint16 else np.uint8).tobytes()
            cached = (image, payload, zlib.crc32(payload))
            self._payloads[id(image)] = cached
            while len(self._payloads) > 8:
                self._payloads.popitem(last=False)
        _, payload, crc = cached
        fmt = proto.PixelFormat.MONO16 if image.dtype == np.uint16 else proto.PixelFormat.MONO8
        header = proto.FrameHeader(self.feed.plane, fmt, frame.number, round(frame.device_time_s * 1e6),
                                   round(frame.exposure_s * 1e6), image.shape[1], image.shape[0], len(payload), crc)
        return header.encode(), payload

    def _apply(self, fault: Fault, wire: bytes) -> bytes:
        data = bytearray(wire)
        if fault is Fault.CORRUPT_HEADER:
            data[8 + int(self._rng.integers(0, proto.HEADER_SIZE - 12))] ^= 0x5A
        elif fault is Fault.BAD_CRC:
            data[proto.HEADER_SIZE + int(self._rng.integers(0, len(data) - proto.HEADER_SIZE))] ^= 0x01
        elif fault is Fault.TRUNCATE:
            del data[proto.HEADER_SIZE + (len(data) - proto.HEADER_SIZE) // 2:]
        elif fault is Fault.GARBAGE:
            data[:0] = self._rng.integers(0, 256, size=int(self._rng.integers(1, 300)), dtype=np.uint8).tobytes()
        elif fault in (Fault.STALL, Fault.TIMEOUT):
            self._fault_at = proto.HEADER_SIZE + (len(data) - proto.HEADER_SIZE) // 2
        return bytes(data)

    def _send(self, buffer: memoryview) -> int:
        end = min(self._length, self._offset + len(buffer))
        if self._fault is Fault.SHORT_TRANSFERS:
            end = min(end, self._offset + int(self._rng.integers(1, max(2, min(700, self._length // 3)))))
        if self._fault_at >= 0 and self._offset >= self._fault_at:
            fault, self._fault_at = self._fault, -1
            if fault is Fault.STALL:
                self.halted = True
                raise _usb_error(errno.EPIPE, "Pipe error")
            raise _usb_error(errno.ETIMEDOUT, "Operation timed out")
        if self._fault_at >= 0:
            end = min(end, self._fault_at)
        # Copy straight from the frame's segments into the host's buffer, as the controller's DMA would.
        written, position = 0, 0
        for segment in self._segments:
            lo, hi = max(self._offset, position), min(end, position + len(segment))
            if lo < hi:
                buffer[written:written + hi - lo] = segment[lo - position:hi - position]
                written += hi - lo
            position += len(segment)
        self._offset = end
        return written


class FakeGrabberBackend(usb.backend.IBackend):
    """pyusb backend over :class:`FakeGrabberDevice` objects (device ids are the devices themselves)."""

    def __init__(self, devices: Iterable[FakeGrabberDevice]) -> None:
        super().__init__()
        self.devices = list(devices)

    def device(self, serial: str) -> FakeGrabberDevice:
        return next(dev for dev in self.devices if dev.serial == serial)

    def enumerate_devices(self) -> Iterable[FakeGrabberDevice]:
        return [dev for dev in self.devices if not dev.unplugged]

    def get_parent(self, dev: FakeGrabberDevice) -> None:
        return None

    def get_device_descriptor(self, dev: FakeGrabberDevice) -> Any:
        return dev.device_descriptor

    def get_configuration_descriptor(self, dev: FakeGrabberDevice, config: int) -> Any:
        if config != 0:
            raise IndexError(config)
        return dev.configuration_descriptor

    def get_interface_descriptor(self, dev: FakeGrabberDevice, intf: int, alt: int, config: int) -> Any:
        if (intf, alt, config) != (0, 0, 0):
            raise IndexError((intf, alt, config))
        return dev.interface_descriptor

    def get_endpoint_descriptor(self, dev: FakeGrabberDevice, ep: int, intf: int, alt: int, config: int) -> Any:
        if (ep, intf, alt, config) != (0, 0, 0, 0):
            raise IndexError((ep, intf, alt, config))
        return dev.endpoint_descriptor

    def open_device(self, dev: FakeGrabberDevice) -> SimpleNamespace:
        if dev.unplugged:
            raise _usb_error(errno.ENODEV, "No such device (it may have been disconnected)")
        if dev.permission_denied:
            raise _usb_error(errno.EACCES, "Access denied (insufficient permissions)")
        return SimpleNamespace(dev=dev)

    def close_device(self, handle: SimpleNamespace) -> None:
        if handle.dev.claimed_by is handle:
            handle.dev.claimed_by = None

    def set_configuration(self, handle: SimpleNamespace, config_value: int) -> None:
        dev = self._live(handle)
        if dev.claimed_by is not None and dev.claimed_by is not handle:
            raise _usb_error(errno.EBUSY, "Resource busy")
        dev.configuration = config_value

    def get_configuration(self, handle: SimpleNamespace) -> int:
        return self._live(handle).configuration

    def set_interface_altsetting(self, handle: SimpleNamespace, intf: int, altsetting: int) -> None:
        self._live(handle)

    def claim_interface(self, handle: SimpleNamespace, intf: int) -> None:
        dev = self._live(handle)
        if dev.claimed_by is not None and dev.claimed_by is not handle:
            raise _usb_error(errno.EBUSY, "Resource busy")
        dev.claimed_by = handle

    def release_interface(self, handle: SimpleNamespace, intf: int) -> None:
        if handle.dev.claimed_by is handle:
            handle.dev.claimed_by = None

    def is_kernel_driver_active(self, handle: SimpleNamespace, intf: int) -> bool:
        return False

    def detach_kernel_driver(self, handle: SimpleNamespace, intf: int) -> None:
        return None

    def attach_kernel_driver(self, handle: SimpleNamespace, intf: int) -> None:
        return None

    def clear_halt(self, handle: SimpleNamespace, ep: int) -> None:
        self._live(handle).clear_halt()

    def reset_device(self, handle: SimpleNamespace) -> None:
        self._live(handle).clear_halt()

    def bulk_read(self, handle: SimpleNamespace, ep: int, intf: int, buff: Any, timeout: int) -> int:
        dev = self._live(handle)
        if ep != proto.BULK_IN_ENDPOINT:
            raise _usb_error(errno.EPIPE, f"no endpoint {ep:#04x}")
        if dev.claimed_by is not handle:
            raise _usb_error(errno.EBUSY, "interface not claimed")
        return dev.bulk_read(memoryview(buff).cast("B"), timeout)

    def ctrl_transfer(self, handle: SimpleNamespace, bmRequestType: int, bRequest: int, wValue: int,  # noqa: N803
                      wIndex: int, data: Any, timeout: int) -> int:  # noqa: N803
        dev = self._live(handle)
        is_in = bool(bmRequestType & 0x80)
        kind = (bmRequestType >> 5) & 0x3
        if kind == 0 and bRequest == 0x06 and is_in:            # GET_DESCRIPTOR
            reply = self._descriptor(dev, wValue >> 8, wValue & 0xFF)
        elif kind == 2:                                          # vendor
            reply = dev.vendor_request(bRequest, wValue, None if is_in else bytes(data))
        else:
            raise _usb_error(errno.EPIPE, f"request {bmRequestType:#04x}/{bRequest:#04x} not supported")
        if not is_in:
            dev.control_log.append((bmRequestType, bRequest, wValue, wIndex, bytes(data)))
            return len(data)
        reply = (reply or b"")[:len(data)]
        memoryview(data).cast("B")[:len(reply)] = reply
        dev.control_log.append((bmRequestType, bRequest, wValue, wIndex, bytes(reply)))
        return len(reply)

    @staticmethod
    def _descriptor(dev: FakeGrabberDevice, kind: int, index: int) -> bytes:
        if kind != 3:                                            # only string descriptors are asked for
            raise _usb_error(errno.EPIPE, f"descriptor type {kind} not supported")
        if index == 0:
            return bytes([4, 3, 0x09, 0x04])                     # LANGID en-US
        text = dev.strings.get(index)
        if text is None:
            raise _usb_error(errno.EPIPE, f"no string {index}")
        encoded = text.encode("utf-16-le")
        return bytes([2 + len(encoded), 3]) + encoded

    @staticmethod
    def _live(handle: SimpleNamespace) -> FakeGrabberDevice:
        if handle.dev.unplugged:
            raise _usb_error(errno.ENODEV, "No such device (it may have been disconnected)")
        return handle.dev
