"""``appliance amp status|enable|set|zero|clear --port URL``: bench checks of the EMA amplifier.

Each action opens the port, identifies the amplifier and prints its measured currents, coil
temperatures, state and faults. ``enable`` and ``set`` keep the output on for ``--hold`` seconds
(heartbeat running, status printed every ``--every`` seconds) and then ramp to zero and disable:
the amplifier's watchdog would trip anyway once this program stops talking. ``zero`` ramps to zero
and disables; ``clear`` clears latched faults (refused while the e-stop is pressed).

Try it against the loopback: ``appliance loopback amp`` prints a pty path; pass it as ``--port``.
"""
from __future__ import annotations

import argparse
import sys
import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from drivers.amplifier import Amplifier, AmplifierStatus

NAME = "amp"
HELP = "bench checks of the EMA coil-current amplifier: status, enable, set currents, zero, clear faults"

_ACTIONS = ("status", "enable", "set", "zero", "clear")


def _currents(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"--currents wants amps separated by commas, e.g. 1.5,-2,0: {err}") from err


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("action", choices=_ACTIONS, help="what to do")
    parser.add_argument("--port", required=True, metavar="URL",
                        help="serial device, pty path, socket://host:port or host:port")
    parser.add_argument("--currents", type=_currents, metavar="A,B,...",
                        help="for 'set': one current per channel in amperes")
    parser.add_argument("--hold", type=float, default=1.0, metavar="S",
                        help="for 'enable'/'set': seconds to keep the output on before ramping to zero (default 1)")
    parser.add_argument("--every", type=float, default=0.25, metavar="S",
                        help="status print period while holding (default 0.25 s)")
    parser.add_argument("--timeout", type=float, default=0.1, metavar="S",
                        help="acknowledgement deadline per attempt (default 0.1 s)")
    parser.add_argument("--baud", type=int, default=115200, help="line rate for RS-232/485 adapters (default 115200)")


def _fault_names(faults: int) -> str:
    from firmware_protocol.amplifier import Fault

    names = [flag.name for flag in Fault if flag and flag.name and faults & flag]
    return "|".join(names) or "NONE"


def _print_status(status: "AmplifierStatus") -> None:
    print(f"state {status.state.name}   faults {_fault_names(status.faults)}   uptime {status.uptime_s:.1f} s")
    print("  ch   setpoint_a   measured_a   temperature_c")
    for c, (sp, meas, temp) in enumerate(zip(status.setpoint_a, status.measured_a, status.temperature_c)):
        print(f"  {c:2d}   {sp:10.3f}   {meas:10.3f}   {temp:13.1f}")
    sys.stdout.flush()


def _hold(amp: "Amplifier", seconds: float, every: float) -> None:
    end = time.monotonic() + max(seconds, 0.0)
    while True:
        _print_status(amp.status())
        remaining = end - time.monotonic()
        if remaining <= 0:
            return
        time.sleep(min(max(every, 0.02), remaining))


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from drivers.amplifier import Amplifier
    from drivers.errors import ApplianceError
    from drivers.transport import open_serial

    if args.action == "set" and args.currents is None:
        raise ApplianceError("amp set needs --currents A,B,... (one value per channel, amperes)")
    port = open_serial(args.port, baudrate=args.baud, timeout=args.timeout)
    amp = Amplifier(port, ack_timeout_s=args.timeout)
    enabled = False
    try:
        info = amp.info
        version = ".".join(str(v) for v in info.firmware_version)
        print(f"amplifier on {args.port}: {info.channels} channels, firmware {version},"
              f" serial 0x{info.serial_number:08X},"
              f" limits {max(info.limits.max_current_a):g} A, {max(info.limits.slew_a_per_s):g} A/s,"
              f" watchdog {info.limits.watchdog_ms} ms")
        if args.action == "status":
            _print_status(amp.status())
            return 0
        if args.action == "clear":
            amp.clear_fault()
            _print_status(amp.status())
            return 0
        if args.action == "zero":
            safe = amp.shutdown()
            print("output ramped to zero and disabled" if safe else "output disabled (zero not confirmed)")
            return 0 if safe else 1
        if args.action == "set" and len(args.currents) != info.channels:
            raise ApplianceError(
                f"--currents has {len(args.currents)} values; the amplifier has {info.channels} channels")
        enabled = True   # from here on, any way out ramps to zero and disables (see finally)
        amp.enable()
        if args.action == "set":
            target = np.asarray(args.currents, dtype=float)
            # Keep commanding until the host-side slew limiter lets the whole step through.
            result = amp.set_currents(target)
            while result.slew_scale < 1.0:
                time.sleep(0.01)
                result = amp.set_currents(target)
            if result.current_scale < 1.0:
                print(f"requested vector scaled by {result.current_scale:.4f} to respect the current limit")
        _hold(amp, args.hold, args.every)
        safe = amp.shutdown()
        print("output ramped to zero and disabled" if safe else "output disabled (zero not confirmed)")
        return 0 if safe else 1
    except KeyboardInterrupt:
        print("interrupted: ramping to zero", file=sys.stderr)
        raise
    finally:
        if enabled:
            amp.shutdown()   # no-op when already shut down; never leaves the output on after an error
        amp.close()          # idempotent; stops the heartbeat and frees the port
