"""``appliance validate`` end to end in simulation: two robots, tiny counts, every output file and key checked.

The session goes through the real paths: pairs from the fake USB grabbers through the pyusb driver and
the biplane pairing, tool poses from the loopback NDI tracker over a pty through the NDI driver, the
registration measured with the simulated fiducial phantom and pointer.
"""
from __future__ import annotations

import csv
import io
import json
import math
from contextlib import redirect_stdout
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from appliance import cli
from appliance.config_io import config_path, read_yaml
from appliance.geometry import Calibration
from appliance.registration import RigidTransform, registration_from_calibration
from appliance.validation.lab import OperatorLab
from appliance.validation.session import Sample

ROBOTS = (1, 4)          # the default robot and the smallest one
POSTURES, SAMPLES = 2, 3


def _session_variant(path: Path, **sections: object) -> Path:
    """The shipped simulation session with some top-level sections replaced (its file names stay resolvable:
    a session looks beside itself, then in config/)."""
    data = read_yaml(config_path("sim.yaml"))
    data.update(sections)
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str, int]:
    out = tmp_path_factory.mktemp("validate") / "report"
    buffer = io.StringIO()
    with redirect_stdout(buffer):
        code = cli.main(["validate", "--robot", ",".join(map(str, ROBOTS)), "--postures", str(POSTURES),
                         "--samples", str(SAMPLES), "--out", str(out)])
    return out, buffer.getvalue(), code


