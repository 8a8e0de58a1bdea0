"""Host-side types of the EMA amplifier driver: limits, results, events, errors and the limiter.

Kept apart from :mod:`drivers.amplifier` (the I/O) so the orchestrator and the current allocator can
use the limits and :func:`limit_currents` without a link, and so the limiter is testable on its own.
Host units are SI (A, A/s, s); the wire's integer milliamps stay inside the driver.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from drivers.errors import ApplianceError, DeviceFaultError, ProtocolError
from firmware_protocol.amplifier import Fault, HelloReply, NakReason, State, Status


class CurrentCommandError(ApplianceError, ValueError):
    """A current vector the driver refuses before sending: wrong length, NaN or infinite values."""


class CommandRejectedError(ProtocolError):
    """The amplifier NAKed a request for a reason other than a fault (wrong state, bad payload...)."""

    def __init__(self, message: str, *, reason: NakReason) -> None:
        super().__init__(message)
        self.reason = reason


class AmplifierFaultError(DeviceFaultError):
    """The amplifier reports a latched fault; ``faults`` carries every flag, ``state`` its state."""

    def __init__(self, message: str, *, faults: Fault, state: State) -> None:
        super().__init__(message)
        self.faults = faults
        self.state = state


class EStopError(AmplifierFaultError):
    """The emergency-stop input is (or was) asserted; output cut; software alone cannot clear it."""


class OverCurrentError(AmplifierFaultError):
    """A measured current passed the over-current threshold; output cut."""


class OverTemperatureError(AmplifierFaultError):
    """A coil passed the over-temperature threshold; ramped to zero; clear refused until it cools."""


class WatchdogError(AmplifierFaultError):
    """The amplifier's link watchdog expired (the host went silent); ramped to zero."""


def fault_error(faults: Fault, state: State, message: str) -> AmplifierFaultError:
    """The most specific error for ``faults`` (e-stop before over-current before temperature before
    watchdog: the order in which a bench engineer must act on them)."""
    for flag, cls in ((Fault.ESTOP | Fault.ESTOP_INPUT, EStopError), (Fault.OVER_CURRENT, OverCurrentError),
                      (Fault.OVER_TEMPERATURE | Fault.TEMPERATURE_HIGH, OverTemperatureError),
                      (Fault.WATCHDOG, WatchdogError)):
        if faults & flag:
            return cls(f"{message} ({faults!r})", faults=faults, state=state)
    return AmplifierFaultError(f"{message} ({faults!r})", faults=faults, state=state)


@dataclass(frozen=True)
class AmplifierLimits:
    """Per-channel current limit (A), slew limit (A/s) and the link watchdog period (ms)."""

    max_current_a: tuple[float, ...]
    slew_a_per_s: tuple[float, ...]
    watchdog_ms: int

    def __post_init__(self) -> None:
        if len(self.max_current_a) != len(self.slew_a_per_s) or not self.max_current_a:
            raise ValueError("max_current_a and slew_a_per_s need one value per channel")
        if any(not np.isfinite(v) or v <= 0 for v in (*self.max_current_a, *self.slew_a_per_s)):
            raise ValueError("current and slew limits must be positive and finite")
        if not 10 <= self.watchdog_ms <= 10_000:
            raise ValueError(f"watchdog_ms={self.watchdog_ms}: the protocol allows 10..10000")

    @classmethod
    def uniform(cls, channels: int, *, max_current_a: float, slew_a_per_s: float,
                watchdog_ms: int) -> "AmplifierLimits":
        return cls((max_current_a,) * channels, (slew_a_per_s,) * channels, watchdog_ms)

    @property
    def channels(self) -> int:
        return len(self.max_current_a)

    @property
    def max_current_ma(self) -> tuple[int, ...]:
        # Truncated so the integer limit never exceeds the one asked for.
        return tuple(int(v * 1000) for v in self.max_current_a)

    @property
    def slew_ma_per_s(self) -> tuple[int, ...]:
        return tuple(max(1, int(v * 1000)) for v in self.slew_a_per_s)

    def check_against(self, info: "AmplifierInfo") -> None:
        """Raise ValueError unless these limits fit the amplifier's channel count and ratings."""
        if self.channels != info.channels:
            raise ValueError(f"limits for {self.channels} channels, the amplifier has {info.channels}")
        over = [c for c, (m, r) in enumerate(zip(self.max_current_a, info.rated_current_a)) if m > r]
        if over:
            raise ValueError(f"max_current_a above the amplifier's rating on channels {over} "
                             f"(rated {[info.rated_current_a[c] for c in over]} A)")


@dataclass(frozen=True)
class AmplifierInfo:
    """What HELLO tells: identity, ratings and the limits in force."""

    channels: int
    firmware_version: tuple[int, int, int]
    serial_number: int
    rated_current_a: tuple[float, ...]
    over_temperature_c: float
    limits: AmplifierLimits

    @classmethod
    def from_reply(cls, reply: HelloReply) -> "AmplifierInfo":
        limits = AmplifierLimits(tuple(v / 1000 for v in reply.max_current_ma),
                                 tuple(v / 1000 for v in reply.slew_ma_per_s), reply.watchdog_ms)
        return cls(channels=reply.channels, firmware_version=reply.firmware_version,
                   serial_number=reply.serial_number, rated_current_a=tuple(v / 1000 for v in reply.rated_current_ma),
                   over_temperature_c=reply.over_temperature_dc / 10, limits=limits)


