"""``appliance calibrate`` end to end on rendered phantom images written to disk like a bench's."""
from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile

from appliance.cli import main
from appliance.geometry import Calibration
from appliance.xray_calibration.mayacam import read_mayacam
from appliance.xray_calibration.phantom import Phantom, write_phantom
from drivers.loopback.xray_render import TrueView


@pytest.fixture(scope="module")
def bench(tmp_path_factory: pytest.TempPathFactory, cube_images: dict[str, np.ndarray], cube: Phantom,
          nominal_calibration: Calibration) -> Path:
    folder = tmp_path_factory.mktemp("bench")
    cv2.imwrite(str(folder / "p.png"), cube_images["p"])
    tifffile.imwrite(folder / "q.tif", cube_images["q"])
    # XMALab's frame-specification layout: a header line, then x,y,z rows (ids = row numbers).
    (folder / "FrameSpec.csv").write_text("x y z\n" + "\n".join(",".join(f"{c:.6f}" for c in row)
                                                              for row in cube.points_mm) + "\n")
    write_phantom(folder / "beads.csv", cube)
    nominal_calibration.save(folder / "approx.yaml")
    return folder


def test_with_initial_geometry_writes_calibration_report_and_mayacam(bench: Path, true_views: dict[str, TrueView],
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    out = bench / "out" / "calibration.yaml"
    out.parent.mkdir()
    status = main(["calibrate", "--phantom", str(bench / "FrameSpec.csv"), "--p", str(bench / "p.png"),
                   "--q", str(bench / "q.tif"), "--initial", str(bench / "approx.yaml"), "--out", str(out),
                   "--mayacam", str(bench / "out" / "mayacam")])
    captured = capsys.readouterr()
    assert status == 0, captured.err
    assert "view p: detecting beads" in captured.err  # progress
    assert "reprojection" in captured.err and f"calibration written to {out}" in captured.out
    calibration = Calibration.load(out)
    for name in ("p", "q"):
        assert np.linalg.norm(calibration.views[name].source_mm - true_views[name].source_mm) < 0.5
        assert calibration.metadata[f"reprojection_rms_px_{name}"] < 0.3
    report = bench / "out" / "calibration_report"
    image = cv2.imread(str(report / "calibration_report.png"))
    assert image.shape[0] == 448 and image.shape[1] > 2 * 512
    with (report / "calibration_residuals.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert {r["view"] for r in rows} == {"p", "q"}
    residuals = [float(r["residual_px"]) for r in rows if r["residual_px"] != "outlier"]
    assert len(residuals) >= 80 and max(residuals) < 1.0
    np.testing.assert_array_equal(read_mayacam(bench / "out" / "mayacam" / "camera_p.txt", "p").P, calibration.p.P)


def test_with_marked_reference_beads(bench: Path, cube: Phantom, true_views: dict[str, TrueView]) -> None:
    args = ["calibrate", "--phantom", str(bench / "beads.csv"), "--p", str(bench / "p.png"), "--q", str(bench / "q.tif"),
            "--out", str(bench / "marked.yaml")]
    for name in ("p", "q"):
        for bead in cube.references:
            u, v = true_views[name].project(cube.points_mm[cube.index(bead)][None])[0] + 0.4
            args += [f"--ref-{name}", f"{bead}:{u:.1f},{v:.1f}"]
    assert main(args) == 0
    calibration = Calibration.load(bench / "marked.yaml")
    assert np.linalg.norm(calibration.q.source_mm - true_views["q"].source_mm) < 0.5


@pytest.mark.parametrize("change, message", [
    (lambda b: ["--phantom", str(b / "missing.csv")], "missing.csv: file not found"),
    (lambda b: ["--p", str(b / "beads.csv")], "beads.csv: not an image"),
    (lambda b: ["--initial", str(b / "beads.csv")], "beads.csv"),
    (lambda b: ["--ref-p", "7:1,2", "--initial", str(b / "nothing.yaml")], "nothing.yaml: file not found"),
])
def test_bad_input_exits_2_with_a_named_cause(bench: Path, change, message: str,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    base = {"--phantom": str(bench / "beads.csv"), "--p": str(bench / "p.png"), "--q": str(bench / "q.tif"),
            "--initial": str(bench / "approx.yaml"), "--out": str(bench / "bad.yaml")}
    extra = change(bench)
    for key, value in zip(extra[::2], extra[1::2]):
        if key in base:
            base[key] = value
    args = ["calibrate"] + [x for pair in base.items() for x in pair]
    if "--ref-p" in extra:
        args += ["--ref-p", "7:1,2"]
    assert main(args) == 2
    assert message in capsys.readouterr().err


def test_malformed_marked_bead_option(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["calibrate", "--phantom", "b.csv", "--p", "p.png", "--q", "q.png", "--ref-p", "7:12"])
    assert "expected ID:u,v" in capsys.readouterr().err


def test_simulate_renders_through_the_loopback_grabber_and_recovers_the_truth(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["calibrate", "--simulate", str(tmp_path / "sim")]) == 0
    out = capsys.readouterr().out
    assert "vs " in out and "truth.yaml" in out
    truth = Calibration.load(tmp_path / "sim" / "truth.yaml")
    ours = Calibration.load(tmp_path / "sim" / "calibration.yaml")
    initial = Calibration.load(tmp_path / "sim" / "initial.yaml")
    for name in ("p", "q"):
        assert np.linalg.norm(ours.views[name].source_mm - truth.views[name].source_mm) < 0.5
        assert np.linalg.norm(initial.views[name].t - truth.views[name].t) > 2.0  # it started far off
    assert (tmp_path / "sim" / "calibration_report" / "calibration_report.png").is_file()
