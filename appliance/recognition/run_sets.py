"""Union-find over the row runs of a binary image: the connected-components labelling both the ROI
segmentation (:mod:`.view_kernels`) and the coarse detection (:mod:`.background_kernels`) build on.

A component is a set of row runs; runs of neighbouring rows that touch are joined with
:func:`union`, and :func:`number_sets` numbers the sets 1.. in raster order of their first run (the
root of each set is its first run, as OpenCV numbers components by their first pixel).
"""
from __future__ import annotations

import numpy as np

from appliance.compiled import kernel, register_warm_up


@kernel
def find_root(parent: np.ndarray, i: int) -> int:  # pragma: no cover - compiled
    """The root of ``i`` in the forest ``parent``, halving the path on the way."""
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@kernel
def union(parent: np.ndarray, a: int, b: int) -> None:  # pragma: no cover - compiled
    """Join the sets of ``a`` and ``b``; the smaller root (the earlier run) stays the root."""
    ra, rb = find_root(parent, a), find_root(parent, b)
    if ra < rb:
        parent[rb] = ra
    elif rb < ra:
        parent[ra] = rb


@kernel
def number_sets(parent: np.ndarray, n_runs: int) -> tuple[np.ndarray, int]:  # pragma: no cover - compiled
    """Label (1..) of every run's set, numbered in order of the sets' roots, and the number of labels + 1."""
    label_of = np.zeros(n_runs, dtype=np.int64)
    n = 1
    for r in range(n_runs):
        root = find_root(parent, r)
        if root == r:
            label_of[r] = n
            n += 1
        else:
            label_of[r] = label_of[root]
    return label_of, n


def warm_up() -> None:
    """Compile the kernels on a tiny forest."""
    parent = np.arange(3, dtype=np.int64)
    union(parent, 2, 0)
    number_sets(parent, 3)


register_warm_up(__name__)
