"""Loopback EMA amplifier: the amplifier's side of the wire protocol with simple coil physics.

The fake is fed the bytes a host wrote and answers like the firmware described in
``firmware_protocol/AMPLIFIER.md``, built on the same codec as the driver. It advances on the clock
passed to ``feed``/``tick`` (seconds), so tests may drive it in-process with a synthetic clock or
serve it on a pty / TCP socket with :mod:`drivers.loopback.serve`.

Modelled, per channel:
- the slew-limited reference (setpoint): moves along the straight segment towards the commanded
  target at the greatest speed at which no channel exceeds its slew limit (the field's direction is
  kept during a ramp); the commanded vector is scaled as a whole if a channel exceeds its limit;
- the coil current following the reference as a first-order lag with tau = L/R; with the output off
  the current decays through the free-wheel path with the same tau;
- coil temperature: C dT/dt = I^2 R - (T - T_ambient) / R_th, with C = tau_th / R_th;
- the state machine (DISABLED / ENABLED / FAULT), the link watchdog (controlled ramp to zero at the
  slew limit, then output off, WATCHDOG latched), over-temperature (controlled ramp, latched; clear
  refused until the coil cooled below the restart threshold), over-current (output cut at once),
  the e-stop input (output cut at once; clear refused while the input is asserted), duplicate
  detection by sequence number and refusal of stale sequence numbers.

Fault injection: :meth:`press_estop`, :meth:`release_estop`, :meth:`inject_over_temperature`,
:meth:`set_temperature_c`, :meth:`inject_over_current`; link faults (dropped/corrupted bytes, an
unplugged cable) are injected by the server's ``link_filter`` and ``unplugged``.

Not modelled: mutual inductance between coils, supply voltage limits (the current loop is ideal up
to the L/R lag, so no voltage saturation on fast ramps), measurement noise and ADC quantisation
(measured currents are rounded to 1 mA), current-loop overshoot, temperature dependence of R,
thermal coupling between coils, power-supply faults, and the serial line rate (a pty has none).
"""
from __future__ import annotations

import logging
import threading
from collections import deque
from dataclasses import dataclass
from typing import Union

import numpy as np

from firmware_protocol.amplifier import (
    Ack,
    ClearFault,
    ConfigureLimits,
    Disable,
    Enable,
    Fault,
    GetStatus,
    Heartbeat,
    Hello,
    HelloReply,
    Message,
    MessageDecoder,
    MsgType,
    Nak,
    NakReason,
    SetCurrents,
    SetCurrentsReply,
    State,
    Status,
    encode_message,
    seq_newer,
)

log = logging.getLogger(__name__)

_SUBSTEP_S = 0.0005          # step while the reference ramps: well below the default 10 ms coil tau
_STEADY_STEP_S = 0.005       # step otherwise: the coil is integrated exactly, temperature by Euler
_MAX_ADVANCE_S = 600.0       # a clock jump beyond this is integrated as this much (keeps ticks bounded)
_OVER_CURRENT_FACTOR = 1.1
_OVER_CURRENT_MARGIN_A = 0.1
_WATCHDOG_MIN_MS, _WATCHDOG_MAX_MS = 10, 10_000


PerChannel = Union[float, tuple[float, ...]]


