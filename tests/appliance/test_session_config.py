"""Session files: the shipped ones load, and every mistake is named by file and key path."""
from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import pytest
import yaml

from appliance.config_io import config_path, read_yaml
from appliance.errors import ConfigError
from appliance.session_config import SCHEMA_VERSION, load_session, session_from_mapping


def sim_data() -> dict[str, Any]:
    return copy.deepcopy(read_yaml(config_path("sim.yaml")))


def write(tmp_path: Path, data: dict[str, Any]) -> Path:
    path = tmp_path / "session.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


def test_shipped_sessions_load() -> None:
    sim = load_session()
    assert sim.config.is_simulation and sim.config.schema_version == SCHEMA_VERSION
    assert sim.config.devices.amplifier.kind == "loopback" and sim.config.devices.xray.link == "usb"
    assert sim.coils_path == config_path("coils.yaml") and sim.vessel_path.is_file()
    bench = load_session(config_path("bench.yaml"))
    assert not bench.config.is_simulation
    assert bench.config.calibration.source == "file"
    assert set(bench.config.devices.xray.sources or {}) == {"p", "q"}


def test_unknown_key_is_named_with_its_path(tmp_path: Path) -> None:
    data = sim_data()
    data["devices"]["amplifier"]["watchdog"] = 200
    with pytest.raises(ConfigError, match=r"session.yaml: devices\.amplifier\.watchdog: Extra inputs"):
        load_session(write(tmp_path, data))


def test_out_of_range_value_is_named(tmp_path: Path) -> None:
    data = sim_data()
    data["imaging"]["fps"] = 0
    with pytest.raises(ConfigError, match=r"imaging\.fps"):
        load_session(write(tmp_path, data))
    data = sim_data()
    data["control"]["speed_mm_s"] = 20.0      # above max_speed_mm_s: the follower's own check
    with pytest.raises(ConfigError, match=r"control"):
        load_session(write(tmp_path, data))


def test_serial_devices_need_their_ports() -> None:
    data = read_yaml(config_path("bench.yaml"))
    del data["devices"]["amplifier"]["port"]
    with pytest.raises(ConfigError, match=r"devices\.amplifier.*needs 'port'"):
        session_from_mapping(data, "bench.yaml")
    data = read_yaml(config_path("bench.yaml"))
    del data["devices"]["ots"]["rom"]
    with pytest.raises(ConfigError, match=r"devices\.ots.*'rom'"):
        session_from_mapping(data, "bench.yaml")


def test_loopback_and_real_devices_do_not_mix() -> None:
    data = sim_data()
    data["devices"]["amplifier"] = {"kind": "serial", "port": "/dev/ttyACM0"}
    with pytest.raises(ConfigError, match="either every device is loopback"):
        session_from_mapping(data, "mixed.yaml")


def test_nominal_calibration_exists_only_in_simulation() -> None:
    data = read_yaml(config_path("bench.yaml"))
    data["calibration"] = {"source": "nominal"}
    with pytest.raises(ConfigError, match="only in simulation"):
        session_from_mapping(data, "bench.yaml")


def test_schema_version_is_checked(tmp_path: Path) -> None:
    data = sim_data()
    data["schema_version"] = 99
    with pytest.raises(ConfigError, match="schema_version.*unsupported schema_version 99"):
        load_session(write(tmp_path, data))


def test_relative_files_resolve_beside_the_session_first(tmp_path: Path) -> None:
    (tmp_path / "coils.yaml").write_text(config_path("coils.yaml").read_text())
    session = load_session(write(tmp_path, sim_data()))
    assert session.coils_path == tmp_path / "coils.yaml"       # beside the session file
    assert session.vessel_path == config_path("vessel.yaml")   # falls back to config/
