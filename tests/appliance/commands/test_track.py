"""``appliance track``: its error paths (exit status 2, a message naming the file/frame) and its output."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from appliance.cli import main
from appliance.commands.demo import compare
from appliance.geometry import Calibration, View
from drivers.biplane_folder import PLANES, write_frame

SIZE = (64, 48)




def _calibration() -> Calibration:
    p = View.look_at("p", (-500.0, 0.0, 0.0), (0, 0, 0), focal_px=200.0, image_size=SIZE)
    q = View.look_at("q", (0.0, -500.0, 0.0), (0, 0, 0), focal_px=200.0, image_size=SIZE)
    return Calibration.from_views(p, q, {"source": "test"})


def _blank(shape: tuple[int, int] = (SIZE[1], SIZE[0])) -> np.ndarray:
    return np.random.default_rng(0).integers(30000, 30100, shape, dtype=np.uint16)


@pytest.fixture()
def folder(tmp_path: Path) -> Path:
    root = tmp_path / "scene"
    for number in (1, 2):
        for plane in PLANES:
            write_frame(root, plane, number, _blank())
    _calibration().save(root / "calibration.yaml")
    return root


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(["track", *argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_missing_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = _run(capsys, str(tmp_path / "nowhere"))
    assert code == 2 and out == ""
    assert f"appliance track: error: {tmp_path / 'nowhere'}: no such folder" in err


def test_folder_without_planes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = _run(capsys, str(tmp_path))
    assert code == 2 and "no p/ or q/ subfolder" in err


def test_missing_calibration(folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (folder / "calibration.yaml").unlink()
    code, out, err = _run(capsys, str(folder))
    assert code == 2 and out == ""
    assert "calibration.yaml: file not found" in err and "--calibration FILE" in err
    code, _, err = _run(capsys, str(folder), "--calibration", str(folder / "other.yaml"))
    assert code == 2 and f"{folder / 'other.yaml'}: file not found" in err


def test_bad_calibration_names_key_path(folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = _calibration().to_dict()
    data["views"]["q"]["R"][2] = [-v for v in data["views"]["q"]["R"][2]]  # a mirror, det -1
    path = folder / "calibration.yaml"
    path.write_text(yaml.safe_dump(data))
    code, out, err = _run(capsys, str(folder))
    assert code == 2 and out == ""
    assert f"{path}: views.q.R: not a rotation (det -1.000" in err


def test_empty_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for plane in PLANES:
        (tmp_path / plane).mkdir()
    write_frame(tmp_path, "p", 3, _blank())
    _calibration().save(tmp_path / "calibration.yaml")
    code, _, err = _run(capsys, str(tmp_path))
    assert code == 2 and "no frame pairs to track (p/: 1 unpaired, q/: 0 unpaired" in err


def test_frame_size_not_the_calibrations(folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_frame(folder, "q", 1, _blank((24, 32)))
    code, out, err = _run(capsys, str(folder))
    assert code == 2 and out == ""
    assert f"{folder / 'q' / '000001.png'}: frame 1 is 32x24 pixels but plane q is 64x48 (from the calibration)" in err


def test_unreadable_frame_keeps_earlier_records(folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (folder / "p" / "000002.png").write_bytes(b"\x89PNG\r\n\x1a\n broken")
    out_file = folder / "postures.jsonl"
    code, out, err = _run(capsys, str(folder), "--out", str(out_file))
    assert code == 2 and out == ""
    assert f"{folder / 'p' / '000002.png'}: frame 2: not a readable PNG or TIFF image" in err
    records = [json.loads(line) for line in out_file.read_text().splitlines()]
    assert [r["frame"] for r in records] == [1]


def test_blank_frames_are_reported_lost_not_invented(folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = _run(capsys, str(folder), "--fps", "10")
    assert code == 0 and err == ""  # stderr is not a terminal here: no progress line
    records = [json.loads(line) for line in out.splitlines()]
    assert [r["frame"] for r in records] == [1, 2]
    assert [r["t"] for r in records] == [0.1, 0.2]
    for record in records:
        assert record["ok"] is False and record["reason"]
        assert record["centroid_mm"] is None and record["direction"] is None and record["tips_mm"] is None


def test_bad_arguments(folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["track", str(folder), "--fps", "0"])
    assert info.value.code == 2
    assert "--fps: must be positive" in capsys.readouterr().err


# -- the happy path on rendered frames ------------------------------------------------------------
RECORD_KEYS = {"frame", "t", "ok", "ambiguous", "centroid_mm", "direction", "tips_mm", "head_identified",
               "length_mm", "reprojection_px", "views", "reason"}


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[dict[str, object]]]:
    """Four frame pairs of robot 1 rendered by the loopback simulator (no vessel), with the true poses."""
    from appliance.robots import load_robots
    from drivers.loopback.xray_render import BiplaneRenderer, RobotBody, RobotPose, biplane_views

    root = tmp_path_factory.mktemp("rendered")
    robot = load_robots()[1]
    true_views = biplane_views(image_size=(384, 336))
    renderer = BiplaneRenderer(true_views, RobotBody(robot.length_mm, robot.diameter_mm, robot.tip_angle_deg,
                                                     robot.attenuation_per_mm), seed=3)
    Calibration.from_views(*(View(n, v.K, v.dist, v.R, v.t, v.image_size) for n, v in sorted(true_views.items()))
                           ).save(root / "calibration.yaml")
    truth = []
    for number in range(4):
        pose = RobotPose((-8.0 + 4.0 * number, 3.0, 2.0 - number), (0.6, -0.3, 0.5 + 0.1 * number))
        pair = renderer.render(pose)
        for plane in PLANES:
            write_frame(root, plane, 10 + number, pair.images[plane], fmt="tif" if plane == "q" else "png")
        truth.append({"frame": 10 + number, "centroid_mm": pose.centroid_mm, "direction": pose.direction})
    return root, truth


def test_tracks_rendered_frames(rendered: tuple[Path, list[dict[str, object]]],
                                capsys: pytest.CaptureFixture[str]) -> None:
    root, truth = rendered
    out_file = root / "postures.jsonl"
    code, out, err = _run(capsys, str(root), "--out", str(out_file), "--robot", "1")
    assert code == 0 and out == "" and err == ""
    records = [json.loads(line) for line in out_file.read_text().splitlines()]
    assert [r["frame"] for r in records] == [10, 11, 12, 13]
    for record, true in zip(records, truth):
        assert RECORD_KEYS <= set(record)
        assert record["robot"] == 1 and record["nominal_length_mm"] == 10.0
        assert record["ok"] is True
        # Loose bounds: they hold for any working recognition, and fail if a view, F or the
        # triangulation were wrong (a swapped or mirrored view puts the robot centimetres away).
        assert np.linalg.norm(np.array(record["centroid_mm"]) - true["centroid_mm"]) < 0.5
        cos = abs(float(np.dot(record["direction"], true["direction"])))
        assert np.degrees(np.arccos(min(cos, 1.0))) < 3.0
        assert record["reprojection_px"] < 3.0


def test_paper_estimator_runs_on_the_same_frames(rendered: tuple[Path, list[dict[str, object]]],
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    root, truth = rendered
    code, out, _ = _run(capsys, str(root), "--estimator", "paper")
    assert code == 0
    records = [json.loads(line) for line in out.splitlines()]
    assert len(records) == 4 and all(r["ok"] for r in records)
    errors = [np.linalg.norm(np.array(r["centroid_mm"]) - t["centroid_mm"]) for r, t in zip(records, truth)]
    assert max(errors) < 1.0


def test_unknown_robot(rendered: tuple[Path, list[dict[str, object]]], capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = _run(capsys, str(rendered[0]), "--robot", "99")
    assert code == 2 and "no robot with id 99" in err


# -- demo -------------------------------------------------------------------------------------------
def test_demo_writes_a_folder_that_track_reads(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "demo"
    code = main(["demo", "--out", str(out), "--frames", "3", "--robot", "7"])
    printed = capsys.readouterr().out
    assert code in (0, 1)  # 1 would mean a silent failure of the recognition, which the summary names
    assert "centroid" in printed and "silent failures" in printed
    assert sorted(p.name for p in (out / "p").iterdir()) == ["000000.png", "000001.png", "000002.png"]
    assert len((out / "postures.jsonl").read_text().splitlines()) == 3
    truth = [json.loads(line) for line in (out / "truth.jsonl").read_text().splitlines()]
    cal = Calibration.load(out / "calibration.yaml")
    assert cal.metadata["robot"] == 7
    # the truth projects inside both images: the scene is in the field of view
    for item in truth:
        for view in cal.views.values():
            assert view.contains(view.project(item["centroid_mm"]), margin_px=10).all()
    # and a second demo refuses to overwrite it
    assert main(["demo", "--out", str(out), "--frames", "1"]) == 2
    assert "already holds frames" in capsys.readouterr().err


def test_compare_scores_against_the_truth() -> None:
    from appliance.commands.demo import TrueFrame

    true = TrueFrame(0, np.zeros(3), np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 5.0]), np.array([0.0, 0.0, -5.0]))
    flipped = {"frame": 0, "ok": True, "ambiguous": False, "centroid_mm": [0.3, 0.0, 0.4],
               "direction": [0.0, np.sin(0.1), -np.cos(0.1)], "head_identified": False,
               "tips_mm": [[0.0, 0.0, -5.0], [0.0, 0.0, 5.0]]}
    result = compare([flipped, {"frame": 0, "ok": False, "ambiguous": False}], [true])
    assert result["counts"]["ok"] == 1 and result["counts"]["lost"] == 1
    assert result["centroid_mm"][0] == pytest.approx(0.5)
    assert result["axis_deg"][0] == pytest.approx(np.degrees(0.1))  # an unidentified head may point either way
    assert result["tips_mm"][0] == pytest.approx(0.0)
    wrong = dict(flipped, direction=[0.0, 1.0, 0.0])
    assert compare([wrong], [true])["silent"] == [0]


def test_progress_only_on_a_terminal(rendered: tuple[Path, list[dict[str, object]]],
                                     capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    import sys

    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    code, out, err = _run(capsys, str(rendered[0]))
    assert code == 0 and len(out.splitlines()) == 4
    assert "\rtrack: frame 13 (4/4)" in err and "tracked 4 frame pairs" in err
    assert "track:" not in out  # the records stay clean


# -- detector dark level ----------------------------------------------------------------------------
def test_dark_level_from_calibration_metadata_and_override(tmp_path: Path) -> None:
    from appliance.geometry import dark_level_of
    from appliance.errors import CalibrationError

    cal = _calibration()
    assert dark_level_of(cal) == 0.0  # no metadata: no offset assumed
    cal.metadata["detector"] = {"dark_level": 1000}
    cal.save(tmp_path / "calibration.yaml")
    loaded = Calibration.load(tmp_path / "calibration.yaml")
    assert dark_level_of(loaded) == 1000.0
    assert dark_level_of(loaded, 250.0) == 250.0  # --dark-level wins
    loaded.metadata["detector"] = {"dark_level": -3}
    with pytest.raises(CalibrationError, match=r"calibration.yaml: metadata.detector.dark_level"):
        dark_level_of(loaded)
    loaded.metadata["detector"] = "flat panel"
    with pytest.raises(CalibrationError, match=r"metadata.detector: expected a mapping"):
        dark_level_of(loaded)


def test_dark_level_reaches_the_tracker(rendered: tuple[Path, list[dict[str, object]]],
                                        capsys: pytest.CaptureFixture[str],
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    import appliance.recognition as recognition

    seen: list[float] = []
    original = recognition.PostureTracker.__init__

    def spy(self: object, calibration: Calibration, settings: object = None, **kw: object) -> None:
        seen.append(getattr(settings, "dark_level", 0.0))
        original(self, calibration, settings, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(recognition.PostureTracker, "__init__", spy)
    assert _run(capsys, str(rendered[0]), "--dark-level", "1000")[0] == 0
    assert _run(capsys, str(rendered[0]))[0] == 0
    assert seen == [1000.0, 0.0]  # the rendered folder's calibration has no detector metadata
    with pytest.raises(SystemExit) as info:
        main(["track", str(rendered[0]), "--dark-level", "-5"])
    assert info.value.code == 2 and "--dark-level: must be a finite number >= 0" in capsys.readouterr().err


def test_demo_saves_the_detector_dark_level(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from drivers.loopback.xray_render import ImagingSettings

    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--frames", "2", "--robot", "4"]) in (0, 1)
    capsys.readouterr()
    cal = Calibration.load(out / "calibration.yaml")
    assert cal.metadata["detector"]["dark_level"] == ImagingSettings().dark_level