@dataclass(frozen=True)
class FakeAmplifierConfig:
    """Ratings, power-on limits and coil physics of the loopback amplifier (SI units). Ratings and
    limits are the same on every channel; coil constants may differ per channel."""

    channels: int = 8
    rated_current_a: float = 12.0
    max_current_a: float = 10.0
    slew_a_per_s: float = 200.0
    watchdog_ms: int = 200
    # Coil constants: one value for every channel, or a tuple with one value per channel.
    coil_resistance_ohm: PerChannel = 0.5
    coil_inductance_h: PerChannel = 0.005          # tau = L/R = 10 ms
    thermal_resistance_k_per_w: PerChannel = 1.0   # 50 K rise at 10 A continuous
    thermal_time_constant_s: PerChannel = 60.0
    ambient_temperature_c: float = 25.0
    over_temperature_c: float = 80.0
    restart_temperature_c: float = 70.0
    firmware_version: tuple[int, int, int] = (1, 0, 0)
    serial_number: int = 0xA3F00001

    def __post_init__(self) -> None:
        if not 1 <= self.channels <= 16:
            raise ValueError(f"channels={self.channels}: the protocol carries 1..16")
        if not 0 < self.max_current_a <= self.rated_current_a:
            raise ValueError("need 0 < max_current_a <= rated_current_a")
        for name in ("coil_resistance_ohm", "coil_inductance_h", "thermal_resistance_k_per_w",
                     "thermal_time_constant_s"):
            values = np.atleast_1d(np.asarray(getattr(self, name), dtype=float))
            if values.shape not in ((1,), (self.channels,)):
                raise ValueError(f"{name}: one value or one per channel ({self.channels}), got {values.size}")
            if not np.all(np.isfinite(values)) or np.any(values <= 0):
                raise ValueError(f"{name} must be positive")
        if self.slew_a_per_s <= 0:
            raise ValueError("slew_a_per_s must be positive")
        if not _WATCHDOG_MIN_MS <= self.watchdog_ms <= _WATCHDOG_MAX_MS:
            raise ValueError(f"watchdog_ms must be in {_WATCHDOG_MIN_MS}..{_WATCHDOG_MAX_MS}")
        if not self.restart_temperature_c < self.over_temperature_c:
            raise ValueError("restart_temperature_c must be below over_temperature_c")

    def per_channel(self, name: str) -> np.ndarray:
        """A coil constant as one value per channel."""
        return np.broadcast_to(np.asarray(getattr(self, name), dtype=float), (self.channels,)).copy()

    @property
    def coil_time_constant_s(self) -> np.ndarray:
        """tau = L / R per channel (s)."""
        return self.per_channel("coil_inductance_h") / self.per_channel("coil_resistance_ohm")


@dataclass(frozen=True)
class AppliedCommand:
    """A SET_CURRENTS the fake accepted: what was asked and the target it applied after scaling."""

    seq: int
    t: float
    requested_ma: tuple[int, ...]
    target_ma: tuple[int, ...]


@dataclass(frozen=True)
class FakeAmplifierState:
    """A consistent snapshot of the fake for the simulated world, tests and displays."""

    t: float
    state: State
    faults: Fault
    estop_input: bool
    output_on: bool            # output stage driving the coils (off: currents decay with L/R)
    target_a: np.ndarray
    setpoint_a: np.ndarray
    measured_a: np.ndarray
    temperature_c: np.ndarray
    max_current_a: np.ndarray
    slew_a_per_s: np.ndarray
    watchdog_ms: int


