"""File sources for every format, written by the tests: biplane folders (PNG/TIFF), multi-page TIFF,
multi-frame DICOM, video; pacing at recorded/fixed/max rate; looping; clear errors."""
from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile

from drivers.biplane_folder import write_frame
from drivers.biplane_pairing import BiplanePairer, BiplaneStream
from drivers.errors import InputDataError
from drivers.file_sources import TIMESTAMP_COLUMNS, TIMESTAMPS_FILE, DicomSource, FolderSource
from drivers.frame_source import EndOfStream, FrameSource, open_source

W, H = 64, 48


def images(count: int, seed: int = 0, dtype: type = np.uint16) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    top = 65535 if dtype == np.uint16 else 255
    return [rng.integers(0, top, size=(H, W), dtype=dtype) for _ in range(count)]


def read_all(source: FrameSource) -> list:
    out = []
    with source:
        while True:
            try:
                out.append(source.read(5.0))
            except EndOfStream:
                return out


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0
        self.slept: list[float] = []

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.slept.append(seconds)
        self.now += seconds


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("biplane")
    for n, (p, q) in enumerate(zip(images(6, 1), images(6, 2)), start=10):
        write_frame(root, "p", n, p, fmt="png")
        write_frame(root, "q", n, q, fmt="tif")
    with (root / TIMESTAMPS_FILE).open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(TIMESTAMP_COLUMNS)
        for n in range(10, 16):
            for plane in "pq":
                writer.writerow([plane, n, 100 + (n - 10) * 0.04, 0.0, 0.005])
    return root


def test_folder_planes_replay_files_and_recorded_times(folder: Path) -> None:
    got = {plane: read_all(open_source(f"file://{folder}?plane={plane}")) for plane in "pq"}
    for plane, seed in (("p", 1), ("q", 2)):
        assert [f.number for f in got[plane]] == list(range(10, 16))
        assert all(np.array_equal(f.image, ref) for f, ref in zip(got[plane], images(6, seed)))
        assert [f.device_time_s for f in got[plane]] == pytest.approx([i * 0.04 for i in range(6)])
        assert all(f.exposure_s == 0.005 and f.pixel_format == "mono16" for f in got[plane])


def test_folder_planes_pair_through_a_stream(folder: Path) -> None:
    sources = [open_source(f"file://{folder}?plane={plane}") for plane in "pq"]
    numbers = []
    with BiplaneStream(sources, BiplanePairer(mode="all")) as stream:
        with pytest.raises(EndOfStream):
            while True:
                numbers.append(stream.next_pair(5.0).number)
    assert numbers == list(range(10, 16))


def test_pacing_fixed_recorded_and_max_and_looping(folder: Path) -> None:
    clock = FakeClock()
    source = FolderSource(folder, plane="p", rate=10.0, clock=clock, sleep=clock.sleep)
    read_all(source)
    assert sum(clock.slept) == pytest.approx(0.5)          # six frames at 10 Hz: the last is due at 0.5 s
    clock = FakeClock()
    read_all(FolderSource(folder, plane="p", rate="recorded", clock=clock, sleep=clock.sleep))
    assert sum(clock.slept) == pytest.approx(0.2)          # recorded 40 ms apart
    clock = FakeClock()
    read_all(FolderSource(folder, plane="p", clock=clock, sleep=clock.sleep))
    assert clock.slept == []
    looped = FolderSource(folder, plane="q", loop=True)
    with looped:
        frames = [looped.read(1.0) for _ in range(14)]
    assert [f.number for f in frames] == list(range(10, 24))           # numbers keep increasing
    assert all(b.device_time_s > a.device_time_s for a, b in zip(frames, frames[1:]))
    assert np.array_equal(frames[6].image, frames[0].image) and looped.counters.dropped == 0


def test_multipage_tiff(tmp_path: Path) -> None:
    stack = np.stack(images(5, 3))
    path = tmp_path / "run.tif"
    tifffile.imwrite(path, stack, imagej=True, metadata={"finterval": 0.05, "axes": "TYX"})
    got = read_all(open_source(f"file://{path}?plane=q"))
    assert [f.number for f in got] == [0, 1, 2, 3, 4] and all(f.plane == "q" for f in got)
    assert all(np.array_equal(f.image, ref) for f, ref in zip(got, stack))
    assert [f.device_time_s for f in got] == pytest.approx([0, 0.05, 0.1, 0.15, 0.2])
    plain = tmp_path / "plain.tif"
    for page in images(3, 4, np.uint8):      # page by page, as a grabber's recorder appends them
        tifffile.imwrite(plain, page, append=True, photometric="minisblack")
    got = read_all(open_source(f"file://{plain}"))
    assert len(got) == 3 and got[0].pixel_format == "mono8"
    assert [f.device_time_s for f in got] == pytest.approx([0, 1 / 30, 2 / 30])   # no recorded times: nominal


