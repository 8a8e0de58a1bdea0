"""Background threads step out of the frame loop's way (SCHED_BATCH, a higher nice value); a refusal is logged,
never raised."""
from __future__ import annotations

import logging
import os
import sys
import threading

import pytest

from drivers import scheduling

linux = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="thread scheduling calls are Linux's")


def _in_thread(work):
    """``work()``'s result, run in a new thread (what it changes dies with that thread)."""
    out: list[object] = []
    thread = threading.Thread(target=lambda: out.append(work()))
    thread.start()
    thread.join()
    return out[0]


@linux
def test_the_calling_thread_goes_to_the_background_and_the_others_stay() -> None:
    def work() -> tuple[bool, bool, int]:
        before = os.getpriority(os.PRIO_PROCESS, 0)
        done = scheduling.run_in_background("a test thread", nice=3)
        return done, scheduling.is_background(), os.getpriority(os.PRIO_PROCESS, 0) - before

    done, background, raised = _in_thread(work)
    assert done and background and raised == min(3, 19 - os.getpriority(os.PRIO_PROCESS, 0))
    assert not scheduling.is_background()          # this thread is untouched


@linux
def test_another_thread_is_moved_by_its_native_id_and_threads_it_starts_inherit() -> None:
    moved = threading.Event()
    seen: dict[str, object] = {}

    def target() -> None:
        moved.wait(5.0)
        seen["self"] = scheduling.is_background()
        seen["child"] = _in_thread(scheduling.is_background)

    thread = threading.Thread(target=target)
    thread.start()
    assert thread.native_id is not None
    assert scheduling.move_to_background(thread.native_id, "a test thread", nice=0)
    moved.set()
    thread.join()
    assert seen == {"self": True, "child": True}


@linux
def test_a_refusal_is_logged_once_and_leaves_the_thread_as_it_was(caplog: pytest.LogCaptureFixture) -> None:
    missing = 2 ** 22 + 12345      # above the kernel's largest thread id: no such thread
    with caplog.at_level(logging.DEBUG, logger="drivers.scheduling"):
        assert not scheduling.move_to_background(missing, "a thread that is not there")
        assert not scheduling.move_to_background(missing, "a thread that is not there")
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "a thread that is not there keeps its scheduling" in warnings[0].getMessage()


def test_without_the_calls_nothing_changes_and_nothing_is_raised(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delattr(os, "sched_setscheduler", raising=False)
    assert not scheduling.move_to_background(0, "a thread on a platform without SCHED_BATCH")

