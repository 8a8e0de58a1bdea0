"""``appliance loopback amp|ots``: run one loopback device fake on its own, for bench software and people.

The first line printed is the pty path (or ``host:port`` with ``--tcp``) so scripts can read it; the fake
then serves until interrupted.
"""
from __future__ import annotations

import argparse
import sys
import threading

NAME = "loopback"
HELP = "run a loopback device fake (amplifier or optical tracker) on a pty or TCP port"


def _pose(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"--pose wants 7 numbers x,y,z,qw,qx,qy,qz: {err}") from err
    if len(values) != 7:
        raise argparse.ArgumentTypeError(f"--pose wants 7 numbers x,y,z,qw,qx,qy,qz, got {len(values)}")
    return values


def add_arguments(parser: argparse.ArgumentParser) -> None:
    kinds = parser.add_subparsers(dest="device", metavar="DEVICE", required=True)
    amp = kinds.add_parser("amp", help="the EMA coil-current amplifier")
    amp.add_argument("--tcp", type=int, metavar="PORT", help="serve on 127.0.0.1:PORT instead of a pty (0: any free port)")
    ots = kinds.add_parser("ots", help="the NDI-style optical tracker")
    ots.add_argument("--tcp", type=int, metavar="PORT", help="serve on 127.0.0.1:PORT instead of a pty (0: any free port)")
    ots.add_argument("--pose", type=_pose, metavar="x,y,z,qw,qx,qy,qz",
                     help="pose (mm, unit quaternion) reported for every loaded tool")


def run(args: argparse.Namespace) -> int:
    from drivers.loopback.serve import PtyServer, TcpServer

    if args.device == "amp":
        from drivers.loopback.amplifier_fake import make_default_fake
        device = make_default_fake()
    else:
        from drivers.loopback.ots_fake import make_default_fake as make_tracker
        device = make_tracker(pose=args.pose)
    server = TcpServer(device, port=args.tcp) if args.tcp is not None else PtyServer(device)
    with server:
        print(server.address if args.tcp is not None else server.path, flush=True)
        print(f"loopback {args.device} serving; Ctrl-C to stop", file=sys.stderr, flush=True)
        try:
            threading.Event().wait()
        except KeyboardInterrupt:
            pass
    return 0
