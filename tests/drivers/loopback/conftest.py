"""What the tests of the loopback devices run in a child process (renderer, simulated lab) share."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable
from pathlib import Path

import pytest


@pytest.fixture
def child_outlives_no_parent(tmp_path: Path) -> Callable[[str, str, str], None]:
    """``check(start, how, what)``: a parent process runs ``start`` (Python that binds ``device``, a
    device with a child process, and makes its first request), prints the child's pid and frames file, and
    waits; the test ends that parent as ``how`` says ("sigint": Ctrl-C to its process group; "sigkill") and
    asserts that the child (``what``, for the messages) and its frames file do not outlive it."""

    def check(start: str, how: str, what: str) -> None:
        script = tmp_path / "parent.py"
        # The parent takes Ctrl-C as a program started from a terminal does, whatever this test run inherited:
        # a runner started as a background job (no job control) hands its children SIGINT ignored.
        prelude = (f"import signal, sys, time\nsignal.signal(signal.SIGINT, signal.default_int_handler)\n"
                   f"sys.path[:0] = {sys.path!r}\n")
        script.write_text(prelude + textwrap.dedent(start) + textwrap.dedent("""
            try:
                print(device.process.pid, device.shm_path, flush=True)
                time.sleep(60)
            finally:
                device.close()
        """))
        parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True,
                                  start_new_session=True)
        try:
            pid, shm_path = parent.stdout.readline().split()
            child = int(pid)
            assert _alive(child)
            if how == "sigint":
                os.killpg(parent.pid, signal.SIGINT)     # what a terminal's Ctrl-C does
            else:
                parent.kill()
            parent.wait(20)
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline and _alive(child):
                time.sleep(0.05)
            assert not _alive(child), f"the {what} child outlived its parent"
            assert not os.path.exists(shm_path), "the frames file outlived the session"
        finally:
            if parent.poll() is None:
                parent.kill()

    return check


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False
