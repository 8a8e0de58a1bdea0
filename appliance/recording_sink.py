"""The file side of a session recording: the MCAP writer, and the thread that keeps it off the loop.

:class:`McapSink` owns the ``mcap`` writer and the open file: it registers the channels, adds
messages, turns images into ``foxglove.RawImage`` messages, closes a chunk and forces it to disk
(``flush``), and writes the summary (``finish``). It is not thread-safe.

:class:`BackgroundWriter` runs a sink on its own thread so that the per-frame loop never waits for
base64 encoding, chunk compression or ``fsync`` (a 768x672 pair costs milliseconds of each). The
caller submits operations in order; at a frame boundary it waits only while more than
``max_lag_frames`` earlier boundaries are still unwritten, which bounds what a crash can lose. The
first error on the writer thread is kept and raised to the caller on its next call (never
swallowed); nothing after it is written.
"""
from __future__ import annotations

import base64
import json
import logging
import os
import threading
from collections import deque
from pathlib import Path
from typing import IO, Any

import numpy as np
from mcap.writer import CompressionType, Writer

from appliance import recording_schemas as rs

log = logging.getLogger(__name__)

COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}

#: ("msg", topic, log_time_ns, data, sequence) | ("images", log_time_ns, frame, image_p, image_q)
#: | ("flush",) | ("finish",)
Operation = tuple[Any, ...]


class McapSink:
    """The MCAP writer over an open binary file (see the module docstring)."""

    def __init__(self, stream: IO[bytes], path: Path, *, compression: str, fsync: bool) -> None:
        self.path = path
        self._stream = stream
        self._fsync = fsync
        self._writer = Writer(stream, compression=COMPRESSIONS[compression])
        self._channels: dict[str, int] = {}
        self._writer.start(profile=rs.PROFILE, library=f"appliance recording v{rs.FORMAT_VERSION}")
        for topic, (name, schema) in rs.SCHEMAS.items():
            self._register(topic, name, schema)
        for topic in rs.TOPIC_IMAGE.values():
            self._register(topic, rs.IMAGE_SCHEMA_NAME, rs.RAW_IMAGE_SCHEMA)

    def _register(self, topic: str, name: str, schema: dict[str, Any]) -> None:
        schema_id = self._writer.register_schema(name=name, encoding="jsonschema", data=rs.schema_bytes(schema))
        self._channels[topic] = self._writer.register_channel(topic=topic, message_encoding="json",
                                                              schema_id=schema_id)

    def apply(self, op: Operation) -> None:
        kind = op[0]
        if kind == "msg":
            self.add(*op[1:])
        elif kind == "images":
            _, log_time, frame, image_p, image_q = op
            for plane, image in (("p", image_p), ("q", image_q)):
                self.add(rs.TOPIC_IMAGE[plane], log_time, raw_image_message(plane, log_time, image), frame)
            self.flush()
        elif kind == "flush":
            self.flush()
        elif kind == "finish":
            self.finish()
        else:
            raise ValueError(f"unknown recorder operation {kind!r}")

    def add(self, topic: str, log_time: int, data: bytes, sequence: int = 0) -> None:
        self._writer.add_message(channel_id=self._channels[topic], log_time=log_time, data=data,
                                 publish_time=log_time, sequence=sequence)

    def flush(self) -> None:
        """Close the current chunk, hand it to the OS and (``fsync``) force it to the disk."""
        self._writer.flush()
        if self._fsync:
            os.fsync(self._stream.fileno())

    def finish(self) -> None:
        """Write the summary section and close the file."""
        try:
            self._writer.finish()
            self._stream.flush()
            if self._fsync:
                os.fsync(self._stream.fileno())
        finally:
            self._stream.close()

    def abandon(self) -> None:
        """Close the file without a summary (after a write error; what is on disk stays readable)."""
        try:
            self._stream.close()
        except OSError:
            pass


def raw_image_message(plane: str, log_time: int, image: np.ndarray) -> bytes:
    """A ``foxglove.RawImage`` JSON message (``mono16``, little-endian, base64 data) of a uint16 image."""
    pixels = np.ascontiguousarray(image, dtype="<u2")
    height, width = pixels.shape
    header = {"timestamp": {"sec": log_time // 1_000_000_000, "nsec": log_time % 1_000_000_000},
              "frame_id": f"xray_{plane}", "width": width, "height": height,
              "encoding": rs.IMAGE_ENCODING, "step": 2 * width}
    # Base64 text never needs JSON escaping, so the pixel data is spliced in as bytes: running a
    # megabyte string through json.dumps (which scans it for escapes) doubled the cost of a frame.
    head = json.dumps(header, separators=(",", ":")).encode("ascii")
    return b"".join((head[:-1], b',"data":"', base64.b64encode(pixels.data), b'"}'))


class BackgroundWriter:
    """Applies submitted operations to a sink on one thread, in order (see the module docstring)."""

    def __init__(self, sink: McapSink, *, max_lag_frames: int = 1) -> None:
        self._sink = sink
        self._max_lag = max_lag_frames
        self._queue: deque[Operation] = deque()
        self._cond = threading.Condition()
        self._submitted = 0      # flushes (frame boundaries, syncs) submitted
        self._done = 0           # ... and done
        self._images_pending = 0
        self.error: BaseException | None = None
        self._finished = False
        self._thread = threading.Thread(target=self._run, name=f"recorder {sink.path.name}", daemon=True)
        self._thread.start()

    @property
    def images_pending(self) -> int:
        """Image pairs submitted but not yet written (the writer is behind when this is not zero)."""
        return self._images_pending

    def submit(self, op: Operation, *, boundary: bool = False) -> None:
        """Queue ``op``; at a boundary, wait while more than ``max_lag_frames`` boundaries are unwritten."""
        with self._cond:
            self._raise_if_failed()
            self._queue.append(op)
            if op[0] == "images":
                self._images_pending += 1
            if boundary:
                self._queue.append(("flush",))
                self._submitted += 1
            self._cond.notify_all()
            if boundary:
                self._cond.wait_for(lambda: self.error is not None or self._submitted - self._done <= self._max_lag)
                self._raise_if_failed()

    def sync(self) -> None:
        """Write everything submitted so far to disk, and return when it is there."""
        with self._cond:
            self._raise_if_failed()
            self._queue.append(("flush",))
            self._submitted += 1
            self._cond.notify_all()
            self._cond.wait_for(lambda: self.error is not None or self._done == self._submitted)
            self._raise_if_failed()

    def close(self) -> None:
        """Write what is queued and the summary, stop the thread; raises a pending writer error."""
        with self._cond:
            if not self._finished:
                self._finished = True
                self._queue.append(("finish",))
                self._cond.notify_all()
        self._thread.join()
        self._raise_if_failed()

    def _raise_if_failed(self) -> None:
        if self.error is not None:
            raise self.error

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: bool(self._queue))
                op = self._queue.popleft()
            try:
                self._sink.apply(op)
            except BaseException as err:  # noqa: BLE001 - handed to the caller, never swallowed
                log.error("%s: recording stopped: %s", self._sink.path, err)
                self._sink.abandon()
                with self._cond:
                    self.error = err
                    self._queue.clear()
                    self._cond.notify_all()
                return
            with self._cond:
                if op[0] == "images":
                    self._images_pending -= 1
                if op[0] == "flush":
                    self._done += 1
                self._cond.notify_all()
            if op[0] == "finish":
                return
