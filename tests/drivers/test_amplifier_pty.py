"""The amplifier driver against the loopback fake over a real pseudo-terminal (and once over TCP):
enable and a command sequence converging, the watchdog when the host goes silent, e-stop,
over-temperature, an unplugged link, recovery after clear-fault, and retries on a noisy line.
The same contract runs against real hardware with ``--device-url amplifier=URL`` (status only)."""
from __future__ import annotations

import random
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from drivers.amplifier import (
    Amplifier,
    AmplifierEvent,
    AmplifierLimits,
    EStopError,
    OverCurrentError,
    OverTemperatureError,
    WatchdogError,
)
from drivers.errors import DeviceTimeoutError
from drivers.loopback.amplifier_fake import FakeAmplifier, FakeAmplifierConfig
from drivers.loopback.serve import PtyServer, TcpServer
from drivers.transport import open_serial
from firmware_protocol.amplifier import Fault, State

CHANNELS = 4


# Tests that are not about the watchdog use a long one: on a loaded 2-core CI machine a thread can be
# starved for longer than a 100 ms period, which would trip it for reasons that are not under test.
@pytest.fixture
def fake() -> FakeAmplifier:
    return FakeAmplifier(FakeAmplifierConfig(channels=CHANNELS, watchdog_ms=1000))


@pytest.fixture
def short_watchdog_fake() -> FakeAmplifier:
    return FakeAmplifier(FakeAmplifierConfig(channels=CHANNELS, watchdog_ms=200))


@pytest.fixture
def server(fake: FakeAmplifier) -> Iterator[PtyServer]:
    with PtyServer(fake) as srv:
        yield srv


@pytest.fixture
def short_watchdog_server(short_watchdog_fake: FakeAmplifier) -> Iterator[PtyServer]:
    with PtyServer(short_watchdog_fake) as srv:
        yield srv


def wait_until(predicate, timeout_s: float = 5.0, step_s: float = 0.005) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(step_s)
    return predicate()


