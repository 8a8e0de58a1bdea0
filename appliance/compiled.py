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

Where the machine code is kept: numba checks a cached kernel against its own source file only, not
against the kernels it calls in other modules, so an edit of ``geometry_kernels.py`` would leave a
kernel of ``reconstruction_kernels.py`` running the old code it had inlined. The cache therefore lives
in a directory named by a hash of the source of every module that defines kernels (under
``$NUMBA_CACHE_DIR`` if set, else the user's cache directory): any change to any kernel compiles them
all afresh, and an unchanged install reuses them.

Compilation happens at the first call. A module with kernels offers ``warm_up()`` which calls each
of them once on tiny inputs; :func:`warm_up_all` runs them all, and the loop and the benchmark call it
before the first frame so that no frame pays for compilation.
"""
from __future__ import annotations

import hashlib
import importlib
import logging
import os
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import numba
import numba.core.config

log = logging.getLogger(__name__)

F = TypeVar("F", bound=Callable[..., Any])

#: Modules whose ``warm_up()`` :func:`warm_up_all` calls (each compiles its kernels on tiny inputs).
_WARM_UP_MODULES: list[str] = []


#: Text by which a module is recognised as defining kernels (for the cache's source hash): the decorator at
#: the start of a line. Not the import of this module, which modules without kernels have too (the
#: orchestrator's GC hold-off, the sim command's cache check): editing those must not recompile every kernel.
_KERNEL_MARK = b"\n@kernel"
#: Cache directories of older sources kept beside the current one (for a quick switch back).
_KEEP_OLD_CACHES = 2


def _sources_digest(package_root: Path) -> str:
    """Hash of numba's version and of every module under ``package_root`` that defines kernels."""
    digest = hashlib.sha256(numba.__version__.encode())
    for path in sorted(package_root.rglob("*.py")):
        text = path.read_bytes()
        if _KERNEL_MARK in text or path.name == "compiled.py":
            digest.update(str(path.relative_to(package_root)).encode())
            digest.update(text)
    return digest.hexdigest()[:16]


def _writable(directory: Path) -> bool:
    try:
        directory.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=directory):
            pass
    except OSError:
        return False
    return True


def _prune(base: Path, current: Path) -> None:
    """Remove cache directories of older sources beyond the newest :data:`_KEEP_OLD_CACHES`."""
    try:
        old = sorted((d for d in base.iterdir() if d.is_dir() and d != current),
                     key=lambda d: d.stat().st_mtime, reverse=True)
    except OSError:
        return
    for directory in old[_KEEP_OLD_CACHES:]:
        shutil.rmtree(directory, ignore_errors=True)


def _select_cache_dir() -> Path:
    """Point numba's cache at a directory keyed by the kernels' sources (see the module docstring)."""
    digest = _sources_digest(Path(__file__).resolve().parent)
    user = os.environ.get("NUMBA_CACHE_DIR")
    cache_home = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    bases = ([Path(user)] if user else []) + [cache_home / "microrobot-appliance" / "kernels",
                                               Path(tempfile.gettempdir()) / f"microrobot-appliance-kernels-{os.getuid()}"]
    for base in bases:
        directory = base / digest
        if _writable(directory):
            os.utime(directory)
            _prune(base, directory)
            numba.core.config.CACHE_DIR = str(directory)
            return directory
    raise OSError(f"no writable directory for the compiled kernels' cache (tried {', '.join(map(str, bases))})")


#: Where the compiled kernels are cached (set before any kernel is defined).
CACHE_DIR = _select_cache_dir()


def cache_is_warm() -> bool:
    """True if kernels compiled from the current sources are on disk (the next warm-up takes seconds,
    not the minute or two of a first compilation): commands use it to say why a start is slow."""
    try:
        return any(CACHE_DIR.rglob("*.nbi"))
    except OSError:
        return False


#: How often a start-up runs the per-frame Python path before the first frame that counts: more than the 8 calls
#: after which CPython 3.11's adaptive interpreter specialises ("quickens") a function's bytecode, so that the
#: session's first frames do not run it unspecialised (issue 8: pairs 2-5 were slower than the rest).
BYTECODE_WARM_CALLS = 12


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
    for name in _WARM_UP_MODULES:
        importlib.import_module(name).warm_up()
    elapsed = time.perf_counter() - start
    log.debug("compiled kernels ready in %.2f s", elapsed)
    return elapsed
