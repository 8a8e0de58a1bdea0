"""Ctrl-C as an operator stop for the commands that drive coil current (``appliance run``, ``appliance sim``).

Python's default turns SIGINT into a ``KeyboardInterrupt`` raised wherever the interpreter happens to be:
half-way through encoding a SET_CURRENTS frame, between writing it and reading its acknowledgement, or on
the way out of a compiled kernel (where numba reports it as a ``SystemError``). The loop would then stop at
an arbitrary point, and what it writes on the way down depends on that point.

:func:`ctrl_c_requests_stop` instead turns the first Ctrl-C into the loop's own operator stop
(``request_stop``): the step in progress finishes, the next one latches STOP, the coils ramp to zero and the
run ends with its summary and recording as after any other stop. A second Ctrl-C, for an operator who finds
the ramp too slow or the loop stuck, raises ``KeyboardInterrupt`` as before: the orchestrator's shutdown still
runs on the way out, and where it cannot finish, the amplifier's watchdog switches the coils off when the
commands stop.
"""
from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

REASON = "operator stop (Ctrl-C)"


@contextmanager
def ctrl_c_requests_stop(request_stop: Callable[[str], None], command: str = "appliance") -> Iterator[None]:
    """Inside the block, the first SIGINT calls ``request_stop(REASON)`` and prints what happens next on
    stderr; the second raises ``KeyboardInterrupt``. The previous handler is restored on exit. Off the main
    thread (where Python cannot install signal handlers) the block runs with the default behaviour."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    presses = 0

    def on_sigint(signum: int, frame: Any) -> None:
        nonlocal presses
        presses += 1
        if presses > 1:
            raise KeyboardInterrupt
        request_stop(REASON)
        print(f"\n{command}: stopping: the coils ramp to zero (Ctrl-C again aborts at once; the amplifier's "
              "watchdog then switches them off)",
              file=sys.stderr, flush=True)

    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
