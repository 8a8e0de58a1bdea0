"""Builders of simulated scenes shared by tests and benchmarks: smooth vessel centrelines, random vessels,
and true X-ray views perturbed away from their nominal pose (a fluoroscope as built, not as designed)."""
from __future__ import annotations

import cv2
import numpy as np

from drivers.loopback.xray_render import TrueView, VesselPhantom

#: Control points (mm) of the default vessel of config/vessel.yaml: an S-bend through the field, so that
#: robots at random poses lie over it in some frames. Tests and the accuracy benchmark build their
#: phantom on it (``smooth_centreline``).
S_BEND_CENTRELINE_MM = [[-60.0, -20.0, -6.0], [-40.0, -23.0, -2.0], [-20.0, -12.0, 4.0], [0.0, 0.0, 6.0],
                        [20.0, 12.0, 2.0], [40.0, 20.0, -4.0], [60.0, 16.0, -6.0]]


def smooth_centreline(points: np.ndarray | list[list[float]], step_mm: float = 1.0) -> np.ndarray:
    """Densely resampled polyline through the control points (Catmull-Rom), so the tube bends smoothly."""
    p = np.asarray(points, dtype=float)
    ext = np.vstack([2 * p[0] - p[1], p, 2 * p[-1] - p[-2]])
    out = []
    for i in range(1, len(ext) - 2):
        p0, p1, p2, p3 = ext[i - 1], ext[i], ext[i + 1], ext[i + 2]
        n = max(2, int(np.linalg.norm(p2 - p1) / step_mm))
        for s in np.linspace(0.0, 1.0, n, endpoint=False):
            out.append(0.5 * ((2 * p1) + (-p0 + p2) * s + (2 * p0 - 5 * p1 + 4 * p2 - p3) * s * s
                              + (-p0 + 3 * p1 - 3 * p2 + p3) * s ** 3))
    out.append(p[-1])
    return np.asarray(out)


def random_vessel(rng: np.random.Generator) -> VesselPhantom:
    """A smooth random contrast-filled vessel through the field: 25 mm steps turning up to 35 degrees each
    (no bend tight enough for the mitred tube to overlap itself), in any 3D direction, so that parts of it
    run nearly along one view's rays and parts cross each other in projection."""
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    x = rng.uniform(-20.0, 20.0, 3) - 60.0 * d
    points = [x]
    for _ in range(6):
        side = rng.normal(size=3)
        side -= side.dot(d) * d
        side /= np.linalg.norm(side)
        angle = np.radians(rng.uniform(0.0, 35.0))
        d = np.cos(angle) * d + np.sin(angle) * side
        x = x + 25.0 * d
        points.append(x)
    return VesselPhantom(smooth_centreline(np.asarray(points)), rng.uniform(1.0, 3.0), rng.uniform(0.04, 0.08))


def perturb_view(view: TrueView, rng: np.random.Generator, deg: float = 1.5, mm: float = 3.0) -> TrueView:
    """The same view turned by ``deg`` about a random axis and with its source moved by about ``mm``."""
    axis = rng.normal(size=3)
    turn, _ = cv2.Rodrigues(axis / np.linalg.norm(axis) * np.radians(deg))
    source = view.source_mm + rng.normal(size=3) * mm / np.sqrt(3)
    R = turn @ view.R
    return TrueView(view.name, view.K, view.dist, R, -R @ source, view.image_size)
