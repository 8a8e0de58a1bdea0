"""``appliance grab``: record biplane pairs from two frame sources into a biplane frame folder, or list grabbers.

    appliance grab --source usb://1209:0001?serial=XRG-P --source usb://1209:0001?serial=XRG-Q --frames 300 --out DIR
    appliance grab --source v4l2:///dev/video0?plane=p --source v4l2:///dev/video1?plane=q --match time --out DIR
    appliance grab --source file://OLD?plane=p --source file://OLD?plane=q --out NEW      (re-record a folder)
    appliance grab --source loopback://?plane=p --source loopback+usb://?plane=q --frames 60
    appliance grab --list

The folder (``DIR/p``, ``DIR/q``, 16-bit PNG or TIFF) is what ``appliance track DIR`` reads;
``DIR/timestamps.csv`` keeps every frame's device and host times and exposure so that file playback can
replay the recorded timing. The summary gives the pair rate, each source's frames, drops, corrupt
frames and timeouts, unpaired frames per plane and the p-q skew. The folder contract is 16-bit, so
8-bit sources (a video capture card, a video file) are written scaled by 256 (value << 8).

Loopback sources (fakes, for trying the command without hardware) render one robot of the catalogue
moving slowly through the field of the true simulated views: ``loopback://`` serves the frames directly;
``loopback+usb://`` serves them through the fake USB grabber, read by the real USB driver through pyusb.
Scene options come from the first loopback URL (``rate``, ``size=WxH``, ``robot``, ``exposure_ms``,
``interleaved``, ``seed``); per source: ``plane``, ``jitter_ms``, ``drop``, ``corrupt``. For loopback
runs the true calibration is saved beside the frames.
"""
from __future__ import annotations

import argparse
import csv
import sys
import time
from pathlib import Path
from typing import Any
from appliance.commands._common import count, prepare_frame_folder

NAME = "grab"
HELP = "record biplane frame pairs from two frame sources into a biplane frame folder, or list grabbers"





def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--list", action="store_true", help="list USB grabbers and V4L2 devices, then exit")
    parser.add_argument("--source", metavar="URL", action="append", default=[],
                        help="a frame source, twice (plane p and plane q): usb://VID:PID[?serial=..], "
                             "v4l2:///dev/videoN?plane=.., file://DIR?plane=.., loopback://?plane=..")
    parser.add_argument("--frames", metavar="N", type=count, default=100, help="pairs to record (default 100)")
    parser.add_argument("--out", metavar="DIR", type=Path,
                        help="biplane folder to write (new or empty); without it the pairs are only counted")
    parser.add_argument("--format", choices=("png", "tif"), default="png", help="image format (default png)")
    parser.add_argument("--match", choices=("number", "time"), default="number",
                        help="pair by frame number (grabbers on one trigger) or by host arrival time (default number)")
    parser.add_argument("--max-skew-ms", type=float, default=5.0, metavar="MS",
                        help="largest p-q time difference for --match time (default 5 ms)")
    parser.add_argument("--timeout", type=float, default=5.0, metavar="S",
                        help="give up when no pair arrives for this long (default 5 s)")


def run(args: argparse.Namespace) -> int:
    from appliance.errors import ConfigError

    if args.list:
        return _list()
    if len(args.source) != 2:
        raise ConfigError(f"give exactly two --source URLs (planes p and q), got {len(args.source)}")
    return _grab(args)


def _list() -> int:
    from drivers.errors import DeviceError
    from drivers.usb_grabber import list_grabbers
    from drivers.v4l2_source import list_v4l2_devices, v4l2_backend_available

    print("USB frame grabbers:")
    try:
        grabbers = list_grabbers()
        for info in grabbers:
            serial = info.serial or "(serial unreadable: permissions? see config/udev/99-xray-grabber.rules)"
            print(f"  {info.url:40s} bus {info.bus} address {info.address}  serial {serial}")
        if not grabbers:
            print("  none")
    except DeviceError as err:
        print(f"  cannot look: {err}")
    print("V4L2 devices:" + ("" if v4l2_backend_available() else " (this OpenCV has no V4L2 backend)"))
    devices = list_v4l2_devices()
    for device in devices:
        print(f"  {device.url:40s} {device.name or ''}")
    if not devices:
        print("  none")
    return 0


