"""Byte-exact exchanges of the amplifier driver against scripted replies: retries on a bad CRC and on
silence (same bytes, same sequence number), NAKs as typed errors, late replies discarded, scaling,
shutdown order. The scripted port fails on an unexpected write, a leftover exchange or an unread reply."""
from __future__ import annotations

import time
from collections import deque

import numpy as np
import pytest
import serial
from hypothesis import given
from hypothesis import strategies as st

from drivers.amplifier import (
    Amplifier,
    AmplifierEvent,
    CommandRejectedError,
    CurrentCommandError,
    EStopError,
    WatchdogError,
)
from drivers.amplifier_types import AmplifierLimits, limit_current_list, limit_currents
from drivers.errors import DeviceTimeoutError, LinkLostError, ProtocolError
from firmware_protocol.amplifier import (
    Ack,
    Disable,
    Enable,
    Fault,
    GetStatus,
    Hello,
    HelloReply,
    MsgType,
    Nak,
    NakReason,
    SetCurrents,
    SetCurrentsReply,
    State,
    Status,
    encode_message,
)

CHANNELS = 3
# Slew so high that the host-side slew limiter never shortens a step in these tests.
HELLO_REPLY = HelloReply((1, 0, 0), 7, 100, 800, (12000,) * CHANNELS, (10000,) * CHANNELS,
                         (4_000_000_000,) * CHANNELS)


class ScriptedPort:
    """A pyserial-like port that plays a script of (expected write, reply) pairs."""

    name = "scripted"

    def __init__(self, script: list[tuple[bytes, bytes]]) -> None:
        self.script = deque(script)
        self.pending = bytearray()
        self.timeout: float | None = None
        self.closed = False
        self.fail_writes = False

    def write(self, data: bytes) -> int:
        if self.fail_writes:
            raise serial.SerialException("device reports readiness to read but returned no data")
        assert not self.pending, f"host wrote {data.hex(' ')} with an unread reply {self.pending.hex(' ')}"
        assert self.script, f"unexpected write {data.hex(' ')}"
        expected, reply = self.script.popleft()
        assert data == expected, f"wrote {data.hex(' ')}, expected {expected.hex(' ')}"
        self.pending += reply
        return len(data)

    @property
    def in_waiting(self) -> int:
        return len(self.pending)

    def read(self, size: int = 1) -> bytes:
        if not self.pending:
            time.sleep(self.timeout or 0.0)
            return b""
        out = bytes(self.pending[:size])
        del self.pending[:size]
        return out

    def reset_input_buffer(self) -> None:
        self.pending.clear()

    def close(self) -> None:
        self.closed = True

    def assert_done(self) -> None:
        assert not self.script, f"{len(self.script)} scripted exchanges left"
        assert not self.pending, "reply bytes left unread"


def status(state: State, faults: Fault = Fault.NONE, measured: tuple[int, ...] = (0,) * CHANNELS) -> Status:
    return Status(state, faults, 1000, 0, (0,) * CHANNELS, measured, (250,) * CHANNELS)


def connect(seq_status_state: State = State.DISABLED) -> list[tuple[bytes, bytes]]:
    # HELLO with sequence number 1, byte for byte as in amplifier_vectors.json.
    hello = bytes.fromhex("00 04 01 01 01 01 03 d9 fa 00")
    assert hello == encode_message(Hello(), 1)
    return [(hello, encode_message(HELLO_REPLY, 1)),
            (encode_message(GetStatus(), 2), encode_message(status(seq_status_state), 2))]


def ack(kind: MsgType, seq: int, state: State = State.ENABLED, faults: Fault = Fault.NONE) -> bytes:
    return encode_message(Ack(kind, state, faults), seq)


def open_amp(script: list[tuple[bytes, bytes]], **kwargs) -> tuple[Amplifier, ScriptedPort]:
    port = ScriptedPort(script)
    amp = Amplifier(port, ack_timeout_s=0.01, retries=2, heartbeat_period_s=0, **kwargs)
    return amp, port