@dataclass(frozen=True)
class AmplifierStatus:
    state: State
    faults: Fault
    uptime_s: float
    last_seq: int
    setpoint_a: np.ndarray
    measured_a: np.ndarray
    temperature_c: np.ndarray

    @classmethod
    def from_reply(cls, reply: Status) -> "AmplifierStatus":
        return cls(state=reply.state, faults=reply.faults, uptime_s=reply.uptime_ms / 1000, last_seq=reply.last_seq,
                   setpoint_a=np.asarray(reply.setpoint_ma, dtype=float) / 1000,
                   measured_a=np.asarray(reply.measured_ma, dtype=float) / 1000,
                   temperature_c=np.asarray(reply.temperature_dc, dtype=float) / 10)


@dataclass(frozen=True)
class SetResult:
    """What became of one ``set_currents`` call.

    ``commanded_a = previous + slew_scale * (current_scale * requested_a - previous)``, rounded towards
    zero to the wire's milliamps. ``device_clamped_mask`` has bit c set when the amplifier itself had
    to scale the vector because of channel c (a host/amplifier limit mismatch worth logging).
    """

    seq: int
    requested_a: np.ndarray
    commanded_a: np.ndarray
    current_scale: float
    slew_scale: float
    device_clamped_mask: int
    measured_a: np.ndarray
    state: State
    faults: Fault
    attempts: int
    round_trip_s: float
    written_at_s: float = 0.0   # the driver's clock when the command's (first) write returned

    @property
    def scaled(self) -> bool:
        return self.current_scale < 1.0 or self.slew_scale < 1.0


EventKind = Literal["fault", "fault_cleared", "link_lost", "link_restored"]


@dataclass(frozen=True)
class AmplifierEvent:
    kind: EventKind
    state: State
    faults: Fault
    t: float
    message: str


def limit_currents(requested_a: np.ndarray, previous_a: np.ndarray, dt_s: float,
                   limits: AmplifierLimits) -> tuple[np.ndarray, float, float]:
    """Scale a current vector to the limits, keeping directions: ``(commanded, current_scale, slew_scale)``.

    The whole requested vector is scaled so no channel exceeds its current limit (clipping one coil
    at a time would turn the field). Then the step from ``previous_a`` is scaled so no channel moves
    faster than its slew limit over ``dt_s``.
    """
    commanded, current_scale, slew_scale = limit_current_list(
        np.asarray(requested_a, dtype=float).tolist(), np.asarray(previous_a, dtype=float).tolist(), dt_s, limits)
    return np.array(commanded), current_scale, slew_scale


def limit_current_list(requested_a: list[float], previous_a: list[float], dt_s: float,
                       limits: AmplifierLimits, *, milliamps: bool = False) -> tuple[list[Any], float, float]:
    """:func:`limit_currents` on plain float lists: what the driver runs on every command (8 channels of
    float arithmetic cost ~3 us; the same on numpy arrays, a dozen calls of ~2 us each). Comparisons in
    place of ``abs``/``min``/``max`` calls on every channel (the same results, to the bit, as those calls:
    only a channel over its limit pays one).

    With ``milliamps`` the commanded currents come as the wire's integer milliamps, rounded towards zero
    (``int(a * 1000.0)`` of the floats it returns otherwise): the driver sends nothing else, and one pass
    over the channels less is ~2 us of its command path after a frame has cycled the caches (issue 8)."""
    max_a = limits.max_current_a
    current_scale = 1.0
    for value, limit in zip(requested_a, max_a):
        if value > limit or -value > limit:   # abs(value) > limit
            current_scale = min(current_scale, limit / abs(value))
    target = [value * current_scale for value in requested_a] if current_scale < 1.0 else requested_a
    dt = 0.0 if 0.0 > dt_s else dt_s   # max(dt_s, 0.0)
    slew_scale = 1.0
    for t, p, rate in zip(target, previous_a, limits.slew_a_per_s):
        delta = t - p
        allowed = rate * dt
        if delta > allowed or -delta > allowed:   # abs(delta) > allowed
            slew_scale = min(slew_scale, allowed / abs(delta))
    # Guard against rounding pushing a channel a hair over its limit: min(max(value, -m), m), as comparisons.
    commanded: list[Any] = []
    if milliamps:
        for t, p, m in zip(target, previous_a, max_a):
            value = p + (t - p) * slew_scale
            value = -m if -m > value else value
            commanded.append(int((m if m < value else value) * 1000.0))
    else:
        for t, p, m in zip(target, previous_a, max_a):
            value = p + (t - p) * slew_scale
            value = -m if -m > value else value
            commanded.append(m if m < value else value)
    return commanded, current_scale, slew_scale
