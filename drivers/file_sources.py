"""Frame sources that replay recorded X-ray frames from files: biplane folders, multi-page TIFF, DICOM, video.

- ``file://DIR?plane=p`` — a biplane frame folder (``DIR/p/NNNNNN.png|tif``, read through
  :class:`drivers.biplane_folder.BiplaneFolder`); the frame numbers are the file numbers. When the folder
  has ``DIR/timestamps.csv`` (written by ``appliance grab``; columns ``plane,number,device_time_s,
  host_time_s,exposure_s``) the recorded device times and exposures are replayed too.
- ``file://stack.tif`` — a multi-page TIFF (tifffile), one page per frame; an ImageJ ``finterval`` gives
  the recorded frame interval.
- ``file://run.dcm`` — a DICOM file (pydicom), single- or multi-frame (X-ray angiography / RF from a
  C-arm); ``FrameTimeVector``, ``FrameTime`` or ``CineRate`` give the recorded times, ``ExposureTime``
  the exposure; MONOCHROME1 data is inverted so that attenuation stays dark, as on the detector.
- ``file://clip.mp4`` (any container OpenCV reads) — a video of a fluoroscope's monitor output, converted
  to 8-bit grayscale; the container's frame rate gives the recorded times.

Options (query): ``plane=p|q`` (the folder needs it; single files default to p), ``rate=max`` (as fast
as the reader reads; the default), ``rate=recorded`` (the recorded timing, or 30 Hz when there is
none), ``rate=<Hz>`` (fixed), ``loop=1`` (start again after the last frame; numbers and times keep
increasing so pairing and tracking see one continuous stream). Without ``loop`` the read after the last
frame raises :class:`EndOfStream`. Device times are the recorded times when known, else ``index / rate``
(30 Hz when playing at ``max``).
"""
from __future__ import annotations

import csv
import logging
import time
from abc import abstractmethod
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from drivers.errors import InputDataError
from drivers.frame_source import EndOfStream, Frame, FrameSource, SourceUrl, check_known_keys, query_bool

log = logging.getLogger(__name__)

NOMINAL_RATE_HZ = 30.0
TIMESTAMPS_FILE = "timestamps.csv"
TIMESTAMP_COLUMNS = ("plane", "number", "device_time_s", "host_time_s", "exposure_s")
VIDEO_SUFFIXES = {".mp4", ".avi", ".mkv", ".mov", ".m4v", ".mpg", ".mpeg", ".wmv"}
Rate = float | str | None   # Hz, "recorded", or None (as fast as possible)


def parse_rate(text: str | None, where: str) -> Rate:
    if text is None or text in ("", "max"):
        return None
    if text == "recorded":
        return "recorded"
    try:
        rate = float(text)
    except ValueError as err:
        raise InputDataError(f"{where}: rate={text!r}: use max, recorded or a frame rate in Hz") from err
    if rate <= 0:
        raise InputDataError(f"{where}: rate must be > 0 Hz, got {rate}")
    return rate


