"""Typed model of ``config/coils.yaml``: the EMA coil system as the appliance is configured to know it.

Coordinates are in the X-ray world frame (the frame of the calibration file), millimetres. Each coil is
one amplifier channel, in file order. A coil is a winding of ``turns`` turns about ``axis`` (positive
current makes field along ``+axis`` at the coil's centre, right-hand rule) with a mean radius; an
optional ``winding`` block spreads the turns over a rectangular cross-section (axial length x radial
depth) discretised into loops, which matters near the coil and little in the workspace.

The simulated world reads the same file as plain data (and may perturb it); this module is only the
appliance's view.
"""
from __future__ import annotations

import math
from pathlib import Path

from pydantic import Field, field_validator, model_validator

from appliance.config_io import StrictModel, config_path, load_model

SCHEMA_VERSION = 1

Vec3 = tuple[float, float, float]


class Winding(StrictModel):
    """Finite winding cross-section; the turns are shared equally by ``loops_axial * loops_radial`` loops."""

    length_mm: float = Field(ge=0.0)
    depth_mm: float = Field(ge=0.0)
    loops_axial: int = Field(default=1, ge=1, le=16)
    loops_radial: int = Field(default=1, ge=1, le=16)


class CoilConfig(StrictModel):
    """One coil = one amplifier channel."""

    name: str = Field(min_length=1)
    centre_mm: Vec3
    axis: Vec3
    radius_mm: float = Field(gt=0.0)
    turns: int = Field(ge=1)
    resistance_ohm: float = Field(gt=0.0)
    inductance_h: float = Field(ge=0.0)
    max_current_a: float = Field(gt=0.0)
    winding: Winding | None = None

    @field_validator("axis")
    @classmethod
    def _unit_axis(cls, axis: Vec3) -> Vec3:
        norm = math.sqrt(sum(a * a for a in axis))
        if norm < 1e-9:
            raise ValueError("axis must be a non-zero vector")
        return (axis[0] / norm, axis[1] / norm, axis[2] / norm)

    @model_validator(mode="after")
    def _winding_fits(self) -> CoilConfig:
        if self.winding is not None and self.winding.depth_mm >= 2.0 * self.radius_mm:
            raise ValueError("winding.depth_mm must be smaller than the coil diameter")
        return self


class CoilLimits(StrictModel):
    """System-wide limits the allocator honours besides each coil's ``max_current_a``."""

    max_power_w: float = Field(gt=0.0)
    max_slew_a_per_s: float = Field(gt=0.0)


class CoilsConfig(StrictModel):
    """The whole ``coils.yaml``."""

    schema_version: int
    name: str = "ema"
    coils: list[CoilConfig] = Field(min_length=1)
    limits: CoilLimits

    @field_validator("schema_version")
    @classmethod
    def _known_version(cls, version: int) -> int:
        if version != SCHEMA_VERSION:
            raise ValueError(f"unsupported schema_version {version}; this appliance reads {SCHEMA_VERSION}")
        return version

    @field_validator("coils")
    @classmethod
    def _unique_names(cls, coils: list[CoilConfig]) -> list[CoilConfig]:
        seen: set[str] = set()
        for coil in coils:
            if coil.name in seen:
                raise ValueError(f"coil name {coil.name!r} is used twice")
            seen.add(coil.name)
        return coils

    @property
    def channel_count(self) -> int:
        return len(self.coils)


def load_coils(path: str | Path | None = None) -> CoilsConfig:
    """Load and validate a coils file (default: the shipped ``config/coils.yaml``)."""
    return load_model(path if path is not None else config_path("coils.yaml"), CoilsConfig)
