"""Session recording: one append-only MCAP file per session that survives a crash or a power loss.

:class:`Recorder` writes everything the loop sees and does (postures, commands, measured currents,
optical-tracker samples, faults, device status, per-frame stage timings, the config and calibration
used, and the X-ray frames, all or every n-th) as MCAP messages that Foxglove and Lichtblick open
directly; the topics and their JSON Schemas are in :mod:`appliance.recording_schemas`.

Durability. Messages collect in the current MCAP chunk; at a *frame boundary* the chunk is closed,
written, flushed to the operating system and (``fsync=True``, the default) forced to the disk. A
frame boundary is :meth:`Recorder.write_timing` (the loop writes a frame's timing last, once the
frame's work is done), :meth:`Recorder.write_frames` and :meth:`Recorder.flush`; a chunk that spans
more than ``max_unflushed_s`` of loop time is closed too, so side channels are kept while the imaging
chain is silent. :meth:`Recorder.write_fault` returns only once the fault and everything before it
are on disk. The writing itself runs on a background thread (``threaded=True``, the default) so the
loop does not wait for base64, compression or ``fsync``; when ``write_timing`` of frame n returns,
frame n-1 is on disk (``max_lag_frames=1``). So a crash or power loss loses at most the last frame
and the one being written (``threaded=False``: only the one being written, at the loop's expense).
The summary and indexes that make seeking fast are appended by :meth:`Recorder.close`; a file cut
off before that still reads.

Times. ``t_s`` is the loop's clock (monotonic, seconds, any origin). MCAP log times are nanoseconds
of the wall clock: the first ``t_s`` written (or ``t0_s``) is mapped to the wall-clock time at which
the recording was created, so a viewer shows real dates and the reader gives back ``t_s``.

:class:`RecordingReader` reads a recording with the ``mcap`` library's record-level stream reader
(CRCs checked) over a file object that refuses short reads, so a file cut off anywhere (mid-record,
mid-chunk, in the summary) yields every complete message before the cut and records why it stopped
(:attr:`RecordingReader.stop_reason`).
"""
from __future__ import annotations

import atexit
import datetime as _dt
import json
import logging
import math
import os
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import IO, Any

import numpy as np

from appliance import recording_schemas as rs
from appliance.errors import ApplianceError
from appliance.recording_reader import RecordingReader, RecordingSummary
from appliance.recording_sink import COMPRESSIONS, BackgroundWriter, McapSink

log = logging.getLogger(__name__)

__all__ = ["Recorder", "RecordingError", "RecordingReader", "RecordingSummary", "jsonable"]


class RecordingError(ApplianceError, OSError):
    """The recording cannot be created or written (disk full, no permission, file exists, closed)."""


#: Recorders not closed yet. At interpreter exit they are closed, so what the background thread still
#: holds reaches the file (a daemon thread would otherwise die with it) and the summary is written.
#: A strong set: a forgotten recorder must stay reachable until then (its thread holds only the sink).
_OPEN: set[Recorder] = set()


@atexit.register
def _close_forgotten() -> None:
    for recorder in list(_OPEN):
        log.warning("%s: recording still open at exit; closing it", recorder.path)
        try:
            recorder.close()
        except Exception as err:  # noqa: BLE001 - at exit there is no caller left to raise to
            log.error("%s: could not close the recording at exit: %s", recorder.path, err)


def jsonable(value: Any, where: str = "") -> Any:
    """``value`` as plain JSON types: numpy arrays and scalars become lists and numbers, tuples lists,
    paths strings, and non-finite floats ``null`` (the posture contract: unknown numbers are null)."""
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, (int, np.integer)) and not isinstance(value, np.bool_):
        return int(value)
    if isinstance(value, (float, np.floating)):
        number = float(value)
        return number if math.isfinite(number) else None
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist(), where)
    if isinstance(value, Mapping):
        return {str(key): jsonable(item, f"{where}.{key}" if where else str(key)) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(item, f"{where}[{index}]") for index, item in enumerate(value)]
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    raise TypeError(f"cannot record {where or 'value'}: {type(value).__name__} is not JSON data")


def _check_options(frames_every: int, compression: str) -> None:
    if frames_every < 1:
        raise ValueError(f"frames_every must be >= 1, got {frames_every}")
    if compression not in COMPRESSIONS:
        raise ValueError(f"compression must be one of {sorted(COMPRESSIONS)}, got {compression!r}")


def _encode(value: Mapping[str, Any], what: str) -> bytes:
    return json.dumps(jsonable(value, what), separators=(",", ":"), allow_nan=False).encode("utf-8")