class PlaybackSource(FrameSource):
    """Replays indexed frames with pacing and looping; subclasses load the file and decode frame ``i``."""

    def __init__(self, path: str | Path, *, plane: str = "p", rate: Rate = None, loop: bool = False,
                 clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep) -> None:
        self.path = Path(path)
        super().__init__(plane=plane, name=f"file:{self.path}" + ("" if self.path.is_file() else f"[{plane}]"))
        if isinstance(rate, str) and rate != "recorded":
            rate = parse_rate(rate, self.name)
        self.rate = rate
        self.loop = loop
        self._clock, self._sleep = clock, sleep
        self.numbers: list[int] = []
        self.times_s: list[float] | None = None      # recorded device times, when the file has them
        self.exposures_s: list[float | None] | None = None
        self._index = 0
        self._cycle = 0
        self._start = 0.0

    # -- subclass hooks --------------------------------------------------------------------------
    @abstractmethod
    def _load(self) -> None:
        """Open the file(s); fill ``numbers`` (and ``times_s``/``exposures_s`` when recorded), width, height,
        pixel_format."""

    @abstractmethod
    def _image(self, index: int) -> np.ndarray:
        """Decode frame ``index`` (0-based position in the file)."""

    def _rewind(self) -> None:
        """Called before a loop starts again (sequential readers seek back)."""

    # -- template --------------------------------------------------------------------------------
    def _open_internal(self) -> None:
        if not self.path.exists():
            raise InputDataError(f"{self.path}: no such file or folder")
        self._load()
        if not self.numbers:
            raise InputDataError(f"{self.name}: no frames to play")
        if self.times_s is not None and any(b <= a for a, b in zip(self.times_s, self.times_s[1:])):
            raise InputDataError(f"{self.name}: recorded frame times do not increase")
        self._index = 0
        self._cycle = 0
        self._start = self._clock()
        log.info("%s: %d frames, %s", self.name, len(self.numbers),
                 "recorded times" if self.times_s is not None else "no recorded times")

    def _close_internal(self) -> None:
        pass

    def _nominal_period(self) -> float:
        return 1.0 / self.rate if isinstance(self.rate, float) else 1.0 / NOMINAL_RATE_HZ

    def _time_of(self, index: int) -> float:
        """Device time of frame ``index`` in the first pass (s)."""
        if self.times_s is not None:
            return self.times_s[index] - self.times_s[0]
        return index * self._nominal_period()

    def _duration(self) -> float:
        count = len(self.numbers)
        if self.times_s is not None and count > 1:
            return self._time_of(count - 1) + (self.times_s[-1] - self.times_s[0]) / (count - 1)
        return count * self._nominal_period()

    def _play_time(self, index: int) -> float | None:
        """Seconds after the start at which frame ``index`` of the current pass is due, or None (no pacing)."""
        if self.rate is None:
            return None
        if self.rate == "recorded":
            return self._cycle * self._duration() + self._time_of(index)
        return (self._cycle * len(self.numbers) + index) / float(self.rate)

    def _read_internal(self, deadline: float) -> Frame | None:
        if self._index >= len(self.numbers):
            if not self.loop:
                raise EndOfStream(f"{self.name}: all {len(self.numbers)} frames played")
            self._index = 0
            self._cycle += 1
            self._rewind()
        index = self._index
        due = self._play_time(index)
        if due is not None:
            while True:
                wait = self._start + due - self._clock()
                if wait <= 0:
                    break
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._sleep(min(wait, remaining))
        image = self._image(index)
        self._index += 1
        span = self.numbers[-1] - self.numbers[0] + 1
        number = self.numbers[index] + self._cycle * span
        exposure = self.exposures_s[index] if self.exposures_s is not None else None
        return Frame(image=image, plane=self.plane, number=number,
                     device_time_s=self._cycle * self._duration() + self._time_of(index),
                     host_time_s=time.monotonic(), exposure_s=exposure, pixel_format=self.pixel_format)

    def _set_format(self, image: np.ndarray, where: str) -> None:
        if image.ndim != 2:
            raise InputDataError(f"{where}: frames must be 2-D grayscale, got shape {image.shape}")
        if image.dtype == np.uint16:
            self.pixel_format = "mono16"
        elif image.dtype == np.uint8:
            self.pixel_format = "mono8"
        else:
            raise InputDataError(f"{where}: frames must be 8- or 16-bit unsigned, got {image.dtype}")
        self.height, self.width = image.shape


class FolderSource(PlaybackSource):
    """One plane of a biplane frame folder."""

    def _load(self) -> None:
        from drivers.biplane_folder import BiplaneFolder

        self.folder = BiplaneFolder(self.path)
        other = "q" if self.plane == "p" else "p"
        self.numbers = sorted(set(self.folder.frame_numbers) | set(self.folder.unpaired.get(self.plane, []))
                              - set(self.folder.unpaired.get(other, [])))
        if not self.numbers:
            return
        self._set_format(self.folder.read(self.plane, self.numbers[0]), self.name)
        self._load_timestamps()

    def _load_timestamps(self) -> None:
        path = self.path / TIMESTAMPS_FILE
        if not path.is_file():
            return
        rows: dict[int, tuple[float, float | None]] = {}
        try:
            with path.open(newline="", encoding="utf-8") as handle:
                reader = csv.DictReader(handle)
                missing = set(TIMESTAMP_COLUMNS) - set(reader.fieldnames or [])
                if missing:
                    raise InputDataError(f"{path}: missing column(s) {', '.join(sorted(missing))}")
                for line, row in enumerate(reader, start=2):
                    if row["plane"] != self.plane:
                        continue
                    try:
                        exposure = float(row["exposure_s"]) if row["exposure_s"] not in ("", "None") else None
                        rows[int(row["number"])] = (float(row["device_time_s"]), exposure)
                    except ValueError as err:
                        raise InputDataError(f"{path}: line {line}: {err}") from err
        except OSError as err:
            raise InputDataError(f"{path}: cannot read ({err.strerror or err})") from err
        if not all(n in rows for n in self.numbers):
            log.warning("%s: does not cover every frame of plane %s; ignoring recorded times", path, self.plane)
            return
        self.times_s = [rows[n][0] for n in self.numbers]
        self.exposures_s = [rows[n][1] for n in self.numbers]

    def _image(self, index: int) -> np.ndarray:
        return self.folder.read(self.plane, self.numbers[index])


