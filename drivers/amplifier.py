"""Driver for the EMA coil-current amplifier (protocol: ``firmware_protocol/AMPLIFIER.md``).

:class:`Amplifier` takes a ready byte transport (a ``serial.SerialBase`` from
``drivers.transport.open_serial``: a tty, a pty, ``socket://host:port``) and owns it from then on.
Every request waits for the reply carrying its sequence number within ``ack_timeout_s``; a lost
frame is retransmitted byte for byte with the same sequence number, so the amplifier answers a
duplicate from its cache instead of applying it twice, and a late copy of an old command is refused
as stale by the amplifier. Commands are serialised by one lock, so sequence numbers on the wire only
ever increase.

Host-side limits mirror the amplifier's (:mod:`drivers.amplifier_types`): a requested vector over
a current limit is scaled as a whole (the field keeps its direction) and the step from the previous
command is scaled to respect the slew limit; :class:`SetResult` reports both factors.

A background thread sends HEARTBEAT when the link has been quiet for ``heartbeat_period_s`` (default
a quarter of the amplifier's watchdog). Faults come back as exceptions from the call that met them
(:class:`AmplifierFaultError` subclasses carrying the flags) and as :class:`AmplifierEvent` to
listeners registered with :meth:`Amplifier.add_listener`, also when only the heartbeat saw them.

Typical use::

    limits = AmplifierLimits.uniform(8, max_current_a=10.0, slew_a_per_s=200.0, watchdog_ms=200)
    with Amplifier(open_serial("/dev/ttyACM0"), limits=limits) as amp:   # HELLO, status, limits
        amp.add_listener(on_amplifier_event)
        amp.enable()
        while running:
            result = amp.set_currents(currents_a)     # SetResult: commanded, scales, measured
    # leaving the block ramps to zero at the slew limit, disables the output and closes the port
"""
from __future__ import annotations

import logging
import math
import threading
import time
from typing import Callable, Literal, Sequence, TypeVar, overload

import numpy as np
import serial

from drivers.amplifier_types import (
    AmplifierEvent,
    AmplifierFaultError,
    AmplifierInfo,
    AmplifierLimits,
    AmplifierStatus,
    CommandRejectedError,
    CurrentCommandError,
    EStopError,
    OverCurrentError,
    OverTemperatureError,
    SetResult,
    WatchdogError,
    fault_error,
    limit_current_list,
)
from drivers.errors import DeviceError, DeviceTimeoutError, LinkLostError, ProtocolError
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
    SetCurrentsReply,
    State,
    Status,
    encode_message,
    encode_set_currents,
)

log = logging.getLogger(__name__)

__all__ = [
    "Amplifier", "AmplifierEvent", "AmplifierFaultError", "AmplifierInfo", "AmplifierLimits", "AmplifierStatus",
    "CommandRejectedError", "CurrentCommandError", "EStopError", "OverCurrentError", "OverTemperatureError",
    "SetResult", "WatchdogError", "Fault", "State",
]

ReplyT = TypeVar("ReplyT", bound=Message)
Listener = Callable[[AmplifierEvent], None]

_READ_POLL_S = 0.005          # port read timeout: bounds how late a deadline is noticed
_SHUTDOWN_RESIDUAL_A = 0.05   # measured current regarded as zero before the output is disabled
#: How many times a start-up runs the command path without writing (:meth:`Amplifier.rehearse_command`):
#: more than the 8 calls after which CPython 3.11 quickens a function's bytecode.
REHEARSAL_PASSES = 16


