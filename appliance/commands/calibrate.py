"""``appliance calibrate``: calibrate both X-ray views from one image pair of a bead phantom.

    appliance calibrate --phantom beads.csv --p p.tif --q q.tif --initial approx.yaml --out calibration.yaml

Correspondence between blobs and phantom beads comes from ``--initial`` (a rough calibration file:
nominal source distances and angles of the equipment; or ``--initial-mayacam P.txt Q.txt``) or, as in
XMALab, from reference beads marked by hand: ``--ref-p ID:u,v`` (repeat it; 6 or more beads per view,
or 4-5 with ``--focal-px``), where ID is the bead's id in the phantom file (its 1-based row when the
file has no id column) and u,v the pixel of its centre (column, row; 0,0 the centre of the top-left
pixel). Marked beads need not be the reference beads of an XMALab references file.

Writes the calibration file (architecture.md contract, with RMS, inliers, date in ``metadata``), a
report directory (per-bead residuals CSV, a PNG with detected beads and reprojections, a summary) and,
with ``--mayacam DIR``, MayaCam 2.0 files for XMALab and Autoscoper.

In simulation, ``appliance calibrate --simulate DIR [--config sim.yaml]`` first puts the simulated
100 mm bead cube in the simulated fluoroscope (the session's true geometry), grabs one pair through
the loopback grabber, writes ``beads.csv``, ``p.tif``, ``q.tif``, a rough ``initial.yaml`` (the design
geometry turned and moved by ``--simulate-error``) and ``truth.yaml`` into DIR, calibrates them, and
prints how far the result is from the truth. A simulation session can then use
``calibration: {source: file, file: DIR/calibration.yaml}``.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

NAME = "calibrate"
HELP = "calibrate the two X-ray views from images of a bead phantom (writes calibration.yaml and a report)"


def _marked(text: str) -> tuple[str, tuple[float, float]]:
    try:
        bead, uv = text.split(":", 1)
        u, v = (float(x) for x in uv.split(","))
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"expected ID:u,v (e.g. 12:403.5,220.0), got {text!r}") from err
    if not bead.strip():
        raise argparse.ArgumentTypeError(f"expected ID:u,v with a bead id before the colon, got {text!r}")
    return bead.strip(), (u, v)


def _error(text: str) -> tuple[float, float]:
    try:
        deg, mm = (float(v) for v in text.split(","))
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"expected DEG,MM (e.g. 1.5,3), got {text!r}") from err
    return deg, mm


def simulate_phantom(directory: Path, config: Path | None, error: tuple[float, float]) -> dict[str, Path]:
    """Render the simulated bead cube through the loopback grabber; write the inputs of a calibration."""
    import numpy as np
    import tifffile

    from appliance.device_factory import perturbed_calibration
    from appliance.errors import InputDataError
    from appliance.geometry import Calibration, View
    from appliance.session_config import load_session
    from appliance.xray_calibration.phantom import make_cube_phantom, write_phantom
    from drivers.loopback.loopback_grabber import LoopbackFrameSource, LoopbackScene
    from drivers.loopback.xray_render import BiplaneRenderer, ImagingSettings, biplane_views

    session = load_session(config)
    if not session.config.is_simulation:
        raise InputDataError(f"{session.source}: --simulate needs a simulation session (loopback devices)")
    imaging = session.config.imaging
    true_views = biplane_views(sod_mm=imaging.sod_mm, sdd_mm=imaging.sdd_mm, fov_mm=imaging.fov_mm,
                               image_size=imaging.image_size, separation_deg=imaging.separation_deg,
                               elevation_deg=imaging.elevation_deg)
    phantom = make_cube_phantom()
    renderer = BiplaneRenderer(true_views, None, beads=(phantom.points_mm, 1.0, 2.0), seed=session.config.simulation.seed,
                               settings=ImagingSettings(photons_per_pixel=imaging.photons_per_pixel))
    scene = LoopbackScene(renderer, lambda t: None, rate_hz=imaging.fps, exposure_s=imaging.exposure_ms / 1000.0)
    directory.mkdir(parents=True, exist_ok=True)
    paths = {"phantom": write_phantom(directory / "beads.csv", phantom)}
    for plane in ("p", "q"):
        with LoopbackFrameSource(scene, plane, seed=session.config.simulation.seed) as source:
            paths[plane] = directory / f"{plane}.tif"
            tifffile.imwrite(paths[plane], np.asarray(source.read(timeout_s=5.0).image))
    truth = Calibration.from_views(*(View(n, v.K, v.dist, v.R, v.t, v.image_size) for n, v in sorted(true_views.items())),
                                   metadata={"source": f"true geometry of the simulated fluoroscope ({session.source})"})
    paths["truth"] = truth.save(directory / "truth.yaml")
    paths["initial"] = perturbed_calibration(true_views, error[0], error[1], seed=1).save(directory / "initial.yaml")
    return paths


def _compare(calibration: Any, truth_path: Path) -> str:
    import cv2
    import numpy as np

    from appliance.geometry import Calibration

    truth = Calibration.load(truth_path)
    lines = [f"{'view':<5}{'focal error %':>15}{'rotation deg':>14}{'source mm':>11}{'t mm':>8}  (vs {truth_path})"]
    for name in ("p", "q"):
        ours, true = calibration.views[name], truth.views[name]
        focal = float(np.max(np.abs(np.diag(ours.K)[:2] / np.diag(true.K)[:2] - 1))) * 100
        rotation = float(np.degrees(np.linalg.norm(cv2.Rodrigues(ours.R @ true.R.T)[0])))
        lines.append(f"{name:<5}{focal:>15.4f}{rotation:>14.4f}{np.linalg.norm(ours.source_mm - true.source_mm):>11.3f}"
                     f"{np.linalg.norm(ours.t - true.t):>8.3f}")
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--phantom", type=Path, metavar="CSV",
                        help="bead coordinates (mm): x,y,z or id,x,y,z per line, optional header; XMALab "
                             "frame-specification CSV works as is")
    parser.add_argument("--references", type=Path, metavar="FILE",
                        help="XMALab references file (<id> <name> per line), listed in the report")
    parser.add_argument("--p", type=Path, metavar="IMG", help="image of the phantom in plane p")
    parser.add_argument("--q", type=Path, metavar="IMG", help="image of the phantom in plane q")
    parser.add_argument("--initial", type=Path, metavar="YAML",
                        help="rough calibration file used to match beads automatically")
    parser.add_argument("--initial-mayacam", nargs=2, type=Path, metavar=("P_TXT", "Q_TXT"),
                        help="rough calibration as two MayaCam 2.0 files instead of --initial")
    parser.add_argument("--ref-p", action="append", type=_marked, default=[], metavar="ID:u,v",
                        help="a marked bead in image p (repeat; >= 6, or >= 4 with --focal-px)")
    parser.add_argument("--ref-q", action="append", type=_marked, default=[], metavar="ID:u,v",
                        help="a marked bead in image q (repeat)")
    parser.add_argument("--focal-px", type=float, metavar="F", help="focal length guess (px) for 4-5 marked beads")
    parser.add_argument("--out", type=Path, metavar="YAML",
                        help="calibration file to write (default: ./calibration.yaml, or DIR/calibration.yaml "
                             "with --simulate)")
    parser.add_argument("--report-dir", type=Path, metavar="DIR",
                        help="where the report goes (default: <out without .yaml>_report/)")
    parser.add_argument("--mayacam", type=Path, metavar="DIR", help="also export MayaCam 2.0 files to DIR")
    parser.add_argument("--distortion", default="none", choices=("none", "k1", "k1k2", "k1k2p", "full"),
                        help="OpenCV distortion terms to estimate (default none: a flat-panel detector)")
    parser.add_argument("--square-pixels", action="store_true", help="force fx = fy")
    parser.add_argument("--fix-intrinsics", action="store_true",
                        help="keep K and dist of --initial; refine only the poses (after the C-arm moved)")
    parser.add_argument("--bead-tolerance", type=float, default=0.0, metavar="MM",
                        help="jointly refine both views and the beads within this tolerance (default 0: beads exact)")
    parser.add_argument("--plate-p", type=Path, metavar="IMG",
                        help="image-intensifier view p: image of a perforated plate; its distortion map is fitted, "
                             "saved next to --out and applied to the bead centres")
    parser.add_argument("--plate-q", type=Path, metavar="IMG", help="the same for view q")
    parser.add_argument("--simulate", type=Path, metavar="DIR",
                        help="simulation: render the bead cube through the loopback grabber into DIR and calibrate it")
    parser.add_argument("--config", type=Path, metavar="YAML", help="session file for --simulate (default: sim.yaml)")
    parser.add_argument("--simulate-error", type=_error, default=(1.5, 3.0), metavar="DEG,MM",
                        help="how far --simulate's initial geometry is from the truth (default 1.5,3)")
    parser.add_argument("--max-bead-radius-px", type=float, default=15.0, metavar="PX",
                        help="largest bead radius in the images (default 15)")


def read_image(path: Path) -> Any:
    """A 2D grey image from PNG/TIFF (any bit depth) or DICOM (first frame)."""
    import cv2
    import numpy as np

    from appliance.errors import InputDataError

    if not path.is_file():
        raise InputDataError(f"{path}: image file not found")
    suffix = path.suffix.lower()
    try:
        if suffix in (".dcm", ".dicom"):
            import pydicom
            pixels = pydicom.dcmread(str(path)).pixel_array
        elif suffix in (".tif", ".tiff"):
            import tifffile
            pixels = tifffile.imread(str(path))
        else:
            pixels = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    except Exception as err:  # noqa: BLE001 -- any decoder failure is a bad input file; say which
        raise InputDataError(f"{path}: cannot decode image ({err})") from err
    if pixels is None:
        raise InputDataError(f"{path}: not an image this program can read (PNG, TIFF or DICOM)")
    pixels = np.asarray(pixels)
    if pixels.ndim == 3 and pixels.shape[-1] not in (3, 4):
        pixels = pixels[0]  # a multi-frame file: the first frame
    if pixels.ndim == 3:
        pixels = pixels[..., :3].mean(axis=2)
    return pixels


def run(args: argparse.Namespace) -> int:
    from appliance.errors import InputDataError
    from appliance.geometry import Calibration
    from appliance.xray_calibration.cube import CubeOptions, calibrate_cube, to_calibration
    from appliance.xray_calibration.mayacam import export_calibration, import_calibration
    from appliance.xray_calibration.phantom import load_phantom
    from appliance.xray_calibration.report import summary_text, write_report

    def say(message: str) -> None:
        print(f"calibrate: {message}", file=sys.stderr, flush=True)

    if args.initial and args.initial_mayacam:
        raise InputDataError("give --initial or --initial-mayacam, not both")
    truth_path = None
    if args.simulate is not None:
        say(f"simulation: rendering the bead cube through the loopback grabber into {args.simulate}")
        made = simulate_phantom(args.simulate, args.config, args.simulate_error)
        args.phantom = args.phantom or made["phantom"]
        args.p, args.q = args.p or made["p"], args.q or made["q"]
        if not (args.ref_p or args.ref_q or args.initial_mayacam):
            args.initial = args.initial or made["initial"]
        args.out = args.out or args.simulate / "calibration.yaml"
        truth_path = made["truth"]
    missing = [flag for flag, value in (("--phantom", args.phantom), ("--p", args.p), ("--q", args.q)) if value is None]
    if missing:
        raise InputDataError(f"missing {', '.join(missing)} (or use --simulate DIR in simulation)")
    args.out = args.out or Path("calibration.yaml")
    phantom = load_phantom(args.phantom, args.references)
    images = {"p": read_image(args.p), "q": read_image(args.q)}
    initial = None
    if args.initial:
        initial = Calibration.load(args.initial)
    elif args.initial_mayacam:
        initial = import_calibration(*args.initial_mayacam)
    references = {"p": dict(args.ref_p), "q": dict(args.ref_q)}
    corrections = {}
    correction_files = {}
    for name, plate in (("p", args.plate_p), ("q", args.plate_q)):
        if plate is not None:
            from appliance.xray_calibration.distortion import correction_from_image
            say(f"view {name}: fitting the image-intensifier distortion map from {plate}")
            corrections[name] = correction_from_image(read_image(plate))
            correction_files[name] = str(corrections[name].save(args.out.with_name(f"{args.out.stem}_distortion_{name}.yaml")))
    options = CubeOptions(distortion=args.distortion, square_pixels=args.square_pixels,
                          max_radius_px=args.max_bead_radius_px, bead_tolerance_mm=args.bead_tolerance,
                          focal_guess_px=args.focal_px, fix_intrinsics=args.fix_intrinsics)
    result = calibrate_cube(images, phantom, initial=initial, references=references, options=options, progress=say,
                            corrections=corrections)
    extra: dict[str, Any] = {"images": {"p": str(args.p), "q": str(args.q)}}
    if correction_files:
        # The views are pinhole views of corrected pixels: trackers must apply these maps first.
        extra["point_correction"] = correction_files
    if phantom.references:
        extra["phantom_references"] = dict(phantom.references)
    calibration = to_calibration(result, extra)
    out = calibration.save(args.out)
    report_dir = args.report_dir or out.with_name(out.stem + "_report")
    paths = write_report(report_dir, images, result)
    print(summary_text(result))
    print(f"calibration written to {out}")
    print(f"report: {paths['png']}, {paths['csv']}")
    if args.mayacam:
        mayacam = export_calibration(calibration, args.mayacam)
        print(f"MayaCam 2.0: {mayacam['p']}, {mayacam['q']}")
    if truth_path is not None:
        print(_compare(calibration, truth_path))
    return 0