class TiffStackSource(PlaybackSource):
    """A multi-page TIFF, one page per frame."""

    def _load(self) -> None:
        import tifffile

        try:
            self._tif = tifffile.TiffFile(self.path)
            pages = len(self._tif.pages)
            first = self._tif.pages[0].asarray()
        except (OSError, ValueError, IndexError, tifffile.TiffFileError) as err:
            raise InputDataError(f"{self.path}: not a readable TIFF ({err})") from err
        self._set_format(first, str(self.path))
        self.numbers = list(range(pages))
        interval = (self._tif.imagej_metadata or {}).get("finterval")
        if interval:
            self.times_s = [i * float(interval) for i in range(pages)]

    def _image(self, index: int) -> np.ndarray:
        image = self._tif.pages[index].asarray()
        if image.shape != (self.height, self.width) or image.dtype.name != ("uint16" if self.pixel_format == "mono16"
                                                                             else "uint8"):
            raise InputDataError(f"{self.path}: page {index} is {image.dtype}{image.shape}, page 0 was "
                                 f"{self.pixel_format} {self.width}x{self.height}")
        return image

    def _close_internal(self) -> None:
        tif = getattr(self, "_tif", None)
        if tif is not None:
            tif.close()


class DicomSource(PlaybackSource):
    """A single- or multi-frame DICOM image (pydicom)."""

    def _load(self) -> None:
        import pydicom
        from pydicom.errors import InvalidDicomError

        try:
            ds = pydicom.dcmread(self.path)
            pixels = ds.pixel_array
        except (InvalidDicomError, OSError, AttributeError) as err:
            raise InputDataError(f"{self.path}: not a readable DICOM image ({err})") from err
        except (RuntimeError, NotImplementedError) as err:   # compressed transfer syntax without a decoder
            raise InputDataError(f"{self.path}: cannot decode the DICOM pixel data ({err})") from err
        frames = int(getattr(ds, "NumberOfFrames", 1) or 1)
        if getattr(ds, "SamplesPerPixel", 1) != 1:
            raise InputDataError(f"{self.path}: colour DICOM ({ds.SamplesPerPixel} samples/pixel); X-ray frames are grayscale")
        if int(getattr(ds, "PixelRepresentation", 0)) != 0:
            raise InputDataError(f"{self.path}: signed pixel data; expected unsigned detector intensity")
        stack = pixels.reshape(frames, *pixels.shape[-2:])
        if getattr(ds, "PhotometricInterpretation", "MONOCHROME2") == "MONOCHROME1":
            # MONOCHROME1 displays low values white; flip so that attenuation is dark as on the detector.
            top = (1 << int(getattr(ds, "BitsStored", stack.dtype.itemsize * 8))) - 1
            stack = (top - stack.astype(np.int64)).clip(0, top).astype(stack.dtype)
        self._stack = stack
        self._set_format(np.ascontiguousarray(stack[0]), str(self.path))
        self.numbers = list(range(frames))
        self.times_s = self._recorded_times(ds, frames)
        exposure = getattr(ds, "ExposureTime", None)                    # ms
        if exposure not in (None, ""):
            self.exposures_s = [float(exposure) / 1000.0] * frames

    @staticmethod
    def _recorded_times(ds: Any, frames: int) -> list[float] | None:
        vector = getattr(ds, "FrameTimeVector", None)                   # ms; first entry is 0
        if vector is not None and len(vector) == frames:
            return list(np.cumsum([float(v) for v in vector]) / 1000.0)
        frame_time = getattr(ds, "FrameTime", None)                     # ms
        if frame_time not in (None, "") and float(frame_time) > 0:
            return [i * float(frame_time) / 1000.0 for i in range(frames)]
        cine_rate = getattr(ds, "CineRate", None)                       # frames/s
        if cine_rate not in (None, "") and float(cine_rate) > 0:
            return [i / float(cine_rate) for i in range(frames)]
        return None

    def _image(self, index: int) -> np.ndarray:
        return np.ascontiguousarray(self._stack[index])


