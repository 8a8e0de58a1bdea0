"""The foundation: CLI discovery, config validation messages, layer contracts."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from appliance import cli
from appliance.config_io import StrictModel, load_model
from appliance.errors import ApplianceError, ConfigError, DeviceError, DeviceTimeoutError

ROOT = Path(__file__).resolve().parents[1]


class _Limits(StrictModel):
    max_current_a: float
    watchdog_ms: int


class _Amp(StrictModel):
    port: str
    limits: list[_Limits]


def test_error_root_and_builtin_bases() -> None:
    assert issubclass(ConfigError, ApplianceError) and issubclass(ConfigError, ValueError)
    assert issubclass(DeviceTimeoutError, DeviceError) and issubclass(DeviceTimeoutError, TimeoutError)


def test_config_error_names_file_and_key_path(tmp_path: Path) -> None:
    bad = tmp_path / "amp.yaml"
    bad.write_text("port: /dev/ttyACM0\nlimits:\n  - {max_current_a: 5, watchdog_ms: 200}\n"
                   "  - {max_current_a: lots, watchdog_ms: 200}\n")
    with pytest.raises(ConfigError) as info:
        load_model(bad, _Amp)
    assert f"{bad}: limits[1].max_current_a" in str(info.value)
    assert "'lots'" in str(info.value)


def test_config_unknown_key_and_bad_yaml(tmp_path: Path) -> None:
    extra = tmp_path / "extra.yaml"
    extra.write_text("port: x\nlimits: []\nbaud: 9600\n")
    with pytest.raises(ConfigError, match=r"extra.yaml: baud: Extra inputs are not permitted"):
        load_model(extra, _Amp)
    broken = tmp_path / "broken.yaml"
    broken.write_text("port: [x\n")
    with pytest.raises(ConfigError, match=r"broken.yaml: not valid YAML at line"):
        load_model(broken, _Amp)
    with pytest.raises(ConfigError, match="file not found"):
        load_model(tmp_path / "missing.yaml", _Amp)


def test_cli_help_lists_commands(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        cli.main(["--help"])
    assert info.value.code == 0
    assert "COMMAND" in capsys.readouterr().out


def test_python_dash_m_appliance_runs() -> None:
    result = subprocess.run([sys.executable, "-m", "appliance", "--help"], cwd=ROOT, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert "usage: appliance" in result.stdout


def test_layers_point_one_way() -> None:
    """import-linter contracts in pyproject.toml: appliance -> drivers -> firmware_protocol; no fakes in production."""
    lint = Path(sys.executable).with_name("lint-imports")
    if not lint.exists():
        pytest.skip("import-linter is not installed in this environment")
    result = subprocess.run([str(lint), "--no-cache"], cwd=ROOT, capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr


def test_closed_pipe_ends_quietly() -> None:
    """`appliance ... | head` ends with status 0 and no BrokenPipe traceback."""
    program = (
        "import sys, types\n"
        "from appliance import cli\n"
        "def run(args):\n"
        "    for _ in range(20000):\n"
        "        print('x' * 200)\n"
        "    return 0\n"
        "spam = types.SimpleNamespace(NAME='spam', HELP='h', add_arguments=lambda p: None, run=run)\n"
        "cli._command_modules = lambda: [spam]\n"
        "sys.exit(cli.main(['spam']))\n")
    shell = f"{sys.executable} -c \"$PROGRAM\" | head -c 10 >/dev/null; echo \"status=${{PIPESTATUS[0]}}\""
    result = subprocess.run(["bash", "-c", shell], cwd=ROOT, capture_output=True, text=True,
                            env={"PROGRAM": program, "PATH": "/usr/bin:/bin"})
    assert "Traceback" not in result.stderr, result.stderr
    assert "status=0" in result.stdout