def test_every_output_file_is_written(report: tuple[Path, str, int]) -> None:
    out, text, code = report
    assert code == 0
    for name in ("table.md", "table.csv", "boxplots.png", "samples.csv", "summary.json"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
        assert str(out / name) in text
    assert (out / "boxplots.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    saved = registration_from_calibration(Calibration.load(out / "calibration_registered.yaml"))
    summary = json.loads((out / "summary.json").read_text())
    assert saved is not None and np.allclose(saved.R, summary["registration"]["R"], atol=1e-9)
    assert "| # | L (mm) | D (mm)" in text and "fewer than the protocol's 30" in text


def test_table_has_one_row_per_robot_with_its_geometry(report: tuple[Path, str, int]) -> None:
    out, _, _ = report
    with (out / "table.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert [int(r["robot"]) for r in rows] == list(ROBOTS)
    assert [float(r["length_mm"]) for r in rows] == [10.0, 3.0]
    for row in rows:
        assert row["recognised"] == f"{POSTURES * SAMPLES}/{POSTURES * SAMPLES}"
        assert "±" in row["position_mm"] and "±" in row["axis_deg"] and "±" in row["processing_ms"]
    markdown = (out / "table.md").read_text()
    assert markdown.count("\n| 1 |") == 2 and markdown.count("\n| 4 |") == 2   # Table 1 and the truth table
    assert "FRE RMS" in markdown and "expected TRE at the postures" in markdown


def test_raw_samples_hold_every_pair_with_errors(report: tuple[Path, str, int]) -> None:
    out, _, _ = report
    with (out / "samples.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == len(ROBOTS) * POSTURES * SAMPLES
    assert set(rows[0]) >= {f for f in Sample.__dataclass_fields__} | {"pixels"}
    for row in rows:
        assert row["ok"] == "True"       # (a reason may still warn of reduced accuracy)
        assert float(row["position_mm"]) < 1.0 and float(row["axis_deg"]) < 10.0
        assert float(row["truth_position_mm"]) < 1.0 and float(row["processing_ms"]) > 0.0
        assert int(row["pixels_p"]) > 20 and int(row["pixels_q"]) > 20
        assert len(row["reference_centroid_mm"].split()) == 3
    frames = [(row["robot"], int(row["frame"])) for row in rows]
    assert len(set(frames)) == len(frames), "each sample is a new biplane pair"
    ots = [(row["robot"], int(row["ots_frame"])) for row in rows]
    assert len(set(ots)) == len(ots), "each sample has its own tracker frame"


def test_summary_json_keys_and_the_registration_recovers_the_world(report: tuple[Path, str, int]) -> None:
    out, _, _ = report
    summary = json.loads((out / "summary.json").read_text())
    assert {"session", "simulation", "lab", "plan", "registration", "robots", "overall", "paper", "files"} <= set(summary)
    assert summary["simulation"] is True
    assert summary["plan"] == {"robots": list(ROBOTS), "postures": POSTURES, "samples": SAMPLES,
                               "meets_protocol": False, "protocol_samples": 30}
    robot = summary["robots"][0]
    assert {"statistics", "postures", "samples", "recognised", "ambiguous", "devices"} <= set(robot)
    assert set(robot["statistics"]) >= {"position_mm", "axis_deg", "tip_mean_mm", "pixels", "processing_ms"}
    assert {"n", "mean", "sd", "rms", "median", "q1", "q3", "p95", "max"} <= set(robot["statistics"]["position_mm"])
    assert len(robot["postures"]) == POSTURES and robot["postures"][0]["samples"] == SAMPLES
    assert "pty" in robot["devices"]["ots"] or "/dev/" in robot["devices"]["ots"]

    reg = summary["registration"]
    assert reg["source"] == "measured with the fiducial phantom" and reg["fiducials"] == 8
    # Averaged pointer touches: FRE well under the tracker's 0.19 mm per frame, but not zero.
    assert 0.005 < reg["fre_rms_mm"] < 0.19 and reg["pivot"]["rms_mm"] < 0.5
    assert len(reg["tre_rms_mm_at_targets"]) == len(ROBOTS) * POSTURES
    # The registration finds the tracker where the simulated world put it (vessel.yaml, world.ots_from_world),
    # up to the appliance's calibration, which is perturbed by 0.05 deg / 0.2 mm from the truth.
    world = read_yaml(config_path("vessel.yaml"))["world"]["ots_from_world"]
    truth = RigidTransform(Rotation.from_euler("xyz", world["rotation_deg_xyz"], degrees=True).as_matrix(),
                           world["translation_mm"])
    found = RigidTransform(np.array(reg["R"]), np.array(reg["t"]))
    centre = np.array([c for r in summary["robots"] for p in r["postures"] for c in [p["reference_centroid_mm"]]])
    assert np.max(np.linalg.norm(found.apply(centre) - truth.apply(centre), axis=1)) < 0.5
    turn = Rotation.from_matrix(found.R @ truth.R.T).magnitude()
    assert math.degrees(turn) < 0.2


def test_bad_requests_fail_with_clear_messages(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["validate", "--robot", "99", "--out", str(tmp_path / "x")]) == 2
    assert "no robot with id 99 in the catalogue" in capsys.readouterr().err
    data = read_yaml(config_path("sim.yaml"))
    session = _session_variant(tmp_path / "no-ots.yaml", devices={**data["devices"], "ots": {"kind": "none"}})
    assert cli.main(["validate", "--config", str(session), "--robot", "1", "--out", str(tmp_path / "y")]) == 2
    assert "needs the optical tracker" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(["validate", "--samples", "0"])
    assert "--samples: must be at least 1, got 0" in capsys.readouterr().err


def test_operator_lab_prompts_each_step() -> None:
    prompts: list[str] = []
    out = io.StringIO()
    lab = OperatorLab("pointer.rom", 6, ask=lambda text: prompts.append(text) or "", out=out)
    assert lab.place_fiducials() == 6
    lab.touch_fiducial(2)
    lab.place_robot(0, 3)
    assert len(prompts) == 3 and lab.true_pose() is None
    assert "fiducial 3 of 6" in out.getvalue() and "posture 1 of 3" in out.getvalue()


def test_a_calibration_with_a_saved_registration_skips_the_fiducials(report: tuple[Path, str, int],
                                                                      tmp_path: Path) -> None:
    out, _, _ = report
    session = _session_variant(tmp_path / "registered.yaml", calibration={
        "source": "file", "file": str(out / "calibration_registered.yaml")})
    buffer = io.StringIO()
    with redirect_stdout(buffer):
        code = cli.main(["validate", "--config", str(session), "--robot", "1", "--postures", "1", "--samples", "2",
                         "--out", str(tmp_path / "again")])
    assert code == 0
    summary = json.loads((tmp_path / "again" / "summary.json").read_text())
    first = json.loads((out / "summary.json").read_text())
    assert summary["registration"]["source"].startswith("saved with the calibration")
    assert summary["registration"]["R"] == pytest.approx(np.array(first["registration"]["R"]))
    assert "fiducials" not in summary["registration"] and not (tmp_path / "again" / "calibration_registered.yaml").exists()
    assert summary["overall"]["recognised"] == 2
    assert summary["overall"]["statistics"]["position_mm"]["max"] < 1.0
