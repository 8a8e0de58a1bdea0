"""``appliance amp``: bench checks against the loopback amplifier on a pty, and the errors a bench
engineer meets: a missing port, a busy port, a device that does not answer, a wrong current vector."""
from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from appliance.cli import main
from drivers.loopback.amplifier_fake import FakeAmplifier, make_default_fake
from drivers.loopback.serve import PtyServer
from drivers.transport import open_serial
from firmware_protocol.amplifier import State


class Silent:
    """A device that never answers (wrong baud rate, wrong port, powered off)."""

    def feed(self, data: bytes, now: float) -> bytes:
        return b""

    def tick(self, now: float) -> bytes:
        return b""


@pytest.fixture
def served() -> Iterator[tuple[PtyServer, FakeAmplifier]]:
    fake = make_default_fake()
    with PtyServer(fake) as server:
        yield server, fake


def test_status_prints_state_and_every_channel(served, capsys: pytest.CaptureFixture[str]) -> None:
    server, _ = served
    assert main(["amp", "status", "--port", server.path]) == 0
    out = capsys.readouterr().out
    assert "8 channels, firmware 1.0.0" in out and "state DISABLED   faults NONE" in out
    assert sum(1 for line in out.splitlines() if line.strip()[:1].isdigit()) == 8


def test_set_drives_the_currents_then_ramps_to_zero(served, capsys: pytest.CaptureFixture[str]) -> None:
    server, fake = served
    currents = "1,-1,0.5,0,0,0,0,30"   # 30 A exceeds the 10 A limit: the whole vector is scaled by 1/3
    assert main(["amp", "set", "--port", server.path, "--currents", currents, "--hold", "0.1"]) == 0
    out = capsys.readouterr().out
    assert "scaled by 0.3333" in out and "state ENABLED" in out and "ramped to zero and disabled" in out
    assert fake.applied and max(fake.applied[-2].target_ma) == 10000
    assert fake.state is State.DISABLED and np.all(np.abs(fake.measured_currents_a()) < 0.05)


def test_clear_reports_an_estop_that_is_still_pressed(served, capsys: pytest.CaptureFixture[str]) -> None:
    server, fake = served
    fake.press_estop()
    assert main(["amp", "clear", "--port", server.path]) == 2
    assert "emergency stop is pressed" in capsys.readouterr().err


def test_missing_port(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["amp", "status", "--port", "/dev/ttyNOPE9"]) == 2
    assert "appliance amp: error: port '/dev/ttyNOPE9' does not exist" in capsys.readouterr().err


def test_busy_port(served, capsys: pytest.CaptureFixture[str]) -> None:
    server, _ = served
    holder = open_serial(server.path)   # exclusive, like another program holding it
    try:
        assert main(["amp", "status", "--port", server.path]) == 2
    finally:
        holder.close()
    assert "is busy" in capsys.readouterr().err


def test_device_that_does_not_answer(capsys: pytest.CaptureFixture[str]) -> None:
    with PtyServer(Silent()) as server:
        assert main(["amp", "status", "--port", server.path, "--timeout", "0.02"]) == 2
    err = capsys.readouterr().err
    assert "did not answer HELLO" in err and server.path in err


def test_wrong_number_of_currents_is_refused_before_enabling(served, capsys: pytest.CaptureFixture[str]) -> None:
    server, fake = served
    assert main(["amp", "set", "--port", server.path, "--currents", "1,2"]) == 2
    assert "has 2 values; the amplifier has 8 channels" in capsys.readouterr().err
    assert fake.state is State.DISABLED and not fake.applied


def test_set_without_currents(served, capsys: pytest.CaptureFixture[str]) -> None:
    server, _ = served
    assert main(["amp", "set", "--port", server.path]) == 2
    assert "needs --currents" in capsys.readouterr().err


def test_loopback_command_serves_the_default_fake_for_bench_software(capsys: pytest.CaptureFixture[str]) -> None:
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    proc = subprocess.Popen([sys.executable, "-m", "appliance", "loopback", "amp"], cwd=root,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        path = proc.stdout.readline().strip()   # first line: the pty path
        assert path.startswith("/dev/")
        assert main(["amp", "status", "--port", path]) == 0
        assert "8 channels" in capsys.readouterr().out
    finally:
        proc.terminate()
        proc.wait(timeout=5)
