"""The control kernels' vector arguments, passed through without a copy when they already fit.

A kernel (:mod:`appliance.compiled`) is compiled for the array types it was warmed up with: float64,
C-contiguous, writable. Anything else (a list, a read-only or strided view into a posture, float32)
would compile a new variant at the first frame that brings it, so such values are copied into a
fresh array. Copying everything costs the loop an array construction per vector per frame: ~1 us
each when the caches are warm, 10-20 us after a frame's recognition has cycled them (issue 8), so an
array that already fits goes through as it is. The kernels never write into these inputs.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

_FLOAT64 = np.dtype(np.float64)


def float_vector(value: ArrayLike, size: int, name: str) -> NDArray[np.float64]:
    """``value`` as a C-contiguous, writable float64 array of shape (``size``,): itself when it is one,
    else a copy. Raises ValueError (naming ``name``) when it does not hold ``size`` values."""
    if type(value) is np.ndarray and value.dtype is _FLOAT64 and value.shape == (size,):
        flags = value.flags
        if flags.c_contiguous and flags.writeable:
            return value
    vector = np.array(value, dtype=np.float64).reshape(-1)
    if vector.size != size:
        raise ValueError(f"{name} needs {size} values, got {vector.size}")
    return vector
