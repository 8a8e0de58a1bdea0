"""The simulated lab's process on a CPU core of its own, the appliance's threads on the others (Linux).

On a bench the amplifier, the optical tracker and the fluoroscope are other machines: their work never
takes the host's cores. In simulation they are one child process (:mod:`drivers.loopback.lab_process`:
the world, the fakes' servers and the X-ray renderer). Left to the scheduler on a two-core machine, the
child is woken on the loop's core by the loop's own writes (the amplifier command on its pty) and by
the frames it renders, and the loop waits for it. ``benchmarks/sim_latency.py --stages`` on 2 cores
(load ~1), 6 alternated pairs of 20 s runs, "frame on host -> command written": p99 1.17-1.82 ms (median
1.43) with the scheduler's placement (``--scheduler-placement``), 0.91-1.20 ms (median 1.00) with the lab
on core 1 and this process on core 0, lower in every pair; p50 0.62 -> 0.55 ms, the worst step 1.9-4.6 ->
1.2-1.6 ms. Only the lab's first thread pinned (its server threads left free) gained half as much, and
the lab on a core of its own with this process free to use it too less again.

:func:`give_lab_its_own_core` pins every thread of the child to the highest core this process may use and
every thread of this process to the others (threads started later inherit their starter's cores);
:meth:`CorePlacement.restore` gives every thread of this process the cores it had. With fewer than two
cores, or where the system has no per-thread affinity, nothing is changed (None). Placement is a matter
of latency, never of correctness: a refusal by the system is logged and the session goes on.
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass

log = logging.getLogger(__name__)

_TASKS = "/proc/self/task"


@dataclass(frozen=True)
class CorePlacement:
    """Where :func:`give_lab_its_own_core` put the lab's process and this one; :meth:`restore` undoes the
    latter (the lab's process ends with the session)."""

    lab_pid: int
    lab_core: int
    host_cores: frozenset[int]
    previous_cores: frozenset[int]

    def restore(self) -> None:
        """Every thread of this process back on ``previous_cores`` (idempotent)."""
        _set_every_thread(self.previous_cores)


def give_lab_its_own_core(lab_pid: int) -> CorePlacement | None:
    """Pin process ``lab_pid`` to one core and this process's threads to the other cores it may use.

    None (nothing changed) with fewer than two usable cores, without per-thread affinity (not Linux), or if
    the system refuses (logged)."""
    if not hasattr(os, "sched_setaffinity") or not os.path.isdir(_TASKS):
        return None
    previous = frozenset(os.sched_getaffinity(0))
    if len(previous) < 2:
        return None
    lab_core = max(previous)
    host = previous - {lab_core}
    try:
        # Every thread the child has started (its servers'): those it starts later inherit the core.
        _set_every_thread(frozenset({lab_core}), lab_pid, missing_ok=False)
    except OSError as err:   # the child gone, or affinity not permitted here
        log.warning("simulated lab (process %d) not given a core of its own: %s", lab_pid, err)
        return None
    _set_every_thread(host)
    return CorePlacement(lab_pid, lab_core, frozenset(host), previous)


def thread_ids(pid: int | None = None) -> list[int]:
    """The kernel's ids of the threads of process ``pid`` (None: this one) now."""
    return [int(name) for name in os.listdir(_TASKS if pid is None else f"/proc/{pid}/task")]


def _set_every_thread(cores: frozenset[int], pid: int | None = None, *, missing_ok: bool = True) -> None:
    """Every thread of process ``pid`` (None: this one) on ``cores``; a thread that ended meanwhile is passed
    over, and so is a process that has gone unless not ``missing_ok`` (ProcessLookupError)."""
    try:
        tids = thread_ids(pid)
    except FileNotFoundError as err:
        if missing_ok:
            return
        raise ProcessLookupError(f"no process {pid}") from err
    for tid in tids:
        try:
            os.sched_setaffinity(tid, cores)
        except ProcessLookupError:   # the thread ended meanwhile
            continue
