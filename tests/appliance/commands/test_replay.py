"""``appliance replay``: re-running recognition on a recording reproduces what the loop recorded, a
recording whose postures disagree with its frames is caught frame by frame, tolerances set the exit
status, and bad recordings end with status 2 and a message naming the file."""
from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from appliance.cli import main
from appliance.commands.replay import compare
from appliance.geometry import Calibration, View
from appliance.recognition import PostureTracker
from appliance.recording import Recorder
from drivers.loopback.xray_render import BiplaneRenderer, ImagingSettings, RobotBody, RobotPose, biplane_views

FRAMES = 8
LOST_FRAME = 6  # the robot is out of the picture in this frame


@pytest.fixture(scope="module")
def session() -> tuple[Calibration, list[tuple[int, float, np.ndarray, np.ndarray, dict[str, Any]]]]:
    """A short live session: rendered pairs of a robot moving along x and what the live tracker made of them."""
    views = biplane_views(image_size=(160, 140), fov_mm=(80.0, 70.0))
    calibration = Calibration.from_views(*(View(n, v.K, v.dist, v.R, v.t, v.image_size)
                                           for n, v in sorted(views.items())))
    renderer = BiplaneRenderer(views, RobotBody(10.0, 2.0, 20.0, 1.0), settings=ImagingSettings(), seed=3)
    tracker = PostureTracker(calibration)
    direction = np.array([0.3, 0.5, 0.81]) / np.linalg.norm([0.3, 0.5, 0.81])
    frames = []
    for frame in range(FRAMES):
        t = 10.0 + frame / 30.0
        pose = None if frame == LOST_FRAME else RobotPose(np.array([3.0 + 0.5 * frame, -4.0, 5.0]), direction)
        pair = renderer.render(pose)
        posture = tracker.process(pair.images["p"], pair.images["q"], frame=frame, t=t).to_record()
        frames.append((frame, t, pair.images["p"], pair.images["q"], posture))
    assert [f[4]["ok"] for f in frames] == [frame != LOST_FRAME for frame in range(FRAMES)]
    return calibration, frames


def _record(path: Path, calibration: Calibration, frames: list, *, frames_every: int = 1,
            tamper: dict[int, dict[str, Any]] | None = None, images: bool = True,
            config: dict[str, Any] | None = None) -> Path:
    with Recorder.create(path, config=config or {"name": "replay test"}, calibration=calibration.to_dict(),
                         frames_every=frames_every, fsync=False, threaded=False) as rec:
        for frame, t, image_p, image_q, posture in frames:
            posture = copy.deepcopy(posture)
            posture.update((tamper or {}).get(frame, {}))
            rec.write_posture(t, posture)
            rec.write_currents(t, [0.0] * 3, [0.0] * 3)
            if images:
                rec.write_frames(t, frame, image_p, image_q)
            rec.write_timing(t, frame, {"recognition": 1000.0})
    return path


def _replay(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, list[dict[str, Any]], str]:
    code = main(["replay", *argv])
    captured = capsys.readouterr()
    return code, [json.loads(line) for line in captured.out.splitlines()], captured.err