def test_connect_reads_identity_and_state() -> None:
    amp, port = open_amp(connect())
    assert amp.info.channels == CHANNELS and amp.info.firmware_version == (1, 0, 0)
    assert amp.info.rated_current_a == (12.0,) * CHANNELS and amp.limits.watchdog_ms == 100
    assert amp.state is State.DISABLED
    port.assert_done()
    amp.close()
    amp.close()   # idempotent
    assert port.closed


def test_set_currents_sends_milliamps_and_returns_measured() -> None:
    request = encode_message(SetCurrents((1500, -250, 0)), 4)
    reply = encode_message(SetCurrentsReply(State.ENABLED, Fault.NONE, 0, (1400, -240, 1)), 4)
    amp, port = open_amp(connect() + [(encode_message(Enable(), 3), ack(MsgType.ENABLE, 3)), (request, reply)])
    amp.enable()
    result = amp.set_currents([1.5, -0.25, 0.0])
    assert result.seq == 4 and result.attempts == 1 and not result.scaled
    np.testing.assert_allclose(result.measured_a, [1.4, -0.24, 0.001])
    port.assert_done()


def test_every_form_of_the_vector_puts_the_same_bytes_on_the_wire() -> None:
    """A list, a float64 array, an int array and a strided view: the same SET_CURRENTS frame (built by
    the driver's own encoder) and the same result arrays."""
    values = [(1.5, -0.25, 0.0), np.array([1.5, -0.25, 0.0]), np.array([[1.5, 9.0], [-0.25, 9.0], [0.0, 9.0]])[:, 0],
              np.array([2, -1, 0])]
    script = connect() + [(encode_message(Enable(), 3), ack(MsgType.ENABLE, 3))]
    for seq, vector in enumerate(values, start=4):
        ma = tuple(int(v * 1000.0) for v in np.asarray(vector, float))
        script.append((encode_message(SetCurrents(ma), seq),
                       encode_message(SetCurrentsReply(State.ENABLED, Fault.NONE, 0, ma), seq)))
    amp, port = open_amp(script)
    amp.enable()
    for vector in values:
        result = amp.set_currents(vector)
        assert result.requested_a.dtype == np.float64 and result.commanded_a.dtype == np.float64
        np.testing.assert_array_equal(result.requested_a, np.asarray(vector, float))
        np.testing.assert_array_equal(result.commanded_a, result.measured_a)
    port.assert_done()


def test_a_vector_over_the_limit_is_scaled_as_a_whole() -> None:
    # 20 A on channel 0 against a 10 A limit: every channel halves, the direction is kept.
    request = encode_message(SetCurrents((10000, -3000, 500)), 4)
    reply = encode_message(SetCurrentsReply(State.ENABLED, Fault.NONE, 0, (0, 0, 0)), 4)
    amp, port = open_amp(connect() + [(encode_message(Enable(), 3), ack(MsgType.ENABLE, 3)), (request, reply)])
    amp.enable()
    result = amp.set_currents([20.0, -6.0, 1.0])
    assert result.current_scale == pytest.approx(0.5) and result.slew_scale == 1.0
    np.testing.assert_allclose(result.commanded_a, [10.0, -3.0, 0.5])
    port.assert_done()


def test_bad_crc_reply_is_counted_and_the_same_frame_is_retransmitted() -> None:
    request = encode_message(SetCurrents((1000, 0, 0)), 4)
    good = encode_message(SetCurrentsReply(State.ENABLED, Fault.NONE, 0, (1000, 0, 0)), 4)
    bad = bytearray(good)
    bad[-2] ^= 0x40   # inside the CRC
    amp, port = open_amp(connect() + [(encode_message(Enable(), 3), ack(MsgType.ENABLE, 3)),
                                      (request, bytes(bad)), (request, good)])
    amp.enable()
    result = amp.set_currents([1.0, 0.0, 0.0])
    assert result.attempts == 2 and result.seq == 4
    assert amp.decoder_rejections["crc"] == 1 and amp.retransmissions == 1
    port.assert_done()


