"""How the appliance compiles its per-pixel and per-frame kernels (numba), in one place.

A frame pair has a budget of tens of microseconds in steady state (issue 8), less than numpy's
overhead for a few dozen small calls, so the inner work of recognition runs as compiled kernels.
Every kernel is decorated with :func:`kernel`:

* ``cache=True``: the machine code is kept beside the module (``__pycache__``), so only the first
  process after an install or a change pays the compilation;
* ``nogil=True``: a kernel releases the GIL, so the recorder's writer, the device readers and the
  heartbeats are not held up while a frame is recognised;
* no ``fastmath``: IEEE semantics (NaN and infinity checks, summation order) as in the numpy code
  each kernel replaced.

Compilation happens at the first call. A module with kernels offers ``warm_up()`` which calls each
of them once on tiny inputs; :func:`warm_up_all` runs them all, and the loop and the benchmark call it
before the first frame so that no frame pays for compilation.
"""
from __future__ import annotations

import importlib
import logging
import time
from collections.abc import Callable
from typing import Any, TypeVar

import numba

log = logging.getLogger(__name__)

F = TypeVar("F", bound=Callable[..., Any])

#: Modules whose ``warm_up()`` :func:`warm_up_all` calls (each compiles its kernels on tiny inputs).
_WARM_UP_MODULES: list[str] = []


def kernel(function: F) -> F:
    """Compile ``function`` in nopython mode, cached on disk, releasing the GIL (see the module docstring)."""
    return numba.njit(cache=True, nogil=True)(function)  # type: ignore[no-any-return]


def register_warm_up(module_name: str) -> None:
    """Have :func:`warm_up_all` call ``module_name.warm_up()``."""
    if module_name not in _WARM_UP_MODULES:
        _WARM_UP_MODULES.append(module_name)


def warm_up_all() -> float:
    """Compile (or load from the cache) every registered kernel; returns the seconds it took."""
    start = time.perf_counter()
    for name in list(_WARM_UP_MODULES):
        importlib.import_module(name).warm_up()
    elapsed = time.perf_counter() - start
    log.debug("compiled kernels ready in %.2f s", elapsed)
    return elapsed