def _build_sources(urls: list[str]) -> tuple[list[Any], Any]:
    """Frame sources for the URLs; loopback ones share one scene. Returns (sources, scene or None)."""
    from drivers.frame_source import open_source, parse_source_url

    parsed = [parse_source_url(url) for url in urls]
    scene = None
    sources = []
    for url in parsed:
        if url.scheme in ("loopback", "loopback+usb"):
            if scene is None:
                scene = _loopback_scene(url)
            sources.append(_loopback_source(url, scene))
        else:
            sources.append(open_source(url.text))
    return sources, scene


def _loopback_scene(url: Any) -> Any:
    import numpy as np

    from appliance.errors import ConfigError
    from appliance.robots import load_robots, select_robot
    from drivers.frame_source import query_bool, query_float, query_int
    from drivers.loopback.loopback_grabber import LoopbackScene, scripted_trajectory
    from drivers.loopback.xray_render import BiplaneRenderer, RobotBody, biplane_views

    size = url.take("size", "768x672")
    try:
        width, height = (int(v) for v in size.lower().split("x"))
    except ValueError:
        raise ConfigError(f"{url.text}: size={size!r}: expected WxH, e.g. 768x672") from None
    robot = select_robot(load_robots(), query_int(url, "robot", 2) or 2)
    body = RobotBody(robot.length_mm, robot.diameter_mm, robot.tip_angle_deg, robot.attenuation_per_mm)
    views = biplane_views(image_size=(width, height))
    renderer = BiplaneRenderer(views, body, seed=query_int(url, "seed", 1))
    # A slow glide across the field, tilted so that its axis stays out of the epipolar planes.
    direction = np.array([1.0, 0.4, 0.5])
    provider = scripted_trajectory([0.0, 20.0], [[-15.0, -5.0, -5.0], [15.0, 5.0, 5.0]], [direction, direction])
    scene = LoopbackScene(renderer, provider, rate_hz=query_float(url, "rate", 30.0) or 30.0,
                          exposure_s=(query_float(url, "exposure_ms", 5.0) or 5.0) / 1000.0,
                          interleaved=query_bool(url, "interleaved", False))
    scene.true_views = views  # type: ignore[attr-defined]  (saved as the calibration of loopback runs)
    scene.robot_id = robot.id  # type: ignore[attr-defined]
    return scene


def _loopback_source(url: Any, scene: Any) -> Any:
    from drivers.frame_source import query_float, query_int
    from drivers.loopback.loopback_grabber import LoopbackFrameSource, make_usb_backend
    from drivers.usb_grabber import usb_source_from_url

    plane = url.take("plane") or "p"
    if url.scheme == "loopback+usb":
        backend = make_usb_backend(scene, planes=(plane,), seed=query_int(url, "seed", None))
        from drivers.frame_source import parse_source_url
        return usb_source_from_url(parse_source_url(f"usb://1209:0001?serial=XRG-{plane.upper()}"), backend=backend)
    return LoopbackFrameSource(scene, plane, jitter_s=(query_float(url, "jitter_ms", 0.0) or 0.0) / 1000.0,
                               drop_probability=query_float(url, "drop", 0.0) or 0.0,
                               corrupt_probability=query_float(url, "corrupt", 0.0) or 0.0,
                               seed=query_int(url, "seed", None), name=f"loopback-{plane}")





