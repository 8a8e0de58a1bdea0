"""Pair the frames of X-ray planes p and q into biplane pairs, and a threaded stream that reads two sources.

:class:`BiplanePairer` is pure logic (no threads, no clock): frames are pushed in, pairs come out.

- ``match="number"``: same frame number = same exposure (grabbers triggered by the same generator).
- ``match="time"``: the closest frame of the other plane within ``max_skew_s``, on the host clock
  (``clock="host"``, the one clock both grabbers share) or on the device clock (``clock="device"``,
  when both grabbers are synchronised by hardware). The pair takes plane p's number.
- ``mode="latest"`` (real time): :meth:`BiplanePairer.latest` returns the newest complete pair and
  discards every older one (counted as ``superseded``), so latency never builds up.
- ``mode="all"`` (offline): :meth:`BiplanePairer.pop` returns every pair, oldest first.

A pending frame is abandoned (counted as unpaired for its plane) as soon as the other plane has moved
past it: a later number (``number``) or a time later than its own plus the skew (``time``). Sources
deliver in order, so such a frame can never be paired. ``flush()`` abandons whatever still waits.
When a plane's frame number goes backwards (its grabber restarted), pairing by number starts over.

Interleaved exposures (the planes alternate to reduce scatter) are flagged on the pair when the two
exposure windows ``[device_time, device_time + exposure]`` do not overlap (``interleaved="auto"``, the
default; it needs device times on a common clock and both exposures) or when configured
(``interleaved=True``); the pair keeps both exposure times so the tracker can account for motion.

:class:`BiplaneStream` runs one reader thread per source and a pairer; ``next_pair(timeout_s)`` hands
the newest (latest mode) or next (all mode) pair to the one thread that owns the frame loop. Errors in a
reader (a lost link) are raised from ``next_pair``, never swallowed.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from types import TracebackType
from typing import Literal

from drivers.errors import DeviceTimeoutError
from drivers.frame_source import EndOfStream, Frame, FrameSource

log = logging.getLogger(__name__)

Match = Literal["number", "time"]
Mode = Literal["latest", "all"]


@dataclass(frozen=True)
class BiplanePair:
    """Two frames of the same exposure (or the closest in time), p and q."""

    p: Frame
    q: Frame
    number: int
    skew_s: float          # q time - p time on the pairing clock (host, or device when so configured)
    interleaved: bool

    @property
    def exposures_s(self) -> tuple[float | None, float | None]:
        return self.p.exposure_s, self.q.exposure_s

    @property
    def frames(self) -> dict[str, Frame]:
        return {"p": self.p, "q": self.q}


@dataclass(frozen=True)
class PairingCounters:
    pairs: int = 0            # pairs formed
    superseded: int = 0       # pairs discarded by latest-pair mode because a newer one was ready
    unpaired_p: int = 0       # p frames that never found a partner
    unpaired_q: int = 0


class BiplanePairer:
    """Pairs frames pushed from two planes; see the module docstring."""

    def __init__(self, *, match: Match = "number", mode: Mode = "latest", max_skew_s: float = 0.005,
                 clock: Literal["host", "device"] = "host", interleaved: bool | Literal["auto"] = "auto",
                 max_pending: int = 256) -> None:
        if match not in ("number", "time"):
            raise ValueError(f"match must be 'number' or 'time', got {match!r}")
        if mode not in ("latest", "all"):
            raise ValueError(f"mode must be 'latest' or 'all', got {mode!r}")
        if max_skew_s < 0:
            raise ValueError(f"max_skew_s must be >= 0, got {max_skew_s}")
        self.match = match
        self.mode = mode
        self.max_skew_s = max_skew_s
        self.clock = clock
        self.interleaved = interleaved
        self.max_pending = max_pending
        self._pending: dict[str, deque[Frame]] = {"p": deque(), "q": deque()}
        self._newest: dict[str, Frame | None] = {"p": None, "q": None}
        self._ready: deque[BiplanePair] = deque()
        self._pairs = 0
        self._superseded = 0
        self._unpaired = {"p": 0, "q": 0}

    # -- input -----------------------------------------------------------------------------------
    def push(self, frame: Frame) -> None:
        """Add a frame of plane p or q; pairs it completes become available to ``latest``/``pop``."""
        plane = frame.plane
        if plane not in self._pending:
            raise ValueError(f"frame from unknown plane {plane!r}")
        other = "q" if plane == "p" else "p"
        previous = self._newest[plane]
        if self.match == "number" and previous is not None and frame.number <= previous.number:
            # The grabber restarted its counter (reconnected, re-armed): old numbers mean nothing now.
            log.info("plane %s frame number went from %d to %d: pairing starts over", plane, previous.number,
                     frame.number)
            self.flush()
            self._newest[other] = None
        self._newest[plane] = frame
        # The other plane's frames that this one has moved past can never pair any more.
        self._abandon_passed(other, frame)
        partner = self._find_partner(frame, self._pending[other])
        if partner is None:
            self._pending[plane].append(frame)
            # It may already be too old for the other plane (it arrived late): abandon it at once.
            self._abandon_passed(plane, self._newest[other])
            while len(self._pending[plane]) > self.max_pending:
                self._pending[plane].popleft()
                self._unpaired[plane] += 1
            return
        # Frames of the other plane older than the partner were skipped over: unpaired for good.
        pending = self._pending[other]
        while pending and pending[0] is not partner:
            pending.popleft()
            self._unpaired[other] += 1
        pending.popleft()
        p, q = (frame, partner) if plane == "p" else (partner, frame)
        self._emit(p, q)

    def flush(self) -> None:
        """Abandon every frame still waiting for a partner (end of a recording)."""
        for plane in ("p", "q"):
            self._unpaired[plane] += len(self._pending[plane])
            self._pending[plane].clear()

    # -- output ----------------------------------------------------------------------------------
    def latest(self) -> BiplanePair | None:
        """The newest complete pair, discarding older ones; None when no new pair is ready."""
        if not self._ready:
            return None
        newest = self._ready.pop()
        self._superseded += len(self._ready)
        self._ready.clear()
        return newest

    def pop(self) -> BiplanePair | None:
        """The oldest complete pair not yet returned (all-frames mode), or None."""
        return self._ready.popleft() if self._ready else None

    def take(self) -> BiplanePair | None:
        """``latest()`` or ``pop()`` according to the mode."""
        return self.latest() if self.mode == "latest" else self.pop()

    @property
    def ready(self) -> int:
        return len(self._ready)

    def pending(self, plane: str) -> int:
        """How many frames of ``plane`` wait for a partner."""
        return len(self._pending[plane])

    @property
    def counters(self) -> PairingCounters:
        return PairingCounters(self._pairs, self._superseded, self._unpaired["p"], self._unpaired["q"])

    # -- internals -------------------------------------------------------------------------------
    def _time(self, frame: Frame) -> float:
        return frame.host_time_s if self.clock == "host" else frame.device_time_s

    def _find_partner(self, frame: Frame, candidates: deque[Frame]) -> Frame | None:
        if self.match == "number":
            for other in candidates:
                if other.number == frame.number:
                    return other
            return None
        t = self._time(frame)
        best: Frame | None = None
        for other in candidates:
            gap = abs(self._time(other) - t)
            if gap <= self.max_skew_s and (best is None or gap < abs(self._time(best) - t)):
                best = other
        return best

    def _passed(self, waiting: Frame, newest_other: Frame) -> bool:
        if self.match == "number":
            return newest_other.number > waiting.number
        return self._time(newest_other) > self._time(waiting) + self.max_skew_s

    def _abandon_passed(self, plane: str, newest_other: Frame | None) -> None:
        if newest_other is None:
            return
        pending = self._pending[plane]
        while pending and self._passed(pending[0], newest_other):
            pending.popleft()
            self._unpaired[plane] += 1

    def _is_interleaved(self, p: Frame, q: Frame) -> bool:
        if self.interleaved != "auto":
            return bool(self.interleaved)
        if p.exposure_s is None or q.exposure_s is None:
            return False
        p0, q0 = p.device_time_s, q.device_time_s
        return p0 + p.exposure_s <= q0 or q0 + q.exposure_s <= p0

    def _emit(self, p: Frame, q: Frame) -> None:
        number = p.number
        pair = BiplanePair(p=p, q=q, number=number, skew_s=self._time(q) - self._time(p),
                           interleaved=self._is_interleaved(p, q))
        self._pairs += 1
        if self.mode == "latest" and self._ready:
            # Keep only the newest: a real-time consumer must never work through a backlog.
            self._superseded += len(self._ready)
            self._ready.clear()
        self._ready.append(pair)


class BiplaneStream:
    """Reads two frame sources on their own threads and pairs them; ``next_pair`` serves one consumer.

    The stream opens the sources on ``start`` (or ``with``) and closes them on ``stop``. Reader threads
    read with a short timeout so that ``stop`` is prompt; a reader error ends the stream and is raised
    from ``next_pair``. When every source has reached its end (files), ``next_pair`` raises
    :class:`EndOfStream` once the remaining pairs are handed out.
    """

    def __init__(self, sources: dict[str, FrameSource] | list[FrameSource], pairer: BiplanePairer | None = None,
                 *, poll_s: float = 0.1, backlog: int = 64) -> None:
        if isinstance(sources, list):
            sources = {source.plane: source for source in sources}
        if sorted(sources) != ["p", "q"]:
            raise ValueError(f"a biplane stream needs one source per plane p and q, got planes {sorted(sources)}")
        for plane, source in sources.items():
            if source.plane != plane:
                raise ValueError(f"source {source.name} delivers plane {source.plane!r}, not {plane!r}")
        self.sources = sources
        self.pairer = pairer or BiplanePairer()
        self.poll_s = poll_s
        self.backlog = min(backlog, self.pairer.max_pending)
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._error: BaseException | None = None
        self._ended: set[str] = set()

    def start(self) -> None:
        if self._threads:
            return
        opened: list[FrameSource] = []
        try:
            for source in self.sources.values():
                source.open()
                opened.append(source)
        except BaseException:
            for source in opened:
                source.close()
            raise
        self._stop.clear()
        for plane, source in self.sources.items():
            thread = threading.Thread(target=self._reader, args=(plane, source), name=f"grab-{plane}", daemon=True)
            self._threads.append(thread)
            thread.start()

    def stop(self) -> None:
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        for thread in self._threads:
            thread.join(timeout=5.0)
            if thread.is_alive():
                log.warning("reader thread %s did not stop within 5 s", thread.name)
        self._threads.clear()
        for source in self.sources.values():
            source.close()

    def __enter__(self) -> BiplaneStream:
        self.start()
        return self

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None,
                 trace: TracebackType | None) -> None:
        self.stop()

    def next_pair(self, timeout_s: float) -> BiplanePair:
        """The newest pair (latest mode) or the next pair (all mode); DeviceTimeoutError at the deadline."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                pair = self.pairer.take()
                if pair is not None:
                    self._cond.notify_all()  # wake readers held back in all-frames mode
                    return pair
                if self._error is not None:
                    raise self._error
                if len(self._ended) == len(self.sources):
                    self.pairer.flush()
                    raise EndOfStream("every source has delivered its last frame")
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DeviceTimeoutError(f"no biplane pair within {timeout_s * 1000:.0f} ms")
                self._cond.wait(remaining)

    def _reader(self, plane: str, source: FrameSource) -> None:
        while not self._stop.is_set():
            try:
                frame = source.read(self.poll_s)
            except DeviceTimeoutError:
                continue
            except EndOfStream:
                with self._cond:
                    self._ended.add(plane)
                    self._cond.notify_all()
                return
            except BaseException as err:  # handed to the consumer, never swallowed
                log.error("reader %s stopped: %s", source.name, err)
                with self._cond:
                    self._error = err
                    self._cond.notify_all()
                return
            with self._cond:
                self.pairer.push(frame)
                if self.pairer.ready:
                    self._cond.notify_all()
                if self.pairer.mode == "all":
                    # Offline: never lose a frame to a full queue; let the consumer and the slower plane catch up.
                    while not self._stop.is_set() and (self.pairer.ready >= self.backlog
                                                       or self.pairer.pending(plane) >= self.backlog):
                        self._cond.wait(self.poll_s)
