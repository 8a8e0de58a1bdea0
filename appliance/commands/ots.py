"""``appliance ots stream|info``: read an NDI optical tracker (Polaris, Vega, or the loopback tracker).

``stream`` loads the given tool definitions and prints one JSON object per tool and tracker frame:
``handle``, ``rom``, ``position_mm`` [x, y, z], ``quaternion`` [w, x, y, z], ``rms_mm``, ``frame`` (the
tracker's 60 Hz counter), ``t`` (host wall-clock time of the reply, s) and ``missing`` (position,
quaternion and RMS are null when the tracker does not see the tool). ``info`` prints the VER:0 text.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

NAME = "ots"
HELP = "read an NDI optical tracker: stream tool poses as JSON lines, or print its version text"
#: Line speeds a COMM command can select (NDI's table).
_SPEEDS = (9600, 14400, 19200, 38400, 57600, 115200, 230400, 921600, 1228739)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    stream = actions.add_parser("stream", help="load .rom tools, start tracking and print poses as JSON lines")
    info = actions.add_parser("info", help="print the tracker's version text (VER:0)")
    for sub in (stream, info):
        sub.add_argument("--port", required=True, metavar="PATH_OR_HOST:PORT",
                         help="serial device or pty path (Polaris), or host:port (Vega, default port 8765)")
        sub.add_argument("--baud", type=int, default=115200, choices=_SPEEDS, metavar="BAUD",
                         help="serial speed to switch to after INIT (default 115200; ignored on TCP)")
        sub.add_argument("--reset", action="store_true",
                         help="send a serial break first so the tracker resets (serial only)")
        sub.add_argument("--timeout", type=float, default=2.0, metavar="S", help="reply timeout per command")
    stream.add_argument("--rom", action="append", required=True, type=Path, metavar="FILE",
                        help="passive tool definition (.rom); repeat for several tools")
    stream.add_argument("--frames", type=int, default=None, metavar="N",
                        help="stop after N tracker frames (default: until Ctrl-C)")
    stream.add_argument("--mode", choices=("tx", "bx"), default="tx", help="TX text or BX binary replies")
    stream.add_argument("--rate", type=float, default=60.0, metavar="HZ", help="polling rate (tracker: 60 Hz)")


def _record(sample: object) -> dict[str, object]:
    from drivers.ndi_tracker import ToolSample

    assert isinstance(sample, ToolSample)
    position = sample.position_mm
    return {
        "handle": sample.handle,
        "rom": sample.rom,
        "position_mm": [round(v, 4) for v in position] if position is not None else None,
        "quaternion": [round(v, 6) for v in sample.quaternion] if sample.quaternion is not None else None,
        "rms_mm": round(sample.rms_mm, 4) if sample.rms_mm is not None else None,
        "frame": sample.frame,
        "t": round(sample.t, 6),
        "missing": sample.missing,
    }


def run(args: argparse.Namespace) -> int:
    from drivers.errors import InputDataError
    from drivers.ndi_tracker import NDITracker
    from drivers.transport import open_serial

    roms = list(getattr(args, "rom", None) or [])
    for rom in roms:     # before touching the tracker, so a typo costs nothing
        if not rom.is_file():
            raise InputDataError(f"tool definition {rom} does not exist")
    if getattr(args, "frames", None) is not None and args.frames < 1:
        raise InputDataError(f"--frames must be at least 1, got {args.frames}")
    if not getattr(args, "rate", 1.0) > 0 or not args.timeout > 0:
        raise InputDataError("--rate and --timeout must be positive")

    port = open_serial(args.port, baudrate=9600, timeout=0.05)
    with NDITracker(port, reply_timeout_s=args.timeout, clock=time.time) as tracker:
        tracker.connect(baudrate=args.baud, reset=args.reset)
        if args.action == "info":
            print(tracker.version().rstrip("\n"))
            return 0
        for rom in roms:
            handle = tracker.load_tool(rom)
            print(f"loaded {rom} on handle {handle:02X}", file=sys.stderr)
        tracker.start()
        return _stream(tracker, args.mode, args.frames, args.rate)


def _stream(tracker: object, mode: str, frames: int | None, rate_hz: float) -> int:
    from drivers.ndi_tracker import NDITracker

    assert isinstance(tracker, NDITracker)
    period = 1.0 / rate_hz
    printed, last_frame, next_at = 0, None, time.monotonic()
    try:
        while frames is None or printed < frames:
            samples = tracker.read_frame(mode)
            frame = samples[0].frame if samples else None
            if frame is None or frame != last_frame:    # polling faster than 60 Hz repeats frames
                for sample in samples:
                    sys.stdout.write(json.dumps(_record(sample)) + "\n")
                sys.stdout.flush()
                printed, last_frame = printed + 1, frame
            next_at += period
            time.sleep(max(0.0, next_at - time.monotonic()))
    except BrokenPipeError:      # `... | head`: the reader left, which is not an error
        sys.stderr.close()
    return 0
