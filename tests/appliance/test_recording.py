"""Session recording: every topic round-trips, the file is a valid MCAP for standard readers and
viewers, frames are decimated as asked, and a file cut off anywhere (crash, power loss, a killed
process) still yields every message flushed before the cut and nothing else."""
from __future__ import annotations

import json
import os
import random
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from appliance import recording_schemas as rs
from appliance.errors import InputDataError
from appliance.recording import Recorder, RecordingError, RecordingReader, jsonable

SHAPE = (48, 64)  # height, width
CONFIG = {"schema_version": 1, "name": "test", "recording": {"frames_every": 1}}
CALIBRATION = {"views": {"p": {"image_size": [64, 48]}, "q": {"image_size": [64, 48]}}, "metadata": {}}
T0 = 1234.5  # the loop's clock has an arbitrary origin


def _images(frame: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(frame)
    return (rng.integers(0, 65536, SHAPE, dtype=np.uint16), rng.integers(0, 65536, SHAPE, dtype=np.uint16))


def _posture(frame: int, t: float) -> dict:
    return {"frame": frame, "t": t, "ok": frame % 4 != 3, "ambiguous": False,
            "centroid_mm": np.array([frame * 0.5, -1.0, 2.0]), "direction": (0.0, 0.0, 1.0),
            "tips_mm": None, "head_identified": True, "length_mm": float("nan"), "reprojection_px": 0.25,
            "views": {"p": None, "q": None}, "reason": None if frame % 4 != 3 else "lost in noise"}


def _write_frame(rec: Recorder, frame: int) -> None:
    """One loop step as the orchestrator writes it: timing last (the frame boundary)."""
    t = T0 + frame / 30.0
    rec.write_posture(t, _posture(frame, t))
    rec.write_command(t, {"frame": frame, "mode": "run", "field_T": [0.0, 0.01, 0.0], "scale": 1.0})
    rec.write_currents(t, measured_a=np.array([0.5, -0.25, frame]), commanded_a=[0.5, -0.25, frame])
    rec.write_ots(t + 0.004, {"handle": "0A", "position_mm": [1.0, 2.0, 3.0], "missing": False})
    rec.write_frames(t, frame, *_images(frame))
    rec.write_timing(t, frame, {"segmentation": 812.5, "control": 40.0})


@pytest.fixture(scope="module")
def closed_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rec") / "session.mcap"
    with Recorder.create(path, config=CONFIG, calibration=CALIBRATION, frames_every=3, fsync=False,
                         threaded=False) as rec:
        for frame in range(10):
            _write_frame(rec, frame)
        rec.write_status(T0 + 0.5, "amplifier", {"state": "enabled", "temperature_c": np.float32(31.5)})
        rec.write_fault(T0 + 0.6, {"device": "amplifier", "reason": "link lost"})
    return path


def test_topics_round_trip(closed_recording: Path) -> None:
    reader = RecordingReader(closed_recording)
    assert reader.config == CONFIG and reader.calibration == CALIBRATION
    assert reader.session["format_version"] == rs.FORMAT_VERSION and reader.session["frames_every"] == 3
    postures = list(reader.messages(rs.TOPIC_POSTURE))
    assert [m["frame"] for _, _, m in postures] == list(range(10))
    topic, t_s, first = postures[0]
    assert topic == "/posture" and t_s == pytest.approx(T0, abs=1e-9)
    assert postures[9][1] == pytest.approx(T0 + 9 / 30.0, abs=1e-9)
    # numpy became plain JSON; an unknown (NaN) number became null, never a made-up value
    assert first["centroid_mm"] == [0.0, -1.0, 2.0] and first["length_mm"] is None
    assert postures[3][2]["ok"] is False and postures[3][2]["reason"] == "lost in noise"
    currents = [m for _, _, m in reader.messages("/currents")]
    assert currents[7] == {"measured_a": [0.5, -0.25, 7], "commanded_a": [0.5, -0.25, 7]}
    (_, t_ots, ots), = list(reader.messages("/ots"))[:1]
    assert t_ots == pytest.approx(T0 + 0.004, abs=1e-9) and ots["handle"] == "0A"
    (_, _, status), = reader.messages("/status")
    assert status == {"device": "amplifier", "state": "enabled", "temperature_c": 31.5}
    (_, t_fault, fault), = reader.messages("/fault")
    assert t_fault == pytest.approx(T0 + 0.6) and fault["reason"] == "link lost"
    timing = [m for _, _, m in reader.messages("/timing")]
    assert timing[4] == {"frame": 4, "stages_us": {"segmentation": 812.5, "control": 40.0}}
    # the default selection leaves out images and bookkeeping topics
    assert {name for name, _, _ in reader.messages()} == {"/posture", "/command", "/currents", "/ots", "/status",
                                                           "/fault", "/timing"}


def test_frames_are_decimated_and_exact(closed_recording: Path) -> None:
    reader = RecordingReader(closed_recording)
    frames = list(reader.frames())
    assert [number for number, *_ in frames] == [0, 3, 6, 9]  # the first, then every 3rd offered pair
    for number, t_s, image_p, image_q in frames:
        expected_p, expected_q = _images(number)
        assert image_p.dtype == np.uint16 and np.array_equal(image_p, expected_p)
        assert np.array_equal(image_q, expected_q)
        assert t_s == pytest.approx(T0 + number / 30.0, abs=1e-9)
    summary = reader.summary()
    assert summary.complete and summary.stop_reason is None and summary.frames == 4
    assert summary.messages["/posture"] == 10 and summary.messages["/xray/p/image"] == 4
    assert summary.first_t_s == pytest.approx(T0) and summary.last_t_s == pytest.approx(T0 + 0.6)


def test_standard_mcap_reader_and_viewer_schemas(closed_recording: Path) -> None:
    """The strict, seeking reader of the mcap library (what tools use) accepts the file; channels are JSON
    with JSON Schemas, and the images are foxglove.RawImage mono16 as the Image panel expects."""
    with closed_recording.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count > 0
        topics = {channel.topic: channel for channel in summary.channels.values()}
        assert set(rs.SCHEMAS) | set(rs.TOPIC_IMAGE.values()) == set(topics)
        for channel in topics.values():
            schema = summary.schemas[channel.schema_id]
            assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
            json.loads(schema.data)
        image_schema = summary.schemas[topics["/xray/q/image"].schema_id]
        assert image_schema.name == "foxglove.RawImage"
        seen = 0
        for _, channel, message in reader.iter_messages(topics=["/xray/q/image"]):
            image = json.loads(message.data)
            assert image["encoding"] == "mono16" and image["step"] == 2 * image["width"] == 128
            assert image["height"] == 48 and image["frame_id"] == "xray_q"
            assert image["timestamp"]["sec"] * 10**9 + image["timestamp"]["nsec"] == message.log_time
            seen += 1
        assert seen == 4


def _write_unclosed(path: Path, frames: int) -> list[tuple[int, int, int]]:
    """Write ``frames`` frames and leave the file open (as at a crash); returns (file size, messages so
    far, image pairs so far) after each frame, i.e. what a cut at or after that size must still deliver."""
    stream = path.open("xb")
    rec = Recorder(stream, path=path, config=CONFIG, calibration=CALIBRATION, frames_every=2, fsync=False,
                   threaded=False)
    boundaries = [(path.stat().st_size, 0, 0)]
    for frame in range(frames):
        _write_frame(rec, frame)
        # posture, command, currents, ots, timing per frame; images of frames 0, 2, 4...
        boundaries.append((path.stat().st_size, 5 * (frame + 1), frame // 2 + 1))
    stream.close()  # the process died: no summary, no footer
    with pytest.raises(ValueError, match="closed file"):
        rec.close()  # its file is gone: closing fails loudly (and the exit hook has nothing left to do)
    return boundaries


def test_crash_while_open_loses_nothing_flushed(tmp_path: Path) -> None:
    path = tmp_path / "crashed.mcap"
    _write_unclosed(path, 6)
    reader = RecordingReader(path)
    assert [m["frame"] for _, _, m in reader.messages("/posture")] == list(range(6))
    assert [number for number, *_ in reader.frames()] == [0, 2, 4]
    assert reader.complete is False and "without a footer" in (reader.stop_reason or "")


def test_cut_at_any_offset_recovers_every_complete_frame(tmp_path: Path) -> None:
    source = tmp_path / "full.mcap"
    boundaries = _write_unclosed(source, 8)
    data = source.read_bytes()
    everything = [(name, m) for name, _, m in RecordingReader(source).messages()]
    rng = random.Random(11)
    header_end = boundaries[0][0]
    cuts = sorted({rng.randrange(header_end, len(data)) for _ in range(40)} | {b for b, _, _ in boundaries[1:]})
    for cut in cuts:
        path = tmp_path / f"cut{cut}.mcap"
        path.write_bytes(data[:cut])
        reader = RecordingReader(path)
        got = [(name, m) for name, _, m in reader.messages()]
        flushed, flushed_pairs = max((count, pairs) for size, count, pairs in boundaries if size <= cut)
        assert got == everything[:len(got)], f"cut at {cut}: not a prefix of what was written"
        assert len(got) >= flushed, f"cut at {cut}: {len(got)} messages, {flushed} were flushed before it"
        assert reader.complete is False and reader.stop_reason
        pairs = [number for number, *_ in reader.frames()]
        assert pairs == [0, 2, 4, 6][:len(pairs)] and len(pairs) >= flushed_pairs, f"cut at {cut}: pairs {pairs}"


def test_cut_in_the_summary_keeps_every_message(closed_recording: Path, tmp_path: Path) -> None:
    data = closed_recording.read_bytes()
    for cut in (len(data) - 1, len(data) - 40, len(data) - 200):
        path = tmp_path / f"tail{cut}.mcap"
        path.write_bytes(data[:cut])
        summary = RecordingReader(path).summary()
        assert summary.messages["/posture"] == 10 and summary.frames == 4


def test_garbage_after_the_last_flush_is_ignored(tmp_path: Path) -> None:
    """Some file systems leave zeros or stale blocks past the last write after a power loss."""
    source = tmp_path / "source.mcap"
    _write_unclosed(source, 3)
    data = source.read_bytes()
    for tail in (bytes(4096), os.urandom(4096), b"\x05" + (10**12).to_bytes(8, "little") + b"x" * 100):
        path = tmp_path / "garbage.mcap"
        path.write_bytes(data + tail)
        reader = RecordingReader(path)
        assert [m["frame"] for _, _, m in reader.messages("/posture")] == [0, 1, 2]
        assert [number for number, *_ in reader.frames()] == [0, 2]
        assert reader.complete is False


def test_killed_writer_process(tmp_path: Path) -> None:
    """A real crash: a process writes frames, then dies without closing anything."""
    path = tmp_path / "killed.mcap"
    script = textwrap.dedent(f"""
        import os, numpy as np
        from appliance.recording import Recorder
        rec = Recorder.create({str(path)!r}, config={{}}, calibration={{"views": {{}}}})
        for frame in range(5):
            t = frame / 30.0
            rec.write_posture(t, {{"frame": frame, "ok": True}})
            rec.write_frames(t, frame, np.full((48, 64), frame, np.uint16), np.zeros((48, 64), np.uint16))
            rec.write_timing(t, frame, {{"total": 1.0}})
        rec.write_posture(5 / 30.0, {{"frame": 5, "ok": True}})  # the frame being written when it died
        os._exit(3)
    """)
    done = subprocess.run([sys.executable, "-c", script], cwd=Path(__file__).parents[2], timeout=60)
    assert done.returncode == 3
    reader = RecordingReader(path)
    # Threaded writer, max_lag_frames=1: when frame 4's timing returned, frames 0-3 were on disk.
    postures = [m["frame"] for _, _, m in reader.messages("/posture")]
    assert postures == list(range(len(postures))) and len(postures) >= 4
    pairs = [(n, int(p[0, 0])) for n, _, p, _ in reader.frames()]
    assert pairs == [(n, n) for n in range(len(pairs))] and len(pairs) + reader.summary().messages["/status"] >= 4


def test_a_recorder_left_open_is_closed_at_exit(tmp_path: Path) -> None:
    path = tmp_path / "forgotten.mcap"
    script = textwrap.dedent(f"""
        import numpy as np
        from appliance.recording import Recorder
        rec = Recorder.create({str(path)!r}, config={{}}, calibration={{"views": {{}}}})
        for frame in range(3):
            rec.write_frames(frame / 30.0, frame, np.zeros((48, 64), np.uint16), np.zeros((48, 64), np.uint16))
            rec.write_timing(frame / 30.0, frame, {{"total": 1.0}})
    """)
    subprocess.run([sys.executable, "-c", script], cwd=Path(__file__).parents[2], timeout=60, check=True)
    reader = RecordingReader(path)
    assert [n for n, *_ in reader.frames()] == [0, 1, 2] and reader.complete


@pytest.mark.parametrize("threaded", [False, True])
def test_every_frame_boundary_is_forced_to_disk(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                threaded: bool) -> None:
    synced: list[int] = []
    real_fsync = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (synced.append(fd), real_fsync(fd))[1])
    with Recorder.create(tmp_path / "s.mcap", config={}, calibration={"views": {}}, threaded=threaded) as rec:
        at_start = len(synced)
        for frame in range(4):
            _write_frame(rec, frame)
            if not threaded:
                assert len(synced) >= at_start + frame + 1
        rec.write_fault(1.0, {"device": "amplifier", "reason": "test"})
        assert len(synced) >= at_start + 5  # the fault returns once it is on disk, threaded or not
    assert at_start >= 1  # the config and calibration are on disk before the first frame


def test_side_channels_are_flushed_while_imaging_is_silent(tmp_path: Path) -> None:
    path = tmp_path / "silent.mcap"
    stream = path.open("xb")
    rec = Recorder(stream, path=path, config={}, calibration={"views": {}}, fsync=False, threaded=False)
    for k in range(10):
        rec.write_ots(k * 0.05, {"handle": "01", "k": k})  # 0.45 s of OTS samples, no frame boundary
    stream.close()
    with pytest.raises(ValueError, match="closed file"):
        rec.close()
    got = [m["k"] for _, _, m in RecordingReader(path).messages("/ots")]
    assert got[:4] == [0, 1, 2, 3] and len(got) >= 7  # at most max_unflushed_s (0.1 s) of them lost


def test_threaded_writer_writes_what_the_direct_one_does(tmp_path: Path) -> None:
    contents = []
    for threaded in (False, True):
        path = tmp_path / f"threaded_{threaded}.mcap"
        with Recorder.create(path, config=CONFIG, calibration=CALIBRATION, fsync=False, threaded=threaded) as rec:
            for frame in range(5):
                _write_frame(rec, frame)
                rec.flush()  # paced like a loop whose disk keeps up: nothing is dropped
            assert rec.images_dropped == 0
            # A copy taken while the recorder is still open (as a crash would leave it) reads in full.
            copy = tmp_path / f"copy_{threaded}.mcap"
            copy.write_bytes(path.read_bytes())
            assert [n for n, *_ in RecordingReader(copy).frames()] == [0, 1, 2, 3, 4]
        reader = RecordingReader(path)
        contents.append(([(n, m) for n, _, m in reader.messages()],
                         [(n, p.tobytes(), q.tobytes()) for n, _, p, q in reader.frames()]))
    assert contents[0] == contents[1] and len(contents[0][1]) == 5


class _StalledDisk:
    """A file whose writes block until released: the disk is slower than the loop."""

    def __init__(self, path: Path) -> None:
        self._file = path.open("xb")
        self.release = threading.Event()
        self.release.set()

    def write(self, data: bytes) -> int:
        self.release.wait(timeout=30)
        return self._file.write(data)

    def flush(self) -> None:
        self._file.flush()

    def tell(self) -> int:
        return self._file.tell()

    def fileno(self) -> int:
        return self._file.fileno()

    def close(self) -> None:
        self._file.close()


def test_images_are_dropped_not_the_loop_stalled_when_the_disk_is_slow(tmp_path: Path) -> None:
    path = tmp_path / "slow.mcap"
    disk = _StalledDisk(path)
    rec = Recorder(disk, path=path, config={}, calibration={"views": {}}, fsync=False, max_pending_images=2)
    disk.release.clear()
    kept = [rec.write_frames(k / 30.0, k, *_images(k)) for k in range(5)]  # returns although nothing is written
    rec.write_posture(0.2, {"frame": 4, "ok": True})
    assert kept == [True, True, False, False, False] and rec.images_dropped == 3
    disk.release.set()
    rec.close()
    reader = RecordingReader(path)
    assert [n for n, *_ in reader.frames()] == [0, 1]
    assert [m["images_dropped"] for _, _, m in reader.messages("/status")] == [1, 2, 3]
    assert [m["frame"] for _, _, m in reader.messages("/posture")] == [4]


def test_a_write_error_on_the_writer_thread_reaches_the_caller(tmp_path: Path) -> None:
    path = tmp_path / "full.mcap"
    disk = _StalledDisk(path)
    rec = Recorder(disk, path=path, config={}, calibration={"views": {}}, fsync=False)

    def disk_full(data: bytes) -> int:
        raise OSError(28, "No space left on device")

    disk.write = disk_full  # type: ignore[method-assign]
    rec.write_posture(0.0, {"frame": 0})
    with pytest.raises(RecordingError, match="full.mcap: cannot write the recording \\(No space left on device\\)"):
        for frame in range(3):
            rec.write_timing(frame / 30.0, frame, {"total": 1.0})
    with pytest.raises(RecordingError, match="No space left"):
        rec.close()


def test_errors(tmp_path: Path) -> None:
    with pytest.raises(InputDataError, match="nowhere.mcap: file not found"):
        RecordingReader(tmp_path / "nowhere.mcap")
    with pytest.raises(InputDataError, match="is a folder"):
        RecordingReader(tmp_path)
    (tmp_path / "text.mcap").write_text("frame,t\n1,0.0\n")
    with pytest.raises(InputDataError, match="text.mcap: not an MCAP recording"):
        RecordingReader(tmp_path / "text.mcap")
    (tmp_path / "empty.mcap").write_bytes(b"")
    with pytest.raises(InputDataError, match="empty.mcap: empty or cut off"):
        RecordingReader(tmp_path / "empty.mcap")
    path = tmp_path / "a" / "b" / "s.mcap"   # folders are made
    rec = Recorder.create(path, config={}, calibration={"views": {}}, fsync=False)
    with pytest.raises(RecordingError, match="exists; it is not overwritten"):
        Recorder.create(path, config={}, calibration={})
    with pytest.raises(ValueError, match="frame 7: image q must be a 2-D uint16 array, got float64"):
        rec.write_frames(0.0, 7, np.zeros(SHAPE, np.uint16), np.zeros(SHAPE))
    with pytest.raises(TypeError, match="posture.views.p"):
        rec.write_posture(0.0, {"frame": 1, "views": {"p": object()}})
    rec.close()
    rec.close()  # idempotent
    with pytest.raises(RecordingError, match="closed"):
        rec.write_posture(1.0, {"frame": 1})
    with pytest.raises(ValueError, match="frames_every"):
        Recorder.create(tmp_path / "x.mcap", config={}, calibration={}, frames_every=0)
    assert not (tmp_path / "x.mcap").exists()  # checked before the file is made


def test_jsonable_plain_types() -> None:
    assert jsonable({"a": np.int64(3), "b": (np.float32(0.5), np.inf), "c": np.bool_(True), "d": Path("x")}) == \
        {"a": 3, "b": [0.5, None], "c": True, "d": "x"}
