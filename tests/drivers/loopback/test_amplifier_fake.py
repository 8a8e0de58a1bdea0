"""The loopback amplifier driven in-process through the codec on a synthetic clock: coil physics,
state machine, watchdog, protections, sequence-number rules, and a property test that no request
sequence drives the setpoint past the current or slew limit."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.loopback.amplifier_fake import FakeAmplifier, FakeAmplifierConfig, make_default_fake
from firmware_protocol.amplifier import (
    Ack,
    ClearFault,
    ConfigureLimits,
    Disable,
    Enable,
    Fault,
    GetStatus,
    Heartbeat,
    Hello,
    HelloReply,
    Message,
    MessageDecoder,
    Nak,
    NakReason,
    SetCurrents,
    SetCurrentsReply,
    State,
    Status,
    encode_message,
)


class Host:
    """Talks to the fake through the codec with a synthetic clock."""

    def __init__(self, fake: FakeAmplifier) -> None:
        self.fake = fake
        self.t = 0.0
        self.seq = 0
        self.decoder = MessageDecoder()
        fake.tick(self.t)

    def send(self, message: Message, seq: int | None = None) -> Message:
        if seq is None:
            self.seq = (self.seq + 1) & 0xFFFF
            seq = self.seq
        replies = self.decoder.feed(self.fake.feed(encode_message(message, seq), self.t))
        assert [r.seq for r in replies] == [seq]
        return replies[0].message

    def wait(self, seconds: float, *, heartbeat_s: float | None = None, step_s: float = 0.01) -> None:
        end = self.t + seconds
        while self.t < end - 1e-12:
            self.t = min(end, self.t + (heartbeat_s or step_s))
            if heartbeat_s:
                self.send(Heartbeat())
            else:
                self.fake.tick(self.t)


def enabled_host(config: FakeAmplifierConfig | None = None) -> Host:
    host = Host(FakeAmplifier(config or FakeAmplifierConfig(channels=3)))
    assert isinstance(host.send(Hello()), HelloReply)
    assert host.send(Enable()) == Ack(Enable.TYPE, State.ENABLED, Fault.NONE)
    return host


def test_output_starts_disabled_and_refuses_currents() -> None:
    host = Host(make_default_fake())
    hello = host.send(Hello())
    assert isinstance(hello, HelloReply) and hello.channels == 8 and hello.max_current_ma == (10000,) * 8
    assert host.fake.state is State.DISABLED
    reply = host.send(SetCurrents((1000,) * 8))
    assert isinstance(reply, Nak) and reply.reason is NakReason.BAD_STATE
    assert not host.fake.applied


def test_current_follows_a_first_order_lag_with_tau_l_over_r() -> None:
    # A slew limit so high that the reference steps at once: the coil alone shapes the response.
    cfg = FakeAmplifierConfig(channels=3, slew_a_per_s=1e6, coil_inductance_h=0.01, coil_resistance_ohm=0.5)
    host = enabled_host(cfg)
    host.send(SetCurrents((2000, -1000, 0)))
    host.wait(float(cfg.coil_time_constant_s[0]), heartbeat_s=0.005)   # tau = 20 ms
    expected = 1 - math.exp(-1)
    np.testing.assert_allclose(host.fake.measured_currents_a(), [2 * expected, -expected, 0], atol=5e-3)
    host.wait(0.2, heartbeat_s=0.02)
    np.testing.assert_allclose(host.fake.measured_currents_a(), [2.0, -1.0, 0.0], atol=1e-3)


def test_each_coil_has_its_own_time_constant() -> None:
    cfg = FakeAmplifierConfig(channels=2, slew_a_per_s=1e6, coil_inductance_h=(0.005, 0.02),
                              coil_resistance_ohm=(0.5, 1.0))   # tau 10 ms and 20 ms
    host = enabled_host(cfg)
    host.send(SetCurrents((1000, 1000)))
    host.wait(0.02, heartbeat_s=0.005)
    np.testing.assert_allclose(host.fake.measured_currents_a(), [1 - math.exp(-2), 1 - math.exp(-1)], atol=5e-3)


def test_per_channel_constants_must_match_the_channel_count() -> None:
    with pytest.raises(ValueError, match="coil_inductance_h: one value or one per channel"):
        FakeAmplifierConfig(channels=3, coil_inductance_h=(0.01, 0.02))


def test_reference_ramps_at_the_slew_limit_along_a_straight_line() -> None:
    host = enabled_host()   # 200 A/s
    host.send(SetCurrents((8000, -4000, 2000)))
    host.wait(0.02, heartbeat_s=0.01)
    snap = host.fake.snapshot()
    # 20 ms at 200 A/s on the largest step (channel 0): 4 A; the others in proportion.
    np.testing.assert_allclose(snap.setpoint_a, [4.0, -2.0, 1.0], atol=1e-6)


def test_vector_over_the_limit_is_scaled_whole_by_the_amplifier() -> None:
    host = enabled_host()
    reply = host.send(SetCurrents((20000, -5000, 0)))
    assert isinstance(reply, SetCurrentsReply) and reply.clamped_mask == 0b001
    assert host.fake.applied[-1].target_ma == (10000, -2500, 0)


def test_watchdog_ramps_to_zero_at_the_slew_limit_and_latches() -> None:
    host = enabled_host(FakeAmplifierConfig(channels=3, watchdog_ms=100))
    host.send(SetCurrents((6000, 0, -3000)))
    host.wait(0.1, heartbeat_s=0.02)
    assert host.fake.state is State.ENABLED
    host.wait(0.105, step_s=0.001)   # silent host: 100 ms watchdog expired about 5 ms ago
    snap = host.fake.snapshot()
    assert snap.state is State.FAULT and snap.faults & Fault.WATCHDOG
    assert 4.5 < snap.setpoint_a[0] < 6.0   # a ramp at 200 A/s, not a cut
    host.wait(0.2)
    snap = host.fake.snapshot()
    assert not snap.output_on and np.all(np.abs(snap.measured_a) < 1e-3)
    reply = host.send(SetCurrents((1000, 0, 0)))
    assert isinstance(reply, Nak) and reply.reason is NakReason.FAULT_ACTIVE
    assert host.send(ClearFault()) == Ack(ClearFault.TYPE, State.DISABLED, Fault.NONE)
    assert isinstance(host.send(Enable()), Ack) and host.fake.state is State.ENABLED


def test_a_retransmitted_command_is_answered_again_but_applied_once() -> None:
    host = enabled_host()
    frame = encode_message(SetCurrents((1000, 2000, 3000)), 50)
    first = host.fake.feed(frame, host.t)
    again = host.fake.feed(frame, host.t + 0.001)
    assert first == again
    assert [a.seq for a in host.fake.applied] == [50] and host.fake.duplicates == 1


def test_a_stale_command_is_refused_and_not_applied() -> None:
    host = enabled_host()
    host.send(SetCurrents((1000, 0, 0)), seq=100)
    reply = host.send(SetCurrents((9000, 0, 0)), seq=99)
    assert isinstance(reply, Nak) and reply.reason is NakReason.STALE_SEQUENCE
    assert [a.target_ma for a in host.fake.applied] == [(1000, 0, 0)]
    # HELLO starts a new session whatever its number; numbering continues from it.
    assert isinstance(host.send(Hello(), seq=7), HelloReply)
    assert isinstance(host.send(Heartbeat(), seq=8), Ack)
    assert host.send(Heartbeat(), seq=6).reason is NakReason.STALE_SEQUENCE


def test_sequence_numbers_wrap_from_65535_to_0() -> None:
    host = Host(FakeAmplifier(FakeAmplifierConfig(channels=3)))
    host.send(Hello(), seq=0xFFFD)
    host.send(Enable(), seq=0xFFFE)
    assert isinstance(host.send(SetCurrents((1000, 0, 0)), seq=0xFFFF), SetCurrentsReply)
    assert isinstance(host.send(SetCurrents((2000, 0, 0)), seq=0), SetCurrentsReply)
    assert host.send(SetCurrents((3000, 0, 0)), seq=0xFFFF).reason is NakReason.STALE_SEQUENCE
    assert [a.seq for a in host.fake.applied] == [0xFFFF, 0]


def test_estop_cuts_output_and_cannot_be_cleared_while_pressed() -> None:
    host = enabled_host()
    host.send(SetCurrents((5000, 0, 0)))
    host.wait(0.1, heartbeat_s=0.02)
    host.fake.press_estop()
    snap = host.fake.snapshot()
    assert snap.state is State.FAULT and not snap.output_on and snap.faults & Fault.ESTOP_INPUT
    host.wait(0.1, heartbeat_s=0.02)
    assert np.all(np.abs(host.fake.measured_currents_a()) < 0.01)   # decayed with L/R (10 ms)
    for request in (ClearFault(), Enable()):
        reply = host.send(request)
        assert isinstance(reply, Nak) and reply.reason is NakReason.ESTOP_ACTIVE
    host.fake.release_estop()
    assert isinstance(host.send(ClearFault()), Ack)
    assert isinstance(host.send(Enable()), Ack)


def test_over_temperature_ramps_down_and_clear_waits_for_the_coil_to_cool() -> None:
    host = enabled_host()
    host.send(SetCurrents((2000, 0, 0)))
    host.wait(0.05, heartbeat_s=0.01)
    host.fake.inject_over_temperature(channel=1)
    host.wait(0.001)
    snap = host.fake.snapshot()
    assert snap.state is State.FAULT and snap.faults & Fault.OVER_TEMPERATURE and snap.output_on
    reply = host.send(ClearFault())
    assert isinstance(reply, Nak) and reply.reason is NakReason.CONDITION_PRESENT
    host.fake.set_temperature_c(1, 60.0)
    assert isinstance(host.send(ClearFault()), Ack)


def test_over_current_cuts_the_output_at_once() -> None:
    host = enabled_host()
    host.send(SetCurrents((1000, 0, 0)))
    host.fake.inject_over_current(channel=2)
    snap = host.fake.snapshot()
    assert snap.faults & Fault.OVER_CURRENT and not snap.output_on and snap.state is State.FAULT


def test_over_current_clears_only_once_the_surge_has_decayed() -> None:
    host = enabled_host()
    host.fake.inject_over_current(channel=2)
    reply = host.send(ClearFault())                       # the surge still flows through the coil
    assert isinstance(reply, Nak) and reply.reason is NakReason.CONDITION_PRESENT
    host.wait(0.1)                                        # ten L/R time constants of the default coil
    assert isinstance(host.send(ClearFault()), Ack)
    assert isinstance(host.send(Enable()), Ack)
    host.wait(0.01)
    assert host.fake.snapshot().state is State.ENABLED   # and it does not trip again


def test_coil_heats_towards_i2r_times_thermal_resistance() -> None:
    cfg = FakeAmplifierConfig(channels=1, thermal_time_constant_s=0.5, thermal_resistance_k_per_w=2.0)
    host = enabled_host(cfg)
    host.send(SetCurrents((4000,)))
    host.wait(4.0, heartbeat_s=0.05)   # 8 thermal time constants
    # 4 A through 0.5 ohm is 8 W; 2 K/W gives a 16 K rise over the 25 degC ambient.
    assert host.fake.snapshot().temperature_c[0] == pytest.approx(41.0, abs=0.1)
    status = host.send(GetStatus())
    assert isinstance(status, Status) and status.temperature_dc == (410,)


def test_limits_are_configured_only_while_disabled_and_within_rating() -> None:
    host = enabled_host()
    limits = ConfigureLimits(watchdog_ms=150, max_current_ma=(5000, 5000, 5000), slew_ma_per_s=(50000,) * 3)
    assert host.send(limits).reason is NakReason.BAD_STATE
    host.send(Disable())
    too_high = ConfigureLimits(watchdog_ms=150, max_current_ma=(13000, 5000, 5000), slew_ma_per_s=(50000,) * 3)
    assert host.send(too_high).reason is NakReason.OUT_OF_RANGE
    assert isinstance(host.send(limits), Ack)
    host.send(Enable())
    host.send(SetCurrents((8000, 0, 0)))
    assert host.fake.applied[-1].target_ma == (5000, 0, 0)
    assert host.fake.snapshot().watchdog_ms == 150


# ---- property: the setpoint never exceeds the current or slew limit --------------------------

_requests = st.one_of(
    st.tuples(st.just("set"), st.lists(st.integers(-40_000, 40_000), min_size=3, max_size=3)),
    st.tuples(st.just("limits"), st.tuples(st.integers(1, 12_000), st.integers(1, 500_000))),
    st.sampled_from([("enable", None), ("disable", None), ("clear", None), ("heartbeat", None),
                     ("estop", None), ("release", None), ("hot", None), ("cool", None)]),
)


@given(st.lists(st.tuples(_requests, st.floats(0.0, 0.02)), max_size=25))
@settings(max_examples=60, deadline=None)
def test_no_request_sequence_drives_the_setpoint_past_a_limit(steps) -> None:
    host = Host(FakeAmplifier(FakeAmplifierConfig(channels=3, watchdog_ms=50)))
    host.send(Hello())
    before = host.fake.snapshot()
    for (kind, arg), dt in steps:
        applied_before = len(host.fake.applied)
        if kind == "set":
            host.send(SetCurrents(tuple(arg)))
        elif kind == "limits":
            host.send(ConfigureLimits(100, (arg[0],) * 3, (arg[1],) * 3))
        elif kind in ("enable", "disable", "clear", "heartbeat"):
            host.send({"enable": Enable(), "disable": Disable(), "clear": ClearFault(),
                       "heartbeat": Heartbeat()}[kind])
        elif kind == "estop":
            host.fake.press_estop()
        elif kind == "release":
            host.fake.release_estop()
        elif kind == "hot":
            host.fake.inject_over_temperature(0)
        else:
            host.fake.set_temperature_c(0, 25.0)
        for _ in range(2):   # observe within and at the end of the interval
            host.t += dt / 2
            host.fake.tick(host.t)
            after = host.fake.snapshot()
            assert np.all(np.abs(after.setpoint_a) <= after.max_current_a + 1e-9)
            step = np.abs(after.setpoint_a - before.setpoint_a)
            within_slew = np.all(step <= after.slew_a_per_s * (after.t - before.t) + 1e-9)
            # The only faster change allowed is switching the output off (currents then decay with L/R).
            assert within_slew or (not after.output_on and not np.any(after.setpoint_a))
            before = after
        # Commands are checked at the moment they are applied too: a SET_CURRENTS this step applied holds the
        # limits in force (one refused, e.g. while disabled, leaves an older command last, applied under older
        # limits).
        if kind == "set" and len(host.fake.applied) > applied_before:
            target = np.abs(np.asarray(host.fake.applied[-1].target_ma))
            assert np.all(target <= before.max_current_a * 1000 + 1e-9)
