"""What a validation session asks of the lab, and how it takes biplane pairs and tracker samples.

A validation session is a protocol run by people: pivot the tracked pointer, put the fiducial phantom in
the field of view, touch each fiducial with the pointer, clamp the robot's holder in one posture after
another. The session runner (:mod:`appliance.validation.session`) says *what* to do through the
:class:`Lab` protocol; who does it is the lab's business. On a bench an operator does it when prompted
(:class:`OperatorLab`); in simulation the simulated world does it (``appliance/commands/validate.py``,
the one place where the validation may touch the loopback world). Either way the measurements come
through the real devices: pairs from the frame stream, poses from the NDI tracker driver.

``wait(seconds)`` is how time passes: the operator's lab sleeps, the simulated lab advances the
simulated clock (frames and tracker frames are produced on that clock).
"""
from __future__ import annotations

import logging
import sys
import time
from collections.abc import Callable
from typing import Any, Protocol, TextIO

import numpy as np

from appliance.errors import DeviceError, DeviceTimeoutError
from drivers.biplane_pairing import BiplanePair, BiplaneStream
from drivers.ndi_tracker import NDITracker

log = logging.getLogger(__name__)

#: Tracker frame period of an NDI Polaris (60 Hz).
OTS_PERIOD_S = 1.0 / 60.0


class Lab(Protocol):
    """The hands of the lab (see the module docstring)."""

    name: str

    def wait(self, seconds: float) -> None:
        """Let ``seconds`` pass."""

    def pointer_rom(self) -> tuple[bytes | str, str]:
        """The tracked pointer's tool definition (bytes or a .rom path) and its name."""

    def start_pivoting(self) -> None:
        """Put the pointer's tip in a divot and keep pivoting it until the next instruction."""

    def place_fiducials(self) -> int:
        """Put the fiducial phantom in the field of view (robot out of it); returns its number of fiducials."""

    def touch_fiducial(self, index: int) -> None:
        """Hold the pointer's tip in fiducial ``index`` (0-based, in the phantom's numbering)."""

    def clear_fiducials(self) -> None:
        """Take the fiducial phantom (and the pointer) out of the field of view."""

    def place_robot(self, posture: int, count: int) -> None:
        """Clamp the robot's holder in posture ``posture`` (0-based) of ``count``, inside the field of view."""

    def true_pose(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Simulation only: the robot's true (centroid mm, unit direction) now; None on a bench."""


class OperatorLab:
    """A bench lab: each instruction is printed and the operator confirms it with Enter."""

    name = "bench (operator)"

    def __init__(self, pointer_rom: str, fiducial_count: int, *, ask: Callable[[str], str] = input,
                 out: TextIO = sys.stderr) -> None:
        self._rom = pointer_rom
        self._count = fiducial_count
        self._ask = ask
        self._out = out

    def _instruct(self, text: str) -> None:
        print(f"validate: {text}", file=self._out, flush=True)
        self._ask("          press Enter when done ")

    def wait(self, seconds: float) -> None:
        time.sleep(seconds)

    def pointer_rom(self) -> tuple[bytes | str, str]:
        return self._rom, self._rom

    def start_pivoting(self) -> None:
        self._instruct("put the pointer's tip in the pivot divot and keep pivoting it (about 30 deg each way)")

    def place_fiducials(self) -> int:
        self._instruct("put the fiducial phantom in the field of view of both X-ray planes; the robot out of it")
        return self._count

    def touch_fiducial(self, index: int) -> None:
        self._instruct(f"hold the pointer's tip in fiducial {index + 1} of {self._count}")

    def clear_fiducials(self) -> None:
        self._instruct("take the fiducial phantom and the pointer out of the field of view")

    def place_robot(self, posture: int, count: int) -> None:
        self._instruct(f"clamp the robot's holder in posture {posture + 1} of {count}")

    def true_pose(self) -> tuple[np.ndarray, np.ndarray] | None:
        return None


class PairFeed:
    """Biplane pairs, one per frame period, each newer than the last; pairs from before a lab action are skipped."""

    def __init__(self, frames: BiplaneStream, lab: Lab, fps: float, *, timeout_s: float = 2.0,
                 settle_frames: int = 3) -> None:
        self.frames = frames
        self.lab = lab
        self.period_s = 1.0 / fps
        self.timeout_s = timeout_s
        self.settle_frames = settle_frames
        self._last = -1
        self._first_allowed = 0

    def settle(self) -> None:
        """The scene just changed: pairs exposed before may still be on their way; skip a few frame numbers
        past the newest pair already here (the stream keeps only the newest, whatever we last took)."""
        try:
            newest = self.frames.next_pair(min(self.timeout_s, 0.2))
            self._last = max(self._last, newest.number)
        except DeviceTimeoutError:
            pass
        self._first_allowed = self._last + 1 + self.settle_frames

    def next(self) -> BiplanePair:
        for _ in range(64 + self.settle_frames):
            self.lab.wait(self.period_s)
            try:
                pair = self.frames.next_pair(self.timeout_s)
            except DeviceTimeoutError:
                continue
            if pair.number <= self._last:
                continue
            self._last = pair.number
            if pair.number >= self._first_allowed:
                return pair
        raise DeviceTimeoutError(f"no new biplane pair after frame {self._last} in "
                                 f"{64 + self.settle_frames} frame periods")


class ToolFeed:
    """Tracker samples of one tool, one per tracker frame (each a new frame number)."""

    def __init__(self, ots: NDITracker, lab: Lab, *, timeout_s: float = 2.0) -> None:
        self.ots = ots
        self.lab = lab
        self.timeout_s = timeout_s
        self._last = -1

    def next(self, handle: int, *, attempts: int = 30) -> tuple[int, np.ndarray | None]:
        """(frame number, 4x4 pose or None when the tool is missing) of the next tracker frame."""
        without = 0
        for _ in range(attempts):
            self.lab.wait(OTS_PERIOD_S)
            try:
                samples = self.ots.wait_for_frame(self._last, self.timeout_s)
            except DeviceTimeoutError:
                continue
            self._last = samples[0].frame
            for sample in samples:
                if sample.handle == handle:
                    return sample.frame, (None if sample.missing or sample.transform is None else sample.transform)
            # A frame read before the tool was loaded (the driver keeps its newest frame across a restart).
            without += 1
        if without:
            raise DeviceError(f"tracker at {self.ots.where}: no record of tool handle {handle:02X} in {without} frames")
        raise DeviceTimeoutError(f"tracker at {self.ots.where}: no new frame after {self._last} in {attempts} periods")

    def poses(self, handle: int, count: int, *, what: str) -> list[np.ndarray]:
        """``count`` poses of a tool that must be visible; a tool missing in over half the frames is an error."""
        poses: list[np.ndarray] = []
        missing = 0
        while len(poses) < count:
            _, pose = self.next(handle)
            if pose is None:
                missing += 1
                if missing > count:
                    raise DeviceError(f"{what}: the tracker does not see the tool (missing in {missing} frames)")
                continue
            poses.append(pose)
        return poses


def load_extra_tool(ots: NDITracker, rom: Any, name: str, mode: str, rate_hz: float) -> int:
    """Load another tool while tracking: NDI tools are loaded in setup mode, so tracking stops and restarts."""
    ots.stop()
    handle = ots.load_tool(rom, name)
    ots.start()
    ots.start_streaming(mode, rate_hz)
    log.info("tracker at %s: %s loaded on handle %02X", ots.where, name, handle)
    return handle
