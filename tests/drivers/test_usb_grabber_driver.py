"""USB grabber driver through the real pyusb path on the fake backend: intact frames, injected faults, errors.

The contract test at the end also runs against a real grabber: ``--device-url grabber=usb://VID:PID?serial=..``.
"""
from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np
import pytest
import usb.core

from drivers.errors import DeviceBusyError, DeviceError, DeviceNotFoundError, DevicePermissionError, LinkLostError
from drivers.frame_source import FrameSource, open_source
from drivers.loopback.usb_backend import FakeGrabberBackend, FakeGrabberDevice, Fault, PatternFeed, lost_by
from drivers.usb_grabber import UsbGrabber, find_grabber, list_grabbers

URL = "usb://1209:0001"


def fake(plane: str = "p", serial: str = "XRG-1", *, realtime: bool = False, **options: object
         ) -> tuple[FakeGrabberBackend, FakeGrabberDevice, PatternFeed]:
    feed = PatternFeed(plane, 64, 48, seed=hash(serial) % 1000)
    device = FakeGrabberDevice(feed, serial=serial, realtime=realtime, seed=11, **options)  # type: ignore[arg-type]
    return FakeGrabberBackend([device]), device, feed


@pytest.mark.parametrize("transfer_kib", [1, 4, 1024])
def test_frames_arrive_intact_across_transfer_sizes(transfer_kib: int) -> None:
    backend, _, feed = fake()
    with open_source(f"{URL}?transfer_kib={transfer_kib}", backend=backend) as source:
        got = [source.read(2.0) for _ in range(12)]
        assert isinstance(source, UsbGrabber)
        stats = source.link_stats
    assert [f.number for f in got] == list(range(12))
    for f in got:
        assert f.image.dtype == np.uint16 and np.array_equal(f.image, feed.frame(f.number).image)
        assert f.device_time_s == pytest.approx(f.number / feed.rate_hz, abs=1e-6)
        assert f.exposure_s == pytest.approx(feed.exposure_s) and f.plane == "p"
    assert source.counters.corrupt == 0 and source.counters.dropped == 0
    assert stats.transfers >= 12 and stats.skipped_bytes == 0


def test_a_frame_over_transfers_ends_with_a_small_transfer() -> None:
    # 6144-byte payloads in 4 KiB transfers: the first carries the header and ~4 KiB, and the rest (~2 KiB)
    # would be the last; with final_transfer=512 the driver asks for all but 512 bytes of it first.
    backend, device, feed = fake()
    sizes: list[int] = []
    read = device.bulk_read

    def recorded(buffer: memoryview, timeout_ms: int) -> int:
        sizes.append(read(buffer, timeout_ms))
        return sizes[-1]

    device.bulk_read = recorded  # type: ignore[method-assign]
    with open_source(f"{URL}?transfer_kib=4", backend=backend, final_transfer=512) as source:
        got = [source.read(2.0) for _ in range(6)]
    assert [f.number for f in got] == list(range(6))
    assert all(np.array_equal(f.image, feed.frame(f.number).image) for f in got)
    assert source.counters.corrupt == 0
    # Three transfers a frame: 4096 bytes (the 40-byte header and payload), the rest less 512, then 512.
    assert sizes[:18] == [4096, 40 + 6144 - 4096 - 512, 512] * 6


def test_injected_faults_are_counted_survived_and_never_handed_on() -> None:
    backend, device, feed = fake()
    plan = {3: Fault.CORRUPT_HEADER, 5: Fault.BAD_CRC, 7: Fault.TRUNCATE, 9: Fault.STALL, 11: Fault.TIMEOUT,
            13: Fault.SHORT_TRANSFERS, 15: Fault.GARBAGE, 16: Fault.TRUNCATE, 17: Fault.STALL}
    for number, fault in plan.items():
        device.schedule(number, fault)
    with open_source(f"{URL}?transfer_kib=2", backend=backend) as source:
        got = [source.read(2.0) for _ in range(15)]
        stats = source.link_stats
    lost = sorted(n for n, fault in plan.items() if lost_by(fault))
    assert [f.number for f in got] == [n for n in range(40) if n not in lost][:15]
    assert all(np.array_equal(f.image, feed.frame(f.number).image) for f in got)   # 0 corrupt frames handed on
    counters = source.counters
    assert counters.corrupt == 4 and counters.dropped == len(lost)
    assert (stats.corrupt_headers, stats.bad_crc, stats.truncated) == (1, 1, 2)
    assert stats.stalls == 2 and stats.usb_timeouts >= 1


