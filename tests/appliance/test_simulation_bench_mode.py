"""``appliance run`` on real device kinds: the amplifier on a serial port (a pty served by the loopback fake,
as a bench engineer would with ``appliance loopback amp``) and both X-ray planes from a biplane frame folder
played back at 30 fps. The bench code path (open_serial, open_source, calibration file) runs unchanged."""
from __future__ import annotations

import re
import time
from pathlib import Path

import pytest
import yaml

from appliance.cli import main
from appliance.config_io import config_path, read_yaml
from appliance.device_factory import perturbed_calibration
from appliance.recording import RecordingReader
from appliance.robots import load_robots
from drivers.biplane_folder import write_frame
from drivers.loopback.amplifier_fake import make_default_fake
from drivers.loopback.serve import PtyServer
from drivers.loopback.vessel import Vessel
from drivers.loopback.xray_render import BiplaneRenderer, RobotBody, RobotPose, VesselPhantom, biplane_views


@pytest.fixture(scope="module")
def frame_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Twelve pairs of a robot resting in the vessel phantom, 256 x 224, with their calibration."""
    root = tmp_path_factory.mktemp("frames")
    views = biplane_views(image_size=(256, 224), elevation_deg=15.0)
    vessel = Vessel.from_config(read_yaml(config_path("vessel.yaml"))["vessel"])
    robot = load_robots()[1]
    body = RobotBody(robot.length_mm, robot.diameter_mm, robot.tip_angle_deg, robot.attenuation_per_mm)
    renderer = BiplaneRenderer(views, body, vessel=VesselPhantom(vessel.sample(1.0), vessel.radius_mm, 0.06), seed=2)
    for number in range(12):
        pair = renderer.render(RobotPose(vessel.point_at(6.0), vessel.tangent_at(6.0)))
        for plane in ("p", "q"):
            write_frame(root, plane, number, pair.images[plane])
    perturbed_calibration(views, 0.0, 0.0, 0, renderer.settings.dark_level).save(root / "calibration.yaml")
    return root


def bench_session(tmp_path: Path, frames: Path, amplifier_port: str) -> Path:
    data = read_yaml(config_path("bench.yaml"))
    data["calibration"] = {"source": "file", "file": str(frames / "calibration.yaml")}
    data["devices"] = {
        # Not a test of the link's timing: the fake is served by a thread of this process, which a loaded
        # 2-core machine (load 12-19) leaves without the GIL or a core for longer than bench.yaml's 3 x 50 ms
        # ack time-out and its 200 ms watchdog; those have their own tests (tests/drivers/test_amplifier_pty.py).
        "amplifier": {"kind": "serial", "port": amplifier_port, "watchdog_ms": 2000, "ack_timeout_ms": 1000.0,
                      "max_current_a": 10.0},
        "xray": {"kind": "sources", "sources": {p: f"file://{frames}?plane={p}&rate=30&loop=1" for p in ("p", "q")}},
        "ots": {"kind": "none"},
    }
    data["recording"] = {"folder": str(tmp_path / "runs"), "frames_every": 4}
    path = tmp_path / "bench.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


def test_run_steers_on_a_serial_amplifier_and_played_back_frames(tmp_path: Path, frame_folder: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    fake = make_default_fake()
    with PtyServer(fake) as server:
        session = bench_session(tmp_path, frame_folder, server.path)
        code = main(["run", "--config", str(session), "--seconds", "3", "--out", str(tmp_path / "out")])
        text = capsys.readouterr().out
        assert code == 0, text
        time.sleep(0.1)               # the stop cut the output: the coils decay with L/R = 10 ms
        state = fake.snapshot()
    assert "stopped: time limit of 3 s" in text and "ramped to zero and disabled" in text
    assert re.search(r"loop latency  frame on host -> command written: p50 \d+\.\d\d ms, p99 \d+\.\d\d ms\n", text)
    assert not state.output_on and max(abs(state.measured_a)) < 0.05
    assert any(any(command.target_ma) for command in fake.applied)   # it did drive the coils
    reader = RecordingReader(tmp_path / "out" / "session.mcap")
    summary = reader.summary()
    assert summary.complete and summary.messages["/posture"] >= 20
    faults = [m for _, _, m in reader.messages("/fault")]
    assert faults[-1]["device"] == "operator" and "time limit" in faults[-1]["reason"]


def test_run_names_the_missing_amplifier_port(tmp_path: Path, frame_folder: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    session = bench_session(tmp_path, frame_folder, str(tmp_path / "ttyACM9"))
    assert main(["run", "--config", str(session)]) == 2
    assert "ttyACM9" in capsys.readouterr().err
