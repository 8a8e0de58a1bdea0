"""The frame-source interface: template read (deadline, validation, counters), URL parsing, open_source."""
from __future__ import annotations

import numpy as np
import pytest

from drivers.errors import DeviceError, DeviceTimeoutError, InputDataError
from drivers.frame_source import Frame, FrameSource, SourceCounters, open_source, parse_source_url


class Scripted(FrameSource):
    """Hands out the frames it was given; None means "nothing before the deadline"."""

    def __init__(self, items: list[Frame | None], **kwargs: object) -> None:
        super().__init__(plane="p", name="scripted", width=6, height=4, **kwargs)  # type: ignore[arg-type]
        self.items = list(items)
        self.opened = 0
        self.closed = 0

    def _open_internal(self) -> None:
        self.opened += 1

    def _close_internal(self) -> None:
        self.closed += 1

    def _read_internal(self, deadline: float) -> Frame | None:
        return self.items.pop(0)


def frame(number: int, *, shape: tuple[int, int] = (4, 6), dtype: type = np.uint16, plane: str = "p",
          fmt: str = "mono16") -> Frame:
    return Frame(np.zeros(shape, dtype=dtype), plane, number, number / 30, number / 30 + 0.01, None, fmt)


def test_counters_count_frames_gaps_and_timeouts_and_restarts_are_not_drops() -> None:
    source = Scripted([frame(0), frame(1), frame(4), None, frame(5), frame(0), frame(1)])
    with source:
        numbers = []
        for _ in range(7):
            try:
                numbers.append(source.read(0.1).number)
            except DeviceTimeoutError:
                numbers.append(None)
    assert numbers == [0, 1, 4, None, 5, 0, 1]
    assert source.counters == SourceCounters(frames=6, dropped=2, corrupt=0, timeouts=1)


def test_frames_are_read_only_and_checked() -> None:
    with Scripted([frame(0)]) as source:
        got = source.read(0.1)
        with pytest.raises(ValueError):
            got.image[0, 0] = 1
    for bad, message in ((frame(0, shape=(5, 6)), "announced 6x4"), (frame(0, dtype=np.float32), "expected 2-D"),
                         (frame(0, plane="q"), "plane 'q'"), (frame(0, fmt="mono8"), "expected 2-D uint8")):
        with Scripted([bad]) as source, pytest.raises(DeviceError, match=message):
            source.read(0.1)


def test_lifecycle_is_idempotent_and_read_needs_open() -> None:
    source = Scripted([frame(0)])
    with pytest.raises(DeviceError, match="not open"):
        source.read(0.1)
    source.open()
    source.open()
    source.close()
    source.close()
    assert (source.opened, source.closed) == (1, 1)
    with pytest.raises(InputDataError, match="plane"):
        FrameSource.__init__(source, plane="x", name="bad")


def test_url_parsing_and_refusals() -> None:
    url = parse_source_url("file:///data/run1?plane=q&rate=30&loop=1")
    assert (url.scheme, url.path, url.query) == ("file", "/data/run1", {"plane": "q", "rate": "30", "loop": "1"})
    with pytest.raises(InputDataError, match="given twice"):
        parse_source_url("file:///x?plane=p&plane=q")
    with pytest.raises(InputDataError, match="no scheme"):
        open_source("/dev/video0")
    with pytest.raises(InputDataError, match="unknown scheme 'rtsp'"):
        open_source("rtsp://camera/stream")
    with pytest.raises(DeviceError, match="loopback fake"):
        open_source("loopback://?plane=p")
    with pytest.raises(InputDataError, match="VID:PID"):
        open_source("usb://grabber")