def test_silence_is_retried_then_reported_as_a_timeout() -> None:
    request = encode_message(SetCurrents((1000, 0, 0)), 4)
    events: list[AmplifierEvent] = []
    amp, port = open_amp(connect() + [(encode_message(Enable(), 3), ack(MsgType.ENABLE, 3))]
                         + [(request, b"")] * 3)
    amp.add_listener(events.append)
    amp.enable()
    with pytest.raises(DeviceTimeoutError, match=r"scripted did not answer SET_CURRENTS \(seq 4\) within 3 x"):
        amp.set_currents([1.0, 0.0, 0.0])
    assert [e.kind for e in events] == ["link_lost"]
    port.assert_done()


def test_a_late_reply_to_an_earlier_sequence_number_is_never_taken_for_the_current_one() -> None:
    late = encode_message(SetCurrentsReply(State.ENABLED, Fault.NONE, 0, (9999, 9999, 9999)), 4)
    right = encode_message(SetCurrentsReply(State.ENABLED, Fault.NONE, 0, (2000, 0, 0)), 5)
    amp, port = open_amp(connect() + [
        (encode_message(Enable(), 3), ack(MsgType.ENABLE, 3)),
        (encode_message(SetCurrents((1000, 0, 0)), 4), b""),      # reply lost three times
        (encode_message(SetCurrents((1000, 0, 0)), 4), b""),
        (encode_message(SetCurrents((1000, 0, 0)), 4), b""),
        (encode_message(SetCurrents((2000, 0, 0)), 5), late + right)])
    amp.enable()
    with pytest.raises(DeviceTimeoutError):
        amp.set_currents([1.0, 0.0, 0.0])
    result = amp.set_currents([2.0, 0.0, 0.0])
    np.testing.assert_allclose(result.measured_a, [2.0, 0.0, 0.0])
    assert amp.discarded_replies == 1
    port.assert_done()


def test_nak_for_wrong_state_is_a_rejected_command() -> None:
    nak = encode_message(Nak(MsgType.SET_CURRENTS, NakReason.BAD_STATE, State.DISABLED, Fault.NONE), 3)
    amp, port = open_amp(connect() + [(encode_message(SetCurrents((0, 0, 0)), 3), nak)])
    with pytest.raises(CommandRejectedError, match="BAD_STATE") as info:
        amp.set_currents([0.0, 0.0, 0.0])
    assert info.value.reason is NakReason.BAD_STATE
    port.assert_done()


def test_a_latched_watchdog_fault_raises_a_typed_error_and_notifies_listeners() -> None:
    flags = Fault.WATCHDOG
    nak = encode_message(Nak(MsgType.SET_CURRENTS, NakReason.FAULT_ACTIVE, State.FAULT, flags), 3)
    events: list[AmplifierEvent] = []
    amp, port = open_amp(connect() + [(encode_message(SetCurrents((100, 0, 0)), 3), nak)])
    amp.add_listener(events.append)
    with pytest.raises(WatchdogError) as info:
        amp.set_currents([0.1, 0.0, 0.0])
    assert info.value.faults == flags and info.value.state is State.FAULT
    assert [(e.kind, e.faults) for e in events] == [("fault", flags)]
    assert amp.faults == flags
    port.assert_done()


def test_enable_during_estop_raises_estop_error() -> None:
    flags = Fault.ESTOP | Fault.ESTOP_INPUT
    nak = encode_message(Nak(MsgType.ENABLE, NakReason.ESTOP_ACTIVE, State.FAULT, flags), 3)
    amp, port = open_amp(connect() + [(encode_message(Enable(), 3), nak)])
    with pytest.raises(EStopError, match="emergency stop"):
        amp.enable()
    port.assert_done()


def test_a_reply_of_the_wrong_type_is_a_protocol_error() -> None:
    amp, port = open_amp(connect() + [(encode_message(SetCurrents((0, 0, 0)), 3), ack(MsgType.SET_CURRENTS, 3))])
    with pytest.raises(ProtocolError, match="answered by Ack"):
        amp.set_currents([0.0, 0.0, 0.0])
    port.assert_done()


