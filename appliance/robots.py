"""The robot catalogue: the microrobots the appliance can track and steer (``config/robots.yaml``).

Each robot is a cylinder of diameter ``D`` with a conical head; ``length_mm`` is the overall length
``L`` and ``tip_angle_deg`` the FULL apex angle of the cone. The cone is ``(D/2) / tan(angle/2)``
long, capped at ``MAX_CONE_FRACTION * L`` so the body always keeps a cylinder (the capped cone is
then blunter than the nominal angle). The head is the apex end; the tail is the flat face.

Robots with a polymer body around the magnet (robots 3 and 6 of the seed paper) carry a magnet
volume fraction; their X-ray attenuation and density are volume-weighted means of the two
materials, and their magnetic moment counts only the magnet.

Load with :func:`load_robots`; everything is validated at load, and errors name the file and key.
"""
from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Literal

from pydantic import Field

from appliance.config_io import StrictModel, config_path, read_yaml, validate_model
from appliance.errors import ConfigError

log = logging.getLogger(__name__)

# Keep in step with drivers.loopback.xray_scene.MAX_CONE_FRACTION (a test checks they agree; the
# appliance may not import the simulator).
MAX_CONE_FRACTION = 0.8
MU0 = 4e-7 * math.pi  # vacuum permeability, T m / A


class MaterialSpec(StrictModel):
    """A material's effective X-ray attenuation, density and (for a magnet) remanence."""

    attenuation_per_mm: float = Field(ge=0)
    density_kg_m3: float = Field(gt=0)
    remanence_t: float | None = Field(default=None, gt=0, lt=2.0)


class RobotEntry(StrictModel):
    """One robot as written in the file; materials by name, magnet first."""

    id: int = Field(gt=0)
    length_mm: float = Field(gt=0)
    diameter_mm: float = Field(gt=0)
    tip_angle_deg: float = Field(gt=0, lt=90)
    material: tuple[str, ...] = Field(min_length=1, max_length=2)
    magnet_volume_fraction: float = Field(default=1.0, gt=0, le=1)


class RobotsFile(StrictModel):
    schema_version: Literal[1]
    materials: dict[str, MaterialSpec]
    robots: list[RobotEntry] = Field(min_length=1)


class RobotSpec(StrictModel):
    """A robot with its materials resolved: what tracking, control and simulation need."""

    id: int
    length_mm: float
    diameter_mm: float
    tip_angle_deg: float
    material: tuple[str, ...]
    magnet_volume_fraction: float
    attenuation_per_mm: float   # effective, homogenised over the body
    density_kg_m3: float        # mean over the body
    remanence_t: float          # of the magnet

    @property
    def radius_mm(self) -> float:
        return self.diameter_mm / 2.0

    @property
    def cone_length_mm(self) -> float:
        natural = self.radius_mm / math.tan(math.radians(self.tip_angle_deg) / 2.0)
        return min(natural, MAX_CONE_FRACTION * self.length_mm)

    @property
    def cone_capped(self) -> bool:
        """True when the nominal tip angle would not leave a cylinder (the cone was shortened)."""
        return self.radius_mm / math.tan(math.radians(self.tip_angle_deg) / 2.0) > \
            MAX_CONE_FRACTION * self.length_mm

    @property
    def cylinder_length_mm(self) -> float:
        return self.length_mm - self.cone_length_mm

    @property
    def volume_mm3(self) -> float:
        area = math.pi * self.radius_mm ** 2
        return area * (self.cylinder_length_mm + self.cone_length_mm / 3.0)

    @property
    def centroid_from_tail_mm(self) -> float:
        """Distance along the axis from the tail face to the volume centroid."""
        area = math.pi * self.radius_mm ** 2
        cyl, cone = self.cylinder_length_mm, self.cone_length_mm
        v_cyl, v_cone = area * cyl, area * cone / 3.0
        return (v_cyl * cyl / 2.0 + v_cone * (cyl + cone / 4.0)) / (v_cyl + v_cone)

    @property
    def magnet_volume_mm3(self) -> float:
        return self.magnet_volume_fraction * self.volume_mm3

    @property
    def mass_kg(self) -> float:
        return self.density_kg_m3 * self.volume_mm3 * 1e-9

    @property
    def magnetic_moment_am2(self) -> float:
        """|m| = Br V / mu0 of a uniformly magnetised magnet (A m^2)."""
        return self.remanence_t * self.magnet_volume_mm3 * 1e-9 / MU0


def _resolve(entry: RobotEntry, index: int, materials: dict[str, MaterialSpec], source: str) -> RobotSpec:
    where = f"{source}: robots[{index}]"
    for k, name in enumerate(entry.material):
        if name not in materials:
            known = ", ".join(sorted(materials)) or "none"
            raise ConfigError(f"{where}.material[{k}]: unknown material {name!r} (known: {known})")
    magnet = materials[entry.material[0]]
    if magnet.remanence_t is None:
        raise ConfigError(f"{where}.material[0]: {entry.material[0]!r} is listed first, so it must be "
                          "the magnet, but it has no remanence_t")
    f = entry.magnet_volume_fraction
    if len(entry.material) == 1 and f != 1.0:
        raise ConfigError(f"{where}.magnet_volume_fraction: a single-material robot is all magnet "
                          f"(1.0), got {f}; name the body material as the second material")
    if len(entry.material) == 2 and f == 1.0:
        raise ConfigError(f"{where}.magnet_volume_fraction: a robot with a "
                          f"{entry.material[1]} body needs a magnet fraction below 1")
    body = materials[entry.material[-1]] if len(entry.material) == 2 else magnet
    return RobotSpec(
        id=entry.id, length_mm=entry.length_mm, diameter_mm=entry.diameter_mm,
        tip_angle_deg=entry.tip_angle_deg, material=entry.material, magnet_volume_fraction=f,
        attenuation_per_mm=f * magnet.attenuation_per_mm + (1 - f) * body.attenuation_per_mm,
        density_kg_m3=f * magnet.density_kg_m3 + (1 - f) * body.density_kg_m3,
        remanence_t=magnet.remanence_t)


def load_robots(path: str | Path | None = None) -> dict[int, RobotSpec]:
    """Read and validate the robot catalogue; keys are the robot ids (Table 1 numbers)."""
    path = Path(path) if path is not None else config_path("robots.yaml")
    source = str(path)
    data = validate_model(RobotsFile, read_yaml(path), source)
    robots: dict[int, RobotSpec] = {}
    for index, entry in enumerate(data.robots):
        if entry.id in robots:
            raise ConfigError(f"{source}: robots[{index}].id: duplicate robot id {entry.id}")
        spec = _resolve(entry, index, data.materials, source)
        if spec.cone_capped:
            log.debug("%s: robot %d: cone capped at %.0f%% of its length", source, spec.id,
                      100 * MAX_CONE_FRACTION)
        robots[entry.id] = spec
    return robots


def select_robot(robots: dict[int, RobotSpec], robot_id: int) -> RobotSpec:
    """The robot with ``robot_id``, or a ConfigError that lists the ids there are."""
    try:
        return robots[robot_id]
    except KeyError:
        known = ", ".join(str(k) for k in sorted(robots))
        raise ConfigError(f"no robot with id {robot_id} in the catalogue (ids: {known})") from None
