"""The biplane frame folder: recorded or generated X-ray frame pairs on disk (architecture.md contract).

Layout::

    DIR/p/NNNNNN.png|tif    plane p, frame number NNNNNN (six or more digits)
    DIR/q/NNNNNN.png|tif    plane q; the same number is the same exposure
    DIR/calibration.yaml    optional: the views the frames were taken with

Frames are 16-bit grayscale raw detector intensity (the robot is darker than its surroundings). 8-bit
or colour files are *rejected*, not converted: an 8-bit export has already lost the dynamic range the
attenuation-based recognition relies on, and a colour file is not detector data; the message says so
and names the file. Every error is an :class:`InputDataError` naming the file and the frame number.

This module is the folder contract only (listing, pairing, reading, writing); the file frame source
that replays a folder at a frame rate builds on it.
"""
from __future__ import annotations

import logging
import re
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from drivers.errors import InputDataError

log = logging.getLogger(__name__)

PLANES = ("p", "q")
FORMATS = {"png": ".png", "tif": ".tif", "tiff": ".tif"}
CALIBRATION_FILE = "calibration.yaml"
_FRAME_NAME = re.compile(r"^(\d{6,})\.(png|tif|tiff)$", re.IGNORECASE)


def frame_name(number: int, fmt: str = "png") -> str:
    """``12, "png"`` -> ``000012.png``."""
    if fmt.lower() not in FORMATS:
        raise ValueError(f"frame format must be one of {sorted(FORMATS)}, got {fmt!r}")
    if number < 0:
        raise ValueError(f"frame numbers are non-negative, got {number}")
    return f"{number:06d}{FORMATS[fmt.lower()]}"


def _check_plane(plane: str) -> None:
    if plane not in PLANES:
        raise ValueError(f"plane must be one of {PLANES}, got {plane!r}")


class BiplaneFolder:
    """A biplane frame folder, listed once at construction.

    ``expected_sizes`` (plane -> (width, height)), e.g. from the calibration's views, makes every read
    check the frame against it; otherwise each plane's first frame read sets the size the others must have.
    """

    def __init__(self, root: str | Path, *, expected_sizes: dict[str, tuple[int, int]] | None = None) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            what = "is not a folder" if self.root.exists() else "no such folder"
            raise InputDataError(f"{self.root}: {what} (expected a biplane frame folder with p/ and q/)")
        missing = [plane for plane in PLANES if not (self.root / plane).is_dir()]
        if missing:
            raise InputDataError(f"{self.root}: not a biplane frame folder: no {' or '.join(f'{m}/' for m in missing)}"
                                 " subfolder (expected DIR/p/NNNNNN.png and DIR/q/NNNNNN.png)")
        self._files: dict[str, dict[int, Path]] = {plane: self._list(plane) for plane in PLANES}
        numbers = {plane: set(files) for plane, files in self._files.items()}
        self.frame_numbers: list[int] = sorted(numbers["p"] & numbers["q"])
        self.unpaired: dict[str, list[int]] = {
            plane: sorted(numbers[plane] - numbers[other]) for plane, other in (("p", "q"), ("q", "p"))}
        calibration = self.root / CALIBRATION_FILE
        self.calibration_path: Path | None = calibration if calibration.is_file() else None
        self._sizes: dict[str, tuple[int, int]] = dict(expected_sizes or {})
        self._size_from: dict[str, str] = {plane: "the calibration" for plane in self._sizes}
        if any(self.unpaired.values()):
            log.warning("%s: frames without a partner: %s", self.root,
                        ", ".join(f"{plane}: {_summary(nums)}" for plane, nums in self.unpaired.items() if nums))

    def _list(self, plane: str) -> dict[int, Path]:
        files: dict[int, Path] = {}
        for path in sorted((self.root / plane).iterdir()):
            match = _FRAME_NAME.match(path.name)
            if not match or not path.is_file():
                if path.suffix.lower() in (".png", ".tif", ".tiff"):
                    log.warning("%s: ignored: not named NNNNNN%s", path, path.suffix)
                continue
            number = int(match.group(1))
            if number in files:
                raise InputDataError(f"{self.root / plane}: frame {number} exists twice: "
                                     f"{files[number].name} and {path.name}")
            files[number] = path
        return files

    def __len__(self) -> int:
        return len(self.frame_numbers)

    def __repr__(self) -> str:
        return f"BiplaneFolder({str(self.root)!r}, {len(self)} pairs)"

    def path(self, plane: str, number: int) -> Path:
        """The file of ``number`` in ``plane``; :class:`InputDataError` if there is none."""
        _check_plane(plane)
        try:
            return self._files[plane][number]
        except KeyError:
            raise InputDataError(f"{self.root / plane}: no frame {number} "
                                 f"(expected {self.root / plane / frame_name(number)})") from None

    def read(self, plane: str, number: int) -> np.ndarray:
        """Frame ``number`` of ``plane`` as uint16 (h, w)."""
        path = self.path(plane, number)
        image = read_image(path, f"frame {number}")
        h, w = image.shape
        expected = self._sizes.setdefault(plane, (w, h))
        self._size_from.setdefault(plane, f"frame {number}")
        if (w, h) != expected:
            raise InputDataError(f"{path}: frame {number} is {w}x{h} pixels but plane {plane} is "
                                 f"{expected[0]}x{expected[1]} (from {self._size_from[plane]})")
        return image

    def read_pair(self, number: int) -> tuple[np.ndarray, np.ndarray]:
        """Both planes of frame ``number``: ``(image_p, image_q)``."""
        if number not in self._files["p"] or number not in self._files["q"]:
            have = [plane for plane in PLANES if number in self._files[plane]]
            where = f"only in plane {have[0]}" if have else "in neither plane"
            raise InputDataError(f"{self.root}: frame {number} is {where}; a pair needs p/ and q/")
        return self.read("p", number), self.read("q", number)

    def pairs(self) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        """``(number, image_p, image_q)`` for every paired frame, in order."""
        for number in self.frame_numbers:
            image_p, image_q = self.read_pair(number)
            yield number, image_p, image_q


