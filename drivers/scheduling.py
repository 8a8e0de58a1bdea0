"""Keeping the frame loop's core: threads and processes that are not the loop step out of its way.

The loop's window - a frame pair on the host to the current command written, about a millisecond - is
lost when the loop's thread waits for a core. On a small host (two cores here) any thread that wakes
inside the window can take the loop's core: a task that slept is favoured when it wakes and may preempt
the running one. Threads that nobody in the loop waits for (the tracker's reader, the recorder's writer,
in simulation the tracker fake's server and the world's real-time stepping) therefore run as background
work:

* ``SCHED_BATCH``: the scheduler treats the thread as CPU-bound work; it never preempts a running
  thread when it wakes, it waits for that thread to sleep or for its time slice to end. It keeps its
  share of the CPU (late by a time slice, never starved). That is why a thread the loop waits for is not
  background work: the amplifier's heartbeat holds the link until its reply is in, the simulated lab's
  amplifier fake acknowledges the loop's commands (see :mod:`drivers.loopback.child_process`);
* optionally a higher nice value (``nice`` steps above the present one; none by default): a smaller share
  when the cores are short. The callers here keep their nice value: a thread of the appliance's process
  shares the interpreter's lock with the loop and, at a small share, could be kept off the cores while it
  holds it.

Nothing here needs a privilege: an unprivileged process may lower the scheduling of its own threads
(never raise it back), and nothing raises any thread above the others. Where the platform has no such
calls (not Linux) or refuses them (a container's seccomp policy), the thread simply runs as before and
the refusal is logged once per thread's role and reason: it is never an error, the loop is only less protected.

On Linux nice values and policies belong to threads: :func:`run_in_background` changes the calling
thread (and the threads it starts afterwards, which inherit it), :func:`move_to_background` any thread of
this process by its native id (``threading.get_native_id``).
"""
from __future__ import annotations

import logging
import os
import threading

log = logging.getLogger(__name__)

_reported: set[tuple[str, str]] = set()
_reported_lock = threading.Lock()


def _report_once(reason: str, what: str) -> None:
    with _reported_lock:
        first = (what, reason) not in _reported
        _reported.add((what, reason))
    (log.warning if first else log.debug)("%s keeps its scheduling (%s): the frame loop is less protected "
                                          "from it", what, reason)


def move_to_background(native_id: int, what: str, nice: int = 0) -> bool:
    """Run thread ``native_id`` of this process (0: the calling thread) as background work (see the module
    docstring): ``SCHED_BATCH`` and ``nice`` steps above its present nice value (the cap is 19). True when
    both took effect; a refusal is logged (once per ``what`` and reason) and leaves the thread as it was."""
    set_scheduler = getattr(os, "sched_setscheduler", None)
    batch = getattr(os, "SCHED_BATCH", None)
    if set_scheduler is None or batch is None:
        _report_once("no SCHED_BATCH on this platform", what)
        return False
    try:
        present = os.getpriority(os.PRIO_PROCESS, native_id)
        os.setpriority(os.PRIO_PROCESS, native_id, min(19, present + max(0, nice)))
        set_scheduler(native_id, batch, os.sched_param(0))
    except OSError as err:
        _report_once(f"{type(err).__name__}: {err.strerror or err}", what)
        return False
    return True


def run_in_background(what: str, nice: int = 0) -> bool:
    """:func:`move_to_background` for the calling thread (threads it starts from now on inherit it)."""
    return move_to_background(0, what, nice)


def is_background(native_id: int = 0) -> bool:
    """Whether thread ``native_id`` (0: the calling one) runs with ``SCHED_BATCH`` (Linux; False elsewhere)."""
    get_scheduler = getattr(os, "sched_getscheduler", None)
    batch = getattr(os, "SCHED_BATCH", None)
    if get_scheduler is None or batch is None:
        return False
    return bool(get_scheduler(native_id) == batch)

