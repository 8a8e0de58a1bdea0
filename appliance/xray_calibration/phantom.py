"""The calibration phantom: known 3D bead centres (mm) read from a CSV file, and its reference beads.

Accepted bead files (one bead per line, comma, semicolon, tab or space separated):

- ``x,y,z`` per line, with or without one header line (a line that is not all numbers);
- ``id,x,y,z`` per line: a leading id column (any text without separators, e.g. ``7`` or ``ref_a``);
- XMALab's frame-specification CSV as is: its first line is always a header (``x y z``, or ``white``
  for bright beads, or scale factors ``s<sx>,s<sy>,s<sz>,...`` that multiply every coordinate), then
  ``x,y,z`` rows. Bead ids are then the 1-based row numbers, as XMALab numbers them.

Reference beads (the few beads an operator marks by hand, XMALab's "references" file) come from a
separate text file with ``<id> <name>`` per line (XMALab's layout: 1-based id, then a name).

A phantom needs at least :data:`MIN_BEADS` beads and must not be planar for the DLT method; planar
targets are handled by :mod:`appliance.xray_calibration.grid`.
"""
from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from appliance.errors import CalibrationError, InputDataError

log = logging.getLogger(__name__)

#: The DLT has 11 unknowns: 6 beads are the bare minimum, and RANSAC needs spares to find outliers.
MIN_BEADS = 8
#: Smallest spread (mm, RMS distance from the best-fit plane) for a "3D" phantom.
MIN_DEPTH_MM = 1.0

_SPLIT = re.compile(r"[,;\t ]+")


@dataclass(frozen=True)
class Phantom:
    """Bead ids (text), bead centres ``points_mm`` (N,3), reference bead ids, and whether beads are bright."""

    ids: tuple[str, ...]
    points_mm: np.ndarray
    references: dict[str, str] = field(default_factory=dict)  # id -> name
    bright_beads: bool = False
    source: str = "phantom"

    def __post_init__(self) -> None:
        points = np.asarray(self.points_mm, dtype=np.float64).reshape(-1, 3)
        points.setflags(write=False)
        object.__setattr__(self, "points_mm", points)
        if len(self.ids) != len(points):
            raise ValueError(f"{self.source}: {len(self.ids)} ids for {len(points)} beads")
        if len(set(self.ids)) != len(self.ids):
            duplicates = sorted({i for i in self.ids if self.ids.count(i) > 1})
            raise InputDataError(f"{self.source}: duplicate bead ids {duplicates}")
        unknown = sorted(set(self.references) - set(self.ids))
        if unknown:
            raise InputDataError(f"{self.source}: reference beads {unknown} are not in the phantom")

    def __len__(self) -> int:
        return len(self.ids)

    def index(self, bead_id: str) -> int:
        """Row of a bead id; an unknown id is an :class:`InputDataError` naming the known ones."""
        try:
            return self.ids.index(str(bead_id))
        except ValueError:
            shown = ", ".join(self.ids[:12]) + (" ..." if len(self.ids) > 12 else "")
            raise InputDataError(f"{self.source}: no bead with id {bead_id!r} (ids: {shown})") from None

    def planarity_mm(self) -> float:
        """RMS distance of the beads from their best-fit plane (0 for a planar target)."""
        centred = self.points_mm - self.points_mm.mean(axis=0)
        return float(np.linalg.svd(centred, compute_uv=False)[-1] / np.sqrt(len(self)))

    def check_for_dlt(self) -> None:
        """Raise :class:`CalibrationError` unless the beads can calibrate a view on their own."""
        if len(self) < MIN_BEADS:
            raise CalibrationError(f"{self.source}: {len(self)} beads; a phantom needs at least {MIN_BEADS}")
        spread = self.planarity_mm()
        if spread < MIN_DEPTH_MM:
            raise CalibrationError(
                f"{self.source}: the beads are (nearly) coplanar (RMS {spread:.3g} mm off their plane); "
                "the DLT needs a 3D phantom -- use the planar grid method for flat targets")

    def with_references(self, references: dict[str, str]) -> Phantom:
        return Phantom(self.ids, self.points_mm, dict(references), self.bright_beads, self.source)


def _numbers(fields: list[str]) -> list[float] | None:
    try:
        return [float(f) for f in fields]
    except ValueError:
        return None


def _xmalab_header(fields: list[str]) -> tuple[np.ndarray, bool] | None:
    """Scale and bead colour from an XMALab header line, or None if it is not one."""
    text = " ".join(fields).lower()
    bright = "white" in text
    scale = np.ones(3)
    if len(fields) >= 3 and all(f.lower().startswith("s") for f in fields[:3]):
        values = _numbers([f[1:] for f in fields[:3]])
        if values is not None:
            scale = np.asarray(values)
            return scale, bright
    if bright or text.replace(" ", "") in ("xyz", "x,y,z"):
        return scale, bright
    return None


