"""The robot catalogue: Table 1 of the seed paper, derived geometry, and load-time validation."""
from __future__ import annotations

import math
from pathlib import Path

import pytest
import yaml

from appliance.errors import ConfigError
from appliance.robots import MAX_CONE_FRACTION, load_robots, select_robot
from drivers.loopback import xray_scene

TABLE_1 = {  # id: (L mm, D mm, tip angle deg, materials)
    1: (10, 2, 20, ("NdFeB",)),
    2: (15, 1.5, 30, ("NdFeB",)),
    3: (19, 2, 15, ("NdFeB", "VeroClear")),
    4: (3, 1.5, 30, ("NdFeB",)),
    5: (15, 1.5, 20, ("NdFeB",)),
    6: (30, 5, 15, ("NdFeB", "VeroWhite")),
    7: (8, 1, 20, ("NdFeB",)),
}


@pytest.fixture(scope="module")
def robots():
    return load_robots()


def test_catalogue_holds_table_1(robots) -> None:
    assert sorted(robots) == list(TABLE_1)
    for rid, (length, diameter, angle, materials) in TABLE_1.items():
        spec = robots[rid]
        assert (spec.length_mm, spec.diameter_mm, spec.tip_angle_deg, spec.material) == \
            (length, diameter, angle, materials)


def test_polymer_bodied_robots_attenuate_less(robots) -> None:
    solid = robots[1].attenuation_per_mm
    for rid in (3, 6):
        assert 0 < robots[rid].magnet_volume_fraction < 1
        assert robots[rid].attenuation_per_mm < 0.5 * solid
        assert robots[rid].density_kg_m3 < robots[1].density_kg_m3
    assert all(1.2 <= r.remanence_t <= 1.3 for r in robots.values())


def test_cone_follows_tip_angle_and_is_capped(robots) -> None:
    r1 = robots[1]
    assert r1.cone_length_mm == pytest.approx(1.0 / math.tan(math.radians(10.0)))
    assert not r1.cone_capped
    r4 = robots[4]  # 0.75 / tan(15 deg) = 2.8 mm of a 3 mm body: capped so a cylinder remains
    assert r4.cone_capped and r4.cone_length_mm == pytest.approx(MAX_CONE_FRACTION * 3.0)
    assert all(r.cylinder_length_mm > 0 for r in robots.values())


def test_geometry_agrees_with_the_simulator(robots) -> None:
    assert MAX_CONE_FRACTION == xray_scene.MAX_CONE_FRACTION
    for spec in robots.values():
        body = xray_scene.RobotBody.from_spec(spec)
        assert body.attenuation_per_mm == spec.attenuation_per_mm
        assert body.cone_length_mm == pytest.approx(spec.cone_length_mm)
        assert body.volume_mm3 == pytest.approx(spec.volume_mm3)
        assert body.centroid_from_tail_mm == pytest.approx(spec.centroid_from_tail_mm)


def test_centroid_lies_toward_the_tail_of_the_midpoint(robots) -> None:
    # The cone holds less volume than a cylinder of its length, so the centroid moves to the tail.
    for spec in robots.values():
        assert 0 < spec.centroid_from_tail_mm < spec.length_mm / 2


def test_magnetic_moment_of_robot_1(robots) -> None:
    spec = robots[1]
    expected = spec.remanence_t * spec.volume_mm3 * 1e-9 / (4e-7 * math.pi)
    assert spec.magnetic_moment_am2 == pytest.approx(expected)
    assert 0.01 < spec.magnetic_moment_am2 < 0.03  # ~20 mm^3 of N42: about 0.02 A m^2


def _write(tmp_path: Path, data: dict) -> Path:
    path = tmp_path / "robots.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


def _base() -> dict:
    return yaml.safe_load(Path("config/robots.yaml").read_text(encoding="utf-8"))


@pytest.mark.parametrize("key, value, expected", [
    ("tip_angle_deg", 95.0, "robots[0].tip_angle_deg"),
    ("tip_angle_deg", 0.0, "robots[0].tip_angle_deg"),
    ("length_mm", -1.0, "robots[0].length_mm"),
    ("diameter_mm", 0.0, "robots[0].diameter_mm"),
    ("colour", "red", "robots[0].colour"),
    ("material", ["Unobtainium"], "robots[0].material[0]: unknown material 'Unobtainium'"),
    ("material", ["VeroClear"], "robots[0].material[0]: 'VeroClear' is listed first"),
    ("magnet_volume_fraction", 0.5, "robots[0].magnet_volume_fraction: a single-material robot"),
])
def test_bad_entries_name_file_and_key(tmp_path: Path, key: str, value: object, expected: str) -> None:
    data = _base()
    data["robots"][0][key] = value
    path = _write(tmp_path, data)
    with pytest.raises(ConfigError) as info:
        load_robots(path)
    assert str(path) in str(info.value) and expected in str(info.value)


def test_schema_version_and_duplicates_are_checked(tmp_path: Path) -> None:
    data = _base()
    data["schema_version"] = 2
    with pytest.raises(ConfigError, match="schema_version"):
        load_robots(_write(tmp_path, data))
    data = _base()
    data["robots"][1]["id"] = 1
    with pytest.raises(ConfigError, match=r"robots\[1\]\.id: duplicate robot id 1"):
        load_robots(_write(tmp_path, data))


def test_missing_file_and_unknown_id(tmp_path: Path, robots) -> None:
    with pytest.raises(ConfigError, match="file not found"):
        load_robots(tmp_path / "nope.yaml")
    with pytest.raises(ConfigError, match=r"no robot with id 9 .*ids: 1, 2, 3, 4, 5, 6, 7"):
        select_robot(robots, 9)
    assert select_robot(robots, 6).diameter_mm == 5.0
