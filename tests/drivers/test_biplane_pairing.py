"""Biplane pairing: by number and by time, latest-pair and all-frames modes, jitter, drops, interleaving."""
from __future__ import annotations

import numpy as np
import pytest

from drivers.biplane_pairing import BiplanePairer, BiplaneStream
from drivers.errors import DeviceTimeoutError, LinkLostError
from drivers.frame_source import EndOfStream, Frame, FrameSource

IMAGE = np.zeros((4, 6), dtype=np.uint16)


def frame(plane: str, number: int, t: float, *, host: float | None = None, exposure: float | None = 0.004) -> Frame:
    return Frame(IMAGE, plane, number, t, t + 0.002 if host is None else host, exposure, "mono16")


def stream_of(plane: str, numbers: list[int], rate: float = 30.0, *, offset: float = 0.0,
              jitter: np.ndarray | None = None) -> list[Frame]:
    out = []
    for i, n in enumerate(numbers):
        t = n / rate + offset
        host = t + 0.002 + (0.0 if jitter is None else float(jitter[i]))
        out.append(frame(plane, n, t, host=host))
    return out


def interleave(a: list[Frame], b: list[Frame]) -> list[Frame]:
    """Arrival order on one host clock."""
    return sorted(a + b, key=lambda f: f.host_time_s)


def test_by_number_all_mode_pairs_everything_in_order() -> None:
    pairer = BiplanePairer(match="number", mode="all")
    for f in interleave(stream_of("p", list(range(10))), stream_of("q", list(range(10)))):
        pairer.push(f)
    pairs = [pairer.pop() for _ in range(pairer.ready)]
    assert [p.number for p in pairs] == list(range(10))
    assert all(p.p.plane == "p" and p.q.plane == "q" and p.p.number == p.q.number for p in pairs)
    assert pairer.counters.pairs == 10 and pairer.counters.unpaired_p == pairer.counters.unpaired_q == 0


def test_drops_are_counted_per_plane_and_never_mispaired() -> None:
    rng = np.random.default_rng(3)
    numbers = list(range(200))
    keep_p = [n for n in numbers if rng.random() > 0.1]
    keep_q = [n for n in numbers if rng.random() > 0.1]
    jitter_p, jitter_q = rng.uniform(0, 0.02, len(keep_p)), rng.uniform(0, 0.02, len(keep_q))
    pairer = BiplanePairer(match="number", mode="all")
    for f in interleave(stream_of("p", keep_p, jitter=jitter_p), stream_of("q", keep_q, jitter=jitter_q)):
        pairer.push(f)
    pairer.flush()
    pairs = []
    while (pair := pairer.pop()) is not None:
        pairs.append(pair)
    both = sorted(set(keep_p) & set(keep_q))
    assert [p.number for p in pairs] == both
    counters = pairer.counters
    assert counters.unpaired_p == len(set(keep_p) - set(keep_q))
    assert counters.unpaired_q == len(set(keep_q) - set(keep_p))


def test_latest_mode_never_builds_up_latency() -> None:
    pairer = BiplanePairer(match="number", mode="latest")
    for f in interleave(stream_of("p", list(range(8))), stream_of("q", list(range(8)))):
        pairer.push(f)
    newest = pairer.latest()
    assert newest is not None and newest.number == 7
    assert pairer.latest() is None
    assert pairer.counters.superseded == 7 and pairer.counters.pairs == 8
    # A late q frame older than the newest pair is abandoned at once, not held back.
    pairer.push(frame("p", 9, 9 / 30))
    pairer.push(frame("q", 8, 8 / 30))
    assert pairer.latest() is None and pairer.counters.unpaired_q == 1
    pairer.push(frame("q", 9, 9 / 30))
    assert pairer.latest().number == 9


def test_a_restarted_counter_starts_pairing_over() -> None:
    pairer = BiplanePairer(match="number", mode="all")
    for f in interleave(stream_of("p", [100, 101]), stream_of("q", [100, 101])):
        pairer.push(f)
    pairer.push(frame("p", 102, 102 / 30))          # never completed: both grabbers restart instead
    for f in interleave(stream_of("q", [0, 1, 2], offset=4.0), stream_of("p", [0, 1, 2], offset=4.0)):
        pairer.push(f)
    assert [pairer.pop().number for _ in range(pairer.ready)] == [100, 101, 0, 1, 2]
    assert pairer.counters.unpaired_p == 1 and pairer.counters.unpaired_q == 0


