"""Safety supervisor: a small state machine between the path follower and the current allocator.

States and what the coils are asked for in each:

* ``RUN``   - the follower's command, unchanged.
* ``HOLD``  - tracking lost for more than ``hold_after_lost_frames`` frames, or the tracked robot
  faster than ``max_robot_speed_mm_s``: no gradient (no push), a gentle field (``hold_field_t``)
  along the last commanded direction so the robot keeps its orientation instead of tumbling.
* ``ZERO``  - tracking lost for more than ``zero_after_lost_frames``: field and force zero (the
  allocator ramps the currents down at the slew limit). Left only after tracking is back for
  ``resume_after_frames`` consecutive frames.
* ``STOP``  - latched by an amplifier fault, a lost link or the operator: currents to zero now (the
  orchestrator disables the amplifier output; ``Decision.immediate`` says so), until :meth:`reset`.

Every transition is kept in :attr:`SafetySupervisor.events` with its time and reason, for the recording.
"""
from __future__ import annotations

import enum
import logging
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from pydantic import Field, model_validator

from appliance.config_io import StrictModel

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


class Mode(enum.Enum):
    RUN = "run"
    HOLD = "hold"
    ZERO = "zero"
    STOP = "stop"


class SafetySettings(StrictModel):
    """Thresholds of the safety behaviours (a config section)."""

    hold_after_lost_frames: int = Field(default=3, ge=0)
    zero_after_lost_frames: int = Field(default=30, ge=1)
    resume_after_frames: int = Field(default=3, ge=1)
    hold_field_t: float = Field(default=0.25e-3, ge=0.0)
    max_robot_speed_mm_s: float = Field(default=20.0, gt=0.0)

    @model_validator(mode="after")
    def _order(self) -> SafetySettings:
        if self.zero_after_lost_frames <= self.hold_after_lost_frames:
            raise ValueError("zero_after_lost_frames must be greater than hold_after_lost_frames")
        return self


class Decision(NamedTuple):
    """What to request from the allocator this frame (an immutable named tuple: built every frame,
    and cheaper to build than a frozen dataclass)."""

    mode: Mode
    field_T: FloatArray
    force_N: FloatArray
    reason: str | None
    immediate: bool = False   # STOP: switch the outputs off now, do not ramp


@dataclass(frozen=True)
class SafetyEvent:
    t_s: float
    previous: Mode
    mode: Mode
    reason: str


_FLOAT64 = np.dtype(np.float64)


def _as_float64(value: FloatArray) -> FloatArray:
    """``np.asarray(value, dtype=np.float64)``, without the call when it is one already."""
    return value if type(value) is np.ndarray and value.dtype is _FLOAT64 else np.asarray(value, dtype=np.float64)


class SafetySupervisor:
    """Decides each frame whether the follower's command goes through, is held, or is zeroed."""

    def __init__(self, settings: SafetySettings | None = None) -> None:
        self.settings = settings or SafetySettings()
        self.mode = Mode.RUN
        self.reason: str | None = None
        self.events: list[SafetyEvent] = []
        self._lost = 0
        self._reacquired = 0
        self._last_field_dir: tuple[float, float, float] | None = None   # unit, of the last non-zero field
        self._t = 0.0

    def _enter(self, mode: Mode, reason: str) -> None:
        if mode is self.mode:
            return   # one event per change of mode; the reason is the one that caused it
        self.events.append(SafetyEvent(self._t, self.mode, mode, reason))
        log = logger.warning if mode in (Mode.ZERO, Mode.STOP) else logger.info
        log("safety: %s -> %s (%s)", self.mode.value, mode.value, reason)
        self.mode, self.reason = mode, reason

    # -- latched stops, called by the orchestrator -------------------------------------------------
    def fault(self, reason: str, t_s: float | None = None) -> Decision:
        """Amplifier fault or link loss: stop, latched."""
        self._t = self._t if t_s is None else t_s
        self._enter(Mode.STOP, reason)
        return self._zero(immediate=True)

    def operator_stop(self, reason: str = "operator stop", t_s: float | None = None) -> Decision:
        return self.fault(reason, t_s)

    def reset(self, t_s: float | None = None) -> None:
        """Operator acknowledges a stop: back to RUN with fresh counters."""
        self._t = self._t if t_s is None else t_s
        self._lost = self._reacquired = 0
        self._enter(Mode.RUN, "reset by operator")

    # -- per frame ---------------------------------------------------------------------------------
    def update(self, t_s: float, tracked: bool, field_T: FloatArray | None = None,
               force_N: FloatArray | None = None, robot_speed_mm_s: float | None = None) -> Decision:
        """Decide this frame from whether the robot was tracked, the follower's field and force
        (None when there is no command), and the tracked speed (None when unknown)."""
        cfg = self.settings
        self._t = t_s
        if self.mode is Mode.STOP:
            return self._zero(immediate=True)
        if tracked:
            self._lost = 0
            self._reacquired += 1
        else:
            self._lost += 1
            self._reacquired = 0
        if self._lost > cfg.zero_after_lost_frames:
            self._enter(Mode.ZERO, f"tracking lost for {self._lost} frames")
            return self._zero()
        if self._lost > cfg.hold_after_lost_frames:
            if self.mode is not Mode.ZERO:
                self._enter(Mode.HOLD, f"tracking lost for {self._lost} frames")
                return self._hold()
            return self._zero()
        if self.mode is Mode.ZERO and self._reacquired < cfg.resume_after_frames:
            return self._zero()
        if robot_speed_mm_s is not None and robot_speed_mm_s > cfg.max_robot_speed_mm_s:
            self._enter(Mode.HOLD, f"robot speed {robot_speed_mm_s:.1f} mm/s over {cfg.max_robot_speed_mm_s:g} mm/s")
            return self._hold()
        if field_T is None or force_N is None:
            # Tracked but nothing to command (e.g. before the first command): keep orientation.
            return self._hold() if self.mode is Mode.HOLD else Decision(self.mode, np.zeros(3), np.zeros(3), self.reason)
        # A few lost frames (up to hold_after_lost_frames) pass the caller's command through: it
        # coasts on its last posture. Recovery to RUN needs a tracked frame.
        if self.mode is not Mode.RUN and not self._lost:
            self._enter(Mode.RUN, "tracking and speed within limits")
        field = _as_float64(field_T)
        # Plain floats, no numpy calls on three numbers: after a frame's recognition has cycled the
        # caches, each numpy call costs the loop 10-20 us (issue 8). The direction is what HOLD keeps.
        x, y, z = field.tolist()
        norm = math.sqrt(x * x + y * y + z * z)
        if norm > 0.0:
            self._last_field_dir = (x / norm, y / norm, z / norm)
        return Decision(self.mode, field, _as_float64(force_N), self.reason)

    def _hold(self) -> Decision:
        direction = self._last_field_dir
        field = (self.settings.hold_field_t * np.array(direction) if direction is not None else np.zeros(3))
        return Decision(Mode.HOLD, field, np.zeros(3), self.reason)

    def _zero(self, immediate: bool = False) -> Decision:
        return Decision(self.mode, np.zeros(3), np.zeros(3), self.reason, immediate)