class VideoSource(PlaybackSource):
    """A video file (OpenCV), as 8-bit grayscale."""

    def _load(self) -> None:
        import cv2

        self._capture = cv2.VideoCapture(str(self.path))
        if not self._capture.isOpened():
            raise InputDataError(f"{self.path}: OpenCV cannot open this video (unknown container or codec)")
        count = int(self._capture.get(cv2.CAP_PROP_FRAME_COUNT))
        fps = float(self._capture.get(cv2.CAP_PROP_FPS))
        ok, first = self._capture.read()
        if not ok:
            raise InputDataError(f"{self.path}: the video has no readable frame")
        self._pending = self._gray(first)
        self._position = 0
        self._set_format(self._pending, str(self.path))
        self.numbers = list(range(max(count, 1)))
        if fps > 0:
            self.times_s = [i / fps for i in range(len(self.numbers))]

    @staticmethod
    def _gray(image: np.ndarray) -> np.ndarray:
        import cv2

        return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)

    def _rewind(self) -> None:
        import cv2

        self._capture.set(cv2.CAP_PROP_POS_FRAMES, 0)
        self._pending, self._position = None, 0

    def _image(self, index: int) -> np.ndarray:
        if self._pending is not None and index == self._position:
            image, self._pending = self._pending, None
        else:
            ok, raw = self._capture.read()
            if not ok:
                # Containers may announce more frames than they hold; end the pass here.
                self.numbers = self.numbers[:index]
                if self.times_s is not None:
                    self.times_s = self.times_s[:index]
                raise EndOfStream(f"{self.name}: video ended after {index} frames")
            image = self._gray(raw)
        self._position = index + 1
        return image

    def _close_internal(self) -> None:
        capture = getattr(self, "_capture", None)
        if capture is not None:
            capture.release()


def file_source_from_url(url: SourceUrl, **options: Any) -> PlaybackSource:
    """``file://PATH[?plane=..&rate=..&loop=..]`` -> the playback source for that kind of file (not open)."""
    check_known_keys(url, {"plane", "rate", "loop"})
    path = Path(url.netloc + url.path) if url.netloc else Path(url.path)
    kwargs: dict[str, Any] = {"rate": parse_rate(url.take("rate"), url.text), "loop": query_bool(url, "loop", False)}
    plane = url.take("plane")
    if not path.exists():
        raise InputDataError(f"frame source {url.text!r}: {path} does not exist")
    if path.is_dir():
        if plane is None:
            raise InputDataError(f"frame source {url.text!r}: a biplane folder holds two planes; add ?plane=p or ?plane=q")
        kind: type[PlaybackSource] = FolderSource
    else:
        suffix = path.suffix.lower()
        if suffix in (".tif", ".tiff"):
            kind = TiffStackSource
        elif suffix in (".dcm", ".dicom") or _is_dicom(path):
            kind = DicomSource
        elif suffix in VIDEO_SUFFIXES:
            kind = VideoSource
        else:
            raise InputDataError(f"frame source {url.text!r}: cannot tell what {path.name} is; expected a folder, "
                                 f".tif, .dcm or a video ({', '.join(sorted(VIDEO_SUFFIXES))})")
    kwargs["plane"] = plane or "p"
    kwargs.update(options)
    return kind(path, **kwargs)


def _is_dicom(path: Path) -> bool:
    try:
        with path.open("rb") as handle:
            return handle.read(132)[128:132] == b"DICM"
    except OSError:
        return False