class Recorder:
    """Writes one session's MCAP recording; see the module docstring. Context manager; ``close`` is
    idempotent. Thread-safe (one lock), though the loop normally writes from its owner thread only.

    ``threaded`` (default): a background thread encodes, compresses and writes, so a frame costs the
    loop only the JSON encoding of its records and a copy of its images; a frame boundary waits only
    while more than ``max_lag_frames`` earlier frames are still unwritten. An image pair offered
    while ``max_pending_images`` pairs still wait to be written is dropped (counted in
    ``images_dropped`` and reported on ``/status`` as device ``recorder``): the disk must not stall
    the coils' control. Structured messages are never dropped.
    ``threaded=False`` writes in the caller's thread (a frame boundary returns once it is on disk)."""

    def __init__(self, stream: IO[bytes], *, path: Path, config: Mapping[str, Any],
                 calibration: Mapping[str, Any], frames_every: int = 1, compression: str = "zstd",
                 fsync: bool = True, t0_s: float | None = None, max_unflushed_s: float = 0.1,
                 threaded: bool = True, max_lag_frames: int = 1, max_pending_images: int = 2) -> None:
        _check_options(frames_every, compression)
        self.path = path
        self.frames_every = int(frames_every)
        self._max_unflushed_s = max_unflushed_s
        self._max_pending_images = max_pending_images
        self._lock = threading.Lock()
        self._closed = False
        self._frames_offered = 0
        self.frames_written = 0
        self.images_dropped = 0
        self.messages_written = 0
        self._unflushed_since: float | None = None
        self._origin_ns = time.time_ns()
        self._t0_s = t0_s
        try:
            self._sink = McapSink(stream, path, compression=compression, fsync=fsync)
            # The session description, config and calibration are on disk before the loop starts.
            self._sink.add(rs.TOPIC_SESSION, self._origin_ns, self._session_message())
            self._sink.add(rs.TOPIC_CONFIG, self._origin_ns, _encode(config, "config"))
            self._sink.add(rs.TOPIC_CALIBRATION, self._origin_ns, _encode(calibration, "calibration"))
            self._sink.flush()
        except OSError as err:
            raise RecordingError(f"{path}: cannot write the recording ({err.strerror or err})") from err
        self._background = BackgroundWriter(self._sink, max_lag_frames=max_lag_frames) if threaded else None
        _OPEN.add(self)

    @classmethod
    def create(cls, path: Path, *, config: Mapping[str, Any], calibration: Mapping[str, Any],
               frames_every: int = 1, compression: str = "zstd", fsync: bool = True,
               t0_s: float | None = None, threaded: bool = True, max_lag_frames: int = 1,
               max_pending_images: int = 2) -> Recorder:
        """Create a new recording at ``path`` (its folder is made; an existing file is never overwritten)."""
        path = Path(path)
        _check_options(frames_every, compression)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            stream = open(path, "xb")  # noqa: SIM115 (owned by the recorder, closed in close())
        except FileExistsError as err:
            raise RecordingError(f"{path}: a recording of that name exists; it is not overwritten") from err
        except OSError as err:
            raise RecordingError(f"{path}: cannot create the recording ({err.strerror or err})") from err
        try:
            return cls(stream, path=path, config=config, calibration=calibration, frames_every=frames_every,
                       compression=compression, fsync=fsync, t0_s=t0_s, threaded=threaded,
                       max_lag_frames=max_lag_frames, max_pending_images=max_pending_images)
        except BaseException:
            stream.close()
            raise

    # -- the topics ---------------------------------------------------------------------------------
    def write_posture(self, t_s: float, record: Mapping[str, Any]) -> None:
        """One posture record (architecture.md contract); its ``frame`` becomes the message sequence."""
        self._write(rs.TOPIC_POSTURE, t_s, record, sequence=record.get("frame"))

    def write_command(self, t_s: float, command: Mapping[str, Any]) -> None:
        """The controller's output: field, force, commanded currents, scale and what limited it."""
        self._write(rs.TOPIC_COMMAND, t_s, command, sequence=command.get("frame"))

    def write_currents(self, t_s: float, measured_a: Sequence[float], commanded_a: Sequence[float]) -> None:
        """The amplifier's measured currents beside the commanded ones, per channel (A)."""
        self._write(rs.TOPIC_CURRENTS, t_s, {"measured_a": measured_a, "commanded_a": commanded_a})

    def write_ots(self, t_s: float, sample: Mapping[str, Any]) -> None:
        """An optical-tracker sample (reference only, never in the control path)."""
        self._write(rs.TOPIC_OTS, t_s, sample)

    def write_fault(self, t_s: float, fault: Mapping[str, Any]) -> None:
        """A fault or safety event; returns once it (and everything before it) is on disk."""
        self._write(rs.TOPIC_FAULT, t_s, fault)
        self.flush()

    def write_status(self, t_s: float, device: str, status: Mapping[str, Any]) -> None:
        """A device's status; the message carries ``device`` beside the status keys."""
        self._write(rs.TOPIC_STATUS, t_s, {"device": device, **status})

    def write_timing(self, t_s: float, frame: int | None, stages_us: Mapping[str, float]) -> None:
        """The wall-clock duration of each loop stage for ``frame`` (µs); ends the frame (flushed)."""
        self._write(rs.TOPIC_TIMING, t_s, {"frame": frame, "stages_us": stages_us}, sequence=frame,
                    boundary=True)

    def write_frames(self, t_s: float, frame_number: int, image_p: np.ndarray, image_q: np.ndarray) -> bool:
        """Offer a biplane pair; every ``frames_every``-th offered pair (the first included) is kept.
        Returns whether this pair was written. Images must be 2-D ``uint16``."""
        for name, image in (("p", image_p), ("q", image_q)):
            if not isinstance(image, np.ndarray) or image.ndim != 2 or image.dtype != np.uint16:
                shape = getattr(image, "shape", None)
                raise ValueError(f"frame {frame_number}: image {name} must be a 2-D uint16 array, "
                                 f"got {getattr(image, 'dtype', type(image).__name__)} {shape}")
        with self._lock:
            self._check_open()
            keep = self._frames_offered % self.frames_every == 0
            self._frames_offered += 1
            if not keep:
                return False
            log_time = self._log_time(t_s)
            if self._background is not None and self._background.images_pending >= self._max_pending_images:
                # The disk is slower than the loop: losing a picture beats stalling the coils' control.
                self.images_dropped += 1
                if self.images_dropped == 1 or self.images_dropped % 100 == 0:
                    log.warning("%s: writer behind, image pair of frame %d dropped (%d so far)", self.path,
                                frame_number, self.images_dropped)
                status = {"device": "recorder", "images_dropped": self.images_dropped, "frame": frame_number}
                self._submit(("msg", rs.TOPIC_STATUS, log_time, _encode(status, "status"), 0))
                return False
            if self._background is not None:
                # The caller may reuse its buffers once we return; the writer thread needs its own copy.
                image_p, image_q = image_p.copy(), image_q.copy()
            self._submit(("images", log_time, int(frame_number) % (1 << 32), image_p, image_q))
            self.frames_written += 1
            self._unflushed_since = None
            return True

    # -- lifecycle ----------------------------------------------------------------------------------
    def flush(self) -> None:
        """Close the current chunk and force everything written so far to disk; returns once it is there."""
        with self._lock:
            self._check_open()
            self._unflushed_since = None
            self._guarded(self._background.sync if self._background is not None else self._sink.flush)

    def close(self) -> None:
        """Write the summary (indexes, statistics) and close the file; idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            _OPEN.discard(self)
            if self._background is not None:
                self._guarded(self._background.close)
            else:
                self._guarded(self._sink.finish)
        log.info("recording %s closed: %d messages, %d frame pairs (%d dropped)", self.path,
                 self.messages_written, self.frames_written, self.images_dropped)

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- internals ----------------------------------------------------------------------------------
    def _session_message(self) -> bytes:
        session = {"format_version": rs.FORMAT_VERSION, "origin_unix_ns": self._origin_ns, "t0_s": self._t0_s,
                   "frames_every": self.frames_every,
                   "created_utc": _dt.datetime.fromtimestamp(self._origin_ns / 1e9, _dt.timezone.utc).isoformat()}
        return _encode(session, "session")

    def _log_time(self, t_s: float) -> int:
        if not math.isfinite(t_s):
            raise ValueError(f"time must be finite, got {t_s}")
        if self._t0_s is None:
            # The loop's clock has an arbitrary origin: pin its first reading to the creation time,
            # and say so in a second /session message so the reader can give back t_s.
            self._t0_s = float(t_s)
            self._submit(("msg", rs.TOPIC_SESSION, self._origin_ns, self._session_message(), 0))
        return self._origin_ns + round((t_s - self._t0_s) * 1e9)

    def _write(self, topic: str, t_s: float, payload: Mapping[str, Any], *, sequence: Any = None,
               boundary: bool = False) -> None:
        data = _encode(payload, topic.strip("/"))
        seq = int(sequence) % (1 << 32) if isinstance(sequence, (int, np.integer)) else 0
        with self._lock:
            self._check_open()
            op = ("msg", topic, self._log_time(t_s), data, seq)
            if self._unflushed_since is None:
                self._unflushed_since = t_s
            # Side channels keep coming while the imaging chain is silent: close their chunk too.
            boundary = boundary or t_s - self._unflushed_since > self._max_unflushed_s
            self._submit(op, boundary=boundary)
            if boundary:
                self._unflushed_since = None

    def _submit(self, op: tuple[Any, ...], *, boundary: bool = False) -> None:
        if op[0] == "msg":
            self.messages_written += 1
        if self._background is not None:
            self._guarded(self._background.submit, op, boundary=boundary)
            return
        self._guarded(self._sink.apply, op)
        if boundary:
            self._guarded(self._sink.flush)

    def _guarded(self, call: Any, *args: Any, **kwargs: Any) -> None:
        try:
            call(*args, **kwargs)
        except OSError as err:
            raise RecordingError(f"{self.path}: cannot write the recording ({err.strerror or err})") from err

    def _check_open(self) -> None:
        if self._closed:
            raise RecordingError(f"{self.path}: the recording is closed")