def parse_phantom(text: str, source: str = "phantom") -> Phantom:
    """Parse bead-file text (see module docstring); errors name ``source`` and the line number."""
    rows: list[tuple[int, list[str]]] = []
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.split("#", 1)[0].strip()
        if stripped:
            rows.append((number, [f for f in _SPLIT.split(stripped) if f]))
    if not rows:
        raise CalibrationError(f"{source}: no beads (the file is empty)")
    scale, bright = np.ones(3), False
    first_number, first = rows[0]
    if _numbers(first) is None and not (len(first) == 4 and _numbers(first[1:]) is not None):
        header = _xmalab_header(first)
        if header is not None:
            scale, bright = header
        log.debug("%s: header line %d: %s", source, first_number, first)
        rows = rows[1:]
    ids: list[str] = []
    points: list[list[float]] = []
    for row_index, (number, fields) in enumerate(rows, start=1):
        if len(fields) == 3:
            values = _numbers(fields)
            bead_id = str(row_index)
        elif len(fields) == 4:
            values = _numbers(fields[1:])
            bead_id = fields[0]
        else:
            raise InputDataError(f"{source}: line {number}: expected x,y,z or id,x,y,z, got {len(fields)} fields")
        if values is None or not np.all(np.isfinite(values)):
            raise InputDataError(f"{source}: line {number}: coordinates are not numbers: {','.join(fields)}")
        ids.append(bead_id)
        points.append(values)
    if not points:
        raise CalibrationError(f"{source}: no beads (only a header line)")
    return Phantom(tuple(ids), np.asarray(points) * scale, {}, bright, source)


def parse_references(text: str, source: str = "references") -> dict[str, str]:
    """XMALab references: ``<id> <name>`` per line (the name is optional here)."""
    references: dict[str, str] = {}
    for number, line in enumerate(text.splitlines(), start=1):
        fields = line.split("#", 1)[0].split(None, 1)
        if not fields:
            continue
        references[fields[0].rstrip(",")] = fields[1].strip() if len(fields) > 1 else f"ref{len(references) + 1}"
    if not references:
        raise InputDataError(f"{source}: no reference beads listed")
    return references


def _read(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8-sig")
    except FileNotFoundError as err:
        raise InputDataError(f"{path}: file not found") from err
    except (OSError, UnicodeDecodeError) as err:
        raise InputDataError(f"{path}: cannot read ({err})") from err


def load_phantom(path: str | Path, references: str | Path | None = None) -> Phantom:
    """Read a bead file (and optionally an XMALab references file)."""
    path = Path(path)
    phantom = parse_phantom(_read(path), source=str(path))
    if references is not None:
        phantom = phantom.with_references(parse_references(_read(Path(references)), source=str(references)))
    log.info("phantom %s: %d beads, %d references", path, len(phantom), len(phantom.references))
    return phantom


def write_phantom(path: str | Path, phantom: Phantom) -> Path:
    """Write ``id,x,y,z`` rows with a header (the format :func:`load_phantom` reads back)."""
    path = Path(path)
    lines = ["id,x_mm,y_mm,z_mm"]
    lines += [f"{i},{x:.6f},{y:.6f},{z:.6f}" for i, (x, y, z) in zip(phantom.ids, phantom.points_mm)]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def make_cube_phantom(size_mm: float = 100.0, layers: int = 4, per_layer: int = 12, *,
                      reference_count: int = 6, seed: int = 7) -> Phantom:
    """A simulated "cube": beads on ``layers`` plates, placed so no two overlap in side or front views.

    On each plate the beads take distinct ``x`` and distinct ``y`` positions (a Latin arrangement, in
    shuffled order), so views along the x or y axis -- a biplane system's usual directions -- never
    see two beads of a plate on top of each other; a small random height per bead breaks the planes.
    The layout is irregular, so a shift by one bead pitch does not line it up with itself (which
    would defeat matching from a rough geometry). ``reference_count`` beads spread through the cube are
    listed as reference beads (for marking by hand).
    """
    rng = np.random.default_rng(seed)
    slots = (np.arange(per_layer) + 0.5) / per_layer * size_mm - size_mm / 2
    points = []
    for layer in range(layers):
        z = -size_mm / 2 + size_mm * layer / max(1, layers - 1)
        xs = rng.permutation(slots) + rng.uniform(-0.15, 0.15, per_layer) * size_mm / per_layer
        ys = rng.permutation(slots) + rng.uniform(-0.15, 0.15, per_layer) * size_mm / per_layer
        zs = z + rng.uniform(-0.1, 0.1, per_layer) * size_mm / max(1, layers - 1)
        points.extend(np.column_stack([xs, ys, zs]).tolist())
    points_mm = np.asarray(points)
    ref_rows = np.linspace(0, len(points_mm) - 1, reference_count).round().astype(int)
    ids = tuple(str(i + 1) for i in range(len(points_mm)))
    references = {ids[r]: f"ref{n + 1}" for n, r in enumerate(ref_rows)}
    return Phantom(ids, points_mm, references, False, "simulated cube")
