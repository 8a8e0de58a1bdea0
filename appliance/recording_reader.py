"""Read a session recording (see :mod:`appliance.recording`), including one cut off by a crash.

The ``mcap`` library's record-level :class:`~mcap.stream_reader.StreamReader` does the parsing (chunk
CRCs checked); it reads through a file wrapper that treats any short read as the end of the data.
So wherever the file was cut (in a record's header, inside a chunk, between a chunk and its index,
in the summary), iteration stops cleanly after the last complete record and every message before
the cut is delivered; :attr:`RecordingReader.stop_reason` says where and why it stopped, and
:attr:`RecordingReader.complete` whether the file was closed properly (footer present).

Import it from :mod:`appliance.recording`: ``from appliance.recording import RecordingReader``.
"""
from __future__ import annotations

import base64
import binascii
import json
import logging
import struct
from collections import Counter
from collections.abc import Collection, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
import zstandard
from mcap.exceptions import EndOfFile, InvalidMagic, McapError, RecordLengthLimitExceeded
from mcap.records import Channel, Footer, McapRecord, Message
from mcap.stream_reader import CRCValidationError, StreamReader

from appliance import recording_schemas as rs
from appliance.errors import InputDataError

log = logging.getLogger(__name__)

#: Topics that describe the recording rather than the session; ``messages()`` skips them unless asked.
_BOOKKEEPING = frozenset({rs.TOPIC_SESSION, rs.TOPIC_CONFIG, rs.TOPIC_CALIBRATION, *rs.TOPIC_IMAGE.values()})
_PLANE_OF_TOPIC = {topic: plane for plane, topic in rs.TOPIC_IMAGE.items()}
#: What a torn or corrupted tail can raise inside the library (decompression, CRC, struct, UTF-8).
_TORN = (McapError, CRCValidationError, struct.error, ValueError, RuntimeError, zstandard.ZstdError)


class _WholeReads:
    """A binary file for the stream reader in which a read that cannot be served in full ends the data
    (the library's own stream returns short reads, which would parse a torn record as garbage)."""

    def __init__(self, stream: IO[bytes]) -> None:
        self._stream = stream
        self.offset = 0

    def read(self, size: int = -1) -> bytes:
        data = self._stream.read(size)
        self.offset += len(data)
        if size is not None and size >= 0 and len(data) < size:
            raise EndOfFile()
        return data


@dataclass
class RecordingSummary:
    """What a full pass over a recording found."""

    path: Path
    complete: bool                 # closed properly (footer present)
    stop_reason: str | None        # why reading stopped early, when it did
    messages: Counter[str] = field(default_factory=Counter)   # per topic
    frames: int = 0                # complete biplane pairs
    first_t_s: float | None = None
    last_t_s: float | None = None