class FakeAmplifier:
    """The amplifier side of the link; implements ``feed(data, now)`` and ``tick(now)``."""

    def __init__(self, config: FakeAmplifierConfig | None = None) -> None:
        self.config = cfg = config or FakeAmplifierConfig()
        n = cfg.channels
        self._lock = threading.RLock()
        self.decoder = MessageDecoder()
        self._rated_ma = np.full(n, round(cfg.rated_current_a * 1000), dtype=np.int64)
        self._max_ma = np.full(n, round(cfg.max_current_a * 1000), dtype=np.int64)
        self._slew_ma_per_s = np.full(n, round(cfg.slew_a_per_s * 1000), dtype=np.int64)
        self._watchdog_ms = cfg.watchdog_ms
        self._resistance_ohm = cfg.per_channel("coil_resistance_ohm")
        self._tau_s = cfg.coil_time_constant_s
        self._thermal_r_k_per_w = cfg.per_channel("thermal_resistance_k_per_w")
        self._capacity_j_per_k = cfg.per_channel("thermal_time_constant_s") / self._thermal_r_k_per_w
        self._target = np.zeros(n)
        self._setpoint = np.zeros(n)
        self._actual = np.zeros(n)
        self._temperature = np.full(n, cfg.ambient_temperature_c)
        self._state = State.DISABLED
        self._latched = Fault.NONE
        self._estop_input = False
        self._driving = False            # output stage on (current loop active)
        self._t0: float | None = None
        self._now = 0.0
        self._last_valid = 0.0
        self._last_seq: int | None = None
        self._last_reply: tuple[int, int, bytes] | None = None   # (seq, type, frame) for retransmissions
        self.applied: deque[AppliedCommand] = deque(maxlen=100_000)   # the latest accepted SET_CURRENTS
        self.duplicates = 0
        self.stale = 0

    # ---- the StreamDevice interface ---------------------------------------------------------

    def feed(self, data: bytes, now: float) -> bytes:
        with self._lock:
            self._advance(now)
            out = bytearray()
            for env in self.decoder.feed(data):
                out += self._handle(env.seq, env.msg_type, env.message)
            return bytes(out)

    def tick(self, now: float) -> bytes:
        with self._lock:
            self._advance(now)
        return b""

    # ---- typed state for the simulated world -------------------------------------------------

    def measured_currents_a(self) -> np.ndarray:
        """Coil currents now (A); the simulated world computes the coils' field from these."""
        with self._lock:
            return self._actual.copy()

    @property
    def state(self) -> State:
        with self._lock:
            return self._state

    @property
    def faults(self) -> Fault:
        """Latched faults plus the live input bits."""
        with self._lock:
            return self._faults()

    def snapshot(self) -> FakeAmplifierState:
        with self._lock:
            return FakeAmplifierState(
                t=self._now, state=self._state, faults=self._faults(), estop_input=self._estop_input,
                output_on=self._driving, target_a=self._target.copy(), setpoint_a=self._setpoint.copy(),
                measured_a=self._actual.copy(),
                temperature_c=self._temperature.copy(), max_current_a=self._max_ma / 1000.0,
                slew_a_per_s=self._slew_ma_per_s / 1000.0, watchdog_ms=self._watchdog_ms)

    # ---- fault injection ---------------------------------------------------------------------

    def press_estop(self) -> None:
        with self._lock:
            self._estop_input = True
            self._protect()

    def release_estop(self) -> None:
        with self._lock:
            self._estop_input = False

    def set_temperature_c(self, channel: int, temperature_c: float) -> None:
        with self._lock:
            self._temperature[channel] = temperature_c
            self._protect()

    def inject_over_temperature(self, channel: int = 0) -> None:
        """Heat a coil just past the trip threshold (as a blocked cooling channel would)."""
        self.set_temperature_c(channel, self.config.over_temperature_c + 5.0)

    def inject_over_current(self, channel: int = 0, surge_a: float | None = None) -> None:
        """A current surge (e.g. a shorted turn) on one channel; it trips the over-current protection."""
        with self._lock:
            limit = self._max_ma[channel] / 1000.0
            self._actual[channel] += surge_a if surge_a is not None else 2.0 * limit + 1.0
            self._protect()

    # ---- protocol ----------------------------------------------------------------------------

    def _faults(self) -> Fault:
        live = Fault.ESTOP_INPUT if self._estop_input else Fault.NONE
        if np.any(self._temperature > self.config.restart_temperature_c):
            live |= Fault.TEMPERATURE_HIGH
        return self._latched | live

    def _ack(self, request: int) -> Ack:
        return Ack(request_type=request, state=self._state, faults=self._faults())

    def _nak(self, request: int, reason: NakReason) -> Nak:
        return Nak(request_type=request, reason=reason, state=self._state, faults=self._faults())

    def _handle(self, seq: int, msg_type: int, message: Message | None) -> bytes:
        if msg_type >= 0x80:
            return b""   # a reply-type frame sent to the amplifier: nothing to answer
        if message is None:
            reason = NakReason.BAD_PAYLOAD if msg_type in set(MsgType) else NakReason.UNKNOWN_TYPE
            return encode_message(self._nak(msg_type, reason), seq)
        if isinstance(message, Hello):
            self._last_seq = None   # a new session: HELLO's own number is accepted whatever it is
        elif self._last_seq is not None:
            if seq == self._last_seq and self._last_reply and self._last_reply[:2] == (seq, msg_type):
                # A retransmission of the request just executed: answer again, never execute twice.
                self.duplicates += 1
                self._last_valid = self._now
                return self._last_reply[2]
            if not seq_newer(seq, self._last_seq):
                self.stale += 1
                log.debug("stale request seq %d (last %d) refused", seq, self._last_seq)
                return encode_message(self._nak(msg_type, NakReason.STALE_SEQUENCE), seq)
        self._last_seq = seq
        self._last_valid = self._now
        reply = encode_message(self._execute(seq, message), seq)
        self._last_reply = (seq, msg_type, reply)
        return reply

    def _execute(self, seq: int, msg: Message) -> Message:
        kind = msg.TYPE
        if isinstance(msg, Hello):
            return HelloReply(firmware_version=self.config.firmware_version, serial_number=self.config.serial_number,
                              watchdog_ms=self._watchdog_ms,
                              over_temperature_dc=round(self.config.over_temperature_c * 10),
                              rated_current_ma=tuple(int(v) for v in self._rated_ma),
                              max_current_ma=tuple(int(v) for v in self._max_ma),
                              slew_ma_per_s=tuple(int(v) for v in self._slew_ma_per_s))
        if isinstance(msg, (Heartbeat,)):
            return self._ack(kind)
        if isinstance(msg, GetStatus):
            return self._status()
        if isinstance(msg, Enable):
            if self._estop_input:
                return self._nak(kind, NakReason.ESTOP_ACTIVE)
            if self._state is State.FAULT:
                return self._nak(kind, NakReason.FAULT_ACTIVE)
            if self._state is State.DISABLED:
                self._state = State.ENABLED
                self._target[:] = 0.0
                self._setpoint[:] = 0.0
                self._driving = True
            return self._ack(kind)
        if isinstance(msg, Disable):
            if self._state is State.ENABLED:
                self._state = State.DISABLED
            self._cut_output()
            return self._ack(kind)
        if isinstance(msg, ClearFault):
            return self._clear_fault()
        if isinstance(msg, ConfigureLimits):
            return self._configure(msg)
        if isinstance(msg, SetCurrents):
            return self._set_currents(seq, msg)
        return self._nak(kind, NakReason.UNKNOWN_TYPE)

    def _status(self) -> Status:
        return Status(state=self._state, faults=self._faults(),
                      uptime_ms=int((self._now - (self._t0 or self._now)) * 1000) & 0xFFFFFFFF,
                      last_seq=self._last_seq or 0,
                      setpoint_ma=tuple(int(round(v * 1000)) for v in self._setpoint),
                      measured_ma=tuple(int(round(v * 1000)) for v in self._actual),
                      temperature_dc=tuple(int(round(v * 10)) for v in self._temperature))

    def _clear_fault(self) -> Message:
        if self._estop_input:
            return self._nak(MsgType.CLEAR_FAULT, NakReason.ESTOP_ACTIVE)
        if self._latched & Fault.OVER_TEMPERATURE and np.any(self._temperature > self.config.restart_temperature_c):
            return self._nak(MsgType.CLEAR_FAULT, NakReason.CONDITION_PRESENT)
        if self._over_current_present():
            # The output is cut but the coil current still decays through L/R: clearing now would re-trip.
            return self._nak(MsgType.CLEAR_FAULT, NakReason.CONDITION_PRESENT)
        if self._state is State.FAULT:
            self._cut_output()
            self._state = State.DISABLED
        self._latched = Fault.NONE
        return self._ack(MsgType.CLEAR_FAULT)

    def _configure(self, msg: ConfigureLimits) -> Message:
        kind = MsgType.CONFIGURE_LIMITS
        if len(msg.max_current_ma) != self.config.channels:
            return self._nak(kind, NakReason.BAD_PAYLOAD)
        if self._state is not State.DISABLED:
            return self._nak(kind, NakReason.BAD_STATE)
        max_ma = np.asarray(msg.max_current_ma, dtype=np.int64)
        slew = np.asarray(msg.slew_ma_per_s, dtype=np.int64)
        if (np.any(max_ma > self._rated_ma) or np.any(slew < 1)
                or not _WATCHDOG_MIN_MS <= msg.watchdog_ms <= _WATCHDOG_MAX_MS):
            return self._nak(kind, NakReason.OUT_OF_RANGE)
        self._max_ma, self._slew_ma_per_s, self._watchdog_ms = max_ma, slew, msg.watchdog_ms
        return self._ack(kind)

    def _set_currents(self, seq: int, msg: SetCurrents) -> Message:
        kind = MsgType.SET_CURRENTS
        if len(msg.currents_ma) != self.config.channels:
            return self._nak(kind, NakReason.BAD_PAYLOAD)
        if self._state is State.FAULT:
            return self._nak(kind, NakReason.ESTOP_ACTIVE if self._estop_input else NakReason.FAULT_ACTIVE)
        if self._state is not State.ENABLED:
            return self._nak(kind, NakReason.BAD_STATE)
        requested = np.asarray(msg.currents_ma, dtype=np.int64)
        over = np.abs(requested) > self._max_ma
        target = requested.astype(float)
        if np.any(over):
            # Scale the whole vector so the field keeps its direction; truncate towards zero in mA.
            scale = float(np.min(self._max_ma[over] / np.abs(requested[over])))
            target = np.trunc(requested * scale)
            target = np.clip(target, -self._max_ma, self._max_ma)
        self._target = target / 1000.0
        mask = sum(1 << int(c) for c in np.flatnonzero(over))
        self.applied.append(AppliedCommand(seq=seq, t=self._now, requested_ma=tuple(int(v) for v in requested),
                                           target_ma=tuple(int(v) for v in target)))
        return SetCurrentsReply(state=self._state, faults=self._faults(), clamped_mask=mask,
                                measured_ma=tuple(int(round(v * 1000)) for v in self._actual))

    # ---- physics and protection --------------------------------------------------------------

    def _over_current_present(self) -> bool:
        limit_a = self._max_ma / 1000.0 * _OVER_CURRENT_FACTOR + _OVER_CURRENT_MARGIN_A
        return bool(np.any(np.abs(self._actual) > limit_a))

    def _cut_output(self) -> None:
        self._driving = False
        self._target[:] = 0.0
        self._setpoint[:] = 0.0

    def _trip(self, fault: Fault, *, hard: bool) -> None:
        if not self._latched & fault:
            log.warning("amplifier fault %s (%s)", fault.name, "output cut" if hard else "ramping to zero")
        self._latched |= fault
        self._state = State.FAULT
        if hard:
            self._cut_output()
        else:
            self._target[:] = 0.0   # controlled ramp at the slew limit; output off once at zero

    def _protect(self) -> None:
        cfg = self.config
        if self._estop_input:
            self._trip(Fault.ESTOP, hard=True)
        if self._over_current_present():
            self._trip(Fault.OVER_CURRENT, hard=True)
        if np.any(self._temperature > cfg.over_temperature_c):
            self._trip(Fault.OVER_TEMPERATURE, hard=False)
        if self._state is State.ENABLED and self._now - self._last_valid > self._watchdog_ms / 1000.0:
            self._trip(Fault.WATCHDOG, hard=False)

    def _advance(self, now: float) -> None:
        if self._t0 is None:
            self._t0 = self._now = self._last_valid = now
            return
        remaining = min(now - self._now, _MAX_ADVANCE_S)
        if remaining <= 0:
            return
        t = self._now
        while remaining > 1e-12:
            ramping = self._driving and not np.array_equal(self._setpoint, self._target)
            # Short steps while the reference ramps; otherwise the coil response is integrated exactly
            # and only the (slow) temperature needs the step to be short against its time constant.
            h = _SUBSTEP_S if ramping else _STEADY_STEP_S
            if self._state is State.ENABLED:
                # Land just past the watchdog deadline so the trip happens at the right moment.
                h = min(h, max(self._last_valid + self._watchdog_ms / 1000.0 - t, 0.0) + 1e-6)
            h = min(h, remaining)
            t += h
            remaining -= h
            self._now = t
            self._step(h)
            self._protect()
        self._now = now

    def _step(self, h: float) -> None:
        cfg = self.config
        if self._driving:
            delta = self._target - self._setpoint
            slew = self._slew_ma_per_s / 1000.0
            needed_s = float(np.max(np.abs(delta) / slew))
            if needed_s <= h:
                self._setpoint = self._target.copy()
            else:
                self._setpoint = self._setpoint + delta * (h / needed_s)
            if self._state is State.FAULT and not np.any(self._setpoint):
                self._driving = False   # controlled ramp finished: output stage off
        tau = self._tau_s
        decay = np.exp(-h / tau)
        follow = self._setpoint if self._driving else np.zeros_like(self._actual)
        offset = self._actual - follow
        self._actual = follow + offset * decay
        # Mean of I^2 over the step for i(t) = follow + offset * exp(-t / tau), exactly.
        mean_i2 = (follow ** 2 + 2.0 * follow * offset * (tau / h) * (1.0 - decay)
                   + offset ** 2 * (tau / (2.0 * h)) * (1.0 - decay * decay))
        heating_w = mean_i2 * self._resistance_ohm
        cooling_w = (self._temperature - cfg.ambient_temperature_c) / self._thermal_r_k_per_w
        self._temperature = self._temperature + (heating_w - cooling_w) * h / self._capacity_j_per_k


def make_default_fake() -> FakeAmplifier:
    """The loopback amplifier ``appliance loopback amp`` serves: 8 channels, 10 A limit (12 A rated),
    200 A/s slew, 200 ms watchdog, coils of 0.5 ohm / 5 mH (tau 10 ms), over-temperature at 80 degC."""
    return FakeAmplifier(FakeAmplifierConfig())