def write_dicom(path: Path, stack: np.ndarray, *, photometric: str = "MONOCHROME2", **tags: object) -> None:
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.12.1"   # X-Ray Angiographic Image Storage
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = meta.MediaStorageSOPClassUID
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.Modality = "XA"
    ds.NumberOfFrames = len(stack)
    ds.Rows, ds.Columns = stack.shape[1:]
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = photometric
    ds.BitsAllocated = ds.BitsStored = 16
    ds.HighBit = 15
    ds.PixelRepresentation = 0
    for key, value in tags.items():
        setattr(ds, key, value)
    ds.PixelData = stack.astype("<u2").tobytes()
    ds.save_as(path, enforce_file_format=True)


def test_multiframe_dicom(tmp_path: Path) -> None:
    stack = np.stack(images(4, 5))
    path = tmp_path / "carm.dcm"
    write_dicom(path, stack, FrameTime=66.7, ExposureTime=8)
    got = read_all(open_source(f"file://{path}?plane=p"))
    assert all(np.array_equal(f.image, ref) for f, ref in zip(got, stack)) and len(got) == 4
    assert [f.device_time_s for f in got] == pytest.approx([0, 0.0667, 0.1334, 0.2001])
    assert all(f.exposure_s == pytest.approx(0.008) for f in got)
    vector = tmp_path / "vector"          # no suffix: recognised by the DICM preamble
    write_dicom(vector, stack, FrameTimeVector=[0, 40, 40, 80])
    got = read_all(open_source(f"file://{vector}"))
    assert [f.device_time_s for f in got] == pytest.approx([0, 0.04, 0.08, 0.16])
    inverted = tmp_path / "mono1.dcm"
    write_dicom(inverted, stack, photometric="MONOCHROME1")
    first = read_all(DicomSource(inverted))[0]
    assert np.array_equal(first.image, 65535 - stack[0])


def test_video(tmp_path: Path) -> None:
    path = tmp_path / "monitor.avi"
    frames = [np.full((H, W), 40 * i + 20, dtype=np.uint8) for i in range(5)]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (W, H))
    assert writer.isOpened()
    for frame in frames:
        writer.write(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR))
    writer.release()
    got = read_all(open_source(f"file://{path}"))
    assert len(got) == 5 and all(f.pixel_format == "mono8" and f.image.shape == (H, W) for f in got)
    assert all(abs(float(f.image.mean()) - float(ref.mean())) < 3 for f, ref in zip(got, frames))  # lossy codec
    assert [f.device_time_s for f in got] == pytest.approx([0, 0.04, 0.08, 0.12, 0.16])


def test_clear_errors(tmp_path: Path, folder: Path) -> None:
    with pytest.raises(InputDataError, match="does not exist"):
        open_source(f"file://{tmp_path}/nothing")
    with pytest.raises(InputDataError, match=r"add \?plane=p"):
        open_source(f"file://{folder}")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(InputDataError, match="cannot tell what notes.txt is"):
        open_source(f"file://{tmp_path}/notes.txt")
    with pytest.raises(InputDataError, match="rate='fast'"):
        open_source(f"file://{folder}?plane=p&rate=fast")
    with pytest.raises(InputDataError, match="unknown option"):
        open_source(f"file://{folder}?plane=p&speed=2")
    (tmp_path / "broken.tif").write_bytes(b"II*\x00garbage")
    with pytest.raises(InputDataError, match="not a readable TIFF"):
        open_source(f"file://{tmp_path}/broken.tif").open()
    eight = tmp_path / "eight"
    for plane in "pq":
        (eight / plane).mkdir(parents=True)
        cv2.imwrite(str(eight / plane / "000001.png"), images(1, 6, np.uint8)[0])
    with pytest.raises(InputDataError, match="8-bit"):
        open_source(f"file://{eight}?plane=p").open()