class RecordingReader:
    """Reads a recording written by :class:`appliance.recording.Recorder`; tolerant of a cut-off tail.

    ``config`` and ``calibration`` are the dicts the session ran with; ``session`` the recording's own
    description. Missing, empty or non-MCAP files raise :class:`InputDataError` naming the file."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            what = "is a folder, not a recording" if self.path.is_dir() else "file not found"
            raise InputDataError(f"{self.path}: {what}")
        #: After a full pass (messages(), frames() or summary() run to the end): closed properly?
        self.complete: bool | None = None
        #: After a full pass: why reading stopped before the end of the file, if it did.
        self.stop_reason: str | None = None
        self.session: dict[str, Any] = {}
        self.config: dict[str, Any] | None = None
        self.calibration: dict[str, Any] | None = None
        self._origin_ns: int | None = None
        self._t0_s: float | None = None
        self._read_prelude()

    # -- public -------------------------------------------------------------------------------------
    def messages(self, topic: str | Collection[str] | None = None) -> Iterator[tuple[str, float, dict[str, Any]]]:
        """``(topic, t_s, message)`` in file order; by default every topic except the images and the
        bookkeeping ones (``/session``, ``/config``, ``/calibration``), which must be asked for by name."""
        wanted = {topic} if isinstance(topic, str) else (set(topic) if topic is not None else None)
        for name, message in self._messages():
            if (name in wanted) if wanted is not None else (name not in _BOOKKEEPING):
                yield name, self._t_s(message.log_time), self._decode(name, message)

    def frames(self) -> Iterator[tuple[int, float, np.ndarray, np.ndarray]]:
        """``(frame_number, t_s, image_p, image_q)`` for every complete recorded pair (uint16 images)."""
        pending: dict[int, tuple[str, np.ndarray]] = {}
        for name, message in self._messages():
            plane = _PLANE_OF_TOPIC.get(name)
            if plane is None:
                continue
            frame = message.sequence
            image = self._image(name, message)
            other = pending.pop(frame, None)
            if other is None:
                pending[frame] = (plane, image)
                continue
            images = {plane: image, other[0]: other[1]}
            if set(images) != {"p", "q"}:
                raise InputDataError(f"{self.path}: frame {frame}: two images of plane {plane}")
            yield frame, self._t_s(message.log_time), images["p"], images["q"]
        if pending:
            log.info("%s: %d frame(s) with one plane only (cut off): %s", self.path, len(pending), sorted(pending))

    def summary(self) -> RecordingSummary:
        """One full pass: message counts per topic, complete pairs, time span, whether it was cut off."""
        counts: Counter[str] = Counter()
        first = last = None
        planes: Counter[int] = Counter()
        for name, message in self._messages():
            counts[name] += 1
            if name in _PLANE_OF_TOPIC:
                planes[message.sequence] += 1
            if name not in _BOOKKEEPING:
                t_s = self._t_s(message.log_time)
                first = t_s if first is None else min(first, t_s)
                last = t_s if last is None else max(last, t_s)
        return RecordingSummary(self.path, bool(self.complete), self.stop_reason, counts,
                                sum(1 for n in planes.values() if n >= 2), first, last)

    # -- internals ----------------------------------------------------------------------------------
    def _read_prelude(self) -> None:
        """Session description, config and calibration: written first, so read only the head."""
        for name, message in self._messages():
            if name == rs.TOPIC_SESSION:
                self.session = self._decode(name, message)
                self._origin_ns = int(self.session.get("origin_unix_ns", 0))
                if self.session.get("t0_s") is not None:
                    self._t0_s = float(self.session["t0_s"])
                    break   # the time base is pinned by the first timed message, after config/calibration
            elif name == rs.TOPIC_CONFIG:
                self.config = self._decode(name, message)
            elif name == rs.TOPIC_CALIBRATION:
                self.calibration = self._decode(name, message)
            else:
                break
        if not self.session:
            raise InputDataError(f"{self.path}: not a session recording (no {rs.TOPIC_SESSION} message)"
                                 + (f"; {self.stop_reason}" if self.stop_reason else ""))

    def _messages(self) -> Iterator[tuple[str, Message]]:
        topics: dict[int, str] = {}
        for record in self._records():
            if isinstance(record, Message):
                name = topics.get(record.channel_id)
                if name is None:
                    log.warning("%s: message on unknown channel %d skipped", self.path, record.channel_id)
                    continue
                yield name, record
            elif isinstance(record, Channel):
                topics[record.id] = record.topic

    def _records(self) -> Iterator[McapRecord]:
        try:
            stream = open(self.path, "rb")  # noqa: SIM115 (closed by the with below)
        except OSError as err:
            raise InputDataError(f"{self.path}: cannot read ({err.strerror or err})") from err
        with stream:
            size = self.path.stat().st_size
            wrapper = _WholeReads(stream)
            # A record longer than the file cannot be complete: stop there rather than try to read it.
            reader = StreamReader(wrapper, validate_crcs=True, record_size_limit=max(size, 16))
            records = reader.records
            good_until = 0
            footer_seen = False
            while True:
                try:
                    record = next(records)
                except StopIteration:
                    self.complete, self.stop_reason = True, None
                    return
                except InvalidMagic as err:
                    raise InputDataError(f"{self.path}: not an MCAP recording ({err})") from err
                except (EndOfFile, RecordLengthLimitExceeded):
                    # A record longer than the whole file ends past the cut just like a short read.
                    if good_until == 0:
                        raise InputDataError(f"{self.path}: empty or cut off before the MCAP header") from None
                    if footer_seen:   # only the closing magic is missing: data and summary are all there
                        self.complete, self.stop_reason = True, None
                    elif good_until >= size:
                        self._stopped(f"ends at byte {size} without a footer: the recording was not closed")
                    else:
                        self._stopped(f"cut off at byte {size}: the record after byte {good_until} is incomplete")
                    return
                except _TORN as err:
                    if good_until == 0:
                        raise InputDataError(f"{self.path}: not a readable MCAP recording ({err})") from err
                    self._stopped(f"unreadable after byte {good_until} ({type(err).__name__}: {err})")
                    return
                good_until = wrapper.offset
                footer_seen = footer_seen or isinstance(record, Footer)
                yield record

    def _stopped(self, reason: str) -> None:
        if reason != self.stop_reason:
            log.warning("%s: %s; messages before that are read", self.path, reason)
        self.complete, self.stop_reason = False, reason

    def _t_s(self, log_time: int) -> float:
        return (self._t0_s or 0.0) + (log_time - (self._origin_ns or 0)) / 1e9

    def _decode(self, topic: str, message: Message) -> dict[str, Any]:
        try:
            value = json.loads(message.data)
        except (UnicodeDecodeError, json.JSONDecodeError) as err:
            # The chunk's CRC held, so this is how it was written: a corrupt recording, not a cut.
            raise InputDataError(f"{self.path}: {topic} message at log time {message.log_time}: "
                                 f"not JSON ({err})") from err
        if not isinstance(value, dict):
            raise InputDataError(f"{self.path}: {topic} message at log time {message.log_time}: not a JSON object")
        return value

    def _image(self, topic: str, message: Message) -> np.ndarray:
        value = self._decode(topic, message)
        where = f"{self.path}: {topic} frame {message.sequence}"
        try:
            width, height, step = int(value["width"]), int(value["height"]), int(value["step"])
            encoding = value["encoding"]
            data = base64.b64decode(value["data"], validate=True)
        except (KeyError, TypeError, ValueError, binascii.Error) as err:
            raise InputDataError(f"{where}: not a RawImage ({err})") from err
        if encoding not in (rs.IMAGE_ENCODING, "16UC1") or step != 2 * width or len(data) != step * height:
            raise InputDataError(f"{where}: expected {rs.IMAGE_ENCODING} {width}x{height} with step {2 * width}, "
                                 f"got {encoding} step {step} and {len(data)} bytes")
        return np.frombuffer(data, dtype="<u2").reshape(height, width).astype(np.uint16)