def test_replay_reproduces_the_live_postures(session: tuple, tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    calibration, frames = session
    path = _record(tmp_path / "live.mcap", calibration, frames)
    summary_path = tmp_path / "summary.json"
    code, lines, err = _replay(capsys, str(path), "--summary", str(summary_path), "--max-centroid-mm", "0.001",
                               "--max-axis-deg", "0.01", "--max-state-changes", "0")
    assert code == 0, err
    assert [line["frame"] for line in lines] == list(range(FRAMES))
    for line in lines:
        assert line["state_changed"] is False
        if line["frame"] == LOST_FRAME:
            assert line["recorded_state"] == line["replayed_state"] == "lost" and line["centroid_diff_mm"] is None
        else:
            assert line["replayed_state"] == "ok" and line["centroid_diff_mm"] < 1e-3
            assert line["replayed"]["frame"] == line["frame"] and line["replayed"]["views"]["p"]["pixel_count"] > 0
    summary = json.loads(summary_path.read_text())
    assert summary["frames_replayed"] == summary["frames_compared"] == FRAMES
    assert summary["centroid_diff_mm"]["n"] == FRAMES - 1 and summary["state_changes"] == 0
    assert summary["replayed_states"] == {"ok": FRAMES - 1, "lost": 1}
    assert f"replayed {FRAMES} recorded frame pairs" in err and "state changed (ok/ambiguous/lost) in 0 frames" in err


def test_replay_places_the_recorded_robots_body(session: tuple, tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    # A session that tracked robot 1 (config robot.id) recorded postures placed by its body: the replay gives the
    # tracker that robot too and reproduces them; without it (a model-free replay) the centroids differ.
    from appliance.robots import load_robots

    calibration, frames = session
    tracker = PostureTracker(calibration, body=load_robots()[1])
    placed = [(frame, t, p, q, tracker.process(p, q, frame=frame, t=t).to_record()) for frame, t, p, q, _ in frames]
    moved = [abs(np.subtract(a[4]["centroid_mm"], b[4]["centroid_mm"])).max() for a, b in zip(frames, placed)
             if a[4]["ok"]]
    assert max(moved) > 1e-3  # the body moved the centroids (else this test shows nothing)
    path = _record(tmp_path / "robot1.mcap", calibration, placed, config={"name": "replay test", "robot": {"id": 1}})
    code, lines, err = _replay(capsys, str(path), "--max-centroid-mm", "0.001", "--max-state-changes", "0")
    assert code == 0, err
    path = _record(tmp_path / "unnamed.mcap", calibration, placed)
    code, lines, err = _replay(capsys, str(path), "--max-centroid-mm", "0.001")
    assert code == 1


def test_disagreeing_recording_is_caught(session: tuple, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    calibration, frames = session
    shifted = [c + d for c, d in zip(frames[2][4]["centroid_mm"], (1.5, 0.0, 0.0))]
    flipped = [-c for c in frames[5][4]["direction"]]
    tamper = {2: {"centroid_mm": shifted}, 4: {"ok": False, "reason": "lost"}, 5: {"direction": flipped}}
    path = _record(tmp_path / "tampered.mcap", calibration, frames, tamper=tamper)
    code, lines, err = _replay(capsys, str(path), "--max-centroid-mm", "1.0")
    assert code == 1
    assert "centroid difference 1.5 mm at frame 2 exceeds 1 mm" in err
    by_frame = {line["frame"]: line for line in lines}
    assert by_frame[2]["centroid_diff_mm"] == pytest.approx(1.5, abs=1e-3)
    assert by_frame[4]["state_changed"] and by_frame[4]["recorded_state"] == "lost"
    assert by_frame[5]["direction_flipped"] is True and by_frame[5]["axis_diff_deg"] < 0.01
    assert "state changed (ok/ambiguous/lost) in 1 frames: {'lost->ok': 1}" in err
    assert "head and tail swapped in 1 frames" in err
    code, _, err = _replay(capsys, str(path), "--max-state-changes", "0")
    assert code == 1 and "1 frames changed state (allowed: 0)" in err


def test_decimated_and_cut_off_recordings(session: tuple, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    calibration, frames = session
    path = _record(tmp_path / "every3.mcap", calibration, frames, frames_every=3)
    code, lines, _ = _replay(capsys, str(path))
    assert code == 0 and [line["frame"] for line in lines] == [0, 3, 6]
    assert all(not line["state_changed"] for line in lines)
    data = _record(tmp_path / "full.mcap", calibration, frames).read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:len(data) * 2 // 3])
    out = tmp_path / "out.jsonl"
    code, _, err = _replay(capsys, str(cut), "--out", str(out))
    replayed = [json.loads(line)["frame"] for line in out.read_text().splitlines()]
    assert code == 0 and 2 <= len(replayed) < FRAMES and replayed == list(range(len(replayed)))
    assert "the recording was not closed" in err and "replayed up to its last complete frame" in err


def test_bad_recordings_exit_2_naming_the_file(session: tuple, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    calibration, frames = session
    code, lines, err = _replay(capsys, str(tmp_path / "nowhere.mcap"))
    assert code == 2 and not lines and f"appliance replay: error: {tmp_path / 'nowhere.mcap'}: file not found" in err
    (tmp_path / "notes.mcap").write_text("not a recording\n")
    code, _, err = _replay(capsys, str(tmp_path / "notes.mcap"))
    assert code == 2 and "notes.mcap: not an MCAP recording" in err
    path = _record(tmp_path / "no_images.mcap", calibration, frames, images=False)
    code, lines, err = _replay(capsys, str(path))
    assert code == 2 and not lines and "no_images.mcap: the recording has no frames to replay" in err
    bad = calibration.to_dict()
    bad["views"]["q"]["K"][2] = [0.0, 0.0, 2.0]
    with Recorder.create(tmp_path / "bad_cal.mcap", config={}, calibration=bad, fsync=False) as rec:
        rec.write_frames(0.0, 0, frames[0][2], frames[0][3])
    code, _, err = _replay(capsys, str(tmp_path / "bad_cal.mcap"))
    assert code == 2 and "bad_cal.mcap: /calibration: views.q.K" in err
    code, _, err = _replay(capsys, str(path), "--out", str(tmp_path / "missing" / "dir" / "x.jsonl"))
    assert code == 2 and "cannot write the comparison" in err


def test_compare_unknowns_stay_null() -> None:
    replayed = {"frame": 3, "t": 0.1, "ok": True, "ambiguous": True, "centroid_mm": [1.0, 2.0, 3.0],
                "direction": None, "head_identified": False}
    line = compare({"frame": 3, "ok": True, "centroid_mm": [1.0, 2.0, 4.0], "direction": [0.0, 0.0, 1.0]}, replayed)
    assert line["state_changed"] and line["recorded_state"] == "ok" and line["replayed_state"] == "ambiguous"
    assert line["centroid_diff_mm"] == pytest.approx(1.0) and line["axis_diff_deg"] is None
    assert compare(None, replayed)["state_changed"] is None
    axis = compare({"ok": True, "direction": [0.0, 1.0, 0.0], "head_identified": False},
                   {"frame": 1, "ok": True, "direction": [0.0, -1.0, 1e-9], "head_identified": True})
    assert axis["axis_diff_deg"] == pytest.approx(0.0, abs=1e-6) and axis["direction_flipped"] is None