def drive(amp: Amplifier, target: np.ndarray, seconds: float) -> None:
    """Command ``target`` at 200 Hz for ``seconds``, as a control loop would."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        amp.set_currents(target)
        time.sleep(0.005)


def drive_until_settled(amp: Amplifier, target: np.ndarray, timeout_s: float = 5.0) -> float:
    """Command ``target`` at 200 Hz until the measured currents in the acknowledgements settle on it;
    returns how long it took (a deadline instead of a fixed time: CI machines are loaded)."""
    start = time.monotonic()
    while time.monotonic() - start < timeout_s:
        result = amp.set_currents(target)
        if np.allclose(result.measured_a, target, atol=1e-3):   # tighter than the checks that follow
            return time.monotonic() - start
        time.sleep(0.005)
    raise AssertionError(f"measured {amp.status().measured_a} did not settle on {target} in {timeout_s} s")


def test_enable_and_a_command_sequence_converge(server: PtyServer, fake: FakeAmplifier) -> None:
    with Amplifier(open_serial(server.path), ack_timeout_s=0.2) as amp:
        assert amp.info.channels == CHANNELS and amp.state is State.DISABLED
        amp.enable()
        for target in ([2.0, -1.0, 0.5, 0.0], [-3.0, 3.0, 0.0, 1.5], [0.5, 0.5, -0.5, -0.5]):
            drive_until_settled(amp, np.array(target))   # slew 200 A/s, tau 10 ms: ~60 ms unloaded
            np.testing.assert_allclose(amp.status().measured_a, target, atol=2e-3)
            np.testing.assert_allclose(fake.measured_currents_a(), target, atol=2e-3)
        applied = [a.seq for a in fake.applied]
        assert applied == sorted(set(applied))   # each command applied once, in order
    assert fake.state is State.DISABLED
    assert np.all(np.abs(fake.measured_currents_a()) < 0.05)


def test_watchdog_fires_when_the_host_goes_silent_then_clear_fault_recovers(
        short_watchdog_server: PtyServer, short_watchdog_fake: FakeAmplifier) -> None:
    fake = short_watchdog_fake
    events: list[AmplifierEvent] = []
    amp = Amplifier(open_serial(short_watchdog_server.path), ack_timeout_s=0.2, heartbeat_period_s=0)
    amp.add_listener(events.append)
    amp.enable()
    drive(amp, np.array([3.0, 0.0, -2.0, 1.0]), 0.1)
    # Silence: no heartbeat, no command. 200 ms watchdog, then a ramp at 200 A/s (15 ms) and tau 10 ms.
    assert wait_until(lambda: fake.state is State.FAULT)
    assert wait_until(lambda: bool(np.all(np.abs(fake.measured_currents_a()) < 1e-3)))
    status = amp.status()
    assert status.state is State.FAULT and status.faults & Fault.WATCHDOG
    assert np.all(np.abs(status.measured_a) < 0.002)
    assert [e.kind for e in events] == ["fault"]
    with pytest.raises(WatchdogError):
        amp.set_currents(np.ones(CHANNELS))
    amp.clear_fault()
    assert [e.kind for e in events] == ["fault", "fault_cleared"]
    amp.enable()
    result = amp.set_currents(np.zeros(CHANNELS))
    assert result.state is State.ENABLED
    assert amp.shutdown() is True


def test_heartbeat_keeps_an_idle_enabled_amplifier_alive(server: PtyServer, fake: FakeAmplifier) -> None:
    limits = AmplifierLimits.uniform(CHANNELS, max_current_a=10.0, slew_a_per_s=200.0, watchdog_ms=400)
    with Amplifier(open_serial(server.path), ack_timeout_s=0.2, limits=limits) as amp:   # heartbeat 100 ms
        assert amp.heartbeat_period_s == pytest.approx(0.1)
        amp.enable()
        time.sleep(1.2)   # three watchdog periods without a command
        assert fake.state is State.ENABLED and amp.status().faults == Fault.NONE


def test_estop_is_reported_and_blocks_until_released(server: PtyServer, fake: FakeAmplifier) -> None:
    events: list[AmplifierEvent] = []
    with Amplifier(open_serial(server.path), ack_timeout_s=0.2) as amp:
        amp.add_listener(events.append)
        amp.enable()
        drive(amp, np.array([1.0, 1.0, 1.0, 1.0]), 0.05)
        fake.press_estop()
        # The heartbeat alone brings the news to listeners.
        assert wait_until(lambda: any(e.kind == "fault" and e.faults & Fault.ESTOP for e in events))
        with pytest.raises(EStopError):
            amp.set_currents(np.zeros(CHANNELS))
        with pytest.raises(EStopError, match="release it"):
            amp.clear_fault()
        fake.release_estop()
        amp.clear_fault()
        amp.enable()
        assert amp.set_currents(np.zeros(CHANNELS)).state is State.ENABLED


def test_over_temperature_trips_and_clears_once_cool(server: PtyServer, fake: FakeAmplifier) -> None:
    with Amplifier(open_serial(server.path), ack_timeout_s=0.2) as amp:
        amp.enable()
        drive(amp, np.array([2.0, 0.0, 0.0, 0.0]), 0.05)
        fake.inject_over_temperature(channel=0)
        with pytest.raises(OverTemperatureError) as info:
            drive(amp, np.array([2.0, 0.0, 0.0, 0.0]), 0.5)
        assert info.value.faults & Fault.OVER_TEMPERATURE
        with pytest.raises(OverTemperatureError, match="restart temperature"):
            amp.clear_fault()
        fake.set_temperature_c(0, 40.0)
        amp.clear_fault()
        assert amp.status().state is State.DISABLED


def test_over_current_cuts_the_output_and_is_a_typed_error(server: PtyServer, fake: FakeAmplifier) -> None:
    with Amplifier(open_serial(server.path), ack_timeout_s=0.2) as amp:
        amp.enable()
        drive(amp, np.array([1.0, 0.0, 0.0, 0.0]), 0.05)
        fake.inject_over_current(channel=3)
        with pytest.raises(OverCurrentError) as info:
            amp.set_currents(np.array([1.0, 0.0, 0.0, 0.0]))
        assert info.value.faults & Fault.OVER_CURRENT and not fake.snapshot().output_on
        # The surge decays through the coil's L/R once the output is cut; only then may the fault clear.
        assert wait_until(lambda: float(np.max(np.abs(fake.measured_currents_a()))) < 1.0)
        amp.clear_fault()
        amp.enable()


def test_unplugged_link_times_out_and_the_amplifier_protects_itself(
        short_watchdog_server: PtyServer, short_watchdog_fake: FakeAmplifier) -> None:
    server, fake = short_watchdog_server, short_watchdog_fake
    events: list[AmplifierEvent] = []
    with Amplifier(open_serial(server.path), ack_timeout_s=0.2, retries=1) as amp:
        amp.add_listener(events.append)
        amp.enable()
        drive(amp, np.array([1.0, 0.0, 0.0, 0.0]), 0.05)
        server.unplugged.set()
        with pytest.raises(DeviceTimeoutError, match="did not answer SET_CURRENTS"):
            amp.set_currents(np.array([1.0, 0.0, 0.0, 0.0]))
        assert wait_until(lambda: fake.state is State.FAULT)
        server.unplugged.clear()
        status = amp.status()
        assert status.faults & Fault.WATCHDOG
        assert [e.kind for e in events][:2] == ["link_lost", "link_restored"]
        amp.clear_fault()


def test_noisy_line_is_retried_and_never_applies_a_wrong_value(fake: FakeAmplifier) -> None:
    rng = random.Random(11)
    lock = threading.Lock()

    def noise(data: bytes, direction: str) -> bytes:
        with lock:
            out = bytearray(data)
            for i in range(len(out)):
                if rng.random() < 0.002:
                    out[i] ^= 1 << rng.randrange(8)
            return bytes(out)

    with PtyServer(fake, link_filter=noise) as srv:
        amp = Amplifier(open_serial(srv.path), ack_timeout_s=0.05, retries=10, heartbeat_period_s=0)
        amp.enable()
        sent: dict[int, tuple[int, ...]] = {}
        for k in range(200):
            target = np.array([np.sin(k / 20), np.cos(k / 20), 0.5, -0.5]) * 2.0
            result = amp.set_currents(target)
            sent[result.seq] = tuple(int(round(v * 1000)) for v in result.commanded_a)
        assert amp.retransmissions > 0
        amp.shutdown()
    wrong = [a for a in fake.applied if a.seq in sent and a.target_ma != sent[a.seq]]
    assert wrong == []
    assert {a.seq for a in fake.applied} >= set(sent)


def test_tcp_transport_speaks_the_same_protocol(fake: FakeAmplifier) -> None:
    with TcpServer(fake) as srv, Amplifier(open_serial(srv.address), ack_timeout_s=0.2) as amp:
        amp.enable()
        drive_until_settled(amp, np.array([1.0, -1.0, 0.0, 0.0]))
        np.testing.assert_allclose(amp.status().measured_a, [1.0, -1.0, 0.0, 0.0], atol=2e-3)


@pytest.mark.hardware
def test_real_amplifier_identifies_and_reports_status(device_urls: dict[str, str]) -> None:
    url = device_urls.get("amplifier")
    if url is None:
        pytest.skip("no --device-url amplifier=URL given")
    amp = Amplifier(open_serial(url), ack_timeout_s=0.2)
    try:
        assert 1 <= amp.info.channels <= 16
        status = amp.status()
        assert status.measured_a.shape == (amp.info.channels,)
    finally:
        amp.close()   # never touches the output