class Amplifier:
    """One EMA amplifier on one link. Context manager: leaving the block calls :meth:`shutdown`."""

    def __init__(self, port: serial.SerialBase, *, limits: AmplifierLimits | None = None,
                 ack_timeout_s: float = 0.05, retries: int = 2, heartbeat_period_s: float | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if ack_timeout_s <= 0 or retries < 0:
            raise ValueError("ack_timeout_s must be positive and retries non-negative")
        self._port = port
        self._name = str(getattr(port, "name", None) or getattr(port, "port", None) or "amplifier port")
        self.ack_timeout_s = ack_timeout_s
        self.retries = retries
        self._clock = clock
        self._io_lock = threading.RLock()
        self._decoder = MessageDecoder()
        self._seq = 0
        self._closed = False
        self._listeners: list[Listener] = []
        self._listener_error: BaseException | None = None
        self._state = State.DISABLED
        self._faults = Fault.NONE
        self._last_exchange = clock()
        self._link_ok = True
        self.retransmissions = 0
        self.discarded_replies = 0
        self._stop = threading.Event()
        self._heartbeat: threading.Thread | None = None
        self._heartbeat_ident: int | None = None
        try:
            port.timeout = min(_READ_POLL_S, ack_timeout_s)
            if hasattr(port, "reset_input_buffer"):
                port.reset_input_buffer()
            self.info = self.identify()
            self.limits = self.info.limits
            self.status()   # learn state and faults now: a previous session may have left a fault
            self._pending_limits: AmplifierLimits | None = None
            if limits is not None:
                self._configure_at_connect(limits)
        except BaseException:
            self._close_port()
            raise
        self._previous = [0.0] * self.info.channels   # last commanded currents (A)
        self._previous_t = clock()
        period = self.limits.watchdog_ms / 4000.0 if heartbeat_period_s is None else heartbeat_period_s
        self.heartbeat_period_s = period
        if period > 0:
            self._heartbeat = threading.Thread(target=self._heartbeat_loop, name=f"amp-heartbeat-{self._name}",
                                               daemon=True)
            self._heartbeat.start()
            self._heartbeat_ident = self._heartbeat.ident

    # ---- lifecycle ---------------------------------------------------------------------------

    def __enter__(self) -> "Amplifier":
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    def close(self) -> None:
        """Stop the heartbeat and close the port without touching the output (idempotent)."""
        if self._closed:
            return
        self.stop_heartbeat()
        with self._io_lock:   # never pull the port from under an exchange in flight
            self._closed = True
            self._close_port()

    def shutdown(self, *, timeout_s: float | None = None) -> bool:
        """Ramp every channel to zero at the slew limit, disable the output, then close.

        Returns True when the amplifier confirmed zero current and a disabled output; device errors on
        the way are logged (the port is closed whatever happens) and give False.
        """
        if self._closed:
            return False
        safe = False
        deferred: list[Exception] = []   # not device errors (a listener's, a bug): raised once safe
        try:
            safe = self._ramp_to_zero(timeout_s)
        except AmplifierFaultError as err:
            log.warning("shutdown: amplifier in fault (%s); its own protection owns the output", err)
        except DeviceError as err:
            log.error("shutdown: could not ramp down: %s", err)
        except Exception as err:  # noqa: BLE001 - the output is made safe first, then this is raised
            deferred.append(err)
        try:
            self.disable()
        except DeviceError as err:
            log.error("shutdown: could not disable the output: %s", err)
            safe = False
        except Exception as err:  # noqa: BLE001
            deferred.append(err)
            safe = False
        finally:
            self.close()
        if deferred:
            raise deferred[0]
        return safe

    def stop_heartbeat(self) -> None:
        """Stop the background heartbeat (the amplifier's watchdog then trips unless commands continue)."""
        self._stop.set()
        if self._heartbeat and self._heartbeat is not threading.current_thread():
            self._heartbeat.join(timeout=2.0)

    def add_listener(self, listener: Listener) -> None:
        """``listener(event)`` is called on fault, fault cleared, link lost and link restored.

        It runs in whichever thread met the event (often the heartbeat): keep it short. An exception it
        raises is logged and re-raised from the next call into this driver, never swallowed.
        """
        self._listeners.append(listener)

    def remove_listener(self, listener: Listener) -> None:
        self._listeners.remove(listener)

    @property
    def state(self) -> State:
        """State reported by the last reply."""
        return self._state

    @property
    def faults(self) -> Fault:
        """Fault flags reported by the last reply."""
        return self._faults

    @property
    def decoder_rejections(self) -> dict[str, int]:
        """Frames from the amplifier rejected by reason (CRC, COBS, truncated, ...)."""
        return dict(self._decoder.rejected)

    # ---- commands ----------------------------------------------------------------------------

    def identify(self) -> AmplifierInfo:
        """HELLO: channels, firmware version, ratings and the limits in force. Starts a new session."""
        reply = self._transact(Hello(), HelloReply)
        return AmplifierInfo.from_reply(reply)

    def configure_limits(self, limits: AmplifierLimits) -> None:
        """Set per-channel current and slew limits and the watchdog (the output must be disabled)."""
        limits.check_against(self.info)
        self._transact(ConfigureLimits(watchdog_ms=limits.watchdog_ms, max_current_ma=limits.max_current_ma,
                                       slew_ma_per_s=limits.slew_ma_per_s), Ack)
        self.limits = limits

    def enable(self) -> None:
        """Enable the output; currents start at zero."""
        self._transact(Enable(), Ack)
        self._previous = [0.0] * self.info.channels   # last commanded currents (A)
        self._previous_t = self._clock()

    def disable(self) -> None:
        """Disable the output at once (currents decay through the free-wheel path)."""
        self._transact(Disable(), Ack)
        self._previous = [0.0] * self.info.channels   # last commanded currents (A)

    def clear_fault(self) -> None:
        """Clear latched faults; refused while the e-stop is asserted or a coil is still hot. Limits
        given at connection to an amplifier that was in fault are configured now."""
        self._transact(ClearFault(), Ack)
        if self._pending_limits is not None:
            self.configure_limits(self._pending_limits)
            self._pending_limits = None

    def rehearse_command(self, passes: int = REHEARSAL_PASSES) -> None:
        """Run :meth:`set_currents` up to its write (the vector's checks, the limit check, the frame's
        encoding) ``passes`` times on zero currents, writing nothing and changing no state.

        For a loop's start-up: CPython runs a function's bytecode unspecialised for its first calls (3.11's
        adaptive interpreter quickens a code object after 8), so without this the first commands of a
        session pay that on their way to the wire."""
        zeros = np.zeros(self.info.channels)
        for _ in range(passes):
            self.set_currents(zeros, dry_run=True)

    def heartbeat(self) -> None:
        self._transact(Heartbeat(), Ack)

    def status(self) -> AmplifierStatus:
        return AmplifierStatus.from_reply(self._transact(GetStatus(), Status))

    @overload
    def set_currents(self, currents_a: Sequence[float] | np.ndarray) -> SetResult: ...

    @overload
    def set_currents(self, currents_a: Sequence[float] | np.ndarray, *, dry_run: Literal[False]) -> SetResult: ...

    @overload
    def set_currents(self, currents_a: Sequence[float] | np.ndarray, *, dry_run: Literal[True]) -> None: ...

    def set_currents(self, currents_a: Sequence[float] | np.ndarray, *, dry_run: bool = False) -> SetResult | None:
        """Command every channel at once (A). The vector is validated, scaled to the host-side limits,
        sent, and acknowledged with the measured currents; raises on NAK, fault or silence. With
        ``dry_run`` everything up to the write runs (checks, limits, encoding) and nothing is sent or
        changed: None (:meth:`rehearse_command`).

        The path to the write is plain float arithmetic on the channels' values and one struct for the
        frame (no numpy calls, no message object): it is what the loop waits for between the allocation
        and the command on the wire, and after a frame's recognition has cycled the caches every call
        on it costs the loop ~10 us (issue 8). The result's arrays are built once the command is out.
        """
        n = self.info.channels
        if type(currents_a) is np.ndarray and currents_a.shape == (n,):
            values = currents_a.tolist()
        else:
            shape = np.shape(currents_a)
            if shape != (n,):
                raise CurrentCommandError(
                    f"set_currents wants {n} currents (one per channel), got shape {shape}")
            values = np.asarray(currents_a, dtype=float).tolist()
        if not all(map(math.isfinite, values)):
            raise CurrentCommandError(f"set_currents got a non-finite current: {values}")
        now = self._clock()
        command_ma, current_scale, slew_scale = limit_current_list(
            values, self._previous, now - self._previous_t, self.limits, milliamps=True)
        if dry_run:
            encode_set_currents(command_ma, 0)
            return None
        reply, seq, attempts, written_at = self._exchange(
            MsgType.SET_CURRENTS, lambda seq: encode_set_currents(command_ma, seq), SetCurrentsReply)
        round_trip_s = self._clock() - now
        commanded_list = [v / 1000.0 for v in command_ma]
        self._previous, self._previous_t = commanded_list, now
        if reply.clamped_mask:
            # The host already scaled to its limits: the amplifier's differ (a config mismatch).
            log.warning("set_currents seq %d: the amplifier itself scaled the vector (channels mask 0x%04X)",
                        seq, reply.clamped_mask)
        if current_scale < 1.0 or slew_scale < 1.0:
            log.debug("set_currents seq %d scaled: current x%.4f, slew x%.4f", seq, current_scale, slew_scale)
        return SetResult(seq=seq, requested_a=np.array(values, dtype=float), commanded_a=np.array(commanded_list),
                         current_scale=current_scale, slew_scale=slew_scale, device_clamped_mask=reply.clamped_mask,
                         measured_a=np.array(reply.measured_ma, dtype=float) / 1000.0,
                         state=reply.state, faults=reply.faults, attempts=attempts, round_trip_s=round_trip_s,
                         written_at_s=written_at)

    # ---- exchange ----------------------------------------------------------------------------

    def _transact(self, request: Message, expected: type[ReplyT]) -> ReplyT:
        return self._exchange(request.TYPE, lambda seq: encode_message(request, seq), expected)[0]

    def _exchange(self, kind: MsgType, frame_for: Callable[[int], bytes],
                  expected: type[ReplyT]) -> tuple[ReplyT, int, int, float]:
        """Send the request of type ``kind`` whose frame ``frame_for(seq)`` encodes, await its reply:
        (reply, sequence number, attempts, clock time when the first attempt's write returned)."""
        if self._closed:
            raise LinkLostError(f"amplifier on {self._name} is closed")
        if self._listener_error is not None and threading.get_ident() != self._heartbeat_ident:
            self._raise_listener_error()
        with self._io_lock:
            self._seq = (self._seq + 1) & 0xFFFF
            seq = self._seq
            frame = frame_for(seq)
            reply: Message | None = None
            attempts = 0
            written_at = 0.0
            while reply is None and attempts <= self.retries:
                attempts += 1
                if attempts > 1:
                    self.retransmissions += 1
                    log.debug("%s seq %d: no reply, retransmitting (attempt %d)", kind.name, seq, attempts)
                self._write(frame)
                if attempts == 1:
                    written_at = self._clock()
                reply = self._await_reply(seq, self._clock() + self.ack_timeout_s)
            if reply is None:
                self._link_state(False, f"no reply to {kind.name}")
                raise DeviceTimeoutError(
                    f"amplifier on {self._name} did not answer {kind.name} (seq {seq}) within "
                    f"{attempts} x {self.ack_timeout_s * 1000:.0f} ms: is it powered and on this port?")
            self._last_exchange = self._clock()
            # Under the lock, so the heartbeat and the owner see state changes in reply order and
            # each fault is announced once.
            self._link_state(True, "")
            if isinstance(reply, (Ack, Nak, SetCurrentsReply, Status)):
                self._observe(reply.state, reply.faults)
        if isinstance(reply, Nak):
            if reply.request_type != kind:
                raise ProtocolError(f"NAK for message type {reply.request_type} answers {kind.name}")
            raise self._nak_error(kind, reply)
        if not isinstance(reply, expected):
            raise ProtocolError(f"{kind.name} (seq {seq}) answered by {type(reply).__name__}")
        if isinstance(reply, Ack) and reply.request_type != kind:
            raise ProtocolError(f"ACK for message type {reply.request_type} answers {kind.name}")
        return reply, seq, attempts, written_at

    def _write(self, frame: bytes) -> None:
        try:
            self._port.write(frame)
        except (serial.SerialException, OSError) as err:
            self._link_state(False, str(err))
            raise LinkLostError(f"link to amplifier on {self._name} lost while writing: {err}") from err

    def _await_reply(self, seq: int, deadline: float) -> Message | None:
        while True:
            try:
                waiting = getattr(self._port, "in_waiting", 0) or 1
                data = self._port.read(waiting)
            except (serial.SerialException, OSError) as err:
                self._link_state(False, str(err))
                raise LinkLostError(f"link to amplifier on {self._name} lost while reading: {err}") from err
            for env in self._decoder.feed(data):
                if env.seq != seq:
                    # The late answer to an earlier attempt or request: never taken for this one.
                    self.discarded_replies += 1
                    log.debug("discarding reply seq %d type 0x%02X while waiting for %d", env.seq, env.msg_type, seq)
                    continue
                if env.message is None:
                    raise ProtocolError(f"amplifier on {self._name} sent an undecodable reply: {env.error}")
                return env.message
            if self._clock() >= deadline:
                return None

    def _nak_error(self, kind: MsgType, nak: Nak) -> Exception:
        what = f"amplifier refused {kind.name}: {nak.reason.name}"
        if nak.reason is NakReason.ESTOP_ACTIVE:
            return EStopError(f"{what}: the emergency stop is pressed; release it, then clear the fault",
                              faults=nak.faults, state=nak.state)
        if nak.reason is NakReason.CONDITION_PRESENT:
            return fault_error(nak.faults, nak.state, f"{what}: a coil is still above the restart temperature")
        if nak.reason is NakReason.FAULT_ACTIVE:
            return fault_error(nak.faults, nak.state, f"{what}: a fault is latched, clear it first")
        return CommandRejectedError(f"{what} (state {nak.state.name}, faults {nak.faults!r})", reason=nak.reason)

    # ---- events ------------------------------------------------------------------------------

    def _observe(self, state: State, faults: Fault) -> None:
        before = self._faults
        self._state, self._faults = state, faults
        new = Fault(int(faults.latched) & ~int(before.latched))
        if new:
            self._emit(AmplifierEvent(kind="fault", state=state, faults=faults, t=self._clock(),
                                      message=f"amplifier fault latched: {new!r}"))
        elif before.latched and not faults.latched:
            self._emit(AmplifierEvent(kind="fault_cleared", state=state, faults=faults, t=self._clock(),
                                      message="amplifier faults cleared"))

    def _link_state(self, ok: bool, why: str) -> None:
        if ok == self._link_ok:
            return
        self._link_ok = ok
        kind = "link_restored" if ok else "link_lost"
        self._emit(AmplifierEvent(kind=kind, state=self._state, faults=self._faults, t=self._clock(),
                                  message=why or kind.replace("_", " ")))

    def _emit(self, event: AmplifierEvent) -> None:
        log.info("amplifier event %s: %s", event.kind, event.message)
        for listener in list(self._listeners):
            try:
                listener(event)
            except Exception as err:  # noqa: BLE001 - kept and re-raised in the owner's next call
                log.exception("amplifier listener %r failed on %s", listener, event.kind)
                self._listener_error = err

    def _raise_listener_error(self) -> None:
        err, self._listener_error = self._listener_error, None
        if err is not None:
            raise err

    # ---- internals ---------------------------------------------------------------------------

    def _heartbeat_loop(self) -> None:
        while not self._stop.wait(self.heartbeat_period_s / 2):
            if self._clock() - self._last_exchange < self.heartbeat_period_s:
                continue
            try:
                self.heartbeat()
            except (DeviceTimeoutError, LinkLostError, ProtocolError, CommandRejectedError) as err:
                log.warning("heartbeat: %s", err)
                if isinstance(err, LinkLostError):
                    return   # the port is gone; the next command reports it to the owner
            except AmplifierFaultError:
                pass         # reported to listeners by _observe already

    def _ramp_to_zero(self, timeout_s: float | None) -> bool:
        if self._state is not State.ENABLED:
            return self._state is State.DISABLED
        slowest = max(abs(a) / rate for a, rate in zip(self._previous, self.limits.slew_a_per_s))
        deadline = self._clock() + (timeout_s if timeout_s is not None else slowest + 1.0)
        step_s = max(0.005, min(0.02, self.heartbeat_period_s or 0.02))
        zero = np.zeros(self.info.channels)
        result = self.set_currents(zero)
        while np.any(result.commanded_a) and self._clock() < deadline:
            time.sleep(step_s)
            result = self.set_currents(zero)
        while self._clock() < deadline:
            if np.all(np.abs(self.status().measured_a) < _SHUTDOWN_RESIDUAL_A):
                return True
            time.sleep(step_s)
        return False

    def _configure_at_connect(self, limits: AmplifierLimits) -> None:
        # The amplifier takes limits only while DISABLED; a previous session may have left it otherwise.
        if self._state is State.ENABLED:
            log.warning("amplifier on %s was left enabled; disabling before configuring limits", self._name)
            self.disable()
        if self._state is State.FAULT:
            # Nothing can be enabled before the fault is cleared; clear_fault() applies the limits first.
            limits.check_against(self.info)
            log.warning("amplifier on %s has latched faults %r; limits will be configured by clear_fault()",
                        self._name, self._faults)
            self._pending_limits = limits
            return
        self.configure_limits(limits)

    def _close_port(self) -> None:
        try:
            self._port.close()
        except (serial.SerialException, OSError) as err:
            log.debug("closing %s: %s", self._name, err)