def read_image(path: Path, what: str = "image") -> np.ndarray:
    """Decode a 16-bit grayscale PNG or TIFF; anything else is an :class:`InputDataError` naming ``path``."""
    try:
        data = path.read_bytes()
    except OSError as err:
        raise InputDataError(f"{path}: {what}: cannot read ({err.strerror or err})") from err
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED) if data else None
    if image is None:
        raise InputDataError(f"{path}: {what}: not a readable PNG or TIFF image"
                             f"{' (empty file)' if not data else ''}")
    if image.ndim != 2:
        raise InputDataError(f"{path}: {what}: has {image.shape[2]} channels; frames must be grayscale "
                             "raw detector intensity (colour files are rejected, not converted)")
    if image.dtype != np.uint16:
        raise InputDataError(f"{path}: {what}: is {image.dtype} ({image.dtype.itemsize * 8}-bit); frames must be "
                             "16-bit raw detector intensity (8-bit exports lose the dynamic range the "
                             "recognition needs, so they are rejected, not converted)")
    return image


def write_frame(root: str | Path, plane: str, number: int, image: np.ndarray, fmt: str = "png") -> Path:
    """Write ``image`` (uint16, h x w) as ``root/plane/NNNNNN.<fmt>``; returns the path."""
    _check_plane(plane)
    image = np.asarray(image)
    if image.dtype != np.uint16 or image.ndim != 2:
        raise ValueError(f"frames are uint16 (h, w); got {image.dtype} {image.shape}")
    path = Path(root) / plane / frame_name(number, fmt)
    ok, encoded = cv2.imencode(path.suffix, image)
    if not ok:
        raise InputDataError(f"{path}: cannot encode frame {number} as {fmt}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(encoded.tobytes())
    except OSError as err:
        raise InputDataError(f"{path}: cannot write frame {number} ({err.strerror or err})") from err
    return path


def _summary(numbers: list[int], shown: int = 8) -> str:
    head = ", ".join(str(n) for n in numbers[:shown])
    return head + (f" ... ({len(numbers)} in all)" if len(numbers) > shown else "")
