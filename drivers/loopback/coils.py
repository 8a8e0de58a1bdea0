"""The TRUE coils of the simulated EMA system: exact current-loop fields computed by magpylib.

This is the physical truth the simulated world uses; the appliance has its own (configured) model in
``appliance.control.actuation``. The two read the same ``config/coils.yaml`` data, but the world may
perturb it as a real bench differs from its drawings: coil centres displaced, axes tilted, and gains
(ampere-turns per ampere, i.e. turns, winding and current-sensor errors together) off by a percent.

A coil is one amplifier channel: a winding of ``turns`` turns about ``axis`` (positive current gives
field along ``+axis`` at its centre). An optional finite cross-section is discretised into coaxial
loops sharing the turns. The field is linear in the currents, so the world keeps one magpylib
collection per coil carrying 1 A and scales by the measured currents.

Units: mm at this module's interface (magpylib >= 5 works in metres and tesla internally).
Not modelled: iron, eddy currents, coil heating (resistance drift), mutual coupling: the amplifier
fake owns current dynamics and this module only maps currents to field.
"""
from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import magpylib as magpy
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
_FD_STEP_M = 20e-6
_OFFSETS = np.array([[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)


@dataclass(frozen=True)
class CoilGeometry:
    """One coil as built: centre (mm), unit axis, mean radius (mm), turns, winding block, gain."""

    name: str
    centre_mm: tuple[float, float, float]
    axis: tuple[float, float, float]
    radius_mm: float
    turns: float
    winding_length_mm: float = 0.0
    winding_depth_mm: float = 0.0
    loops_axial: int = 1
    loops_radial: int = 1
    gain: float = 1.0  # true ampere-turns per commanded ampere-turn

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any]) -> CoilGeometry:
        """From one entry of ``coils.yaml`` ``coils:`` (plain dict; electrical keys are ignored here)."""
        axis = np.asarray(data["axis"], float)
        axis = axis / np.linalg.norm(axis)
        winding = data.get("winding") or {}
        return cls(name=str(data["name"]), centre_mm=tuple(float(v) for v in data["centre_mm"]),  # type: ignore[arg-type]
                   axis=tuple(float(v) for v in axis), radius_mm=float(data["radius_mm"]),  # type: ignore[arg-type]
                   turns=float(data["turns"]), winding_length_mm=float(winding.get("length_mm", 0.0)),
                   winding_depth_mm=float(winding.get("depth_mm", 0.0)),
                   loops_axial=int(winding.get("loops_axial", 1)), loops_radial=int(winding.get("loops_radial", 1)))


def _rotation_from_z(axis: FloatArray) -> Rotation:
    """A rotation taking +z (magpylib's loop normal) to ``axis``."""
    if axis[2] < -1.0 + 1e-12:
        return Rotation.from_rotvec([np.pi, 0.0, 0.0])
    rotation, _ = Rotation.align_vectors([axis], [[0.0, 0.0, 1.0]])
    return rotation


def _coil_collection(coil: CoilGeometry) -> magpy.Collection:
    """The coil's loops carrying a total of ``turns * gain`` ampere-turns for 1 A."""
    axis = np.asarray(coil.axis, float)
    rotation = _rotation_from_z(axis)
    centre = np.asarray(coil.centre_mm, float) * 1e-3
    n_loops = coil.loops_axial * coil.loops_radial
    current = coil.turns * coil.gain / n_loops
    collection = magpy.Collection()
    for i in range(coil.loops_axial):
        z = (-0.5 + (i + 0.5) / coil.loops_axial) * coil.winding_length_mm * 1e-3
        for j in range(coil.loops_radial):
            radius = coil.radius_mm * 1e-3 + (-0.5 + (j + 0.5) / coil.loops_radial) * coil.winding_depth_mm * 1e-3
            collection.add(magpy.current.Circle(current=current, diameter=2.0 * radius,
                                                position=centre + z * axis, orientation=rotation))
    return collection


