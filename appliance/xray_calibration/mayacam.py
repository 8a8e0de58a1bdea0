"""MayaCam 2.0 camera files: the plain-text calibration exchanged by XMALab, Autoscoper and SlicerAutoscoperM.

One file per view. The layout we read and write (XMALab's export; blank lines separate sections)::

    image size
    <width>,<height>

    camera matrix
    fx,0,cx
    0,fy,cy
    0,0,1

    rotation
    r11,r12,r13
    r21,r22,r23
    r31,r32,r33

    translation
    tx
    ty
    tz

    undistortion                      (optional; XMALab writes it only for distorted views)
    k1,k2,p1,p2,k3,k4,k5,k6

The conventions are OpenCV's, exactly those of our calibration file: ``x_cam = R X + t`` (world to
camera), pixels ``K x_cam`` with ``v`` growing downwards and pixel centres at integer coordinates
(Autoscoper flips ``v`` itself with ``cy' = (h - 1) - cy`` when it loads one), units the world's
(mm). The image size is width then height, as XMALab reads and writes it (Autoscoper's documentation
calls the pair "height,width", but its loader takes the second number as the height it flips with).
Our contract has five distortion terms; a file with non-zero ``k4 k5 k6`` (OpenCV's rational model)
is refused rather than silently truncated.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from appliance.errors import CalibrationError
from appliance.geometry import Calibration, View

log = logging.getLogger(__name__)

_SECTIONS = ("image size", "camera matrix", "rotation", "translation")
_SHAPES = {"image size": (1, 2), "camera matrix": (3, 3), "rotation": (3, 3), "translation": (3, 1),
           "undistortion": (1, None)}


def format_mayacam(view: View) -> str:
    """The MayaCam 2.0 text of one view (17 significant digits, so a read gives back the same numbers)."""
    def row(values: np.ndarray) -> str:
        return ",".join(repr(float(v)) for v in values)

    w, h = view.image_size
    lines = ["image size", f"{w},{h}", "", "camera matrix"]
    lines += [row(r) for r in view.K]
    lines += ["", "rotation"] + [row(r) for r in view.R]
    lines += ["", "translation"] + [repr(float(v)) for v in view.t]
    if view.has_distortion:
        dist = np.zeros(8)
        dist[: view.dist.size] = view.dist[:8]
        lines += ["", "undistortion", row(dist)]
    return "\n".join(lines) + "\n"


def parse_mayacam(text: str, name: str, source: str = "MayaCam file") -> View:
    """Parse MayaCam 2.0 text into a :class:`View` named ``name``; errors name ``source`` and the line."""
    sections: dict[str, list[list[float]]] = {}
    current: str | None = None
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line:
            if current is not None and sections[current]:
                current = None  # a blank line ends a section that has its numbers
            continue
        key = line.lower()
        if key in _SHAPES:
            if key in sections:
                raise CalibrationError(f"{source}: line {number}: section {key!r} appears twice")
            current = key
            sections[key] = []
            continue
        if current is None:
            raise CalibrationError(f"{source}: line {number}: {line!r} is outside any section "
                                   f"(expected one of {', '.join(_SECTIONS)})")
        try:
            sections[current].append([float(v) for v in line.replace(";", ",").split(",") if v.strip()])
        except ValueError as err:
            raise CalibrationError(f"{source}: line {number}: section {current!r}: not numbers: {line!r}") from err
    missing = [s for s in _SECTIONS if s not in sections]
    if missing:
        raise CalibrationError(f"{source}: not a MayaCam 2.0 file: missing section(s) {', '.join(missing)}")
    arrays: dict[str, np.ndarray] = {}
    for key, rows in sections.items():
        want_rows, want_cols = _SHAPES[key]
        widths = {len(r) for r in rows}
        if len(rows) != want_rows or len(widths) != 1 or (want_cols is not None and widths != {want_cols}):
            shape = f"{want_rows} line(s) of {want_cols if want_cols else 'N'} number(s)"
            raise CalibrationError(f"{source}: section {key!r}: expected {shape}, got {[len(r) for r in rows]}")
        arrays[key] = np.asarray(rows, dtype=np.float64)
    w, h = arrays["image size"].ravel()
    if w <= 0 or h <= 0 or w != int(w) or h != int(h):
        raise CalibrationError(f"{source}: image size must be two positive integers, got {w:g},{h:g}")
    dist = np.zeros(5)
    if "undistortion" in arrays:
        coefficients = arrays["undistortion"].ravel()
        if coefficients.size not in (4, 5, 8):
            raise CalibrationError(f"{source}: undistortion needs 4, 5 or 8 coefficients, got {coefficients.size}")
        if coefficients.size == 8 and np.any(coefficients[5:] != 0):
            raise CalibrationError(f"{source}: rational distortion terms k4 k5 k6 = {coefficients[5:].tolist()} "
                                   "are not supported by the calibration file (5 coefficients)")
        dist[: min(5, coefficients.size)] = coefficients[:5]
    K, R, t = arrays["camera matrix"], arrays["rotation"], arrays["translation"].ravel()
    if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationError(f"{source}: camera matrix is not [[fx,s,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0")
    if abs(np.linalg.det(R) - 1) > 1e-4 or np.max(np.abs(R.T @ R - np.eye(3))) > 1e-4:
        raise CalibrationError(f"{source}: rotation is not a rotation matrix (det {np.linalg.det(R):.4f})")
    if np.max(np.abs(R.T @ R - np.eye(3))) > 1e-12:
        # Files written with a few digits: project onto the nearest rotation. One exact to rounding is
        # kept bit for bit, so that a write/read round trip gives the same view.
        u, _, vt = np.linalg.svd(R)
        R = u @ vt
    return View(name, K, dist, R, t, (int(w), int(h)))


def write_mayacam(path: str | Path, view: View) -> Path:
    path = Path(path)
    try:
        path.write_text(format_mayacam(view), encoding="utf-8")
    except OSError as err:
        raise CalibrationError(f"{path}: cannot write ({err.strerror or err})") from err
    return path


def read_mayacam(path: str | Path, name: str) -> View:
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as err:
        raise CalibrationError(f"{path}: cannot read ({err.strerror or err})") from err
    return parse_mayacam(text, name, source=str(path))


def export_calibration(calibration: Calibration, directory: str | Path, stem: str = "camera") -> dict[str, Path]:
    """Write ``<stem>_p.txt`` and ``<stem>_q.txt`` MayaCam 2.0 files; returns their paths by view."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths = {name: write_mayacam(directory / f"{stem}_{name}.txt", view)
             for name, view in sorted(calibration.views.items())}
    log.info("exported MayaCam 2.0 files %s", ", ".join(str(p) for p in paths.values()))
    return paths


def import_calibration(p_path: str | Path, q_path: str | Path) -> Calibration:
    """A validated :class:`Calibration` from two MayaCam 2.0 files (view p, view q)."""
    views = {"p": read_mayacam(p_path, "p"), "q": read_mayacam(q_path, "q")}
    metadata = {"method": "imported MayaCam 2.0", "mayacam_p": str(p_path), "mayacam_q": str(q_path)}
    return Calibration.from_views(views["p"], views["q"], metadata)
