"""Figures of a closed-loop run: the path the robot followed against the operator's path (PNG, Agg backend).

Three panels: top view (x-y) and side view (x-z) of the target path, the TRUE robot centroid (from the
simulated world, or on a bench the optical tracker's) and the centroid the appliance tracked; below,
the cross-track error over time with the moments the safety supervisor changed mode or a fault stopped
the loop. Matplotlib runs on the non-interactive Agg backend, so this works without a display.
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

log = logging.getLogger(__name__)


def plot_path(out: str | Path, path_mm: ArrayLike, true_mm: ArrayLike, times_s: ArrayLike, cross_track_mm: ArrayLike,
              *, tracked_mm: ArrayLike | None = None, events: Sequence[tuple[float, str]] = (),
              title: str = "path following") -> Path:
    """Write the figure to ``out`` (PNG) and return its path.

    ``path_mm`` (M,3) target; ``true_mm`` (N,3) the robot's true centroids at ``times_s`` (N,) with their
    ``cross_track_mm`` (N,); ``tracked_mm`` (K,3) what recognition reported; ``events`` (t, label) marks.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = np.asarray(path_mm, float).reshape(-1, 3)
    truth = np.asarray(true_mm, float).reshape(-1, 3)
    times = np.asarray(times_s, float).ravel()
    cross = np.asarray(cross_track_mm, float).ravel()
    tracked = np.asarray(tracked_mm, float).reshape(-1, 3) if tracked_mm is not None else np.zeros((0, 3))
    if len(truth) != len(times) or len(cross) != len(times):
        raise ValueError(f"true_mm ({len(truth)}), times_s ({len(times)}) and cross_track_mm ({len(cross)}) "
                         "must have one entry per frame")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)

    figure = plt.figure(figsize=(11, 8), dpi=110)
    grid = figure.add_gridspec(2, 2, height_ratios=[3, 2])
    for column, (a, b, label) in enumerate(((0, 1, "y"), (0, 2, "z"))):
        axes = figure.add_subplot(grid[0, column])
        axes.plot(path[:, a], path[:, b], color="0.6", linewidth=6, alpha=0.5, label="target path")
        if len(tracked):
            axes.plot(tracked[:, a], tracked[:, b], ".", color="tab:orange", markersize=1.5, label="tracked (X-ray)")
        if len(truth):
            axes.plot(truth[:, a], truth[:, b], color="tab:blue", linewidth=1.0, label="true centroid")
            axes.plot(*truth[0, [a, b]], "o", color="tab:green", label="start")
            axes.plot(*truth[-1, [a, b]], "s", color="tab:red", label="end")
        axes.set_xlabel("x (mm)")
        axes.set_ylabel(f"{label} (mm)")
        axes.set_title("top view" if label == "y" else "side view")
        axes.set_aspect("equal", adjustable="datalim")
        axes.grid(True, alpha=0.3)
        if column == 0:
            axes.legend(loc="best", fontsize=8)

    axes = figure.add_subplot(grid[1, :])
    if len(times):
        axes.plot(times - times[0], cross, color="tab:blue", linewidth=1.0)
        rms = float(np.sqrt(np.mean(cross ** 2)))
        axes.axhline(rms, color="tab:blue", linestyle="--", linewidth=0.8, label=f"RMS {rms:.3f} mm")
        for t, label in events:
            axes.axvline(t - times[0], color="tab:red", linewidth=0.8)
            axes.annotate(label, (t - times[0], axes.get_ylim()[1]), fontsize=7, rotation=90, va="top", ha="right")
        axes.legend(loc="upper right", fontsize=8)
    axes.set_xlabel("time (s, simulated)" if len(times) else "time (s)")
    axes.set_ylabel("cross-track error (mm)")
    axes.grid(True, alpha=0.3)
    figure.suptitle(title)
    figure.tight_layout()
    figure.savefig(out)
    plt.close(figure)
    log.info("path plot written to %s", out)
    return out