@pytest.mark.parametrize("bad", [[1.0, 2.0], [1.0, float("nan"), 0.0], [[1.0, 2.0, 3.0]]])
def test_invalid_vectors_are_refused_before_anything_is_sent(bad) -> None:
    amp, port = open_amp(connect())
    with pytest.raises(CurrentCommandError):
        amp.set_currents(bad)
    port.assert_done()


def test_a_dry_run_and_the_rehearsal_send_nothing_and_leave_the_next_command_as_it_was() -> None:
    """The start-up's rehearsal of the command path writes nothing (the scripted port refuses any write not
    in its script) and keeps the sequence number and the slew state: the command after it is the same
    frame, with the same sequence number, as without it."""
    request = encode_message(SetCurrents((1500, -250, 0)), 4)
    reply = encode_message(SetCurrentsReply(State.ENABLED, Fault.NONE, 0, (1400, -240, 1)), 4)
    amp, port = open_amp(connect() + [(encode_message(Enable(), 3), ack(MsgType.ENABLE, 3)), (request, reply)])
    amp.enable()
    assert amp.set_currents([9.0, -9.0, 9.0], dry_run=True) is None
    amp.rehearse_command()
    result = amp.set_currents([1.5, -0.25, 0.0])
    assert result.seq == 4 and not result.scaled
    port.assert_done()


def test_a_dry_run_still_refuses_an_invalid_vector() -> None:
    amp, port = open_amp(connect())
    with pytest.raises(CurrentCommandError):
        amp.set_currents([1.0, float("nan"), 0.0], dry_run=True)
    port.assert_done()


def test_shutdown_ramps_to_zero_then_disables_then_closes() -> None:
    zero = encode_message(SetCurrents((0, 0, 0)), 5)
    amp, port = open_amp(connect() + [
        (encode_message(Enable(), 3), ack(MsgType.ENABLE, 3)),
        (encode_message(SetCurrents((3000, 0, 0)), 4),
         encode_message(SetCurrentsReply(State.ENABLED, Fault.NONE, 0, (2900, 0, 0)), 4)),
        (zero, encode_message(SetCurrentsReply(State.ENABLED, Fault.NONE, 0, (2800, 0, 0)), 5)),
        (encode_message(GetStatus(), 6), encode_message(status(State.ENABLED, measured=(10, 0, 0)), 6)),
        (encode_message(Disable(), 7), ack(MsgType.DISABLE, 7, State.DISABLED))])
    with amp:
        amp.enable()
        amp.set_currents([3.0, 0.0, 0.0])
    port.assert_done()
    assert port.closed
    assert amp.shutdown() is False   # already closed: nothing sent


def test_a_failing_port_is_reported_as_link_lost() -> None:
    amp, port = open_amp(connect())
    port.fail_writes = True
    with pytest.raises(LinkLostError, match="scripted"):
        amp.heartbeat()


def test_a_listener_error_is_raised_from_the_next_call() -> None:
    nak = encode_message(Nak(MsgType.ENABLE, NakReason.FAULT_ACTIVE, State.FAULT, Fault.OVER_CURRENT), 3)
    amp, port = open_amp(connect() + [(encode_message(Enable(), 3), nak)])

    def broken(event: AmplifierEvent) -> None:
        raise RuntimeError("recorder is full")

    amp.add_listener(broken)
    with pytest.raises(Exception, match="OVER_CURRENT"):
        amp.enable()
    with pytest.raises(RuntimeError, match="recorder is full"):
        amp.status()
    port.assert_done()


