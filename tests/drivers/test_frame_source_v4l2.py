"""V4L2 capture: honest errors without a device (none exists on CI), and frame conversion on a stand-in capture."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from drivers import v4l2_source
from drivers.errors import DeviceBusyError, DeviceNotFoundError, InputDataError
from drivers.frame_source import open_source
from drivers.v4l2_source import V4l2Source, list_v4l2_devices, open_v4l2_capture


def test_missing_device_is_not_found_by_path_and_index() -> None:
    with pytest.raises(DeviceNotFoundError, match="/dev/video97: no such video device"):
        open_source("v4l2:///dev/video97").open()
    with pytest.raises(DeviceNotFoundError, match="/dev/video98"):
        open_source("v4l2://98?bits=8").open()


def test_a_node_that_will_not_capture_is_reported_busy(tmp_path: Path) -> None:
    node = tmp_path / "video0"
    node.write_bytes(b"")          # exists and is accessible, but no V4L2 device answers
    with pytest.raises(DeviceBusyError, match="another program"):
        open_v4l2_capture(str(node))


def test_no_v4l2_backend_is_said_plainly(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(v4l2_source, "v4l2_backend_available", lambda: False)
    with pytest.raises(DeviceNotFoundError, match="no V4L2 backend"):
        open_v4l2_capture("/dev/video0")


def test_url_options_are_checked() -> None:
    with pytest.raises(InputDataError, match="unknown option"):
        open_source("v4l2:///dev/video0?colour=1")
    with pytest.raises(InputDataError, match="bits must be 8 or 16"):
        open_source("v4l2:///dev/video0?bits=12")
    assert list_v4l2_devices(pattern="/nonexistent/video*") == []


class StandInCapture:
    """Behaves like cv2.VideoCapture on a card: reports a size, returns frames, sometimes none (timeout)."""

    def __init__(self, frames: list[np.ndarray | None], width: int, height: int) -> None:
        self.frames = list(frames)
        self.size = (width, height)
        self.released = False
        self.stamp = 1000.0

    def get(self, prop: int) -> float:
        if prop == cv2.CAP_PROP_FRAME_WIDTH:
            return self.size[0]
        if prop == cv2.CAP_PROP_FRAME_HEIGHT:
            return self.size[1]
        if prop == cv2.CAP_PROP_POS_MSEC:
            return self.stamp
        return 0.0

    def read(self) -> tuple[bool, np.ndarray | None]:
        frame = self.frames.pop(0) if self.frames else None
        self.stamp += 40.0
        return frame is not None, frame

    def release(self) -> None:
        self.released = True


def test_raw_y16_colour_and_gray_frames_convert() -> None:
    y16 = np.arange(8 * 6, dtype="<u2").reshape(6, 8) * 1000
    colour = np.zeros((6, 8, 3), dtype=np.uint8)
    colour[..., 1] = 200
    capture = StandInCapture([y16.view(np.uint8).reshape(1, -1), None, y16], 8, 6)
    with V4l2Source(lambda: capture, name="card") as source:
        first = source.read(1.0)
        second = source.read(1.0)            # after one empty read (the backend's timeout)
    assert np.array_equal(first.image, y16) and first.pixel_format == "mono16"
    assert np.array_equal(second.image, y16) and (first.number, second.number) == (0, 1)
    assert second.device_time_s - first.device_time_s == pytest.approx(0.08)
    assert capture.released
    gray = StandInCapture([colour], 8, 6)
    with V4l2Source(lambda: gray, bits=8) as source:
        frame = source.read(1.0)
    assert frame.pixel_format == "mono8" and frame.image.shape == (6, 8) and 100 < int(frame.image[0, 0]) < 140


@pytest.mark.hardware
def test_contract_a_real_capture_card(device_urls: dict[str, str]) -> None:
    """``--device-url v4l2=v4l2:///dev/video0?bits=8``: frames in order with the announced size."""
    if "v4l2" not in device_urls:
        pytest.skip("pass --device-url v4l2=v4l2:///dev/videoN")
    with open_source(device_urls["v4l2"]) as source:
        got = [source.read(2.0) for _ in range(5)]
    assert [f.number for f in got] == [0, 1, 2, 3, 4]
    assert all((f.width, f.height) == (source.width, source.height) for f in got)
    assert all(b.host_time_s > a.host_time_s for a, b in zip(got, got[1:]))