@pytest.mark.parametrize("transfer_kib", [3, 1024])   # frames over transfers; a frame per transfer (lent, no copy)
def test_random_faults_over_many_frames(transfer_kib: int) -> None:
    rates = {Fault.CORRUPT_HEADER: 0.03, Fault.BAD_CRC: 0.03, Fault.TRUNCATE: 0.03, Fault.STALL: 0.02,
             Fault.TIMEOUT: 0.03, Fault.SHORT_TRANSFERS: 0.05, Fault.GARBAGE: 0.03}
    backend, device, feed = fake(fault_rates=rates)
    with open_source(f"{URL}?transfer_kib={transfer_kib}", backend=backend) as source:
        got = [source.read(2.0) for _ in range(300)]
        stats = source.link_stats
    injected = device.faults_injected
    delivered = {f.number for f in got}
    assert all(np.array_equal(f.image, feed.frame(f.number).image) for f in got)
    assert not delivered & {n for n, fault in injected.items() if lost_by(fault)}
    last = got[-1].number
    assert delivered == {n for n in range(last + 1) if not lost_by(injected.get(n))}
    expected_corrupt = sum(f in (Fault.CORRUPT_HEADER, Fault.BAD_CRC, Fault.TRUNCATE)
                           for n, f in injected.items() if n <= last)
    # A stall right before a cut frame can swallow the evidence of the cut: at most that many fewer.
    assert expected_corrupt - stats.stalls <= source.counters.corrupt <= expected_corrupt
    assert stats.stalls == sum(f is Fault.STALL for n, f in injected.items() if n <= last)
    assert source.counters.dropped == last + 1 - len(got)


@pytest.mark.parametrize("transfer_kib", [1, 1024])   # payloads collected over transfers; views on one transfer
def test_frames_a_consumer_holds_are_never_overwritten_and_the_rest_reuse_buffers(transfer_kib: int) -> None:
    backend, _, feed = fake()
    held = {}
    with open_source(f"{URL}?transfer_kib={transfer_kib}", backend=backend) as source:
        assert isinstance(source, UsbGrabber)
        for _ in range(80):
            frame = source.read(2.0)
            if frame.number % 20 == 3:
                held[frame.number] = frame.image[4:40, 8:30]    # a region of interest: a view, as the tracker's
            del frame
        made = source.link_stats.buffers_made
    # The feed cycles through 4 different images, so a reused buffer under a held frame would show.
    assert all(np.array_equal(image, feed.frame(n).image[4:40, 8:30]) for n, image in held.items())
    assert len(held) == 4 and made <= 2 * (len(held) + source.max_queued + 2)   # 80 frames: without reuse >= 80


def test_control_exchange_is_byte_exact() -> None:
    backend, device, _ = fake(serial="XRG-P")
    with open_source(f"{URL}?serial=XRG-P&rate=29.97&exposure_ms=5", backend=backend) as source:
        source.read(2.0)
    vendor = [entry for entry in device.control_log if entry[0] in (0x40, 0xC0)]
    assert vendor == [
        (0xC0, 0x01, 0, 0, bytes.fromhex("58524749 01 70 4000 3000 02 00 40420f00 0201 0000")),  # IDENTIFY
        (0x40, 0x04, 0, 0, bytes.fromhex("12750000")),     # SET_FRAME_RATE 29.970 Hz
        (0x40, 0x05, 0, 0, bytes.fromhex("88130000")),     # SET_EXPOSURE 5000 us
        (0x40, 0x02, 0, 0, b""),                           # START
        (0x40, 0x03, 0, 0, b""),                           # STOP (on close)
    ]
    # The serial number was read through standard GET_DESCRIPTOR(STRING) requests, LANGID first.
    strings = [entry for entry in device.control_log if entry[:2] == (0x80, 0x06)]
    assert strings[0][2] == 0x0300 and strings[0][4] == bytes([4, 3, 0x09, 0x04])
    assert strings[1][2] == 0x0303 and strings[1][4][2:].decode("utf-16-le") == "XRG-P"


def test_rate_and_exposure_reach_the_device_and_status_reports() -> None:
    backend, device, feed = fake()
    with open_source(f"{URL}?rate=250&exposure_ms=2.5", backend=backend) as source:
        source.read(2.0)
        status = source.status()
    assert feed.rate_hz == pytest.approx(250.0) and feed.exposure_s == pytest.approx(0.0025)
    assert status.state.name == "STREAMING" and status.frames_sent >= 1 and status.rate_hz == pytest.approx(250.0)
    assert not device.streaming and device.claimed_by is None      # STOP and release on close


