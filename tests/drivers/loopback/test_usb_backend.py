"""The fake pyusb backend seen through pyusb itself: enumeration, descriptors, strings, control and bulk."""
from __future__ import annotations

import errno

import pytest
import usb.core
import usb.util

from drivers.loopback.usb_backend import FakeGrabberBackend, FakeGrabberDevice, Fault, PatternFeed
from firmware_protocol import usb_grabber as proto


@pytest.fixture
def setup() -> tuple[FakeGrabberBackend, FakeGrabberDevice, usb.core.Device]:
    device = FakeGrabberDevice(PatternFeed("q", 16, 8), serial="XRG-7", realtime=False, seed=2)
    backend = FakeGrabberBackend([device])
    dev = usb.core.find(idVendor=proto.VENDOR_ID, idProduct=proto.PRODUCT_ID, backend=backend)
    assert dev is not None
    return backend, device, dev


def test_descriptors_and_strings_through_pyusb(setup: tuple) -> None:
    _, _, dev = setup
    text = str(dev)                      # walks every descriptor the way `lsusb -v` would
    assert "0x1209" in text and "Bulk" in text and "0x81" in text
    assert usb.util.get_string(dev, dev.iSerialNumber) == "XRG-7"
    assert (dev.manufacturer, dev.product) == ("Microrobot Lab", "X-ray frame grabber")
    interface = dev[0][(0, 0)]
    assert interface.bInterfaceClass == 0xFF
    endpoint = usb.util.find_descriptor(interface, custom_match=lambda e:
                                        usb.util.endpoint_direction(e.bEndpointAddress) == usb.util.ENDPOINT_IN)
    assert endpoint.bEndpointAddress == proto.BULK_IN_ENDPOINT
    assert usb.util.endpoint_type(endpoint.bmAttributes) == usb.util.ENDPOINT_TYPE_BULK


def test_control_requests(setup: tuple) -> None:
    _, device, dev = setup
    reply = proto.IdentifyReply.decode(bytes(dev.ctrl_transfer(0xC0, proto.Request.IDENTIFY, 0, 0, 20)))
    assert (reply.plane, reply.width, reply.height) == ("q", 16, 8)
    assert dev.ctrl_transfer(0x40, proto.Request.SET_FRAME_RATE, 0, 0, proto.encode_rate(12.5)) == 4
    assert device.feed.rate_hz == 12.5
    with pytest.raises(usb.core.USBError) as info:
        dev.ctrl_transfer(0x40, 0x7F, 0, 0, b"")
    assert info.value.errno == errno.EPIPE


def test_bulk_stream_timeout_before_start_then_frames(setup: tuple) -> None:
    _, _, dev = setup
    dev.set_configuration()
    usb.util.claim_interface(dev, 0)
    with pytest.raises(usb.core.USBTimeoutError):
        dev.read(0x81, 4096, timeout=20)
    dev.ctrl_transfer(0x40, proto.Request.START, 0, 0, b"")
    first = bytes(dev.read(0x81, 4096, timeout=100))
    # A transfer ends at the end of a frame: header + 16x8 mono16 payload.
    assert len(first) == proto.HEADER_SIZE + 16 * 8 * 2
    assert proto.FrameHeader.decode(first).number == 0


def test_stall_until_clear_halt_then_the_next_frame(setup: tuple) -> None:
    _, device, dev = setup
    device.schedule(1, Fault.STALL)
    usb.util.claim_interface(dev, 0)
    dev.ctrl_transfer(0x40, proto.Request.START, 0, 0, b"")
    dev.read(0x81, 4096, timeout=100)                          # frame 0
    dev.read(0x81, 4096, timeout=100)                          # first half of frame 1
    for _ in range(2):
        with pytest.raises(usb.core.USBError) as info:
            dev.read(0x81, 4096, timeout=100)
        assert info.value.errno == errno.EPIPE
    dev.clear_halt(0x81)
    assert proto.FrameHeader.decode(bytes(dev.read(0x81, 4096, timeout=100))).number == 2


def test_short_transfers_and_unplug(setup: tuple) -> None:
    backend, device, dev = setup
    device.schedule(0, Fault.SHORT_TRANSFERS)
    usb.util.claim_interface(dev, 0)
    dev.ctrl_transfer(0x40, proto.Request.START, 0, 0, b"")
    sizes = []
    total = 0
    while total < proto.HEADER_SIZE + 256:
        sizes.append(len(dev.read(0x81, 4096, timeout=100)))
        total += sizes[-1]
    assert total == proto.HEADER_SIZE + 256 and len(sizes) > 1
    device.unplug()
    with pytest.raises(usb.core.USBError) as info:
        dev.read(0x81, 4096, timeout=100)
    assert info.value.errno == errno.ENODEV
    assert usb.core.find(idVendor=proto.VENDOR_ID, backend=backend) is None


class _LinkClock:
    """The link's clock for the paced fake: its sleep moves it, and the test moves it by hand."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        self.t += seconds


def test_a_paced_link_hands_each_transfer_on_once_its_bytes_crossed_it() -> None:
    clock = _LinkClock()
    rate = 1e6                                                    # 1 MB/s: a 16x8 mono16 frame (296 B) 296 us
    device = FakeGrabberDevice(PatternFeed("q", 16, 8), serial="XRG-8", realtime=False, link_bytes_per_s=rate,
                               link_clock=clock, link_sleep=clock.sleep)
    dev = usb.core.find(idVendor=proto.VENDOR_ID, backend=FakeGrabberBackend([device]))
    usb.util.claim_interface(dev, 0)
    dev.ctrl_transfer(0x40, proto.Request.START, 0, 0, b"")
    frame = proto.HEADER_SIZE + 16 * 8 * 2
    returned, sizes = [], []
    start = clock.t
    while sum(sizes) < frame:                                     # one frame in 100-byte transfers, back to back
        sizes.append(len(dev.read(0x81, 100, timeout=100)))
        returned.append(clock.t)
    assert sizes == [100, 100, 96]
    # Each transfer returns when its last byte has crossed the link, one after the other.
    assert returned == pytest.approx([start + 100 / rate, start + 200 / rate, start + frame / rate])
    # A host that asks late finds the link idle meanwhile: the next frame's bytes take their whole time
    # from the moment it asks, however long the link was free.
    clock.t += 1.0
    asked = clock.t
    assert len(dev.read(0x81, 4096, timeout=100)) == frame
    assert clock.t == pytest.approx(asked + frame / rate)


def test_an_unpaced_link_never_waits() -> None:
    clock = _LinkClock()
    device = FakeGrabberDevice(PatternFeed("q", 16, 8), serial="XRG-9", realtime=False,
                               link_clock=clock, link_sleep=clock.sleep)
    dev = usb.core.find(idVendor=proto.VENDOR_ID, backend=FakeGrabberBackend([device]))
    usb.util.claim_interface(dev, 0)
    dev.ctrl_transfer(0x40, proto.Request.START, 0, 0, b"")
    for _ in range(3):
        dev.read(0x81, 100, timeout=100)
    assert clock.t == 100.0
    with pytest.raises(ValueError):
        FakeGrabberDevice(PatternFeed("q", 16, 8), link_bytes_per_s=0.0)
