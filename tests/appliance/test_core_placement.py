"""The simulated lab's process on a core of its own (appliance.core_placement): where the machine has two
cores or more, the child is pinned to one, every thread of this process to the others, and restore gives
them back; with one core nothing changes."""
from __future__ import annotations

import os
import subprocess
import sys
import threading

import pytest

from appliance.core_placement import give_lab_its_own_core, thread_ids

cores = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else set()
needs_two_cores = pytest.mark.skipif(len(cores) < 2 or not os.path.isdir("/proc/self/task"),
                                     reason="needs per-thread affinity and two cores")


#: A child with a second thread (as the lab's servers are) started before it says it is ready.
CHILD = ("import sys, threading; threading.Thread(target=threading.Event().wait, daemon=True).start(); "
         "print('ready', flush=True); sys.stdin.read()")


@pytest.fixture
def child() -> subprocess.Popen[bytes]:
    process = subprocess.Popen([sys.executable, "-c", CHILD], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    assert process.stdout is not None and process.stdout.readline() == b"ready\n"
    yield process
    assert process.stdin is not None
    process.stdin.close()
    process.wait(10)


def _affinities(pid: int | None = None) -> dict[int, set[int]]:
    out = {}
    for tid in thread_ids(pid):
        try:
            out[tid] = os.sched_getaffinity(tid)
        except ProcessLookupError:
            continue
    return out


@needs_two_cores
def test_the_lab_gets_one_core_and_every_thread_here_the_others_until_restored(
        child: subprocess.Popen[bytes]) -> None:
    before = os.sched_getaffinity(0)
    started = threading.Event()
    stop = threading.Event()
    # A thread that exists before the placement and one started after it: both must leave the lab's core.
    early = threading.Thread(target=lambda: (started.set(), stop.wait()), daemon=True)
    early.start()
    started.wait()
    placement = give_lab_its_own_core(child.pid)
    try:
        assert placement is not None
        assert placement.lab_core == max(before) and placement.previous_cores == before
        in_child = _affinities(child.pid)
        assert len(in_child) == 2 and all(c == {placement.lab_core} for c in in_child.values())
        late_cores: list[set[int]] = []
        late = threading.Thread(target=lambda: late_cores.append(os.sched_getaffinity(0)))
        late.start()
        late.join()
        assert late_cores == [set(placement.host_cores)]
        during = _affinities()
        assert len(during) >= 2 and all(c == before - {placement.lab_core} for c in during.values())
    finally:
        if placement is not None:
            placement.restore()
        stop.set()
        early.join()
    assert all(c == before for c in _affinities().values())


@needs_two_cores
def test_with_one_core_nothing_is_changed(child: subprocess.Popen[bytes]) -> None:
    # Called from a thread that may use one core only: the process is left as it was, the child too.
    one = min(cores)
    result: list[object] = []

    def on_one_core() -> None:
        os.sched_setaffinity(0, {one})
        result.append(give_lab_its_own_core(child.pid))

    before = _affinities()
    worker = threading.Thread(target=on_one_core)
    worker.start()
    worker.join()
    assert result == [None]
    assert os.sched_getaffinity(child.pid) == cores
    assert {tid: c for tid, c in _affinities().items() if tid in before} == before


def test_a_lab_process_that_is_gone_is_logged_and_nothing_changes(caplog: pytest.LogCaptureFixture) -> None:
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait(10)
    before = _affinities() if cores else {}
    placement = give_lab_its_own_core(process.pid)
    assert placement is None
    if len(cores) >= 2:
        assert "not given a core of its own" in caplog.text
        assert {tid: c for tid, c in _affinities().items() if tid in before} == before