def test_a_slow_host_overruns_the_device_buffer_and_sees_drops() -> None:
    backend, device, _ = fake(realtime=True, buffer_frames=2)
    with open_source(f"{URL}?rate=500", backend=backend) as source:
        source.read(2.0)
        time.sleep(0.1)                                  # fifty frame periods without reading
        numbers = [source.read(2.0).number for _ in range(3)]
    assert numbers == sorted(numbers) and numbers[-1] > 10
    assert device.frames_overrun > 0 and source.counters.dropped > 0


def test_missing_device_wrong_serial_and_ambiguity() -> None:
    backend, _, _ = fake(serial="XRG-1")
    with pytest.raises(DeviceNotFoundError, match="no USB grabber usb://1209:0002"):
        open_source("usb://1209:0002", backend=backend)
    with pytest.raises(DeviceNotFoundError, match="have serials: XRG-1"):
        open_source(f"{URL}?serial=XRG-9", backend=backend)
    two = FakeGrabberBackend([FakeGrabberDevice(PatternFeed("p"), serial="A"), FakeGrabberDevice(PatternFeed("q"), serial="B")])
    with pytest.raises(DeviceError, match="choose one with"):
        find_grabber(backend=two)
    assert [g.url for g in list_grabbers(backend=two)] == [f"{URL}?serial=A", f"{URL}?serial=B"]
    assert open_source(f"{URL}?serial=B", backend=two).plane == "q"


def test_permission_busy_and_plane_errors_name_the_fix() -> None:
    backend, device, _ = fake()
    device.permission_denied = True
    with pytest.raises(DevicePermissionError, match="99-xray-grabber.rules"):
        open_source(URL, backend=backend)
    device.permission_denied = False
    other = usb.core.find(idVendor=0x1209, idProduct=0x0001, backend=backend)
    other.set_configuration()
    usb.util.claim_interface(other, 0)          # another program holds the grabber
    source = open_source(URL, backend=backend)
    with pytest.raises(DeviceBusyError, match="busy"):
        source.open()
    usb.util.dispose_resources(other)
    with pytest.raises(DeviceError, match="identifies as plane 'p' but plane='q'"):
        open_source(f"{URL}?plane=q", backend=backend)


def test_unplugging_mid_stream_is_a_lost_link() -> None:
    backend, device, _ = fake()
    with open_source(URL, backend=backend) as source:
        source.read(2.0)
        device.unplug()
        with pytest.raises(LinkLostError, match="gone"):
            for _ in range(100):
                source.read(2.0)


# -- contract: the same checks against the fake and (opt-in) a real grabber -----------------------
@pytest.fixture(params=["fake", pytest.param("hardware", marks=pytest.mark.hardware)])
def grabber(request: pytest.FixtureRequest, device_urls: dict[str, str]) -> Iterator[FrameSource]:
    if request.param == "fake":
        backend, _, _ = fake(realtime=True)
        source = open_source(f"{URL}?rate=200", backend=backend)
    else:
        if "grabber" not in device_urls:
            pytest.skip("pass --device-url grabber=usb://VID:PID?serial=...")
        source = open_source(device_urls["grabber"])
    with source:
        yield source


def test_contract_frames_in_order_with_sane_timestamps(grabber: FrameSource) -> None:
    got = [grabber.read(2.0) for _ in range(10)]
    numbers = [f.number for f in got]
    assert numbers == sorted(numbers) and len(set(numbers)) == 10
    assert all(b.device_time_s > a.device_time_s and b.host_time_s >= a.host_time_s for a, b in zip(got, got[1:]))
    assert all((f.width, f.height) == (grabber.width, grabber.height) for f in got)
    assert grabber.counters.frames == 10 and grabber.counters.corrupt == 0


def test_the_shipped_udev_rule_matches_the_protocol_ids() -> None:
    import re
    from pathlib import Path

    from firmware_protocol import usb_grabber as proto

    rules = (Path(__file__).resolve().parents[2] / "config/udev/99-xray-grabber.rules").read_text()
    active = [line for line in rules.splitlines() if line and not line.startswith("#")]
    assert active and all(f'ATTR{{idVendor}}=="{proto.VENDOR_ID:04x}"' in line and
                          f'ATTR{{idProduct}}=="{proto.PRODUCT_ID:04x}"' in line for line in active)
    assert any(re.search(r'MODE="0660", GROUP="plugdev"', line) for line in active)