def test_by_time_with_jitter_pairs_within_skew_and_reports_it() -> None:
    rng = np.random.default_rng(7)
    n = 100
    # Two free-running grabbers on one host clock: q's numbers are offset, host arrival jitters by up to 4 ms.
    p = stream_of("p", list(range(n)), jitter=rng.uniform(0, 0.004, n))
    q = [Frame(IMAGE, "q", 1000 + f.number, f.device_time_s + 5.0, f.host_time_s + float(rng.uniform(-0.004, 0.004)),
               0.004, "mono16") for f in stream_of("q", list(range(n)))]
    pairer = BiplanePairer(match="time", mode="all", max_skew_s=0.008)
    for f in interleave(p, q):
        pairer.push(f)
    pairs = [pairer.pop() for _ in range(pairer.ready)]
    assert len(pairs) == n
    assert all(pair.q.number == pair.p.number + 1000 for pair in pairs)
    assert all(abs(pair.skew_s) <= 0.008 for pair in pairs)
    assert all(pair.number == pair.p.number for pair in pairs)


def test_by_time_refuses_frames_beyond_the_skew() -> None:
    pairer = BiplanePairer(match="time", mode="all", max_skew_s=0.003)
    pairer.push(frame("p", 0, 0.0, host=0.0))
    pairer.push(frame("q", 0, 0.0, host=0.010))      # 10 ms later: too far; p0 can never pair now
    pairer.push(frame("p", 1, 0.0, host=0.0115))
    pair = pairer.pop()
    assert pair is not None and pair.p.number == 1 and pair.skew_s == pytest.approx(-0.0015)
    assert pairer.counters.unpaired_p == 1


def test_interleaved_exposures_are_flagged_with_both_exposure_times() -> None:
    rate, exposure = 30.0, 0.005
    p = [frame("p", n, n / rate, exposure=exposure) for n in range(5)]
    q = [frame("q", n, n / rate + 0.5 / rate, exposure=exposure) for n in range(5)]
    pairer = BiplanePairer(match="number", mode="all")
    for f in interleave(p, q):
        pairer.push(f)
    pairs = [pairer.pop() for _ in range(pairer.ready)]
    assert len(pairs) == 5 and all(pair.interleaved for pair in pairs)
    assert pairs[0].exposures_s == (exposure, exposure)
    # Simultaneous exposures are not interleaved; unknown exposure times cannot be judged.
    together = BiplanePairer(mode="all")
    together.push(frame("p", 0, 0.0))
    together.push(frame("q", 0, 0.001))
    assert together.pop().interleaved is False
    unknown = BiplanePairer(mode="all")
    unknown.push(frame("p", 0, 0.0, exposure=None))
    unknown.push(frame("q", 0, 0.5, exposure=None))
    assert unknown.pop().interleaved is False
    forced = BiplanePairer(mode="all", interleaved=True)
    forced.push(frame("p", 0, 0.0, exposure=None))
    forced.push(frame("q", 0, 0.0, exposure=None))
    assert forced.pop().interleaved is True


def test_bad_configuration_is_refused() -> None:
    with pytest.raises(ValueError, match="match"):
        BiplanePairer(match="nearest")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="mode"):
        BiplanePairer(mode="newest")  # type: ignore[arg-type]


class ListSource(FrameSource):
    """A scripted source: frames from a list, then EndOfStream (or an error)."""

    def __init__(self, plane: str, frames: list[Frame], end: BaseException | None = None) -> None:
        super().__init__(plane=plane, name=f"list-{plane}", width=6, height=4)
        self._frames = list(frames)
        self._end = end

    def _open_internal(self) -> None:
        pass

    def _close_internal(self) -> None:
        pass

    def _read_internal(self, deadline: float) -> Frame | None:
        if self._frames:
            return self._frames.pop(0)
        raise self._end or EndOfStream("done")


def test_stream_all_mode_delivers_every_pair_then_ends() -> None:
    n = 300   # more than the backlog: the readers must wait for the consumer, never lose frames
    sources = [ListSource("p", stream_of("p", list(range(n)))), ListSource("q", stream_of("q", list(range(n))))]
    numbers = []
    with BiplaneStream(sources, BiplanePairer(mode="all")) as stream:
        with pytest.raises(EndOfStream):
            while True:
                numbers.append(stream.next_pair(5.0).number)
    assert numbers == list(range(n))
    assert all(not source.is_open for source in sources)


def test_stream_raises_a_reader_error_to_the_consumer() -> None:
    sources = [ListSource("p", stream_of("p", [0]), end=LinkLostError("cable pulled")),
               ListSource("q", stream_of("q", [0]), end=LinkLostError("cable pulled"))]
    with BiplaneStream(sources, BiplanePairer(mode="all")) as stream:
        assert stream.next_pair(5.0).number == 0
        with pytest.raises(LinkLostError, match="cable pulled"):
            stream.next_pair(5.0)


def test_stream_times_out_without_pairs_and_checks_planes() -> None:
    class Silent(ListSource):
        def _read_internal(self, deadline: float) -> Frame | None:
            return None

    with BiplaneStream([Silent("p", []), Silent("q", [])], poll_s=0.01) as stream:
        with pytest.raises(DeviceTimeoutError):
            stream.next_pair(0.05)
    with pytest.raises(ValueError, match="one source per plane"):
        BiplaneStream([ListSource("p", []), ListSource("p", [])])