def test_host_side_limiter_keeps_direction_and_slew() -> None:
    limits = AmplifierLimits.uniform(3, max_current_a=10.0, slew_a_per_s=100.0, watchdog_ms=100)
    commanded, current_scale, slew_scale = limit_currents(np.array([30.0, -15.0, 0.0]), np.zeros(3), 0.05, limits)
    assert current_scale == pytest.approx(1 / 3)
    # Target (10, -5, 0); 100 A/s over 50 ms allows 5 A on the largest step: half the way.
    assert slew_scale == pytest.approx(0.5)
    np.testing.assert_allclose(commanded, [5.0, -2.5, 0.0])


def test_limits_given_at_connection_wait_for_clear_fault_when_the_amplifier_is_in_fault() -> None:
    from firmware_protocol.amplifier import ClearFault, ConfigureLimits

    limits = AmplifierLimits.uniform(CHANNELS, max_current_a=5.0, slew_a_per_s=100.0, watchdog_ms=150)
    script = connect(State.FAULT)
    script[1] = (script[1][0], encode_message(status(State.FAULT, Fault.WATCHDOG), 2))
    script += [(encode_message(ClearFault(), 3), ack(MsgType.CLEAR_FAULT, 3, State.DISABLED)),
               (encode_message(ConfigureLimits(150, (5000,) * CHANNELS, (100000,) * CHANNELS), 4),
                ack(MsgType.CONFIGURE_LIMITS, 4, State.DISABLED))]
    amp, port = open_amp(script, limits=limits)
    assert amp.limits != limits and amp.faults == Fault.WATCHDOG
    amp.clear_fault()
    assert amp.limits == limits
    port.assert_done()


@given(st.lists(st.floats(-100, 100), min_size=3, max_size=3), st.lists(st.floats(-10, 10), min_size=3, max_size=3),
       st.floats(0, 0.2), st.floats(0.1, 20), st.floats(1, 1000))
def test_host_limiter_never_exceeds_a_limit_and_keeps_the_field_direction(
        requested, previous, dt_s, max_a, slew) -> None:
    limits = AmplifierLimits.uniform(3, max_current_a=max_a, slew_a_per_s=slew, watchdog_ms=100)
    requested_a, previous_a = np.array(requested), np.clip(np.array(previous), -max_a, max_a)
    commanded, current_scale, slew_scale = limit_currents(requested_a, previous_a, dt_s, limits)
    assert np.all(np.abs(commanded) <= max_a + 1e-9)
    assert np.all(np.abs(commanded - previous_a) <= slew * dt_s + 1e-9)
    assert 0 <= current_scale <= 1 and 0 <= slew_scale <= 1
    # The target is the requested vector scaled as a whole (same direction, never clipped per channel),
    # scaled no more than needed, and the command lies on the segment from the previous command to it.
    target = requested_a * current_scale
    assert np.all(np.abs(target) <= max_a * (1 + 1e-12))
    assert current_scale == 1.0 or np.isclose(np.max(np.abs(target)), max_a)
    np.testing.assert_allclose(commanded, previous_a + slew_scale * (target - previous_a), atol=1e-9)


@given(st.lists(st.floats(-30, 30), min_size=8, max_size=8), st.lists(st.floats(-12, 12), min_size=8, max_size=8),
       st.floats(0, 0.2), st.floats(0.5, 20), st.floats(1, 1000))
def test_the_drivers_milliamps_are_the_limited_currents_truncated(requested, previous, dt_s, max_a, slew) -> None:
    """The driver's one-pass form (``milliamps=True``) sends int(a * 1000) of the float form's currents, to
    the unit, scaled or not (rounding to nearest, or the clamp missing, would differ)."""
    limits = AmplifierLimits.uniform(8, max_current_a=max_a, slew_a_per_s=slew, watchdog_ms=100)
    previous = [min(max(p, -max_a), max_a) for p in previous]
    floats, current_scale, slew_scale = limit_current_list(requested, previous, dt_s, limits)
    milliamps, current_ma_scale, slew_ma_scale = limit_current_list(requested, previous, dt_s, limits, milliamps=True)
    assert milliamps == [int(v * 1000.0) for v in floats]
    assert all(type(v) is int for v in milliamps)
    assert (current_ma_scale, slew_ma_scale) == (current_scale, slew_scale)