def _grab(args: argparse.Namespace) -> int:
    import numpy as np

    from appliance.errors import ConfigError
    from drivers.biplane_folder import write_frame
    from drivers.biplane_pairing import BiplanePairer, BiplaneStream
    from drivers.errors import DeviceTimeoutError
    from drivers.file_sources import TIMESTAMP_COLUMNS, TIMESTAMPS_FILE
    from drivers.frame_source import EndOfStream

    sources, scene = _build_sources(args.source)
    planes = sorted(source.plane for source in sources)
    if planes != ["p", "q"]:
        raise ConfigError(f"the two sources must be planes p and q, got {planes}; add ?plane=p / ?plane=q")
    if args.out is not None:
        prepare_frame_folder(args.out)
    pairer = BiplanePairer(match=args.match, mode="all", max_skew_s=args.max_skew_ms / 1000.0)
    skews: list[float] = []
    interleaved = 0
    rows: list[list[Any]] = []
    pairs = 0
    ended = ""
    start = time.monotonic()
    last_progress = 0.0
    with BiplaneStream(sources, pairer) as stream:
        while pairs < args.frames:
            try:
                pair = stream.next_pair(args.timeout)
            except EndOfStream:
                ended = "the recorded sources ended"
                break
            except DeviceTimeoutError:
                ended = f"no pair for {args.timeout:g} s"
                break
            pairs += 1
            skews.append(pair.skew_s)
            interleaved += pair.interleaved
            if args.out is not None:
                for frame in (pair.p, pair.q):
                    image = frame.image if frame.image.dtype == np.uint16 else frame.image.astype(np.uint16) << 8
                    write_frame(args.out, frame.plane, pair.number, image, fmt=args.format)
                    rows.append([frame.plane, pair.number, f"{frame.device_time_s:.6f}", f"{frame.host_time_s:.6f}",
                                 "" if frame.exposure_s is None else f"{frame.exposure_s:.6f}"])
            now = time.monotonic()
            if now - last_progress > 0.5 or pairs == args.frames:
                last_progress = now
                _progress(f"grab: {pairs}/{args.frames} pairs, {pairs / max(now - start, 1e-9):.1f} pairs/s")
        counters = {source.plane: (source.name, source.counters) for source in sources}
    elapsed = time.monotonic() - start
    if sys.stderr.isatty():
        sys.stderr.write("\n")
    if args.out is not None:
        with (args.out / TIMESTAMPS_FILE).open("w", newline="", encoding="utf-8") as handle:
            writer = csv.writer(handle)
            writer.writerow(TIMESTAMP_COLUMNS)
            writer.writerows(rows)
        if scene is not None:
            _save_true_calibration(args.out, scene)
    print(_summary(pairs, elapsed, counters, pairer.counters, skews, interleaved, args, ended))
    return 0 if pairs > 0 else 1


def _save_true_calibration(out: Path, scene: Any) -> None:
    from appliance.geometry import Calibration, View

    views = {name: View(name, v.K, v.dist, v.R, v.t, v.image_size) for name, v in scene.true_views.items()}
    Calibration.from_views(views["p"], views["q"], {
        "source": "true views of the simulated biplane system (appliance grab, loopback sources)",
        "robot": scene.robot_id}).save(out / "calibration.yaml")


def _progress(text: str) -> None:
    if sys.stderr.isatty():
        sys.stderr.write(f"\r{text}   ")
        sys.stderr.flush()


def _summary(pairs: int, elapsed: float, counters: dict[str, Any], pairing: Any, skews: list[float],
             interleaved: int, args: argparse.Namespace, ended: str) -> str:
    import numpy as np

    lines = [f"grabbed {pairs} pair(s) in {elapsed:.2f} s: {pairs / max(elapsed, 1e-9):.1f} pairs/s"
             + (f" (stopped early: {ended})" if ended else "")]
    for plane in ("p", "q"):
        name, c = counters[plane]
        lines.append(f"  plane {plane} {name}: {c.frames} frames, {c.dropped} dropped, {c.corrupt} corrupt, "
                     f"{c.timeouts} timeouts")
    lines.append(f"  pairing by {args.match}: {pairing.pairs} pairs formed, unpaired p {pairing.unpaired_p}, "
                 f"unpaired q {pairing.unpaired_q}" + (f", {interleaved} interleaved" if interleaved else ""))
    if skews:
        ms = np.abs(np.array(skews)) * 1000.0
        clock = "host arrival" if args.match == "time" else "host arrival, same frame number"
        lines.append(f"  p-q skew ({clock}): mean {ms.mean():.2f} ms, p50 {np.percentile(ms, 50):.2f} ms, "
                     f"p99 {np.percentile(ms, 99):.2f} ms, max {ms.max():.2f} ms")
    if args.out is not None:
        lines.append(f"  written {args.out}/{{p,q}}/NNNNNN.{args.format} and {args.out}/timestamps.csv"
                     f" (read it with: appliance track {args.out})")
    return "\n".join(lines)
