"""Ctrl-C as an operator stop: the first press asks the loop to stop, the second aborts."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from appliance.operator_stop import REASON, ctrl_c_requests_stop

from test_simulation_command import small_sim_file


def test_first_ctrl_c_requests_the_stop_and_the_second_aborts(capsys: pytest.CaptureFixture[str]) -> None:
    before = signal.getsignal(signal.SIGINT)
    requests: list[str] = []
    with pytest.raises(KeyboardInterrupt):
        with ctrl_c_requests_stop(requests.append, "appliance test"):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.01)                      # the handler runs at the next bytecode boundary
            assert requests == [REASON]           # asked, not raised
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1.0)                       # interrupted well before this ends
            pytest.fail("the second Ctrl-C did not abort")
    assert requests == [REASON]
    assert "appliance test: stopping: the coils ramp to zero" in capsys.readouterr().err
    assert signal.getsignal(signal.SIGINT) is before


def test_the_previous_handler_is_back_after_a_normal_exit() -> None:
    before = signal.getsignal(signal.SIGINT)
    with ctrl_c_requests_stop(lambda reason: None):
        assert signal.getsignal(signal.SIGINT) is not before
    assert signal.getsignal(signal.SIGINT) is before


def test_off_the_main_thread_nothing_is_installed() -> None:
    seen: list[object] = []

    def body() -> None:
        with ctrl_c_requests_stop(lambda reason: None):
            seen.append(signal.getsignal(signal.SIGINT))

    before = signal.getsignal(signal.SIGINT)
    worker = threading.Thread(target=body)
    worker.start()
    worker.join(10)
    assert seen == [before]


def test_ctrl_c_during_a_simulated_run_ends_it_as_an_operator_stop(tmp_path: Path) -> None:
    """A terminal's Ctrl-C (SIGINT to the whole process group, the simulated lab's child included) stops
    ``appliance sim`` through the loop's own stop: summary printed, coils ramped down, exit status 0."""
    command = [sys.executable, "-m", "appliance", "-v", "sim", "--config", str(small_sim_file(tmp_path)),
               "--seconds", "120", "--no-recording", "--out", str(tmp_path / "run")]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    sim = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                           start_new_session=True)
    try:
        assert sim.stderr is not None
        deadline = time.monotonic() + 600          # a cold kernel cache compiles first
        while time.monotonic() < deadline:
            line = sim.stderr.readline()
            assert line, "appliance sim ended before its loop started"
            if "loop started" in line:
                break
        time.sleep(0.5)
        os.killpg(sim.pid, signal.SIGINT)
        out, err = sim.communicate(timeout=60)
    finally:
        if sim.poll() is None:
            os.killpg(sim.pid, signal.SIGKILL)
    assert sim.returncode == 0, err[-2000:]
    assert f"stop          {REASON}" in out
    assert "ramped to zero and disabled" in out
    assert "Traceback" not in err
