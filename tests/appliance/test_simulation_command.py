"""``appliance sim`` and ``appliance run`` through the command line, and the path plot."""
from __future__ import annotations

import copy
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from appliance.cli import main
from appliance.config_io import config_path, read_yaml
from appliance.plots import plot_path
from appliance.recording import RecordingReader


def small_sim_file(tmp_path: Path) -> Path:
    data = copy.deepcopy(read_yaml(config_path("sim.yaml")))
    data["imaging"]["image_size"] = [256, 224]
    data["devices"]["ots"] = {"kind": "none"}
    # Not a test of the link's timing: on a loaded 2-core machine the simulated lab's process answers later
    # than sim.yaml's 3 x 50 ms ack time-out.
    data["devices"]["amplifier"] = {**data["devices"]["amplifier"], "ack_timeout_ms": 1000.0}
    # Relative names resolve beside the session file first, then in config/.
    path = tmp_path / "small-sim.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


def test_sim_command_runs_and_writes_summary_plot_and_recording(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                                                 ) -> None:
    out = tmp_path / "run"
    assert main(["sim", "--config", str(small_sim_file(tmp_path)), "--seconds", "1", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert re.search(r"cross-track\s+RMS \d+\.\d+ mm\s+max \d+\.\d+ mm", text)
    assert "path end      not reached in 1.0" in text
    assert re.search(r"loop latency .* p50 \d+\.\d\d ms, p99 \d+\.\d\d ms; -> acknowledged: p50 \d+\.\d\d ms", text)
    assert re.search(r"simulated in \d+\.\d+ s wall: (faster|slower) than real time", text)
    assert "ramped to zero and disabled" in text
    assert (out / "path.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    reader = RecordingReader(out / "session.mcap")
    summary = reader.summary()
    assert summary.complete and summary.messages["/posture"] >= 28
    assert reader.calibration is not None and set(reader.calibration["views"]) == {"p", "q"}
    assert reader.config is not None and reader.config["imaging"]["image_size"] == [256, 224]


def test_sim_refuses_a_bench_session(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["sim", "--config", str(config_path("bench.yaml"))]) == 2
    assert "not a simulation session" in capsys.readouterr().err


def test_run_refuses_a_simulated_session_and_bad_seconds(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", "--config", str(config_path("sim.yaml"))]) == 2
    assert "every device is loopback" in capsys.readouterr().err

def test_sim_rejects_non_positive_seconds() -> None:
    with pytest.raises(SystemExit):
        main(["sim", "--seconds", "0"])


def test_path_plot_is_written_and_checks_its_inputs(tmp_path: Path) -> None:
    s = np.linspace(0.0, 1.0, 50)
    path = np.column_stack([100 * s - 50, 10 * np.sin(6 * s), np.zeros_like(s)])
    truth = path + 0.2
    times = 2.0 * s
    plot = plot_path(tmp_path / "figs" / "p.png", path, truth, times, np.full(50, 0.28), tracked_mm=truth[::2],
                     events=[(1.0, "estop")])
    assert plot.read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(ValueError, match="one entry per frame"):
        plot_path(tmp_path / "q.png", path, truth, times[:-1], np.zeros(50))


def test_progress_line_shows_frame_position_error_and_currents_on_a_terminal_only() -> None:
    import io

    from appliance.commands.sim import ProgressLine, progress_text
    from appliance.loop_events import FrameReport

    report = FrameReport(index=3, t_s=1.5, frame=45, posture={"centroid_mm": [-12.04, -8.31, 3.0]}, tracked=True,
                         mode="run", reason=None, cross_track_mm=0.31, progress=0.52, done=False,
                         field_T=np.zeros(3), force_N=np.zeros(3), commanded_a=np.array([1.0, -4.9]),
                         measured_a=np.array([1.0, -4.86]), scale=1.0, limited_by=None)
    text = progress_text(report, cross_track_mm=0.18)
    assert "frame    45" in text and "pos (-12.0, -8.3, 3.0) mm" in text and "xt 0.18 mm" in text
    assert "52%" in text and "|I| max 4.9 A" in text

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    piped, terminal = io.StringIO(), Terminal()
    ProgressLine(piped).show(text)
    ProgressLine(terminal).show(text)
    assert piped.getvalue() == "" and terminal.getvalue().startswith("\rframe    45")