class TrueCoils:
    """Per-ampere field and gradient of every coil at a point, from magpylib loops."""

    def __init__(self, coils: Sequence[CoilGeometry]) -> None:
        if not coils:
            raise ValueError("TrueCoils needs at least one coil")
        self.coils = tuple(coils)
        self.n = len(self.coils)
        self._sources = [_coil_collection(c) for c in self.coils]

    @classmethod
    def from_config(cls, data: Mapping[str, Any], perturbation: Mapping[str, Any] | None = None,
                    seed: int | None = 0) -> TrueCoils:
        """Build from the plain ``coils.yaml`` mapping, optionally perturbed (see :func:`perturb`)."""
        coils = [CoilGeometry.from_mapping(c) for c in data["coils"]]
        if perturbation:
            coils = perturb(coils, np.random.default_rng(seed), **perturbation)
        return cls(coils)

    def _per_amp_m(self, points_m: FloatArray) -> FloatArray:
        """(P, 3, n) field in T per A at points given in metres."""
        raw = magpy.getB(self._sources, points_m, squeeze=False)          # (n, 1, 1, P, 3)
        return np.moveaxis(raw.reshape(self.n, -1, 3), 0, -1)

    def field_per_amp(self, point_mm: ArrayLike) -> FloatArray:
        """3 x n: field (T) at ``point_mm`` for 1 A in each coil."""
        p = np.asarray(point_mm, float).reshape(1, 3) * 1e-3
        return self._per_amp_m(p)[0]

    def field_and_gradient_per_amp(self, point_mm: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """(3 x n field in T/A, 3 x 3 x n gradient dB_i/dx_j in T/m/A) from one magpylib call."""
        p = np.asarray(point_mm, float).reshape(1, 3) * 1e-3
        fields = self._per_amp_m(p + _FD_STEP_M * _OFFSETS)
        grad = np.empty((3, 3, self.n))
        for j in range(3):
            grad[:, j, :] = (fields[1 + 2 * j] - fields[2 + 2 * j]) / (2.0 * _FD_STEP_M)
        return fields[0], grad

    def field_at(self, point_mm: ArrayLike, currents_a: ArrayLike) -> FloatArray:
        """Field (T, shape (3,)) at a point for a currents vector (A)."""
        currents = np.asarray(currents_a, float)
        if currents.shape != (self.n,):
            raise ValueError(f"expected {self.n} coil currents, got shape {currents.shape}")
        return self.field_per_amp(point_mm) @ currents


def perturb(coils: Sequence[CoilGeometry], rng: np.random.Generator, *, position_sd_mm: float = 0.0,
            position_offset_mm: Sequence[float] = (0.0, 0.0, 0.0), axis_sd_deg: float = 0.0,
            gain_sd: float = 0.0, gains: Sequence[float] | None = None) -> list[CoilGeometry]:
    """Coils as built rather than as drawn: random (seeded) centre shifts and axis tilts, a common
    offset of the whole coil system, and gain errors (random, or given per coil)."""
    if gains is not None and len(gains) != len(coils):
        raise ValueError(f"gains has {len(gains)} entries for {len(coils)} coils")
    out = []
    for index, coil in enumerate(coils):
        centre = np.asarray(coil.centre_mm) + np.asarray(position_offset_mm, float) + rng.normal(0.0, position_sd_mm, 3)
        axis = np.asarray(coil.axis)
        if axis_sd_deg > 0.0:
            tilt = np.cross(axis, rng.normal(size=3))
            tilt *= np.radians(abs(rng.normal(0.0, axis_sd_deg))) / max(np.linalg.norm(tilt), 1e-12)
            axis = Rotation.from_rotvec(tilt).apply(axis)
        gain = float(gains[index]) if gains is not None else 1.0 + float(rng.normal(0.0, gain_sd))
        out.append(replace(coil, centre_mm=tuple(centre), axis=tuple(axis / np.linalg.norm(axis)),  # type: ignore[arg-type]
                           gain=coil.gain * gain))
    logger.debug("perturbed %d coils (position sd %.2f mm, gain sd %.3f)", len(out), position_sd_mm, gain_sd)
    return out
